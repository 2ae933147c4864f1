"""Measurements: triggered (``POST /measure``), the newest pose, the pose stream and the newest frame."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import STATUS, ApiError
from api.security import Authorized
from service.annotate import encode_frame
from service.core.results import Reason

router = APIRouter(tags=["measurement"])

# a frame that was measured but gave no pose (too few targets, ...) is a 200 with "ok": false;
# these mean that nothing could be measured
_DEVICE_REASONS = {Reason.camera_disconnected, Reason.initializing, Reason.not_calibrated}


class MeasureRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera: str | None = Field(None, description="camera name; all cameras' next frame if omitted (the first result)")
    timeout_s: float = Field(2.0, gt=0, le=30)


def _camera(worker: Any, camera: str | None) -> None:
    if camera is not None and camera not in worker.processors and camera != "rig":
        raise ApiError("not_found", f"no camera named {camera!r}; cameras: {sorted(worker.processors)}")


@router.post("/measure", dependencies=[Authorized],
             summary="One measurement of the next frame exposed after the request "
             "(software-triggered if so configured)")
async def post_measure(worker: WorkerDep, request: MeasureRequest | None = None) -> Any:
    """The result of DESIGN section 4. ``"ok": false`` with a ``reason`` when the frame gave no pose
    (HTTP 200), or when no frame could be measured (503 camera_disconnected, 409 not_calibrated,
    504 timeout)."""
    req = request or MeasureRequest()
    _camera(worker, req.camera)
    fut = worker.request_measurement(req.camera)
    try:
        result: dict[str, Any] = await asyncio.wait_for(asyncio.wrap_future(fut), req.timeout_s)
    except TimeoutError:
        fut.cancel()
        raise ApiError(Reason.timeout, f"no frame was measured within {req.timeout_s} s; see /health") from None
    if not result.get("ok") and result.get("reason") in _DEVICE_REASONS:
        # the cell could not measure at all: an HTTP error status, with the same result body
        return JSONResponse(result, status_code=STATUS[result["reason"]])
    return result


@router.get("/poses/latest", summary="The newest result (of one camera, or the newest of all)")
def get_latest(worker: WorkerDep, camera: str | None = None) -> dict[str, Any]:
    _camera(worker, camera)
    results = [worker.latest[camera]] if camera in worker.latest else list(worker.latest.values())
    if not results:
        raise ApiError(Reason.no_frame, "no frame has been measured yet; see /health")
    return max(results, key=lambda r: r.get("t_exposure_host_ns", 0))


@router.get("/frames/latest", response_class=Response, summary="The newest frame with its measured targets drawn",
            responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}})
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
    data, media = encode_frame(frame.image, result if annotate else None, format, max_width)
    return Response(data, media_type=media, headers={"Cache-Control": "no-store"})


@router.websocket("/ws/poses")
async def ws_poses(
    websocket: WebSocket,
    camera: str | None = None,
    max_rate_hz: Annotated[float | None, Query(gt=0, le=1000)] = None,
    targets: bool = True,
) -> None:
    """Every result as a JSON text message; ``max_rate_hz`` decimates; ``targets=false`` leaves the
    per-target list out; slow clients lose the oldest messages."""
    hub = websocket.app.state.hub
    await websocket.accept()
    client = hub.add(camera, max_rate_hz, targets)  # subscribe first, then backfill: no result falls between
    try:
        worker = websocket.app.state.worker
        latest = [r for n, r in list(worker.latest.items()) if camera in (None, n)]
        for r in latest:
            await websocket.send_json(r if targets else {k: v for k, v in r.items() if k != "targets"})
        while True:
            text = await client.queue.get()
            await websocket.send_text(text)
            client.sent += 1
    except (WebSocketDisconnect, RuntimeError):
        pass  # a client going away is normal
    finally:
        hub.remove(client)
