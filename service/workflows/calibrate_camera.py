"""The calibration workflow behind ``posecell calibrate camera``, and the image measuring it shares with the rig's.

Camera: read the field, measure the targets in every image with the pipeline
(:class:`service.pipeline.measure.FrameMeasurer`: detect, decode, identify, resect) or read
given observations, run the self-calibrating bundle adjustment
(:func:`service.core.calib.bundle.calibrate_camera`), and write ``camera.json`` (DESIGN
section 2, with ``sigma`` and a ``calibration`` block) and optionally the surveyed
``field.json`` (each target with ``sigma_mm``). Images are measured twice by
default: first with the start camera (its unmodelled distortion limits which
targets are found near the edges), then with the first calibration.

The rig (``posecell calibrate rig``: pairing the cameras' images into epochs, then
:func:`service.core.calib.rig.calibrate_rig`) is :mod:`service.workflows.calibrate_rig`; it
measures its images with :func:`measure_images` here.

Progress goes to stderr: a bar while images are measured, the adjustment's
stages and iterations after.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from service.core.calib.bundle import BundleResult, Datum, ImagePoints, ScaleBar, calibrate_camera
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.results import PoseResult
from service.core.targets.detect_types import DetectSettings
from service.core.targets.field import Field
from service.store import formats

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm", ".pnm", ".bmp", ".jpg", ".jpeg")


class ProgressBar:
    """Progress on a text stream: redrawn in place on a terminal, one line per stage otherwise."""

    def __init__(self, stream: TextIO | None = None, width: int = 28) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._open = False
        self._last_stage = ""

    def bar(self, label: str, done: int, total: int, note: str = "") -> None:
        n = round(self.width * done / max(total, 1))
        text = f"{label} [{'#' * n}{'.' * (self.width - n)}] {done}/{total} {note}"
        if self.tty:
            self._write("\r" + text[:110].ljust(110), newline=False)
        elif done == total:
            self._write(text)

    def status(self, text: str) -> None:
        """A stage line, or (on a terminal) an iteration redrawn in place."""
        stage = text.split(":", 1)[0]
        if self.tty:
            self._write("\r" + text[:110].ljust(110), newline=False)
        elif "iteration" not in text or stage != self._last_stage:
            self._write(text if "iteration" not in text else f"{stage} ...")
        self._last_stage = stage

    def note(self, text: str) -> None:
        """A line that stays (e.g. an image that could not be measured)."""
        self._write(text)

    def close(self) -> None:
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False

    def _write(self, text: str, newline: bool = True) -> None:
        if newline and self._open:
            self.stream.write("\n")
        self.stream.write(text + ("\n" if newline else ""))
        self.stream.flush()
        self._open = not newline


# -- options --------------------------------------------------------------------------


@dataclass(frozen=True)
class MeasureOptions:
    """How the targets are measured in calibration images: the detector's options by the names of the
    service's ``[processing]`` and ``posecell measure`` (None: the detector's default), mapped by
    :meth:`service.pipeline.measure.MeasureSettings.from_options`; and the first pass's tolerances."""

    code_family: str = "posecell12"
    min_contrast_dn: float | None = None
    min_area_px: int | None = None
    max_area_px: int | None = None
    bit_depth: int | None = None  # the images' significant bits (None: their dtype's)
    centre: str | None = None  # "centroid" or "edge" (None: the detector's default)
    start_sigma_px: float = 1.0  # the start camera's unmodelled distortion, px
    start_max_sigma0_px: float = 5.0


def parse_names(text: str | None) -> tuple[str, ...]:
    """``"K3,B1,B2"`` -> camera parameter names (``c`` and ``x0`` accepted for ``c_mm`` and ``x0_mm``)."""
    if not text:
        return ()
    alias = {n.removesuffix("_mm"): n for n in PARAMETER_NAMES}
    out = []
    for item in (s.strip() for s in text.split(",") if s.strip()):
        name = item if item in PARAMETER_NAMES else alias.get(item)
        if name is None:
            raise ValueError(f"unknown camera parameter {item!r}; choose from {', '.join(PARAMETER_NAMES)}")
        out.append(name)
    return tuple(out)


