"""``/ws/corrections``: the online correction stream for an external-control interface.

One JSON message per frame of the camera: the offset (base frame, mm) to add to the commanded
flange position so that the real flange lands where it is commanded, or ``hold`` and why
(:mod:`service.core.robot.online_correction`: smoothed, bounded, with a watchdog). While no frame
comes, the watchdog still speaks: a ``stale`` hold is sent within ``watchdog_ms`` of the last
usable frame. It drives a robot, so it takes the API token (``Authorization: Bearer``), unlike
``/ws/poses``. A client that falls behind loses the oldest messages: a correction is only as good
as it is new.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated, Any

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect

from api.security import UNAUTHORIZED, token_matches
from service.core.measurement import Measurement
from service.core.robot.online_correction import Correction, CorrectionFilter, CorrectionLimits

router = APIRouter(tags=["measurement"])

QUEUE_SIZE = 8  # frames waiting for a slow client; older ones are dropped


def _message(c: Correction, camera: str, m: Measurement | None) -> str:
    dev = None if m is None or m.flange is None else m.flange.deviation
    return json.dumps(
        {
            "camera": camera,
            "seq": None if m is None else m.seq,
            "t_exposure_unix_ns": None if m is None else m.t_unix_ns,
            "state": c.state,
            "offset_mm": [round(float(v), 4) for v in c.offset_mm],
            "reason": c.reason or None,
            "message": c.message or None,
            "deviation_mm": None if dev is None else [round(float(v), 4) for v in dev.vector_mm],
        },
        separators=(",", ":"),
    )


@router.websocket("/ws/corrections")
async def ws_corrections(
    websocket: WebSocket,
    camera: str | None = None,
    max_mm: Annotated[float, Query(gt=0, le=50)] = 2.0,
    max_deg: Annotated[float, Query(gt=0, le=10)] = 0.5,
    gain: Annotated[float, Query(gt=0, le=1)] = 0.5,
    watchdog_ms: Annotated[float, Query(ge=10, le=10_000)] = 250.0,
) -> None:
    """The offsets to apply, one message per frame (see the module docstring); closes with 1008 without
    the token or for an unknown camera."""
    app: Any = websocket.app
    worker = app.state.worker
    name = camera or next(iter(worker.processors), None)
    refusal = ""
    if not token_matches(websocket.headers.get("authorization"), getattr(app.state, "token", None)):
        refusal = UNAUTHORIZED
    elif name not in worker.processors:
        refusal = f"no camera {camera!r}; the cameras are {', '.join(worker.processors)}"
    if refusal or name is None:  # accepted, then closed with the sentence (a refused handshake says only 403)
        await websocket.accept()
        await websocket.close(code=1008, reason=(refusal or "no camera is configured")[:120])
        return
    limits = CorrectionLimits(max_mm=max_mm, max_deg=max_deg, gain=gain, watchdog_s=watchdog_ms * 1e-3)
    loop = asyncio.get_running_loop()
    frames: asyncio.Queue[Measurement] = asyncio.Queue(QUEUE_SIZE)

    def put(m: Measurement) -> None:  # in the event loop
        if frames.full():
            frames.get_nowait()
        frames.put_nowait(m)

    def on_result(m: Measurement) -> None:  # the processing thread: never blocks
        if m.camera == name and m.t_exposure_host_ns is not None:
            loop.call_soon_threadsafe(put, m)

    await websocket.accept()
    unsubscribe = worker.subscribe(on_result)
    correction = CorrectionFilter(limits)
    try:
        while True:
            try:
                m = await asyncio.wait_for(frames.get(), timeout=limits.watchdog_s / 2)
            except TimeoutError:
                stale = correction.check(time.monotonic_ns() * 1e-9)
                if stale is not None:
                    await websocket.send_text(_message(stale, name, None))
                continue
            t_ns = m.t_exposure_host_ns
            if t_ns is None:  # an outage notice: no frame (on_result passes none; the type allows it)
                continue
            f = m.flange
            dev = None if f is None else f.deviation
            why = m.message if not m.ok else ("" if f is None else f.message)
            c = correction.update(
                t_ns * 1e-9,
                None if dev is None else dev.vector_mm,
                None if dev is None else dev.angle_deg,
                why or "",
            )
            await websocket.send_text(_message(c, name, m))
    except (WebSocketDisconnect, RuntimeError):
        pass  # a client going away is normal
    finally:
        unsubscribe()
