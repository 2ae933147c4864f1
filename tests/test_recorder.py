"""Recordings: frames and robot samples written as the replay camera reads them, every frame counted."""

from __future__ import annotations

import csv
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.base import Frame, RobotSample
from drivers.camera.replay import load_folder
from drivers.history import RobotHistory
from service.core.geometry.so3 import T_from_rotvec
from service.runtime.recorder import MANIFEST, ROBOT_FILE, RecordingError, RecordingRequest, Recordings
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose

PERIOD_NS = 10_000_000


class Channel:
    """What a recording needs of a camera channel: the ``tap`` it sets."""

    def __init__(self) -> None:
        self.tap = None

    def deliver(self, frame: Frame) -> None:
        tap = self.tap
        if tap is not None:
            tap(frame)


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    camera, field = reference_camera(), reference_field()
    return [
        render_frame(camera, field, reference_pose(view_angle_deg=80.0 + k), RenderSettings(), rng).image
        for k in range(3)
    ]


def frames(images: list[np.ndarray], n: int, t0_ns: int) -> list[Frame]:
    return [
        Frame(images[k % len(images)], seq=k + 1, t_host_ns=t0_ns + k * PERIOD_NS + 500_000, t_device_ns=7 * k,
              exposure_us=1500.0, t_exposure_host_ns=t0_ns + k * PERIOD_NS)
        for k in range(n)
    ]  # fmt: skip


def robot_history(t0_ns: int, n: int) -> RobotHistory:
    history = RobotHistory(capacity=4 * n)
    for k in range(n):
        T = T_from_rotvec([0.1, -0.2, 0.3 + 1e-3 * k], [400.0 + k, -100.0, 600.0])
        history.append(RobotSample(T, np.full(6, 0.01 * k), t0_ns + k * 2_000_000, 12.5 + 0.002 * k))
    return history