def parse_scale_bar(text: str) -> ScaleBar:
    """``"A,B,DISTANCE_MM[,SIGMA_MM]"`` -> ScaleBar."""
    cells = [c.strip() for c in text.split(",")]
    try:
        if len(cells) not in (3, 4):
            raise ValueError
        return ScaleBar(cells[0], cells[1], float(cells[2]), float(cells[3]) if len(cells) == 4 else 0.01)
    except ValueError:
        raise ValueError(f"scale bar {text!r} is not 'ID_A,ID_B,DISTANCE_MM[,SIGMA_MM]'") from None


def start_camera(
    camera_path: str | None, c_mm: float | None, pixel_size_mm: float | None, size: tuple[int, int] | None
) -> BrownFraser:
    """The start interior orientation: a camera.json, or a nominal one from c, pixel size and image size."""
    if camera_path:
        return formats.read_camera(camera_path)
    if c_mm is None or pixel_size_mm is None:
        raise ValueError("give a start camera (--camera camera.json) or --c-mm and --pixel-size-mm")
    if size is None:
        raise ValueError("the image size is unknown: give --image-size WIDTHxHEIGHT or --camera")
    return BrownFraser(int(size[0]), int(size[1]), (float(pixel_size_mm), float(pixel_size_mm)), float(c_mm))


def image_paths(items: Sequence[str]) -> list[Path]:
    """Image files: the given files, and the images inside given folders (sorted)."""
    out: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
        else:
            out.append(p)
    return out


# -- measuring ---------------------------------------------------------------------------


def measure_images(
    camera: BrownFraser,
    field: Field,
    paths: Sequence[Path],
    options: MeasureOptions,
    progress: ProgressBar | None,
    *,
    first_pass: bool = True,
    label: str = "measuring",
) -> tuple[list[ImagePoints], list[str]]:
    """Identified targets (all of them, also those the image's own resection rejected: the bundle
    judges them again) and start pose of every image; and one sentence per image that failed."""
    from service.pipeline.measure import FrameMeasurer, MeasureSettings

    # whole frames (no tracking); the first pass allows for the start camera's unmodelled distortion
    settings = MeasureSettings.from_options(
        code_family=options.code_family,
        min_contrast_dn=options.min_contrast_dn,
        min_area_px=options.min_area_px,
        max_area_px=options.max_area_px,
        bit_depth=options.bit_depth,
        centre=options.centre,
        sigma_px=options.start_sigma_px if first_pass else None,
        max_sigma0_px=options.start_max_sigma0_px if first_pass else None,
        roi_tracking=False,
    )
    measurer = FrameMeasurer(camera, field, settings)
    images, failures = [], []
    for k, path in enumerate(paths):
        if progress is not None:
            progress.bar(label, k, len(paths), path.name)
        image = formats.read_image(path)
        if image.shape[1] != camera.width or image.shape[0] != camera.height:
            raise formats.FormatError(
                f"{path}: {image.shape[1]}x{image.shape[0]} px, but the camera is {camera.width}x{camera.height} px"
            )
        result = measurer.measure(image).result
        if isinstance(result, PoseResult):
            images.append(
                ImagePoints(
                    path.name,
                    tuple(t.id for t in result.targets),
                    np.array([t.uv for t in result.targets]),
                    np.asarray(result.T_field_camera),
                )
            )
        else:
            failures.append(f"{path.name}: {result.message}")
    if progress is not None:
        progress.bar(label, len(paths), len(paths))
    return images, failures


# -- outputs ------------------------------------------------------------------------------


