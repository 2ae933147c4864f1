"""From a grey IR frame (or given observations) to a :class:`PoseResult`: synchronous, no threads, no I/O.

Full frame (the paper's two steps): detect all blobs, read coded targets' rings
until a dozen are named, resect from them, predict every other target from that
pose and match it to the nearest blob (again from the pose of all named, where
that left many unnamed), then adjust over all targets with gross errors
rejected. ROI mode: predict every target from the last poses, measure only small
windows around the predictions, adjust from the predicted pose; fall back to the
full frame when that fails. With a velocity the constant-velocity prediction is
usually good to a fraction of a pixel: every target is measured at once in tight
windows, and only when a disk lies off its window's centre by more than they allow
does the frame take two stages (see :meth:`FrameMeasurer._measure_roi`). Stage
timings are recorded for the benchmark and the service's latency report.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from service.core._kernels import (
    defects_kernel,
    detect_kernel,
    geometry_kernels,
    json_kernel,
    resection_kernel,
    roi_kernel,
)
from service.core.geometry.camera_model import BrownFraser
from service.core.pose.resection import ResectionResult, resect
from service.core.pose.tracking import PoseSample, predict_pose
from service.core.results import Failure, PoseResult, Reason, SolveError, TargetTable
from service.core.targets.codes import FAMILIES, POSECELL12, CodeFamily
from service.core.targets.decode import read_codes
from service.core.targets.decode import warm_up as decode_warm_up
from service.core.targets.defects import DefectMap
from service.core.targets.detect import Blobs, DetectSettings, detect_blobs, measure_windows
from service.core.targets.detect_types import DTYPE_MAX
from service.core.targets.field import Field
from service.core.targets.identify import (
    Matches,
    eccentricity_px,
    match_coded,
    match_predicted,
    project_field,
)
from service.pipeline.brightness import Brightness
from service.pipeline.hints import size_mismatch, with_calibration_hint, with_image_hints
from service.pipeline.ranges import detect_settings_for_range
from service.pipeline.windows import TIGHT_SLACK, PredictedWindows

Array = NDArray[np.float64]


def pose_result_from_resection(
    result: ResectionResult, field: Field, ids: Sequence[str], uv: Array, rows: NDArray[np.int64] | None = None
) -> PoseResult:
    """Attach target ids, codes and residuals to a resection result (``rows``: the ids' field rows, if known)."""
    if rows is None:
        rows = field.indices_of(list(ids))
    # arrays, not an object per target: the ~230 targets of a frame are encoded from them directly
    targets = TargetTable(
        tuple(ids),
        np.asarray(uv, dtype=np.float64).reshape(-1, 2),
        np.asarray(result.residuals_px, dtype=np.float64),
        field.codes[rows] >= 0,
        np.asarray(result.inliers, dtype=bool),
    )
    return PoseResult(
        T_field_camera=result.T_field_camera,
        sigma_position_mm=result.sigma_position_mm,
        sigma_rotation_deg=result.sigma_rotation_deg,
        rms_px=result.rms_px,
        sigma0_px=result.sigma0_px,
        targets=targets,
        n_iter=result.n_iter,
        covariance=result.covariance,
    )


def resect_observations(
    camera: BrownFraser,
    field: Field,
    ids: Sequence[str],
    uv: Array,
    *,
    sigma_px: float | None = None,
    T_field_camera_init: Array | None = None,
) -> PoseResult:
    """Resection from identified image points ``uv`` (N, 2) px of field targets ``ids``.

    Raises :class:`~service.core.results.SolveError` when no trustworthy pose exists.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    p_field = field.xyz[field.indices_of(list(ids))]
    result = resect(camera, p_field, uv, sigma_px=sigma_px, T_field_camera_init=T_field_camera_init)
    return pose_result_from_resection(result, field, ids, uv)


@dataclass(frozen=True)
class MeasureSettings:
    """Processing options of one camera (all have defaults that suit the reference scene)."""

    detect: DetectSettings = field(default_factory=DetectSettings)
    match_tolerance_px: float = 4.0
    min_coded: int = 4
    min_targets: int = 6
    sigma_px: float | None = None
    correct_eccentricity: bool = True
    roi: bool = True
    roi_min_fraction: float = 0.7  # of predicted targets found, else full frame
    roi_max_sigma0_px: float = 0.3
    roi_refine: bool = True  # tight windows about a precise prediction: as precise as the full frame
    roi_prediction_error_px: float = 4.0  # how far a target may move from its constant-velocity prediction
    max_sigma0_px: float = 0.5
    code_family: CodeFamily = POSECELL12  # the coded targets' ring code (codes.AICON14 for AICON plates)
    # full frame: rings read until this many coded targets of the field are named; the others are
    # identified from that pose like the uncoded ones (0: read every ring). See _read_enough.
    codes_enough: int = 12
    # nearest and farthest camera-to-target distance, mm: if given, blobs smaller or larger than any
    # target of the field can appear there are not measured (:func:`detect_settings_for_range`)
    range_mm: tuple[float, float] | None = None

    @classmethod
    def from_options(
        cls,
        *,
        code_family: str | None = None,
        min_contrast_dn: float | None = None,
        min_area_px: int | None = None,
        max_area_px: int | None = None,
        min_coded: int | None = None,
        codes_enough: int | None = None,
        min_targets: int | None = None,
        sigma_px: float | None = None,
        max_sigma0_px: float | None = None,
        correct_eccentricity: bool = True,
        roi_tracking: bool = True,
        range_mm: tuple[float, float] | None = None,
        bit_depth: int | None = None,
        centre: str | None = None,
        max_saturated_px: int | None = None,
    ) -> MeasureSettings:
        """The settings of the measuring options as the service's ``[processing]`` section, ``posecell
        measure`` and ``posecell calibrate camera`` name them (the one mapping of those knobs).

        A ``None`` leaves the default: the detector's (:class:`DetectSettings`) for ``min_contrast_dn``
        (8-bit DN), ``min_area_px`` and ``max_area_px`` (px), this class's for the others;
        ``sigma_px`` (px) None is its default, the detector's own precision. ``code_family`` is a name of
        :data:`service.core.targets.codes.FAMILIES`; ``roi_tracking`` is :attr:`roi`; ``range_mm``
        (nearest, farthest; mm) narrows the area limits to the field's targets. ``bit_depth`` (8-16)
        is the images' significant bits, so their saturation level (``2 ** bit_depth - 1``, which the
        8-bit levels scale to): a 12-bit camera's frames come as uint16 whose values end at 4095; None:
        the image dtype's maximum. ``centre``: what a target's centre is measured as, "centroid" or
        "edge" (:attr:`DetectSettings.centre`). ``max_saturated_px``: None measures disks clipped at the
        saturation level (flagged); a number rejects those with more pixels there
        (:attr:`DetectSettings.max_saturated_px`).
        """
        if code_family is not None and code_family not in FAMILIES:
            raise ValueError(f"unknown code family {code_family!r}; choose from {', '.join(FAMILIES)}")
        if bit_depth is not None and not 8 <= bit_depth <= 16:
            raise ValueError(f"bit_depth must be 8 to 16, got {bit_depth}")
        d, m = DetectSettings(), cls()  # the defaults, each written once: in those classes
        detect = replace(
            d,
            saturation_dn=d.saturation_dn if bit_depth is None else float(2**bit_depth - 1),
            min_contrast_dn=d.min_contrast_dn if min_contrast_dn is None else min_contrast_dn,
            min_area_px=d.min_area_px if min_area_px is None else min_area_px,
            max_area_px=d.max_area_px if max_area_px is None else max_area_px,
            centre=d.centre if centre is None else centre,
            max_saturated_px=max_saturated_px,
        )
        return replace(
            m,
            detect=detect,
            code_family=m.code_family if code_family is None else FAMILIES[code_family],
            min_coded=m.min_coded if min_coded is None else min_coded,
            codes_enough=m.codes_enough if codes_enough is None else codes_enough,
            min_targets=m.min_targets if min_targets is None else min_targets,
            sigma_px=sigma_px,
            max_sigma0_px=m.max_sigma0_px if max_sigma0_px is None else max_sigma0_px,
            correct_eccentricity=correct_eccentricity,
            roi=roi_tracking,
            range_mm=range_mm,
        )


@dataclass(frozen=True)
class Outcome:
    """One frame's result, how it was obtained and what it cost."""

    result: PoseResult | Failure
    mode: str  # "full" or "roi"
    timings_ms: dict[str, float]
    n_blobs: int = 0
    rejections: dict[str, int] | None = None
    brightness: Brightness | None = None  # None: the image could not be read at all


