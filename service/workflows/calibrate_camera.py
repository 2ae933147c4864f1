"""The calibration workflows behind ``posecell calibrate camera`` and ``posecell calibrate rig``.

Camera: read the field, measure the targets in every image with the pipeline
(:class:`service.pipeline.measure.FrameMeasurer`: detect, decode, identify, resect) or read
given observations, run the self-calibrating bundle adjustment
(:func:`service.core.calib.bundle.calibrate_camera`), and write ``camera.json`` (DESIGN
section 2, with ``sigma`` and a ``calibration`` block) and optionally the surveyed
``field.json`` (each target with ``sigma_mm``). Images are measured twice by
default: first with the start camera (its unmodelled distortion limits which
targets are found near the edges), then with the first calibration.

Rig: the same per camera, then :func:`service.core.calib.rig.calibrate_rig` and ``rig.json``.

Progress goes to stderr: a bar while images are measured, the adjustment's
stages and iterations after.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from service.core.calib.bundle import BundleResult, Datum, ImagePoints, ScaleBar, calibrate_camera
from service.core.calib.rig import RigCalibration, RigImage, calibrate_rig
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.results import PoseResult
from service.core.targets.codes import FAMILIES
from service.core.targets.detect import DetectSettings
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
    """How the targets are measured in calibration images (see ``posecell measure``)."""

    code_family: str = "posecell12"
    min_contrast_dn: float | None = None
    min_area_px: int | None = None
    max_area_px: int | None = None
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

    detect = DetectSettings(
        **{
            k: v
            for k, v in (
                ("min_contrast_dn", options.min_contrast_dn),
                ("min_area_px", options.min_area_px),
                ("max_area_px", options.max_area_px),
            )
            if v is not None
        }
    )
    settings = MeasureSettings(detect=detect, code_family=FAMILIES[options.code_family], roi=False)
    if first_pass:
        settings = replace(settings, sigma_px=options.start_sigma_px, max_sigma0_px=options.start_max_sigma0_px)
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


def camera_json(result: BundleResult) -> dict[str, Any]:
    d = result.camera.to_dict()
    d["calibration"] = result.report()
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


def _common_options(args: Any) -> dict[str, Any]:
    bars = [parse_scale_bar(b) for b in args.scale_bar or []]
    measure = MeasureOptions(
        code_family=args.code_family,
        min_contrast_dn=args.min_contrast_dn,
        min_area_px=args.min_area_px,
        max_area_px=args.max_area_px,
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
        **_common_options(args),
    }


def rig_options(args: Any) -> dict[str, Any]:
    """Keyword arguments of :func:`run_rig_calibration` from ``posecell calibrate rig``'s; ValueError if bad."""
    if args.time_tolerance_s is not None and not (math.isfinite(args.time_tolerance_s) and args.time_tolerance_s > 0):
        raise ValueError(f"--time-tolerance-s {args.time_tolerance_s:g} must be a positive number of seconds")
    return {
        "image_dirs": args.images or (),
        "observations": args.observations,
        "pairs": args.pairs,
        "pair_by": args.pair_by,
        "time_tolerance_s": args.time_tolerance_s,
        "drop_unpaired": args.drop_unpaired,
        "free_interior": parse_names(args.free_interior),
        "survey_field": args.survey_field,
        **_common_options(args),
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
    formats.write_json_atomic(output, formats.null_for_unknown(camera_json(result)))
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


# -- rig: which images were exposed together ---------------------------------------------------

#: How ``calibrate rig`` pairs the images of its camera folders (``--pair-by``).
PAIR_BY = ("auto", "name", "frame", "time")
#: The optional exposure-time sidecar of a camera folder (:func:`formats.read_image_timestamps`).
TIMESTAMPS_FILE = "timestamps.csv"


class PairingError(ValueError):
    """The images cannot be paired into epochs without guessing."""


def _frame_numbers(names: Sequence[str]) -> list[int]:
    """The frame number in each file name of one camera's folder: the only number that differs between
    the names (``cam1_0012.png`` -> 12), or the only number in them. PairingError if there is none or
    it cannot be told which."""
    groups = [re.findall(r"\d+", Path(n).stem) for n in names]
    if any(not g for g in groups) or len({len(g) for g in groups}) != 1:
        odd = next((n for n, g in zip(names, groups, strict=True) if len(g) != len(groups[0]) or not g), names[0])
        raise PairingError(f"the names do not all carry frame numbers in the same place (e.g. {odd!r})")
    varying = [i for i in range(len(groups[0])) if len({g[i] for g in groups}) > 1]
    if len(groups[0]) > 1 and len(varying) != 1:
        raise PairingError(f"it cannot be told which number in names like {names[0]!r} is the frame number")
    pos = varying[0] if len(groups[0]) > 1 else 0
    return [int(g[pos]) for g in groups]


def _unique_keys(names: Sequence[str], keys: Sequence[Any], camera: int, what: str) -> dict[Any, int]:
    out: dict[Any, int] = {}
    for j, key in enumerate(keys):
        if key in out:
            raise PairingError(f"camera {camera} has two images of {what} {key}: {names[out[key]]} and {names[j]}")
        out[key] = j
    return out


def pair_epochs(
    names: Sequence[Sequence[str]],
    by: str,
    *,
    times_ns: Sequence[Sequence[int]] | None = None,
    tolerance_s: float = 0.005,
) -> tuple[list[list[int]], list[tuple[int, int]], str]:
    """Which images of K cameras were exposed together, never by guesswork.

    ``by``: ``name`` (the same file name less its suffix), ``frame`` (the frame number in the names,
    :func:`_frame_numbers`), ``time`` (``times_ns``: the one image of camera k within ``tolerance_s``
    of camera 0's, with no other image of either camera that near) or ``auto`` (``name`` if any name
    is shared by every camera, else ``frame``). Returns the epochs (one image index per camera, in
    camera 0's order), the unpaired images ``(camera, index)`` and the rule used (``auto`` resolved).
    Raises PairingError when a pairing would be ambiguous: two images of one key in a camera, two
    candidates within the tolerance, or names that pair neither by name nor by frame number.
    """
    K = len(names)
    if by == "auto":
        stems = [{Path(n).stem for n in ns} for ns in names]
        if set.intersection(*stems):
            by = "name"
        else:
            try:
                return pair_epochs(names, "frame")
            except PairingError as e:
                raise PairingError(
                    f"the images pair neither by file name nor by frame number ({e}): list them "
                    f"in --pairs FILE or pair them by --pair-by time"
                ) from None
    if by == "time":
        if times_ns is None:
            raise ValueError("pairing by time needs the images' timestamps")
        return (*_pair_by_time(names, times_ns, tolerance_s), "time")
    if by not in ("name", "frame"):
        raise ValueError(f"unknown pairing {by!r}; choose from {', '.join(PAIR_BY)}")
    what = "name" if by == "name" else "frame"
    maps = []
    for k, ns in enumerate(names):
        try:
            keys: list[Any] = [Path(n).stem for n in ns] if by == "name" else _frame_numbers(ns)
        except PairingError as e:
            raise PairingError(f"camera {k}: {e}") from None
        maps.append(_unique_keys(ns, keys, k, what))
    common = set(maps[0]).intersection(*maps[1:])
    epochs = [[m[key] for m in maps] for key in sorted(common, key=lambda key: maps[0][key])]
    unpaired = sorted((k, j) for k in range(K) for key, j in maps[k].items() if key not in common)
    return epochs, unpaired, by


def _pair_by_time(
    names: Sequence[Sequence[str]], times_ns: Sequence[Sequence[int]], tolerance_s: float
) -> tuple[list[list[int]], list[tuple[int, int]]]:
    """:func:`pair_epochs` by exposure time: a pair must be unique within the tolerance both ways."""
    tol_ns = round(tolerance_s * 1e9)
    t0 = np.asarray(times_ns[0], dtype=np.int64)
    partner = []
    for k in range(1, len(names)):
        near = np.abs(t0[:, None] - np.asarray(times_ns[k], dtype=np.int64)[None, :]) <= tol_ns  # (n0, nk)
        # two candidates either way round: which one was exposed with it cannot be told
        for a, b, cand in ((0, k, near), (k, 0, near.T)):
            many = np.flatnonzero(cand.sum(axis=1) > 1)
            if len(many):
                i = int(many[0])
                shown = ", ".join(names[b][j] for j in np.flatnonzero(cand[i])[:3])
                raise PairingError(
                    f"image {names[a][i]} of camera {a} has {int(cand[i].sum())} images of camera "
                    f"{b} within {tolerance_s:g} s ({shown}): lower --time-tolerance-s or list the "
                    f"pairs in --pairs FILE"
                )
        partner.append({int(i): int(j) for i, j in zip(*np.nonzero(near), strict=True)})
    epochs = [[i, *(p[i] for p in partner)] for i in range(len(t0)) if all(i in p for p in partner)]
    used = [{e[k] for e in epochs} for k in range(len(names))]
    unpaired = [(k, j) for k in range(len(names)) for j in range(len(names[k])) if j not in used[k]]
    return epochs, unpaired


def _describe_unpaired(paths: Sequence[Path]) -> str:
    shown = [f"{p.parent.name}/{p.name}" for p in paths[:4]]
    more = f" and {len(paths) - 4} more" if len(paths) > 4 else ""
    return f"{len(paths)} image{'s' if len(paths) > 1 else ''} without a partner ({', '.join(shown)}{more})"


def _rig_shots(
    image_dirs: Sequence[str],
    *,
    pair_by: str = "auto",
    pairs_file: str | None = None,
    n_cameras: int | None = None,
    time_tolerance_s: float = 0.005,
    drop_unpaired: bool = False,
) -> tuple[list[tuple[str, list[Path]]], list[Path], str]:
    """Epoch name (camera 0's image) and one image per camera, the images left out, and the rule used.

    The images come from a folder per camera, paired by :func:`pair_epochs` (``time``: from each
    folder's ``timestamps.csv``), or from ``pairs_file`` (:func:`formats.read_rig_pairs`, paths relative
    to its folder). An image without a partner is refused (a missing frame may mean the cameras'
    counters or clocks are out of step, and a pairing by position would shift every epoch after it),
    or with ``drop_unpaired`` left out (the caller says so). Raises ``ValueError`` (PairingError) for bad input.
    """
    if pairs_file is not None:
        rows = formats.read_rig_pairs(pairs_file, n_cameras or 2)
        base, seen, out = Path(pairs_file).parent, set(), []
        for row in rows:
            paths = [p if p.is_absolute() else base / p for p in map(Path, row)]
            for p in paths:
                if not p.is_file():
                    raise formats.FormatError(f"{pairs_file}: {p} is not an image file")
                if p.resolve() in seen:
                    raise PairingError(f"{pairs_file}: image {p} is listed in two epochs")
                seen.add(p.resolve())
            out.append((row[0], paths))
        return out, [], "pairs file"
    per_cam = [image_paths([d]) for d in image_dirs]
    for d, ps in zip(image_dirs, per_cam, strict=True):
        if not ps:
            raise ValueError(f"camera folder {d} holds no images")
    times = None
    if pair_by == "time":
        times = []
        for d, ps in zip(image_dirs, per_cam, strict=True):
            stamps = formats.read_image_timestamps(Path(d) / TIMESTAMPS_FILE)
            missing = [p.name for p in ps if p.name not in stamps]
            if missing:
                raise PairingError(
                    f"{Path(d) / TIMESTAMPS_FILE} has no timestamp for {missing[0]}"
                    + (f" and {len(missing) - 1} more images" if len(missing) > 1 else "")
                )
            times.append([stamps[p.name] for p in ps])
    epochs, unpaired, by = pair_epochs(
        [[p.name for p in ps] for ps in per_cam], pair_by, times_ns=times, tolerance_s=time_tolerance_s
    )
    left_out = [per_cam[k][j] for k, j in unpaired]
    if left_out and not drop_unpaired:
        raise PairingError(
            f"{_describe_unpaired(left_out)}: a frame is missing in a camera; leave such images out "
            f"with --drop-unpaired, or list the pairs in --pairs FILE"
        )
    if not epochs:
        raise PairingError("no epoch has an image of every camera")
    return [(per_cam[0][e[0]].name, [per_cam[k][j] for k, j in enumerate(e)]) for e in epochs], left_out, by


def run_rig_calibration(
    field_path: str,
    camera_paths: Sequence[str],
    *,
    output: str,
    image_dirs: Sequence[str] = (),
    observations: str | None = None,
    pairs: str | None = None,
    pair_by: str = "auto",
    time_tolerance_s: float | None = None,
    drop_unpaired: bool = False,
    free_interior: Sequence[str] = (),
    survey_field: bool = False,
    scale_bars: Sequence[ScaleBar] = (),
    sigma_px: float = 0.1,
    reject_outliers: bool = True,
    measure: MeasureOptions = MeasureOptions(),
    progress: ProgressBar | None = None,
) -> RigCalibration:
    """Calibrate a rig from simultaneous images (a folder per camera, or ``pairs``) or observations;
    write rig.json. The images are paired into epochs by :func:`_rig_shots` (``pair_by``, ``pairs``,
    ``time_tolerance_s``, ``drop_unpaired``)."""
    if sum(map(bool, (image_dirs, observations, pairs))) != 1:
        raise ValueError("give one of --images (one folder per camera), --pairs or --observations")
    if pairs and pair_by != "auto":
        raise ValueError("--pairs lists the epochs itself: leave out --pair-by")
    if time_tolerance_s is not None and pair_by != "time":
        raise ValueError("--time-tolerance-s is for --pair-by time")
    field = formats.read_field(field_path)
    cameras = [formats.read_camera(p) for p in camera_paths]
    shots: list[RigImage] = []
    left_out: list[Path] = []
    pairing = "observations file"  # its images carry their epoch
    if observations:
        for o in formats.read_image_observations(observations):
            if o.camera is None or o.epoch is None:
                raise formats.FormatError(f"{observations}: image {o.name!r} needs 'camera' and 'epoch' for a rig")
            twin = next((s.name for s in shots if s.epoch == o.epoch and s.camera == o.camera), None)
            if twin is not None:
                raise formats.FormatError(
                    f"{observations}: epoch {o.epoch!r} has two images of camera {o.camera} ({twin!r} and {o.name!r})"
                )
            shots.append(RigImage(o.epoch, o.camera, tuple(o.ids), o.uv, o.name))
    else:
        if image_dirs and len(image_dirs) != len(cameras):
            raise ValueError(f"{len(image_dirs)} image folders but {len(cameras)} cameras (--camera, one per folder)")
        epochs, left_out, pairing = _rig_shots(
            image_dirs,
            pair_by=pair_by,
            pairs_file=pairs,
            n_cameras=len(cameras),
            time_tolerance_s=0.005 if time_tolerance_s is None else time_tolerance_s,
            drop_unpaired=drop_unpaired,
        )
        for k in range(len(cameras)):
            names = [e[1][k].name for e in epochs]
            if len(set(names)) != len(names):  # measured images are matched back by file name
                raise PairingError(f"{pairs}: camera {k}'s images must have distinct file names")
        if left_out and progress is not None:
            progress.note(f"left out {_describe_unpaired(left_out)}")
        meas = replace(measure, start_sigma_px=0.5, start_max_sigma0_px=2.0)  # calibrated cameras
        for k, cam in enumerate(cameras):
            got, failures = measure_images(cam, field, [e[1][k] for e in epochs], meas, progress, label=f"camera {k}")
            by_name = {g.name: g for g in got}
            for name, paths in epochs:
                g = by_name.get(paths[k].name)
                if g is not None:
                    shots.append(RigImage(name, k, g.ids, g.uv, g.name))
            for f in failures:
                if progress is not None:
                    progress.note(f"camera {k}: skipped {f}")
    if len(cameras) < 2:
        raise ValueError("a rig needs at least 2 cameras (--camera cam0.json cam1.json ...)")
    result = calibrate_rig(
        cameras,
        field,
        shots,
        free_interior=free_interior,
        field_fixed=not survey_field,
        datum=Datum(scale_bars=tuple(scale_bars)),
        sigma_px=sigma_px,
        reject_outliers=reject_outliers,
        progress=progress.status if progress is not None else None,
    )
    notes = [f"left out {_describe_unpaired(left_out)}"] if left_out else []
    result = replace(
        result,
        warnings=(*notes, *result.warnings),
        extra={**result.extra, "pairing": pairing, "images_left_out": [str(p) for p in left_out]},
    )
    if progress is not None:
        progress.close()
    formats.write_json_atomic(output, formats.null_for_unknown(result.to_dict()))
    return result


def rig_summary(result: RigCalibration, output: str) -> dict[str, Any]:
    return {
        "ok": True,
        "output": str(output),
        "sigma0_px": round(result.sigma0_px, 5),
        "n_epochs": len(result.epochs),
        "n_cameras": result.rig.n_cameras,
        "T_master_camera": [[[round(float(v), 9) for v in row] for row in T] for T in result.rig.T_master_camera],
        "sigma_position_mm": result.sigma_position_mm.round(6).tolist(),
        "sigma_rotation_deg": result.sigma_rotation_deg.round(8).tolist(),
        "sigma_source": result.sigma_source,
        "sigma_position_formal_mm": result.sigma_position_formal_mm.round(6).tolist(),
        "sigma_position_jackknife_mm": [
            [None if not math.isfinite(v) else round(float(v), 6) for v in row]
            for row in result.sigma_position_jackknife_mm
        ],
        "pairing": result.extra.get("pairing"),
        "warnings": list(result.warnings),
    }


__all__ = [
    "PAIR_BY",
    "MeasureOptions",
    "PairingError",
    "ProgressBar",
    "camera_json",
    "camera_options",
    "measure_images",
    "pair_epochs",
    "parse_names",
    "parse_scale_bar",
    "refined_field_json",
    "rig_options",
    "rig_summary",
    "run_camera_calibration",
    "run_rig_calibration",
    "start_camera",
    "summary",
]
