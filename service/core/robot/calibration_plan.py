"""Planning the robot poses of a kinematic calibration: spread over the joints, every one a view of the field.

The camera measures the flange only where it sees the field, so the candidates are views of
it: the camera looks at a point near the field's centre from ``distance_mm``, tilted from the
field's normal by up to ``max_tilt_deg`` towards any azimuth and rolled about its axis by up to
``max_roll_deg`` (the roll turns the wrist, the tilt and azimuth the wrist and the arm, the
distance and the aim point the shoulder and the elbow). A candidate is kept when the nominal
model's IK reaches it from the seed's branch, inside the joint limits and away from
singularities, with ``min_targets`` targets in the image.

From those, the plan picks ``n`` greedily by D-optimality: each next pose is the one that most
increases ``log det(JᵀJ)`` of the pose Jacobian of the identifiable errors
(:func:`~service.core.robot.identification.pose_jacobian`), the classic observability index of
robot calibration (Borm and Menq 1991, Sun and Hollerbach 2008). Random poses repeat
directions the Jacobian already has; the greedy choice spends the moves where a parameter is
still poorly seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core.calib.handeye_plan import _look_at
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T, inv_T, make_T
from service.core.geometry.so3 import R_from_rotvec
from service.core.results import Reason, SolveError
from service.core.robot.identification import pose_jacobian
from service.core.robot.kinematics import KinematicModel
from service.core.targets.field import Field
from service.core.targets.identify import project_field

Array = NDArray[np.float64]

MIN_DEXTERITY_MM = 50.0  # smallest singular value of the arm's Jacobian (mm/rad) of a planned pose
LIMIT_MARGIN_RAD = np.radians(5.0)


@dataclass(frozen=True)
class CalibrationPlan:
    """Poses to visit: ``T_base_flange`` (n, 4, 4) mm and the nominal joints there ``q_rad`` (n, 6); the
    last ``n_holdout`` are the validation poses (random views, not chosen for the fit)."""

    T_base_flange: Array
    q_rad: Array
    n_holdout: int
    n_candidates: int


def view_candidates(
    nominal: KinematicModel,
    camera: BrownFraser,
    field: Field,
    T_base_field: Array,
    T_flange_camera: Array,
    q_seed_rad: Array,
    n: int,
    rng: np.random.Generator,
    distance_mm: tuple[float, float] = (850.0, 1250.0),
    max_tilt_deg: float = 40.0,
    max_roll_deg: float = 90.0,
    min_targets: int = 30,
    min_coded: int = 12,
    margin_px: float = 40.0,
    max_tries: int = 4000,
) -> tuple[Array, Array]:
    """Up to ``n`` reachable views of the field: ``(T_base_flange (K, 4, 4) mm, q_rad (K, 6))`` (module docstring).

    A view counts ``min_targets`` targets, ``min_coded`` of them coded, at least ``margin_px`` inside the
    image: the margin keeps a coded target's ring (~3 disk radii) in the image too, without which the
    pipeline cannot identify it. The default distances keep clear of the near views (~730 mm) at which
    the reference scene's coded targets were seen but not identified (accuracy_plans.TABLE1_VIEWS).
    """
    Z, X = check_T(T_base_field, "T_base_field"), check_T(T_flange_camera, "T_flange_camera")
    X_inv = inv_T(X)
    centre = field.xyz.mean(axis=0)
    # the field's normal: its z axis, turned towards where the camera is (targets face the camera)
    normal = np.array([0.0, 0.0, 1.0])
    T_out: list[Array] = []
    q_out: list[Array] = []
    for _ in range(max_tries):
        if len(T_out) == n:
            break
        tilt = np.radians(rng.uniform(0.0, max_tilt_deg))
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        axis = R_from_rotvec(azimuth * normal) @ (R_from_rotvec([tilt, 0.0, 0.0]) @ normal)
        aim = centre + np.array([*rng.uniform(-100.0, 100.0, 2), 0.0])
        eye = aim + rng.uniform(*distance_mm) * axis
        R = _look_at(eye, aim, np.array([0.0, 1.0, 0.0])) @ R_from_rotvec(
            [0.0, 0.0, np.radians(rng.uniform(-1, 1) * max_roll_deg)]
        )
        T_fc = make_T(R, eye)
        rows, _ = project_field(camera, field, T_fc, margin_px=margin_px)
        if len(rows) < min_targets or int(np.sum(field.is_coded[rows])) < min_coded:
            continue
        T = Z @ T_fc @ X_inv
        try:
            q = nominal.ik(T, q_seed_rad)
        except SolveError:
            continue
        if nominal.within_limits(q, LIMIT_MARGIN_RAD) and nominal.dexterity_mm(q) >= MIN_DEXTERITY_MM:
            T_out.append(T)
            q_out.append(q)
    return np.array(T_out).reshape(-1, 4, 4), np.array(q_out).reshape(-1, 6)


def select_d_optimal(nominal: KinematicModel, q_rad: Array, n: int, parameterisation: str = "hayati") -> list[int]:
    """Indices of ``n`` of the configurations ``q_rad`` (K, 6), chosen greedily for ``max log det(JᵀJ)``.

    A small ridge (1e-6 of the mean column energy) keeps the determinant finite while fewer poses
    than parameters are chosen, so the first picks already favour unseen directions.
    """
    J, _ = pose_jacobian(nominal, q_rad, parameterisation)
    K = q_rad.shape[0]
    blocks = J.reshape(K, 6, -1)  # the rows of one configuration
    info_each = np.einsum("kri,krj->kij", blocks, blocks)
    ridge = 1e-6 * float(np.mean(np.einsum("kii->k", info_each))) / J.shape[1]
    info = ridge * np.eye(J.shape[1])
    chosen: list[int] = []
    for _ in range(min(n, K)):
        _, logdet = np.linalg.slogdet(info[None] + info_each)
        logdet[chosen] = -np.inf
        k = int(np.argmax(logdet))
        chosen.append(k)
        info = info + info_each[k]
    return chosen


def plan_calibration(
    nominal: KinematicModel,
    camera: BrownFraser,
    field: Field,
    T_base_field: Array,
    T_flange_camera: Array,
    q_seed_rad: Array,
    n: int,
    n_holdout: int,
    rng: np.random.Generator,
    candidates_per_pose: int = 6,
    parameterisation: str = "hayati",
) -> CalibrationPlan:
    """``n`` poses (D-optimal among ``candidates_per_pose * n`` reachable views) in a short joint-space
    tour, then ``n_holdout`` random others of the candidates for validation.

    Raises ``SolveError(degenerate_geometry)`` when fewer than ``n + n_holdout`` reachable views exist.
    """
    T, q = view_candidates(
        nominal, camera, field, T_base_field, T_flange_camera, q_seed_rad, candidates_per_pose * n + n_holdout, rng
    )
    if len(q) < n + n_holdout:
        raise SolveError(
            Reason.degenerate_geometry,
            f"only {len(q)} reachable views of the field were found for {n + n_holdout} poses: "
            "check the hand-eye calibration and that the arm can see the field",
        )
    pick = select_d_optimal(nominal, q, n, parameterisation)
    rest = np.setdiff1d(np.arange(len(q)), pick)
    holdout = [int(k) for k in rng.choice(rest, size=n_holdout, replace=False)]
    # visit them nearest-first from the seed: shorter moves, same set
    order, here, left = [], np.asarray(q_seed_rad, dtype=np.float64), list(pick)
    while left:
        k = min(left, key=lambda i: float(np.max(np.abs(q[i] - here))))
        order.append(k)
        left.remove(k)
        here = q[k]
    order += holdout
    return CalibrationPlan(T[order], q[order], n_holdout, len(q))
