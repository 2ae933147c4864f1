"""Solving a bundle network: start values, the adjustment with gross-error rejection, covariance.

Used by :mod:`service.core.calib.bundle` (one camera) and :mod:`service.core.calib.rig` (a rig).

Start values (:func:`orient_views`): every image with enough points of known
coordinates is resected (:func:`service.core.pose.resection.resect`, closed form then
least squares), points of unknown coordinates seen by two oriented images are
intersected, and both repeat until nothing changes.

Adjustment (:func:`solve_network`): ``scipy.optimize.least_squares`` (trust-region
reflective, LSMR on the analytic sparse Jacobian of :class:`BundleModel`). With
gross-error rejection, a first pass with a soft-L1 loss keeps gross errors from
dragging the solution; then iterative data snooping: each observation's test
statistic ``T = v^T Qvv^-1 v / sigma^2`` (2 degrees of freedom; ``Qvv = I - A Qxx A^T``
its residual cofactor) is compared with the chi-square quantile at a per-observation
false-alarm probability of 1e-5; sigma is robust (from the median statistic) after
the soft-L1 pass and the inliers' sigma0 after each least-squares pass. All
observations above the threshold are rejected per round (the largest first, never
the last two rays of a free point or the last four of an image), the network is
re-adjusted by plain least squares, and the rounds repeat until none is rejected.
Finally each rejected observation is tested as a new one against the clean
solution and taken back if it fits.

Covariance: ``sigma0^2 (J^T J)^-1`` with the datum's rows in ``J``; for inner
constraints ``C`` the gauge part is removed, ``Q = (N + C^T C)^-1 - E (C E)^-1 (C E)^-T E^T``
with ``E`` the network's similarity (or rigid) null space, which gives the
minimum-norm covariance of the datum points.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import NDArray
from scipy.optimize import least_squares

from service.core.calib.bundle_model import BundleModel, ExtraRows, inverse_2x2
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import inv_T
from service.core.geometry.so3 import R_from_rotvec, T_from_rotvec, left_jacobian, rotvec_from_R, skew
from service.core.pose.resection import resect
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
Progress = Callable[[str], None]

#: Per-observation false-alarm probability of data snooping (as the resection's).
SNOOPING_ALPHA = 1e-5
CHI2_CRIT = -2.0 * np.log(SNOOPING_ALPHA)  # chi^2(2) quantile: P(chi^2(2) > x) = exp(-x/2)
MAX_ROUNDS = 8
#: Below this size (rows x unknowns^2) a dense SVD trust-region step costs less than LSMR's
#: Python-level iterations; above it, the sparse Jacobian and LSMR.
DENSE_BELOW = 1e8
#: Gauss-Newton steps that polish each least-squares pass.
GAUSS_NEWTON_STEPS = 6
#: Minimum ray intersection angle for a start value of a new point, deg.
MIN_START_ANGLE_DEG = 2.0


# -- poses as station parameters ------------------------------------------------


def params_from_T(T_a_field: Array) -> Array:
    """The station's parameter block ``[w, t]`` (6,) of ``T_a_field`` (maps field into frame a)."""
    return np.r_[rotvec_from_R(T_a_field[:3, :3]), T_a_field[:3, 3]]


def T_from_params(v: Array) -> Array:
    """``T_a_field`` (4, 4) of a station's parameter block ``[w, t]`` (6,): the inverse of :func:`params_from_T`."""
    return T_from_rotvec(v[:3], v[3:6])


# -- start values -----------------------------------------------------------------


def resect_view(camera: BrownFraser, p_field: Array, uv: Array) -> Array | None:
    """``T_field_camera`` of one image from points of known coordinates, or None.

    The start camera may be far from the truth (no distortion yet), so gross-error
    rejection allows any sigma0 up to 2 % of the image diagonal.
    """
    if len(p_field) < 4:
        return None
    try:
        res = resect(camera, p_field, uv, max_sigma_px=0.02 * float(np.hypot(camera.width, camera.height)))
    except SolveError:
        return None
    return res.T_field_camera


