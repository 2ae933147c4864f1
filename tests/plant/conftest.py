"""Real plant parts for the plant tests: Debian's mosquitto on a free loopback port, a paho subscriber.

``deploy/dev.sh setup`` installs mosquitto (it is in the script's apt package list); each broker
here has a configuration of its own in a temporary folder and is stopped by the test that started it.
"""

from __future__ import annotations

import json
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest

from service.core.measurement import Measurement
from service.core.results import Failure, Reason
from tests.api.conftest import free_port

MOSQUITTO = Path("/usr/sbin/mosquitto")


class Broker:
    """One mosquitto process on ``127.0.0.1:<port>``; ``stop`` and ``start`` again keep the port."""

    def __init__(self, folder: Path) -> None:
        if not MOSQUITTO.exists():
            pytest.fail(f"{MOSQUITTO} is missing: run `bash deploy/dev.sh setup` (it installs Debian's mosquitto)")
        self.port = free_port()
        self.url = f"mqtt://127.0.0.1:{self.port}"
        self.conf = folder / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        self.log = folder / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 10.0) -> None:
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen([str(MOSQUITTO), "-c", str(self.conf)], stdout=log, stderr=log)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}: {self.log.read_text()[-500:]}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"mosquitto did not listen on port {self.port} within {timeout_s} s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(10)
        self.proc = None


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Broker]:
    b = Broker(tmp_path_factory.mktemp("mosquitto"))
    b.start()
    try:
        yield b
    finally:
        b.stop()


@dataclass
class Received:
    topic: str
    payload: bytes
    retain: bool
    t: float  # time.monotonic() on arrival

    def json(self) -> Any:
        return json.loads(self.payload)


@dataclass
class Subscriber:
    """A real MQTT client that records every message it gets, with its arrival time."""

    broker: Broker
    topics: tuple[str, ...]
    messages: list[Received] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv311)
        self.client.on_connect = lambda c, *_: c.subscribe([(t, 1) for t in self.topics])
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(0.1, 0.5)  # type: ignore[arg-type]
        self.client.connect_async("127.0.0.1", self.broker.port, keepalive=5)
        self.client.loop_start()
        assert self._subscribed.wait(10), "the test subscriber could not subscribe"

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        with self._lock:
            self.messages.append(Received(msg.topic, bytes(msg.payload), bool(msg.retain), time.monotonic()))

    def on(self, topic: str, since: float = 0.0) -> list[Received]:
        with self._lock:
            return [m for m in self.messages if m.topic == topic and m.t >= since]

    def wait_for(self, topic: str, predicate: Any = None, since: float = 0.0, timeout_s: float = 15.0) -> Received:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.on(topic, since):
                if predicate is None or predicate(m):
                    return m
            time.sleep(0.02)
        got = [(m.topic, m.payload[:80]) for m in self.on(topic, since)][-5:]
        raise AssertionError(f"no matching message on {topic} within {timeout_s} s; the last ones: {got}")

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def a_measurement(seq: int = 1) -> Measurement:
    """A small real result (a frame that gave no pose), for the publishers on their own."""
    now = time.time_ns()
    return Measurement(
        camera="cam0",
        result=Failure(Reason.too_few_targets, "3 targets found, 6 needed"),
        t_unix_ns=now,
        t_exposure_host_ns=time.monotonic_ns(),
        seq=seq,
    )
