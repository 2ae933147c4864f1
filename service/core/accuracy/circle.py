"""ISO 230-4 circular test from a measured path (pure: arrays in, one frozen result out).

The robot runs the nominal circle (radius ``R`` mm) clockwise and counter-clockwise; the camera
measures the flange positions ``p`` (N, 3) mm, in time order, each labelled with its direction.
ISO 230-4 defines its figures on a 2-D path; a robot's path is 3-D, so:

1. Plane: the least-squares plane of all points (SVD of the centred points; the normal is the
   right singular vector of the smallest singular value), and the points in its 2-D coordinates:
   x along the input frame's x axis projected into the plane (its y axis if the plane is within
   26 deg of perpendicular to x), y = normal × x, θ from x towards y. The normal is oriented so
   that the ccw points turn positively (right-handed) about it: "ccw" is counter-clockwise seen
   from the tip of ``plane_normal``.
2. Least-squares circles (LSC) of the cw points, of the ccw points and of all points. First
   Kåsa's algebraic fit (IEEE Trans. Instrum. Meas. 25, 1976), linear in (D, E, F) of
   ``x² + y² + D x + E y + F = 0``: closed form, needs no start, exact for a perfect circle, but
   it minimises ``Σ (r_i² - ρ²)²``, not the radial deviations, so with noise and on arcs it is
   biased (radius small, centre pulled). From it, the geometric fit that is ISO's LSC: minimise
   ``Σ (|q_i - c| - ρ)²`` over (c, ρ) by ``scipy.optimize.least_squares`` (Levenberg-Marquardt):
   non-linear, it needs a start near the answer. At its optimum ρ is the mean radius about c.
3. Figures, ``r_i = |q_i - c|`` about the named centre c, R the nominal radius:

   - ``G_cw_mm``, ``G_ccw_mm`` (circular deviation): max r - min r of that direction's points
     about that direction's LSC centre;
   - ``G_bidirectional_mm``: the same of all points about the LSC centre of both, the *common
     centre*, which every figure below uses;
   - ``H_mm`` (circular hysteresis): max |r_cw(θ) - r_ccw(θ)| on a grid of ``GRID_STEP_DEG``,
     each profile linearly interpolated in θ with wrap-around, only where both directions cover
     θ (it lies between two of that direction's points, sorted by angle, at most
     ``max_gap_deg`` apart). A direction of several laps is one profile (the laps interleave);
   - ``F_max_mm``, ``F_min_mm`` (radial deviation): max and min of ``r_i - R``, both signed:
     ``F_min_mm`` < 0 where the path dips inside the nominal circle (> 0 if all lies outside);
   - ``mean_radial_deviation_mm``: the mean of the cw and ccw LSC radii, minus R;
   - the minimum-zone circle (MZC, ISO's alternative centre), minimising max r - min r: a linear
     program (``scipy.optimize.linprog``, HiGHS) in the limaçon approximation
     ``r_i(c + δ) ≈ r_i(c) - u_i·δ`` (Chetwynd, Proc. IMechE B 199, 1985), from the LSC,
     re-linearised until the step is < 1e-9 of the span. The LP solves each linearised problem
     exactly, where a simplex search on the non-smooth span can stall on one of its kinks;
   - the common centre's offset from the nominal centre, in the plane and along the normal;
   - beyond a ballbar: each point's signed distance from the plane (span, RMS); with
     orientations, the angle of each ``R`` from their chordal mean (max, RMS, deg) — or, with the
     robot's own orientations too, of each point's rotation from its robot orientation
     (``R_robot^T R``) from the mean of those rotations: a program that turns the tool along the
     circle (a camera kept aimed at a plate) is measured against its command, and a constant
     offset (hand-eye, base) is not counted; with the robot's commanded or reported positions,
     each measured point's distance from its own.

One direction missing: its G, ``G_bidirectional_mm``, ``H_mm`` (and the bidirectional MZC) are
None and ``notes`` says why; F and the per-point arrays are about the LSC of the points there
are, the mean radial deviation is that direction's. ``require_both=True`` raises instead.
Malformed input (shapes, labels, non-finite, R <= 0) raises ``SolveError(bad_input)``, as does
input that gives no figures: ``bad_input`` (< ``MIN_POINTS`` points in a direction, cw and
ccw turning the same way), ``degenerate_geometry`` (collinear or coincident), ``no_convergence``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares, linprog

from service.core.accuracy.inputs import bad_input, finite
from service.core.geometry.so3 import R_mean, angle_between
from service.core.results import Reason, SolveError

Array = NDArray[np.float64]

MIN_POINTS = 8  # per direction: a circle has 3 parameters; fewer than 8 points give no span worth reading
GRID_STEP_DEG = 0.5  # the hysteresis grid (ISO: <= 1 deg)
DEGENERATE = 1e-6  # second / first singular value of the points below this: they lie on a line
_TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, eq=False)
class CircleResult:
    """The circular test's figures (mm unless named), conditions and per-point profile.

    Figures of a missing direction are None. Per-point arrays are in input order:
    ``theta_rad`` (N,) about the common centre in the plane, ``radial_deviation_mm`` (N,)
    ``r_i - R`` about it, ``out_of_plane_mm`` (N,) signed along ``plane_normal``,
    ``orientation_deviation_deg`` (N,) or None, ``is_cw`` (N,) bool. Centres are (3,) mm in the
    input frame; ``plane_normal`` and ``theta_zero_axis`` (θ = 0) are (3,) unit vectors.
    """

    G_cw_mm: float | None
    G_ccw_mm: float | None
    G_bidirectional_mm: float | None
    H_mm: float | None
    F_max_mm: float
    F_min_mm: float
    mean_radial_deviation_mm: float
    G_mzc_cw_mm: float | None
    G_mzc_ccw_mm: float | None
    G_mzc_bidirectional_mm: float | None
    out_of_plane_span_mm: float
    out_of_plane_rms_mm: float
    orientation_deviation_max_deg: float | None
    orientation_deviation_rms_deg: float | None
    robot_deviation_max_mm: float | None
    robot_deviation_rms_mm: float | None
    centre_offset_mm: Array | None  # common centre - nominal centre
    centre_offset_in_plane_mm: float | None  # its length in the plane
    centre_offset_normal_mm: float | None  # its signed component along the normal
    # conditions
    radius_mm: float
    n_cw: int
    n_ccw: int
    plane_normal: Array
    theta_zero_axis: Array
    centre_mm: Array  # the common LSC centre
    radius_lsc_mm: float
    centre_cw_mm: Array | None
    radius_cw_mm: float | None
    centre_ccw_mm: Array | None
    radius_ccw_mm: float | None
    centre_mzc_mm: Array | None  # the MZC of all points
    centre_nominal_mm: Array | None
    max_gap_deg: float
    # per point
    theta_rad: Array
    radial_deviation_mm: Array
    out_of_plane_mm: Array
    orientation_deviation_deg: Array | None
    is_cw: NDArray[np.bool_]
    notes: tuple[str, ...] = ()

    def to_dict(self, points: bool = False) -> dict[str, Any]:
        """DESIGN section 5's JSON: the figures, ``"conditions"``, ``"notes"``; ``"points"`` if asked."""

        def num(x: Any, nd: int = 6) -> Any:
            if x is None or isinstance(x, int):
                return x
            a = np.round(np.asarray(x, dtype=np.float64), nd) + 0.0  # + 0.0: no -0.0
            return a.tolist() if a.ndim else float(a)

        names = [f.name for f in fields(self)]
        i, j = names.index("radius_mm"), names.index("theta_rad")  # figures, conditions, per point
        d: dict[str, Any] = {k: num(getattr(self, k)) for k in names[:i]}
        d["conditions"] = {k: num(getattr(self, k), 9) for k in names[i:j]} | {"grid_step_deg": GRID_STEP_DEG}
        d["notes"] = list(self.notes)
        if points:
            d["points"] = {k: num(getattr(self, k)) for k in names[j + 1 : -2]} | {
                "theta_deg": num(np.degrees(self.theta_rad)),
                "direction": ["cw" if c else "ccw" for c in self.is_cw.tolist()],
            }
        return d


