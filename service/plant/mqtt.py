"""MQTT publishing into the plant's broker: poses at a fixed rate, retained health, test reports.

Why paho-mqtt and not aiomqtt: the publisher must live *outside* the API's event loop (a broker
that is slow or gone must never cost the loop a millisecond) and outside the measurement thread.
paho's own network thread (``loop_start``) already does the socket I/O, keep-alive, the last will
and the reconnection with a doubling back-off; aiomqtt wraps that same paho client for asyncio,
which would pull the traffic into the loop we want to keep free. So: paho's network thread, plus
one thread of ours that decides *what* to send and when.

What never blocks, and why:

- the measurement thread calls :meth:`MqttPublisher.on_result` for every result: one dict
  assignment under a lock (the newest result per camera; older ones are overwritten, counted as
  ``superseded``), nothing else;
- the publisher thread wakes ``pose_rate_hz`` times a second and hands the newest result of each
  camera to the client, but only while connected: with the broker down a result is dropped and
  counted (``dropped``), never queued; the client's own queue is bounded (``queue_size``);
- test reports (:meth:`publish_test_report`, callable from any thread) wait in a short deque
  (the newest 16) until the broker is there.

Topics (``<prefix>`` is ``topic_prefix``): ``<prefix>/<camera>/pose`` the result without its
target list (``Measurement.json_without_targets``, DESIGN section 4), QoS 0, not retained;
``<prefix>/health`` the ``/health`` document, QoS 1, retained, every ``health_interval_s`` and at
once when its status or problems change, with the retained last will ``offline`` (the broker
publishes it when the connection dies without a goodbye; a clean stop publishes it itself);
``<prefix>/tests`` accuracy-test reports and the robot model's verifications (``kind`` "verify"), QoS 1,
not retained.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import urlsplit

import paho.mqtt.client as paho

from service.core.measurement import Measurement
from service.settings import MqttConfig

log = logging.getLogger(__name__)

OFFLINE = b"offline"  # the retained last will on <prefix>/health
TEST_REPORTS_KEPT = 16  # reports waiting for the broker; older ones are dropped (counted)
HEALTH_CHECK_S = 1.0  # how often the health document is looked at for a change of status
STOP_TIMEOUT_S = 6.0  # a clean stop: the "offline" message, the goodbye, the network thread
_TOPIC_UNSAFE = str.maketrans({"/": "_", "+": "_", "#": "_"})
_instances = itertools.count(1)


def broker_address(url: str) -> tuple[str, int, bool]:
    """``(host, port, tls)`` of a broker URL.

    >>> broker_address("mqtt://127.0.0.1:1883"), broker_address("mqtts://broker.plant")
    (('127.0.0.1', 1883, False), ('broker.plant', 8883, True))
    """
    parts = urlsplit(url)
    if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
        raise ValueError(f"broker {url!r} is not an mqtt:// or mqtts:// URL with a host")
    tls = parts.scheme == "mqtts"
    return parts.hostname, parts.port or (8883 if tls else 1883), tls


def camera_topic_level(camera: str) -> str:
    """A camera name as one topic level: '/', '+' and '#' would change the topic's meaning."""
    return camera.translate(_TOPIC_UNSAFE) or "_"


