"""A simulated 6-axis arm: its true geometry and its motion programs.

The controller plans with its *nominal* model; the real arm is a *perturbed*
copy of it (geometric errors of the size the paper reports, ~1-2 mm at the
flange). Joint positions are the common currency: a program is a joint
trajectory computed with the nominal model; the true flange pose is the true
model's forward kinematics of those joints, the reported pose the nominal
model's (plus encoder noise, which :mod:`service.sim.cell` adds).

The kinematic models themselves are pure geometry: :mod:`service.core.robot.kinematics`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from service.core.geometry.frames import check_T, make_T
from service.core.results import Reason, SolveError
from service.core.robot.kinematics import KinematicModel

Array = NDArray[np.float64]

# perturbed(): error magnitudes for scale = 1, drawn uniformly in [lo, hi] with a random sign
LENGTH_ERROR_MM = (0.2, 0.5)  # every a_i and d_i
JOINT_ZERO_ERROR_DEG = (0.01, 0.03)  # every theta_offset_i
ALPHA_ERROR_DEG = (0.005, 0.015)  # every alpha_i (axis misalignment)
BASE_TILT_DEG = (0.005, 0.015)  # about a random horizontal axis of the base


def perturbed(model: KinematicModel, rng: np.random.Generator, scale: float = 1.0) -> KinematicModel:
    """The *true* arm: ``model`` with geometric errors of the size the paper reports.

    For ``scale = 1`` every error's magnitude is drawn uniformly from a band
    and given a random sign: link lengths and offsets (every a_i, d_i)
    0.2-0.5 mm, joint zeros (theta_offset_i) 0.01-0.03 deg, axis
    misalignments (alpha_i) 0.005-0.015 deg, and a base tilt of 0.005-0.015
    deg about a random horizontal axis. Over the working range this moves the
    flange by ~1-2 mm (median over seeds ~1.2 mm, single seeds 0.5-2 mm; see
    ``service.sim.cell.CellConfig``). ``scale`` multiplies every error; 0
    gives the nominal model back.
    """
    if not (np.isfinite(scale) and scale >= 0):
        raise ValueError(f"scale must be finite and non-negative, got {scale}")

    def draw(band: tuple[float, float], n: int) -> Array:
        return scale * rng.uniform(*band, size=n) * rng.choice([-1.0, 1.0], size=n)

    d_a = draw(LENGTH_ERROR_MM, 6)
    d_d = draw(LENGTH_ERROR_MM, 6)
    d_theta = np.radians(draw(JOINT_ZERO_ERROR_DEG, 6))
    d_alpha = np.radians(draw(ALPHA_ERROR_DEG, 6))
    tilt = np.radians(draw(BASE_TILT_DEG, 1)[0])
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    R_tilt = Rotation.from_rotvec(tilt * np.array([np.cos(azimuth), np.sin(azimuth), 0.0])).as_matrix()
    return replace(
        model,
        a_mm=model.a_mm + d_a,
        d_mm=model.d_mm + d_d,
        theta_offset_rad=model.theta_offset_rad + d_theta,
        alpha_rad=model.alpha_rad + d_alpha,
        T_base_j0=make_T(R_tilt, np.zeros(3)) @ model.T_base_j0,
    )


# -- motion programs -----------------------------------------------------------


def _min_jerk(tau: Array, nu: int) -> Array:
    """The quintic 10 t^3 - 15 t^4 + 6 t^5 (rest to rest, C2) or its ``nu``-th derivative."""
    if nu == 0:
        return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    if nu == 1:
        return 30.0 * tau**2 * (1.0 - tau) ** 2
    if nu == 2:
        return 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)
    raise ValueError(f"derivative order must be 0, 1 or 2, got {nu}")


@dataclass(frozen=True, eq=False)
class JointTrajectory:
    """Joint positions over time, C2-smooth between the knots.

    ``t_s`` (K,) s strictly increasing, ``q_rad`` (K, 6) rad. ``mode``:
    ``"spline"`` passes a cubic spline through the knots (periodic when
    ``periodic``, which needs ``q_rad[0] == q_rad[-1]``; else zero velocity at
    both ends); ``"rest"`` moves point to point, resting at every knot, with a
    minimum-jerk quintic per segment (no overshoot: each joint stays between
    its knot values). Outside ``[t_s[0], t_s[-1]]`` a periodic trajectory
    wraps and any other is clamped to its end.
    """

    t_s: Array
    q_rad: Array
    mode: str = "spline"
    periodic: bool = False
    _spline: CubicSpline | None = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        t = np.array(self.t_s, dtype=np.float64).reshape(-1)
        q = np.array(self.q_rad, dtype=np.float64)
        if q.ndim != 2 or q.shape != (t.size, 6) or t.size < 2:
            raise ValueError(f"need t_s (K,) and q_rad (K, 6) with K >= 2, got {t.shape} and {q.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.all(np.diff(t) > 0)):
            raise ValueError("t_s must be finite and strictly increasing, q_rad finite")
        if self.mode not in ("spline", "rest"):
            raise ValueError(f"mode must be 'spline' or 'rest', got {self.mode!r}")
        if self.periodic and not np.allclose(q[0], q[-1], rtol=0.0, atol=1e-12):
            raise ValueError("a periodic trajectory must end on the joints it starts on")
        t.setflags(write=False)
        q.setflags(write=False)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "q_rad", q)
        if self.mode == "spline":
            bc = "periodic" if self.periodic else "clamped"
            q_fit = q.copy()
            if self.periodic:
                q_fit[-1] = q_fit[0]  # exactly, as CubicSpline demands
            object.__setattr__(self, "_spline", CubicSpline(t, q_fit, axis=0, bc_type=bc))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def q_at(self, t_s: ArrayLike, derivative: int = 0) -> Array:
        """Joint positions (6,) rad, or (M, 6) for ``t_s`` (M,) s; ``derivative`` 1 or 2 gives rad/s, rad/s^2."""
        t_in = np.asarray(t_s, dtype=np.float64)
        t = t_in.reshape(-1)
        t0, t1 = self.t_s[0], self.t_s[-1]
        inside = (t >= t0) & (t <= t1)
        if self.periodic:
            t = t0 + np.mod(t - t0, t1 - t0)
            inside = np.ones(t.shape, dtype=bool)
        else:
            t = np.clip(t, t0, t1)
        if self._spline is not None:
            out = self._spline(t, derivative)
        else:
            k = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, self.t_s.size - 2)
            h = self.t_s[k + 1] - self.t_s[k]
            s = _min_jerk((t - self.t_s[k]) / h, derivative) / h**derivative
            dq = self.q_rad[k + 1] - self.q_rad[k]
            out = (self.q_rad[k] if derivative == 0 else 0.0) + s[:, None] * dq
        if derivative > 0:
            out = np.where(inside[:, None], out, 0.0)  # at rest beyond a clamped end
        return out[0] if t_in.ndim == 0 else out


def _ik_from(model: KinematicModel, T_base_flange: ArrayLike, seeds: list[Array]) -> Array:
    """:meth:`KinematicModel.ik` from the first of ``seeds`` it converges from; the first seed's
    error when none does."""
    first: SolveError | None = None
    for seed in seeds:
        try:
            return model.ik(T_base_flange, seed)
        except SolveError as e:
            first = first or e
    assert first is not None
    raise first


def trajectory_through_poses(
    model: KinematicModel,
    T_base_flange_list: Sequence[ArrayLike],
    q_seed: ArrayLike,
    speed_mm_s: float = 250.0,
    dwell_s: float = 0.0,
    *,
    speed_deg_s: float = 45.0,
    joint_speed_deg_s: float = 60.0,
    start_at_seed: bool = False,
    closed: bool = False,
    fallback_seeds: Sequence[ArrayLike] = (),
) -> JointTrajectory:
    """Point-to-point moves through flange poses, planned with ``model`` (the controller's belief).

    Each pose is solved by :meth:`KinematicModel.ik` seeded with the previous
    solution (the first with ``q_seed``; a pose that fails from there is tried
    from ``q_seed`` again, then from each of ``fallback_seeds``). Each move rests at both ends (``mode="rest"``) and
    lasts the longest of: its flange travel / ``speed_mm_s``, its rotation /
    ``speed_deg_s``, its largest joint move / ``joint_speed_deg_s``; then the
    arm dwells ``dwell_s`` at the pose.

    Parameters
    ----------
    T_base_flange_list : sequence of (4, 4) float
    q_seed : (6,) float, rad
    start_at_seed : bool
        Start at ``q_seed`` and move to the first pose (else start there).
    closed : bool
        Return to the start at the end, so that the program loops without a jump.
    fallback_seeds : sequence of (6,) float, rad
        Seeds for a pose the numeric IK does not reach from the previous joints or ``q_seed`` (the
        arm's home: from where an interrupted program left it, the solver can stall mm short).

    Raises
    ------
    SolveError
        When a pose is unreachable (see :meth:`KinematicModel.ik`).
    """
    if not (speed_mm_s > 0 and speed_deg_s > 0 and joint_speed_deg_s > 0 and dwell_s >= 0):
        raise ValueError("speeds must be positive and dwell_s non-negative")
    seed = np.asarray(q_seed, dtype=np.float64).reshape(6)
    qs: list[Array] = [seed] if start_at_seed else []
    for T in T_base_flange_list:
        prev = qs[-1] if qs else seed
        qs.append(_ik_from(model, T, [prev, seed, *(np.asarray(q, dtype=np.float64) for q in fallback_seeds)]))
    if not qs:
        raise ValueError("need at least one pose")
    if closed and len(qs) > 1:
        qs.append(qs[0])
    q_knots = np.array(qs)
    T_knots = model.fk(q_knots)
    times = [0.0]
    q_out = [q_knots[0]]
    if dwell_s > 0:
        times.append(dwell_s)
        q_out.append(q_knots[0])
    for k in range(1, len(q_knots)):
        dist = np.linalg.norm(T_knots[k, :3, 3] - T_knots[k - 1, :3, 3])
        angle = np.linalg.norm(Rotation.from_matrix(T_knots[k - 1, :3, :3].T @ T_knots[k, :3, :3]).as_rotvec())
        move_s = max(
            dist / speed_mm_s,
            np.degrees(angle) / speed_deg_s,
            np.degrees(np.max(np.abs(q_knots[k] - q_knots[k - 1]))) / joint_speed_deg_s,
            0.1,
        )
        times.append(times[-1] + move_s)
        q_out.append(q_knots[k])
        if dwell_s > 0 and not (closed and k == len(q_knots) - 1):
            times.append(times[-1] + dwell_s)
            q_out.append(q_knots[k])
    if len(times) == 1:  # one pose and no dwell: hold it
        times.append(1.0)
        q_out.append(q_knots[0])
    return JointTrajectory(np.array(times), np.array(q_out), mode="rest")


def aim_flange(
    p_base_flange: ArrayLike, look_at_base: ArrayLike, x_hint_base: ArrayLike, T_flange_camera: ArrayLike
) -> Array:
    """``T_base_flange`` (4, 4) at ``p_base_flange`` whose camera's optical axis passes through ``look_at_base``.

    The camera's x axis is ``x_hint_base`` made perpendicular to the optical
    axis (so its y axis points along ``z_camera x x_hint``). The camera sits
    off the flange, so the aim is a fixed point: a few iterations, each 10x
    closer for a camera 100 mm off the flange at 1000 mm from its target.
    """
    p = np.asarray(p_base_flange, dtype=np.float64).reshape(3)
    target = np.asarray(look_at_base, dtype=np.float64).reshape(3)
    hint = np.asarray(x_hint_base, dtype=np.float64).reshape(3)
    X = check_T(T_flange_camera, "T_flange_camera")
    R_flange = np.eye(3)
    for _ in range(50):
        c = p + R_flange @ X[:3, 3]
        z = target - c
        z /= np.linalg.norm(z)
        x = hint - (hint @ z) * z
        n = np.linalg.norm(x)
        if n < 1e-6:
            raise ValueError("x_hint_base is parallel to the optical axis")
        x /= n
        R_camera = np.column_stack([x, np.cross(z, x), z])
        R_new = R_camera @ X[:3, :3].T
        if np.max(np.abs(R_new - R_flange)) < 1e-15:
            break
        R_flange = R_new
    return make_T(R_new, p)


def iso230_circle(
    model: KinematicModel,
    T_base_centre: ArrayLike,
    q_seed: ArrayLike,
    radius_mm: float = 300.0,
    laps: int = 10,
    period_s: float = 10.0,
    *,
    look_at_base_mm: ArrayLike | None = None,
    T_flange_camera: ArrayLike | None = None,
    samples_per_lap: int = 120,
) -> JointTrajectory:
    """The paper's ISO 230-4 circular test: ``laps`` laps of a flange circle at constant speed.

    The flange origin runs counter-clockwise (about the centre frame's z) on
    the circle of ``radius_mm`` in the x-y plane of ``T_base_centre``,
    starting on its +x axis, one lap per ``period_s``. The orientation is the
    centre frame's (constant) or, with ``look_at_base_mm`` and
    ``T_flange_camera``, the one that keeps the camera aimed at that point
    (:func:`aim_flange`, camera x along the centre frame's x). Joints come from
    ``model.ik`` (the controller's nominal model) at ``samples_per_lap``
    points of one lap, seeded one from the next, and a periodic cubic spline
    through them: the program starts and ends on the same joints and loops
    C2-smoothly. 120 samples keep the flange within ~1e-4 mm of the circle.
    """
    T_c = check_T(T_base_centre, "T_base_centre")
    if not (radius_mm > 0 and period_s > 0 and laps >= 1 and samples_per_lap >= 8):
        raise ValueError("radius_mm and period_s must be positive, laps >= 1, samples_per_lap >= 8")
    aimed = look_at_base_mm is not None
    if aimed and T_flange_camera is None:
        raise ValueError("aiming the camera needs T_flange_camera")
    phi = np.arange(samples_per_lap) * (2.0 * np.pi / samples_per_lap)
    q = np.asarray(q_seed, dtype=np.float64).reshape(6)
    q_lap = np.empty((samples_per_lap, 6))
    for k, f in enumerate(phi):
        p = T_c[:3, :3] @ [radius_mm * np.cos(f), radius_mm * np.sin(f), 0.0] + T_c[:3, 3]
        if aimed:
            T = aim_flange(p, look_at_base_mm, T_c[:3, 0], T_flange_camera)  # type: ignore[arg-type]
        else:
            T = make_T(T_c[:3, :3], p)
        q = model.ik(T, q)
        q_lap[k] = q
    n = samples_per_lap * int(laps)
    q_all = np.vstack([np.tile(q_lap, (int(laps), 1)), q_lap[:1]])
    t_all = np.arange(n + 1) * (period_s / samples_per_lap)
    return JointTrajectory(np.asarray(t_all, dtype=np.float64), q_all, mode="spline", periodic=True)


def random_workspace_poses(
    model: KinematicModel,
    rng: np.random.Generator,
    n: int,
    q_seed: ArrayLike,
    T_base_mean: ArrayLike,
    half_size_mm: tuple[float, float, float] = (300.0, 300.0, 200.0),
    max_tilt_deg: float = 30.0,
    min_dexterity_mm: float = 50.0,
    max_tries: int = 1000,
) -> list[Array]:
    """``n`` random flange poses around ``T_base_mean`` that ``model`` reaches from ``q_seed``.

    Positions are uniform in the box ``+-half_size_mm`` about the mean pose's
    origin (base axes); orientations are the mean pose's turned about a random
    axis by up to ``max_tilt_deg``. A pose is kept when its IK converges on the
    seed's branch inside the joint limits and away from singularities
    (:meth:`KinematicModel.dexterity_mm` >= ``min_dexterity_mm``).

    Returns
    -------
    list of (4, 4) float
        ``T_base_flange`` poses.

    Raises
    ------
    SolveError
        ``degenerate_geometry`` when fewer than ``n`` poses were found in ``max_tries``.
    """
    T_m = check_T(T_base_mean, "T_base_mean")
    seed = np.asarray(q_seed, dtype=np.float64).reshape(6)
    out: list[Array] = []
    for _ in range(max_tries):
        if len(out) == n:
            break
        p = T_m[:3, 3] + rng.uniform(-1.0, 1.0, 3) * np.asarray(half_size_mm)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.radians(max_tilt_deg) * np.sqrt(rng.uniform())  # uniform over the cone's cap area
        T = make_T(Rotation.from_rotvec(angle * axis).as_matrix() @ T_m[:3, :3], p)
        try:
            q = model.ik(T, seed)
        except SolveError:
            continue
        if model.dexterity_mm(q) >= min_dexterity_mm:
            out.append(T)
    if len(out) < n:
        raise SolveError(
            Reason.degenerate_geometry, f"found only {len(out)} of {n} reachable poses in {max_tries} tries"
        )
    return out
