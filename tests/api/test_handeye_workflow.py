"""The guided hand-eye calibration, end to end over HTTP in the simulated cell."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from service.core.geometry.frames import pose_difference
from service.settings import load_settings
from tests.api.conftest import free_port, run_server


@pytest.fixture(scope="module")
def uncalibrated(tmp_path_factory):
    state = tmp_path_factory.mktemp("state-he")
    settings = load_settings(
        None,
        state_dir=str(state),
        server__port=free_port(),
        server__token="t",
        sim__program="hold",
        sim__preload_handeye=False,
    )
    yield from run_server(settings)


def _capture(c, timeout_s=6.0):
    """Record a sample as soon as the service finds the arm at rest (it refuses while the arm moves)."""
    deadline = time.monotonic() + timeout_s
    while True:
        r = c.post("/calibration/handeye/session/samples")
        if r.status_code != 409 or r.json()["reason"] != "robot_moving" or time.monotonic() > deadline:
            return r
        time.sleep(0.05)


@pytest.mark.slow  # ~25 s: six robot moves of 1-4 s each, two solves in the solver process and a CLI run
def test_hand_eye_session_from_proposed_poses_to_the_stored_result(uncalibrated, tmp_path):
    live = uncalibrated
    h = live.wait_for(
        lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 2, timeout_s=180.0, what="the cell running"
    )
    assert not h["calibration"]["handeye"]["present"]
    cell = live.worker.cell.cell
    with live.client() as c:
        m = c.post("/measure", json={"timeout_s": 5}).json()
        assert m["ok"] and m["flange_reason"] == "not_calibrated" and m["T_base_flange_measured"] is None
        assert c.post("/calibration/handeye/session/solve").status_code == 404  # no session yet

        r = c.post("/calibration/handeye/session", json={"n_poses": 10})
        assert r.status_code == 200, r.text
        proposals = r.json()["proposals"]
        assert len(proposals) == 10 and len(proposals[0]["ur_pose_m_rotvec"]) == 6

        n = 0
        for k in range(len(proposals)):
            mv = c.post(f"/calibration/handeye/session/move/{k}")
            if mv.status_code == 422:  # the plan knows the field, not the arm: an operator skips such a pose
                assert "not reachable" in mv.json()["message"]
                continue
            assert mv.status_code == 200, mv.text
            time.sleep(mv.json()["duration_s"])  # the move itself; then poll until the arm is still
            r = _capture(c)
            assert r.status_code == 200, r.text
            n += 1
        assert n >= 6
        summary = c.get("/calibration/handeye/session").json()
        assert summary["n_samples"] == n and summary["motion"] is not None

        r = c.post("/calibration/handeye/session/solve", params={"apply": "true"})
        assert r.status_code == 200, r.text
        result = r.json()
        assert result["applied_version"] is not None
        assert result["method"] == "image-level" and len(result["rms_px_per_sample"]) == n

        # the true hand-eye, within what the arm's 1-2 mm model errors allow
        X, Z = np.array(result["T_flange_camera"]), np.array(result["T_base_field"])
        dX_mm, dX_deg = pose_difference(X, cell.T_flange_camera)
        dZ_mm, dZ_deg = pose_difference(Z, cell.T_base_field)
        assert dX_mm < 4.0 and dX_deg < 0.3, (dX_mm, dX_deg)
        assert dZ_mm < 4.0 and dZ_deg < 0.3, (dZ_mm, dZ_deg)
        assert 0.05 < result["rms_position_mm"] < 5.0  # the arm's errors show as residuals
        assert len(result["residual_position_mm"]) == n

        # used from the next frame: the flange deviation is back, of the size of the arm's errors
        m = c.post("/measure", json={"timeout_s": 5}).json()
        assert m.get("deviation") is not None and m["deviation"]["position_mm"] < 5.0, m
        assert c.get("/calibration").json()["handeye"]["version"] == result["applied_version"]

        samples = c.get("/calibration/handeye/session/export").json()

        # the same frames self-calibrate the camera (bundle adjustment over the API)
        r = c.post("/calibration/camera/solve", json={"fix": ["K3", "B1", "B2"]})
        assert r.status_code == 200, r.text
        cam = r.json()["camera"]
        assert r.json()["applied_version"] is None  # not applied without apply=true
        assert abs(cam["c_mm"] - cell.camera.c_mm) < 5 * cam["sigma"]["c_mm"] + 1e-3
        assert 0.002 < r.json()["sigma0_px"] < 0.1
        bad = c.post(
            "/calibration/camera/solve",
            json={
                "images": [
                    {
                        "name": "a",
                        "points": [
                            {"id": "nope", "uv": [1, 2]},
                            {"id": "C1", "uv": [1, 2]},
                            {"id": "C2", "uv": [1, 2]},
                            {"id": "C3", "uv": [1, 2]},
                        ],
                    }
                ]
            },
        )
        assert bad.status_code == 422 and "not in the field" in bad.json()["message"]
    # the same samples solved offline by the CLI give the same answer
    path = tmp_path / "samples.json"
    path.write_text(json.dumps(samples))
    posecell = Path(sys.executable).with_name("posecell")
    out = subprocess.run(
        [str(posecell), "calibrate", "handeye", "--samples", str(path)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    X_cli = np.array(json.loads(out.stdout)["T_flange_camera"])
    assert pose_difference(X_cli, X)[0] < 0.5  # the service weights by the measured σ, the CLI by defaults


def test_hand_eye_session_refuses_samples_while_the_robot_moves(uncalibrated):
    live = uncalibrated
    live.wait_for(lambda h: h["status"] == "ok", timeout_s=180.0, what="the cell running")
    with live.client() as c:
        if c.get("/calibration/handeye/session").status_code == 404:
            assert c.post("/calibration/handeye/session", json={"n_poses": 4}).status_code == 200
        mv = c.post("/calibration/handeye/session/move/0")
        assert mv.status_code == 200
        time.sleep(0.3)  # mid-move
        r = c.post("/calibration/handeye/session/samples")
        assert r.status_code == 409 and r.json()["reason"] == "robot_moving"
        assert c.post("/calibration/handeye/session/move/99").status_code == 404
        # the move runs on: the next test neither records samples nor needs the arm at rest


def test_the_cli_drives_the_service_session(uncalibrated):
    live = uncalibrated
    live.wait_for(lambda h: h["status"] == "ok", timeout_s=180.0, what="the cell running")
    posecell = Path(sys.executable).with_name("posecell")

    def cli(*args):
        return subprocess.run(
            [str(posecell), "calibrate", "handeye-session", *args, "--url", live.url, "--token", live.token],
            capture_output=True,
            text=True,
            timeout=120,
        )

    r = cli("start", "--poses", "4")
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)["proposals"]) == 4
    r = cli("status")
    assert r.returncode == 0 and json.loads(r.stdout)["n_samples"] == 0
    r = cli("solve")
    assert r.returncode == 1 and "poor_motion" in r.stderr  # no samples yet: one clear sentence
    r = subprocess.run(
        [str(posecell), "calibrate", "handeye-session", "status", "--url", "http://127.0.0.1:9"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1 and "cannot be reached" in r.stderr
