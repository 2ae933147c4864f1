"""Planning the robot poses of a hand-eye calibration from where the robot stands now.

Tsai–Lenz and the joint refinement need rotations about well-spread axes by
large angles (Tsai and Lenz 1989: the error falls with the angle between the
rotation axes and with the rotation angle). So the plan orbits the camera
around the field's centre: tilted 15–35° from the current viewing direction
towards azimuths spread evenly around the circle, rolled alternately by up to
±60° about the optical axis, at the current distance ±12 %. Every proposal is
checked to keep enough targets in the image with the camera model.

Only a guess of the hand-eye is needed (``X_guess``; identity means "the
camera sits at the flange looking along the tool axis"): an error of ~100 mm
or a few degrees only shifts the point the camera looks at.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T, inv_T, make_T
from service.core.geometry.so3 import R_from_rotvec
from service.core.results import Reason, SolveError
from service.core.targets.field import Field
from service.core.targets.identify import project_field

Array = NDArray[np.float64]


def _look_at(p_eye: Array, p_target: Array, up_hint: Array) -> Array:
    """Camera rotation (columns x, y, z in the field frame) with z from eye to target, x ⟂ ``up_hint``."""
    z = p_target - p_eye
    z /= np.linalg.norm(z)
    x = np.cross(up_hint, z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def propose_views(
    camera: BrownFraser,
    field: Field,
    T_field_camera_now: ArrayLike,
    n: int = 12,
    tilt_deg: tuple[float, ...] = (15.0, 25.0, 35.0),
    max_roll_deg: float = 60.0,
    distance_spread: float = 0.12,
    min_targets: int = 20,
) -> list[Array]:
    """Camera poses ``T_field_camera`` (4, 4) mm for a hand-eye calibration around the current view.

    Raises ``SolveError(degenerate_geometry)`` when fewer than ``n`` views keep
    ``min_targets`` targets in the image (the camera is too close, or the field too small).
    """
    T_now = check_T(T_field_camera_now, "T_field_camera_now")
    if n < 3:
        raise ValueError("a hand-eye calibration needs at least 3 poses")
    rows, _ = project_field(camera, field, T_now, margin_px=5.0)
    centre = field.xyz[rows].mean(axis=0) if len(rows) else field.xyz.mean(axis=0)
    eye_now = T_now[:3, 3]
    d0 = float(np.linalg.norm(centre - eye_now))
    axis_now = (eye_now - centre) / d0  # from the target point back to the camera
    # a direction perpendicular to the viewing axis, to tilt away from
    perp = np.cross(axis_now, T_now[:3, 0])
    perp /= np.linalg.norm(perp)
    up_now = -T_now[:3, 1]  # image up of the current view
    out: list[Array] = []
    k = 0
    while len(out) < n and k < 6 * n:
        tilt = np.radians(tilt_deg[k % len(tilt_deg)])
        azimuth = 2 * np.pi * (k * 0.618034 % 1.0)  # golden-ratio spread of azimuths, no repeats
        roll = np.radians(max_roll_deg) * np.sin(2.399963 * k)  # spread over ±max_roll, alternating
        distance = d0 * (1.0 + distance_spread * np.cos(1.7 * k + 0.5))
        k += 1
        tilt_axis = R_from_rotvec(azimuth * axis_now) @ perp
        axis = R_from_rotvec(tilt * tilt_axis) @ axis_now
        eye = centre + distance * axis
        R = _look_at(eye, centre, up_now) @ R_from_rotvec([0.0, 0.0, roll])
        T = make_T(R, eye)
        if len(project_field(camera, field, T, margin_px=10.0)[0]) >= min_targets:
            out.append(T)
    if len(out) < n:
        raise SolveError(
            Reason.degenerate_geometry,
            f"only {len(out)} of {n} proposed views keep {min_targets} targets in the image; "
            "move the camera further from the field or use a larger field",
        )
    return out


def flange_poses_for_views(
    T_field_camera_views: list[Array], T_base_flange_now: ArrayLike, T_field_camera_now: ArrayLike, X_guess: ArrayLike
) -> list[Array]:
    """Flange poses that put the camera at the planned views, through the guessed hand-eye.

    The field's place in the base frame follows from the current pair:
    ``Z ≈ T_base_flange_now @ X_guess @ inv(T_field_camera_now)``.
    """
    X = check_T(X_guess, "X_guess")
    Z = check_T(T_base_flange_now, "T_base_flange_now") @ X @ inv_T(check_T(T_field_camera_now))
    X_inv = inv_T(X)
    return [Z @ T @ X_inv for T in T_field_camera_views]
