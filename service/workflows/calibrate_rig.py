"""The calibration workflow behind ``posecell calibrate rig``: the relative orientation of rigid cameras.

Pair the images of the cameras' folders into epochs (one image per camera exposed
together: :func:`pair_epochs`, by file name, frame number or exposure time, or as
listed in a pairs file; never by guesswork), measure every camera's images with
the pipeline (:func:`service.workflows.calibrate_camera.measure_images`) or read
given observations, run the bundle adjustment with the rig constraint
(:func:`service.core.calib.rig.calibrate_rig`) and write ``rig.json``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from service.core.calib.bundle import Datum, ScaleBar
from service.core.calib.rig import RigCalibration, RigImage, calibrate_rig
from service.store import formats
from service.workflows.calibrate_camera import (
    MeasureOptions,
    ProgressBar,
    common_options,
    image_paths,
    measure_images,
    parse_names,
)

_MEASURE = MeasureOptions()  # the detector's defaults (frozen: one instance serves every call)


# -- which images were exposed together -------------------------------------------------------

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


# -- command-line arguments -------------------------------------------------------------------


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
        **common_options(args),
    }


# -- the workflow ---------------------------------------------------------------------------


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
    measure: MeasureOptions = _MEASURE,
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
    "TIMESTAMPS_FILE",
    "PairingError",
    "pair_epochs",
    "rig_options",
    "rig_summary",
    "run_rig_calibration",
]
