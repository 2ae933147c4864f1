"""The collinearity model of the bundle adjustment: unknowns, residuals and their sparse Jacobian.

One model serves the single-camera self-calibration and the multi-camera rig:

- ``K`` cameras, each a :class:`~service.core.geometry.camera_model.BrownFraser` whose ten
  correction parameters (:data:`~service.core.geometry.camera_model.PARAMETER_NAMES`) may be
  partly free;
- ``S`` stations, the pose of camera 0 (the rig) at each exposure, as ``T_rig_field``
  (rotation vector ``w`` and translation ``t``: ``p_rig = R(w) p_field + t``);
- ``K - 1`` rig offsets ``T_cameraK_rig`` (same form), fixed or free;
- ``N`` points in the field frame, each free or fixed.

An observation is a measured pixel ``uv`` of point ``i`` by camera ``k`` at station ``s``.
Its residual is standardized by the a-priori image noise ``sigma_px``, either

- ``"pixel"``: predicted minus measured pixel, through the camera's own inverse
  correction (:meth:`BrownFraser.pixel_from_ideal`), i.e. exactly the quantity
  whose noise is isotropic; or
- ``"ideal"``: the corrected (ideal) image coordinates of the measured pixel
  minus the collinear projection, divided by the pixel size: the classical
  photogrammetric form, as DBAT and PhotoModeler write it.

Both use the same correction ("photogrammetric/backward": measured -> ideal), so the
calibrated camera is the pipeline's. Extra rows: weighted control points, scale bars
(distances) and linear inner constraints (the free-network datum). The Jacobian is
analytic and sparse (``scipy.sparse.csr_matrix``); its structure is fixed at
construction, so each evaluation only fills the values.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.geometry.so3 import R_from_rotvec, left_jacobian, skew

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

N_INTERIOR = len(PARAMETER_NAMES)
RESIDUAL_SPACES = ("pixel", "ideal")


def correction_parameter_jacobian(xb: Array, yb: Array) -> Array:
    """d(Δx, Δy)/d(K1, K2, K3, P1, P2, B1, B2), shape (n, 2, 7), at centred coordinates (n,) mm.

    The derivative of the Brown/Fraser correction of DESIGN section 2 with
    respect to its coefficients (it is linear in them).
    """
    r2 = xb * xb + yb * yb
    r4 = r2 * r2
    D = np.zeros(xb.shape + (2, 7))
    D[..., 0, 0], D[..., 0, 1], D[..., 0, 2] = xb * r2, xb * r4, xb * r4 * r2
    D[..., 1, 0], D[..., 1, 1], D[..., 1, 2] = yb * r2, yb * r4, yb * r4 * r2
    D[..., 0, 3], D[..., 0, 4] = r2 + 2 * xb * xb, 2 * xb * yb
    D[..., 1, 3], D[..., 1, 4] = 2 * xb * yb, r2 + 2 * yb * yb
    D[..., 0, 5], D[..., 0, 6] = xb, yb
    return D


def inverse_2x2(J: Array) -> Array:
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    W = np.empty_like(J)
    W[..., 0, 0], W[..., 1, 1] = J[..., 1, 1] / det, J[..., 0, 0] / det
    W[..., 0, 1], W[..., 1, 0] = -J[..., 0, 1] / det, -J[..., 1, 0] / det
    return W


@dataclass(frozen=True)
class ExtraRows:
    """Observations other than image points, all standardized (divided by their sigma).

    ``control``: rows (point index, xyz (3,) mm, sigma mm > 0), weighted control points.
    ``bars``: (a, b, distance mm, sigma mm > 0), measured distances between two points.
    ``inner``: (point indices (n,), nominal xyz (n, 3) mm, n_gauge 6 or 7, weight):
    linear inner constraints ``C (p - p_nominal) = 0`` (translation, rotation and, for 7,
    scale of the points' coordinates about their nominal centroid).
    """

    control: tuple[tuple[int, Array, float], ...] = ()
    bars: tuple[tuple[int, int, float, float], ...] = ()
    inner: tuple[IntArray, Array, int, float] | None = None


def inner_constraint_matrix(p_nominal: Array, n_gauge: int) -> Array:
    """C (n_gauge, 3 n): translation (3), rotation (3) and scale (1) about the centroid, unit-normalized rows."""
    n = len(p_nominal)
    q = p_nominal - p_nominal.mean(axis=0)
    s = max(float(np.sqrt(np.mean(np.sum(q * q, axis=1)))), 1e-12)
    q = q / s
    C = np.zeros((n_gauge, n, 3))
    for a in range(3):
        C[a, :, a] = 1.0
    C[3:6] = np.transpose(skew(q), (2, 0, 1))  # rows of sum_i q_i x dp_i
    if n_gauge == 7:
        C[6] = q
    rows = C.reshape(n_gauge, 3 * n)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


class BundleModel:
    """Unknowns, residuals and analytic sparse Jacobian of one bundle problem.

    Parameters
    ----------
    cameras : sequence of BrownFraser, length K
        Start values of the interior orientations (and their fixed sensor geometry).
    free_interior : sequence of sequences of str, length K
        Names of the free correction parameters of each camera.
    station, camera, point : (M,) int
        Of each observation.
    uv : (M, 2) float, px
        Measured pixels.
    n_stations : int
    point_free : (N,) bool
        Which points are unknowns (fixed points keep their start coordinates).
    offsets_free : bool
        Whether the rig offsets ``T_cameraK_rig`` (K > 1) are unknowns.
    points_fixed : (N, 3) float, mm
        Coordinates of the fixed points (rows of free points are ignored).
    offsets_fixed : (K - 1, 6) float
        The rig offsets ``[w, t]`` used when they are not free.
    residual_space : {"pixel", "ideal"}
    sigma_px : float
        A-priori standard deviation of an image coordinate, px.
    extra : ExtraRows
    """

    def __init__(
        self,
        cameras: Sequence[BrownFraser],
        free_interior: Sequence[Sequence[str]],
        station: IntArray,
        camera: IntArray,
        point: IntArray,
        uv: Array,
        n_stations: int,
        point_free: NDArray[np.bool_],
        offsets_free: bool,
        points_fixed: Array,
        offsets_fixed: Array,
        residual_space: str,
        sigma_px: float,
        extra: ExtraRows,
    ) -> None:
        if residual_space not in RESIDUAL_SPACES:
            raise ValueError(f"residual_space must be one of {RESIDUAL_SPACES}, got {residual_space!r}")
        self.cameras = tuple(cameras)
        self.n_cam = len(self.cameras)
        self.free_idx = [np.array([PARAMETER_NAMES.index(n) for n in names], dtype=np.int64) for names in free_interior]
        self.station = np.asarray(station, dtype=np.int64)
        self.cam = np.asarray(camera, dtype=np.int64)
        self.point = np.asarray(point, dtype=np.int64)
        self.uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        self.n_obs = len(self.uv)
        self.n_stations = int(n_stations)
        self.point_free = np.asarray(point_free, dtype=bool)
        self.n_points = len(self.point_free)
        self.offsets_free = bool(offsets_free) and self.n_cam > 1
        self._fixed_points = np.array(points_fixed, dtype=np.float64).reshape(self.n_points, 3)
        self._fixed_offsets = np.array(offsets_fixed, dtype=np.float64).reshape(self.n_cam - 1, 6)
        self.residual_space = residual_space
        self.sigma_px = float(sigma_px)
        self.extra = extra
        # -- column layout: [interior of each camera | stations | offsets | free points]
        col = 0
        self.int_cols = []
        for idx in self.free_idx:
            self.int_cols.append(np.arange(col, col + len(idx)))
            col += len(idx)
        self.n_interior = col
        self.station_col0 = col
        col += 6 * self.n_stations
        self.offset_col0 = col
        if self.offsets_free:
            col += 6 * (self.n_cam - 1)
        self.point_col = np.full(self.n_points, -1, dtype=np.int64)
        self.point_col[self.point_free] = col + 3 * np.arange(int(self.point_free.sum()))
        col += 3 * int(self.point_free.sum())
        self.n_params = col
        self.by_cam = [np.flatnonzero(self.cam == k) for k in range(self.n_cam)]
        self.inner_C = (
            inner_constraint_matrix(extra.inner[1], extra.inner[2]) * extra.inner[3]
            if extra.inner is not None
            else None
        )
        self.n_rows = (
            2 * self.n_obs
            + 3 * len(extra.control)
            + len(extra.bars)
            + (0 if self.inner_C is None else len(self.inner_C))
        )
        self._structure()
        self._cache_x: Array | None = None
        self._cache: tuple[Array, Array | None] | None = None

    # -- parameter vector ------------------------------------------------------

    def pack(self, cameras: Sequence[BrownFraser], stations: Array, offsets: Array, points: Array) -> Array:
        """Parameter vector from interior orientations, stations (S, 6), offsets (K-1, 6) and points (N, 3)."""
        x = np.empty(self.n_params)
        for k, cam in enumerate(cameras):
            x[self.int_cols[k]] = cam.params()[self.free_idx[k]]
        x[self.station_col0 : self.station_col0 + 6 * self.n_stations] = np.asarray(stations).ravel()
        if self.offsets_free:
            x[self.offset_col0 : self.offset_col0 + 6 * (self.n_cam - 1)] = np.asarray(offsets).ravel()
        free = self.point_free
        cols = self.point_col[free][:, None] + np.arange(3)
        x[cols.ravel()] = np.asarray(points)[free].ravel()
        return x

    def unpack(self, x: Array) -> tuple[list[BrownFraser], Array, Array, Array]:
        cams = []
        for k, cam in enumerate(self.cameras):
            v = cam.params()
            v[self.free_idx[k]] = x[self.int_cols[k]]
            if v[0] <= 0:  # a trial step may propose c <= 0; keep the model defined, the cost says no
                v[0] = 1e-6
            cams.append(cam.with_params(v))
        stations = x[self.station_col0 : self.station_col0 + 6 * self.n_stations].reshape(-1, 6)
        offsets = (
            x[self.offset_col0 : self.offset_col0 + 6 * (self.n_cam - 1)].reshape(-1, 6)
            if self.offsets_free
            else self._fixed_offsets
        )
        points = self._fixed_points.copy()
        free = self.point_free
        points[free] = x[(self.point_col[free][:, None] + np.arange(3)).ravel()].reshape(-1, 3)
        return cams, stations, offsets, points

    # -- sparse structure ----------------------------------------------------------

    def _structure(self) -> None:
        """Row/column indices of every non-zero, in the order :meth:`_jacobian_values` fills them."""
        rows, cols = [], []
        obs_rows = 2 * np.arange(self.n_obs)[:, None] + np.arange(2)  # (M, 2)
        for k in range(self.n_cam):
            m = self.by_cam[k]
            nk = len(self.int_cols[k])
            rows.append(np.repeat(obs_rows[m][:, :, None], nk, axis=2).ravel())
            cols.append(np.broadcast_to(self.int_cols[k], (len(m), 2, nk)).ravel())
        st_cols = self.station_col0 + 6 * self.station[:, None] + np.arange(6)
        rows.append(np.repeat(obs_rows[:, :, None], 6, axis=2).ravel())
        cols.append(np.broadcast_to(st_cols[:, None, :], (self.n_obs, 2, 6)).ravel())
        self.offset_obs = np.flatnonzero(self.cam > 0) if self.offsets_free else np.zeros(0, np.int64)
        o = self.offset_obs
        off_cols = self.offset_col0 + 6 * (self.cam[o] - 1)[:, None] + np.arange(6)
        rows.append(np.repeat(obs_rows[o][:, :, None], 6, axis=2).ravel())
        cols.append(np.broadcast_to(off_cols[:, None, :], (len(o), 2, 6)).ravel())
        self.free_obs = np.flatnonzero(self.point_free[self.point])
        f = self.free_obs
        pt_cols = self.point_col[self.point[f]][:, None] + np.arange(3)
        rows.append(np.repeat(obs_rows[f][:, :, None], 3, axis=2).ravel())
        cols.append(np.broadcast_to(pt_cols[:, None, :], (len(f), 2, 3)).ravel())
        r0 = 2 * self.n_obs
        for i, _, _ in self.extra.control:
            rows.append(np.repeat(r0 + np.arange(3), 3))
            cols.append(np.tile(self.point_col[i] + np.arange(3), 3))
            r0 += 3
        for a, b, _, _ in self.extra.bars:
            for i in (a, b):
                if self.point_free[i]:
                    rows.append(np.full(3, r0))
                    cols.append(self.point_col[i] + np.arange(3))
            r0 += 1
        if self.inner_C is not None:
            idx = self.extra.inner[0]  # type: ignore[index]
            c = (self.point_col[idx][:, None] + np.arange(3)).ravel()
            n_g = len(self.inner_C)
            rows.append(np.repeat(r0 + np.arange(n_g), len(c)))
            cols.append(np.tile(c, n_g))
        rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)
        probe = sp.csr_matrix(
            (np.arange(1, len(rows_a) + 1, dtype=np.float64), (rows_a, cols_a)), shape=(self.n_rows, self.n_params)
        )
        probe.sort_indices()
        self._perm = probe.data.astype(np.int64) - 1
        self._indices, self._indptr = probe.indices.copy(), probe.indptr.copy()

    def sparsity(self) -> sp.csr_matrix:
        return sp.csr_matrix(
            (np.ones(len(self._perm)), self._indices, self._indptr), shape=(self.n_rows, self.n_params)
        )

    # -- evaluation ----------------------------------------------------------------

    def residuals(self, x: Array) -> Array:
        """Standardized residuals (n_rows,): predicted minus observed over sigma."""
        return self._evaluate(x, jacobian=False)[0]

    def jacobian(self, x: Array) -> sp.csr_matrix:
        J = self._evaluate(x, jacobian=True)[1]
        assert J is not None
        return sp.csr_matrix((J[self._perm], self._indices, self._indptr), shape=(self.n_rows, self.n_params))

    def image_residuals_px(self, x: Array) -> Array:
        """Measured minus predicted, (M, 2) px (ideal space: ideal residuals over the pixel size)."""
        return -self.residuals(x)[: 2 * self.n_obs].reshape(-1, 2) * self.sigma_px

    def camera_frame_points(self, x: Array) -> Array:
        """Each observation's point in its camera's frame, (M, 3) mm."""
        _, stations, offsets, points = self.unpack(x)
        return self._geometry(stations, offsets, points)[0]

    def _geometry(self, stations: Array, offsets: Array, points: Array) -> tuple[Array, ...]:
        Rs = R_from_rotvec(stations[:, :3])
        P = points[self.point]
        Rso = Rs[self.station]
        q = np.einsum("mij,mj->mi", Rso, P) + stations[self.station, 3:]
        Rk = np.concatenate([np.eye(3)[None], R_from_rotvec(offsets[:, :3])]) if self.n_cam > 1 else np.eye(3)[None]
        tk = np.concatenate([np.zeros((1, 3)), offsets[:, 3:]]) if self.n_cam > 1 else np.zeros((1, 3))
        Rko = Rk[self.cam]
        pc = np.einsum("mij,mj->mi", Rko, q) + tk[self.cam]
        return pc, q, Rso, Rko, P

    def _evaluate(self, x: Array, jacobian: bool) -> tuple[Array, Array | None]:
        if (
            self._cache_x is not None
            and np.array_equal(x, self._cache_x)
            and (not jacobian or (self._cache is not None and self._cache[1] is not None))
        ):
            assert self._cache is not None
            return self._cache
        cams, stations, offsets, points = self.unpack(x)
        pc, q, Rso, Rko, P = self._geometry(stations, offsets, points)
        M = self.n_obs
        f = np.empty(self.n_rows)
        s = self.sigma_px
        Z = np.maximum(pc[:, 2], 1e-9)  # behind-camera points are caught after the adjustment
        xn = pc[:, :2] / Z[:, None]
        fi = np.empty((M, 2))
        dF_dideal = np.empty((M, 2, 2))  # d f / d ideal
        dint = np.zeros((M, 2, N_INTERIOR))  # d f / d interior (all ten)
        for k, cam in enumerate(cams):
            m = self.by_cam[k]
            if len(m) == 0:
                continue
            ps = np.asarray(cam.pixel_size_mm)
            ideal = cam.c_mm * xn[m]
            if self.residual_space == "pixel":
                uv_pred = cam.pixel_from_ideal(ideal)
                fi[m] = (uv_pred - self.uv[m]) / s
                if not jacobian:
                    continue
                G = inverse_2x2(cam.ideal_from_pixel_jacobian(uv_pred)) / s  # px/mm
                xy = cam.sensor_from_pixel(uv_pred)
                D = correction_parameter_jacobian(xy[:, 0] - cam.x0_mm, xy[:, 1] - cam.y0_mm)
                dF_dideal[m] = G
                dint[m, :, 0] = np.einsum("mij,mj->mi", G, xn[m])
                dint[m, 0, 1] = 1.0 / (ps[0] * s)
                dint[m, 1, 2] = 1.0 / (ps[1] * s)
                dint[m, :, 3:] = -np.einsum("mij,mjk->mik", G, D)
            else:
                obs_ideal = cam.ideal_from_pixel(self.uv[m])
                fi[m] = (ideal - obs_ideal) / (ps * s)
                if not jacobian:
                    continue
                scale = 1.0 / (ps * s)
                dF_dideal[m] = np.diag(scale)
                dint[m, :, 0] = xn[m] * scale
                Jf = cam.ideal_from_pixel_jacobian(self.uv[m]) / ps[None, None, :]  # d ideal / d sensor
                dint[m, :, 1:3] = Jf * scale[None, :, None]
                xy = cam.sensor_from_pixel(self.uv[m])
                D = correction_parameter_jacobian(xy[:, 0] - cam.x0_mm, xy[:, 1] - cam.y0_mm)
                dint[m, :, 3:] = -D * scale[None, :, None]
        f[: 2 * M] = fi.ravel()
        r0 = 2 * M
        for i, xyz, sig in self.extra.control:
            f[r0 : r0 + 3] = (points[i] - xyz) / sig
            r0 += 3
        for a, b, d, sig in self.extra.bars:
            f[r0] = (np.linalg.norm(points[a] - points[b]) - d) / sig
            r0 += 1
        if self.inner_C is not None:
            idx, p0 = self.extra.inner[0], self.extra.inner[1]  # type: ignore[index]
            f[r0:] = self.inner_C @ (points[idx] - p0).ravel()
        if not jacobian:
            self._cache_x, self._cache = x.copy(), (f, None)
            return f, None
        # d ideal / d pc = (c / Z) [[1, 0, -xn], [0, 1, -yn]]
        c_obs = np.array([cam.c_mm for cam in cams])[self.cam]
        dI = np.zeros((M, 2, 3))
        dI[:, 0, 0] = dI[:, 1, 1] = c_obs / Z
        dI[:, :, 2] = -(c_obs / Z)[:, None] * xn
        A = np.einsum("mij,mjk->mik", dF_dideal, dI)  # d f / d pc
        blocks = []
        for k in range(self.n_cam):
            m = self.by_cam[k]
            blocks.append(dint[m][:, :, self.free_idx[k]].ravel())
        Jl_s = left_jacobian(stations[:, :3])[self.station]
        ARk = np.einsum("mij,mjk->mik", A, Rko)
        d_ws = -np.einsum("mij,mjk,mkl->mil", ARk, skew(np.einsum("mij,mj->mi", Rso, P)), Jl_s)
        blocks.append(np.concatenate([d_ws, ARk], axis=2).ravel())
        o = self.offset_obs
        if len(o):
            Jl_k = left_jacobian(offsets[:, :3])[self.cam[o] - 1]
            d_wk = -np.einsum("mij,mjk,mkl->mil", A[o], skew(np.einsum("mij,mj->mi", Rko[o], q[o])), Jl_k)
            blocks.append(np.concatenate([d_wk, A[o]], axis=2).ravel())
        else:
            blocks.append(np.zeros(0))
        fo = self.free_obs
        blocks.append(np.einsum("mij,mjk->mik", ARk[fo], Rso[fo]).ravel())
        for _, _, sig in self.extra.control:
            blocks.append((np.eye(3) / sig).ravel())
        for a, b, _, sig in self.extra.bars:
            d = points[a] - points[b]
            u = d / max(float(np.linalg.norm(d)), 1e-12) / sig
            for i, sign in ((a, 1.0), (b, -1.0)):
                if self.point_free[i]:
                    blocks.append(sign * u)
        if self.inner_C is not None:
            blocks.append(self.inner_C.ravel())
        J = np.concatenate(blocks)
        self._cache_x, self._cache = x.copy(), (f, J)
        return f, J
