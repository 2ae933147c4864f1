"""From observations (and later frames) to a :class:`PoseResult`: synchronous, no threads, no I/O."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from service.core.camera_model import BrownFraser
from service.core.field import Field
from service.core.resection import ResectionResult, resect
from service.core.results import PoseResult, TargetObservation


def pose_result_from_resection(
    result: ResectionResult, field: Field, ids: Sequence[str], uv: NDArray[np.float64]
) -> PoseResult:
    """Attach target ids, codes and residuals to a resection result."""
    rows = field.indices_of(list(ids))
    targets = tuple(
        TargetObservation(
            id=tid,
            uv=(float(uv[k, 0]), float(uv[k, 1])),
            residual_px=(float(result.residuals_px[k, 0]), float(result.residuals_px[k, 1])),
            coded=bool(field.codes[rows[k]] >= 0),
            used=bool(result.inliers[k]),
        )
        for k, tid in enumerate(ids)
    )
    return PoseResult(
        T_field_camera=result.T_field_camera,
        sigma_position_mm=result.sigma_position_mm,
        sigma_rotation_deg=result.sigma_rotation_deg,
        rms_px=result.rms_px,
        sigma0_px=result.sigma0_px,
        targets=targets,
        n_iter=result.n_iter,
    )


def resect_observations(
    camera: BrownFraser,
    field: Field,
    ids: Sequence[str],
    uv: NDArray[np.float64],
    *,
    sigma_px: float | None = None,
    T_field_camera_init: NDArray[np.float64] | None = None,
) -> PoseResult:
    """Resection from identified image points ``uv`` (N, 2) px of field targets ``ids``.

    Raises :class:`~service.core.results.SolveError` when no trustworthy pose exists.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    p_field = field.xyz[field.indices_of(list(ids))]
    result = resect(camera, p_field, uv, sigma_px=sigma_px, T_field_camera_init=T_field_camera_init)
    return pose_result_from_resection(result, field, ids, uv)
