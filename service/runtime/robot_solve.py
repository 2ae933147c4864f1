"""The robot calibration session's long steps, run in the solver process: planning, identification, report.

Each is a top-level function of picklable arguments (models, arrays) returning plain values, so
that :class:`~service.runtime.solver_process.SolverProcess` can run it in its child: the
planner's IK over hundreds of candidate views and the identification's least squares are
seconds of NumPy under the interpreter lock, which in the service's own process would take
them from the measurement.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.so3 import rotvec_between
from service.core.results import Reason, SolveError
from service.core.robot.calibration_plan import plan_calibration
from service.core.robot.identification import ANGLE_SCALE_MM, identify_kinematics, observability
from service.core.robot.kinematics import KinematicModel
from service.core.targets.field import Field
from service.runtime.handeye_session import SessionError
from service.store.robot_model import robot_model_to_json

Array = NDArray[np.float64]

PARAMETERISATION = "hayati"


def _observability_dict(nominal: KinematicModel, q_rad: Array) -> dict[str, Any]:
    ob = observability(nominal, q_rad, with_orientation=True, parameterisation=PARAMETERISATION)
    return {
        "condition": round(ob.condition, 2),
        "n_identifiable": len(ob.names),
        "identifiable": list(ob.names),
        "frozen_structural": list(ob.structural),
        "frozen_inseparable": list(ob.blind),
    }


def plan_poses(
    nominal: KinematicModel,
    camera: BrownFraser,
    field: Field,
    T_base_field: Array,
    T_flange_camera: Array,
    q_seed_rad: Array,
    n_poses: int,
    n_holdout: int,
    seed: int,
) -> dict[str, Any]:
    """The session's plan (poses, joints, the hold-out split) and its observability before anything moves."""
    try:
        plan = plan_calibration(
            nominal,
            camera,
            field,
            T_base_field,
            T_flange_camera,
            q_seed_rad,
            n_poses,
            n_holdout,
            np.random.default_rng([seed, 15]),
            parameterisation=PARAMETERISATION,
        )
    except SolveError as e:
        raise SessionError(e.reason, e.message) from None
    return {
        "T_base_flange": plan.T_base_flange,
        "q_rad": plan.q_rad,
        "n_candidates": plan.n_candidates,
        "observability": _observability_dict(nominal, plan.q_rad[:n_poses]),
        "solver_pid": os.getpid(),
    }


def pose_errors(T_model: Array, T_measured: Array) -> dict[str, Any]:
    """Position (mm) and orientation (deg) error of model poses against measured ones, (M, 4, 4) each."""
    d_mm = np.linalg.norm(T_model[:, :3, 3] - T_measured[:, :3, 3], axis=1)
    d_deg = np.degrees(np.linalg.norm(rotvec_between(T_measured[:, :3, :3], T_model[:, :3, :3]), axis=1))
    return {
        "position_mean_mm": round(float(d_mm.mean()), 4),
        "position_max_mm": round(float(d_mm.max()), 4),
        "orientation_mean_deg": round(float(d_deg.mean()), 5),
        "orientation_max_deg": round(float(d_deg.max()), 5),
        "per_pose_mm": [round(float(v), 4) for v in d_mm],
        "per_pose_deg": [round(float(v), 5) for v in d_deg],
        "n": len(d_mm),
    }


def _unit(name: str) -> tuple[str, float]:
    angle = name.startswith(("alpha", "theta", "beta")) or name[-2:] in ("rx", "ry", "rz")
    return ("deg", float(np.degrees(1.0))) if angle else ("mm", 1.0)


def solve_robot(
    robot: str,
    nominal: KinematicModel,
    q_rad: Array,
    T_measured: Array,
    holdout: NDArray[np.bool_],
    sigma_position_mm: float,
    sigma_rotation_deg: float,
) -> dict[str, Any]:
    """Identify the kinematic errors from the calibration samples (``~holdout``) and report on the others.

    ``q_rad`` (M, 6) are the joints at the exposures, ``T_measured`` (M, 4, 4) mm the measured flange
    poses (positions *and* orientations: the camera gives both). Orientation residuals are weighted
    by the ratio of the measurement's σ, so each counts as much as the camera resolves it. Parameters
    these poses cannot separate are frozen at their nominal values and named.
    """
    cal = ~holdout
    n_cal = int(cal.sum())
    if n_cal == 0:
        raise SessionError(Reason.poor_motion, "no calibration samples are recorded; record samples before solving")
    ob = observability(nominal, q_rad[cal], with_orientation=True, parameterisation=PARAMETERISATION)
    # counted over every structurally identifiable parameter: a few samples make many "inseparable"
    n_par = len(ob.names) + len(ob.blind)
    need = int(np.ceil(2 * n_par / 6))
    if n_cal < need:
        raise SessionError(
            Reason.poor_motion,
            f"{n_cal} calibration samples give {6 * n_cal} equations for {n_par} parameters; "
            f"record at least {need} (a plan of 24 or more is advised)",
        )
    # mm of position worth one rad of orientation: the measurement's own ratio
    weight_mm = float(
        np.clip(sigma_position_mm / max(np.radians(sigma_rotation_deg), 1e-9), 10.0, 10.0 * ANGLE_SCALE_MM)
    )
    try:
        res = identify_kinematics(
            nominal,
            q_rad[cal],
            T_measured[cal],
            fixed=ob.blind,
            rotation_weight_mm=weight_mm,
            parameterisation=PARAMETERISATION,
        )
    except SolveError as e:
        raise SessionError(e.reason, e.message) from None
    parameters = {}
    for name, (delta, sigma) in res.as_dict().items():
        unit, k = _unit(name)
        parameters[name] = {"delta": round(delta * k, 6), "sigma": round(sigma * k, 6), "unit": unit}
    out: dict[str, Any] = {
        "ok": True,
        "parameterisation": PARAMETERISATION,
        "n_calibration": n_cal,
        "n_holdout": int(holdout.sum()),
        "parameters": parameters,
        "frozen_structural": list(ob.structural),
        "frozen_inseparable": list(ob.blind),
        "condition": round(res.condition, 2),
        "rotation_weight_mm": round(weight_mm, 1),
        "calibration": {
            "before": pose_errors(nominal.fk(q_rad[cal]), T_measured[cal]),
            "after": pose_errors(res.model.fk(q_rad[cal]), T_measured[cal]),
        },
        "holdout": None,
        "warnings": [] if holdout.any() else ["no hold-out samples: the model is not validated on unseen poses"],
        "solver_pid": os.getpid(),
    }
    if holdout.any():
        out["holdout"] = {
            "before": pose_errors(nominal.fk(q_rad[holdout]), T_measured[holdout]),
            "after": pose_errors(res.model.fk(q_rad[holdout]), T_measured[holdout]),
        }
    poses = [
        {"q_rad": q.tolist(), "T_base_flange_measured": T.tolist()} for q, T in zip(q_rad, T_measured, strict=True)
    ]
    out["model_file"] = {
        "ok": True,
        **robot_model_to_json(robot, res.model, PARAMETERISATION),
        "measured_point_on_flange_mm": [0.0, 0.0, 0.0],
        "corrections": {n: {"delta": d, "sigma": s} for n, (d, s) in res.as_dict().items()},
        "unidentifiable": [*ob.structural, *ob.blind],
        "condition": out["condition"],
        "holdout": out["holdout"],
        # the poses it was made from, with the joints: what POST /calibration/robot/verify re-visits
        "poses": [{**p, "holdout": bool(h)} for p, h in zip(poses, holdout, strict=True)],
    }
    return out
