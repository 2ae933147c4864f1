"""``POST /sim/faults``: unplug, plug, stall or garble a device of the simulated cell (tests and demos).

It exists only when the cell is simulated (404 otherwise), needs the token like
every state-changing request, and acts on the simulated drivers the worker
owns, so what follows is exactly what a real outage would cause.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason

router = APIRouter(prefix="/sim", tags=["simulation"])


class FaultRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    device: Literal["camera", "robot"]
    action: Literal["unplug", "plug", "stall", "garble"] = Field(
        description="unplug: the link drops; plug: the device is back, every fault ends; stall (camera): "
        "connected but no frames; garble (camera): frames of noise"
    )
    camera: str | None = Field(None, max_length=100, description="which camera (default: the first)")


@router.post("/faults", dependencies=[Authorized], summary="Inject a device fault into the simulated cell")
def post_fault(worker: WorkerDep, fault: FaultRequest) -> dict[str, Any]:
    if not worker.settings.uses_sim:
        raise ApiError(
            Reason.not_found, "fault injection exists only in the simulated cell; this cell runs real devices"
        )
    try:
        done = worker.inject_fault(fault.device, fault.action, fault.camera)
    except ValueError as e:
        raise ApiError(Reason.bad_input, str(e)) from None
    except LookupError as e:
        raise ApiError(Reason.not_found, str(e.args[0])) from None
    return {"ok": True, "done": done}
