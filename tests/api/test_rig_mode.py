"""Two cameras on the flange with a calibrated rig: the service measures by forward intersection."""

from __future__ import annotations

import time

import numpy as np
import pytest

from service.core.geometry.frames import make_T, pose_difference
from service.settings import CameraConfig, load_settings
from tests.api.conftest import free_port, run_server

# the second camera 250 mm to the right of the master, turned 14 deg to look at the same spot
T_MASTER_CAM1 = make_T(
    np.array([[np.cos(-0.245), 0, np.sin(-0.245)], [0, 1, 0], [-np.sin(-0.245), 0, np.cos(-0.245)]]),
    [250.0, 0.0, 0.0],
)


@pytest.fixture(scope="module")
def rig_cell(tmp_path_factory):
    state = tmp_path_factory.mktemp("state-rig")
    cameras = [
        CameraConfig(name="cam0", frame_rate_hz=8.0),
        CameraConfig(
            name="cam1",
            frame_rate_hz=8.0,
            options={"T_master_camera": T_MASTER_CAM1.tolist(), "seed": 7, "serial": "SIM-0002"},
        ),
    ]
    settings = load_settings(
        None, state_dir=str(state), server__port=free_port(), server__token="t", sim__program="hold", cameras=cameras
    )
    yield from run_server(settings)


def test_rig_pose_by_forward_intersection_matches_the_truth(rig_cell):
    live = rig_cell
    live.wait_for(
        lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 4, timeout_s=180.0, what="both cameras measuring"
    )
    cell = live.worker.cell.cell
    with live.client() as c:
        m = c.post("/measure", json={"timeout_s": 5}).json()
        assert m["camera"] in ("cam0", "cam1")  # no rig calibration yet: single cameras answer
        rig = {
            "model": "rig",
            "master": 0,
            "cameras": [cell.camera.to_dict(), cell.camera.to_dict()],
            "T_master_camera": [np.eye(4).tolist(), T_MASTER_CAM1.tolist()],
        }
        r = c.put("/calibration/rig", json=rig)
        assert r.status_code == 200, r.text
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            m = c.post("/measure", json={"timeout_s": 5}).json()
            if m.get("camera") == "rig":
                break
        assert m["camera"] == "rig" and m["ok"] is True, m
        assert m["mode"] == "intersection" and m["n_intersected"] >= 100
        dpos, dang = pose_difference(m["T_field_camera"], m["truth"]["T_field_camera"])
        assert dpos < 0.3 and dang < 0.02
        assert m["deviation"] is not None and m["deviation"]["position_mm"] < 5.0
        assert c.get("/poses/latest", params={"camera": "rig"}).json()["camera"] == "rig"
        bad = c.put("/calibration/rig", json={"model": "rig", "cameras": []})
        assert bad.status_code == 422
