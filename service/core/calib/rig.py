"""Calibration of a multi-camera rig: the relative orientation of 2..K rigidly mounted cameras.

Simultaneous images of a target field by every camera of the rig (one *epoch*
per exposure) are adjusted as one bundle with the rig constraint: the pose of
camera k at epoch e is ``T_field_camerak(e) = T_field_rig(e) @ T_rig_camerak``,
the rig frame being camera 0's (the master camera of
:class:`~service.core.pose.intersection.Rig`). The unknowns are each epoch's
``T_field_rig``, the K - 1 relative orientations ``T_master_camerak`` and, if
asked, the cameras' interior orientations and the field's targets.

By default the field is taken as calibrated (its targets fixed: they give the
frame and the scale of the baselines); ``field_fixed=False`` adjusts the targets
too, with the datum of :func:`service.core.calib.bundle.calibrate_camera` (inner
constraints on the nominal field, its scale or that of scale bars, or control points).

The network is the bundle's: its points, observations, datum and scale bars and the
checks of all of them come from :mod:`service.core.calib.bundle_network` (a fixed field
is the datum whose control points are all the field's targets), the parameter blocks,
adjustment and gross-error rejection from :mod:`service.core.calib.bundle_solve`. What is
the rig's own: every image is resected on its own for the start values; each relative
orientation starts as the mean over the epochs in which camera 0 and camera k were both
resected (rotations averaged by ``scipy.spatial.transform.Rotation.mean``); and the
jackknife below.

Uncertainty. The formal covariance ``sigma0^2 Q`` treats every image coordinate as an
independent error of the detector's size. A rig's epochs also carry errors that are
common to a whole exposure and that the model lacks: the cameras not exposing at
the same instant while the rig moves, the rig flexing as it is turned, distortion the
camera model leaves out (the same targets land on similar image regions within an
epoch), the fixed field's own error. They move the relative orientation from epoch
to epoch, average down only with the number of epochs (not the number of targets),
and so the formal sigma can be several times too small (3.5-4.4x on a real panel rig).
Hence the delete-one-epoch jackknife (Efron & Stein 1981; Efron 1982, ch. 3): the
network is re-adjusted n times, each time without one epoch, and

    sigma_jk = sqrt((n - 1) / n * sum_i (theta_i - mean(theta))^2)

for every component of every ``T_master_camera``. It sees whatever makes the epochs
disagree, modelled or not, at the price of its own sampling error (about
``1 / sqrt(2 (n - 1))`` relative: 24 % with 10 epochs). The reported sigma is
``max(formal, jackknife)`` per component: the jackknife when the epochs disagree more
than the image noise explains, the formal one when a jackknife from few epochs came
out small by chance. Both are kept in the result (``sigma_source`` says which rule).
Each re-adjustment starts from the full solution and keeps its inliers: it converges
in a few steps, and the jackknife sees the epochs' disagreement rather than a
different choice of outliers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.calib.bundle_network import (
    Datum,
    ImagePoints,
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
    T_from_params,
    Views,
    orient_views,
    params_from_T,
    pose_sigmas,
    resect_view,
    solve_network,
)
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T, inv_T, make_T
from service.core.geometry.so3 import R_mean, rotvec_from_R
from service.core.pose.intersection import Rig
from service.core.results import Reason, SolveError
from service.core.targets.field import Field

Array = NDArray[np.float64]

#: Fewest epochs for a leave-one-epoch-out (jackknife) sigma; with fewer the formal one is reported.
MIN_JACKKNIFE_EPOCHS = 3
#: Jackknife over formal sigma above which the calibration warns of epoch-wise errors.
EPOCH_ERROR_WARN_RATIO = 2.0


@dataclass(frozen=True)
class RigImage:
    """Identified targets in the image of camera ``camera`` taken at epoch ``epoch``."""

    epoch: str
    camera: int
    ids: tuple[str, ...]
    uv: Array
    name: str = ""


@dataclass(frozen=True)
class RigCalibration:
    """The calibrated rig.

    Attributes
    ----------
    rig : Rig
        Cameras (interior orientations, refined if they were free) and ``T_master_camera``
        (K, 4, 4): the pose of each camera in camera 0's frame.
    sigma_rotation_deg, sigma_position_mm : (K, 3) float
        Standard deviations of each ``T_master_camera``: rotation about, and origin along,
        camera 0's axes (zeros for camera 0). As ``sigma_source`` says: ``max(formal, jackknife)``
        per component, or ``formal`` when no jackknife could be made.
    sigma_rotation_formal_deg, sigma_position_formal_mm : (K, 3) float
        The same from the adjustment's covariance ``sigma0^2 Q``.
    sigma_rotation_jackknife_deg, sigma_position_jackknife_mm : (K, 3) float
        The same from the leave-one-epoch-out re-adjustments (NaN if none were made).
    sigma_source : str
        ``"max(formal, jackknife)"`` or ``"formal"``.
    sigma_interior : tuple of dict
        Standard deviation of each camera's parameters (0 where fixed).
    sigma0_px : float
    redundancy : int
    rms_px : (K,) float
        RMS of each camera's inlier residuals per coordinate.
    n_observations, n_rejected : (K,) int
    epochs : tuple of str
        The epochs adjusted; ``T_field_rig`` (E, 4, 4) their rig poses.
    field : Field
        The targets (adjusted if the field was free); ``sigma_xyz_mm`` (N, 3).
    warnings : tuple of str
    """

    rig: Rig
    sigma_rotation_deg: Array
    sigma_position_mm: Array
    sigma_interior: tuple[dict[str, float], ...]
    sigma0_px: float
    redundancy: int
    rms_px: Array
    n_observations: NDArray[np.int64]
    n_rejected: NDArray[np.int64]
    epochs: tuple[str, ...]
    T_field_rig: Array
    field: Field
    sigma_xyz_mm: Array
    sigma_rotation_formal_deg: Array
    sigma_position_formal_mm: Array
    sigma_rotation_jackknife_deg: Array
    sigma_position_jackknife_mm: Array
    sigma_source: str
    warnings: tuple[str, ...] = ()
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """``rig.json``: what :func:`rig_from_dict` (and so :class:`Rig`) needs, plus the quality."""

        def r(v: float, nd: int = 6) -> float | None:
            return round(float(v), nd) if np.isfinite(v) else None  # JSON has no NaN

        def sigmas(rot: Array, pos: Array) -> dict[str, Any]:
            return {
                "rotation_deg": [[r(v, 8) for v in s] for s in rot],
                "position_mm": [[r(v) for v in s] for s in pos],
            }

        cams = []
        for cam, sig in zip(self.rig.cameras, self.sigma_interior, strict=True):
            d = cam.to_dict()
            d["sigma"] = {k: r(v, 9) for k, v in sig.items()}
            cams.append(d)
        return {
            "model": "rig",
            "master": 0,
            "cameras": cams,
            "T_master_camera": [[[r(v, 9) for v in row] for row in T] for T in self.rig.T_master_camera],
            "sigma_rotation_deg": [[r(v, 8) for v in s] for s in self.sigma_rotation_deg],
            "sigma_position_mm": [[r(v) for v in s] for s in self.sigma_position_mm],
            "calibration": {
                "method": "bundle adjustment with the rig constraint (posecell)",
                "sigma0_px": r(self.sigma0_px),
                "redundancy": self.redundancy,
                "n_epochs": len(self.epochs),
                "sigma_source": self.sigma_source,
                "sigma_formal": sigmas(self.sigma_rotation_formal_deg, self.sigma_position_formal_mm),
                "sigma_jackknife": sigmas(self.sigma_rotation_jackknife_deg, self.sigma_position_jackknife_mm),
                "cameras": [
                    {
                        "rms_px": r(self.rms_px[k], 5),
                        "n_observations": int(self.n_observations[k]),
                        "n_rejected": int(self.n_rejected[k]),
                    }
                    for k in range(self.rig.n_cameras)
                ],
                "warnings": list(self.warnings),
                **self.extra,
            },
        }


def rig_from_dict(d: dict[str, Any]) -> Rig:
    """The :class:`Rig` of a ``rig.json`` (:meth:`RigCalibration.to_dict`); raises ``ValueError``."""
    if not isinstance(d, dict) or d.get("model", "rig") != "rig":
        raise ValueError("a rig must be a JSON object with model 'rig'")
    try:
        cams = tuple(BrownFraser.from_dict(c) for c in d["cameras"])
        T = np.array(d["T_master_camera"], dtype=np.float64)
    except KeyError as e:
        raise ValueError(f"rig is missing the key {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise ValueError(f"rig has a malformed value: {e}") from None
    return Rig(cams, T)


def _start_offsets(T_view: dict[tuple[int, int], Array], n_cam: int) -> list[Array]:
    """``T_camerak_rig`` (k >= 1) averaged over the epochs in which camera 0 and camera k were resected."""
    out = []
    for k in range(1, n_cam):
        rel = [inv_T(T_view[(e, k)]) @ T_view[(e, 0)] for (e, kk) in T_view if kk == k and (e, 0) in T_view]
        if not rel:
            raise SolveError(
                Reason.too_few_targets, f"Camera {k} never sees enough known targets at the same time as camera 0."
            )
        out.append(make_T(R_mean(np.array([T[:3, :3] for T in rel])), np.mean([T[:3, 3] for T in rel], axis=0)))
    return out


def _image_points(im: RigImage) -> ImagePoints:
    """The bundle's form of a rig image, named for messages even without a name of its own."""
    return ImagePoints(im.name or f"camera {im.camera} at epoch {im.epoch!r}", im.ids, im.uv)