# Unnamed blobs and unnamed targets in view, each at least this many after the coded pose's
# matching: it is done again from the pose of all named so far, while a round names more
MORE_ROUND_MIN = 5
MORE_ROUNDS = 6  # rounds at most after the first
READ_MORE_MIN = 4  # rings read in a call after the first dozen (see FrameMeasurer._read_enough)
READING_GRID = 3  # cells across and down the image that reading_order takes its turns over


def reading_order(ellipse_px: Array, shape: tuple[int, ...]) -> NDArray[np.intp]:
    """An order to read coded targets' rings in: the largest disk of each cell of a
    READING_GRID x READING_GRID grid over the image, then the next largest of each, and so on.

    Large disks read most surely; spread over the image, the first dozen give a pose that predicts
    the far targets as well as the near ones (a dozen in one corner would extrapolate).
    ``ellipse_px`` (N, 5) is (u, v, a, b, angle) px; ``shape`` the image's (H, W)."""
    h, w = shape[0], shape[1]
    g = READING_GRID
    cell = np.clip(g * ellipse_px[:, 0] // w, 0, g - 1) + g * np.clip(g * ellipse_px[:, 1] // h, 0, g - 1)
    by_cell = np.lexsort((-ellipse_px[:, 2] * ellipse_px[:, 3], cell))  # by cell, largest first in each
    sorted_cell = cell[by_cell]
    rank = np.arange(by_cell.size) - np.searchsorted(sorted_cell, sorted_cell)  # place within its cell
    return by_cell[np.lexsort((sorted_cell, rank))]


def _full_dn(image: NDArray[np.generic], detect: DetectSettings) -> float:
    """The image's saturation level, DN (the detector's: ``saturation_dn`` or the dtype's maximum)."""
    if detect.saturation_dn is not None:
        return float(detect.saturation_dn)
    return DTYPE_MAX.get(image.dtype.char, 1.0)  # the images measured are 8- or 16-bit


# Blur (a lens out of focus, a near target beyond the depth of field) fills the gap between a coded
# target's disk and its ring: at the noise's segmentation level the two are one blob, refused as
# merged, and no ring is read. A frame left with too few coded targets, where as many blobs were
# refused as merged, is detected again with the segmentation level at JOINED_LEVEL of its targets'
# brightness, above the gap's blurred floor (posecell's sheet through cairo and OpenCV, blurred by
# 2.5 px: no pose before; now 91-99 % of the targets named, 0.03-0.04 px; README, *Out of focus*).
JOINED_LEVEL = 0.3


def _joined_rings_settings(
    s: MeasureSettings, e: SolveError, counts: dict[str, int], brightness: Brightness
) -> DetectSettings | None:
    """The detection to try again with after the failure ``e``, or None when it was not that."""
    signal = brightness.peak_dn - brightness.background_dn
    if e.reason != Reason.too_few_targets or counts.get("merged_or_misshapen", 0) < s.min_coded or not signal > 0:
        return None
    # min_contrast_dn is in 8-bit DN; the segmentation level is half of it
    contrast_8bit = 2.0 * JOINED_LEVEL * signal * 255.0 / brightness.full_dn
    if contrast_8bit < 1.5 * s.detect.min_contrast_dn:
        return None  # the targets are faint: no level between their gap and the noise's
    return replace(s.detect, min_contrast_dn=round(contrast_8bit, 1))


class _Clock:
    def __init__(self) -> None:
        self.t = time.perf_counter()
        self.ms: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (now - self.t) * 1e3
        self.t = now


class FrameMeasurer:
    """Measures frames of one camera against one field, keeping the pose history for ROI tracking."""

    def __init__(
        self,
        camera: BrownFraser,
        field: Field,
        settings: MeasureSettings | None = None,
        defects: DefectMap | None = None,
        frames_owned: bool = False,
    ) -> None:
        """``defects``: the sensor's defect pixels (of the camera's image size), patched in each frame
        before it is measured: in a copy, or with ``frames_owned`` (no other thread reads a frame
        while it is measured) in the frame's own pixels, put back before :meth:`measure` returns
        (:meth:`DefectMap.patched_in_place`: ~50 us for 670 defects; a copy of a 1.3 MP frame adds ~0.1 ms)."""
        if defects is not None and (defects.width, defects.height) != (camera.width, camera.height):
            raise ValueError(
                f"the defect map is of a {defects.width} x {defects.height} sensor, "
                f"the camera's images are {camera.width} x {camera.height}"
            )
        self.camera = camera
        self.field = field
        self.defects = defects if defects is not None and len(defects) else None
        self._frames_owned = frames_owned
        self._patched: NDArray[np.generic] | None = None  # the copy's buffer, reused frame after frame
        self.settings = settings or MeasureSettings()
        if self.settings.range_mm is not None:
            self.settings = replace(
                self.settings,
                detect=detect_settings_for_range(self.settings.detect, field, camera, self.settings.range_mm),
            )
        self._roi_detect = self.settings.detect  # with the last full frame's noise, for the ROI windows' levels
        self._blur_px = 0.0  # the last frame's blur (its disks' median edge sigma), for the ROI windows' rims
        self._history: deque[PoseSample] = deque(maxlen=2)
        self._mask: NDArray[np.uint8] | None = None  # detect_blobs' scratch, reused frame after frame
        self._ids = np.array(field.ids, dtype=object)  # ids by field row, for fancy indexing
        # the compiled kernels, once per process (numba's disk cache makes it a load), so that no
        # frame pays for their compilation
        detect_kernel.warm_up()
        defects_kernel.warm_up()
        geometry_kernels.warm_up()
        resection_kernel.warm_up()
        roi_kernel.warm_up()
        json_kernel.warm_up()  # the measurement process encodes the targets
        decode_warm_up()
        self._windows = PredictedWindows(camera, field)

    def reset(self) -> None:
        """Forget the pose history: the next frame is measured in full."""
        self._history.clear()

    # -- public --------------------------------------------------------------

    def measure(self, image: NDArray[np.generic], t_s: float | None = None) -> Outcome:
        """Measure one frame taken at ``t_s`` (s; None: no tracking across frames)."""
        shape = np.shape(image)
        if len(shape) == 2 and shape != (self.camera.height, self.camera.width):
            self._history.clear()  # pixels of another geometry: no pose of it is right, nor one to track
            return Outcome(Failure(Reason.bad_image, size_mismatch(shape, self.camera)), "full", {})
        if self.defects is not None and len(shape) == 2:
            if not self._frames_owned:
                self._patched = self.defects.patch(np.asarray(image), self._patched)
                return self._measure(self._patched, t_s)
            with self.defects.patched_in_place(np.asarray(image)) as patched:
                return self._measure(patched, t_s)
        return self._measure(image, t_s)

    def _measure(self, image: NDArray[np.generic], t_s: float | None) -> Outcome:
        s = self.settings
        if s.roi and t_s is not None:
            T_pred = predict_pose(list(self._history), t_s)
            if T_pred is not None:
                # without a velocity yet, the target may be anywhere the last motion could take it
                slack = 1.0 if len(self._history) >= 2 else 2.5
                out = self._measure_roi(image, T_pred, slack)
                if out is not None:
                    self._remember(out, t_s)
                    return out
        out = self._measure_full(image)
        if t_s is not None:
            self._remember(out, t_s)
        return out

    # -- internals -----------------------------------------------------------

    def _remember(self, out: Outcome, t_s: float) -> None:
        result = out.result
        if out.brightness is not None and out.brightness.n_measured > 0:
            self._blur_px = out.brightness.blur_px
        if isinstance(result, PoseResult):
            self._history.append(PoseSample(np.asarray(result.T_field_camera), t_s))
        else:
            self._history.clear()

    def _finish(self, rows: NDArray[np.int64], uv: Array, T_init: Array | None, clock: _Clock) -> PoseResult:
        """Adjust over matched targets (with eccentricity correction) and build the result."""
        s = self.settings
        p = self.field.xyz[rows]
        if s.correct_eccentricity and T_init is not None:
            # the offsets are hundredths of a pixel and vary slowly with the pose, so the
            # approximate pose is good enough and saves a second adjustment
            uv = uv - eccentricity_px(
                self.camera, p, self._windows.radius_mm[rows], T_init, uv, self.field.normal_rows(rows)
            )
        res = resect(self.camera, p, uv, sigma_px=s.sigma_px, T_field_camera_init=T_init)
        clock.lap("resect")
        if res.sigma0_px > s.max_sigma0_px:
            raise SolveError(
                Reason.no_convergence,
                f"the targets disagree with the pose by {res.sigma0_px:.2f} px (sigma0), "
                f"more than {s.max_sigma0_px} px: check the camera calibration and the field",
                {"sigma0_px": res.sigma0_px},
            )
        result = pose_result_from_resection(res, self.field, self._ids[rows].tolist(), uv, rows)
        clock.lap("result")
        return result

    def _measure_full(self, image: NDArray[np.generic]) -> Outcome:
        s = self.settings
        clock = _Clock()
        shape = np.shape(image)
        if self._mask is None or self._mask.shape != shape:
            self._mask = np.empty(shape, dtype=np.uint8) if len(shape) == 2 else None
        try:
            blobs, rejections = detect_blobs(image, s.detect, mask_buffer=self._mask)
        except SolveError as e:
            return Outcome(Failure.from_error(e), "full", clock.ms)
        clock.lap("detect")
        counts = rejections.counts
        brightness = Brightness.of(blobs, counts.get("saturated", 0), _full_dn(image, s.detect))
        # rounded: the detector caches its constants per settings
        self._roi_detect = replace(s.detect, noise_dn=round(rejections.work.noise_dn, 1))
        try:
            result = self._identify_and_resect(image, blobs, clock)
        except SolveError as e:
            raised = _joined_rings_settings(s, e, counts, brightness)
            if raised is not None:
                try:  # the blur joined the coded targets' disks to their rings: again above the join
                    blobs, rejections = detect_blobs(image, raised, mask_buffer=self._mask)
                    counts = rejections.counts
                    clock.lap("detect")
                    result = self._identify_and_resect(image, blobs, clock)
                    return Outcome(result, "full", clock.ms, len(blobs), counts, brightness)
                except SolveError as again:
                    note = f"again with the segmentation level at {JOINED_LEVEL:.0%} of the targets' brightness"
                    message = f"{again.message.rstrip('.')} ({note}, as for a blurred image)"
                    e = SolveError(again.reason, message, again.details)
            failure = Failure.from_error(with_image_hints(with_calibration_hint(e, self.camera), brightness))
            return Outcome(failure, "full", clock.ms, len(blobs), counts, brightness)
        return Outcome(result, "full", clock.ms, len(blobs), counts, brightness)

    def _identify_and_resect(self, image: NDArray[np.generic], blobs: Blobs, clock: _Clock) -> PoseResult:
        s = self.settings
        if len(blobs) < s.min_coded:
            raise SolveError(
                Reason.too_few_targets,
                f"{len(blobs)} targets found in the image, at least {s.min_coded} coded ones are needed",
            )
        coded = self._read_enough(image, blobs, np.shape(image))
        clock.lap("decode")
        if len(coded.rows) < s.min_coded:
            raise SolveError(
                Reason.too_few_targets,
                f"{len(coded.rows)} coded targets of the field identified, at least {s.min_coded} are needed",
                {"n_blobs": len(blobs), "n_coded": len(coded.rows)},
            )
        res = resect(self.camera, self.field.xyz[coded.rows], blobs.uv[coded.blobs], sigma_px=s.sigma_px)
        # the paper's second step: every other target, predicted from the coded pose
        T_field_camera = res.T_field_camera
        rows, blob_of, left = self._name_from(blobs, coded.rows[res.inliers], coded.blobs[res.inliers], T_field_camera)
        # unnamed blobs where targets in view went unnamed: the coded targets' pose predicted them
        # too far off (an approximate camera, the coded targets read on one side); again from the
        # pose of all named so far, while that names more
        for _ in range(MORE_ROUNDS if min(len(blobs) - len(blob_of), len(left[0])) >= MORE_ROUND_MIN else 0):
            try:
                T_field_camera = resect(
                    self.camera,
                    self.field.xyz[rows],
                    blobs.uv[blob_of],
                    T_field_camera_init=T_field_camera,
                    sigma_px=s.sigma_px,
                    max_sigma_px=s.max_sigma0_px,
                ).T_field_camera
            except SolveError:
                break
            n_named = len(rows)
            rows, blob_of, left = self._name_from(blobs, rows, blob_of, T_field_camera)
            if len(rows) == n_named:
                break
        rows, uv = self._name_in_windows(image, rows, blobs.uv[blob_of], T_field_camera, *left)
        clock.lap("identify")
        if len(rows) < s.min_targets:
            raise SolveError(Reason.too_few_targets, f"only {len(rows)} targets identified")
        return self._finish(rows, uv, T_field_camera, clock)

    def _name_in_windows(
        self,
        image: NDArray[np.generic],
        rows: NDArray[np.int64],
        uv_px: Array,
        T_field_camera: Array,
        left: NDArray[np.int64],
        uv_pred_px: Array,
    ) -> tuple[NDArray[np.int64], Array]:
        """``rows`` and ``uv_px`` with the targets ``left`` in view that no blob named (predicted at
        ``uv_pred_px`` (N, 2) by the pose ``T_field_camera``), measured in windows as ROI tracking
        measures them (coded targets' rings masked) where the window is whole in the image and the disk
        within ``match_tolerance_px`` of its prediction. Seen at 30 deg a far coded target's disk joins
        its ring's near arc at the segmentation level, and the blob is no disk: 1-3 a frame went unnamed."""
        # most frames leave only disks the image border cuts (refused by the detector, and here: no
        # window is whole): none is measured
        height, width = np.shape(image)[:2]
        u, v = uv_pred_px[:, 0], uv_pred_px[:, 1]
        whole = (np.minimum(u, v) > 3) & (u < width - 4) & (v < height - 4)
        if whole.any():
            left, uv_pred_px = left[whole], uv_pred_px[whole]
            u, v = uv_pred_px[:, 0], uv_pred_px[:, 1]
            axis, centre_mm = T_field_camera[:3, 2], T_field_camera[:3, 3]
            depth_mm = (self.field.xyz[left] - centre_mm) @ axis  # along the camera's axis
            half_px = self._window_half_size(left, depth_mm, TIGHT_SLACK)
            whole = (np.minimum(u, v) > half_px) & (u < width - 1 - half_px) & (v < height - 1 - half_px)
        if not whole.any():
            return rows, uv_px
        measured = self._measure_targets(
            image, T_field_camera, left[whole], uv_pred_px[whole], depth_mm[whole], TIGHT_SLACK, least=0
        )
        if measured is None:
            return rows, uv_px
        more, more_uv_px, _ = measured
        predicted_px = np.empty((len(self.field), 2))
        predicted_px[left] = uv_pred_px
        near = np.hypot(*(more_uv_px - predicted_px[more]).T) <= self.settings.match_tolerance_px
        return np.concatenate([rows, more[near]]), np.vstack([uv_px, more_uv_px[near]])

    def _name_from(
        self, blobs: Blobs, rows: NDArray[np.int64], blob_of: NDArray[np.int64], T_field_camera: Array
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], tuple[NDArray[np.int64], Array]]:
        """The paper's second step from the pose ``T_field_camera``: each target in view not among
        the field ``rows`` named so far, predicted and matched one to one to a blob not among
        ``blob_of``. Returns the rows and blobs named in all, and the targets in view left unnamed
        (rows, and where they were predicted (N, 2) px)."""
        named = np.zeros(len(self.field), dtype=bool)
        named[rows] = True
        taken = np.zeros(len(blobs), dtype=bool)
        taken[blob_of] = True
        in_view, uv_pred = project_field(self.camera, self.field, T_field_camera, margin_px=-2.0)
        todo = ~named[in_view]
        m = match_predicted(uv_pred[todo], in_view[todo], blobs.uv, self.settings.match_tolerance_px, taken)
        named[m.rows] = True
        left = ~named[in_view]
        return np.concatenate([rows, m.rows]), np.concatenate([blob_of, m.blobs]), (in_view[left], uv_pred[left])

    def _read_enough(self, image: NDArray[np.generic], blobs: Blobs, shape: tuple[int, ...]) -> Matches:
        """The coded targets named by their rings, read in :func:`reading_order` until
        ``codes_enough`` of them (and ``min_coded``) are matched to the field (0: every ring).

        Only a blob the detector found ring pieces around can be coded. Reading a ring costs ~50 us
        (a third of a reference frame for its 30); the paper's second step names the unread ones
        from the pose of the first dozen just as it names the uncoded targets, and they are as
        "coded" in the result (the field's kind of target, not how it was named). When some of
        the first dozen are not read, twice as many more as are missing are read next (at least
        READ_MORE_MIN: a call costs ~20 us of its own), and so on."""
        s = self.settings
        ringed = np.flatnonzero(blobs.has_ring)
        order = ringed[reading_order(blobs.ellipse[ringed], shape)]
        # never fewer than a pose needs (min_coded): a frame is not refused with rings left unread
        enough = max(s.codes_enough, s.min_coded) if s.codes_enough > 0 else order.size
        codes_read = np.full(len(blobs), -1, dtype=np.int64)
        coded = Matches(np.zeros(0, np.int64), np.zeros(0, np.int64))
        done, want = 0, enough
        while done < order.size and len(coded.rows) < enough:
            batch = order[done : done + want]
            readings = read_codes(image, blobs.ellipse[batch], blobs.background_dn[batch], family=s.code_family)
            codes_read[batch] = [-1 if r is None else r.code for r in readings]
            coded = match_coded(self.field, codes_read)
            done += batch.size
            want = max(READ_MORE_MIN, 2 * (enough - len(coded.rows)))
        return coded

    def _measure_roi(self, image: NDArray[np.generic], T_pred: Array, slack: float = 1.0) -> Outcome | None:
        s = self.settings
        clock = _Clock()
        rows, uv_pred, depth = project_field(self.camera, self.field, T_pred, margin_px=4.0, with_depth=True)
        if len(rows) < s.min_targets:
            return None
        measured = None
        if s.roi_refine and slack <= 1.0:
            # with a velocity the prediction is usually far better than the allowance: measure every
            # target in tight windows right away, and keep that only if each disk lies as close to
            # its window's centre as the tight windows are made for (else: two stages, below)
            measured = self._measure_targets(image, T_pred, rows, uv_pred, depth, TIGHT_SLACK, check_centred=True)
        if measured is None and s.roi_refine:
            # stage 1: locate the uncoded targets in generous windows and re-solve the pose, so
            # that stage 2 can measure every target (coded ones too, whose rings are masked about
            # the predicted disk) in tight windows around precise predictions
            uncoded = self.field.codes[rows] < 0
            half = self._window_half_size(rows[uncoded], depth[uncoded], slack)
            try:
                blobs, found = measure_windows(image, uv_pred[uncoded], half, self._roi_detect)
                ok = found >= 0
                if ok.sum() < max(s.min_targets, s.roi_min_fraction * uncoded.sum()):
                    return None
                T_pred = resect(
                    self.camera,
                    self.field.xyz[rows[uncoded][ok]],
                    blobs.uv[found[ok]],
                    sigma_px=s.sigma_px,
                    T_field_camera_init=T_pred,
                ).T_field_camera
            except (ValueError, SolveError):
                return None
            rows, uv_pred, depth = project_field(self.camera, self.field, T_pred, margin_px=4.0, with_depth=True)
            slack = TIGHT_SLACK
        if measured is None:
            measured = self._measure_targets(image, T_pred, rows, uv_pred, depth, slack)
        clock.lap("windows")
        if measured is None:
            return None
        rows_ok, uv_ok, blobs = measured
        try:
            result = self._finish(rows_ok, uv_ok, T_pred, clock)
        except SolveError:
            return None
        if result.sigma0_px > s.roi_max_sigma0_px:
            return None
        brightness = Brightness.of(blobs, 0, _full_dn(image, s.detect))
        return Outcome(result, "roi", clock.ms, len(rows_ok), None, brightness)

    def _measure_targets(
        self,
        image: NDArray[np.generic],
        T_pred: Array,
        rows: NDArray[np.int64],
        uv_pred: Array,
        depth: Array,
        slack: float,
        check_centred: bool = False,
        least: int | None = None,
    ) -> tuple[NDArray[np.int64], Array, Blobs] | None:
        """Field rows and measured pixels (N, 2) of the targets found in windows about their
        predictions, and the disks measured; None when too few are found or, with
        ``check_centred``, when a disk lies further from its window's centre than ``slack`` times
        the prediction allowance; ``least``: found by default ``roi_min_fraction`` of them and
        ``min_targets``. A coded target's ring is masked in its window (in an oblique view it
        comes within the window of its disk): its own region is its disk predicted by ``T_pred``;
        where the prediction held, windows that found no disk are measured again with all but the
        disk masked (:mod:`service.pipeline.windows`)."""
        s = self.settings
        half = self._window_half_size(rows, depth, slack)
        measured = self._windows.measure(image, T_pred, rows, uv_pred, half, self._roi_detect, s.code_family.ring_inner)
        if measured is None:
            return None
        blobs, found = measured
        # compiled: as array expressions the gathering and the check were 2 % of an ROI frame
        rows_ok, uv, worst_px2 = roi_kernel.gather_found_kernel(found, blobs.uv, rows, uv_pred)
        if check_centred and worst_px2 > (slack * s.roi_prediction_error_px) ** 2:
            return None
        if len(rows_ok) < len(rows):  # the prediction held: something bright beside a disk refused it
            blobs, found = self._windows.measure_missed(
                image, T_pred, rows, uv_pred, half, self._roi_detect, blobs, found
            )
            rows_ok, uv, _ = roi_kernel.gather_found_kernel(found, blobs.uv, rows, uv_pred)
        if least is None:
            least = max(s.min_targets, int(np.ceil(s.roi_min_fraction * len(rows))))
        if len(rows_ok) < least:
            return None
        return rows_ok, uv, blobs

    def _window_half_size(self, rows: NDArray[np.int64], depth: Array, slack: float = 1.0) -> NDArray[np.int64]:
        """Half window (px) per target at ``depth`` (mm): :meth:`PredictedWindows.half_size` with
        ``slack`` times the prediction allowance and the last frame's blur."""
        return self._windows.half_size(rows, depth, slack * self.settings.roi_prediction_error_px, self._blur_px)
