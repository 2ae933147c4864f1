"""Camera self-calibration and field survey by bundle adjustment (the paper's "calibration by the first start").

Unknowns: the Brown/Fraser interior orientation (any subset of c, x0, y0, K1-K3,
P1, P2, B1, B2), every image's exterior orientation and the coordinates of the
targets. The camera model is :class:`~service.core.geometry.camera_model.BrownFraser`
itself (the correction runs from measured to ideal coordinates), so the result
is directly the pipeline's ``camera.json``.

Datum (:class:`Datum`): either control points (their field coordinates fixed, or
weighted by ``control_sigma_mm``), or, with no control points, the nominal
field with inner constraints (a free network: the adjusted targets keep the
nominal field's centroid, orientation and, without a scale bar, its scale; the
minimum-norm covariance) plus any measured distances (:class:`ScaleBar`).
Targets seen in the images but missing from the field are new points: their
start values come from forward intersection, and they are surveyed too.
The network's points and observations, the datum's rows and the checks of both (every
image, every control point and scale bar) are :mod:`service.core.calib.bundle_network`'s,
which the rig's calibration (:mod:`service.core.calib.rig`) shares.

Start values: the closed-form resection of the engine, then its least-squares
refinement (:func:`service.core.pose.resection.resect`), image by image, and forward
intersection (:mod:`service.core.calib.bundle_solve`). The adjustment, gross-error
rejection (soft-L1 pass, then data snooping) and covariance are described there.

A network that cannot separate the interior orientation from the exterior one
is refused with :class:`~service.core.results.SolveError` ``degenerate_geometry``:
too few images, all images looking at a planar field head-on, a free interior
parameter that is numerically a combination of the other unknowns, or c or the
principal point known to worse than :data:`MAX_RELATIVE_SIGMA` (of c, of the sensor
diagonal) -- what a network without convergence or without roll gives; the message
says why (the tilt and roll spread of the views) and what to add (convergent views,
views rolled by 90 degrees). A weak roll diversity short of that is a warning.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.calib.bundle_model import RESIDUAL_SPACES
from service.core.calib.bundle_network import (
    Datum,
    ImagePoints,
    Network,
    ScaleBar,
    adjusted_points,
    check_free,
    collect,
    datum_rows,
    interior_sigmas,
    left_out_warnings,
    network_field,
    point_sigmas,
)
from service.core.calib.bundle_solve import (
    NetworkInput,
    NetworkSolution,
    Progress,
    T_field_view,
    Views,
    orient_views,
    params_from_T,
    pose_sigmas,
    solve_network,
)
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.geometry.frames import inv_T
from service.core.results import Reason, SolveError
from service.core.targets.field import Field

Array = NDArray[np.float64]

#: A free interior parameter with less than this fraction of its information left once the other
#: unknowns are estimated (``1 - rho**2``, rho its global correlation) is numerically undetermined.
MIN_INFORMATION_FRACTION = 1e-10
#: Largest accepted standard deviation of c, as a fraction of c, and of the principal point,
#: as a fraction of the sensor diagonal: beyond them the network does not determine the camera.
MAX_RELATIVE_SIGMA = 0.005
#: Pairs of interior parameters correlated above this get a warning.
WARN_CORRELATION = 0.95
#: All images within this angle of the normal of a planar field: c and the distance are one unknown.
PARALLEL_TILT_DEG = 5.0
#: Below this spread of the images' roll about their optical axes the network has no roll diversity.
MIN_ROLL_SPREAD_DEG = 45.0
MIN_IMAGES = 3
#: The default datum: inner constraints on the nominal field, its scale.
FREE_NETWORK = Datum()


@dataclass(frozen=True)
class ImageResult:
    """One image after the adjustment: pose, its precision and the fit of its targets.

    ``sigma_rotation_deg`` about, and ``sigma_position_mm`` along, the field axes;
    ``rms_px`` per coordinate over the image's inliers.
    """

    name: str
    T_field_camera: Array
    sigma_position_mm: Array
    sigma_rotation_deg: Array
    rms_px: float
    n_points: int
    n_rejected: int


@dataclass(frozen=True)
class BundleResult:
    """The self-calibration.

    Attributes
    ----------
    camera : BrownFraser
        The calibrated interior orientation, ``sigma`` set (0 for fixed parameters).
    free : tuple of str
        The estimated parameters (order of :data:`PARAMETER_NAMES`).
    sigma : dict str -> float
        Standard deviation of every parameter (0 if fixed), units of the parameter.
    correlation : (k, k) float
        Correlation matrix of the free parameters.
    sigma0_px : float
        A-posteriori standard deviation of an image coordinate, px.
    redundancy : int
    images : tuple of ImageResult
        The oriented images (images that could not be oriented are in ``warnings``).
    field : Field
        Adjusted target coordinates (targets of the network; new points appended).
    sigma_xyz_mm : (N, 3) float
        Standard deviations of ``field.xyz`` (0 for fixed control points).
    n_rays : (N,) int
        Inlier observations of each target.
    target_rms_px : (N,) float
        RMS of each target's inlier residuals, px.
    image_index, ids, uv, residuals_px, inliers
        Every observation: image (M,), target id (M,), measured px (M, 2), measured minus
        computed px (M, 2) and whether it was kept (M,).
    warnings : tuple of str
    """

    camera: BrownFraser
    free: tuple[str, ...]
    sigma: dict[str, float]
    correlation: Array
    sigma0_px: float
    redundancy: int
    images: tuple[ImageResult, ...]
    field: Field
    sigma_xyz_mm: Array
    n_rays: NDArray[np.int64]
    target_rms_px: Array
    image_index: NDArray[np.int64]
    ids: tuple[str, ...]
    uv: Array
    residuals_px: Array
    inliers: NDArray[np.bool_]
    warnings: tuple[str, ...]
    datum: dict[str, Any] = dataclasses.field(default_factory=dict)
    residual_space: str = "pixel"
    n_iter: int = 0
    converged: bool = True
    initial_cost: float = float("nan")
    final_cost: float = float("nan")

    @property
    def n_observations(self) -> int:
        return len(self.inliers)

    @property
    def n_rejected(self) -> int:
        return int(np.sum(~self.inliers))

    def rejected(self) -> list[dict[str, Any]]:
        """The rejected observations: image name, target id, measured uv and residual, px."""
        out = []
        for k in np.flatnonzero(~self.inliers):
            out.append(
                {
                    "image": self.images[self.image_index[k]].name,
                    "id": self.ids[k],
                    "uv": [round(float(v), 4) for v in self.uv[k]],
                    "residual_px": [round(float(v), 4) for v in self.residuals_px[k]],
                }
            )
        return out

    def report(self) -> dict[str, Any]:
        """The ``calibration`` block of ``camera.json``: quality, correlations, residuals, rejections."""

        def r(v: float, nd: int = 6) -> float:
            return round(float(v), nd)

        return {
            "method": "self-calibrating bundle adjustment (posecell)",
            "sigma0_px": r(self.sigma0_px),
            "redundancy": self.redundancy,
            "residual_space": self.residual_space,
            "n_images": len(self.images),
            "n_targets": len(self.field),
            "n_observations": self.n_observations,
            "n_rejected": self.n_rejected,
            "free": list(self.free),
            "fixed": [n for n in PARAMETER_NAMES if n not in self.free],
            "correlation": {"names": list(self.free), "matrix": [[r(v, 4) for v in row] for row in self.correlation]},
            "datum": self.datum,
            "outliers": "soft-L1 first pass, then iterative data snooping (chi-square, 2 dof, "
            "alpha 1e-5 per observation) with re-admission",
            "warnings": list(self.warnings),
            "images": [
                {
                    "name": im.name,
                    "rms_px": r(im.rms_px, 5),
                    "n_points": im.n_points,
                    "n_rejected": im.n_rejected,
                    "sigma_position_mm": [r(v) for v in im.sigma_position_mm],
                    "sigma_rotation_deg": [r(v, 8) for v in im.sigma_rotation_deg],
                    "T_field_camera": [[r(v, 9) for v in row] for row in im.T_field_camera],
                }
                for im in self.images
            ],
            "targets": [
                {
                    "id": tid,
                    "n_rays": int(self.n_rays[i]),
                    "rms_px": r(self.target_rms_px[i], 5),
                    "sigma_mm": [r(v) for v in self.sigma_xyz_mm[i]],
                }
                for i, tid in enumerate(self.field.ids)
            ],
            "rejected": self.rejected(),
            "n_iter": self.n_iter,
            "converged": self.converged,
        }


# -- inputs -------------------------------------------------------------------------


def _too_few_images(n: int, what: str) -> SolveError:
    return SolveError(
        Reason.degenerate_geometry,
        f"Self-calibration needs at least {MIN_IMAGES} {what}images, got {n}: take 8 or more "
        f"convergent views from different sides, some rolled by 90 degrees.",
        {"n_images": n},
    )


# -- geometry diagnostics -------------------------------------------------------------


def network_geometry(points: Array, T_field_camera: Sequence[Array]) -> dict[str, float]:
    """Shape of the network, for the diagnosis of a degenerate one.

    ``flatness``: smallest over largest spread of the points (0: planar).
    ``max_tilt_deg``: largest angle between an optical axis and the points' normal
    (their direction of least spread). ``roll_spread_deg``: spread of the images'
    roll about their optical axes modulo 180 deg (0..180: how much of a half-turn the rolls
    cover; a roll by 90 deg is what separates the principal point and affinity from the
    exterior orientation); the
    roll of an image is the direction of the normal, or of the points' main axis for
    an image looking along the normal, in the image.
    """
    q = points - points.mean(axis=0)
    _, s, Vt = np.linalg.svd(q, full_matrices=False)
    normal, main = Vt[2], Vt[0]
    axes = np.array([T[:3, 2] for T in T_field_camera]).reshape(-1, 3)
    tilt = np.degrees(np.arccos(np.clip(np.abs(axes @ normal), 0.0, 1.0)))
    rolls = []
    for T in T_field_camera:
        x, y, z = T[:3, 0], T[:3, 1], T[:3, 2]
        d = normal - (normal @ z) * z
        if np.linalg.norm(d) < np.sin(np.radians(10.0)):
            d = main - (main @ z) * z
        rolls.append(np.degrees(np.arctan2(d @ x, d @ y)))
    doubled = np.sort((2.0 * np.array(rolls)) % 360.0)  # modulo 180 deg, on a full circle
    gaps = np.diff(np.r_[doubled, doubled[:1] + 360.0]) if len(doubled) else np.array([360.0])
    return {
        "flatness": float(s[2] / max(s[0], 1e-12)),
        "max_tilt_deg": float(tilt.max()) if len(tilt) else 0.0,
        "roll_spread_deg": float((360.0 - gaps.max()) / 2.0),
    }


def _advice(geometry: dict[str, float]) -> str:
    why = []
    if geometry["max_tilt_deg"] < 20.0:
        why.append(
            f"the views hardly converge (largest tilt from the field's normal {geometry['max_tilt_deg']:.1f} deg)"
        )
    if geometry["roll_spread_deg"] < MIN_ROLL_SPREAD_DEG:
        why.append(f"the images are not rolled (roll spread {geometry['roll_spread_deg']:.0f} deg)")
    reason = (", because " + " and ".join(why)) if why else ""
    return f"{reason}: add convergent views (tilted 20-45 deg from different sides) and views rolled by 90 degrees"


# -- the calibration -----------------------------------------------------------------------


def calibrate_camera(
    camera: BrownFraser,
    field: Field,
    images: Sequence[ImagePoints],
    *,
    free: Sequence[str] = PARAMETER_NAMES,
    datum: Datum = FREE_NETWORK,
    sigma_px: float = 0.1,
    residual_space: str = "pixel",
    reject_outliers: bool = True,
    progress: Progress | None = None,
) -> BundleResult:
    """Self-calibrating bundle adjustment of one camera from images of a target field.

    Parameters
    ----------
    camera : BrownFraser
        Start values of the interior orientation; its size and pixel size are kept.
    field : Field
        Nominal (or control) coordinates of the targets, mm.
    images : sequence of ImagePoints
        Identified targets of each image; ids missing from ``field`` are new points.
    free : sequence of str
        Parameters to estimate (default all ten); the others keep ``camera``'s values.
    datum : Datum
    sigma_px : float
        A-priori precision of an image coordinate, px: weighs the images against
        weighted control points and scale bars; sigma0 is reported in px regardless.
    residual_space : {"pixel", "ideal"}
        Minimize measured-minus-predicted pixels (default; exact for isotropic
        image noise), or ideal-coordinate residuals over the pixel size (the
        classical photogrammetric form of DBAT and PhotoModeler).
    reject_outliers : bool
    progress : callable str -> None, optional
        Called with a short status line at each stage and iteration.

    Returns
    -------
    BundleResult

    Raises
    ------
    SolveError
        ``degenerate_geometry`` (too few images, a network that does not determine
        the interior orientation), ``bad_input`` (a datum that does not fix the frame,
        unknown ids), ``behind_camera``, ``too_few_targets``.
    """
    free_t = check_free(free)
    if residual_space not in RESIDUAL_SPACES:
        raise ValueError(f"residual_space must be one of {RESIDUAL_SPACES}, got {residual_space!r}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    if len(images) < MIN_IMAGES:
        raise _too_few_images(len(images), "")
    warnings: list[str] = []
    net = collect(field, images)
    say = progress or (lambda _s: None)
    say(f"start values: resecting {len(images)} images")
    T_init = [None if im.T_field_camera is None else np.asarray(im.T_field_camera, dtype=np.float64) for im in images]
    views = Views(net.image, net.point, net.uv, len(images))
    T0, p0 = orient_views([camera], np.zeros(len(images), np.int64), views, net.nominal, T_init)
    oriented = np.array([T is not None for T in T0])
    for j in np.flatnonzero(~oriented):
        warnings.append(f"image {images[int(j)].name!r} could not be oriented (too few known targets) and is left out")
    if oriented.sum() < MIN_IMAGES:
        raise _too_few_images(int(oriented.sum()), "oriented ")
    known = np.all(np.isfinite(p0), axis=1)
    warnings += left_out_warnings(net, p0)
    keep = oriented[net.image] & known[net.point]
    img_map = np.cumsum(oriented) - 1
    station = img_map[net.image[keep]]
    point, uv = net.point[keep], net.uv[keep]
    kept_images = [images[int(j)] for j in np.flatnonzero(oriented)]
    stations = np.array([params_from_T(inv_T(T)) for T in T0 if T is not None])

    rows = datum_rows(datum, field, net, p0)  # the datum and the scale bars, checked

    # -- degenerate networks that no adjustment can fix
    T_start = [T for T in T0 if T is not None]
    geometry = network_geometry(rows.points[np.unique(point)], T_start)
    if "c_mm" in free_t and geometry["flatness"] < 1e-3 and geometry["max_tilt_deg"] < PARALLEL_TILT_DEG:
        raise SolveError(
            Reason.degenerate_geometry,
            f"All images look at the planar field head-on (largest tilt {geometry['max_tilt_deg']:.1f} deg), so "
            f"the principal distance cannot be told from the distance: add convergent views tilted 20-45 deg "
            f"from different sides, and views rolled by 90 degrees.",
            geometry,
        )

    network = NetworkInput(
        cameras=(camera,),
        free_interior=(free_t,),
        station=station,
        camera=np.zeros(len(station), np.int64),
        point=point,
        uv=uv,
        stations=stations,
        offsets=np.zeros((0, 6)),
        offsets_free=False,
        points=rows.points,
        point_free=rows.point_free,
        control=rows.control,
        bars=rows.bars,
        inner=rows.inner,
        residual_space=residual_space,
        sigma_px=float(sigma_px),
    )
    say(f"adjusting {len(kept_images)} images, {len(net.ids)} targets, {len(uv)} observations")
    sol = solve_network(network, reject_outliers=reject_outliers, progress=progress)
    _check_determined(sol, free_t, geometry, camera)
    return _result(sol, network, net, kept_images, free_t, datum, warnings, field)


def _check_determined(
    sol: NetworkSolution, free_t: tuple[str, ...], geometry: dict[str, float], camera: BrownFraser
) -> None:
    rho = sol.global_correlation[sol.model.int_cols[0]]
    bad = [n for n, r in zip(free_t, rho, strict=True) if 1.0 - r * r < MIN_INFORMATION_FRACTION]
    cols = sol.model.int_cols[0]
    sd = dict(zip(free_t, np.sqrt(np.clip(np.diag(sol.Q)[cols], 0.0, None)) * sol.sigma0, strict=True))
    diagonal = float(np.hypot(camera.width * camera.pixel_size_mm[0], camera.height * camera.pixel_size_mm[1]))
    weak = []
    if "c_mm" in sd and sd["c_mm"] > MAX_RELATIVE_SIGMA * camera.c_mm:
        weak.append(f"c (sigma {sd['c_mm']:.3g} mm)")
    for n in ("x0_mm", "y0_mm"):
        if n in sd and sd[n] > MAX_RELATIVE_SIGMA * diagonal:
            weak.append(f"{n[:2]} (sigma {sd[n]:.3g} mm)")
    if bad or weak:
        what = ", ".join(bad) if bad else ", ".join(weak)
        raise SolveError(
            Reason.degenerate_geometry,
            f"The images do not determine the camera's {what}{_advice(geometry)}.",
            {**geometry, "undetermined": bad, "weak": weak},
        )


def _result(
    sol: NetworkSolution,
    network: NetworkInput,
    net: Network,
    kept: list[ImagePoints],
    free_t: tuple[str, ...],
    datum: Datum,
    warnings: list[str],
    field: Field,
) -> BundleResult:
    model, Q, s0 = sol.model, sol.Q, sol.sigma0
    cov_scale = s0 * s0
    cols = model.int_cols[0]
    C = Q[np.ix_(cols, cols)] * cov_scale
    sd = np.sqrt(np.diag(C))
    corr = C / np.outer(sd, sd)
    sigma = interior_sigmas(sol, 0, free_t)
    cam = dataclasses.replace(sol.cameras[0], sigma=sigma)
    for a in range(len(free_t)):
        for b in range(a + 1, len(free_t)):
            if abs(corr[a, b]) > WARN_CORRELATION:
                warnings.append(f"{free_t[a]} and {free_t[b]} are correlated at {corr[a, b]:+.3f}")
    inl = sol.inliers
    res = sol.residuals_px
    images = []
    for j, im in enumerate(kept):
        m = network.station == j
        c0 = model.station_col0 + 6 * j
        sig_rot, sig_pos = pose_sigmas(sol.stations[j], Q[c0 : c0 + 6, c0 : c0 + 6] * cov_scale)
        mi = m & inl
        rms = float(np.sqrt(np.mean(res[mi] ** 2))) if mi.any() else float("nan")
        images.append(
            ImageResult(
                im.name,
                T_field_view(sol.stations, sol.offsets, j, 0),
                sig_pos,
                sig_rot,
                rms,
                int(m.sum()),
                int((m & ~inl).sum()),
            )
        )
    n_pts = len(net.ids)
    sig_xyz = point_sigmas(sol, network.point_free)
    n_rays = np.bincount(network.point[inl], minlength=n_pts)
    ss = np.bincount(network.point[inl], weights=np.sum(res[inl] ** 2, axis=1), minlength=n_pts)
    target_rms = np.sqrt(ss / np.maximum(2 * n_rays, 1))
    target_rms[n_rays == 0] = np.nan
    for i in np.flatnonzero(network.point_free & ~sol.point_used).tolist():
        warnings.append(
            f"target {net.ids[i]!r} has fewer than two rays (after rejections): not adjusted, left out of the field"
        )
    refined = network_field(field.name, net, sol.points, field)
    has_xyz = adjusted_points(sol.points)  # the rows of refined
    geometry = network_geometry(sol.points[sol.point_used], [im.T_field_camera for im in images])
    if geometry["roll_spread_deg"] < MIN_ROLL_SPREAD_DEG and {"x0_mm", "y0_mm", "B1", "B2"} & set(free_t):
        warnings.append(
            f"the images are hardly rolled (roll spread {geometry['roll_spread_deg']:.0f} deg): "
            f"the principal point and affinity are weakly determined; add views rolled by 90 degrees"
        )
    n_rej = int(np.sum(~inl))
    if n_rej > 0.05 * len(inl):
        warnings.append(f"{n_rej} of {len(inl)} observations ({100 * n_rej / len(inl):.1f} %) were rejected")
    ids_obs = tuple(net.ids[i] for i in network.point)
    return BundleResult(
        camera=cam,
        free=free_t,
        sigma=sigma,
        correlation=corr,
        sigma0_px=s0 * network.sigma_px,
        redundancy=sol.redundancy,
        images=tuple(images),
        field=refined,
        sigma_xyz_mm=sig_xyz[has_xyz],
        n_rays=n_rays[has_xyz],
        target_rms_px=target_rms[has_xyz],
        image_index=network.station.copy(),
        ids=ids_obs,
        uv=network.uv.copy(),
        residuals_px=res,
        inliers=inl,
        warnings=tuple(warnings),
        datum=datum.describe(),
        residual_space=network.residual_space,
        n_iter=sol.n_iter,
        converged=sol.converged,
        initial_cost=sol.initial_cost,
        final_cost=sol.final_cost,
    )


__all__ = ["BundleResult", "Datum", "ImagePoints", "ImageResult", "ScaleBar", "calibrate_camera", "network_geometry"]
