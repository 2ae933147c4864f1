"""Liveness, status and Prometheus metrics."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from api.deps import HubDep, WorkerDep
from api.metrics import prometheus_text

router = APIRouter(tags=["health"])


@router.get("/health", summary="Liveness, device and calibration states, rates, latency, dropped messages")
def get_health(worker: WorkerDep, hub: HubDep) -> dict[str, Any]:
    h = worker.health()
    h["websocket"] = hub.stats()
    return h


@router.get("/status", summary="Health plus the configuration in use and the newest result of each camera")
def get_status(worker: WorkerDep, hub: HubDep) -> dict[str, Any]:
    s = worker.settings  # the settings in force (PUT /config swaps them there)
    latest = {
        name: {k: d.get(k) for k in ("ok", "reason", "mode", "t_wall", "rms_px", "n_coded", "n_uncoded", "deviation")}
        for name, r in list(worker.latest.items())
        for d in (r.to_dict(targets=False),)
    }
    return {
        **get_health(worker, hub),
        "config": s.model_dump(mode="json", exclude={"server": {"token"}}),
        "latest": latest,
    }


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus text exposition")
def get_metrics(worker: WorkerDep, hub: HubDep) -> PlainTextResponse:
    return PlainTextResponse(prometheus_text(worker, hub), media_type="text/plain; version=0.0.4; charset=utf-8")
