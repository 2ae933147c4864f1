"""From an accuracy test's raw samples to its report (the dict ``posecell report`` writes) and its tables.

A sample is one measured frame, JSON-ready (what :class:`service.store.tests_store.TestStore`
keeps): ``t_exposure_unix_ns``, ``t_s`` (since the test began), ``label`` (``ccw``/``cw``, a pose
``P1`` …, a position ``1`` …), ``visit`` (lap, cycle, visit), ``stop`` (the stop's number; None on
a path), ``T_base_flange_measured`` (from the camera through the hand-eye), ``T_base_flange_reported``
(the controller's, at the exposure), ``sigma_position_mm`` / ``sigma_rotation_deg`` (of the measured
flange, base axes), and where known ``T_base_flange_cmd`` (the program's target) and
``T_base_flange_true`` (the simulation's truth). The analyses are the core's
(:mod:`service.core.accuracy`); a stop is the mean of its frames (positions averaged, rotations by
their chordal mean), its σ the frames' RMS σ over √n, as for independent frames.

Each report comes with ``details``: the conditions (frames per stop, σ) and, where every sample
carries the truth, ``truth``: the same analysis of the true poses (zero σ), which a simulated
test is checked against.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.accuracy.circle import circle_result
from service.core.accuracy.iso9283 import iso9283_dict, pose_series
from service.core.accuracy.table1 import table1
from service.core.geometry.frames import kuka_abc_deg_from_R, make_T
from service.core.geometry.so3 import R_mean
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]
Sample = dict[str, Any]

# DESIGN section 5's CSV columns (``posecell report`` reads them), then extras it ignores
CIRCLE_CSV = ("t_s", "direction", "x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm")
ISO9283_CSV = ("pose", "cycle", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm", "a_cmd_deg", "b_cmd_deg", "c_cmd_deg")
POSE_CSV = ("x_mm", "y_mm", "z_mm", "a_deg", "b_deg", "c_deg")
SIGMA_CSV = ("sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_a_deg", "sigma_b_deg", "sigma_c_deg")
TRUE_CSV = ("x_true_mm", "y_true_mm", "z_true_mm", "a_true_deg", "b_true_deg", "c_true_deg")


def _T(s: Sample, key: str) -> Array | None:
    v = s.get(key)
    return None if v is None else np.asarray(v, dtype=np.float64)


def _stack(samples: Sequence[Sample], key: str) -> Array | None:
    Ts = [_T(s, key) for s in samples]
    return None if not Ts or any(T is None for T in Ts) else np.stack(Ts)  # type: ignore[arg-type]


def _xyzabc(T: Array) -> list[float]:
    return [*T[:3, 3].tolist(), *kuka_abc_deg_from_R(T[:3, :3]).tolist()]


def _mean_T(Ts: Array) -> Array:
    return make_T(R_mean(Ts[:, :3, :3]), Ts[:, :3, 3].mean(axis=0))


def stops_of(samples: Sequence[Sample]) -> list[dict[str, Any]]:
    """Per stop, in order: label, visit, n frames, the mean measured / reported / commanded / true pose
    (4, 4) and the σ of the mean measured pose (position mm, rotation deg, base axes)."""
    groups: dict[int, list[Sample]] = {}
    for s in samples:
        if s.get("stop") is not None:
            groups.setdefault(int(s["stop"]), []).append(s)
    out = []
    for k in sorted(groups):
        g = groups[k]
        n = len(g)
        sp = np.array([s["sigma_position_mm"] for s in g], dtype=np.float64)
        sr = np.array([s["sigma_rotation_deg"] for s in g], dtype=np.float64)
        stop: dict[str, Any] = {
            "stop": k,
            "label": str(g[0]["label"]),
            "visit": int(g[0]["visit"]),
            "n_frames": n,
            "t_s": float(np.mean([s["t_s"] for s in g])),
            "sigma_position_mm": np.sqrt(np.mean(sp**2, axis=0) / n),
            "sigma_rotation_deg": np.sqrt(np.mean(sr**2, axis=0) / n),
        }
        for key in ("T_base_flange_measured", "T_base_flange_reported", "T_base_flange_cmd", "T_base_flange_true"):
            Ts = _stack(g, key)
            stop[key] = None if Ts is None else _mean_T(Ts)
        out.append(stop)
    return out


def _has_truth(items: Sequence[dict[str, Any]]) -> bool:
    return bool(items) and all(i.get("T_base_flange_true") is not None for i in items)


def _bad(message: str) -> SolveError:
    return SolveError(Reason.bad_input, message)


# ---------------------------------------------------------------- the three analyses


def circle_report(
    samples: Sequence[Sample], radius_mm: float, centre_mm: Sequence[float] | None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(report, details)`` of the circular test: the samples labelled ``ccw``/``cw`` in time order."""
    path = [s for s in samples if s.get("label") in ("ccw", "cw")]
    if not path:
        raise _bad("no measured frame lies on the circle: nothing to analyse (was the camera measuring?)")
    directions = [s["label"] for s in path]
    T_meas = _stack(path, "T_base_flange_measured")
    T_rep = _stack(path, "T_base_flange_reported")
    assert T_meas is not None and T_rep is not None
    result = circle_result(
        T_meas[:, :3, 3],
        directions,
        radius_mm,
        centre_mm=centre_mm,
        R=T_meas[:, :3, :3],
        p_robot_mm=T_rep[:, :3, 3],
        R_robot=T_rep[:, :3, :3],
    )
    sp = np.array([s["sigma_position_mm"] for s in path], dtype=np.float64)
    details: dict[str, Any] = {
        "n_points": {d: directions.count(d) for d in ("ccw", "cw")},
        # the largest per-point σ of the flange position (3-D): what a point's radius may be off by, 1 σ
        "sigma_point_max_mm": float(np.max(np.linalg.norm(sp, axis=1))),
        "sigma_point_median_mm": float(np.median(np.linalg.norm(sp, axis=1))),
    }
    if _has_truth(path):
        T_true = _stack(path, "T_base_flange_true")
        assert T_true is not None
        truth = circle_result(
            T_true[:, :3, 3], directions, radius_mm, centre_mm=centre_mm, R=T_true[:, :3, :3], R_robot=T_rep[:, :3, :3]
        )
        details["truth"] = truth.to_dict()
        err = np.linalg.norm(T_meas[:, :3, 3] - T_true[:, :3, 3], axis=1)
        details["measured_minus_true_mm"] = {"max": float(err.max()), "rms": float(np.sqrt(np.mean(err**2)))}
    return result.to_dict(points=True), details