def wait_ended(recordings: Recordings, rec_id: str, timeout_s: float = 20.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        summary = recordings.get(rec_id)
        if summary["state"] != "recording":
            return summary
        time.sleep(0.02)
    raise AssertionError(f"recording {rec_id} did not end: {recordings.get(rec_id)}")


def test_a_recording_writes_each_frame_losslessly_with_its_times_and_the_robot_beside_it(tmp_path, images):
    t0 = time.monotonic_ns()
    channel, events = Channel(), []
    history = robot_history(t0 - 200_000_000, 300)  # 0.6 s of 500 Hz samples around the frames
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: history, lambda *e: events.append(e))
    summary = recordings.start(RecordingRequest(max_frames=5, label="first", format="png"))
    assert summary["state"] == "recording" and summary["label"] == "first"
    sent = frames(images, 8, t0)
    for f in sent:
        channel.deliver(f)
    summary = wait_ended(recordings, summary["id"])
    assert summary["state"] == "complete", summary
    cam = summary["cameras"]["cam0"]
    assert (cam["written"], cam["dropped"], cam["shape"], cam["dtype"]) == (5, 0, [1030, 1300], "uint8")
    assert channel.tap is None  # the camera is free again
    folder = Path(cam["folder"])
    # the replay camera's reader takes the folder as it is: the same pixels, the recorded times
    rec = load_folder(folder)
    assert len(rec.frames) == 5
    for k in range(5):
        assert np.array_equal(rec.frames[k], sent[k].image)
    assert rec.t_ns.tolist() == [f.t_host_ns for f in sent[:5]]  # the arrivals, the robot samples' clock
    assert rec.t_device_ns.tolist() == [0, 7, 14, 21, 28]
    assert rec.t_exposure_ns.tolist() == [f.t_exposure_host_ns for f in sent[:5]]
    with (folder / "timestamps.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["seq"]) for r in rows] == [1, 2, 3, 4, 5]
    # the robot: every sample from just before the first exposure to just after the last
    with (tmp_path / summary["id"] / ROBOT_FILE).open() as fh:
        robot = list(csv.DictReader(fh))
    t_robot = np.array([int(r["t_host_ns"]) for r in robot])
    assert summary["robot_samples"] == len(robot) > 0
    assert t_robot[0] <= sent[0].t_exposure_host_ns and t_robot[-1] >= sent[4].t_exposure_host_ns
    assert np.all(np.diff(t_robot) == 2_000_000)  # none twice, none missing
    k = (t_robot[0] - (t0 - 200_000_000)) // 2_000_000
    first = robot[0]
    assert float(first["x_mm"]) == pytest.approx(400.0 + k) and float(first["rz_rad"]) == pytest.approx(0.3 + 1e-3 * k)
    assert float(first["q6_rad"]) == pytest.approx(0.01 * k) and float(first["t_robot_s"]) == pytest.approx(
        12.5 + 0.002 * k
    )
    assert json.loads((tmp_path / summary["id"] / MANIFEST).read_text())["state"] == "complete"
    assert [e[1] for e in events] == ["recording_started", "recording_complete"]


def test_every_nth_frame_and_a_stop_that_keeps_what_was_accepted(tmp_path, images):
    channel = Channel()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    rec_id = recordings.start(RecordingRequest(every_n=3, max_frames=1000))["id"]
    for f in frames(images, 10, time.monotonic_ns()):
        channel.deliver(f)
    summary = recordings.stop(rec_id)
    assert summary["state"] == "stopped"
    cam = summary["cameras"]["cam0"]
    assert (cam["offered"], cam["written"], cam["dropped"]) == (10, 4, 0)
    with (Path(cam["folder"]) / "timestamps.csv").open() as fh:
        assert [int(r["seq"]) for r in csv.DictReader(fh)] == [1, 4, 7, 10]
    assert sorted(p.name for p in Path(cam["folder"]).glob("frame-*")) == [f"frame-00000{k}.pgm" for k in (1, 2, 3, 4)]
    assert summary["robot_samples"] == 0  # no robot: an empty robot.csv, its header only
    channel.deliver(frames(images, 1, time.monotonic_ns())[0])  # after the stop: not recorded
    assert recordings.get(rec_id)["cameras"]["cam0"]["offered"] == 10


def test_frames_the_writer_cannot_keep_up_with_are_counted_as_dropped(tmp_path, images, monkeypatch):
    import service.runtime.recorder as recorder

    monkeypatch.setattr(recorder, "QUEUE_FRAMES", 2)
    gate = threading.Event()
    original = recorder.Recording._write

    def slow_write(self, *args):  # a disk far slower than the camera
        gate.wait(10.0)
        original(self, *args)

    monkeypatch.setattr(recorder.Recording, "_write", slow_write)
    channel = Channel()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    rec_id = recordings.start(RecordingRequest(max_frames=50))["id"]
    for f in frames(images, 20, time.monotonic_ns()):
        channel.deliver(f)
    gate.set()
    summary = recordings.stop(rec_id)
    cam = summary["cameras"]["cam0"]
    assert cam["offered"] == 20 and cam["dropped"] >= 16 and cam["written"] + cam["dropped"] == 20
    with (Path(cam["folder"]) / "timestamps.csv").open() as fh:
        seqs = [int(r["seq"]) for r in csv.DictReader(fh)]
    assert len(seqs) == cam["written"] and seqs == sorted(seqs)  # the gaps in seq show where


def test_refusals_say_why(tmp_path):
    channel = Channel()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    for request, kind in [
        (RecordingRequest(cameras=("cam9",)), "not_found"),
        (RecordingRequest(format="jpeg"), "bad_input"),
        (RecordingRequest(max_frames=0), "bad_input"),
        (RecordingRequest(max_seconds=-1.0), "bad_input"),
    ]:
        with pytest.raises(RecordingError) as e:
            recordings.start(request)
        assert e.value.kind == kind
    rec_id = recordings.start(RecordingRequest())["id"]
    with pytest.raises(RecordingError, match="being recorded already") as e:
        recordings.start(RecordingRequest(cameras=("cam0",)))
    assert e.value.kind == "busy"
    with pytest.raises(RecordingError, match="stop it first"):
        recordings.delete(rec_id)
    recordings.stop(rec_id)
    recordings.delete(rec_id)
    assert not (tmp_path / rec_id).exists() and recordings.list() == []
    with pytest.raises(RecordingError) as e:
        recordings.get("../etc")
    assert e.value.kind == "not_found"
    # a disk without room refuses at the start, and says how much there is
    full = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None, min_free_bytes=2**62)
    with pytest.raises(RecordingError, match="MiB free") as e:
        full.start(RecordingRequest())
    assert e.value.kind == "storage"