def calibrate_rig(
    cameras: Sequence[BrownFraser],
    field: Field,
    images: Sequence[RigImage],
    *,
    free_interior: Sequence[str] = (),
    field_fixed: bool = True,
    datum: Datum | None = None,
    T_master_camera_init: Sequence[Array] | None = None,
    sigma_px: float = 0.1,
    reject_outliers: bool = True,
    jackknife: bool = True,
    progress: Progress | None = None,
) -> RigCalibration:
    """Relative orientation of a rig of ``len(cameras)`` cameras from simultaneous images of a field.

    Parameters
    ----------
    cameras : sequence of BrownFraser, K >= 2
        The cameras' interior orientations (camera 0 is the master).
    field : Field
        Target coordinates, mm.
    images : sequence of RigImage
        Identified targets of every image; images of one exposure share their ``epoch``.
    free_interior : sequence of str
        Interior parameters to refine for every camera (default none: the cameras are calibrated).
    field_fixed : bool
        Keep the field's targets fixed (default: they are the control points) or adjust them too.
    datum : Datum, optional
        With ``field_fixed=False``, the datum as for :func:`service.core.calib.bundle.calibrate_camera`
        (default: inner constraints on the nominal field). Its scale bars are checked and used either way
        (between two fixed targets a bar adds nothing); control points need ``field_fixed=False``.
    T_master_camera_init : sequence of (4, 4), optional
        Start values of the relative orientations (default: from per-image resections).
    sigma_px, reject_outliers, progress
        As for :func:`service.core.calib.bundle.calibrate_camera`.
    jackknife : bool
        Re-adjust without each epoch in turn and report ``max(formal, jackknife)`` sigmas (default;
        n more adjustments, each warm-started) or the formal ones only.

    Raises
    ------
    SolveError
        ``too_few_targets`` (a camera never oriented together with camera 0),
        ``degenerate_geometry`` (singular normal equations), ``bad_input`` (an image naming a camera
        the rig lacks, a target twice or non-finite pixels; a scale bar on a target no image saw, or
        without a positive distance and sigma; a datum that does not fix the frame).
    ValueError
        Fewer than 2 cameras, unknown interior parameters, control points with ``field_fixed``.
    """
    K = len(cameras)
    if K < 2:
        raise ValueError(f"a rig needs at least 2 cameras, got {K}")
    free_t = check_free(free_interior)
    if field_fixed and datum is not None and datum.control:
        raise ValueError("control points are for field_fixed=False: a fixed field's targets are all control points")
    for im in images:
        if not 0 <= im.camera < K:
            raise SolveError(
                Reason.bad_input,
                f"Image {im.name or im.epoch!r} names camera {im.camera}, but the rig has {K} cameras.",
            )
    net = collect(field, [_image_points(im) for im in images])
    epochs = list(dict.fromkeys(im.epoch for im in images))
    view_epoch = np.array([epochs.index(im.epoch) for im in images], dtype=np.int64)
    view_cam = np.array([im.camera for im in images], dtype=np.int64)
    say = progress or (lambda _s: None)

    # -- start values: every image resected on its own
    say(f"start values: resecting {len(images)} images")
    in_field: NDArray[np.bool_] = np.all(np.isfinite(net.nominal), axis=1)
    T_view: dict[tuple[int, int], Array] = {}
    for j, im in enumerate(images):
        m = np.flatnonzero(net.image == j)
        m = m[in_field[net.point[m]]]
        T = resect_view(cameras[im.camera], net.nominal[net.point[m]], net.uv[m])
        if T is not None:
            T_view[(int(view_epoch[j]), im.camera)] = T
    if T_master_camera_init is not None:
        offsets_T = [inv_T(check_T(T, "T_master_camera_init")) for T in list(T_master_camera_init)[1:]]
    else:
        offsets_T = _start_offsets(T_view, K)
    warnings: list[str] = []
    stations, keep_epoch = [], []
    for e in range(len(epochs)):
        T_rig_field = None
        for k in range(K):
            if (e, k) in T_view:
                T_camk_field = inv_T(T_view[(e, k)])
                T_rig_field = T_camk_field if k == 0 else inv_T(offsets_T[k - 1]) @ T_camk_field
                break
        if T_rig_field is None:
            warnings.append(f"epoch {epochs[e]!r} could not be oriented and is left out")
        else:
            keep_epoch.append(e)
            stations.append(params_from_T(T_rig_field))
    if not keep_epoch:
        raise SolveError(Reason.too_few_targets, "No epoch could be oriented from the field's targets.")
    e_map = -np.ones(len(epochs), dtype=np.int64)
    e_map[keep_epoch] = np.arange(len(keep_epoch))
    stations_a = np.array(stations)
    offsets = np.array([params_from_T(T) for T in offsets_T]).reshape(-1, 6)

    # -- observations of the oriented epochs and new points (intersected from the start poses)
    view_station = e_map[view_epoch]
    obs = view_station[net.image] >= 0
    views = Views(net.image[obs], net.point[obs], net.uv[obs], len(images))
    T_start: list[Array | None] = [
        None if view_station[j] < 0 else T_field_view(stations_a, offsets, int(view_station[j]), int(view_cam[j]))
        for j in range(len(images))
    ]
    _, p0 = orient_views(list(cameras), view_cam, views, net.nominal, T_start)
    warnings += left_out_warnings(net, p0)
    keep = np.all(np.isfinite(p0), axis=1)[views.point]
    station = view_station[views.view[keep]]
    camera = view_cam[views.view[keep]]

    # -- the datum, as the bundle's: a fixed field is a datum of control points, all its targets
    datum = datum or Datum()
    if field_fixed:
        datum = Datum(control=tuple(t for t in net.ids if t in field.index), scale_bars=datum.scale_bars)
    rows = datum_rows(datum, field, net, p0)
    net_in = NetworkInput(
        cameras=tuple(cameras),
        free_interior=tuple(free_t for _ in range(K)),
        station=station,
        camera=camera,
        point=views.point[keep],
        uv=views.uv[keep],
        stations=stations_a,
        offsets=offsets,
        offsets_free=True,
        points=rows.points,
        point_free=rows.point_free,
        control=rows.control,
        bars=rows.bars,
        inner=rows.inner,
        sigma_px=float(sigma_px),
    )
    say(f"adjusting {len(keep_epoch)} epochs of {K} cameras, {len(net_in.uv)} observations")
    sol = solve_network(net_in, reject_outliers=reject_outliers, progress=progress)

    model, s0 = sol.model, sol.sigma0
    T_master = [np.eye(4)] + [inv_T(T_from_params(v)) for v in sol.offsets]
    formal = np.zeros((K, 6))
    for k in range(1, K):
        c = model.offset_col0 + 6 * (k - 1)
        formal[k, :3], formal[k, 3:] = pose_sigmas(sol.offsets[k - 1], sol.Q[c : c + 6, c : c + 6] * s0 * s0)
    jack = np.full((K, 6), np.nan)
    if jackknife and len(keep_epoch) < MIN_JACKKNIFE_EPOCHS:
        warnings.append(
            f"only {len(keep_epoch)} epochs: no leave-one-epoch-out check, the sigmas are the formal "
            f"ones and miss errors common to an epoch (synchronisation, rig flex)"
        )
    elif jackknife:
        say(f"leave-one-epoch-out: {len(keep_epoch)} re-adjustments")
        jack = _jackknife_sigmas(net_in, sol)
        if not np.all(np.isfinite(jack)):
            warnings.append(
                "a re-adjustment without one epoch failed (a camera seen in that epoch only?): "
                "the sigmas are the formal ones and may be optimistic"
            )
    sigma_source, sigma = "formal", formal
    if np.all(np.isfinite(jack)):
        sigma_source, sigma = "max(formal, jackknife)", np.maximum(formal, jack)
        for k in range(1, K):
            ratio = float(np.max(jack[k] / formal[k]))
            if ratio > EPOCH_ERROR_WARN_RATIO:
                warnings.append(
                    f"camera {k}'s relative orientation scatters between epochs {ratio:.1f}x more than "
                    f"the image residuals explain (synchronisation, rig flex, unmodelled distortion or "
                    f"field error?): its sigma is the leave-one-epoch-out one"
                )
    sig_int = tuple(interior_sigmas(sol, k, free_t) for k in range(K))
    cams = tuple(replace(c, sigma=sd) for c, sd in zip(sol.cameras, sig_int, strict=True))
    inl, res = sol.inliers, sol.residuals_px
    rms = np.array(
        [np.sqrt(np.mean(res[(camera == k) & inl] ** 2)) if np.any((camera == k) & inl) else np.nan for k in range(K)]
    )
    return RigCalibration(
        rig=Rig(cams, np.array(T_master)),
        sigma_rotation_deg=sigma[:, :3],
        sigma_position_mm=sigma[:, 3:],
        sigma_rotation_formal_deg=formal[:, :3],
        sigma_position_formal_mm=formal[:, 3:],
        sigma_rotation_jackknife_deg=jack[:, :3],
        sigma_position_jackknife_mm=jack[:, 3:],
        sigma_source=sigma_source,
        sigma_interior=sig_int,
        sigma0_px=s0 * sigma_px,
        redundancy=sol.redundancy,
        rms_px=rms,
        n_observations=np.bincount(camera, minlength=K),
        n_rejected=np.bincount(camera[~inl], minlength=K),
        epochs=tuple(epochs[e] for e in keep_epoch),
        T_field_rig=np.array([inv_T(T_from_params(v)) for v in sol.stations]),
        field=network_field(field.name, net, sol.points, field),
        sigma_xyz_mm=point_sigmas(sol, net_in.point_free)[adjusted_points(sol.points)],
        warnings=tuple(warnings),
        extra={"free_interior": list(free_t), "field_fixed": field_fixed},
    )


