"""Typed access to what the lifespan put on ``app.state``; 503 until it is there."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from api.errors import ApiError
from api.ws import Hub
from service.core.results import Reason
from service.runtime.worker import Worker
from service.settings import Settings
from service.store.measurements import MeasurementStore


def get_worker(request: Request) -> Worker:
    worker = getattr(request.app.state, "worker", None)
    if worker is None:
        raise ApiError(Reason.initializing, "the service is starting; try again in a moment")
    return worker


def get_store(request: Request) -> MeasurementStore:
    store = getattr(request.app.state, "store", None)
    if store is None:
        raise ApiError(Reason.initializing, "the service is starting; try again in a moment")
    return store


def get_settings(request: Request) -> Settings:
    """The settings in force: the worker's (its ``PUT /config`` changes swap them whole), never a copy."""
    return get_worker(request).settings


def get_hub(request: Request) -> Hub:
    return request.app.state.hub


WorkerDep = Annotated[Worker, Depends(get_worker)]
StoreDep = Annotated[MeasurementStore, Depends(get_store)]
HubDep = Annotated[Hub, Depends(get_hub)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
