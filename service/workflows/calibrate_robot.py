"""``posecell calibrate robot``: identify the arm's kinematic errors from measured flange positions.

Input: a CSV with the joint angles ``joint_1 … joint_6`` (deg) of every pose and
where the measured point really was, either as ``x_mm, y_mm, z_mm`` in the
robot's base frame or in the laser-tracker form ``x_t, y_t, z_t`` (commanded)
plus ``x_dif, y_dif, z_dif`` (measured − commanded). With commanded positions
the measured point's offset on the flange is found first (the controller's own
FK with every DH parameter fixed); otherwise ``--tool-mm`` gives it.
Output (``m.json``, schema version 2 of :mod:`service.store.robot_model`): the
corrected model (DH rows, Hayati's beta on near-parallel links unless
``parameterisation="dh"``, base, flange) with σ of every
identified correction, the combinations frozen as unidentifiable, and the
errors before/after on the calibration poses and, with ``--test``, on poses
that took no part in it.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from service.core.robot.identification import dh_parameter_names, identify_kinematics
from service.core.robot.kinematics import nominal_model
from service.store import formats
from service.store.robot_model import robot_model_to_json


def read_robot_samples(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(q_rad (M, 6), p_commanded_mm (M, 3) or None, p_measured_mm (M, 3)) from a CSV (module docstring)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise formats.FormatError(f"{path}: {e.strerror}") from None
    if not rows:
        raise formats.FormatError(f"{path}: no rows")
    cols = set(rows[0])
    joints = [f"joint_{i}" for i in range(1, 7)]
    if not set(joints) <= cols:
        raise formats.FormatError(f"{path}: needs the columns {', '.join(joints)} (deg)")
    try:
        q = np.radians([[float(r[j]) for j in joints] for r in rows])
        if {"x_t", "y_t", "z_t", "x_dif", "y_dif", "z_dif"} <= cols:
            cmd = np.array([[float(r[c]) for c in ("x_t", "y_t", "z_t")] for r in rows])
            meas = cmd + np.array([[float(r[c]) for c in ("x_dif", "y_dif", "z_dif")] for r in rows])
        elif {"x_mm", "y_mm", "z_mm"} <= cols:
            cmd = None
            meas = np.array([[float(r[c]) for c in ("x_mm", "y_mm", "z_mm")] for r in rows])
        else:
            raise formats.FormatError(f"{path}: needs x_mm, y_mm, z_mm or x_t … z_dif columns (mm)")
    except ValueError as e:
        raise formats.FormatError(f"{path}: a value is not a number ({e})") from None
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(meas))):
        raise formats.FormatError(f"{path}: non-finite values")
    return q, cmd, meas


def _errors(p_true: np.ndarray, p_model: np.ndarray) -> dict[str, float]:
    e = np.linalg.norm(p_true - p_model, axis=1)
    return {
        "mean_mm": round(float(e.mean()), 4),
        "max_mm": round(float(e.max()), 4),
        "rms_mm": round(float(np.sqrt(np.mean(e**2))), 4),
        "n": len(e),
    }


def run_robot_calibration(
    robot: str, samples: Path, test: Path | None, tool_mm: list[float] | None, parameterisation: str = "hayati"
) -> dict[str, Any]:
    nominal = nominal_model(robot)
    q, cmd, meas = read_robot_samples(samples)
    if cmd is not None:
        tool_fit = identify_kinematics(nominal, q, cmd, estimate_base=False, fixed=dh_parameter_names())
        tool = np.array([tool_fit.parameter(n)[0] for n in ("tool_x", "tool_y", "tool_z")])
    else:
        tool = np.zeros(3) if tool_mm is None else np.asarray(tool_mm, dtype=np.float64)
    res = identify_kinematics(nominal, q, meas, p_flange_point_mm=tool, parameterisation=parameterisation)
    # the fair "before": the nominal arm, placed in the measuring frame (base fitted, DH untouched)
    base_only = identify_kinematics(nominal, q, meas, fixed=dh_parameter_names(), p_flange_point_mm=tool)
    m = res.model
    out: dict[str, Any] = {
        "ok": True,
        **robot_model_to_json(robot, m, parameterisation),
        "measured_point_on_flange_mm": res.p_flange_point_mm.tolist(),
        "corrections": {n: {"delta": d, "sigma": s} for n, (d, s) in res.as_dict().items()},
        "unidentifiable": list(res.unidentifiable),
        "condition": round(res.condition, 1),
        "calibration": {
            "nominal_mm": _errors(meas, base_only.predict(q)),
            "corrected_mm": _errors(meas, res.predict(q)),
        },
    }
    if cmd is not None:
        out["calibration"]["commanded_mm"] = _errors(meas, cmd)
    if test is not None:
        qt, cmdt, meast = read_robot_samples(test)
        out["test"] = {
            "nominal_mm": _errors(meast, base_only.predict(qt)),
            "corrected_mm": _errors(meast, res.predict(qt)),
        }
        if cmdt is not None:
            out["test"]["commanded_mm"] = _errors(meast, cmdt)
    return out
