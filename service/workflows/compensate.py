"""``posecell compensate``: joint and Cartesian commands that bring the *real* arm to the user's targets.

Input: a corrected model (``m.json`` of ``posecell calibrate robot``, any schema
version, :mod:`service.store.robot_model`) and targets: per row the flange pose
the real arm shall reach, ``x_mm, y_mm, z_mm, rx, ry, rz`` (a UR rotation
vector, rad, in the base frame), optionally ``seed_joint_1 … seed_joint_6``
(deg) choosing the arm's configuration (all six or none in a row).

Output per target (:data:`COMMAND_COLUMNS`): the joints ``joint_1 … joint_6``
(deg) at which the corrected model's flange is on the target, the Cartesian
pose ``x_cmd_mm … rz_cmd`` to program in the nominal controller (its IK gives
those joints back) and the predicted correction (command − target, mm and deg).
Or, for a UR, a URScript program of ``movej`` lines in those joints. The
maths is :mod:`service.core.robot.compensation`; a refused target fails the
whole file with the row named, so nothing half-compensated is ever written.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from service.core.geometry.so3 import R_from_rotvec, rotvec_from_R
from service.core.robot.compensation import MAX_SEED_DISTANCE_RAD, compensate_targets
from service.store.formats import FormatError
from service.store.robot_model import RobotModelFile

TARGET_COLUMNS = ("x_mm", "y_mm", "z_mm", "rx", "ry", "rz")
SEED_COLUMNS = tuple(f"seed_joint_{i}" for i in range(1, 7))
JOINT_COLUMNS = tuple(f"joint_{i}" for i in range(1, 7))
COMMAND_COLUMNS = (
    "target",
    *JOINT_COLUMNS,
    "x_cmd_mm",
    "y_cmd_mm",
    "z_cmd_mm",
    "rx_cmd",
    "ry_cmd",
    "rz_cmd",
    "correction_mm",
    "correction_deg",
)
# the seed of a first row without one: away from the singularities (stretched elbow, wrist axes aligned)
NEUTRAL_SEED_DEG = {
    "ur5": (0.0, -90.0, 90.0, -90.0, -90.0, 0.0),
    "ur10e": (0.0, -90.0, 90.0, -90.0, -90.0, 0.0),
    "kr15": (0.0, -90.0, 90.0, 0.0, 45.0, 0.0),
}
UR_ROBOTS = ("ur5", "ur10e")
MAX_COORDINATE_MM = 1e5


def _number(v: Any, source: str, k: int, name: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise FormatError(f"{source}: target {k} has {name} = {v!r}, which is not a number") from None
    if isinstance(v, bool) or not math.isfinite(x):
        raise FormatError(f"{source}: target {k} has {name} = {v!r}, which is not a finite number")
    return x


def targets_from_rows(rows: Sequence[Mapping[str, Any]], source: str) -> tuple[np.ndarray, np.ndarray]:
    """``(T_base_flange_target (N, 4, 4) mm, q_seed_rad (N, 6), NaN where a row has no seed)`` from rows
    of the target fields (CSV rows or JSON objects); ``FormatError`` naming the row and the column."""
    if not rows:
        raise FormatError(f"{source}: no targets")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    seeds = np.full((len(rows), 6), np.nan)
    for k, row in enumerate(rows, start=1):
        missing = [c for c in TARGET_COLUMNS if row.get(c) in (None, "")]
        if missing:
            raise FormatError(
                f"{source}: target {k} lacks {', '.join(missing)}; every target needs "
                f"{', '.join(TARGET_COLUMNS)} (mm, UR rotation vector in rad)"
            )
        v = [_number(row[c], source, k, c) for c in TARGET_COLUMNS]
        if max(abs(x) for x in v[:3]) > MAX_COORDINATE_MM:
            raise FormatError(f"{source}: target {k} lies beyond ±{MAX_COORDINATE_MM:g} mm")
        T[k - 1, :3, :3] = R_from_rotvec(v[3:])
        T[k - 1, :3, 3] = v[:3]
        given = [c for c in SEED_COLUMNS if row.get(c) not in (None, "")]
        if given and len(given) < 6:
            absent = [c for c in SEED_COLUMNS if c not in given]
            raise FormatError(f"{source}: target {k} gives {', '.join(given)} but not {', '.join(absent)}")
        if given:
            seeds[k - 1] = np.radians([_number(row[c], source, k, c) for c in SEED_COLUMNS])
    return T, seeds


def targets_from_csv(text: str, source: str = "targets.csv") -> tuple[np.ndarray, np.ndarray]:
    """Targets and seeds from a TARGETS.csv's text (see the module docstring)."""
    reader = csv.DictReader(io.StringIO(text))
    cols = set(reader.fieldnames or ())
    missing = [c for c in TARGET_COLUMNS if c not in cols]
    if missing:
        raise FormatError(
            f"{source}: needs the columns {', '.join(TARGET_COLUMNS)} (mm, UR rotation vector in rad), "
            f"optionally {', '.join(SEED_COLUMNS)} (deg); missing: {', '.join(missing)}"
        )
    partial = [c for c in SEED_COLUMNS if c not in cols]
    if len(partial) < 6 and partial:
        raise FormatError(f"{source}: has some seed columns but not {', '.join(partial)}: give all six or none")
    return targets_from_rows(list(reader), source)


