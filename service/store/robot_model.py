"""The corrected robot model file (``m.json`` of ``posecell calibrate robot``): its schema, reader and writer.

Schema version 2 (written today)::

    {"schema": "posecell.robot-model", "schema_version": 2,
     "robot": "ur5",                       # the nominal model it corrects (kinematics.nominal_model)
     "parameterisation": "hayati",         # "dh" (classic) or "hayati" (beta on near-parallel links)
     "model": {"a_mm": [6], "alpha_rad": [6], "d_mm": [6], "theta_offset_rad": [6],
               "beta_rad": [6], "T_base_j0": 4x4, "T_j6_flange": 4x4},
     "measured_point_on_flange_mm": [3], ...}   # plus corrections, sigma, errors: readers ignore them

Version 1 (before the schema keys existed) is the same without ``schema``,
``schema_version``, ``parameterisation`` and ``beta_rad``: a classic-DH model,
read as a Hayati model with every beta 0. A file of a newer version is refused
rather than half-read.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.core.geometry.frames import check_T
from service.core.robot.identification import PARAMETERISATIONS
from service.core.robot.kinematics import KinematicModel, nominal_model
from service.store.formats import FormatError, _is_finite_number, matrix4_from_json, read_json, reject_non_finite

SCHEMA = "posecell.robot-model"
SCHEMA_VERSION = 2
MAX_LENGTH_MM = 1e5  # a DH length beyond 100 m is a unit mistake, not an arm
_ROWS = {"a_mm": True, "alpha_rad": False, "d_mm": True, "theta_offset_rad": False, "beta_rad": False}


@dataclass(frozen=True)
class RobotModelFile:
    """A read model file: the nominal arm, the corrected one, and where they came from."""

    robot: str
    nominal: KinematicModel
    corrected: KinematicModel
    parameterisation: str
    schema_version: int
    p_flange_point_mm: np.ndarray


def robot_model_to_json(robot: str, model: KinematicModel, parameterisation: str) -> dict[str, Any]:
    """The schema keys and the ``model`` object of a version-2 file (the caller adds its own keys)."""
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "robot": robot,
        "parameterisation": parameterisation,
        "model": {
            "a_mm": model.a_mm.tolist(),
            "alpha_rad": model.alpha_rad.tolist(),
            "d_mm": model.d_mm.tolist(),
            "theta_offset_rad": model.theta_offset_rad.tolist(),
            "beta_rad": model.beta_rad.tolist(),
            "T_base_j0": model.T_base_j0.tolist(),
            "T_j6_flange": model.T_j6_flange.tolist(),
        },
    }


def _row(source: str, name: str, v: Any, length: bool) -> np.ndarray:
    if not (isinstance(v, list) and len(v) == 6 and all(_is_finite_number(x) for x in v)):
        raise FormatError(f"{source}: model.{name} must be a list of 6 numbers, not {v!r}")
    a = np.array(v, dtype=np.float64)
    limit = MAX_LENGTH_MM if length else 2 * np.pi
    if np.max(np.abs(a)) > limit:
        raise FormatError(f"{source}: model.{name} has a value beyond ±{limit:g} {'mm' if length else 'rad'}")
    return a


def _rigid(source: str, name: str, v: Any) -> np.ndarray:
    T = matrix4_from_json(v, f"{source}: model.{name}")
    try:
        return check_T(T, name, atol=1e-6)
    except ValueError as e:
        raise FormatError(f"{source}: model.{name} is not a rigid transform ({e})") from None


def robot_model_from_json(data: Any, source: str = "robot model") -> RobotModelFile:
    """A model file's content (version 1 or 2, see the module docstring), checked; ``FormatError`` if not."""
    if not isinstance(data, dict):
        raise FormatError(f"{source}: a robot model file is a JSON object")
    reject_non_finite(data, source)
    version = data.get("schema_version", 1)
    if "schema" in data and data["schema"] != SCHEMA:
        raise FormatError(f"{source}: schema is {data['schema']!r}, not a robot model ({SCHEMA!r})")
    if version not in (1, 2) or isinstance(version, bool):
        raise FormatError(
            f"{source}: schema_version {version!r} is not one this posecell reads (1 or {SCHEMA_VERSION})"
        )
    robot = data.get("robot")
    try:
        nominal = nominal_model(robot) if isinstance(robot, str) else None
    except ValueError:
        nominal = None
    if nominal is None:
        raise FormatError(f"{source}: robot must name a known nominal model (kr15, ur10e, ur5), not {robot!r}")
    par = data.get("parameterisation", "dh")
    if par not in PARAMETERISATIONS:
        raise FormatError(f"{source}: parameterisation must be one of {', '.join(PARAMETERISATIONS)}, not {par!r}")
    m = data.get("model")
    if not isinstance(m, dict):
        raise FormatError(f"{source}: needs a model object with the DH rows, T_base_j0 and T_j6_flange")
    if version == 1 and "beta_rad" in m:
        raise FormatError(f"{source}: model.beta_rad needs schema_version {SCHEMA_VERSION}")
    rows = {}
    for name, length in _ROWS.items():
        if name == "beta_rad" and name not in m:
            if version >= 2:
                raise FormatError(f"{source}: model.beta_rad is missing (schema_version {version})")
            rows[name] = np.zeros(6)
            continue
        if name not in m:
            raise FormatError(f"{source}: model.{name} is missing")
        rows[name] = _row(source, name, m[name], length)
    if par == "dh" and np.any(rows["beta_rad"]):
        raise FormatError(f"{source}: a classic-DH model (parameterisation dh) has every beta 0")
    corrected = KinematicModel(
        name=f"{nominal.name} (corrected)",
        q_limits_rad=nominal.q_limits_rad,
        T_base_j0=_rigid(source, "T_base_j0", m.get("T_base_j0")),
        T_j6_flange=_rigid(source, "T_j6_flange", m.get("T_j6_flange")),
        wrist_frame=nominal.wrist_frame,
        **rows,
    )
    point = data.get("measured_point_on_flange_mm", [0.0, 0.0, 0.0])
    if not (isinstance(point, list) and len(point) == 3 and all(_is_finite_number(x) for x in point)):
        raise FormatError(f"{source}: measured_point_on_flange_mm must be 3 numbers, not {point!r}")
    return RobotModelFile(robot, nominal, corrected, par, int(version), np.array(point, dtype=np.float64))


def read_robot_model(path: str | os.PathLike[str]) -> RobotModelFile:
    """Read and check a model file written by ``posecell calibrate robot`` (any version it ever wrote)."""
    return robot_model_from_json(read_json(path), str(path))
