"""`posecell serve` in a process of its own, publishing to mosquitto, killed: the broker says ``offline``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.plant.mqtt import OFFLINE
from tests.api.conftest import free_port
from tests.plant.conftest import Broker, Subscriber

pytestmark = pytest.mark.slow  # a service process and a broker

POSECELL = Path(sys.executable).with_name("posecell")


def test_the_last_will_offline_is_retained_when_the_service_process_dies(broker: Broker, tmp_path: Path):
    topic = "plant/cell7/health"
    env = {
        **os.environ,
        "POSECELL_SERVER__PORT": str(free_port()),
        "POSECELL_STATE_DIR": str(tmp_path / "state"),
        "POSECELL_SERVER__TOKEN": "e2e",
        "POSECELL_MQTT__BROKER": broker.url,
        "POSECELL_MQTT__TOPIC_PREFIX": "plant/cell7",
        "POSECELL_MQTT__HEALTH_INTERVAL_S": "1",
    }
    sub = Subscriber(broker, (topic,))
    proc = subprocess.Popen(
        [str(POSECELL), "serve"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        alive = sub.wait_for(topic, lambda m: m.payload != OFFLINE and m.json()["status"] == "ok", timeout_s=120)
        assert alive.json()["mqtt"]["state"] == "connected"
        t_kill = time.monotonic()
        proc.send_signal(signal.SIGKILL)  # no goodbye: the kernel closes the socket, the broker sends the will
        proc.wait(10)
        will = sub.wait_for(topic, lambda m: m.payload == OFFLINE, since=t_kill, timeout_s=10)
        assert will.t - t_kill < 5.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        sub.close()
    late = Subscriber(broker, (topic,))
    try:
        assert late.wait_for(topic, lambda m: m.retain, timeout_s=5).payload == OFFLINE, "the will is retained"
    finally:
        late.close()
