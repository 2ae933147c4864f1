"""The plant interfaces in the app's lifespan: MQTT publishing (``[mqtt]``) and OPC UA (``[opcua]``).

Both are off unless configured, start after the worker and stop before it, and never fail the
service's start: a broker that is not there is retried in the background, an OPC UA port that
is taken is reported in ``/health`` (``opcua.state: failed``) while the cell measures on.

Other code publishes an accuracy-test report with :func:`publish_test_report` (a no-op, False,
when MQTT is off).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Mapping
from typing import Any

from fastapi import FastAPI

from api.ws import Hub
from service.plant.mqtt import MqttPublisher
from service.runtime.worker import Worker
from service.settings import Settings


def health_document(app: FastAPI, worker: Worker, hub: Hub) -> dict[str, Any]:
    """``GET /health``'s document: the worker's, the WebSocket hub's, MQTT's and OPC UA's states."""
    h = worker.health()
    h["websocket"] = hub.stats()
    for name in ("mqtt", "opcua"):
        part = getattr(app.state, name, None)
        if part is not None:
            h[name] = part.stats()
    return h


async def start(app: FastAPI, stack: contextlib.AsyncExitStack, settings: Settings, worker: Worker, hub: Hub) -> None:
    """Start what ``settings`` enable and register their stops on ``stack`` (undone in reverse)."""
    app.state.mqtt = app.state.opcua = None
    if settings.mqtt.broker:
        mqtt = MqttPublisher(settings.mqtt, lambda: health_document(app, worker, hub))
        mqtt.start()
        stack.push_async_callback(asyncio.to_thread, mqtt.stop)
        stack.callback(worker.subscribe(mqtt.on_result))  # unsubscribed before the publisher stops
        app.state.mqtt = mqtt
    if settings.opcua.endpoint:
        from service.plant.opcua import OpcUaServer  # asyncua is imported only when OPC UA is on (0.7 s)

        if settings.log_level != "debug":
            # asyncua logs every session, activation and method call at INFO: a PLC polling the cell
            # would fill the journal
            logging.getLogger("asyncua").setLevel(logging.WARNING)

        opcua = OpcUaServer(
            settings.opcua,
            worker,
            app.state.token,
            lambda: health_document(app, worker, hub),
            tests=lambda: getattr(app.state, "tests", None),  # the tests' router brings its runner up after this
            recordings=lambda: getattr(app.state, "recordings", None),  # so does the recordings' router
            cert_dir=settings.resolved_state_dir() / "opcua",
        )
        opcua.start()
        stack.push_async_callback(asyncio.to_thread, opcua.stop)
        app.state.opcua = opcua


def prometheus_lines(app: FastAPI) -> str:
    """``/metrics``'s MQTT families (Prometheus text 0.0.4), empty when MQTT is off."""
    mqtt = getattr(app.state, "mqtt", None)
    if mqtt is None:
        return ""
    st = mqtt.stats()
    rows = [("posecell_mqtt_up", "gauge", "1 when connected to the broker", int(st["state"] == "connected"))]
    for key, text in (
        ("published", "messages handed to the broker"),
        ("dropped", "messages dropped: broker away or not taking them"),
        ("superseded", "results replaced by a newer one before their period (the rate decimation)"),
        ("reconnects", "reconnections to the broker"),
    ):
        rows.append((f"posecell_mqtt_{key}_total", "counter", text, st[key]))
    return "".join(f"# HELP {n} {t}\n# TYPE {n} {k}\n{n} {v}\n" for n, k, t, v in rows)


def publish_test_report(app: FastAPI, report: Mapping[str, Any] | str | bytes) -> bool:
    """Send an accuracy-test report to ``<prefix>/tests`` (any thread, never blocks); False: MQTT is off."""
    mqtt = getattr(app.state, "mqtt", None)
    if mqtt is None:
        return False
    mqtt.publish_test_report(report)
    return True
