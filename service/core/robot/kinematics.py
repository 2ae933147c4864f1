"""Kinematic models of 6-axis arms: forward kinematics, Jacobians, inverse kinematics.

Kinematics use the classic (distal, standard) Denavit-Hartenberg convention
with Hayati's extra rotation: link ``i`` is
``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)`` with
``theta_i = q_i + theta_offset_i``; ``beta_i`` is 0 in every nominal model (so
the chain is plain classic DH) and is used by a corrected model only on links
whose two joint axes are (near-)parallel (see :func:`near_parallel_links` and
:mod:`service.core.robot.identification` for why), so that
``T_base_flange = T_base_j0 @ A_1 ... A_6 @ T_j6_flange``. ``j0`` is the DH
frame of joint 1 (its z axis is joint 1's axis) and ``j6`` the DH frame of the
last link; ``T_base_j0`` carries the base placement (a base tilt in the true
model), ``T_j6_flange`` the flange's offset from ``j6``. The nominal models of
the arms the project knows (KUKA KR 15, UR10e, UR5) are here; the simulated
cell (:mod:`service.sim.robot`) perturbs them into its true arm, and the robot
model's identification (:mod:`service.core.robot.identification`) estimates them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from service.core.geometry.frames import check_T
from service.core.geometry.so3 import rotvec_between
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

IK_TOL_MM = 1e-6
IK_TOL_RAD = 1e-9
IK_ROT_SCALE_MM = 1000.0  # weight of a radian of orientation error against a millimetre
SINGULARITY_LENGTH_MM = 1000.0  # scales the angular rows of J for :meth:`KinematicModel.dexterity_mm`
# consecutive joint axes closer to parallel than this carry Hayati's beta instead of d: classic DH's common
# normal (hence d) runs away as the axes become parallel, while a tilt beta about y stays a small number
NEAR_PARALLEL_RAD = float(np.radians(5.0))


def _dh_links(theta: Array, a: Array, alpha: Array, d: Array, beta: Array | None = None) -> Array:
    """Link transforms (N, 6, 4, 4) of ``Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)`` for theta (N, 6)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    A = np.zeros((*theta.shape, 4, 4))
    A[..., 0, 0] = ct
    A[..., 0, 1] = -st * ca
    A[..., 0, 2] = st * sa
    A[..., 0, 3] = a * ct
    A[..., 1, 0] = st
    A[..., 1, 1] = ct * ca
    A[..., 1, 2] = -ct * sa
    A[..., 1, 3] = a * st
    A[..., 2, 1] = sa
    A[..., 2, 2] = ca
    A[..., 2, 3] = d
    A[..., 3, 3] = 1.0
    if beta is None or not np.any(beta):
        return A
    cb, sb = np.cos(beta), np.sin(beta)
    Ry = np.zeros((beta.shape[-1], 4, 4))
    Ry[:, 0, 0] = cb
    Ry[:, 0, 2] = sb
    Ry[:, 1, 1] = 1.0
    Ry[:, 2, 0] = -sb
    Ry[:, 2, 2] = cb
    Ry[:, 3, 3] = 1.0
    return A @ Ry


def _wrap(x: Array) -> Array:
    """Angles wrapped to [-pi, pi)."""
    return (x + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True, eq=False)
