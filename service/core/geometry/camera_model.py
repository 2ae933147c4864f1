"""The Brown/Fraser camera model of DESIGN section 2 (the paper, section 4.1).

Coordinate chain (all arrays (N, 2) unless said otherwise)::

    pixel (u, v) px  --sensor_from_pixel-->  sensor (x', y') mm, origin at the sensor centre
    sensor           --ideal_from_sensor-->  ideal (x, y) mm, relative to the principal point,
                                             distortion removed: x = c * Xc / Zc
    camera frame (Xc, Yc, Zc) mm: x right, y down, z along the optical axis

The correction runs from measured (distorted) to ideal coordinates, as in the
paper, so going the other way (a 3-D point to a pixel) needs an iterative
inverse; Newton's method on the analytic 2x2 Jacobian converges to far below
1e-6 px in a few steps.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core._kernels.geometry_kernels import correction_kernel, sensor_from_ideal_kernel

Array = NDArray[np.float64]


def _flat(a: ArrayLike) -> Array:
    """A writable, contiguous float64 1-D copy or view: the one array type the kernels are compiled for."""
    return np.require(np.ravel(a), np.float64, ["C", "W"])


PARAMETER_NAMES = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2", "B1", "B2")


@dataclass(frozen=True)
class BrownFraser:
    """Interior orientation: sensor geometry plus the Brown/Fraser correction.

    Units: ``pixel_size_mm`` (x, y) mm/px, ``c_mm``, ``x0_mm``, ``y0_mm`` mm;
    K1 mm^-2, K2 mm^-4, K3 mm^-6, P1 and P2 mm^-1, B1 and B2 unitless.
    """

    width: int
    height: int
    pixel_size_mm: tuple[float, float]
    c_mm: float
    x0_mm: float = 0.0
    y0_mm: float = 0.0
    K1: float = 0.0
    K2: float = 0.0
    K3: float = 0.0
    P1: float = 0.0
    P2: float = 0.0
    B1: float = 0.0
    B2: float = 0.0
    sigma: dict[str, float] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        px, py = self.pixel_size_mm
        if not (px > 0 and py > 0):
            raise ValueError(f"pixel_size_mm must be positive, got {self.pixel_size_mm}")
        if not self.c_mm > 0:
            raise ValueError(f"c_mm must be positive, got {self.c_mm}")
        object.__setattr__(self, "pixel_size_mm", (float(px), float(py)))

    # -- parameters ---------------------------------------------------------

    def params(self) -> Array:
        """The ten correction parameters in :data:`PARAMETER_NAMES` order."""
        return np.array([getattr(self, n) for n in PARAMETER_NAMES], dtype=np.float64)

    def with_params(self, values: ArrayLike) -> BrownFraser:
        """A copy with the ten parameters replaced (order of :data:`PARAMETER_NAMES`)."""
        v = np.asarray(values, dtype=np.float64).reshape(len(PARAMETER_NAMES))
        values_by_name: dict[str, Any] = {n: float(x) for n, x in zip(PARAMETER_NAMES, v, strict=True)}
        return replace(self, **values_by_name)

    def cropped(self, x_px: int, y_px: int, width: int, height: int) -> BrownFraser:
        """The same camera for a window of its sensor (a camera's ROI): ``width`` x ``height`` px whose
        pixel (0, 0) is the sensor's (``x_px``, ``y_px``). The principal point, given from the image's
        centre, moves by the window's centre; the correction, relative to it, is the same."""
        if not (0 <= x_px and 0 <= y_px and width > 0 and height > 0) or (
            x_px + width > self.width or y_px + height > self.height
        ):
            raise ValueError(
                f"the window {width} x {height} px at ({x_px}, {y_px}) is not inside the {self.width} x "
                f"{self.height} px sensor"
            )
        px, py = self.pixel_size_mm
        return replace(
            self,
            width=int(width),
            height=int(height),
            x0_mm=self.x0_mm - (x_px + (width - 1) / 2.0 - (self.width - 1) / 2.0) * px,
            y0_mm=self.y0_mm - (y_px + (height - 1) / 2.0 - (self.height - 1) / 2.0) * py,
        )

    @property
    def mean_pixel_size_mm(self) -> float:
        return 0.5 * (self.pixel_size_mm[0] + self.pixel_size_mm[1])

    # the model's numbers as the compiled kernels take them, converted once per camera: converted at
    # every call they cost ~5 us three times an ROI frame (the prediction, the eccentricity, the resection)

    @cached_property
    def whitening_args(self) -> tuple[float, ...]:
        """The image centre (px), pixel size, principal point and correction, in the order of
        :func:`~service.core._kernels.geometry_kernels.whitened_ideal_kernel` after its pixels."""
        px, py = self.pixel_size_mm
        return ((self.width - 1) / 2.0, (self.height - 1) / 2.0, px, py, *map(float, self._xy0_and_correction()))

    @cached_property
    def projection_args(self) -> tuple[float | int, ...]:
        """c, the correction, principal point, pixel size and image size, in the order of
        :func:`~service.core._kernels.geometry_kernels.project_kernel` after its pose and points."""
        K1, K2, K3, P1, P2, B1, B2 = map(float, self._xy0_and_correction()[2:])
        px, py = self.pixel_size_mm
        xy0 = (float(self.x0_mm), float(self.y0_mm))
        return (float(self.c_mm), K1, K2, K3, P1, P2, B1, B2, *xy0, px, py, int(self.width), int(self.height))

    def _xy0_and_correction(self) -> tuple[float, ...]:
        return (self.x0_mm, self.y0_mm, self.K1, self.K2, self.K3, self.P1, self.P2, self.B1, self.B2)

    # -- pixel <-> sensor ---------------------------------------------------

    def sensor_from_pixel(self, uv: ArrayLike) -> Array:
        """Sensor coordinates (N, 2) mm of pixel coordinates ``uv`` (N, 2) px."""
        uv = np.asarray(uv, dtype=np.float64)
        centre = np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        return (uv - centre) * np.asarray(self.pixel_size_mm)

    def pixel_from_sensor(self, xy_sensor: ArrayLike) -> Array:
        """Pixel coordinates (N, 2) px of sensor coordinates (N, 2) mm."""
        xy_sensor = np.asarray(xy_sensor, dtype=np.float64)
        centre = np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        return xy_sensor / np.asarray(self.pixel_size_mm) + centre

    # -- the correction -----------------------------------------------------

    def _coefficients(self) -> tuple[float, ...]:
        """K1, K2, K3, P1, P2, B1, B2 as floats (one compiled kernel for any way they were given)."""
        return (
            float(self.K1),
            float(self.K2),
            float(self.K3),
            float(self.P1),
            float(self.P2),
            float(self.B1),
            float(self.B2),
        )

    def _correction(self, xb: Array, yb: Array) -> tuple[Array, Array]:
        xb, yb = np.broadcast_arrays(np.asarray(xb, dtype=np.float64), np.asarray(yb, dtype=np.float64))
        dx, dy, _ = correction_kernel(_flat(xb), _flat(yb), *self._coefficients(), False)
        return dx.reshape(xb.shape), dy.reshape(xb.shape)

    def _correction_jacobian(self, xb: Array, yb: Array) -> Array:
        """d(x, y)/d(x_bar, y_bar), shape (N, 2, 2)."""
        xb, yb = np.broadcast_arrays(np.asarray(xb, dtype=np.float64), np.asarray(yb, dtype=np.float64))
        _, _, J = correction_kernel(_flat(xb), _flat(yb), *self._coefficients(), True)
        return J.reshape(xb.shape + (2, 2))

    def ideal_from_sensor(self, xy_sensor: ArrayLike) -> Array:
        """Ideal coordinates (N, 2) mm from measured sensor coordinates (N, 2) mm."""
        xy_sensor = np.asarray(xy_sensor, dtype=np.float64)
        xb = xy_sensor[..., 0] - self.x0_mm
        yb = xy_sensor[..., 1] - self.y0_mm
        dx, dy = self._correction(xb, yb)
        return np.stack([xb + dx, yb + dy], axis=-1)

    def sensor_from_ideal(self, xy_ideal: ArrayLike, max_iter: int = 20) -> Array:
        """Measured sensor coordinates (N, 2) mm of ideal coordinates (N, 2) mm.

        Inverts :meth:`ideal_from_sensor` by Newton's method, point by point (compiled: the
        prediction of every target runs per frame); each point stops when it moved less than
        1e-12 mm.
        """
        target = np.asarray(xy_ideal, dtype=np.float64)
        flat = _flat(target).reshape(-1, 2)
        xb = sensor_from_ideal_kernel(flat, *self._coefficients(), int(max_iter))
        xb[:, 0] += self.x0_mm
        xb[:, 1] += self.y0_mm
        return xb.reshape(target.shape)

    # -- compositions -------------------------------------------------------

    def ideal_from_pixel(self, uv: ArrayLike) -> Array:
        """Ideal coordinates (N, 2) mm of measured pixels ``uv`` (N, 2) px."""
        return self.ideal_from_sensor(self.sensor_from_pixel(uv))

    def pixel_from_ideal(self, xy_ideal: ArrayLike) -> Array:
        """Measured pixel coordinates (N, 2) px of ideal coordinates (N, 2) mm."""
        return self.pixel_from_sensor(self.sensor_from_ideal(xy_ideal))

    def ideal_from_pixel_jacobian(self, uv: ArrayLike) -> Array:
        """d(ideal x, y)/d(u, v), shape (N, 2, 2), mm/px: propagates pixel noise to ideal coordinates."""
        xy = self.sensor_from_pixel(uv)
        J = self._correction_jacobian(xy[..., 0] - self.x0_mm, xy[..., 1] - self.y0_mm)
        return J * np.asarray(self.pixel_size_mm)[None, :]

    def ideal_from_camera(self, p_camera: ArrayLike) -> Array:
        """Collinearity: ideal coordinates (N, 2) mm of points (N, 3) mm in the camera frame.

        Points at or behind the projection centre (Zc <= 0) give NaN.
        """
        p = np.asarray(p_camera, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z_safe = np.where(z > 0, z, np.nan)
            return self.c_mm * p[..., :2] / z_safe[..., None]

    def pixel_from_camera(self, p_camera: ArrayLike) -> Array:
        """Distorted pixel coordinates (N, 2) px of points (N, 3) mm in the camera frame."""
        return self.pixel_from_ideal(self.ideal_from_camera(p_camera))

    def rays_from_pixel(self, uv: ArrayLike) -> Array:
        """Unit viewing directions (N, 3) in the camera frame of measured pixels (N, 2)."""
        xy = self.ideal_from_pixel(uv)
        d = np.concatenate([xy, np.full(xy.shape[:-1] + (1,), self.c_mm)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def in_image(self, uv: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """Which pixel coordinates (N, 2) lie inside the image by at least ``margin_px``."""
        uv = np.asarray(uv, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return (
                (uv[..., 0] >= -0.5 + margin_px)
                & (uv[..., 0] <= self.width - 0.5 - margin_px)
                & (uv[..., 1] >= -0.5 + margin_px)
                & (uv[..., 1] <= self.height - 0.5 - margin_px)
            )

    def pixel_grid(self, nu: int = 33, nv: int = 27) -> Array:
        """A regular grid (nu*nv, 2) of pixel coordinates spanning the whole sensor, corners included."""
        u = np.linspace(-0.5, self.width - 0.5, nu)
        v = np.linspace(-0.5, self.height - 0.5, nv)
        return np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)

    # -- camera.json --------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The ``camera.json`` form of DESIGN section 2 (plus ``sigma`` when known)."""
        d: dict[str, Any] = {"model": "brown-fraser"}
        raw = asdict(self)
        sigma = raw.pop("sigma")
        raw["pixel_size_mm"] = list(self.pixel_size_mm)
        d.update(raw)
        if sigma:
            d["sigma"] = dict(sigma)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BrownFraser:
        """Parse the ``camera.json`` form; unknown keys are ignored, missing ones raise ``ValueError``."""
        if not isinstance(d, dict):
            raise ValueError("a camera must be a JSON object")
        model = d.get("model", "brown-fraser")
        if model != "brown-fraser":
            raise ValueError(f"unsupported camera model {model!r} (expected 'brown-fraser')")
        try:
            ps = d["pixel_size_mm"]
            if isinstance(ps, (int, float)):
                ps = (ps, ps)
            kwargs: dict[str, Any] = {
                "width": int(d["width"]),
                "height": int(d["height"]),
                "pixel_size_mm": (float(ps[0]), float(ps[1])),
                "c_mm": float(d["c_mm"]),
            }
        except KeyError as e:
            raise ValueError(f"camera is missing the key {e.args[0]!r}") from None
        except (TypeError, ValueError, IndexError) as e:
            raise ValueError(f"camera has a malformed value: {e}") from None
        for name in PARAMETER_NAMES[1:]:
            if name in d:
                kwargs[name] = float(d[name])
        sigma = d.get("sigma")
        if isinstance(sigma, dict):
            kwargs["sigma"] = {k: float(v) for k, v in sigma.items() if isinstance(v, (int, float))}
        return cls(**kwargs)