def _is_cw(direction: ArrayLike, n: int) -> NDArray[np.bool_]:
    """Labels (n,): True = cw, from booleans (True = cw) or the strings "cw" / "ccw" (any case)."""
    d = np.asarray(direction)
    if d.shape != (n,):
        raise bad_input(f"direction must have one label per point, shape ({n},), not {d.shape}.")
    if d.dtype == np.bool_:
        return d.copy()
    s = np.char.lower(np.char.strip(d.astype(str)))
    bad = sorted(set(s.tolist()) - {"cw", "ccw"})
    if bad:
        raise bad_input(f"direction labels must be 'cw' or 'ccw', not {bad[:3]}.")
    return np.asarray(s == "cw")


def _check_spread(q: Array, what: str) -> None:
    """SolveError(degenerate_geometry) if the points (n, k) coincide or lie on a line."""
    m = q.mean(axis=0)
    s = np.linalg.svd(q - m, compute_uv=False)
    if s[0] <= 1e-12 * np.sqrt(len(q)) * (1.0 + float(np.max(np.abs(m)))) or s[1] < DEGENERATE * s[0]:
        raise SolveError(Reason.degenerate_geometry, f"the {what} lie on a line or a point: no circle to fit.")


def _fit_circle(q: Array, what: str) -> tuple[Array, float]:
    """The LSC (centre (2,) mm, radius mm) of points (n, 2): Kåsa's fit, then the geometric fit."""
    _check_spread(q, what)
    m = q.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((q - m) ** 2, axis=1))))  # work in units of the spread: tolerances relative
    z = (q - m) / s
    A = np.column_stack([z, np.ones(len(z))])
    D, E, F = np.linalg.lstsq(A, -np.sum(z * z, axis=1), rcond=None)[0]
    c0 = np.array([-D / 2.0, -E / 2.0])
    rho2 = float(c0 @ c0 - F)
    if not rho2 > 0.0:
        raise SolveError(Reason.degenerate_geometry, f"the {what} fit no circle.")

    def residuals(x: Array) -> Array:
        return np.asarray(np.hypot(z[:, 0] - x[0], z[:, 1] - x[1]) - x[2])

    def jacobian(x: Array) -> Array:
        d = z - x[:2]
        r = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)
        return np.column_stack([-d / r[:, None], -np.ones(len(z))])

    sol = least_squares(residuals, [c0[0], c0[1], np.sqrt(rho2)], jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15)
    if sol.status <= 0 or not np.all(np.isfinite(sol.x)):
        raise SolveError(Reason.no_convergence, f"the least-squares circle of the {what} did not converge.")
    return m + s * np.asarray(sol.x[:2]), s * float(sol.x[2])


