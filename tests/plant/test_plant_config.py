"""The plant interfaces' pure parts: settings that are refused, the PLC's fault from a health document,
the broker URL and topic spelling (no broker, no server: the quick loop runs these)."""

from __future__ import annotations

import pytest

from service.core.results import Reason
from service.plant.mqtt import broker_address, camera_topic_level
from service.plant.opcua import fault_of
from service.settings import MqttConfig, OpcUaConfig


def test_a_topic_prefix_with_wildcards_is_refused():
    with pytest.raises(ValueError, match="topic_prefix"):
        MqttConfig(broker="mqtt://127.0.0.1:1883", topic_prefix="plant/+/cell7")
    with pytest.raises(ValueError, match="broker"):
        MqttConfig(broker="http://127.0.0.1:1883")
    with pytest.raises(ValueError, match="reconnect_max_s"):
        MqttConfig(broker="mqtt://127.0.0.1:1883", reconnect_min_s=5.0, reconnect_max_s=1.0)
    with pytest.raises(ValueError, match="endpoint"):
        OpcUaConfig(endpoint="tcp://127.0.0.1:4840")


def test_broker_urls_and_camera_topic_levels():
    assert broker_address("mqtt://10.0.0.5") == ("10.0.0.5", 1883, False)
    assert broker_address("mqtts://broker.plant:8884") == ("broker.plant", 8884, True)
    assert camera_topic_level("line/2+#") == "line_2__" and camera_topic_level("cam0") == "cam0"


def test_the_fault_comes_from_storage_cameras_and_robot_in_that_order():
    h = {
        "status": "degraded",
        "storage": {"state": "degraded", "error": "database is locked"},
        "cameras": {"cam0": {"state": "disconnected", "error": "unplugged"}},
        "robot": {"state": "disconnected", "error": "no RTDE"},
    }
    assert fault_of(h) == (Reason.storage_unavailable, "database is locked")
    assert fault_of({**h, "storage": {"state": "ok"}}) == (Reason.camera_disconnected, "camera cam0: unplugged")
    assert fault_of({**h, "storage": None, "cameras": {}}) == (Reason.robot_disconnected, "robot: no RTDE")
    no_handeye = {"camera": {"present": True}, "field": {"present": True}, "handeye": {"present": False}}
    assert fault_of({"status": "ok", "calibration": no_handeye}) == (
        Reason.not_calibrated,
        "not calibrated: no handeye calibration",
    )
    assert fault_of({"status": "ok", "problems": [], "cameras": {"cam0": {"state": "ok"}}}) == (None, "")
