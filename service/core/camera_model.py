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
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

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
        return replace(self, **{n: float(x) for n, x in zip(PARAMETER_NAMES, v, strict=True)})

    @property
    def mean_pixel_size_mm(self) -> float:
        return 0.5 * (self.pixel_size_mm[0] + self.pixel_size_mm[1])

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

    def _correction(self, xb: Array, yb: Array) -> tuple[Array, Array]:
        r2 = xb * xb + yb * yb
        radial = r2 * (self.K1 + r2 * (self.K2 + r2 * self.K3))
        dx = xb * radial + self.P1 * (r2 + 2 * xb * xb) + 2 * self.P2 * xb * yb
        dx = dx + self.B1 * xb + self.B2 * yb
        dy = yb * radial + 2 * self.P1 * xb * yb + self.P2 * (r2 + 2 * yb * yb)
        return dx, dy

    def _correction_jacobian(self, xb: Array, yb: Array) -> Array:
        """d(x, y)/d(x_bar, y_bar), shape (N, 2, 2)."""
        r2 = xb * xb + yb * yb
        radial = r2 * (self.K1 + r2 * (self.K2 + r2 * self.K3))
        g = self.K1 + r2 * (2 * self.K2 + 3 * self.K3 * r2)  # d radial / d r^2
        J = np.empty(xb.shape + (2, 2))
        J[..., 0, 0] = 1 + radial + 2 * xb * xb * g + 6 * self.P1 * xb + 2 * self.P2 * yb + self.B1
        J[..., 0, 1] = 2 * xb * yb * g + 2 * self.P1 * yb + 2 * self.P2 * xb + self.B2
        J[..., 1, 0] = 2 * xb * yb * g + 2 * self.P1 * yb + 2 * self.P2 * xb
        J[..., 1, 1] = 1 + radial + 2 * yb * yb * g + 2 * self.P1 * xb + 6 * self.P2 * yb
        return J

    def ideal_from_sensor(self, xy_sensor: ArrayLike) -> Array:
        """Ideal coordinates (N, 2) mm from measured sensor coordinates (N, 2) mm."""
        xy_sensor = np.asarray(xy_sensor, dtype=np.float64)
        xb = xy_sensor[..., 0] - self.x0_mm
        yb = xy_sensor[..., 1] - self.y0_mm
        dx, dy = self._correction(xb, yb)
        return np.stack([xb + dx, yb + dy], axis=-1)

    def sensor_from_ideal(self, xy_ideal: ArrayLike, max_iter: int = 20) -> Array:
        """Measured sensor coordinates (N, 2) mm of ideal coordinates (N, 2) mm.

        Inverts :meth:`ideal_from_sensor` by Newton's method, vectorised over
        all points; stops when every point moved less than 1e-12 mm.
        """
        target = np.asarray(xy_ideal, dtype=np.float64)
        xb = target[..., 0].copy()
        yb = target[..., 1].copy()
        for _ in range(max_iter):
            dx, dy = self._correction(xb, yb)
            rx = xb + dx - target[..., 0]
            ry = yb + dy - target[..., 1]
            J = self._correction_jacobian(xb, yb)
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            step_x = (J[..., 1, 1] * rx - J[..., 0, 1] * ry) / det
            step_y = (-J[..., 1, 0] * rx + J[..., 0, 0] * ry) / det
            xb -= step_x
            yb -= step_y
            if np.all(np.abs(step_x) < 1e-12) and np.all(np.abs(step_y) < 1e-12):
                break
        return np.stack([xb + self.x0_mm, yb + self.y0_mm], axis=-1)

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