def compensate(
    model: RobotModelFile,
    T_base_flange_target: np.ndarray,
    q_seed_rad: np.ndarray,
    max_seed_distance_deg: float = float(np.degrees(MAX_SEED_DISTANCE_RAD)),
) -> list[dict[str, Any]]:
    """The command rows (:data:`COMMAND_COLUMNS`) for the targets; ``SolveError`` (bad_input) naming every
    refused target."""
    res = compensate_targets(
        model.corrected,
        model.nominal,
        T_base_flange_target,
        q_seed_rad,
        q_neutral_rad=np.radians(NEUTRAL_SEED_DEG[model.robot]),
        max_seed_distance_rad=float(np.radians(max_seed_distance_deg)),
    )
    rv = rotvec_from_R(res.T_base_flange_command[:, :3, :3])
    out = []
    for k in range(res.q_rad.shape[0]):
        row: dict[str, Any] = {"target": k + 1}
        row |= dict(zip(JOINT_COLUMNS, np.degrees(res.q_rad[k]).tolist(), strict=True))
        p = res.T_base_flange_command[k, :3, 3]
        row |= {"x_cmd_mm": p[0], "y_cmd_mm": p[1], "z_cmd_mm": p[2]}
        row |= {"rx_cmd": rv[k, 0], "ry_cmd": rv[k, 1], "rz_cmd": rv[k, 2]}
        row |= {"correction_mm": res.correction_mm[k], "correction_deg": res.correction_deg[k]}
        out.append({c: float(v) if c != "target" else v for c, v in row.items()})
    return out


def commands_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """COMMANDS.csv's text: joints to 1e-9 deg, the command to 1e-6 mm and 1e-9 rad."""
    f = io.StringIO()
    w = csv.writer(f, lineterminator="\n")
    w.writerow(COMMAND_COLUMNS)
    for r in rows:
        w.writerow([r["target"], *(f"{r[c]:.9f}" if c[0] in "jr" else f"{r[c]:.6f}" for c in COMMAND_COLUMNS[1:])])
    return f.getvalue()


def commands_urscript(
    rows: Sequence[Mapping[str, Any]], model: RobotModelFile, model_source: str, a_rad_s2: float, v_rad_s: float
) -> str:
    """A URScript program: one ``movej`` per target in its compensated joints (rad), with a header
    naming the model that made it. Joint moves, so the controller's own (nominal) IK plays no part."""
    if model.robot not in UR_ROBOTS:
        raise FormatError(f"URScript is for Universal Robots arms; this model corrects a {model.robot}")
    lines = [
        f"# posecell compensate: {len(rows)} targets, corrected {model.robot} model "
        f"({model.parameterisation}, schema {model.schema_version}) from {model_source}",
        "# joint positions in rad; each puts the corrected model's flange on its target",
        "def posecell_compensated():",
    ]
    for r in rows:
        q = ", ".join(f"{np.radians(r[c]):.9f}" for c in JOINT_COLUMNS)
        lines.append(f"  movej([{q}], a={a_rad_s2:g}, v={v_rad_s:g})  # target {r['target']}")
    lines += ["end", "posecell_compensated()"]
    return "\n".join(lines) + "\n"
