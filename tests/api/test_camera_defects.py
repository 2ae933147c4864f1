"""A camera's defect map in the running service (``[[cameras]] defects``): patched in every frame, said in
/health; a map that does not fit the camera fails each frame with a sentence naming it."""

from __future__ import annotations

import json

import numpy as np
from websockets.sync.client import connect

from service.core.geometry.frames import pose_difference
from service.core.targets.defects import DefectMap
from service.store import formats
from tests.api.conftest import live_settings, run_server


def _map(path, width: int = 1300, height: int = 1030, n: int = 300) -> None:
    rng = np.random.default_rng(3)
    uv = np.unique(np.stack([rng.integers(0, width, n), rng.integers(0, height, n)], axis=1), axis=0)
    formats.write_defects(path, DefectMap(width, height, uv))


def test_the_service_patches_a_cameras_defects_and_says_so(tmp_path):
    _map(tmp_path / "defects.json")
    cameras = [{"frame_rate_hz": 15.0, "defects": str(tmp_path / "defects.json")}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        health = server.wait_for(lambda h: h["processing"]["ok"] >= 5, 120.0, "poses with the defect map")
        report = health["processing"]["measurement"]["cam0"]
        assert report["defects"] == {"file": str(tmp_path / "defects.json"), "pixels": 300}, report
        with connect(f"{server.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
            for _ in range(3):
                msg = json.loads(ws.recv(timeout=10))
                assert msg["ok"], msg
                d_mm = pose_difference(np.array(msg["T_field_camera"]), np.array(msg["truth"]["T_field_camera"]))[0]
                assert d_mm < 0.5, d_mm


def test_a_defect_map_of_another_sensor_fails_each_frame_saying_why(tmp_path):
    _map(tmp_path / "defects.json", width=1000, height=800)
    cameras = [{"frame_rate_hz": 15.0, "defects": str(tmp_path / "defects.json")}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        with connect(f"{server.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
            msg = json.loads(ws.recv(timeout=30))
        assert not msg["ok"] and msg["reason"] == "bad_input", msg
        assert "camera cam0's defect map" in msg["message"] and "1000 x 800 image" in msg["message"], msg
        with server.client() as c:
            assert c.get("/health").json()["processing"]["ok"] == 0
