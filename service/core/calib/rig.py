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
too, with inner constraints on the nominal field (scale from it or from scale
bars), as :func:`service.core.calib.bundle.calibrate_camera` does.

Start values: every image is resected on its own; each relative orientation is the
mean over the epochs in which camera 0 and camera k were both resected
(rotations averaged by ``scipy.spatial.transform.Rotation.mean``). Adjustment and
gross-error rejection: :func:`service.core.calib.bundle_solve.solve_network`.

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
from scipy.spatial.transform import Rotation

from service.core.calib.bundle import Datum
from service.core.calib.bundle_solve import (
    NetworkInput,
    NetworkSolution,
    Progress,
    T_from_params,
    Views,
    orient_views,
    params_from_T,
    pose_sigmas,
    resect_view,
    solve_network,
)
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.geometry.frames import check_T, inv_T, make_T
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
        R = Rotation.from_matrix(np.array([T[:3, :3] for T in rel])).mean().as_matrix()
        out.append(make_T(R, np.mean([T[:3, 3] for T in rel], axis=0)))
    return out


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
        Keep the field's targets fixed (default) or adjust them (inner constraints, ``datum``).
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
        ``degenerate_geometry`` (singular normal equations), ``bad_input``.
    """
    K = len(cameras)
    if K < 2:
        raise ValueError(f"a rig needs at least 2 cameras, got {K}")
    free_t = tuple(n for n in PARAMETER_NAMES if n in set(free_interior))
    if set(free_interior) - set(free_t):
        raise ValueError(f"unknown camera parameters {sorted(set(free_interior) - set(free_t))}")
    for im in images:
        if not 0 <= im.camera < K:
            raise SolveError(
                Reason.bad_input,
                f"Image {im.name or im.epoch!r} names camera {im.camera}, but the rig has {K} cameras.",
            )
    epochs = list(dict.fromkeys(im.epoch for im in images))
    observed = {t for im in images for t in im.ids}
    ids = [t for t in field.ids if t in observed] + sorted(observed - set(field.index))
    index = {t: i for i, t in enumerate(ids)}
    nominal = np.array([field.xyz[field.index[t]] if t in field.index else [np.nan] * 3 for t in ids])
    view_epoch = np.array([epochs.index(im.epoch) for im in images])
    view_cam = np.array([im.camera for im in images])
    say = progress or (lambda _s: None)

    # -- start values: every image resected on its own
    say(f"start values: resecting {len(images)} images")
    T_view: dict[tuple[int, int], Array] = {}
    for j, im in enumerate(images):
        known = [k for k, t in enumerate(im.ids) if t in field.index]
        T = resect_view(
            cameras[im.camera],
            field.xyz[field.indices_of([im.ids[k] for k in known])],
            np.asarray(im.uv, dtype=np.float64)[known],
        )
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

    # -- observations and new points (intersected from the start poses)
    view_idx, point, uv = [], [], []
    for j, im in enumerate(images):
        if e_map[view_epoch[j]] < 0:
            continue
        view_idx += [j] * len(im.ids)
        point += [index[t] for t in im.ids]
        uv.append(np.asarray(im.uv, dtype=np.float64).reshape(-1, 2))
    view_idx_a, point_a, uv_a = np.array(view_idx), np.array(point), np.concatenate(uv)
    T_start: list[Array | None] = []
    for j in range(len(images)):
        e = e_map[view_epoch[j]]
        T_start.append(None if e < 0 else inv_T(_camera_from_field(stations_a[e], offsets, images[j].camera)))
    _, p0 = orient_views(list(cameras), view_cam, Views(view_idx_a, point_a, uv_a, len(images)), nominal, T_start)
    known = np.all(np.isfinite(p0), axis=1)
    for i in np.flatnonzero(~known).tolist():
        warnings.append(f"target {ids[i]!r} is seen in fewer than two oriented images and is left out")
    keep = known[point_a]
    station = e_map[view_epoch[view_idx_a[keep]]]
    camera = view_cam[view_idx_a[keep]]
    point_a, uv_a = point_a[keep], uv_a[keep]

    in_field = np.isfinite(nominal).all(axis=1) & known
    point_free = np.ones(len(ids), bool)
    control: dict[int, tuple[Array, float]] = {}
    inner = None
    bars = []
    if field_fixed:
        point_free[in_field] = False
        p0[in_field] = nominal[in_field]
    else:
        rows = np.flatnonzero(in_field)
        inner = (rows, nominal[rows], 6 if datum is not None and datum.scale_bars else 7)
        for b in (datum or Datum()).scale_bars:
            bars.append((index[b.id_a], index[b.id_b], float(b.distance_mm), float(b.sigma_mm)))
    net = NetworkInput(
        cameras=tuple(cameras),
        free_interior=tuple(free_t for _ in range(K)),
        station=station,
        camera=camera,
        point=point_a,
        uv=uv_a,
        stations=stations_a,
        offsets=offsets,
        offsets_free=True,
        points=p0,
        point_free=point_free,
        control=control,
        bars=tuple(bars),
        inner=inner,
        sigma_px=float(sigma_px),
    )
    say(f"adjusting {len(keep_epoch)} epochs of {K} cameras, {len(uv_a)} observations")
    sol = solve_network(net, reject_outliers=reject_outliers, progress=progress)

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
        jack = _jackknife_sigmas(net, sol)
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
    sig_int = []
    for k in range(K):
        sd = {n: 0.0 for n in PARAMETER_NAMES}
        cols = model.int_cols[k]
        sd.update({n: float(v) for n, v in zip(free_t, np.sqrt(np.diag(sol.Q)[cols]) * s0, strict=True)})
        sig_int.append(sd)
    cams = tuple(
        BrownFraser(
            **{
                **{a: getattr(c, a) for a in ("width", "height", "pixel_size_mm")},
                **dict(zip(PARAMETER_NAMES, c.params().tolist(), strict=True)),
                "sigma": sd,
            }
        )
        for c, sd in zip(sol.cameras, sig_int, strict=True)
    )
    inl, res = sol.inliers, sol.residuals_px
    rms = np.array(
        [np.sqrt(np.mean(res[(camera == k) & inl] ** 2)) if np.any((camera == k) & inl) else np.nan for k in range(K)]
    )
    n_obs = np.bincount(camera, minlength=K)
    n_rej = np.bincount(camera[~inl], minlength=K)
    sig_xyz = np.zeros((len(ids), 3))
    for i in range(len(ids)):
        c = model.point_col[i]
        if c >= 0:
            sig_xyz[i] = np.sqrt(np.clip(np.diag(sol.Q[c : c + 3, c : c + 3]), 0.0, None)) * s0
    codes = [int(field.codes[field.index[t]]) if t in field.index else -1 for t in ids]
    diam = [float(field.diameters_mm[field.index[t]]) if t in field.index else np.nan for t in ids]
    return RigCalibration(
        rig=Rig(cams, np.array(T_master)),
        sigma_rotation_deg=sigma[:, :3],
        sigma_position_mm=sigma[:, 3:],
        sigma_rotation_formal_deg=formal[:, :3],
        sigma_position_formal_mm=formal[:, 3:],
        sigma_rotation_jackknife_deg=jack[:, :3],
        sigma_position_jackknife_mm=jack[:, 3:],
        sigma_source=sigma_source,
        sigma_interior=tuple(sig_int),
        sigma0_px=s0 * sigma_px,
        redundancy=sol.redundancy,
        rms_px=rms,
        n_observations=n_obs,
        n_rejected=n_rej,
        epochs=tuple(epochs[e] for e in keep_epoch),
        T_field_rig=np.array([inv_T(T_from_params(v)) for v in sol.stations]),
        field=Field(field.name, tuple(ids), sol.points, np.array(codes), np.array(diam)),
        sigma_xyz_mm=sig_xyz,
        warnings=tuple(warnings),
        extra={"free_interior": list(free_t), "field_fixed": field_fixed},
    )


def _camera_from_field(station: Array, offsets: Array, k: int) -> Array:
    """``T_camerak_field`` of a station ``[w, t]`` of ``T_rig_field``."""
    T_rig_field = T_from_params(station)
    return T_rig_field if k == 0 else T_from_params(offsets[k - 1]) @ T_rig_field


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
            theta[s, k, :3] = np.degrees(Rotation.from_matrix(R @ full[k - 1][0].T).as_rotvec())
            theta[s, k, 3:] = t - full[k - 1][1]
    dev = theta - theta.mean(axis=0)
    return np.sqrt((S - 1) / S * np.sum(dev * dev, axis=0))
