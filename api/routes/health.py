"""Liveness, status and Prometheus metrics."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from api import plant
from api.deps import HubDep, WorkerDep
from api.metrics import prometheus_text

router = APIRouter(tags=["health"])


@router.get("/health", summary="Liveness, device and calibration states, rates, latency, dropped messages")
def get_health(request: Request, worker: WorkerDep, hub: HubDep) -> dict[str, Any]:
    return plant.health_document(request.app, worker, hub)


@router.get("/status", summary="Health plus the configuration in use and the newest result of each camera")
def get_status(request: Request, worker: WorkerDep, hub: HubDep) -> dict[str, Any]:
    s = worker.settings  # the settings in force (PUT /config swaps them there)
    latest = {
        name: {k: d.get(k) for k in ("ok", "reason", "mode", "t_wall", "rms_px", "n_coded", "n_uncoded", "deviation")}
        for name, r in list(worker.latest.items())
        for d in (r.to_dict(targets=False),)
    }
    return {
        **get_health(request, worker, hub),
        "config": s.model_dump(mode="json", exclude={"server": {"token"}, "mqtt": {"password"}}),
        "latest": latest,
    }


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus text exposition")
def get_metrics(request: Request, worker: WorkerDep, hub: HubDep) -> PlainTextResponse:
    text = prometheus_text(worker, hub) + plant.prometheus_lines(request.app)
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4; charset=utf-8")
