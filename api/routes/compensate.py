"""``POST /compensate``: compensated commands for target flange poses, from a corrected robot model.

The same work as ``posecell compensate`` (:mod:`service.workflows.compensate`): the body carries the
targets as JSON rows with the CSV's fields and, optionally, the corrected model (the ``m.json`` of
``posecell calibrate robot``). Without one, the service's stored ``robot`` calibration is used (the
robot calibration session's result, or a ``PUT /calibration/robot``), and the answer names its
version. Pure computation: no device is touched.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Request
from pydantic import BaseModel, ConfigDict, Field

from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason, SolveError
from service.store.formats import FormatError
from service.store.robot_model import robot_model_from_json
from service.workflows.compensate import compensate, targets_from_rows

router = APIRouter(tags=["robot model"])

MAX_TARGETS = 2000  # each is one or two IK solves of ~1 ms; this bounds a request to seconds


class Target(BaseModel):
    """One target flange pose in the base frame: mm and a UR rotation vector (rad); seed joints in deg."""

    model_config = ConfigDict(extra="forbid")
    x_mm: float
    y_mm: float
    z_mm: float
    rx: float
    ry: float
    rz: float
    seed_joint_1: float | None = None
    seed_joint_2: float | None = None
    seed_joint_3: float | None = None
    seed_joint_4: float | None = None
    seed_joint_5: float | None = None
    seed_joint_6: float | None = None


class CompensateRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    targets: list[Target] = Field(min_length=1, max_length=MAX_TARGETS)
    model: dict[str, Any] | None = Field(
        None, description="the corrected model (the m.json of `posecell calibrate robot`); default the stored one"
    )
    max_seed_distance_deg: float = Field(30.0, gt=0.0, le=180.0)


@router.post(
    "/compensate",
    dependencies=[Authorized],
    summary="Joints and Cartesian commands that bring the real arm (the corrected model) to target flange poses",
)
def post_compensate(request: Annotated[CompensateRequest, Body()], http: Request) -> dict[str, Any]:
    # a plain def: FastAPI runs it in its thread pool, so the IK solves do not hold up the event loop
    version: int | None = None
    try:
        if request.model is not None:
            model = robot_model_from_json(request.model, "model")
        else:
            worker = getattr(http.app.state, "worker", None)
            stored = worker.calibration.robot if worker is not None else None
            if stored is None:
                raise ApiError(
                    Reason.not_calibrated,
                    "no robot model is stored: run the robot calibration session (POST /calibration/robot/session), "
                    "upload one with PUT /calibration/robot, or send the corrected model as 'model'",
                )
            model, version = stored, worker.calibration.versions.get("robot")
        T, seeds = targets_from_rows([t.model_dump() for t in request.targets], "targets")
        rows = compensate(model, T, seeds, request.max_seed_distance_deg)
    except FormatError as e:
        raise ApiError(Reason.bad_input, str(e)) from None
    except SolveError as e:
        raise ApiError(e.reason, e.message, rows=e.details.get("rows", [])) from None
    source = "request" if request.model is not None else "stored"
    return {
        "ok": True,
        "robot": model.robot,
        "parameterisation": model.parameterisation,
        "model_source": source,
        "model_version": version,
        "commands": rows,
    }