def camera_json(result: BundleResult, centre: str | None = None) -> dict[str, Any]:
    """The camera.json of a calibration; ``centre``: what the images' target centres were measured as
    (``calibration.centre``, so that a measurement with the other estimator is warned; None: the
    observations came measured)."""
    d = result.camera.to_dict()
    d["calibration"] = result.report()
    if centre is not None:
        d["calibration"]["centre"] = centre
    return d


def refined_field_json(result: BundleResult, nominal: Field, name: str) -> dict[str, Any]:
    """The surveyed field (DESIGN section 3): the adjusted targets with ``sigma_mm``, rays and residual
    RMS, new targets appended, and the nominal field's unobserved targets as they were (``n_rays`` 0)."""
    d = formats.field_to_json(replace(result.field, name=name))
    for i, t in enumerate(d["targets"]):
        if np.all(np.isfinite(result.sigma_xyz_mm[i])):
            t["sigma_mm"] = [round(float(v), 6) for v in result.sigma_xyz_mm[i]]
        t["n_rays"] = int(result.n_rays[i])
        if math.isfinite(result.target_rms_px[i]):
            t["rms_px"] = round(float(result.target_rms_px[i]), 5)
    unseen = [t for t in formats.field_to_json(nominal)["targets"] if t["id"] not in result.field.index]
    d["targets"] += [{**t, "n_rays": 0} for t in unseen]
    return d


def summary(result: BundleResult, output: str) -> dict[str, Any]:
    cam = result.camera
    return {
        "ok": True,
        "output": str(output),
        "sigma0_px": round(result.sigma0_px, 5),
        "n_images": len(result.images),
        "n_targets": len(result.field),
        "n_observations": result.n_observations,
        "n_rejected": result.n_rejected,
        "camera": {n: {"value": float(getattr(cam, n)), "sigma": result.sigma[n]} for n in result.free},
        "warnings": list(result.warnings),
    }


# -- command-line arguments -------------------------------------------------------------------


def common_options(args: Any) -> dict[str, Any]:
    """The keyword arguments ``calibrate camera`` and ``calibrate rig`` share: the adjustment's and the detector's."""
    bars = [parse_scale_bar(b) for b in args.scale_bar or []]
    measure = MeasureOptions(
        code_family=args.code_family,
        min_contrast_dn=args.min_contrast_dn,
        min_area_px=args.min_area_px,
        max_area_px=args.max_area_px,
        bit_depth=args.bit_depth,
        centre=args.centre,
    )
    return {
        "scale_bars": bars,
        "sigma_px": args.sigma_px,
        "reject_outliers": not args.no_reject,
        "measure": measure,
        "progress": None if args.quiet else ProgressBar(sys.stderr),
        "output": args.output,
    }


def camera_options(args: Any) -> dict[str, Any]:
    """Keyword arguments of :func:`run_camera_calibration` from ``posecell calibrate camera``'s; ValueError if bad."""
    size = None
    if args.image_size:
        try:
            size = tuple(int(v) for v in args.image_size.lower().split("x"))
        except ValueError:
            size = ()
        if len(size) != 2:
            raise ValueError(f"--image-size {args.image_size!r} is not WIDTHxHEIGHT")
    return {
        "images": args.images,
        "observations": args.observations,
        "camera_path": args.camera,
        "c_mm": args.c_mm,
        "pixel_size_mm": args.pixel_size_mm,
        "image_size": size,
        "fix": parse_names(args.fix),
        "control": [c for c in (args.control or "").split(",") if c],
        "control_sigma_mm": args.control_sigma_mm,
        "residual_space": args.residuals,
        "passes": args.passes,
        "field_out": args.field_out,
        "observations_out": args.observations_out,
        **common_options(args),
    }


# -- workflows ------------------------------------------------------------------------------