def _master_from_offset(offset: Array) -> tuple[Array, Array]:
    """``R_master_camera`` (3, 3) and ``t_master_camera`` (3,) mm of an offset ``[w, t]`` of ``T_camera_master``."""
    T = inv_T(T_from_params(offset))
    return T[:3, :3], T[:3, 3]


def _jackknife_sigmas(net: NetworkInput, sol: NetworkSolution) -> Array:
    """Delete-one-epoch jackknife standard deviations (K, 6) of every ``T_master_camera``: rotation
    about camera 0's axes (deg), origin along them (mm); row 0 zeros, all NaN if a re-adjustment failed.

    Each replicate is warm-started from ``sol`` and keeps its inliers (no rejection): see the module
    docstring. Rotations are compared as small left perturbations of the full solution's.
    """
    S, K = len(sol.stations), len(net.cameras)
    full = [_master_from_offset(v) for v in sol.offsets]
    theta = np.zeros((S, K, 6))
    for s in range(S):
        m = sol.inliers & (net.station != s)
        sub = replace(
            net,
            station=net.station[m] - (net.station[m] > s),
            camera=net.camera[m],
            point=net.point[m],
            uv=net.uv[m],
            stations=np.delete(sol.stations, s, axis=0),
            offsets=sol.offsets,
            points=sol.points,
            cameras=tuple(sol.cameras),
        )
        try:
            rep = solve_network(sub, reject_outliers=False, near=True)
            if not rep.converged:  # Gauss-Newton from the full solution did not settle: the full solver
                rep = solve_network(sub, reject_outliers=False)
        except SolveError:
            return np.full((K, 6), np.nan)
        for k in range(1, K):
            R, t = _master_from_offset(rep.offsets[k - 1])
            theta[s, k, :3] = np.degrees(rotvec_from_R(R @ full[k - 1][0].T))  # left: R = exp(d) R_full
            theta[s, k, 3:] = t - full[k - 1][1]
    dev = theta - theta.mean(axis=0)
    return np.sqrt((S - 1) / S * np.sum(dev * dev, axis=0))