class KinematicModel:
    """A serial 6R arm in classic Denavit-Hartenberg parameters (see the module docstring).

    Parameters
    ----------
    name : str
    a_mm, alpha_rad, d_mm, theta_offset_rad : (6,) float
        DH rows of links 1..6 (mm, rad).
    q_limits_rad : (6, 2) float, rad
        Lower and upper limit of each joint, in the joint coordinates ``q``.
    T_base_j0 : (4, 4) float
        The DH frame of joint 1 in the robot base frame (identity nominally).
    T_j6_flange : (4, 4) float
        The flange in the DH frame of link 6.
    wrist_frame : int
        The DH frame whose origin is the arm's wrist point for :meth:`branch`:
        4 (the wrist centre) for a spherical wrist, 3 (on axis 4) for a UR arm,
        whose axes 2, 3 and 4 are parallel.
    beta_rad : (6,) float, rad
        Hayati's rotation about the link's y axis, applied last in each link
        (0 in the nominal models; see the module docstring).
    """

    name: str
    a_mm: Array
    alpha_rad: Array
    d_mm: Array
    theta_offset_rad: Array
    q_limits_rad: Array
    T_base_j0: Array = field(default_factory=lambda: np.eye(4))
    T_j6_flange: Array = field(default_factory=lambda: np.eye(4))
    wrist_frame: int = 4
    beta_rad: Array = field(default_factory=lambda: np.zeros(6))

    def __post_init__(self) -> None:
        for name in ("a_mm", "alpha_rad", "d_mm", "theta_offset_rad", "beta_rad"):
            v = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            if v.shape != (6,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be 6 finite numbers, got {getattr(self, name)!r}")
            v.setflags(write=False)
            object.__setattr__(self, name, v)
        lim = np.array(self.q_limits_rad, dtype=np.float64)
        if lim.shape != (6, 2) or not np.all(lim[:, 0] < lim[:, 1]):
            raise ValueError(f"q_limits_rad must be (6, 2) with lower < upper, got {lim!r}")
        lim.setflags(write=False)
        object.__setattr__(self, "q_limits_rad", lim)
        for name in ("T_base_j0", "T_j6_flange"):
            T = check_T(getattr(self, name), name).copy()
            T.setflags(write=False)
            object.__setattr__(self, name, T)

    # -- kinematics ------------------------------------------------------------

    def _frames(self, q: Array) -> Array:
        """Frames (N, 8, 4, 4) in the base: j0, j1 .. j6, flange, for q (N, 6)."""
        A = _dh_links(q + self.theta_offset_rad, self.a_mm, self.alpha_rad, self.d_mm, self.beta_rad)
        out = np.empty((q.shape[0], 8, 4, 4))
        T = np.broadcast_to(self.T_base_j0, (q.shape[0], 4, 4))
        out[:, 0] = T
        for i in range(6):
            T = T @ A[:, i]
            out[:, i + 1] = T
        out[:, 7] = T @ self.T_j6_flange
        return out

    def fk(self, q_rad: ArrayLike) -> Array:
        """``T_base_flange`` (4, 4), or (N, 4, 4) for ``q_rad`` (N, 6) rad.

        >>> m = kr15()
        >>> (np.round(m.fk(np.radians([0, -90, 90, 0, 0, 0]))[:3, 3], 3) + 0.0).tolist()
        [1040.0, 0.0, 1480.0]
        """
        q = np.asarray(q_rad, dtype=np.float64)
        if q.shape[-1:] != (6,) or q.ndim > 2:
            raise ValueError(f"q_rad must have shape (6,) or (N, 6), got {q.shape}")
        T = self._frames(q.reshape(-1, 6))[:, 7]
        return T[0] if q.ndim == 1 else T

    def jacobian(self, q_rad: ArrayLike) -> Array:
        """Geometric Jacobian (6, 6) of the flange at ``q_rad`` (6,), base frame.

        Rows 0-2: flange origin velocity (mm/rad); rows 3-5: angular velocity (rad/rad).
        """
        q = np.asarray(q_rad, dtype=np.float64).reshape(1, 6)
        F = self._frames(q)[0]
        p = F[7, :3, 3]
        z = F[:6, :3, 2]
        o = F[:6, :3, 3]
        return np.vstack([np.cross(z, p - o).T, z.T])

    def dexterity_mm(self, q_rad: ArrayLike) -> float:
        """Smallest singular value (mm/rad) of the Jacobian with angular rows times 1000 mm.

        It falls to zero at a singularity (stretched elbow, wrist axes 4 and 6
        aligned, wrist centre on the axis of joint 1).
        """
        J = self.jacobian(q_rad)
        J[3:] *= SINGULARITY_LENGTH_MM
        return float(np.linalg.svd(J, compute_uv=False)[-1])

    def within_limits(self, q_rad: ArrayLike, margin_rad: float = 0.0) -> NDArray[np.bool_] | bool:
        """Whether ``q_rad`` (6,) or (N, 6) lies inside the joint limits shrunk by ``margin_rad``."""
        q = np.asarray(q_rad, dtype=np.float64)
        ok = np.all((q >= self.q_limits_rad[:, 0] + margin_rad) & (q <= self.q_limits_rad[:, 1] - margin_rad), axis=-1)
        return bool(ok) if q.ndim == 1 else ok

    def branch(self, q_rad: ArrayLike) -> tuple[int, int, int]:
        """Arm configuration (shoulder, elbow, wrist) as signs +-1; IK never leaves the seed's.

        shoulder: side of joint 1's axis the wrist (origin of frame 5) is on,
        along x1; elbow: side of the line from axis 2 to axis 3 the wrist point
        (origin of frame ``wrist_frame``) is on; wrist: sign of sin theta_5.
        Each changes sign only through its singularity (wrist over axis 1,
        stretched elbow, axes 4 and 6 aligned): these are the 8 solutions of
        the closed-form IK of both arms.
        """
        q = np.asarray(q_rad, dtype=np.float64).reshape(1, 6)
        F = self._frames(q)[0]
        o0, o1, o2, o5 = F[0, :3, 3], F[1, :3, 3], F[2, :3, 3], F[5, :3, 3]
        w = F[self.wrist_frame, :3, 3]
        shoulder = (o5 - o0) @ F[1, :3, 0]
        elbow = F[1, :3, 2] @ np.cross(w - o1, w - o2)
        wrist = np.sin(q[0, 4] + self.theta_offset_rad[4])
        return int(np.sign(shoulder)), int(np.sign(elbow)), int(np.sign(wrist))

    def ik(self, T_base_flange: ArrayLike, q_seed: ArrayLike, check_limits: bool = True) -> Array:
        """Joint positions (6,) rad that put the flange at ``T_base_flange``, found from ``q_seed``.

        A numeric solution (scipy ``least_squares``, Levenberg-Marquardt, on the
        position error in mm and the rotation-vector error times 1000 mm), so it
        works for perturbed models as well as for the nominal ones. The result
        keeps the seed's branch (see :meth:`branch`) and its wrist turns: each
        joint is taken within pi of the seed.

        Raises
        ------
        SolveError
            ``no_convergence`` when the pose error stays above 1e-6 mm or 1e-9
            rad, or the solver ended on another branch than the seed; ``bad_input``
            when ``check_limits`` and the solution is outside the joint limits.
        """
        T_t = check_T(T_base_flange, "T_base_flange")
        seed = np.asarray(q_seed, dtype=np.float64).reshape(6)
        R_t, R_t_T = T_t[:3, :3], T_t[:3, :3].T
        p_t = T_t[:3, 3]

        def residual(q: Array) -> Array:
            F = self._frames(q[None])[0, 7]
            e_rot = rotvec_between(R_t, F[:3, :3])
            return np.concatenate([F[:3, 3] - p_t, IK_ROT_SCALE_MM * e_rot])

        def jac(q: Array) -> Array:
            # d(rotvec(R_t^T R))/dq ~ R_t^T J_w near the solution, which is where accuracy counts
            J = self.jacobian(q)
            return np.vstack([J[:3], IK_ROT_SCALE_MM * (R_t_T @ J[3:])])

        sol = least_squares(residual, seed, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
        q = seed + _wrap(sol.x - seed)
        r = residual(q)
        err_mm = float(np.linalg.norm(r[:3]))
        err_rad = float(np.linalg.norm(r[3:]) / IK_ROT_SCALE_MM)
        if not (err_mm <= IK_TOL_MM and err_rad <= IK_TOL_RAD):
            raise SolveError(
                Reason.no_convergence,
                f"inverse kinematics of {self.name} left {err_mm:.2g} mm and {err_rad:.2g} rad of pose error",
                {"error_mm": err_mm, "error_rad": err_rad},
            )
        # a seed on a singularity (sign 0) does not pin that part of the configuration
        if any(b != s and s != 0 for b, s in zip(self.branch(q), self.branch(seed), strict=True)):
            raise SolveError(
                Reason.no_convergence,
                f"inverse kinematics of {self.name} converged on another arm configuration than the seed's",
                {"q_rad": q.tolist(), "q_seed_rad": seed.tolist()},
            )
        # a joint with more than one turn of travel may reach the same angle a turn away: a controller
        # takes the turn inside the limits, nearest the seed
        lo, hi = self.q_limits_rad[:, 0], self.q_limits_rad[:, 1]
        for j in np.flatnonzero((q < lo) | (q > hi)):
            for turn in sorted((-2 * np.pi, 2 * np.pi), key=lambda d: abs(q[j] + d - seed[j])):
                if lo[j] <= q[j] + turn <= hi[j]:
                    q[j] += turn
                    break
        if check_limits and not self.within_limits(q):
            bad = int(np.flatnonzero(~((q >= self.q_limits_rad[:, 0]) & (q <= self.q_limits_rad[:, 1])))[0])
            raise SolveError(
                Reason.bad_input,
                f"the pose needs joint {bad + 1} of {self.name} at {np.degrees(q[bad]):.1f} deg, beyond its limits",
                {"q_rad": q.tolist()},
            )
        return q


def near_parallel_links(model: KinematicModel, tol_rad: float = NEAR_PARALLEL_RAD) -> tuple[int, ...]:
    """Links ``i`` (1..5) whose joint axes ``i`` and ``i + 1`` are within ``tol_rad`` of parallel.

    Link 6 joins axis 6 to the flange, not two joints, so it is never one.

    >>> near_parallel_links(ur5()), near_parallel_links(kr15())
    ((2, 3), (2,))
    """
    return tuple(i + 1 for i in range(5) if abs(np.sin(model.alpha_rad[i])) < np.sin(tol_rad))


def kr15() -> KinematicModel:
    """A KUKA KR15/2-like arm: reach 1570 mm to the wrist centre (a1 + a2 + |(a3, d4)|), 140 mm flange.

    Joint zeros and directions follow KUKA's A1..A6 except the sign of A1, A4
    and A6 (limits are symmetric there): home is ``q = (0, -90, 90, 0, 0, 0)``
    deg with the upper arm up and the forearm forward; ``q3 = 0`` stretches the
    elbow and ``q5 = 0`` aligns axes 4 and 6 (both singular). Limits as KUKA's
    data sheet (A1 +-185, A2 -155..35, A3 -130..154, A4 +-350, A5 +-130, A6 +-350 deg).
    """
    return KinematicModel(
        name="kr15",
        a_mm=np.array([300.0, 650.0, 155.0, 0.0, 0.0, 0.0]),
        alpha_rad=np.radians([-90.0, 0.0, -90.0, 90.0, -90.0, 0.0]),
        d_mm=np.array([675.0, 0.0, 0.0, 600.0, 0.0, 140.0]),
        theta_offset_rad=np.radians([0.0, 0.0, -90.0, 0.0, 0.0, 0.0]),
        q_limits_rad=np.radians([[-185, 185], [-155, 35], [-130, 154], [-350, 350], [-130, 130], [-350, 350]]),
    )


def ur10e() -> KinematicModel:
    """Universal Robots UR10e with UR's published (classic) DH parameters.

    a = (0, -612.7, -571.55, 0, 0, 0) mm, d = (180.7, 0, 0, 174.15, 119.85,
    116.55) mm, alpha = (90, 0, 0, 90, -90, 0) deg; frame 6 is the tool flange.
    Limits +-360 deg on every joint (the data sheet's).
    """
    return KinematicModel(
        name="ur10e",
        a_mm=np.array([0.0, -612.7, -571.55, 0.0, 0.0, 0.0]),
        alpha_rad=np.radians([90.0, 0.0, 0.0, 90.0, -90.0, 0.0]),
        d_mm=np.array([180.7, 0.0, 0.0, 174.15, 119.85, 116.55]),
        theta_offset_rad=np.zeros(6),
        q_limits_rad=np.radians(np.tile([-360.0, 360.0], (6, 1))),
        wrist_frame=3,
    )


def ur5() -> KinematicModel:
    """Universal Robots UR5 (CB series) with UR's published classic DH parameters (mm, rad)."""
    return KinematicModel(
        name="ur5",
        a_mm=np.array([0.0, -425.0, -392.25, 0.0, 0.0, 0.0]),
        alpha_rad=np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]),
        d_mm=np.array([89.159, 0.0, 0.0, 109.15, 94.65, 82.3]),
        theta_offset_rad=np.zeros(6),
        q_limits_rad=np.radians(np.tile([-360.0, 360.0], (6, 1))),
        wrist_frame=3,
    )


def nominal_model(name: str) -> KinematicModel:
    """The nominal model called ``name`` ("kr15", "ur10e" or "ur5")."""
    builders = {"kr15": kr15, "ur10e": ur10e, "ur5": ur5}
    if name not in builders:
        raise ValueError(f"unknown robot model {name!r}; choose one of {sorted(builders)}")
    return builders[name]()
