"""Accuracy benchmark: the paper's Tables 2 and 3 reproduced by simulation.

Geometry (stated in every table): the reference camera of DESIGN section 7
(1300x1030 px, 6.7 um pixels, c = 12 mm, mild distortion), the reference plate
(30 coded + 200 uncoded targets, z = 0), the camera 1000 mm from the plate
centre. "View angle" is the angle between the optical axis and the plate, as in
the paper (90 deg = head-on). For intersection, a second camera sits 300 mm
along the master's x axis and converges on the plate centre.

Each figure is given twice: predicted (the adjustment's covariance with the
a-priori image precision) and empirical (the standard deviation over seeded
Monte-Carlo trials with Gaussian image noise of that precision).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import apply_T, inv_T
from service.core.pose.intersection import Rig, pose_from_intersection
from service.core.pose.resection import resect
from service.core.targets.field import Field
from service.sim.scene import reference_camera, reference_field, reference_pose

Array = NDArray[np.float64]

BASELINE_MM = 300.0
DISTANCE_MM = 1000.0


@dataclass(frozen=True)
class Sigmas:
    """Predicted and empirical standard deviations of the camera position (3,) mm."""

    predicted_mm: Array
    empirical_mm: Array
    n_points: int


def _visible(camera: BrownFraser, field: Field, T_field_camera: Array) -> tuple[Array, Array]:
    p_camera = apply_T(inv_T(T_field_camera), field.xyz)
    uv = camera.pixel_from_camera(p_camera)
    keep = camera.in_image(uv, margin_px=10.0)
    return field.xyz[keep], uv[keep]


def resection_sigmas(sigma_px: float, view_angle_deg: float, trials: int, rng: np.random.Generator) -> Sigmas:
    camera, field = reference_camera(), reference_field()
    T_true = reference_pose(view_angle_deg=view_angle_deg, distance_mm=DISTANCE_MM)
    p, uv = _visible(camera, field, T_true)
    predicted = resect(camera, p, uv, sigma_px=sigma_px, T_field_camera_init=T_true).sigma_position_mm
    centres = np.empty((trials, 3))
    for k in range(trials):
        noisy = uv + rng.normal(0.0, sigma_px, uv.shape)
        centres[k] = resect(camera, p, noisy, sigma_px=sigma_px, reject_outliers=False).T_field_camera[:3, 3]
    return Sigmas(predicted, centres.std(axis=0, ddof=1), len(p))


def _second_camera_pose(T_field_master: Array) -> Array:
    """A camera BASELINE_MM along the master's x axis, converging on the plate centre."""
    centre = T_field_master[:3, 3] + T_field_master[:3, 0] * BASELINE_MM
    z = -centre / np.linalg.norm(centre)  # look at the field origin (the plate centre)
    x = np.cross(T_field_master[:3, 1], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = centre
    return T


def intersection_sigmas(sigma_px: float, view_angle_deg: float, trials: int, rng: np.random.Generator) -> Sigmas:
    camera, field = reference_camera(), reference_field()
    T_master = reference_pose(view_angle_deg=view_angle_deg, distance_mm=DISTANCE_MM)
    T_second = _second_camera_pose(T_master)
    rig = Rig.from_T_field_camera((camera, camera), np.stack([T_master, T_second]))
    uvs = [camera.pixel_from_camera(apply_T(inv_T(T), field.xyz)) for T in (T_master, T_second)]
    both = camera.in_image(uvs[0], 10.0) & camera.in_image(uvs[1], 10.0)
    p = field.xyz[both]
    uvs = [u[both] for u in uvs]
    predicted = pose_from_intersection(rig, p, uvs, sigma_px=sigma_px).sigma_position_mm
    centres = np.empty((trials, 3))
    for k in range(trials):
        noisy = [u + rng.normal(0.0, sigma_px, u.shape) for u in uvs]
        centres[k] = pose_from_intersection(rig, p, noisy, sigma_px=sigma_px).T_field_master[:3, 3]
    return Sigmas(predicted, centres.std(axis=0, ddof=1), len(p))


def _fmt(v: Array) -> list[str]:
    return [f"{x:.3f}" for x in v]


def table3(trials: int, rng: np.random.Generator) -> str:
    """Resection sigma vs image precision, head-on view (the paper's Table 3)."""
    paper = {5: (0.06, 0.06, 0.02), 10: (0.03, 0.03, 0.009)}
    rows = []
    results = {k: resection_sigmas(1.0 / k, 90.0, trials, rng) for k in (5, 10)}
    for axis, name in enumerate("xyz"):
        row = [f"resection σ{name} (mm)"]
        for k in (5, 10):
            s = results[k]
            row += [f"{paper[k][axis]:.3f}", f"{s.predicted_mm[axis]:.3f}", f"{s.empirical_mm[axis]:.3f}"]
        rows.append("| " + " | ".join(row) + " |")
    n = results[10].n_points
    return "\n".join(
        [
            f"Table 3 — σ of resection, view angle 90°, {DISTANCE_MM:.0f} mm, {n} targets in view, {trials} trials",
            "",
            "| | paper 1/5 px | predicted | Monte Carlo | paper 1/10 px | predicted | Monte Carlo |",
            "|---|---|---|---|---|---|---|",
            *rows,
        ]
    )


def table2(trials: int, rng: np.random.Generator) -> str:
    """Resection vs intersection at 60 and 90 deg view angles, 1/10 px (the paper's Table 2)."""
    paper = {
        ("resection", 60): (0.03, 0.04, 0.08),
        ("resection", 90): (0.5, 0.6, 0.05),
        ("intersection", 60): (0.23, 0.25, 0.32),
        ("intersection", 90): (1.05, 1.10, 0.28),
    }
    sigma_px = 0.1
    res = {}
    for angle in (60, 90):
        res[("resection", angle)] = resection_sigmas(sigma_px, angle, trials, rng)
        res[("intersection", angle)] = intersection_sigmas(sigma_px, angle, max(50, trials // 2), rng)
    lines = [
        f"Table 2 — σ of the camera position (mm) at 1/10 px, {DISTANCE_MM:.0f} mm; "
        f"intersection: 2 cameras, {BASELINE_MM:.0f} mm baseline",
        "",
        "| method | view angle | targets | paper x, y, z | predicted x, y, z | Monte Carlo x, y, z |",
        "|---|---|---|---|---|---|",
    ]
    for (method, angle), s in res.items():
        p = paper[(method, angle)]
        lines.append(
            f"| {method} | {angle}° | {s.n_points} | {', '.join(f'{x:g}' for x in p)} | "
            f"{', '.join(_fmt(s.predicted_mm))} | {', '.join(_fmt(s.empirical_mm))} |"
        )
    return "\n".join(lines)


def run(trials: int, seed: int) -> str:
    rng = np.random.default_rng(seed)
    return table3(trials, rng) + "\n\n" + table2(trials, rng)