def intersect_point(centres: Array, rays: Array) -> tuple[Array, float] | None:
    """Least-squares point closest to lines (centre (n, 3), unit direction (n, 3)) and the largest
    angle between two of them, deg; None if fewer than two lines."""
    if len(centres) < 2:
        return None
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    A, b = P.sum(axis=0), np.einsum("nij,nj->i", P, centres)
    try:
        p = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None
    cosang = np.clip(np.abs(rays @ rays.T), 0.0, 1.0)
    return p, float(np.degrees(np.arccos(cosang.min())))


@dataclass
class Views:
    """Observations grouped per image: ``view`` (M,) index of the image, ``point`` (M,), ``uv`` (M, 2)."""

    view: IntArray
    point: IntArray
    uv: Array
    n_views: int


def orient_views(
    cameras: Sequence[BrownFraser],
    view_camera: IntArray,
    views: Views,
    points: Array,
    T_field_view: list[Array | None],
    min_points: int = 4,
) -> tuple[list[Array | None], Array]:
    """Start poses of the images and start coordinates of the points.

    ``points`` (N, 3) with NaN rows for unknown points; ``T_field_view`` the known
    start poses (None: unknown). Returns both completed as far as possible.
    """
    pts = points.copy()
    T = list(T_field_view)
    by_view = [np.flatnonzero(views.view == j) for j in range(views.n_views)]
    while True:
        changed = False
        for j in range(views.n_views):
            if T[j] is not None:
                continue
            m = by_view[j]
            known = m[np.all(np.isfinite(pts[views.point[m]]), axis=1)]
            if len(known) >= min_points:
                T[j] = resect_view(cameras[view_camera[j]], pts[views.point[known]], views.uv[known])
                changed |= T[j] is not None
        unknown = np.flatnonzero(~np.all(np.isfinite(pts), axis=1))
        for i in unknown:
            m = np.flatnonzero(views.point == i)
            m = m[[T[views.view[k]] is not None for k in m]]
            if len(m) < 2:
                continue
            centres, rays = [], []
            for k in m:
                Tj = T[views.view[k]]
                assert Tj is not None
                ray = cameras[view_camera[views.view[k]]].rays_from_pixel(views.uv[k][None])[0]
                centres.append(Tj[:3, 3])
                rays.append(Tj[:3, :3] @ ray)
            got = intersect_point(np.array(centres), np.array(rays))
            if got is not None and got[1] >= MIN_START_ANGLE_DEG:
                pts[i] = got[0]
                changed = True
        if not changed:
            return T, pts


# -- the adjustment -----------------------------------------------------------------


@dataclass(frozen=True)
class NetworkInput:
    """What :func:`solve_network` adjusts (see :class:`BundleModel` for the meaning of each field).

    ``control``: point index -> (xyz (3,) mm, sigma mm); sigma 0 fixes the point.
    ``bars``: (a, b, distance mm, sigma mm > 0). ``inner``: (datum point indices,
    nominal xyz (n, 3), n_gauge 6 or 7) or None.
    """

    cameras: tuple[BrownFraser, ...]
    free_interior: tuple[tuple[str, ...], ...]
    station: IntArray
    camera: IntArray
    point: IntArray
    uv: Array
    stations: Array  # (S, 6) start
    offsets: Array  # (K - 1, 6) start
    offsets_free: bool
    points: Array  # (N, 3) start
    point_free: NDArray[np.bool_]
    control: dict[int, tuple[Array, float]]
    bars: tuple[tuple[int, int, float, float], ...]
    inner: tuple[IntArray, Array, int] | None
    residual_space: str = "pixel"
    sigma_px: float = 1.0


@dataclass(frozen=True)
class NetworkSolution:
    """The adjusted network: unknowns, quality and the cofactor matrix of its last model.

    ``model``: the last adjustment's model (inliers only; its layout indexes ``Q``).
    ``Q``: cofactor matrix (n, n) of ``model``'s unknowns (covariance = ``sigma0**2 * Q``).
    ``sigma0``: a-posteriori standard deviation of unit weight (unitless; times
    ``sigma_px`` it is px). ``residuals_px`` (M, 2): measured minus computed for every
    observation, rejected ones too. ``inliers`` (M,). ``point_used`` (N,): points with
    enough rays to be adjusted (fixed ones count). ``global_correlation`` (n,):
    of each unknown with all others.
    """

    cameras: list[BrownFraser]
    stations: Array
    offsets: Array
    points: Array
    model: BundleModel
    x: Array
    Q: Array
    sigma0: float
    redundancy: int
    residuals_px: Array
    inliers: NDArray[np.bool_]
    point_used: NDArray[np.bool_]
    global_correlation: Array
    n_iter: int
    initial_cost: float
    final_cost: float
    converged: bool


