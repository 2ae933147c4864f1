"""Calibration sessions survive a restart of the service: what was acknowledged was stored.

Real servers over HTTP on one state directory, one after the other: the first records, stops (as
systemd stops it), the second offers the same session again, with the same samples, and goes on.
"""

from __future__ import annotations

import json
import shutil
import time

import pytest

from service.settings import load_settings
from tests.api.conftest import PLAN_TIMEOUT_S, free_port, run_server


def _server(state, **kw):
    settings = load_settings(None, state_dir=str(state), server__port=free_port(), server__token="t", **kw)
    gen = run_server(settings)
    live = next(gen)
    live.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 2, timeout_s=180.0, what="the cell")
    return gen, live


def _capture(c, url, timeout_s=8.0):
    deadline = time.monotonic() + timeout_s
    while True:
        r = c.post(url)
        if r.status_code != 409 or r.json()["reason"] != "robot_moving" or time.monotonic() > deadline:
            return r
        time.sleep(0.05)


@pytest.mark.slow  # two service starts and two hand-eye samples: ~20 s
def test_a_hand_eye_session_and_its_samples_come_back_after_a_restart(tmp_path):
    gen, live = _server(tmp_path, sim__program="hold")
    try:
        with live.client() as c:
            r = c.post("/calibration/handeye/session", json={"n_poses": 6})
            assert r.status_code == 200, r.text
            for _ in range(2):
                r = _capture(c, "/calibration/handeye/session/samples")
                assert r.status_code == 200, r.text
            before = c.get("/calibration/handeye/session").json()
            assert before["n_samples"] == 2 and not before["restored"]
            # a store that cannot write: the sample is refused, not kept in memory only
            sessions = tmp_path / "sessions"
            shutil.move(sessions, tmp_path / "sessions.moved")
            sessions.write_text("not a directory")
            r = _capture(c, "/calibration/handeye/session/samples")
            assert r.status_code == 503 and r.json()["reason"] == "storage_unavailable", r.text
            assert r.json()["message"].startswith("the sample is not recorded")
            assert c.get("/calibration/handeye/session").json()["n_samples"] == 2
            sessions.unlink()
            shutil.move(tmp_path / "sessions.moved", sessions)
    finally:
        gen.close()

    gen, live = _server(tmp_path, sim__program="hold")
    try:
        with live.client() as c:
            after = c.get("/calibration/handeye/session").json()
            assert after["restored"] and after["created"] == before["created"]
            assert after["samples"] == before["samples"] and after["proposals"] == before["proposals"]
            events = c.get("/events").json()
            assert any(e["kind"] == "session_restored" for e in events["events"]), events
            assert _capture(c, "/calibration/handeye/session/samples").status_code == 200  # it goes on
            assert c.delete("/calibration/handeye/session").status_code == 200
            assert not (tmp_path / "sessions" / "handeye.json").exists()
    finally:
        gen.close()


@pytest.mark.slow  # a 12-pose run in two halves across a restart, and a solve: ~60 s
def test_a_robot_calibration_run_stopped_by_a_restart_goes_on_where_it_stopped(tmp_path):
    gen, live = _server(tmp_path, cameras=[{"frame_rate_hz": 20.0}])
    try:
        with live.client() as c:
            r = c.post(
                "/calibration/robot/session",
                json={"n_poses": 12, "n_holdout": 0, "frames_per_pose": 1},
                timeout=PLAN_TIMEOUT_S,
            )
            assert r.status_code == 200, r.text
            assert c.post("/calibration/robot/session/run").status_code == 202
            deadline = time.monotonic() + 120
            while (s := c.get("/calibration/robot/session").json())["n_samples"] < 4:
                assert s["status"] == "running" and time.monotonic() < deadline, s
                time.sleep(0.2)
    finally:
        gen.close()  # the service stops during the run
    stored = json.loads((tmp_path / "sessions" / "robot.json").read_text())["state"]
    assert stored["status"] == "interrupted" and len(stored["samples"]) >= 4
    first = {x["pose"]: x for x in stored["samples"]}

    gen, live = _server(tmp_path, cameras=[{"frame_rate_hz": 20.0}])
    try:
        with live.client() as c:
            s = c.get("/calibration/robot/session").json()
            assert s["restored"] and s["status"] == "interrupted" and s["n_samples"] == len(first)
            assert "Run again to visit the poses not yet recorded" in s["progress_message"]
            assert c.post("/calibration/robot/session/run").status_code == 202
            deadline = time.monotonic() + 180
            while (s := c.get("/calibration/robot/session").json())["status"] in ("running", "solving"):
                assert time.monotonic() < deadline, s
                time.sleep(0.3)
            assert s["status"] == "solved", s
            assert sorted(x["pose"] for x in s["samples"]) == list(range(12))
            for x in s["samples"]:  # the poses recorded before the restart were not visited again
                if x["pose"] in first:
                    assert x["t_wall"] == first[x["pose"]]["t_wall"]
                    assert x["T_base_flange_measured"] == first[x["pose"]]["T_base_flange_measured"]
            assert s["result"]["n_calibration"] == 12  # the solve used both halves
            r = c.post("/calibration/robot/session/save")
            assert r.status_code == 200 and r.json()["version"] is not None
    finally:
        gen.close()
    assert json.loads((tmp_path / "sessions" / "robot.json").read_text())["state"]["saved_version"] is not None
