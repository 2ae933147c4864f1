"""Measurements: triggered (``POST /measure``), the newest pose, the pose stream and the newest frame."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import STATUS, ApiError
from api.security import Authorized
from api.ws import FrameWriter, StalledClient
from service.core.results import Reason
from service.workflows.annotate import encode_frame

router = APIRouter(tags=["measurement"])

# a frame that was measured but gave no pose (too few targets, ...) is a 200 with "ok": false;
# these mean that nothing could be measured (or nothing current is there to serve)
_DEVICE_REASONS = {Reason.camera_disconnected, Reason.initializing, Reason.not_calibrated, Reason.stale}
_STATUS = {**STATUS, Reason.stale: 503, Reason.storage_unavailable: 503}


class MeasureRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera: str | None = Field(None, description="camera name; all cameras' next frame if omitted (the first result)")
    timeout_s: float = Field(2.0, gt=0, le=30)


def _camera(worker: Any, camera: str | None) -> None:
    if camera is not None and camera not in worker.processors and camera != "rig":
        raise ApiError(Reason.not_found, f"no camera named {camera!r}; cameras: {sorted(worker.processors)}")


@router.post(
    "/measure",
    dependencies=[Authorized],
    summary="One measurement of the next frame exposed after the request (software-triggered if so configured)",
)
async def post_measure(worker: WorkerDep, request: MeasureRequest | None = None) -> Any:
    """The result of DESIGN section 4. ``"ok": false`` with a ``reason`` when the frame gave no pose
    (HTTP 200), or when no frame could be measured (503 camera_disconnected, 409 not_calibrated,
    504 timeout). A 200 is an acknowledgement: the result is committed (and fsynced) in the
    database as row ``measurement_id``; otherwise 503 storage_unavailable."""
    req = request or MeasureRequest()
    _camera(worker, req.camera)
    deadline = time.monotonic() + req.timeout_s
    fut = worker.request_measurement(req.camera)
    try:
        answer = await asyncio.wait_for(asyncio.wrap_future(fut), req.timeout_s)
    except TimeoutError:
        fut.cancel()
        raise ApiError(Reason.timeout, f"no frame was measured within {req.timeout_s} s; see /health") from None
    result = answer.result
    if not result.ok and result.reason in _DEVICE_REASONS:
        # the cell could not measure at all: an HTTP error status, with the same result body
        return JSONResponse(result.to_dict(), status_code=_STATUS[result.reason])
    stored, why = await asyncio.to_thread(worker.wait_stored, answer, deadline - time.monotonic())
    if not stored:
        raise ApiError(
            Reason.storage_unavailable,
            why,
            status=_STATUS[Reason.storage_unavailable],
            camera=result.camera,
            t_exposure_host_ns=result.t_exposure_host_ns,
        )
    return JSONResponse({**result.to_dict(), "measurement_id": answer.stored_seq})


@router.get(
    "/poses/latest",
    summary="The newest result (of one camera, or the newest of all), with its age",
    responses={
        503: {
            "description": "no current result: the camera is down (camera_disconnected) or the "
            "newest result is older than a few frame periods (stale; its values are kept)"
        }
    },
)
def get_latest(worker: WorkerDep, camera: str | None = None) -> Any:
    _camera(worker, camera)
    result = worker.current(camera)
    if result is None:
        raise ApiError(Reason.no_frame, "no frame has been measured yet; see /health")
    status = _STATUS[result.reason] if not result.ok and result.reason in _DEVICE_REASONS else 200
    return JSONResponse(result.to_dict(), status_code=status)


@router.get(
    "/frames/latest",
    response_class=Response,
    summary="The newest frame with its measured targets drawn",
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}},
)
def get_frame(
    worker: WorkerDep,
    camera: str | None = None,
    format: Annotated[str, Query(pattern="^(png|jpeg)$")] = "jpeg",
    annotate: bool = True,
    max_width: Annotated[int, Query(ge=64, le=8192)] = 1600,
) -> Response:
    _camera(worker, camera)
    name = camera or next(iter(worker.latest_frame), None)
    if name is None or name not in worker.latest_frame:
        raise ApiError(Reason.no_frame, "no frame has arrived yet; see /health")
    frame, result = worker.latest_frame[name]
    data, media = encode_frame(frame.image, result.to_dict() if annotate else None, format, max_width)
    return Response(data, media_type=media, headers={"Cache-Control": "no-store"})


@router.websocket("/ws/poses")
async def ws_poses(
    websocket: WebSocket,
    camera: str | None = None,
    max_rate_hz: Annotated[float | None, Query(gt=0, le=1000)] = None,
    targets: bool = True,
) -> None:
    """Every result as a JSON text message; ``max_rate_hz`` decimates; ``targets=false`` leaves the
    per-target list out; slow clients lose the oldest messages, and a client that reads nothing for
    ``server.ws_stall_timeout_s`` is disconnected (close code 1008). The first message is the newest
    result with its ``age_s`` (``"stale": true`` when it is no longer current); during a camera
    outage an outage result arrives once a second."""
    hub = websocket.app.state.hub
    worker = websocket.app.state.worker
    await websocket.accept()
    client = hub.add(camera, max_rate_hz, targets)  # subscribe first, then backfill: no result falls between
    client.writer = FrameWriter.of(websocket)
    try:
        current = worker.current(camera)
        if current is not None:
            await hub.send(websocket, client, current.json if targets else current.json_without_targets)
        while True:
            client.busy = False  # the fan-out may write to the socket itself while nothing is held here
            text = await client.queue.get()
            client.busy = True
            await hub.send(websocket, client, text)
    except StalledClient as e:
        worker.event("warning", "websocket_client_stalled", str(e))
    except (WebSocketDisconnect, RuntimeError):
        pass  # a client going away is normal
    finally:
        hub.remove(client)