def _model(
    net: NetworkInput, inliers: NDArray[np.bool_], point_free: NDArray[np.bool_], x_parts: tuple, weight: float
) -> BundleModel:
    cams, stations, offsets, points = x_parts
    control = tuple((i, xyz, s) for i, (xyz, s) in sorted(net.control.items()) if s > 0 and point_free[i])
    bars = tuple(b for b in net.bars if point_free[b[0]] or point_free[b[1]])
    inner = None
    if net.inner is not None:
        keep = point_free[net.inner[0]]
        inner = (net.inner[0][keep], net.inner[1][keep], net.inner[2], weight)
    m = np.flatnonzero(inliers)
    return BundleModel(
        cams,
        net.free_interior,
        net.station[m],
        net.camera[m],
        net.point[m],
        net.uv[m],
        len(stations),
        point_free,
        net.offsets_free,
        points,
        offsets,
        net.residual_space,
        net.sigma_px,
        ExtraRows(control=control, bars=bars, inner=inner),
    )


def _free_points(net: NetworkInput, inliers: NDArray[np.bool_]) -> NDArray[np.bool_]:
    rays = np.bincount(net.point[inliers], minlength=len(net.points))
    controlled = np.zeros(len(net.points), bool)
    controlled[[i for i, (_, s) in net.control.items() if s > 0]] = True
    return net.point_free & ((rays >= 2) | controlled)