def _series(stops: Sequence[dict[str, Any]], key: str, commanded: dict[str, Array]) -> dict[str, Any]:
    names = list(dict.fromkeys(s["label"] for s in stops))
    out = {}
    for name in names:
        mine = [s for s in stops if s["label"] == name]
        Ts = np.stack([s[key] for s in mine])
        T_c = commanded[name]
        out[name] = pose_series(
            name, T_c[:3, 3], T_c[:3, :3], Ts[:, :3, 3], Ts[:, :3, :3], cycles=[s["visit"] for s in mine]
        )
    return out


def commanded_poses(stops: Sequence[dict[str, Any]]) -> tuple[dict[str, Array], str]:
    """Per pose its commanded ``T_base_flange`` (4, 4): the program's, or (a real robot's program, not
    known here) the mean reported pose over the pose's stops; and which of the two (``program`` / ``reported``)."""
    commanded: dict[str, Array] = {}
    source = "program"
    for name in dict.fromkeys(s["label"] for s in stops):
        mine = [s for s in stops if s["label"] == name]
        if all(s["T_base_flange_cmd"] is not None for s in mine):
            commanded[name] = mine[0]["T_base_flange_cmd"]
        else:
            source = "reported"
            commanded[name] = _mean_T(np.stack([s["T_base_flange_reported"] for s in mine]))
    return commanded, source


