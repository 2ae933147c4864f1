"""Compensated commands: the joints that bring the *corrected* model to a target, and what to program.

A controller runs its nominal model: told to go to a Cartesian pose, it solves
its own inverse kinematics and drives those joints, and the real arm (which the
corrected model describes) ends up a few tenths of a millimetre to millimetres
away. So, per target ``T_base_flange_target``:

1. ``q = corrected.ik(target)`` from a seed (the row's seed joints, else the
   previous row's solution, else a neutral configuration): the joints at which
   the real arm's flange is on the target;
2. ``T_base_flange_command = nominal.fk(q)``: the pose to program in the
   controller, whose nominal IK (from a nearby seed) gives back exactly ``q``.

``correction_mm`` / ``correction_deg`` say how far command and target differ.
A target is refused, never silently approximated: out of reach (the IK does not
converge to 1e-6 mm, lands on another arm configuration than the seed's, or
needs a joint beyond its limits) or, with a given seed, a solution more than
``max_seed_distance_rad`` from it. Every refused row is named; nothing is
returned unless every row succeeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.geometry.so3 import R_from_rotvec, rotvec_between
from service.core.results import Reason, SolveError
from service.core.robot.kinematics import KinematicModel

Array = NDArray[np.float64]

MAX_SEED_DISTANCE_RAD = float(np.radians(30.0))
CONTINUATION_STEPS = 20  # a far seed: walk the pose from the seed's to the target in this many IK solves


@dataclass(frozen=True)
class CompensatedTargets:
    """Per target (N rows): joints for the real arm, the command for the nominal controller, the correction.

    Attributes
    ----------
    q_rad : (N, 6) float, rad
        Joints at which the corrected model's flange is on the target.
    T_base_flange_command : (N, 4, 4) float, mm
        The nominal model's flange pose at ``q_rad``: what to program.
    correction_mm : (N,) float, mm
        Distance between command and target flange origins.
    correction_deg : (N,) float, deg
        Angle between command and target flange orientations.
    residual_mm : (N,) float, mm
        Corrected-model fk of ``q_rad`` against the target (the IK's own error).
    seed_distance_rad : (N,) float, rad
        Largest joint difference to the row's given seed (NaN without one).
    """

    q_rad: Array
    T_base_flange_command: Array
    correction_mm: Array
    correction_deg: Array
    residual_mm: Array
    seed_distance_rad: Array


def _short(x: float) -> str:
    """A distance for a sentence: 1764.2, 12.3, 0.0421."""
    return f"{x:.1f}" if x >= 10.0 else f"{x:.3g}"


def _pose_error(model: KinematicModel, q: Array, T_target: Array) -> tuple[float, float]:
    """(mm, rad) between ``model``'s flange at ``q`` and ``T_target``."""
    T = model.fk(q)
    return (
        float(np.linalg.norm(T[:3, 3] - T_target[:3, 3])),
        float(np.linalg.norm(rotvec_between(T_target[:3, :3], T[:3, :3]))),
    )


def _nearest_pose(model: KinematicModel, T_target: Array, q_seed: Array) -> tuple[float, float]:
    """How far the model's best try from the seed stays from the target (mm, rad), for the refusal's sentence.

    "Best" in the IK's own metric: millimetres plus 1000 mm per radian of orientation error.
    """
    try:
        q = model.ik(T_target, q_seed, check_limits=False)
    except SolveError as e:
        if "error_mm" in e.details:
            return float(e.details["error_mm"]), float(e.details["error_rad"])
        q = np.asarray(e.details.get("q_rad", q_seed), dtype=np.float64)
    return _pose_error(model, q, T_target)


def _solve_from(model: KinematicModel, T_target: Array, q_seed: Array) -> Array:
    """``model.ik`` from the seed; if that fails, walk the pose from the seed's to the target (continuation)."""
    try:
        return model.ik(T_target, q_seed)
    except SolveError as first:
        if first.reason != Reason.no_convergence:
            raise
        T0 = model.fk(q_seed)
        dr = rotvec_between(T0[:3, :3], T_target[:3, :3])  # the rotation from the seed's pose to the target's
        q = q_seed
        try:
            for s in np.linspace(0.0, 1.0, CONTINUATION_STEPS + 1)[1:]:
                T = np.eye(4)
                T[:3, :3] = T0[:3, :3] @ R_from_rotvec(s * dr)
                T[:3, 3] = (1.0 - s) * T0[:3, 3] + s * T_target[:3, 3]
                q = model.ik(T, q, check_limits=s == 1.0)
        except SolveError:
            raise first from None
        return q


def compensate_targets(
    corrected: KinematicModel,
    nominal: KinematicModel,
    T_base_flange_target: ArrayLike,
    q_seed_rad: ArrayLike | None = None,
    *,
    q_neutral_rad: ArrayLike,
    max_seed_distance_rad: float = MAX_SEED_DISTANCE_RAD,
) -> CompensatedTargets:
    """Compensated commands for the targets (see the module docstring).

    Parameters
    ----------
    corrected, nominal : KinematicModel
        The identified model of the real arm and the controller's model.
    T_base_flange_target : (N, 4, 4) float, mm
        Flange poses the real arm shall reach, in the base frame.
    q_seed_rad : (N, 6) float, rad, optional
        Seed joints per row choosing the configuration; a row of NaN has none
        and is seeded from the previous row's solution, the first from
        ``q_neutral_rad``.
    q_neutral_rad : (6,) float, rad
        The seed of a first row without one.
    max_seed_distance_rad : float, rad
        Largest allowed joint difference between a row's solution and its given seed.

    Raises
    ------
    SolveError
        ``bad_input`` naming every refused row (1-based, "target 7 is out of
        reach of the corrected model: the nearest pose is 12.3 mm and 1.2 deg
        away"); ``details["rows"]`` lists them.
    """
    T_t = np.asarray(T_base_flange_target, dtype=np.float64)
    if T_t.ndim != 3 or T_t.shape[1:] != (4, 4) or T_t.shape[0] == 0:
        raise ValueError(f"T_base_flange_target must have shape (N, 4, 4) with N >= 1, got {T_t.shape}")
    N = T_t.shape[0]
    seeds = np.full((N, 6), np.nan) if q_seed_rad is None else np.asarray(q_seed_rad, dtype=np.float64)
    if seeds.shape != (N, 6):
        raise ValueError(f"q_seed_rad must have shape ({N}, 6), got {seeds.shape}")
    neutral = np.asarray(q_neutral_rad, dtype=np.float64).reshape(6)
    if not max_seed_distance_rad > 0:
        raise ValueError(f"max_seed_distance_rad must be positive, got {max_seed_distance_rad}")

    q_out = np.full((N, 6), np.nan)
    seed_dist = np.full(N, np.nan)
    problems: list[str] = []
    rows: list[int] = []
    previous: Array | None = None
    for k in range(N):
        given = bool(np.all(np.isfinite(seeds[k])))
        seed = seeds[k] if given else (previous if previous is not None else neutral)
        try:
            q = _solve_from(corrected, T_t[k], seed)
        except SolveError as e:
            rows.append(k + 1)
            if e.reason == Reason.bad_input:  # converged, but a joint is beyond its limits
                problems.append(f"target {k + 1} is out of reach of the corrected model: {e.message}")
            else:
                mm, rad = _nearest_pose(corrected, T_t[k], seed)
                if mm < 1e-3 and rad < 1e-6:
                    why = "it reaches it only in another arm configuration than the seed's"
                else:
                    why = f"the nearest pose is {_short(mm)} mm and {_short(float(np.degrees(rad)))} deg away"
                problems.append(f"target {k + 1} is out of reach of the corrected model: {why}")
            continue
        if given:
            dist = np.abs(q - seed)
            seed_dist[k] = float(dist.max())
            if seed_dist[k] > max_seed_distance_rad:
                j = int(np.argmax(dist))
                rows.append(k + 1)
                problems.append(
                    f"target {k + 1} needs joint {j + 1} {np.degrees(dist[j]):.1f} deg from its seed "
                    f"(at most {np.degrees(max_seed_distance_rad):.1f} deg allowed): check the seed or the target"
                )
                continue
        q_out[k] = q
        previous = q
    if problems:
        raise SolveError(Reason.bad_input, "; ".join(problems), {"rows": rows})

    T_cmd = nominal.fk(q_out).reshape(N, 4, 4)
    T_fit = corrected.fk(q_out).reshape(N, 4, 4)
    corr_deg = np.degrees(np.linalg.norm(rotvec_between(T_t[:, :3, :3], T_cmd[:, :3, :3]), axis=-1))
    return CompensatedTargets(
        q_rad=q_out,
        T_base_flange_command=T_cmd,
        correction_mm=np.linalg.norm(T_cmd[:, :3, 3] - T_t[:, :3, 3], axis=1),
        correction_deg=corr_deg,
        residual_mm=np.linalg.norm(T_fit[:, :3, 3] - T_t[:, :3, 3], axis=1),
        seed_distance_rad=seed_dist,
    )