def _solve(
    model: BundleModel, x0: Array, loss: str, f_scale: float, progress: Progress | None, stage: str, near: bool = False
) -> tuple[Array, int, bool]:
    """``least_squares`` to a coarse tolerance, then (plain least squares) Gauss-Newton steps on the
    normal equations to full precision; ``near``: the start is already close (Gauss-Newton only).

    Its trust-region steps solve the linear subproblem by LSMR, inexactly in the ill-conditioned
    directions of the interior orientation, so near the minimum it crawls; the normal equations
    are factorized for the covariance anyway, and Gauss-Newton on them converges in 1-3 steps.
    """

    def report(intermediate_result: object) -> None:
        if progress is not None:
            progress(
                f"{stage}: iteration {getattr(intermediate_result, 'nit', '?')}, "
                f"cost {float(getattr(intermediate_result, 'cost', np.nan)):.6g}"
            )

    if model.n_rows * model.n_params**2 < DENSE_BELOW:
        jac, tr_solver = (lambda x: model.jacobian(x).toarray()), "exact"
    else:
        jac, tr_solver = model.jacobian, "lsmr"
    if near and loss == "linear":
        x, nfev, converged = np.asarray(x0, dtype=np.float64), 0, False
    else:
        sol = least_squares(
            model.residuals,
            x0,
            jac=jac,
            method="trf",
            tr_solver=tr_solver,
            x_scale="jac",
            loss=loss,
            f_scale=f_scale,
            ftol=1e-6,
            xtol=1e-8,
            gtol=1e-8,
            max_nfev=100,
            callback=report if progress is not None else None,
        )
        x, nfev, converged = sol.x, int(sol.nfev), bool(sol.status > 0)
    if loss != "linear":
        return x, nfev, converged
    f = model.residuals(x)
    cost = float(f @ f)
    for _ in range(GAUSS_NEWTON_STEPS):
        J = model.jacobian(x)
        N = (J.T @ J).toarray()
        g = J.T @ f
        d = np.sqrt(np.maximum(np.diag(N), 1e-300))
        try:
            cho = scipy.linalg.cho_factor(N / np.outer(d, d), lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            break  # singular: the covariance reports it
        step = -scipy.linalg.cho_solve(cho, g / d, check_finite=False) / d
        predicted = -float(g @ step)  # decrease of f.f to first order, >= 0
        for _ in range(8):  # halve a step that overshoots (far from the minimum only)
            f_new = model.residuals(x + step)
            if float(f_new @ f_new) <= cost:
                break
            step *= 0.5
        else:
            # no step lowers the cost; from a near start that is the minimum, to rounding
            converged = converged or (near and predicted <= 1e-8 * max(cost, 1.0))
            break
        x, f = x + step, f_new
        nfev += 1
        new_cost = float(f @ f)
        done = predicted <= 1e-10 * max(cost, 1.0)
        cost = new_cost
        if done:
            converged = True
            break
    return x, nfev, converged


def cofactor(model: BundleModel, x: Array) -> tuple[Array, Array, Array]:
    """``(J^T J)^-1`` (n, n) of the model at ``x`` with the datum applied, the Jacobian, and each
    unknown's global correlation with all others (n,).

    Raises ``SolveError(degenerate_geometry)`` if the normal equations are singular.
    """
    J = model.jacobian(x)
    N = (J.T @ J).toarray()
    d = np.sqrt(np.diag(N))
    if not np.all(d > 0):
        raise SolveError(Reason.degenerate_geometry, "Some unknowns of the bundle are not observed at all.")
    Ns = N / np.outer(d, d)
    try:
        cho = scipy.linalg.cho_factor(Ns, lower=True, check_finite=False)
        Qs = scipy.linalg.cho_solve(cho, np.eye(len(Ns)), check_finite=False)
    except np.linalg.LinAlgError:
        raise SolveError(
            Reason.degenerate_geometry,
            "The bundle's normal equations are singular: the images do not determine the unknowns.",
        ) from None
    if not np.all(np.isfinite(Qs)) or np.min(np.diag(Qs)) <= 0:
        raise SolveError(Reason.degenerate_geometry, "The bundle's normal equations are singular.")
    rho = np.sqrt(np.clip(1.0 - 1.0 / np.diag(Qs), 0.0, 1.0))
    Q = Qs / np.outer(d, d)
    return Q, J, rho


def gauge_basis(model: BundleModel, x: Array, n_gauge: int) -> Array:
    """Null-space directions E (n, n_gauge) of the network in the model's unknowns: an infinitesimal
    rotation, translation (and scale) of the field frame about the points' centroid.

    With ``p' = s Rg (p - m) + m + tau`` every camera-frame point scales by ``s``, so the
    stations become ``R' = R Rg^T``, ``t' = s t + s R m - R' (m + tau)`` and the rig offsets'
    translations scale by ``s``. Requires every point to be free (no fixed control).
    """
    _, stations, offsets, points = model.unpack(x)
    m = points[model.point_free].mean(axis=0)
    q = points - m
    E = np.zeros((model.n_params, n_gauge))
    Rs = R_from_rotvec(stations[:, :3])
    Jl = left_jacobian(stations[:, :3])
    for j in range(model.n_stations):
        c = model.station_col0 + 6 * j
        # R' = exp(-[R g]x) R: a left perturbation -R g, i.e. dw = -Jl^-1 R g
        E[c : c + 3, :3] = -np.linalg.solve(Jl[j], Rs[j])
        E[c + 3 : c + 6, :3] = -Rs[j] @ skew(m)
        E[c + 3 : c + 6, 3:6] = -Rs[j]
        if n_gauge == 7:
            E[c + 3 : c + 6, 6] = stations[j, 3:] + Rs[j] @ m
    if model.offsets_free and n_gauge == 7:
        for k in range(model.n_cam - 1):
            c = model.offset_col0 + 6 * k
            E[c + 3 : c + 6, 6] = offsets[k, 3:]
    for i in np.flatnonzero(model.point_free):
        c = model.point_col[i]
        E[c : c + 3, :3] = -skew(q[i])
        E[c : c + 3, 3:6] = np.eye(3)
        if n_gauge == 7:
            E[c : c + 3, 6] = q[i]
    return E


def _observation_statistics(model: BundleModel, x: Array, Q: Array, sign: float) -> tuple[Array, Array]:
    """``v^T C^-1 v`` and ``det C`` (M,) with ``C = I + sign A Q A^T``, for the model's image observations
    (unit weight): ``sign = -1`` gives an adjusted observation's residual cofactor, ``+1`` that of one
    left out (its prediction error)."""
    J = model.jacobian(x)
    f = model.residuals(x)[: 2 * model.n_obs].reshape(-1, 2)
    Ji = J[: 2 * model.n_obs]
    even = Ji[::2]
    counts = np.diff(even.indptr)
    width = int(counts.max()) if len(counts) else 0
    idx = np.full((model.n_obs, width), model.n_params, dtype=np.int64)
    A = np.zeros((model.n_obs, 2, width))
    rowpos = np.arange(width)[None, :] < counts[:, None]
    idx[rowpos] = even.indices
    for r in range(2):
        rows = Ji[r::2]
        A[:, r][rowpos] = rows.data  # the two rows of one observation share their columns and order
    Qp = np.zeros((model.n_params + 1, model.n_params + 1))
    Qp[:-1, :-1] = Q
    T2, det = np.empty(model.n_obs), np.empty(model.n_obs)
    for c0 in range(0, model.n_obs, 2048):
        sl = slice(c0, c0 + 2048)
        sub = Qp[idx[sl][:, :, None], idx[sl][:, None, :]]
        h = np.einsum("mac,mcd,mbd->mab", A[sl], sub, A[sl])
        C = np.eye(2)[None] + sign * h
        v = f[sl]
        Ci = inverse_2x2(C)
        T2[sl] = np.einsum("mi,mij,mj->m", v, Ci, v)
        det[sl] = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    return T2, det


def solve_network(
    net: NetworkInput,
    *,
    reject_outliers: bool = True,
    robust_scale_px: float = 2.0,
    progress: Progress | None = None,
    near: bool = False,
) -> NetworkSolution:
    """Adjust the network, rejecting gross errors (see the module docstring), with covariance.

    ``near``: the start values are the solution of a nearly equal network (e.g. one epoch less, for
    a jackknife), so without rejection Gauss-Newton steps alone converge, at a fraction of the cost.
    """
    M = len(net.uv)
    inliers = np.ones(M, dtype=bool)
    parts = (list(net.cameras), net.stations.copy(), net.offsets.copy(), net.points.copy())
    weight = 1.0
    point_free = _free_points(net, inliers)
    model = _model(net, inliers, point_free, parts, weight)
    x = model.pack(*parts)
    f0 = model.residuals(x)
    initial_cost = 0.5 * float(f0 @ f0)
    n_iter, converged = 0, True
    loss = "soft_l1" if reject_outliers else "linear"
    robust_sigma = True
    rounds = 0
    readmitted = False
    while True:
        stage = "robust pass" if loss != "linear" else f"adjustment {rounds + 1}"
        x, nfev, conv = _solve(model, x, loss, robust_scale_px / net.sigma_px, progress, stage, near)
        n_iter += nfev
        converged = conv
        parts = tuple(model.unpack(x))  # type: ignore[assignment]
        if not reject_outliers:
            break
        Q, _, _ = cofactor(model, x)
        T2, det = _observation_statistics(model, x, Q, -1.0)
        r = model.n_rows - model.n_params
        if robust_sigma:
            s2 = float(np.median(T2)) / (2.0 * np.log(2.0))  # median of chi^2(2) is 2 ln 2
        else:
            f = model.residuals(x)
            s2 = float(f @ f) / max(r, 1)
        s2 = max(s2, 1e-12)
        score = T2 / (s2 * CHI2_CRIT)
        score[det <= 1e-6] = 0.0  # an observation the solution must pass through cannot be tested
        if rounds >= MAX_ROUNDS:
            break  # keep the last adjustment and its inliers consistent
        was_robust, robust_sigma, loss = robust_sigma, False, "linear"
        idx = np.flatnonzero(inliers)
        order = np.argsort(-score)
        rays = np.bincount(net.point[idx], minlength=len(net.points))
        per_station = np.bincount(net.station[idx], minlength=len(net.stations))
        rejected_now = 0
        for k in order:
            if score[k] <= 1.0:
                break
            o = idx[k]
            i, s = net.point[o], net.station[o]
            if (point_free[i] and rays[i] <= 2) or per_station[s] <= 4:
                continue
            inliers[o] = False
            rays[i] -= 1
            per_station[s] -= 1
            rejected_now += 1
        rounds += 1
        if rejected_now == 0 and not was_robust:
            if readmitted or inliers.all():
                break
            # swamping: test the rejected observations as new ones against the clean solution
            readmitted = True
            out = np.flatnonzero(~inliers)
            probe = _model(net, np.isin(np.arange(M), out), point_free, parts, weight)
            T2o, _ = _observation_statistics(probe, probe.pack(*parts), Q, 1.0)
            back = out[T2o / (s2 * CHI2_CRIT) <= 1.0]
            if len(back) == 0:
                break
            inliers[back] = True
        # (nothing rejected after the robust pass: one plain least-squares pass, then test again)
        point_free = _free_points(net, inliers)
        model = _model(net, inliers, point_free, parts, weight)
        x = model.pack(*parts)
    Q, _, rho = cofactor(model, x)
    if net.inner is not None and model.inner_C is not None:
        n_g = net.inner[2]
        E = gauge_basis(model, x, n_g)
        idx = model.extra.inner[0]  # type: ignore[index]
        cols = (model.point_col[idx][:, None] + np.arange(3)).ravel()
        CE = model.inner_C @ E[cols]
        F = E @ np.linalg.inv(CE)
        Q = Q - F @ F.T
    f = model.residuals(x)
    redundancy = model.n_rows - model.n_params
    if redundancy <= 0:
        raise SolveError(Reason.too_few_targets, "The bundle has no redundancy: too few observations for its unknowns.")
    sigma0 = float(np.sqrt(f @ f / redundancy))
    cams, stations, offsets, points = model.unpack(x)
    everything = _model(net, np.ones(M, bool), point_free, (cams, stations, offsets, points), weight)
    residuals = everything.image_residuals_px(everything.pack(cams, stations, offsets, points))
    pc = everything.camera_frame_points(everything.pack(cams, stations, offsets, points))
    behind = inliers & (pc[:, 2] <= 0)
    if np.any(behind):
        raise SolveError(
            Reason.behind_camera,
            f"{int(behind.sum())} observations lie behind the adjusted camera: the start values were too poor.",
        )
    return NetworkSolution(
        cameras=cams,
        stations=stations,
        offsets=offsets,
        points=points,
        model=model,
        x=x,
        Q=Q,
        sigma0=sigma0,
        redundancy=int(redundancy),
        residuals_px=residuals,
        inliers=inliers.copy(),
        point_used=point_free | ~net.point_free,
        global_correlation=rho,
        n_iter=n_iter,
        initial_cost=initial_cost,
        final_cost=0.5 * float(f @ f),
        converged=converged,
    )


# -- uncertainty of poses ------------------------------------------------------------------


def pose_sigmas(v: Array, cov6: Array) -> tuple[Array, Array]:
    """Standard deviations of ``T_parent_child = inv(T(v))`` for ``v = [w, t]`` of ``T_child_parent``.

    Returns (sigma_rotation_deg (3,) about the parent's axes, sigma_position_mm (3,) of the child's
    origin in the parent frame), from the covariance (6, 6) of ``v``.
    """
    R = R_from_rotvec(v[:3])
    Jl = left_jacobian(v[:3])
    C = -R.T @ v[3:]
    Rt = R.T
    L = np.zeros((6, 6))
    L[:3, :3] = -Rt @ Jl
    L[3:, :3] = skew(C) @ (-Rt @ Jl)
    L[3:, 3:] = -Rt
    cov = L @ cov6 @ L.T
    s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return np.degrees(s[:3]), s[3:]


def T_field_view(stations: Array, offsets: Array, station: int, camera: int) -> Array:
    """``T_field_camera`` of camera ``camera`` at station ``station``."""
    T_rig_field = T_from_params(stations[station])
    if camera == 0:
        return inv_T(T_rig_field)
    return inv_T(T_from_params(offsets[camera - 1]) @ T_rig_field)