def test_a_recording_cut_by_a_stop_comes_back_interrupted_with_its_frames(tmp_path, images):
    channel = Channel()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    summary = recordings.start(RecordingRequest())
    folder = tmp_path / summary["id"]
    for f in frames(images, 3, time.monotonic_ns()):
        channel.deliver(f)
    deadline = time.monotonic() + 10
    while len(list((folder / "cam0").glob("frame-*"))) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    # a power cut: the manifest on disk still says "recording"
    after = Recordings(tmp_path, {"cam0": Channel()}, lambda: None, lambda *e: None)
    again = after.get(summary["id"])
    assert again["state"] == "interrupted" and again["cameras"]["cam0"]["written"] == 3
    assert "frames written are kept" in again["message"]
    recordings.stop(summary["id"])


def test_a_write_that_fails_ends_the_recording_failed_with_the_reason(tmp_path, images):
    channel = Channel()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    summary = recordings.start(RecordingRequest())
    cam_folder = tmp_path / summary["id"] / "cam0"
    for p in cam_folder.iterdir():
        p.unlink()
    cam_folder.rmdir()
    cam_folder.write_text("not a folder")  # the frames' folder is gone: every write fails
    channel.deliver(frames(images, 1, time.monotonic_ns())[0])
    summary = wait_ended(recordings, summary["id"])
    assert summary["state"] == "failed" and "writing the recording failed" in summary["message"]
    assert channel.tap is None


def test_a_stop_ends_the_recording_while_the_camera_keeps_delivering(tmp_path, images):
    channel, running = Channel(), threading.Event()
    recordings = Recordings(tmp_path, {"cam0": channel}, lambda: None, lambda *e: None)
    # PNG: slower than this camera; the limits far off, so only the stop can end it
    rec_id = recordings.start(RecordingRequest(max_frames=100_000, max_seconds=600.0, format="png"))["id"]
    running.set()

    def camera() -> None:
        while running.is_set():
            channel.deliver(frames(images, 1, time.monotonic_ns())[0])
            time.sleep(0.005)

    thread = threading.Thread(target=camera)
    thread.start()
    try:
        time.sleep(0.5)
        t0 = time.monotonic()
        summary = recordings.stop(rec_id)
        stopped_in_s = time.monotonic() - t0
    finally:
        running.clear()
        thread.join()
    # the frames queued before it are written (at most QUEUE_FRAMES PNG encodings), none after it
    assert summary["state"] == "stopped" and stopped_in_s < 30.0, stopped_in_s
    assert recordings.get(rec_id)["cameras"]["cam0"]["offered"] == summary["cameras"]["cam0"]["offered"]
    cam = summary["cameras"]["cam0"]
    assert cam["written"] >= 1 and cam["written"] + cam["dropped"] <= cam["offered"]


def test_a_request_from_json_is_checked_field_by_field():
    assert RecordingRequest.from_dict({}) == RecordingRequest()
    assert RecordingRequest.from_dict({"cameras": ["cam0"], "max_frames": 10, "max_seconds": 2.5}) == RecordingRequest(
        cameras=("cam0",), max_frames=10, max_seconds=2.5
    )
    for bad, words in [
        ({"frames": 3}, "unknown parameter 'frames'"),
        ({"cameras": "cam0"}, "list of camera names"),
        ({"max_frames": "10"}, "whole numbers"),
        ({"every_n": 2.5}, "whole numbers"),
        ({"max_frames": True}, "whole numbers"),
    ]:
        with pytest.raises(RecordingError, match=words) as e:
            RecordingRequest.from_dict(bad)
        assert e.value.kind == "bad_input"
