"""Conversion between the Brown/Fraser model and OpenCV's pinhole + distortion model.

The two models run in opposite directions (Brown/Fraser corrects measured
coordinates into ideal ones; OpenCV distorts ideal ones into pixels) and differ
in their terms, so neither converts exactly into the other: each conversion is a
least-squares fit over a grid spanning the whole sensor, and reports the fit's
residual in pixels so that a user sees what the conversion costs.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from service.core.geometry.camera_model import BrownFraser

Array = NDArray[np.float64]


@dataclass(frozen=True)
class OpenCVCamera:
    """OpenCV intrinsics: ``K`` (3, 3) px and ``dist`` (5,) = k1, k2, p1, p2, k3; the fit's residuals in px."""

    K: Array
    dist: Array
    rms_px: float
    max_px: float


@dataclass(frozen=True)
class BrownFraserFit:
    """A Brown/Fraser camera fitted to an OpenCV one, with the fit's residuals in px."""

    camera: BrownFraser
    rms_px: float
    max_px: float


def _normalized_from_brown(camera: BrownFraser, uv: Array) -> Array:
    return camera.ideal_from_pixel(uv) / camera.c_mm


def opencv_from_brown(camera: BrownFraser, grid: tuple[int, int] = (41, 33)) -> OpenCVCamera:
    """Fit OpenCV ``K`` and ``dist`` (k1, k2, p1, p2, k3) to ``camera`` over the whole sensor."""
    uv = camera.pixel_grid(*grid)
    n = _normalized_from_brown(camera, uv)
    obj = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    px, py = camera.pixel_size_mm
    cx = (camera.width - 1) / 2 + camera.x0_mm / px
    cy = (camera.height - 1) / 2 + camera.y0_mm / py
    x_init = np.array([camera.c_mm / px, camera.c_mm / py, cx, cy, 0, 0, 0, 0, 0], dtype=np.float64)
    zero = np.zeros(3)

    def residual(x: Array) -> Array:
        K = np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1]])
        proj, _ = cv2.projectPoints(obj, zero, zero, K, x[4:])
        return (proj.reshape(-1, 2) - uv).ravel()

    sol = least_squares(residual, x_init, x_scale="jac", method="lm")
    r = sol.fun.reshape(-1, 2)
    x = sol.x
    K = np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]])
    d = np.linalg.norm(r, axis=1)
    return OpenCVCamera(K=K, dist=x[4:].copy(), rms_px=float(np.sqrt(np.mean(d**2))), max_px=float(d.max()))


def brown_from_opencv(
    K: Array,
    dist: Array,
    width: int,
    height: int,
    pixel_size_mm: tuple[float, float],
    grid: tuple[int, int] = (41, 33),
) -> BrownFraserFit:
    """Fit a Brown/Fraser camera (c, x0, y0, K1-K3, P1, P2, B1) to OpenCV intrinsics.

    ``pixel_size_mm`` fixes the metric scale OpenCV does not carry. fx != fy maps
    onto the affinity B1; OpenCV's rational and prism terms are not represented.
    """
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    px, py = pixel_size_mm
    base = BrownFraser(
        width=width,
        height=height,
        pixel_size_mm=(px, py),
        c_mm=float(K[1, 1] * py),
        x0_mm=float((K[0, 2] - (width - 1) / 2) * px),
        y0_mm=float((K[1, 2] - (height - 1) / 2) * py),
    )
    uv = base.pixel_grid(*grid)
    n = cv2.undistortPointsIter(  # type: ignore[call-overload]  # the stubs do not admit None for R and P
        uv.reshape(-1, 1, 2), K, dist, None, None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ).reshape(-1, 2)
    free = ("c_mm", "x0_mm", "y0_mm", "K1", "K2", "K3", "P1", "P2", "B1")
    scale = np.array([1, 1, 1, 1e-3, 1e-5, 1e-7, 1e-4, 1e-4, 1e-4])

    def camera_of(x: Array) -> BrownFraser:
        return base.with_params(np.append(x * scale, 0.0))

    def residual(x: Array) -> Array:
        cam = camera_of(x)
        return ((cam.ideal_from_pixel(uv) - cam.c_mm * n) / np.asarray(base.pixel_size_mm)).ravel()

    x0 = base.params()[: len(free)] / scale
    sol = least_squares(residual, x0, method="lm", x_scale="jac")
    d = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1)
    return BrownFraserFit(camera=camera_of(sol.x), rms_px=float(np.sqrt(np.mean(d**2))), max_px=float(d.max()))
