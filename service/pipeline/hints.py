"""The sentences a failed frame adds to say its likely cause: an uncalibrated camera, clipped or
blurred targets, a frame of another size than the camera model."""

from __future__ import annotations

import numpy as np

from service.core.geometry.camera_model import BrownFraser
from service.core.results import SolveError
from service.pipeline.brightness import Brightness


def nominal(camera: BrownFraser) -> bool:
    """True for a camera with no calibration: no sigma (``posecell calibrate camera`` writes one)
    and no correction terms at all (a camera.json written from the data sheet)."""
    return camera.sigma is None and not np.any(camera.params()[1:])


def size_mismatch(shape: tuple[int, ...], camera: BrownFraser) -> str:
    return (
        f"the frame is {shape[1]} x {shape[0]} px but the camera model is for {camera.width} x {camera.height} px: "
        "a camera's ROI needs the camera of that window (BrownFraser.cropped; the service makes it from the "
        "camera's configured roi), another image size a calibration of its own"
    )


def with_calibration_hint(e: SolveError, camera: BrownFraser) -> SolveError:
    """``e`` with a sentence saying the camera is not calibrated, when that is the likely cause: the
    targets disagree with every pose (sigma0, gross errors), as an uncorrected lens's distortion makes
    them do (a 24 mm lens: 0.7 px against the 0.5 px limit)."""
    if not nominal(camera) or not ({"sigma0_px", "rejected"} & set(e.details)):
        return e
    return SolveError(
        e.reason,
        f"{e.message.rstrip('.')}. The camera is not calibrated (its camera.json has no "
        "distortion terms and no sigma), and an uncorrected lens alone does this: run "
        "`posecell calibrate camera` on images of the field and measure with the camera.json it "
        "writes.",
        e.details,
    )


def with_image_hints(e: SolveError, brightness: Brightness) -> SolveError:
    """``e`` with the saturated targets named when they are a fifth or more of those seen (rejected,
    ``max_saturated_px``, or clipped so far that their rings no longer read), and with the blur
    when it is beyond ``BLURRED_PX``."""
    b = brightness
    notes = [b.focus_note] if b.focus_note else []
    if b.n_saturated >= max(2, 0.2 * (b.n_measured + b.n_saturated)):
        notes.insert(0, b.saturation_note)
    if not notes:
        return e
    return SolveError(e.reason, f"{e.message.rstrip('.')}; {'; '.join(notes)}.", e.details)