def iso9283_report(samples: Sequence[Sample]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(report, details)`` of ISO 9283: one attained pose per stop (the mean of its frames) against
    the commanded pose (the program's; in record mode the mean reported pose of that pose's stops)."""
    stops = stops_of(samples)
    if not stops:
        raise _bad("no stop was measured: nothing to analyse")
    commanded, source = commanded_poses(stops)
    report = iso9283_dict(_series(stops, "T_base_flange_measured", commanded))
    details: dict[str, Any] = {
        "commanded_from": source,
        "frames_per_stop": [s["n_frames"] for s in stops],
        "commanded": {name: _xyzabc(T) for name, T in commanded.items()},
        # σ of a pose's barycentre from its cycles' σ: sqrt(mean σ² / n) per axis, then the 3-D norm
        "sigma_barycentre_mm": {
            name: float(
                np.linalg.norm(
                    np.sqrt(np.mean([s["sigma_position_mm"] ** 2 for s in stops if s["label"] == name], axis=0))
                    / np.sqrt(sum(1 for s in stops if s["label"] == name))
                )
            )
            for name in commanded
        },
    }
    if _has_truth(stops):
        details["truth"] = iso9283_dict(_series(stops, "T_base_flange_true", commanded))
    return report, details


def table1_report(samples: Sequence[Sample]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(report, details)`` of the paper's Table 1: the stops in visit order, labelled by position."""
    stops = stops_of(samples)
    if len(stops) < 2:
        raise _bad(f"{len(stops)} stop(s) measured; the forward and reverse visits need at least 2")
    labels = [s["label"] for s in stops]
    T = np.stack([s["T_base_flange_measured"] for s in stops])
    sp = np.stack([s["sigma_position_mm"] for s in stops])
    sr = np.stack([s["sigma_rotation_deg"] for s in stops])
    report = table1(T, sp, sr, labels=labels).to_dict()
    details: dict[str, Any] = {"frames_per_stop": [s["n_frames"] for s in stops], "labels": labels}
    if _has_truth(stops):
        T_true = np.stack([s["T_base_flange_true"] for s in stops])
        details["truth"] = table1(T_true, np.zeros_like(sp), np.zeros_like(sr), labels=labels).to_dict()
    return report, details


# ---------------------------------------------------------------- tables (CSV / JSON export)


def sample_table(kind: str, samples: Sequence[Sample], per: str) -> tuple[list[str], list[list[Any]]]:
    """Columns and rows of the samples as DESIGN section 5's CSV of ``kind`` (``posecell report`` reads
    them back), one row per frame (``per="frame"``) or per stop (``per="stop"``, ISO 9283 and Table 1)."""
    if per not in ("frame", "stop"):
        raise ValueError(f"per must be 'frame' or 'stop', not {per!r}")
    if kind == "circle":
        columns = [*CIRCLE_CSV, *TRUE_CSV[:3], "lap", "sigma_mm", "t_exposure_unix_ns"]
        rows = []
        for s in samples:
            if s.get("label") not in ("ccw", "cw"):
                continue
            m, r, t = (_T(s, k) for k in ("T_base_flange_measured", "T_base_flange_reported", "T_base_flange_true"))
            assert m is not None and r is not None
            true = [None] * 3 if t is None else t[:3, 3].tolist()
            sigma = float(np.linalg.norm(s["sigma_position_mm"]))
            rows.append([s["t_s"], s["label"], *_xyzabc(m), *r[:3, 3].tolist(), *true, s["visit"], sigma])
            rows[-1].append(s["t_exposure_unix_ns"])
        return columns, rows
    first = ["pose", "cycle"] if kind == "iso9283" else ["position", "visit"]
    cmd = list(ISO9283_CSV[2:])
    columns = [*first, *cmd, *POSE_CSV, *SIGMA_CSV, *TRUE_CSV, "n_frames", "stop", "t_s"]
    items: list[dict[str, Any]]
    stops = stops_of(samples)
    commanded = commanded_poses(stops)[0] if stops else {}
    if per == "stop":
        items = stops
    else:
        items = []
        for s in samples:
            if s.get("stop") is None:
                continue
            item: dict[str, Any] = {
                k: _T(s, k) for k in ("T_base_flange_measured", "T_base_flange_cmd", "T_base_flange_true")
            }
            item.update({k: s[k] for k in ("label", "visit", "stop", "t_s", "sigma_position_mm", "sigma_rotation_deg")})
            item["n_frames"] = 1
            items.append(item)
    rows = []
    for it in items:
        c, t = it.get("T_base_flange_cmd"), it.get("T_base_flange_true")
        c = commanded.get(it["label"]) if c is None and kind == "iso9283" else c
        rows.append(
            [
                it["label"],
                it["visit"],
                *([None] * 6 if c is None else _xyzabc(c)),
                *_xyzabc(it["T_base_flange_measured"]),
                *np.asarray(it["sigma_position_mm"], dtype=np.float64).tolist(),
                *np.asarray(it["sigma_rotation_deg"], dtype=np.float64).tolist(),
                *([None] * 6 if t is None else _xyzabc(t)),
                it["n_frames"],
                it["stop"],
                it["t_s"],
            ]
        )
    return columns, rows