def _radii(q: Array, c: Array) -> Array:
    return np.asarray(np.hypot(q[:, 0] - c[0], q[:, 1] - c[1]))


def _span(q: Array, c: Array) -> float:
    return float(np.ptp(_radii(q, c)))


def _min_zone(q: Array, c: Array) -> tuple[Array, float]:
    """Minimum-zone centre (2,) and span mm of points (n, 2): the iterated limaçon LP from c."""
    best_c, best = c, _span(q, c)
    S = best
    if S <= 1e-12 * (1.0 + float(np.max(_radii(q, c)))):
        return best_c, best
    n, bounds = len(q), [(-2.0, 2.0), (-2.0, 2.0), (None, None), (None, None)]  # a step of <= 2 spans a time
    for _ in range(20):
        r = _radii(q, c)
        u = (q - c) / r[:, None]
        b = (r - r.mean()) / S  # unknowns: the step δ/S, the zone's inner and outer radius (- mean)/S
        A = np.block([[-u, np.zeros((n, 1)), -np.ones((n, 1))], [u, np.ones((n, 1)), np.zeros((n, 1))]])
        lp = linprog([0.0, 0.0, -1.0, 1.0], A_ub=A, b_ub=np.concatenate([-b, b]), bounds=bounds, method="highs")
        if not lp.success:
            break
        step = S * np.asarray(lp.x[:2])
        c = c + step
        g = _span(q, c)
        if g < best:
            best_c, best = c, g
        if np.hypot(step[0], step[1]) < 1e-9 * S:
            break
    return best_c, best


def _profile(theta: Array, r: Array, grid: Array, max_gap: float) -> tuple[Array, NDArray[np.bool_]]:
    """r (n,) at angles theta (n,) rad interpolated at the grid (k,), and which grid angles are covered."""
    order = np.argsort(theta)
    t, rr = theta[order], r[order]
    n = len(t)
    ok = np.diff(t, append=t[0] + _TWO_PI) <= max_gap * (1.0 + 1e-12)  # gap j: from t[j] to the next point
    j = (np.searchsorted(t, grid, side="right") - 1) % n
    tol = 1e-9  # a grid angle on a point (to rounding) is covered by the gaps on either side
    near_start = np.mod(grid - t[j], _TWO_PI) < tol
    near_end = np.mod(t[(j + 1) % n] - grid, _TWO_PI) < tol
    covered = ok[j] | (near_start & ok[j - 1]) | (near_end & ok[(j + 1) % n])
    return np.interp(grid, t, rr, period=_TWO_PI), covered


