"""The guided hand-eye calibration over the API (see ``service/runtime/handeye_session.py`` for the steps).

POST   /calibration/handeye/session            plan: proposed flange poses around the field
GET    /calibration/handeye/session            proposals, samples, motion quality, result
POST   /calibration/handeye/session/move/{k}   simulated cell only: move the arm to proposal k
POST   /calibration/handeye/session/samples    record a sample at the robot's current (resting) pose
DELETE /calibration/handeye/session/samples/{k}
POST   /calibration/handeye/session/solve      solve X and Z; ?apply=true stores and uses the result
GET    /calibration/handeye/session/export     samples for `posecell calibrate handeye --samples`
DELETE /calibration/handeye/session
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason, SolveError
from service.runtime.arm import ARRIVAL_MARGIN_S, ArmBusy
from service.runtime.handeye_session import HandEyeSession, SessionError
from service.runtime.solver_process import SolverCrashed
from service.store.formats import FormatError

router = APIRouter(prefix="/calibration/handeye/session", tags=["hand-eye calibration"])


def _err(e: SessionError) -> ApiError:
    return ApiError(Reason(e.reason), e.message)  # its status: api/errors.STATUS


def _session(worker: Any) -> HandEyeSession:
    s = getattr(worker, "handeye_session", None)
    if s is None:
        raise ApiError(Reason.not_found, "no hand-eye session; start one with POST /calibration/handeye/session")
    return s


class StartRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera: str | None = None
    n_poses: int = Field(12, ge=3, le=60)


@router.post("", dependencies=[Authorized], summary="Start a session: propose robot poses around the field")
def start(worker: WorkerDep, req: StartRequest | None = None) -> dict[str, Any]:
    req = req or StartRequest()
    camera = req.camera or next(iter(worker.processors))
    if camera not in worker.processors:
        raise ApiError(Reason.not_found, f"no camera named {camera!r}")
    try:
        worker.handeye_session = HandEyeSession.start(worker, camera, req.n_poses)
    except SessionError as e:
        raise _err(e) from None
    worker.solver.start()  # the solve at the end of the session finds its process ready
    worker.event("info", "handeye_session", f"hand-eye session started with {req.n_poses} proposed poses")
    return worker.handeye_session.summary()


@router.get("", summary="The session: proposals, samples, motion quality, result")
def get(worker: WorkerDep) -> dict[str, Any]:
    return _session(worker).summary()


@router.delete("", dependencies=[Authorized], summary="Discard the session")
def delete(worker: WorkerDep) -> dict[str, Any]:
    s = getattr(worker, "handeye_session", None)
    worker.handeye_session = None
    if s is not None:
        s.discard()
    return {"ok": True}


@router.post("/move/{index}", dependencies=[Authorized], summary="Simulated cell only: move the arm to a proposal")
def move(index: int, worker: WorkerDep) -> dict[str, Any]:
    s = _session(worker)
    if not 0 <= index < len(s.proposals):
        raise ApiError(Reason.not_found, f"no proposal #{index}; there are {len(s.proposals)}")
    move_to = getattr(worker.robot, "move_to", None)
    if move_to is None:
        raise ApiError(
            Reason.unsupported,
            "this robot is moved by its own program: send it to the proposed "
            "T_base_flange (ur_pose_m_rotvec for UR), then record a sample",
            status=409,
        )
    try:
        arm = worker.arm.claim(f"the hand-eye session's move to proposal #{index}")
    except ArmBusy as e:
        raise ApiError(Reason.busy, str(e), status=409) from None
    duration_s = 0.0
    try:
        duration_s = move_to(s.proposals[index])
    except SolveError as e:
        raise ApiError(str(e.reason), f"proposal #{index} is not reachable: {e.message}", status=422) from None
    finally:
        # the move is not waited for here: the claim ends when the arm has arrived (it starts in 0.05 s)
        worker.arm.release(arm, after_s=duration_s + ARRIVAL_MARGIN_S if duration_s > 0 else 0.0)
    return {"ok": True, "index": index, "duration_s": round(duration_s, 3)}


@router.post("/samples", dependencies=[Authorized], summary="Record a sample at the robot's current resting pose")
def capture(worker: WorkerDep) -> dict[str, Any]:
    s = _session(worker)
    try:
        sample = s.capture(worker)
    except SessionError as e:
        raise _err(e) from None
    except TimeoutError:
        raise ApiError(Reason.timeout, "no frame was measured within 5 s; see /health") from None
    return {"ok": True, "index": len(s.samples) - 1, "sample": sample.to_dict(), "n_samples": len(s.samples)}


@router.delete("/samples/{index}", dependencies=[Authorized], summary="Remove a sample")
def remove(index: int, worker: WorkerDep) -> dict[str, Any]:
    try:
        _session(worker).remove(index)
    except SessionError as e:
        raise _err(e) from None
    return {"ok": True}


@router.post("/solve", dependencies=[Authorized], summary="Solve X and Z; apply=true stores and uses the result")
def solve(worker: WorkerDep, apply: bool = False) -> dict[str, Any]:
    s = _session(worker)
    try:
        result = s.solve(worker.calibration.camera, worker.calibration.field, run=worker.solver.run)
        if apply:
            try:
                version = worker.calibration.update("handeye", s.handeye_payload(), note="hand-eye session")
            except FormatError as e:  # a result outside the physical limits is not stored
                raise ApiError(Reason.bad_input, f"the hand-eye result is not applied: {e}") from None
            worker.event("info", "calibration_changed", f"hand-eye version {version} from a session")
            why = s.applied(version)
            if why:
                worker.event("warning", "session_not_stored", why)
                result = {**result, "session_storage_error": why}
    except SessionError as e:
        raise _err(e) from None
    except SolverCrashed as e:
        raise ApiError(Reason.solver_unavailable, f"{e}; the samples are kept, solve again", status=503) from None
    return {**result, "applied_version": s.applied_version}


@router.get("/export", summary="The samples, as `posecell calibrate handeye --samples` reads them")
def export(worker: WorkerDep) -> dict[str, Any]:
    return _session(worker).export()
