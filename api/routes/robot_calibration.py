"""The robot calibration session and its verification over the API (``service/runtime/robot_calibration.py``).

POST   /calibration/robot/session             plan: {mode, n_poses, n_holdout, seed, frames_per_pose, robot}
GET    /calibration/robot/session             status, progress, observability, proposals, samples, result
DELETE /calibration/robot/session
POST   /calibration/robot/session/move/{k}    simulated cell only: move the arm to planned pose k (returns at rest)
POST   /calibration/robot/session/samples     record a sample at the robot's resting pose (?pose=k: the planned one)
DELETE /calibration/robot/session/samples/{i}
POST   /calibration/robot/session/run         simulated cell only: visit, record and solve every pose (202; poll GET)
POST   /calibration/robot/session/solve       identify and report before/after on the hold-out poses
POST   /calibration/robot/session/save        store the model as calibration kind ``robot`` (versioned)
POST   /calibration/robot/verify              re-measure stored poses: drift against the stored model, a verdict
                                              (kept as a test of kind "verify": GET /tests lists it)

The session lives on ``app.state.robot_calibration``, made in this router's lifespan (after the app's
own, which started the worker).
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, FastAPI, Query, Request
from pydantic import ValidationError

from api import plant
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.runtime.handeye_session import SessionError
from service.runtime.robot_calibration import RobotCalibration
from service.store.tests_store import TestStore


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    # each verification's outcome goes to the plant beside the accuracy tests' reports (MQTT <prefix>/tests)
    # each kept in the tests' table too (kind "verify"), on a connection of its own to the database
    tests = TestStore(app.state.store.path)
    app.state.robot_calibration = RobotCalibration(app.state.worker, lambda m: plant.publish_test_report(app, m), tests)
    try:
        yield
    finally:
        app.state.robot_calibration.close()
        tests.close()


router = APIRouter(prefix="/calibration/robot", tags=["robot calibration"], lifespan=lifespan)


def get_calibration(request: Request) -> RobotCalibration:
    rc = getattr(request.app.state, "robot_calibration", None)
    if rc is None:
        raise ApiError(Reason.initializing, "the service is starting; try again in a moment")
    return rc


RobotCalibrationDep = Annotated[RobotCalibration, Depends(get_calibration)]


def _call(fn: Any, *args: Any) -> Any:
    try:
        return fn(*args)
    except SessionError as e:
        raise ApiError(Reason(e.reason), e.message, status=409 if e.reason == Reason.busy else None) from None
    except ValidationError as e:
        problems = "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}" for err in e.errors())
        raise ApiError(Reason.bad_input, f"invalid parameters: {problems}") from None


@router.post("/session", dependencies=[Authorized], summary="Start a session: plan observable poses that see the field")
def start(rc: RobotCalibrationDep, body: Annotated[dict[str, Any] | None, Body()] = None) -> dict[str, Any]:
    return _call(rc.start, body).summary()  # type: ignore[no-any-return]


@router.get("/session", summary="The session: status, observability, proposals, samples, result")
def get(rc: RobotCalibrationDep) -> dict[str, Any]:
    return _call(rc.get).summary()  # type: ignore[no-any-return]


@router.delete("/session", dependencies=[Authorized], summary="Discard the session (a run is cancelled)")
def delete(rc: RobotCalibrationDep) -> dict[str, Any]:
    rc.discard()
    return {"ok": True}


@router.post("/session/move/{index}", dependencies=[Authorized], summary="Simulated cell only: move to a planned pose")
def move(index: int, rc: RobotCalibrationDep) -> dict[str, Any]:
    duration_s = _call(rc.move, index)
    return {"ok": True, "index": index, "duration_s": round(duration_s, 3)}


@router.post("/session/samples", dependencies=[Authorized], summary="Record a sample at the robot's resting pose")
def capture(
    rc: RobotCalibrationDep, pose: Annotated[int | None, Query(ge=0, description="the planned pose it is at")] = None
) -> dict[str, Any]:
    sample = _call(rc.capture, pose)
    return {"ok": True, "sample": sample.to_dict(), "n_samples": len(rc.get().samples)}


@router.delete("/session/samples/{index}", dependencies=[Authorized], summary="Remove a sample")
def remove(index: int, rc: RobotCalibrationDep) -> dict[str, Any]:
    _call(rc.remove, index)
    return {"ok": True}


@router.post(
    "/session/run", dependencies=[Authorized], status_code=202, summary="Simulated cell: visit, record and solve all"
)
def run(rc: RobotCalibrationDep) -> dict[str, Any]:
    return _call(rc.run).summary()  # type: ignore[no-any-return]


@router.post("/session/solve", dependencies=[Authorized], summary="Identify the errors; before/after on the hold-out")
def solve(rc: RobotCalibrationDep) -> dict[str, Any]:
    return _call(rc.solve)  # type: ignore[no-any-return]


@router.post("/session/save", dependencies=[Authorized], summary="Store the identified model (calibration kind robot)")
def save(
    rc: RobotCalibrationDep, note: Annotated[str, Query(max_length=1000, description="kept with the version")] = ""
) -> dict[str, Any]:
    version = _call(rc.save, note)
    return {"ok": True, "kind": "robot", "version": version}


@router.post("/verify", dependencies=[Authorized], summary="Re-measure stored poses: drift against the stored model")
def verify(rc: RobotCalibrationDep, body: Annotated[dict[str, Any] | None, Body()] = None) -> dict[str, Any]:
    return _call(rc.verify, body)  # type: ignore[no-any-return]


# the and an integrator's name for the shift's check: the same call under /tests, beside the
# accuracy tests (registered before /tests/{kind}, whose kinds it would otherwise be taken for)
verify_alias = APIRouter(tags=["accuracy tests"])
verify_alias.add_api_route(
    "/tests/verify",
    verify,
    methods=["POST"],
    dependencies=[Authorized],
    summary="The shift's check (= POST /calibration/robot/verify)",
)