def run_camera_calibration(
    field_path: str,
    *,
    output: str,
    images: Sequence[str] = (),
    observations: str | None = None,
    camera_path: str | None = None,
    c_mm: float | None = None,
    pixel_size_mm: float | None = None,
    image_size: tuple[int, int] | None = None,
    fix: Sequence[str] = (),
    control: Sequence[str] = (),
    control_sigma_mm: float = 0.0,
    scale_bars: Sequence[ScaleBar] = (),
    sigma_px: float = 0.1,
    residual_space: str = "pixel",
    reject_outliers: bool = True,
    passes: int = 2,
    measure: MeasureOptions = MeasureOptions(),
    field_out: str | None = None,
    observations_out: str | None = None,
    progress: ProgressBar | None = None,
) -> BundleResult:
    """Self-calibrate a camera from images (or observations) of a field; write the outputs.

    Raises ``formats.FormatError`` / ``ValueError`` for bad input and ``SolveError``
    when the network cannot be calibrated.
    """
    if bool(images) == bool(observations):
        raise ValueError("give either images or --observations, not both or neither")
    field = formats.read_field(field_path)
    free = tuple(n for n in PARAMETER_NAMES if n not in set(fix))
    datum = Datum(control=tuple(control), control_sigma_mm=control_sigma_mm, scale_bars=tuple(scale_bars))
    say = progress.status if progress is not None else None
    failures: list[str] = []
    if observations:
        obs = formats.read_image_observations(observations)
        camera = start_camera(camera_path, c_mm, pixel_size_mm, image_size)
        shots = [ImagePoints(o.name, tuple(o.ids), o.uv) for o in obs]
        passes = 1
    else:
        paths = image_paths(images)
        if not paths:
            raise ValueError("no images given")
        size = image_size
        if camera_path is None and size is None:
            first = formats.read_image(paths[0])
            size = (first.shape[1], first.shape[0])
        camera = start_camera(camera_path, c_mm, pixel_size_mm, size)
        shots, failures = measure_images(camera, field, paths, measure, progress)
    for f in failures:
        if progress is not None:
            progress.note(f"skipped {f}")
    result = calibrate_camera(
        camera,
        field,
        shots,
        free=free,
        datum=datum,
        sigma_px=sigma_px,
        residual_space=residual_space,
        reject_outliers=reject_outliers,
        progress=say,
    )
    for k in range(1, passes):
        # again with the calibrated camera: targets near the edges, lost to the start camera's
        # unmodelled distortion, are found now
        start = replace(result.camera, sigma=None)
        shots2, failures = measure_images(
            start, field, paths, measure, progress, first_pass=False, label=f"measuring again ({k + 1}/{passes})"
        )
        if len(shots2) >= len(result.images) and sum(len(s.ids) for s in shots2) >= result.n_observations:
            result = calibrate_camera(
                start,
                field,
                shots2,
                free=free,
                datum=datum,
                sigma_px=sigma_px,
                residual_space=residual_space,
                reject_outliers=reject_outliers,
                progress=say,
            )
            shots = shots2
    if progress is not None:
        progress.close()
    # results say "not determined" as null (a sigma of a target seen once), never as a NaN
    centre = (measure.centre or DetectSettings().centre) if images else None
    formats.write_json_atomic(output, formats.null_for_unknown(camera_json(result, centre)))
    if field_out:
        formats.write_json_atomic(
            field_out, formats.null_for_unknown(refined_field_json(result, field, f"{field.name}-surveyed"))
        )
    if observations_out:
        formats.write_json_atomic(
            observations_out,
            formats.image_observations_to_json([formats.ImageObservations(s.name, list(s.ids), s.uv) for s in shots]),
        )
    return result


__all__ = [
    "MeasureOptions",
    "ProgressBar",
    "camera_json",
    "camera_options",
    "common_options",
    "image_paths",
    "measure_images",
    "parse_names",
    "parse_scale_bar",
    "refined_field_json",
    "run_camera_calibration",
    "start_camera",
    "summary",
]
