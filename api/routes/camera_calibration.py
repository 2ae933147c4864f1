"""Camera self-calibration through the service.

    POST /calibration/camera/solve?apply=      observations in the body (OBS.json), or none: the frames
                                               recorded by the hand-eye session (the same robot poses
                                               serve both calibrations)

The current camera calibration is the start, the current field the datum (inner
constraints on its nominal coordinates, so a slightly wrong field is surveyed
too); the bundle runs in a worker thread, its report comes back, and with
``apply=true`` the new camera is stored (versioned, atomically) and used from
the next frame.
"""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.calib.bundle import ImagePoints, calibrate_camera
from service.core.geometry.camera_model import PARAMETER_NAMES
from service.core.results import Reason, SolveError
from service.runtime.solver_process import SolverCrashed
from service.store.formats import MAX_IMAGE_PX, FormatError
from service.workflows.calibrate_camera import camera_json

router = APIRouter(prefix="/calibration/camera", tags=["camera calibration"])


# a pixel coordinate lies within an image of at most formats.MAX_IMAGE_PX a side
PixelCoordinate = Annotated[float, Field(ge=-MAX_IMAGE_PX, le=MAX_IMAGE_PX, allow_inf_nan=False)]


class Point(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: str
    uv: tuple[PixelCoordinate, PixelCoordinate] = Field(description="u, v in px (DESIGN section 2), finite")


class Image(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    points: list[Point] = Field(min_length=4)


class SolveRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    images: list[Image] | None = Field(None, description="OBS.json images; omit to use the hand-eye session's frames")
    fix: list[str] = Field([], description=f"parameters held fixed, of {list(PARAMETER_NAMES)}")


@router.post("/solve", dependencies=[Authorized], summary="Self-calibrate the camera (bundle adjustment)")
def solve(worker: WorkerDep, req: SolveRequest | None = None, apply: bool = False) -> dict[str, Any]:
    req = req or SolveRequest()
    cal = worker.calibration
    if cal.camera is None or cal.field is None:
        raise ApiError(Reason.not_calibrated, "a start camera and a field are needed", status=409)
    unknown = sorted(set(req.fix) - set(PARAMETER_NAMES))
    if unknown:
        raise ApiError(Reason.bad_input, f"unknown parameters {unknown}; choose from {list(PARAMETER_NAMES)}")
    if req.images is not None:
        images = [
            ImagePoints(im.name, tuple(p.id for p in im.points), np.array([p.uv for p in im.points]))
            for im in req.images
        ]
    else:
        session = getattr(worker, "handeye_session", None)
        if session is None or not session.samples:
            raise ApiError(Reason.not_found, "no observations given and no hand-eye session frames recorded")
        images = [ImagePoints(f"sample{k}", tuple(s.ids), s.uv) for k, s in enumerate(session.samples)]
    unknown_ids = {i for im in images for i in im.ids} - set(cal.field.ids)
    if unknown_ids:
        raise ApiError(Reason.bad_input, f"targets not in the field: {sorted(unknown_ids)[:10]}")
    free = tuple(p for p in PARAMETER_NAMES if p not in req.fix)
    try:
        result = worker.solver.run(partial(calibrate_camera, free=free), cal.camera, cal.field, images)
    except SolveError as e:
        raise ApiError(str(e.reason), e.message, status=422) from None
    except SolverCrashed as e:
        raise ApiError(Reason.solver_unavailable, f"{e}; solve again", status=503) from None
    payload = camera_json(result)
    version = None
    if apply:
        try:
            version = cal.update("camera", payload, note=f"self-calibration over the API, {len(images)} images")
        except FormatError as e:  # a result outside the physical limits is not stored
            raise ApiError(Reason.bad_input, f"the self-calibration is not applied: {e}") from None
        worker.event("info", "calibration_changed", f"camera version {version} from a self-calibration")
    return {
        "ok": True,
        "applied_version": version,
        "sigma0_px": result.sigma0_px,
        "warnings": list(result.warnings),
        "camera": payload,
    }