class MqttPublisher:
    """Publishes a running cell's results and health (see the module docstring).

    ``health`` returns the ``/health`` document; it is called from the publisher thread.
    """

    def __init__(self, config: MqttConfig, health: Callable[[], Mapping[str, Any]]) -> None:
        self.config = config
        self._health = health
        self._host, self._port, tls = broker_address(config.broker)
        self._prefix = config.topic_prefix
        self.health_topic = f"{self._prefix}/health"
        self.tests_topic = f"{self._prefix}/tests"
        self._lock = threading.Lock()
        self._latest: dict[str, Measurement] = {}
        self._reports: deque[bytes] = deque(maxlen=TEST_REPORTS_KEPT)
        self._stop = threading.Event()
        self._health_now = threading.Event()  # set on (re)connection: publish the health at once
        self._thread: threading.Thread | None = None
        self.counters = {"published": 0, "dropped": 0, "superseded": 0, "connects": 0, "reports_dropped": 0}
        self._state = "stopped"
        self._last_error = ""
        # two publishers under one id would take the session from each other in turns (the broker
        # closes the older connection): the default is unique per process and publisher
        client_id = config.client_id or f"posecell-{socket.gethostname()}-{os.getpid()}-{next(_instances)}"
        self._client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=client_id, protocol=paho.MQTTv311)
        if config.username:
            self._client.username_pw_set(config.username, config.password or None)
        if tls:
            self._client.tls_set()  # the system's CA store, the broker's host name checked
        self._client.will_set(self.health_topic, OFFLINE, qos=1, retain=True)
        self._client.reconnect_delay_set(config.reconnect_min_s, config.reconnect_max_s)  # type: ignore[arg-type]
        self._client.max_queued_messages_set(config.queue_size)
        self._client.connect_timeout = min(5.0, float(config.keepalive_s))
        self._client.on_connect = self._on_connect
        self._client.on_connect_fail = self._on_connect_fail
        self._client.on_disconnect = self._on_disconnect

    # --- life cycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Connect in the background (a broker that is not there yet is retried) and start publishing."""
        self._state = "connecting"
        self._client.connect_async(self._host, self._port, keepalive=self.config.keepalive_s)
        self._client.loop_start()
        self._thread = threading.Thread(target=self._run, name="mqtt-publisher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Say ``offline`` (retained), disconnect, end both threads; bounded by ``STOP_TIMEOUT_S``."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S)
            if self._thread.is_alive():
                log.warning("the MQTT publisher did not stop within %.0f s; left behind", STOP_TIMEOUT_S)
            self._thread = None

    # --- what other threads call -------------------------------------------------------------------

    def on_result(self, result: Measurement) -> None:
        """A worker subscriber (the measurement thread): keep the newest result per camera; O(1)."""
        with self._lock:
            if result.camera in self._latest:
                self.counters["superseded"] += 1
            self._latest[result.camera] = result

    def publish_test_report(self, report: Mapping[str, Any] | str | bytes) -> None:
        """Queue an accuracy-test report for ``<prefix>/tests`` (any thread; never blocks).

        A mapping is sent as JSON. Up to ``TEST_REPORTS_KEPT`` reports wait for a broker that is
        away; beyond that the oldest is dropped and counted (``reports_dropped``).
        """
        if isinstance(report, Mapping):
            payload = json.dumps(report, separators=(",", ":"), allow_nan=False, default=str).encode()
        else:
            payload = report.encode() if isinstance(report, str) else bytes(report)
        with self._lock:
            if len(self._reports) == self._reports.maxlen:
                self.counters["reports_dropped"] += 1
            self._reports.append(payload)

    def stats(self) -> dict[str, Any]:
        """The ``mqtt`` section of ``/health``."""
        c = self.counters
        return {
            "state": self._state,
            "broker": self.config.broker,
            "topic_prefix": self._prefix,
            "published": c["published"],
            "dropped": c["dropped"],
            "superseded": c["superseded"],
            "reconnects": max(0, c["connects"] - 1),
            "reports_dropped": c["reports_dropped"],
            "last_error": self._last_error,
        }

    # --- paho's callbacks (its network thread) -------------------------------------------------------

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            self._state = "refused"
            self._last_error = f"the broker {self.config.broker} refused the connection: {reason_code}"
            log.warning("%s", self._last_error)
            return
        self.counters["connects"] += 1
        self._state = "connected"
        self._health_now.set()
        log.info("MQTT connected to %s", self.config.broker)

    def _on_connect_fail(self, client: Any, userdata: Any) -> None:
        self._state = "disconnected"
        self._last_error = f"cannot connect to the broker {self.config.broker}; retrying with back-off"

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if self._stop.is_set():
            self._state = "stopped"
            return
        self._state = "disconnected"
        self._last_error = f"lost the connection to the broker {self.config.broker} ({reason_code}); reconnecting"
        log.warning("%s", self._last_error)

    # --- the publisher thread ----------------------------------------------------------------------

    def _run(self) -> None:
        period_s = 1.0 / self.config.pose_rate_hz
        next_t = time.monotonic()
        next_health_check = next_t
        next_health = next_t
        last_signature: Any = None
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            now = time.monotonic()
            # after a stall (a loaded machine) start afresh rather than catch up in a burst
            next_t = next_t + period_s if next_t + period_s > now else now + period_s
            self._publish_poses()
            self._publish_reports()
            if self._health_now.is_set() or now >= next_health_check:
                next_health_check = now + min(HEALTH_CHECK_S, self.config.health_interval_s)
                doc = self._health_document()
                signature = None if doc is None else (doc.get("status"), tuple(doc.get("problems") or ()))
                if doc is not None and (self._health_now.is_set() or now >= next_health or signature != last_signature):
                    self._health_now.clear()
                    if self._send(self.health_topic, _json_bytes(doc), qos=1, retain=True):
                        last_signature, next_health = signature, now + self.config.health_interval_s
        self._shutdown()

    def _publish_poses(self) -> None:
        with self._lock:
            latest, self._latest = self._latest, {}
        for camera, result in latest.items():
            topic = f"{self._prefix}/{camera_topic_level(camera)}/pose"
            text = result.json_without_targets  # encoded once per result, shared with the WebSocket clients
            self._send(topic, text if isinstance(text, bytes) else text.encode(), qos=0)

    def _publish_reports(self) -> None:
        while self._client.is_connected():
            with self._lock:
                if not self._reports:
                    return
                payload = self._reports.popleft()
            if not self._send(self.tests_topic, payload, qos=1):
                with self._lock:
                    self._reports.appendleft(payload)  # kept for the next connection
                return

    def _health_document(self) -> dict[str, Any] | None:
        try:
            return dict(self._health())
        except Exception:
            log.exception("the health document for MQTT could not be built")
            return None

    def _send(self, topic: str, payload: bytes, qos: int, retain: bool = False) -> bool:
        """Hand one message to the client if connected; otherwise (or if its queue is full) drop and count."""
        if not self._client.is_connected():
            self.counters["dropped"] += 1
            return False
        # paho bounds its QoS 1 queue (max_queued_messages) but not its outgoing packets: a broker that
        # is connected and takes nothing (a stuck process, a full link) would grow them until the
        # keep-alive gives up; its private deque is the only measure of that backlog
        if len(getattr(self._client, "_out_packet", ())) >= self.config.queue_size:
            self.counters["dropped"] += 1
            self._last_error = f"the broker takes nothing: {self.config.queue_size} messages wait; dropping"
            return False
        info = self._client.publish(topic, payload, qos=qos, retain=retain)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            self.counters["dropped"] += 1
            if info.rc == paho.MQTT_ERR_QUEUE_SIZE:
                self._last_error = f"the client's queue of {self.config.queue_size} messages is full; dropping"
            return False
        self.counters["published"] += 1
        return True

    def _shutdown(self) -> None:
        if self._client.is_connected():
            info = self._client.publish(self.health_topic, OFFLINE, qos=1, retain=True)
            try:
                info.wait_for_publish(timeout=2.0)
            except (RuntimeError, ValueError) as e:  # lost the connection meanwhile: the will says it
                log.info("MQTT: the offline message was not confirmed: %s", e)
        self._client.disconnect()
        self._client.loop_stop()
        self._state = "stopped"


def _json_bytes(doc: Mapping[str, Any]) -> bytes:
    # the same document /health serves; a NumPy scalar in it becomes its plain value
    return json.dumps(doc, separators=(",", ":"), default=_plain).encode()


def _plain(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