def _hysteresis(theta: Array, r: Array, cw: NDArray[np.bool_], max_gap: float) -> float | None:
    """max |r_cw - r_ccw| mm on the grid where both directions cover the angle; None where none does."""
    grid = np.radians(np.arange(0.0, 360.0, GRID_STEP_DEG))
    r_cw, cov_cw = _profile(theta[cw], r[cw], grid, max_gap)
    r_ccw, cov_ccw = _profile(theta[~cw], r[~cw], grid, max_gap)
    common = cov_cw & cov_ccw
    return float(np.max(np.abs(r_cw - r_ccw)[common])) if common.any() else None


def circle_result(
    p_mm: ArrayLike,
    direction: ArrayLike,
    radius_mm: float,
    *,
    centre_mm: ArrayLike | None = None,
    R: ArrayLike | None = None,
    p_robot_mm: ArrayLike | None = None,
    R_robot: ArrayLike | None = None,
    minimum_zone: bool = True,
    require_both: bool = False,
    max_gap_deg: float = 45.0,
) -> CircleResult:
    """The ISO 230-4 circular test of a measured path (method: the module docstring).

    Parameters
    ----------
    p_mm : (N, 3) float, mm
        Measured positions in time order (both directions, in any arrangement of runs).
    direction : (N,) "cw" / "ccw" strings, or bool (True = cw)
    radius_mm : float, mm
        The nominal radius R.
    centre_mm : (3,) float, mm, optional
        The nominal centre; gives the centre offset.
    R : (N, 3, 3) float, optional
        Measured orientations; gives the orientation deviation along the path.
    p_robot_mm : (N, 3) float, mm, optional
        The robot's commanded or reported positions at the same instants; gives
        ``robot_deviation_*_mm`` (the distance of each measured point from its own).
    R_robot : (N, 3, 3) float, optional
        The robot's commanded or reported orientations at the same instants (with ``R``): the
        orientation deviation is then measured against them (module docstring).
    minimum_zone : bool
        Also compute the minimum-zone figures (``G_mzc_*_mm``, ``centre_mzc_mm``).
    require_both : bool
        Raise ``SolveError(bad_input)`` if a direction is missing, rather than answer None for
        the bidirectional figures.
    max_gap_deg : float, deg
        The largest angular gap between a direction's points that still counts as covered.
    """
    p = np.asarray(p_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise bad_input(f"p_mm must have shape (N, 3), not {p.shape}.")
    p = finite(p, "p_mm", p.shape)
    N = len(p)
    if not (np.isfinite(radius_mm) and radius_mm > 0.0 and 0.0 < max_gap_deg < 360.0):
        raise bad_input(f"radius_mm must be > 0 and max_gap_deg in (0, 360), not {radius_mm}, {max_gap_deg}.")
    cw = _is_cw(direction, N)
    c_nom = None if centre_mm is None else finite(centre_mm, "centre_mm", (3,))
    Rs = None if R is None else finite(R, "R", (N, 3, 3))
    p_rob = None if p_robot_mm is None else finite(p_robot_mm, "p_robot_mm", (N, 3))
    R_rob = None if R_robot is None or Rs is None else finite(R_robot, "R_robot", (N, 3, 3))
    n_cw, n_ccw = int(cw.sum()), int(N - cw.sum())
    for label, n in (("cw", n_cw), ("ccw", n_ccw)):
        if 0 < n < MIN_POINTS or N == 0:
            raise SolveError(
                Reason.bad_input, f"{n} {label} points: the circular test needs at least {MIN_POINTS} per direction."
            )
    both = n_cw > 0 and n_ccw > 0
    notes: list[str] = []
    if not both:
        missing = "cw" if n_cw == 0 else "ccw"
        if require_both:
            raise SolveError(Reason.bad_input, f"no {missing} points: the bidirectional figures need both directions.")
        notes.append(f"no {missing} points: G_{missing}, G_bidirectional and H need both directions (None).")

    # 1. the plane, its 2-D coordinates, and 2. the common LSC
    _check_spread(p, "points")
    o = p.mean(axis=0)
    normal = np.linalg.svd(p - o)[2][2]
    e = np.eye(3)[0] if abs(normal[0]) < 0.9 else np.eye(3)[1]
    x_axis = (e - (e @ normal) * normal) / np.linalg.norm(e - (e @ normal) * normal)
    q = np.column_stack([(p - o) @ x_axis, (p - o) @ np.cross(normal, x_axis)])
    c, rho = _fit_circle(q, "points")
    t_cw, t_ccw = _signed_turn(q[cw], c), _signed_turn(q[~cw], c)
    if t_ccw - t_cw < 0.0:  # orient the normal: ccw turns positively about it
        normal, q, c, t_cw, t_ccw = -normal, q * [1.0, -1.0], c * [1.0, -1.0], -t_cw, -t_ccw
    if both and min(abs(t_cw), abs(t_ccw)) > np.pi / 2 and t_cw * t_ccw > 0:
        raise SolveError(Reason.bad_input, "the cw and the ccw points turn the same way: labels or time order wrong.")
    y_axis = np.cross(normal, x_axis)

    def in3d(c2: Array) -> Array:
        return np.asarray(o + c2[0] * x_axis + c2[1] * y_axis)

    # 3. the figures
    out: dict[str, Any] = {"radius_mm": float(radius_mm), "n_cw": n_cw, "n_ccw": n_ccw}
    for k, m in (("cw", cw), ("ccw", ~cw)):
        f = _fit_circle(q[m], f"{k} points") if m.any() else None
        mz = _min_zone(q[m], f[0]) if f is not None and minimum_zone else None
        out[f"G_{k}_mm"] = None if f is None else _span(q[m], f[0])
        out[f"centre_{k}_mm"] = None if f is None else in3d(f[0])
        out[f"radius_{k}_mm"] = None if f is None else f[1]
        out[f"G_mzc_{k}_mm"] = None if mz is None else mz[1]
    r = _radii(q, c)
    theta = np.mod(np.arctan2(q[:, 1] - c[1], q[:, 0] - c[0]), _TWO_PI)
    theta[theta >= _TWO_PI] = 0.0  # mod of -1e-17 rounds to 2 pi
    H = _hysteresis(theta, r, cw, np.radians(max_gap_deg)) if both else None
    if both and H is None:
        notes.append(f"the cw and ccw points share no angle (gaps <= {max_gap_deg:g} deg): H is None.")
    mz_all = _min_zone(q, c) if minimum_zone else None
    offset = None if c_nom is None else in3d(c) - c_nom
    dist = (p - o) @ normal
    ang: Array | None = None
    if Rs is not None and R_rob is not None:
        D = np.swapaxes(R_rob, -1, -2) @ Rs  # each point's rotation from its robot orientation
        ang = np.degrees(angle_between(R_mean(D), D))
    elif Rs is not None:
        ang = np.degrees(angle_between(R_mean(Rs), Rs))
    rob = None if p_rob is None else np.linalg.norm(p - p_rob, axis=1)
    radii = [x for x in (out["radius_cw_mm"], out["radius_ccw_mm"]) if x is not None]
    return CircleResult(
        **out,
        G_bidirectional_mm=float(r.max() - r.min()) if both else None,
        H_mm=H,
        F_max_mm=float(r.max() - radius_mm),
        F_min_mm=float(r.min() - radius_mm),
        mean_radial_deviation_mm=float(np.mean(radii) - radius_mm),
        G_mzc_bidirectional_mm=None if mz_all is None or not both else mz_all[1],
        out_of_plane_span_mm=float(np.ptp(dist)),
        out_of_plane_rms_mm=float(np.sqrt(np.mean(dist**2))),
        orientation_deviation_max_deg=None if ang is None else float(ang.max()),
        orientation_deviation_rms_deg=None if ang is None else float(np.sqrt(np.mean(ang**2))),
        robot_deviation_max_mm=None if rob is None else float(rob.max()),
        robot_deviation_rms_mm=None if rob is None else float(np.sqrt(np.mean(rob**2))),
        centre_offset_mm=offset,
        centre_offset_in_plane_mm=None if offset is None else float(np.linalg.norm(np.cross(offset, normal))),
        centre_offset_normal_mm=None if offset is None else float(offset @ normal),
        plane_normal=normal,
        theta_zero_axis=x_axis,
        centre_mm=in3d(c),
        radius_lsc_mm=rho,
        centre_mzc_mm=None if mz_all is None else in3d(mz_all[0]),
        centre_nominal_mm=c_nom,
        max_gap_deg=float(max_gap_deg),
        theta_rad=theta,
        radial_deviation_mm=r - radius_mm,
        out_of_plane_mm=dist,
        orientation_deviation_deg=ang,
        is_cw=cw,
        notes=tuple(notes),
    )


def _signed_turn(q: Array, c: Array) -> float:
    """The angle rad the points (n, 2) turn about c, in their order (positive: counter-clockwise)."""
    a = np.unwrap(np.arctan2(q[:, 1] - c[1], q[:, 0] - c[0]))
    return float(a[-1] - a[0]) if len(a) > 1 else 0.0


def circle_profile(result: CircleResult) -> dict[str, Any]:
    """What the polar plot of the test needs (ISO 230-4's plot, the seed paper's Figure 7), as JSON:
    :func:`radial_profile` of the result's own per-point arrays, centres and plane."""
    return radial_profile(
        result.theta_rad,
        result.radial_deviation_mm,
        result.is_cw,
        result.radius_mm,
        centre_mm=result.centre_mm,
        centre_cw_mm=result.centre_cw_mm,
        centre_ccw_mm=result.centre_ccw_mm,
        plane_normal=result.plane_normal,
        theta_zero_axis=result.theta_zero_axis,
        radius_lsc_mm=result.radius_lsc_mm,
    )


def radial_profile(
    theta_rad: ArrayLike,
    radial_deviation_mm: ArrayLike,
    is_cw: ArrayLike,
    radius_mm: float,
    *,
    centre_mm: ArrayLike,
    centre_cw_mm: ArrayLike | None,
    centre_ccw_mm: ArrayLike | None,
    plane_normal: ArrayLike,
    theta_zero_axis: ArrayLike,
    radius_lsc_mm: float,
) -> dict[str, Any]:
    """The polar plot's data from a :class:`CircleResult`'s fields (or their JSON: a report that
    kept ``to_dict(points=True)`` can be plotted after the fact), as JSON.

    Per direction present (``"cw"``, ``"ccw"``), in time order, each point's ``theta_deg`` and
    ``radial_deviation_mm`` (``r_i - R``) about the common centre in the plane, and the G
    envelope: the two circles about that direction's LSC centre through its nearest and farthest
    point, as ``envelope_inner_mm`` and ``envelope_outer_mm`` (their radii minus R: outer -
    inner = G of that direction) and ``centre_offset_mm`` (2,), that centre minus the common one
    along the plane's x (``theta_zero_axis``) and y (``plane_normal × x``). With both directions,
    ``"bidirectional"`` holds the envelope of all points about the common centre (inner = F_min,
    outer = F_max). Lengths in mm, rounded to 1 nm.

    A point's radius about a direction's centre is exact, not the limaçon approximation: the
    point is ``(R + dev) (cos θ, sin θ)`` from the common centre.
    """
    theta = np.asarray(theta_rad, dtype=np.float64)
    dev = np.asarray(radial_deviation_mm, dtype=np.float64)
    cw = np.asarray(is_cw, dtype=np.bool_)
    if not theta.shape == dev.shape == cw.shape or theta.ndim != 1:
        raise bad_input(f"theta, deviation and direction need one value per point, not {theta.shape}, {dev.shape}.")
    normal = np.asarray(plane_normal, dtype=np.float64)
    x_axis = np.asarray(theta_zero_axis, dtype=np.float64)
    c = np.asarray(centre_mm, dtype=np.float64)
    axes = np.stack([x_axis, np.cross(normal, x_axis)])  # (2, 3): the plane's x and y
    R = float(radius_mm)
    q = (R + dev)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])  # (N, 2) about the common centre

    def rounded(x: Any) -> Any:
        a = np.round(np.asarray(x, dtype=np.float64), 6) + 0.0  # + 0.0: no -0.0
        return a.tolist() if a.ndim else float(a)

    def envelope(points: Array, offset: Array) -> dict[str, Any]:
        r = np.hypot(points[:, 0] - offset[0], points[:, 1] - offset[1])
        return {
            "centre_offset_mm": rounded(offset),
            "envelope_inner_mm": rounded(r.min() - R),
            "envelope_outer_mm": rounded(r.max() - R),
        }

    out: dict[str, Any] = {"radius_mm": R, "radius_lsc_mm": rounded(radius_lsc_mm), "centre_mm": rounded(c)}
    for k, m, c_k in (("cw", cw, centre_cw_mm), ("ccw", ~cw, centre_ccw_mm)):
        if c_k is None or not m.any():
            continue
        offset = axes @ (np.asarray(c_k, dtype=np.float64) - c)
        out[k] = {
            "theta_deg": rounded(np.degrees(theta[m])),
            "radial_deviation_mm": rounded(dev[m]),
            **envelope(q[m], offset),
        }
    if "cw" in out and "ccw" in out:
        out["bidirectional"] = envelope(q, np.zeros(2))
    return out
