"""Recordings of the cameras' frames and the robot's poses (see ``service/runtime/recorder.py``).

POST   /recordings               start one: 202 {id, state "recording", folder, cameras, ...}
GET    /recordings               every recording, newest first
GET    /recordings/{id}          its state and counts (frames written and dropped per camera, robot samples)
POST   /recordings/{id}/stop     end it now (what was accepted is written first)
DELETE /recordings/{id}          remove it and its files (refused while it runs)

A recording's camera folder is what the ``replay`` camera plays: ``[[cameras]] driver = "replay"``,
``options = { source = "<folder>/<camera>" }``.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Request
from pydantic import BaseModel, ConfigDict, Field

from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.runtime.recorder import RecordingError, RecordingRequest, Recordings


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    worker = app.state.worker
    app.state.recordings = Recordings(
        worker.settings.resolved_state_dir() / "recordings",
        worker.cameras,
        lambda: None if worker.robot is None else worker.robot.history,
        worker.event,
        describe=lambda: _latencies(worker.settings),
    )
    try:
        yield
    finally:
        app.state.recordings.close()


def _latencies(settings: Any) -> dict[str, Any]:
    """The stated delivery delays the pairing used: a replay in step needs the same to pair the same."""
    return {
        "robot_transport_latency_s": settings.robot.transport_latency_s,
        "camera_transport_latency_s": {c.name: c.transport_latency_s for c in settings.cameras},
    }


router = APIRouter(prefix="/recordings", tags=["recordings"], lifespan=lifespan)


def get_recordings(request: Request) -> Recordings:
    recordings = getattr(request.app.state, "recordings", None)
    if recordings is None:
        raise ApiError(Reason.initializing, "the service is starting; try again in a moment")
    return recordings


RecordingsDep = Annotated[Recordings, Depends(get_recordings)]


def _call(fn: Any, *args: Any) -> Any:
    try:
        return fn(*args)
    except RecordingError as e:
        raise ApiError(e.reason, e.message, status=409 if e.reason is Reason.busy else None) from None


class RecordingBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    cameras: list[str] = Field(default_factory=list, description="cameras to record; all when empty")
    max_frames: int = Field(1000, ge=1, le=1_000_000, description="frames a camera at most")
    max_seconds: float = Field(60.0, gt=0, le=86_400)
    every_n: int = Field(1, ge=1, le=10_000, description="every n-th frame the camera delivers")
    format: Literal["pgm", "png", "tiff"] = "pgm"
    label: str = Field("", max_length=200)


@router.post("", dependencies=[Authorized], status_code=202, summary="Start recording frames and robot poses")
def start(recordings: RecordingsDep, body: RecordingBody | None = None) -> dict[str, Any]:
    b = body or RecordingBody()
    request = RecordingRequest(tuple(b.cameras), b.max_frames, b.max_seconds, b.every_n, b.format, b.label)
    summary: dict[str, Any] = _call(recordings.start, request)
    return summary


@router.get("", summary="The recordings, newest first")
def list_recordings(recordings: RecordingsDep) -> dict[str, Any]:
    return {"recordings": recordings.list()}


@router.get("/{rec_id}", summary="A recording: state, frames written and dropped per camera, robot samples")
def get(rec_id: str, recordings: RecordingsDep) -> dict[str, Any]:
    summary: dict[str, Any] = _call(recordings.get, rec_id)
    return summary


@router.post("/{rec_id}/stop", dependencies=[Authorized], summary="End a recording now")
def stop(rec_id: str, recordings: RecordingsDep) -> dict[str, Any]:
    summary: dict[str, Any] = _call(recordings.stop, rec_id)
    return summary


@router.delete("/{rec_id}", dependencies=[Authorized], summary="Remove a recording and its files")
def delete(rec_id: str, recordings: RecordingsDep) -> dict[str, Any]:
    _call(recordings.delete, rec_id)
    return {"ok": True, "id": rec_id}
