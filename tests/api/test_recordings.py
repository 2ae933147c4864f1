"""Recording the running cell over HTTP, then measuring the recording through the replay camera."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.base import CameraSettings
from drivers.registry import make_camera
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer
from service.sim.scene import reference_camera, reference_field

pytestmark = pytest.mark.slow


def ended(client, rec_id: str, timeout_s: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        summary = client.get(f"/recordings/{rec_id}").json()
        if summary["state"] != "recording":
            return summary
        time.sleep(0.1)
    raise AssertionError(f"recording {rec_id} did not end: {summary}")


def test_a_recorded_session_replays_and_measures_like_the_cell(live):
    live.wait_for(lambda h: h["status"] == "ok" and h["cameras"]["cam0"]["state"] == "ok", what="the cell")
    with live.client() as c:
        r = c.post("/recordings", json={"max_frames": 4, "label": "acceptance"})
        assert r.status_code == 202, r.text
        rec_id = r.json()["id"]
        busy = c.post("/recordings", json={"cameras": ["cam0"]})
        assert (busy.status_code, busy.json()["reason"]) == (409, "busy")
        summary = ended(c, rec_id)
        assert summary["state"] == "complete" and summary["label"] == "acceptance"
        assert [s["id"] for s in c.get("/recordings").json()["recordings"]] == [rec_id]
    cam = summary["cameras"]["cam0"]
    assert cam["written"] == 4 and cam["dropped"] == 0 and summary["robot_samples"] > 0
    folder = Path(cam["folder"])
    with (folder / "timestamps.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    t_ns = np.array([int(r["t_ns"]) for r in rows])
    seq = np.array([int(r["seq"]) for r in rows])
    period_ns = 1e9 / live.settings.cameras[0].frame_rate_hz
    # the exposure instants follow the frame counter at the camera's rate
    assert np.allclose(np.diff(t_ns), np.diff(seq) * period_ns, atol=0.2 * period_ns)
    with (folder.parent / "robot.csv").open() as fh:
        robot = list(csv.DictReader(fh))
    t_robot = np.array([int(r["t_host_ns"]) for r in robot])
    assert t_robot[0] <= t_ns[0] and t_robot[-1] >= t_ns[-1]  # the robot over the whole recording
    # every sample the robot's reader took over it, as the service holds them
    t_held, _, T_held, q_held = live.worker.robot.history.columns_between(int(t_robot[0]), int(t_robot[-1]))
    assert t_held.tolist() == t_robot.tolist()
    xyz = np.array([[float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] for r in robot])
    q = np.array([[float(r[f"q{i}_rad"]) for i in range(1, 7)] for r in robot])
    assert np.allclose(xyz, T_held[:, :3, 3], atol=1e-5) and np.allclose(q, q_held, atol=1e-7)

    # the recording, played by the replay camera, measures as the live cell did: a pose per frame
    replay = make_camera("replay", source=str(folder), loop=False, n_buffers=100)
    replay.open()
    replay.configure(CameraSettings(frame_rate_hz=100.0))
    measurer = FrameMeasurer(reference_camera(), reference_field())
    try:
        for k in range(4):
            frame = replay.fetch(timeout_s=2.0)
            assert frame.t_device_ns == t_ns[k]  # the recorded exposure instant
            result = measurer.measure(frame.image).result
            assert isinstance(result, PoseResult), result
            assert result.n_coded >= 10 and result.rms_px < 0.1
    finally:
        replay.close()

    with live.client() as c:
        assert c.delete(f"/recordings/{rec_id}").status_code == 200
        assert c.get(f"/recordings/{rec_id}").status_code == 404
        assert not folder.exists()


def test_refusals_over_http(live):
    with live.client() as c:
        for body, status, reason in [
            ({"cameras": ["nope"]}, 404, "not_found"),
            ({"format": "jpeg"}, 422, "bad_input"),
            ({"max_frames": 0}, 422, "bad_input"),
            ({"max_seconds": 1e9}, 422, "bad_input"),
            ({"frames": 3}, 422, "bad_input"),
        ]:
            r = c.post("/recordings", json=body)
            assert (r.status_code, r.json()["reason"]) == (status, reason), (body, r.text)
        assert c.get("/recordings/20990101-000000").status_code == 404
        assert c.post("/recordings/20990101-000000/stop").status_code == 404
    with live.client(auth=False) as anonymous:
        assert anonymous.post("/recordings", json={}).status_code == 401
