"""``create_app(settings)``: the FastAPI application of one cell (no import-time globals).

The lifespan opens the stores, starts the worker (which brings the devices up
in its own threads, so the HTTP side answers at once and reports progress in
``/health``), binds the WebSocket hub to the event loop, and undoes each step
in reverse order on shutdown (one ``AsyncExitStack``). ``READY=1`` goes to
systemd once HTTP is up; device states are reported through ``/health``
rather than by failing the start (a camera that is unplugged at boot must not
put the unit into a restart loop).

The settings in force are the worker's (``worker.settings``, frozen, swapped whole
by ``PUT /config``); routes read them there (``api.deps.SettingsDep``), never a
copy of their own. ``create_app``'s ``settings`` are the configuration file's: the
lifespan applies the saved run-time changes to them and builds the worker with
the result.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import socket
import threading
from collections.abc import AsyncIterator
from functools import partial
from pathlib import Path

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from api import docs, errors, plant
from api.middleware import EdgeGuard, EdgeRules
from api.routes import (
    calibration,
    camera_calibration,
    compensate,
    config,
    corrections,
    data,
    defects,
    handeye,
    health,
    measure,
    recordings,
    robot_calibration,
    sim,
    tests,
)
from api.security import resolve_token
from api.ws import Hub, TapRawSend
from service.runtime.worker import Worker
from service.settings import Settings, apply_runtime_file
from service.store.calibrations import CalibrationStore
from service.store.measurements import MeasurementStore

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"


def _notify_systemd(message: str) -> None:
    """sd_notify without a dependency: one datagram to $NOTIFY_SOCKET, if systemd gave one."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return
    if address.startswith("@"):
        address = "\0" + address[1:]
    with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.sendto(message.encode(), address)


def create_app(settings: Settings) -> FastAPI:
    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with contextlib.AsyncExitStack() as stack:
            state_dir = settings.resolved_state_dir()
            state_dir.mkdir(parents=True, exist_ok=True)
            app.state.token = resolve_token(settings.server.token, state_dir)
            store = MeasurementStore(
                state_dir / settings.storage.database, retention_days=settings.storage.retention_days
            )
            store.start()
            stack.callback(store.close)
            runtime = apply_runtime_file(settings, events=store)  # a bad file: set aside, an event, not applied
            calib_store = CalibrationStore(state_dir / "calibration")
            # loading calibrations may build the simulated cell (a second); keep the loop free
            worker = await asyncio.to_thread(partial(Worker, runtime, store, calib_store=calib_store))
            hub = Hub(stall_timeout_s=settings.server.ws_stall_timeout_s)
            hub.bind(asyncio.get_running_loop())
            app.state.worker, app.state.store, app.state.hub = worker, store, hub
            app.state.calib_store = calib_store
            await asyncio.to_thread(worker.start)
            stack.push_async_callback(asyncio.to_thread, worker.stop)
            stack.callback(worker.subscribe(hub.publish_threadsafe))
            await plant.start(app, stack, settings, worker, hub)  # MQTT and OPC UA, if configured
            # what start-up built (modules, FastAPI's routes, numba's dispatchers: ~10^6 objects) never
            # dies: out of the collector's sight, a full collection no longer stalls every thread for
            # 0.1-0.2 s (the p99 of exposure -> WebSocket)
            gc.freeze()
            gc.set_threshold(50_000, 20, 20)  # few objects live per frame now: collect young ones rarely
            _notify_systemd("READY=1")
            stack.callback(_notify_systemd, "STOPPING=1")
            log.info("posecell serving on %s:%s", settings.server.host, settings.server.port)
            yield

    app = FastAPI(
        title="posecell",
        summary="Real-time photogrammetric robot pose measurement",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,  # served from local assets by api.docs
        redoc_url=None,
    )
    app.state.config_lock = threading.Lock()  # one PUT /config at a time: each applies all of itself or nothing
    errors.install(app)
    # Host, WebSocket Origin, token and body size are checked from the headers before any route runs;
    # CORS (added last, so outermost) puts its headers on those refusals too
    app.add_middleware(EdgeGuard, rules=EdgeRules.of(settings.server), token=lambda: getattr(app.state, "token", None))
    if settings.server.cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=settings.server.cors_origins, allow_methods=["*"], allow_headers=["*"]
        )
    # outermost of all: the WebSocket fan-out writes its frames with the server's own send (api.ws)
    app.add_middleware(TapRawSend)
    # the hand-eye and robot session routes come before /calibration/{kind} so that their paths win
    routers = (
        health,
        measure,
        corrections,
        data,
        config,
        handeye,
        camera_calibration,
        defects,
        robot_calibration,
        calibration,
        sim,
        tests,
        recordings,
    )
    app.include_router(robot_calibration.verify_alias)  # POST /tests/verify, before /tests/{kind}
    for module in (*routers, compensate):
        app.include_router(module.router)
    docs.install(app)
    if STATIC.is_dir():
        app.mount("/", StaticFiles(directory=STATIC, html=True), name="dashboard")
    return app
