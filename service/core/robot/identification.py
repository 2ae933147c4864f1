"""Kinematic identification: correct a robot's DH model from measured flange positions or poses.

posecell measures the arm's true flange pose (camera + hand-eye) while the
controller reports its joint angles; this module fits the geometric errors of
the controller's classic Denavit-Hartenberg model (see
:mod:`service.sim.robot`) to those pairs, the last step of the paper's method
("comparison with the robot controller's own pose to correct the robot model").

Parameters (all *errors* added to the nominal model, mm and rad):

- per joint ``i = 1..6``: ``a{i}``, ``alpha{i}``, ``d{i}``, ``theta{i}``
  (the DH row and the joint's zero offset); with ``parameterisation="hayati"``
  also ``beta{i}`` for every near-parallel link (below);
- ``base_x, base_y, base_z, base_rx, base_ry, base_rz``: a small transform
  ``T_delta`` (rotation vector, translation) with
  ``T_base_j0 = T_delta @ T_base_j0_nominal``;
- ``tool_x, tool_y, tool_z`` (and ``tool_rx, tool_ry, tool_rz`` for pose
  data): ``T_j6_flange = T_j6_flange_nominal @ T_delta``. With position-only
  data the measured point is ``p_flange_point_mm`` on the flange, and the
  fitted translation moves the flange frame so that the corrected model puts
  that point where it was measured.

Classic DH is redundant: with a base transform, ``theta1`` and ``d1`` are
rotations/translations about/along the base z; a tool transform absorbs the
last link's row; consecutive parallel axes make their ``d`` offsets
interchangeable. Those combinations are found numerically (singular values
of the column-normalised identification Jacobian at a fixed, data-independent
spread of joint configurations, below ``RANK_TOL`` of the largest, so that
near-redundancies count too: a point 0.09 mm off axis 6 does not make ``d5``
separable from ``alpha5`` in practice) and frozen at their nominal values, keeping
base and tool parameters first and earlier joints before later ones. The
data must then determine every remaining parameter, or the solve refuses
(``poor_motion``) and names the parameters it cannot see.

**Parallel axes: classic DH or Hayati's beta.** Classic DH has no small
number for a tilt of one of two parallel axes about the link's y axis (across
the common normal): for exactly parallel axes that error is not in the model
at all (UR's axes 2-4, KUKA's 2-3), and for nearly parallel ones the
common normal slides far along the axis, ``d_i`` and ``d_{i+1}`` become nearly
the same column of the Jacobian and the identification is ill-conditioned
(its condition number grows like 1/eps^2 with the angle eps between the axes:
~1e3 at 4 deg, ~3e5 at 0.25 deg, Hayati's ~17; tests/core/test_hayati.py).
``parameterisation="hayati"``
(the default of ``posecell calibrate robot``) uses Hayati and Mirmirani's
modification (1985) on exactly those links: link ``i`` becomes
``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)`` with ``d_i`` held at its
nominal value and ``beta_i`` identified, for every link whose nominal axes are
within 5 deg of parallel (:func:`~service.core.robot.kinematics.near_parallel_links`);
other links keep classic DH, which is regular there and which a beta would
only duplicate (four numbers already place a line). We chose this
over a product-of-exponentials model because it keeps one chain for every
user of :class:`KinematicModel` (nominal models, simulator, hand-eye, the
model files, whose classic-DH versions stay readable: they are Hayati models
with beta = 0), keeps the numeric freezing of redundant combinations above as
the one identifiability reduction (POE needs its own: 6 numbers per twist for
4 line parameters and a zero), and every parameter stays a length or an angle
of one link that a person can check against a data sheet.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.stats import qmc

from service.core.geometry.so3 import R_from_rotvec, T_from_rotvec, rotvec_between, rotvec_from_R
from service.core.results import Reason, SolveError
from service.core.robot.kinematics import KinematicModel, near_parallel_links

Array = NDArray[np.float64]

ANGLE_SCALE_MM = 1000.0  # internal unit of an angle: 1 mrad = 1 mm at 1 m, so lengths and angles are comparable
RANK_TOL = 1e-3  # relative singular value below which a combination counts as redundant (near-redundant too)
DATA_RANK_TOL = 1e-4  # relative singular value below which the data cannot see a combination
N_STRUCTURE_CONFIGS = 64  # Halton configurations used to find the model's structural redundancies
FD_STEP = 1e-4  # central-difference step, internal units (mm, or mrad at 1 m)

_DH_KINDS = ("a", "alpha", "d", "theta")
_MODEL_KINDS = (*_DH_KINDS, "beta")
_ANGLE_KINDS = ("alpha", "theta", "beta")
PARAMETERISATIONS = ("dh", "hayati")
BASE_NAMES = ("base_x", "base_y", "base_z", "base_rx", "base_ry", "base_rz")
TOOL_NAMES = ("tool_x", "tool_y", "tool_z", "tool_rx", "tool_ry", "tool_rz")


def dh_parameter_names() -> list[str]:
    """Names of the 24 DH error parameters, joint by joint: ``a1, alpha1, d1, theta1, a2, ...``."""
    return [f"{k}{i}" for i in range(1, 7) for k in _DH_KINDS]


def hayati_parameter_names(nominal: KinematicModel) -> list[str]:
    """Names of the Hayati model's link parameters: the DH rows plus ``beta{i}`` after ``theta{i}``
    for every near-parallel link ``i`` of ``nominal``."""
    parallel = near_parallel_links(nominal)
    return [n for i in range(1, 7) for n in (*[f"{k}{i}" for k in _DH_KINDS], *([f"beta{i}"] * (i in parallel)))]


def _is_angle(name: str) -> bool:
    return name.startswith(_ANGLE_KINDS) or name[-2:] in ("rx", "ry", "rz")


@dataclass(frozen=True)
class _Layout:
    """Which parameters exist, which are free, and how an error vector becomes a model."""

    nominal: KinematicModel
    names: tuple[str, ...]  # every parameter of the problem, fixed or not
    free: NDArray[np.bool_]
    with_orientation: bool
    p_flange_point_mm: Array

    @property
    def scale(self) -> Array:
        """Internal units per physical unit: 1 for mm, ANGLE_SCALE_MM for rad."""
        return np.array([ANGLE_SCALE_MM if _is_angle(n) else 1.0 for n in self.names])

    def model(self, delta: Array) -> KinematicModel:
        """The nominal model with the physical errors ``delta`` (len(names),) applied."""
        v = dict(zip(self.names, delta, strict=True))
        nom = self.nominal
        rows = {k: np.array([v.get(f"{k}{i}", 0.0) for i in range(1, 7)]) for k in _MODEL_KINDS}
        T_b = T_from_rotvec([v.get(n, 0.0) for n in BASE_NAMES[3:]], [v.get(n, 0.0) for n in BASE_NAMES[:3]])
        T_t = T_from_rotvec([v.get(n, 0.0) for n in TOOL_NAMES[3:]], [v.get(n, 0.0) for n in TOOL_NAMES[:3]])
        return replace(
            nom,
            a_mm=nom.a_mm + rows["a"],
            alpha_rad=nom.alpha_rad + rows["alpha"],
            d_mm=nom.d_mm + rows["d"],
            theta_offset_rad=nom.theta_offset_rad + rows["theta"],
            beta_rad=nom.beta_rad + rows["beta"],
            T_base_j0=T_b @ nom.T_base_j0,
            T_j6_flange=nom.T_j6_flange @ T_t,
        )

    def observe(self, model: KinematicModel, q: Array) -> Array:
        """Observation vector (M, 3) mm or (M, 6) mm + rad for ``model`` at joints ``q`` (M, 6)."""
        T = model.fk(q).reshape(-1, 4, 4)
        p = T[:, :3, :3] @ self.p_flange_point_mm + T[:, :3, 3]
        if not self.with_orientation:
            return p
        return np.hstack([p, rotvec_from_R(T[:, :3, :3])])


def _residual(layout: _Layout, delta: Array, q: Array, measured: Array, rot_weight_mm: float) -> Array:
    """Weighted residuals (predicted - measured), flattened; rotation as rotvec(R_meas^T R_pred) times weight."""
    pred = layout.observe(layout.model(delta), q)
    r_pos = pred[:, :3] - measured[:, :3]
    if not layout.with_orientation:
        return r_pos.ravel()
    r_rot = rotvec_between(R_from_rotvec(measured[:, 3:]), R_from_rotvec(pred[:, 3:]))
    return np.hstack([r_pos, rot_weight_mm * r_rot]).ravel()


def _jacobian(
    layout: _Layout, delta: Array, q: Array, measured: Array, rot_weight_mm: float, columns: NDArray[np.intp]
) -> Array:
    """Central-difference Jacobian of the residuals w.r.t. ``columns`` of ``delta``, internal units.

    Numeric because the DH chain and the rotation-vector residual make the
    analytic form long; FK is vectorised, so 2 x 36 evaluations are cheap.
    """
    scale = layout.scale
    J = np.empty((q.shape[0] * (6 if layout.with_orientation else 3), columns.size))
    for c, j in enumerate(columns):
        h = np.zeros_like(delta)
        h[j] = FD_STEP / scale[j]
        J[:, c] = (
            _residual(layout, delta + h, q, measured, rot_weight_mm)
            - _residual(layout, delta - h, q, measured, rot_weight_mm)
        ) / (2.0 * FD_STEP)
    return J


def _dependent_columns(J: Array, tol: float) -> tuple[list[int], int]:
    """Greedy column selection, in column order: the columns that add no new direction to the ones kept.

    Returns the dependent column indices and the numerical rank of ``J``
    (singular values of the column-normalised matrix above ``tol`` times the
    largest). Columns are visited in order, so earlier ones (base, tool,
    earlier joints) are kept in preference to later ones.
    """
    norms = np.linalg.norm(J, axis=0)
    Jn = J / np.where(norms > 0, norms, 1.0)
    s = np.linalg.svd(Jn, compute_uv=False)
    rank = int(np.sum(s > tol * s[0])) if s.size else 0
    kept: list[int] = []
    dependent: list[int] = []
    for j in range(J.shape[1]):
        if norms[j] == 0.0:
            dependent.append(j)
            continue
        trial = Jn[:, [*kept, j]]
        s_t = np.linalg.svd(trial, compute_uv=False)
        if s_t[-1] > tol * s_t[0]:
            kept.append(j)
        else:
            dependent.append(j)
    return dependent, rank


def _structure_configs(nominal: KinematicModel) -> Array:
    """A fixed, data-independent spread (N_STRUCTURE_CONFIGS, 6) of joints inside the limits, rad."""
    lo = np.maximum(nominal.q_limits_rad[:, 0], -np.pi)
    hi = np.minimum(nominal.q_limits_rad[:, 1], np.pi)
    u = qmc.Halton(d=6, scramble=False).random(N_STRUCTURE_CONFIGS + 1)[1:]  # row 0 is the all-zero corner
    return lo + u * (hi - lo)


@dataclass(frozen=True)
class KinematicIdResult:
    """A corrected kinematic model and how well the data determined it.

    Attributes
    ----------
    model : KinematicModel
        The corrected model (nominal plus the identified errors).
    names : tuple of str
        Every parameter of the problem (see the module docstring).
    delta : (P,) float, mm or rad
        Identified error of each parameter (0 for fixed ones).
    sigma : (P,) float, mm or rad
        Standard deviation of each identified error (a posteriori, scaled by
        the residuals' variance factor); 0 for fixed ones.
    fixed : tuple of str
        Parameters held at their nominal value.
    unidentifiable : tuple of str
        Those of ``fixed`` that the model's structure makes redundant (frozen
        automatically), as opposed to those the caller fixed.
    rms_before_mm, rms_after_mm : float
        RMS of the 3D position error of the measured point, nominal model and
        corrected model.
    rms_rotation_before_rad, rms_rotation_after_rad : float or None
        RMS orientation error (pose data only).
    residuals_mm : (M, 3) float, mm
        Corrected-model position residuals (predicted - measured).
    p_flange_point_mm : (3,) float, mm
        The measured point in the flange frame (origin for pose data).
    n_configs, n_iter : int
    parameterisation : str
        ``"dh"`` (classic) or ``"hayati"`` (see the module docstring).
    condition : float
        Condition number of the column-normalised identification Jacobian of
        the free parameters at the solution: large means nearly redundant.
    """

    model: KinematicModel
    names: tuple[str, ...]
    delta: Array
    sigma: Array
    fixed: tuple[str, ...]
    unidentifiable: tuple[str, ...]
    rms_before_mm: float
    rms_after_mm: float
    rms_rotation_before_rad: float | None
    rms_rotation_after_rad: float | None
    residuals_mm: Array
    p_flange_point_mm: Array
    n_configs: int
    n_iter: int
    covariance: Array = field(repr=False)  # (P, P), mm and rad; zero rows/columns for fixed parameters
    parameterisation: str = "dh"
    condition: float = float("nan")

    def parameter(self, name: str) -> tuple[float, float]:
        """``(delta, sigma)`` of one parameter, mm or rad."""
        k = self.names.index(name)
        return float(self.delta[k]), float(self.sigma[k])

    def as_dict(self) -> dict[str, tuple[float, float]]:
        """``{name: (delta, sigma)}`` of the identified (free) parameters."""
        return {
            n: (float(d), float(s))
            for n, d, s in zip(self.names, self.delta, self.sigma, strict=True)
            if n not in self.fixed
        }

    def predict(self, q_rad: ArrayLike) -> Array:
        """Where the corrected model puts the measured point: (M, 3) mm for ``q_rad`` (M, 6) rad, or (3,).

        This is the arm's true position for commanded joints, i.e. the
        commanded position plus the predicted error; see :meth:`compensate`
        for the inverse use.
        """
        q = np.asarray(q_rad, dtype=np.float64)
        T = self.model.fk(q.reshape(-1, 6))
        p = T[:, :3, :3] @ self.p_flange_point_mm + T[:, :3, 3]
        return p[0] if q.ndim == 1 else p

    def predict_T(self, q_rad: ArrayLike) -> Array:
        """``T_base_flange`` (4, 4) or (M, 4, 4) of the corrected model for ``q_rad`` (6,) or (M, 6) rad."""
        return self.model.fk(q_rad)

    def compensate(self, nominal: KinematicModel, T_base_flange_target: ArrayLike, q_seed_rad: ArrayLike) -> Array:
        """The flange pose to command to a controller running ``nominal`` so the real arm reaches the target.

        Solves the corrected model's inverse kinematics for the target, then
        maps those joints through the nominal model: the controller's IK of
        the returned pose gives exactly the joints that put the true flange on
        ``T_base_flange_target`` (4, 4), mm.

        Raises
        ------
        SolveError
            When the target is unreachable (see ``KinematicModel.ik``).
        """
        q = self.model.ik(T_base_flange_target, q_seed_rad)
        return nominal.fk(q)


def identification_jacobian(
    nominal: KinematicModel, q_rad: ArrayLike, names: Sequence[str], p_flange_point_mm: ArrayLike | None = None
) -> Array:
    """Column-normalised Jacobian (3M, len(names)) of measured positions w.r.t. the named errors, at zero errors.

    For looking at a parameterisation's conditioning (``np.linalg.cond`` of it):
    ``names`` may mix base, tool, DH and ``beta{i}`` names of any link.
    """
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1, 6)
    point = np.zeros(3) if p_flange_point_mm is None else np.asarray(p_flange_point_mm, dtype=np.float64).reshape(3)
    layout = _Layout(nominal, tuple(names), np.ones(len(names), dtype=bool), False, point)
    J = _jacobian(layout, np.zeros(len(names)), q, layout.observe(nominal, q), 1.0, np.arange(len(names)))
    norms = np.linalg.norm(J, axis=0)
    return J / np.where(norms > 0, norms, 1.0)


def identify_kinematics(
    nominal: KinematicModel,
    q_rad: ArrayLike,
    measured: ArrayLike,
    *,
    estimate_base: bool = True,
    estimate_tool: bool = True,
    fixed: Sequence[str] = (),
    p_flange_point_mm: ArrayLike | None = None,
    rotation_weight_mm: float = ANGLE_SCALE_MM,
    max_nfev: int = 100,
    parameterisation: str = "dh",
) -> KinematicIdResult:
    """Identify the geometric errors of ``nominal`` from joint angles and measured flange positions or poses.

    Parameters
    ----------
    nominal : KinematicModel
        The controller's model; the starting point and the reference of every error.
    q_rad : (M, 6) float, rad
        Joint angles the controller reported at each measurement.
    measured : (M, 3) float, mm, or (M, 4, 4) float
        Measured position of the point ``p_flange_point_mm`` on the flange in
        the base frame, or measured ``T_base_flange`` poses (mm).
    estimate_base : bool
        Fit a 6-parameter correction of the base (``T_base_j0``).
    estimate_tool : bool
        Fit a correction of the flange offset (``T_j6_flange``): 3 parameters
        for position data, 6 for pose data.
    fixed : sequence of str
        Parameters to hold at their nominal value (see the module docstring
        for the names, e.g. ``("theta6", "d4")``).
    p_flange_point_mm : (3,) float, mm, optional
        Nominal position of the measured point in the flange frame (position
        data only; default the flange origin).
    rotation_weight_mm : float, mm
        Weight of a radian of orientation error against a millimetre of
        position error (pose data only).
    max_nfev : int
        Iteration limit of the least-squares solver.
    parameterisation : {"dh", "hayati"}
        Classic DH errors, or Hayati's beta in place of d on near-parallel
        links (see the module docstring).

    Returns
    -------
    KinematicIdResult

    Raises
    ------
    SolveError
        ``bad_input`` for non-finite input or an unknown name in ``fixed``;
        ``poor_motion`` when there are fewer than twice as many equations as
        free parameters, or the configurations do not determine every
        structurally identifiable parameter (``details["unidentifiable"]``
        names them; vary the joints more or pass them in ``fixed``);
        ``no_convergence`` when the solver stops without converging.
    """
    q = np.asarray(q_rad, dtype=np.float64)
    meas = np.asarray(measured, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 6:
        raise ValueError(f"q_rad must have shape (M, 6), got {q.shape}")
    M = q.shape[0]
    if meas.shape == (M, 4, 4):
        with_orientation = True
        obs = np.hstack([meas[:, :3, 3], rotvec_from_R(meas[:, :3, :3])])
    elif meas.shape == (M, 3):
        with_orientation = False
        obs = meas
    else:
        raise ValueError(f"measured must have shape ({M}, 3) or ({M}, 4, 4), got {meas.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(obs))):
        raise SolveError(Reason.bad_input, "joint angles or measurements contain non-finite values")
    if with_orientation and p_flange_point_mm is not None:
        raise ValueError("p_flange_point_mm is for position data; pose data measure the flange frame itself")
    point = np.zeros(3) if p_flange_point_mm is None else np.asarray(p_flange_point_mm, dtype=np.float64).reshape(3)
    if not rotation_weight_mm > 0:
        raise ValueError(f"rotation_weight_mm must be positive, got {rotation_weight_mm}")

    if parameterisation not in PARAMETERISATIONS:
        raise ValueError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}")
    link_names = dh_parameter_names() if parameterisation == "dh" else hayati_parameter_names(nominal)
    # Hayati: beta replaces d on a near-parallel link, whose d only slides the common normal along the axis
    replaced = {f"d{i}" for i in near_parallel_links(nominal)} if parameterisation == "hayati" else set()
    names = list(link_names)
    if estimate_base:
        names += BASE_NAMES
    if estimate_tool:
        names += TOOL_NAMES if with_orientation else TOOL_NAMES[:3]
    unknown = sorted(set(fixed) - set(names))
    if unknown:
        raise SolveError(Reason.bad_input, f"cannot fix unknown or unestimated parameters {unknown}", {"known": names})
    # base and tool first so that the greedy selection keeps them and freezes the DH rows they absorb
    order = [n for n in names if n.startswith(("base", "tool"))] + link_names
    user_fixed = set(fixed)
    layout = _Layout(
        nominal, tuple(order), np.array([n not in user_fixed | replaced for n in order]), with_orientation, point
    )
    P = len(order)
    zero = np.zeros(P)

    # structural redundancy: same for every data set, so find it on a fixed spread of configurations
    q_s = _structure_configs(nominal)
    obs_s = layout.observe(nominal, q_s)
    cand = np.flatnonzero(layout.free)
    J_s = _jacobian(layout, zero, q_s, obs_s, rotation_weight_mm, cand)
    dep, _ = _dependent_columns(J_s, RANK_TOL)
    structural = tuple(n for n in order if n in replaced - user_fixed) + tuple(order[cand[j]] for j in dep)
    free = layout.free.copy()
    free[cand[dep]] = False
    layout = replace(layout, free=free)
    cols = np.flatnonzero(free)
    n_eq = M * (6 if with_orientation else 3)
    if n_eq < 2 * cols.size:
        raise SolveError(
            Reason.poor_motion,
            f"{M} configurations give {n_eq} equations for {cols.size} parameters; measure at least "
            f"{int(np.ceil(2 * cols.size / (6 if with_orientation else 3)))} well-spread configurations",
            {"n_configs": M, "n_parameters": int(cols.size)},
        )

    # what these data can see: refuse rather than return numbers the data do not determine
    J0 = _jacobian(layout, zero, q, obs, rotation_weight_mm, cols)
    dep_data, rank = _dependent_columns(J0, DATA_RANK_TOL)
    if dep_data or rank < cols.size:
        blind = [order[cols[j]] for j in dep_data]
        raise SolveError(
            Reason.poor_motion,
            f"the {M} configurations do not determine {len(blind) or cols.size - rank} of the "
            f"{cols.size} parameters ({', '.join(blind)}); move the joints over a wider range or fix them",
            {"unidentifiable": blind, "rank": rank, "n_parameters": int(cols.size)},
        )

    scale = layout.scale[cols]

    def fun(x: Array) -> Array:
        d = zero.copy()
        d[cols] = x / scale
        return _residual(layout, d, q, obs, rotation_weight_mm)

    def jac(x: Array) -> Array:
        d = zero.copy()
        d[cols] = x / scale
        return _jacobian(layout, d, q, obs, rotation_weight_mm, cols)

    r0 = fun(np.zeros(cols.size))
    sol = least_squares(fun, np.zeros(cols.size), jac=jac, method="lm", xtol=1e-12, ftol=1e-12, max_nfev=max_nfev)
    if sol.status <= 0:
        raise SolveError(
            Reason.no_convergence,
            f"kinematic identification did not converge in {sol.nfev} evaluations ({sol.message})",
            {"n_eval": int(sol.nfev)},
        )
    delta = zero.copy()
    delta[cols] = sol.x / scale

    J = sol.jac
    dof = n_eq - cols.size
    s0_sq = float(sol.fun @ sol.fun) / dof
    cov_int = s0_sq * np.linalg.inv(J.T @ J)
    cov = np.zeros((P, P))
    cov[np.ix_(cols, cols)] = cov_int / np.outer(scale, scale)
    sigma = np.sqrt(np.diag(cov))
    s_J = np.linalg.svd(J / np.linalg.norm(J, axis=0), compute_uv=False)

    def split(r: Array) -> tuple[Array, float | None]:
        rr = r.reshape(M, -1)
        rot = None
        if with_orientation:
            rot = float(np.sqrt(np.mean(np.sum(rr[:, 3:] ** 2, axis=1)))) / rotation_weight_mm
        return rr[:, :3], rot

    pos0, rot0 = split(r0)
    pos1, rot1 = split(sol.fun)
    return KinematicIdResult(
        model=layout.model(delta),
        names=tuple(order),
        delta=delta,
        sigma=sigma,
        fixed=tuple(n for n, f in zip(order, free, strict=True) if not f),
        unidentifiable=structural,
        rms_before_mm=float(np.sqrt(np.mean(np.sum(pos0**2, axis=1)))),
        rms_after_mm=float(np.sqrt(np.mean(np.sum(pos1**2, axis=1)))),
        rms_rotation_before_rad=rot0,
        rms_rotation_after_rad=rot1,
        residuals_mm=pos1.copy(),
        p_flange_point_mm=point,
        n_configs=M,
        n_iter=int(sol.nfev),
        covariance=cov,
        parameterisation=parameterisation,
        condition=float(s_J[0] / s_J[-1]),
    )


@dataclass(frozen=True)
class Observability:
    """What a set of configurations lets :func:`identify_kinematics` see (its defaults: base and tool estimated).

    Attributes
    ----------
    names : tuple of str
        The parameters the data determine (to be identified).
    structural : tuple of str
        Frozen whatever the data: redundant in the model itself (see the module docstring).
    blind : tuple of str
        Structurally identifiable, but these configurations cannot separate them from the others.
    condition : float
        Condition number of the column-normalised Jacobian of ``names`` (large: nearly redundant).
    rank : int
        Numerical rank of that Jacobian over every structurally identifiable parameter.
    """

    names: tuple[str, ...]
    structural: tuple[str, ...]
    blind: tuple[str, ...]
    condition: float
    rank: int


def _pose_problem(
    nominal: KinematicModel, with_orientation: bool, parameterisation: str
) -> tuple[_Layout, tuple[str, ...]]:
    """The layout of :func:`identify_kinematics` (base and tool estimated, nothing fixed by the caller) after
    its structural freezing, and the names frozen that way."""
    if parameterisation not in PARAMETERISATIONS:
        raise ValueError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}")
    link_names = dh_parameter_names() if parameterisation == "dh" else hayati_parameter_names(nominal)
    replaced = {f"d{i}" for i in near_parallel_links(nominal)} if parameterisation == "hayati" else set()
    tool = TOOL_NAMES if with_orientation else TOOL_NAMES[:3]
    order = [*BASE_NAMES, *tool, *link_names]
    layout = _Layout(nominal, tuple(order), np.array([n not in replaced for n in order]), with_orientation, np.zeros(3))
    q_s = _structure_configs(nominal)
    cand = np.flatnonzero(layout.free)
    J_s = _jacobian(layout, np.zeros(len(order)), q_s, layout.observe(nominal, q_s), ANGLE_SCALE_MM, cand)
    dep, _ = _dependent_columns(J_s, RANK_TOL)
    structural = tuple(n for n in order if n in replaced) + tuple(order[cand[j]] for j in dep)
    free = layout.free.copy()
    free[cand[dep]] = False
    return replace(layout, free=free), structural


def pose_jacobian(
    nominal: KinematicModel, q_rad: ArrayLike, parameterisation: str = "hayati"
) -> tuple[Array, tuple[str, ...]]:
    """Jacobian (6M, P) of measured flange poses (mm, rad x ANGLE_SCALE_MM) w.r.t. the structurally identifiable
    errors at zero error, internal units, and those P names: for planning configurations that see them."""
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1, 6)
    layout, _ = _pose_problem(nominal, True, parameterisation)
    cols = np.flatnonzero(layout.free)
    obs = layout.observe(nominal, q)
    J = _jacobian(layout, np.zeros(len(layout.names)), q, obs, ANGLE_SCALE_MM, cols)
    return J, tuple(layout.names[c] for c in cols)


def observability(
    nominal: KinematicModel, q_rad: ArrayLike, with_orientation: bool = True, parameterisation: str = "hayati"
) -> Observability:
    """Which errors the configurations ``q_rad`` (M, 6) rad determine, measured as poses (or positions).

    The same test :func:`identify_kinematics` applies before it solves, without solving: a plan can be
    judged before the robot moves, and the blind parameters passed to it as ``fixed``.
    """
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1, 6)
    layout, structural = _pose_problem(nominal, with_orientation, parameterisation)
    cols = np.flatnonzero(layout.free)
    J = _jacobian(layout, np.zeros(len(layout.names)), q, layout.observe(nominal, q), ANGLE_SCALE_MM, cols)
    dep, rank = _dependent_columns(J, DATA_RANK_TOL)
    keep = np.setdiff1d(np.arange(cols.size), dep)
    Jk = J[:, keep]
    s = np.linalg.svd(Jk / np.where((nrm := np.linalg.norm(Jk, axis=0)) > 0, nrm, 1.0), compute_uv=False)
    return Observability(
        names=tuple(layout.names[cols[j]] for j in keep),
        structural=structural,
        blind=tuple(layout.names[cols[j]] for j in dep),
        condition=float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf"),
        rank=rank,
    )
