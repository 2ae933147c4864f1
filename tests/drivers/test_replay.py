"""The replay camera: a folder of frames or the simulated cell rendered ahead, on a steady clock."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.base import (
    CameraSettings,
    DriverDisconnected,
    DriverInitError,
    DriverTimeout,
    FeatureUnsupported,
    TriggerMode,
)
from drivers.registry import make_camera
from service.core.geometry.frames import pose_difference
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer
from tests.drivers.test_camera_contract import write_frames


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    write_frames(tmp_path, n=3)
    return tmp_path


def opened(source, settings: CameraSettings | None = None, **options):
    # a deep "buffer pool": a consumer stalled on a loaded machine loses no frame (unless a test says so)
    cam = make_camera("replay", source=str(source), **{"n_buffers": 1000, **options})
    cam.open()
    cam.configure(settings or CameraSettings(frame_rate_hz=200.0))
    return cam


def test_frames_come_at_the_configured_rate(folder):
    cam = opened(folder, CameraSettings(frame_rate_hz=200.0))
    try:
        t0 = time.monotonic()
        frames = []
        while time.monotonic() - t0 < 1.0:
            frames.append(cam.fetch(timeout_s=1.0))
        elapsed_s = time.monotonic() - t0
    finally:
        cam.close()
    # a steady schedule: the count follows the wall clock, not the sum of late wake-ups
    assert len(frames) == pytest.approx(200.0 * elapsed_s, rel=0.05)
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(frames)))  # none lost by a consumer that keeps up
    # stamped with the scheduled instants: exactly one period apart
    assert set(np.diff([f.t_host_ns for f in frames]).tolist()) <= {5_000_000}
    assert all(f.t_exposure_host_ns == f.t_host_ns == f.t_device_ns for f in frames)  # no timestamps.csv


def test_frames_loop_and_are_the_folder_images_in_name_order(folder):
    files = sorted(folder.glob("*.png"))
    cam = opened(folder)
    try:
        frames = [cam.fetch(timeout_s=1.0) for _ in range(7)]
        assert [f.meta["replay_index"] for f in frames] == [0, 1, 2, 0, 1, 2, 0]
        assert [f.meta["replay_pass"] for f in frames] == [0, 0, 0, 1, 1, 1, 2]
        for f in frames:
            expected = cv2.imread(str(files[f.meta["replay_index"]]), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(f.image, expected)
            assert f.meta["file"] == files[f.meta["replay_index"]].name
        assert cam.info.width == 64 and cam.info.height == 48 and cam.info.pixel_format == "Mono8"
    finally:
        cam.close()


def test_without_loop_the_replay_ends_after_the_last_frame(folder):
    cam = opened(folder, loop=False)
    try:
        assert [cam.fetch(timeout_s=1.0).meta["replay_index"] for _ in range(3)] == [0, 1, 2]
        with pytest.raises(DriverTimeout, match="all 3 frames were played"):
            cam.fetch(timeout_s=0.1)
        assert cam.try_fetch() is None
    finally:
        cam.close()


def test_a_bounce_plays_forward_then_back_and_its_device_time_runs_on_by_the_recorded_intervals(folder):
    stamps = [1_000_000_000, 1_010_000_000, 1_030_000_000]  # intervals of 10 and 20 ms
    rows = "".join(f"frame_{k:04d}.png,{t}\n" for k, t in enumerate(stamps))
    (folder / "timestamps.csv").write_text("file,t_ns\n" + rows)
    files = sorted(folder.glob("*.png"))
    cam = opened(folder, loop="bounce")
    try:
        frames = [cam.fetch(timeout_s=1.0) for _ in range(9)]
    finally:
        cam.close()
    # no jump from the last frame to the first: the motion of a recording stays continuous
    assert [f.meta["replay_index"] for f in frames] == [0, 1, 2, 1, 0, 1, 2, 1, 0]
    for f in frames:
        np.testing.assert_array_equal(f.image, cv2.imread(str(files[f.meta["replay_index"]]), cv2.IMREAD_UNCHANGED))
    steps_ms = np.diff([f.t_device_ns for f in frames]) / 1e6
    assert steps_ms.tolist() == [10, 20, 20, 10, 10, 20, 20, 10]
    assert [f.seq for f in frames] == list(range(9))
    with pytest.raises(ValueError, match='"bounce"'):
        make_camera("replay", source=str(folder), loop="pingpong")


def test_timestamps_file_gives_the_device_times_and_they_keep_increasing_over_loops(folder):
    # recorded at ~100 Hz with a jitter, replayed at 200 Hz
    stamps = [1_000_000_000, 1_010_000_100, 1_019_999_900]
    rows = "".join(f"frame_{k:04d}.png,{t}\n" for k, t in enumerate(stamps))
    (folder / "timestamps.csv").write_text("file,t_ns\n" + rows + "other.png,5\n")  # a row of no image: ignored
    cam = opened(folder)
    try:
        frames = [cam.fetch(timeout_s=1.0) for _ in range(6)]
    finally:
        cam.close()
    span_ns = stamps[-1] - stamps[0] + int(np.median(np.diff(stamps)))  # one pass: the span and one period
    assert [f.t_device_ns for f in frames] == stamps + [t + span_ns for t in stamps]
    assert np.diff([f.t_host_ns for f in frames]).tolist() == [5_000_000] * 5  # delivery keeps its own rate


def test_timestamps_in_seconds_with_the_calibration_header_are_accepted(folder):
    (folder / "timestamps.csv").write_text("name,t_s\nframe_0000.png,1.5\nframe_0001.png,1.6\nframe_0002.png,1.7\n")
    cam = opened(folder)
    try:
        assert cam.fetch(timeout_s=1.0).t_device_ns == 1_500_000_000
    finally:
        cam.close()


@pytest.mark.parametrize(
    "text, message",
    [
        ("image,time\nframe_0000.png,1\n", "the first row must be the header 'file,t_ns'"),
        ("file,t_ns\nframe_0000.png,1\nframe_0001.png,2\n", "has no timestamp for frame_0002.png"),
        ("file,t_ns\nframe_0000.png,1\nframe_0001.png,x\n", "row 3 is not 'file,t_ns'"),
        ("file,t_ns\nframe_0000.png,5\nframe_0001.png,4\nframe_0002.png,6\n", "timestamp of frame_0001.png"),
    ],
)
def test_a_bad_timestamps_file_is_refused_with_its_reason(folder, text, message):
    (folder / "timestamps.csv").write_text(text)
    cam = make_camera("replay", source=str(folder))
    with pytest.raises(DriverInitError, match=message) as e:
        cam.open()
    assert "timestamps.csv" in str(e.value)


def test_a_missing_or_empty_folder_is_refused(tmp_path):
    with pytest.raises(DriverInitError, match=r"replay folder .*nothing-here does not exist"):
        make_camera("replay", source=str(tmp_path / "nothing-here")).open()
    (tmp_path / "notes.txt").write_text("no images here")
    with pytest.raises(DriverInitError, match=rf"replay folder {tmp_path} holds no images"):
        make_camera("replay", source=str(tmp_path)).open()


def test_an_unreadable_image_is_named(folder):
    (folder / "frame_0001b.png").write_bytes(b"not a png at all")
    with pytest.raises(DriverInitError, match=r"replay image .*frame_0001b\.png cannot be read"):
        make_camera("replay", source=str(folder)).open()


def test_images_of_another_size_or_depth_are_named(folder):
    cv2.imwrite(str(folder / "frame_0009.png"), np.zeros((40, 64), np.uint8))
    with pytest.raises(DriverInitError, match=r"frame_0009\.png is 64 x 40 px uint8, but frame_0000\.png is 64 x 48"):
        make_camera("replay", source=str(folder)).open()
    cv2.imwrite(str(folder / "frame_0009.png"), np.zeros((48, 64), np.uint16))
    with pytest.raises(DriverInitError, match=r"frame_0009\.png is 64 x 48 px uint16"):
        make_camera("replay", source=str(folder)).open()


def test_sixteen_bit_frames_are_cropped_to_the_roi_and_keep_their_depth(tmp_path):
    files = write_frames(tmp_path, n=2, shape=(30, 50), dtype=np.uint16)
    cam = opened(tmp_path, CameraSettings(roi=(10, 5, 20, 12), pixel_format="Mono12"))
    try:
        frame = cam.fetch(timeout_s=1.0)
        full = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(frame.image, full[5:17, 10:30])
        assert frame.image.dtype == np.uint16 and frame.image.flags.c_contiguous
        assert (cam.info.width, cam.info.height, cam.info.pixel_format) == (20, 12, "Mono12")
        with pytest.raises(FeatureUnsupported, match="Mono16, they cannot become Mono8"):
            cam.configure(CameraSettings(pixel_format="Mono8"))
        with pytest.raises(FeatureUnsupported, match="outside the replay's 50 x 30 frames"):
            cam.configure(CameraSettings(roi=(40, 0, 20, 10)))
    finally:
        cam.close()


def test_sixteen_bit_frames_that_never_pass_4095_are_a_12_bit_cameras(tmp_path):
    # a recording of a Mono12 camera (its values in a uint16's low 12 bits) replays as Mono12, so that
    # the service measures it with 12 bits (tests/test_bit_depth.py); brighter frames are Mono16
    for name, top, want in (("deep", 65535, "Mono16"), ("twelve", 4095, "Mono12")):
        folder = tmp_path / name
        folder.mkdir()
        for path in write_frames(folder, n=2, shape=(30, 50), dtype=np.uint16):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(path), (image.astype(np.float64) * top / 65535).round().astype(np.uint16))
        cam = opened(folder)
        try:
            assert cam.info.pixel_format == want
            assert cam.fetch(timeout_s=1.0).image.max() <= top
        finally:
            cam.close()


def test_settings_a_recording_cannot_follow_are_refused_and_the_strobe_is_ignored(folder):
    cam = opened(folder)
    try:
        with pytest.raises(FeatureUnsupported) as e:
            cam.configure(CameraSettings(gain_db=6.0))
        assert e.value.feature == "Gain"
        with pytest.raises(FeatureUnsupported) as e:
            cam.configure(CameraSettings(trigger=TriggerMode.HARDWARE))
        assert e.value.feature == "TriggerMode"
        with pytest.raises(FeatureUnsupported):
            cam.trigger()  # free run
        cam.configure(CameraSettings(exposure_us=800.0, strobe=None))  # the operator's statement of the exposure
        frame = cam.fetch(timeout_s=1.0)
        assert frame.exposure_us == 800.0
        assert "strobe" not in cam.info.features and "gain" not in cam.info.features
    finally:
        cam.close()


def test_a_consumer_that_falls_behind_gets_the_buffered_frames_then_a_gap(folder):
    cam = opened(folder, CameraSettings(frame_rate_hz=200.0), n_buffers=4)
    try:
        first = cam.fetch(timeout_s=1.0)
        time.sleep(0.2)  # 40 periods
        late = [cam.fetch(timeout_s=1.0) for _ in range(4)]
    finally:
        cam.close()
    gap = late[0].seq - first.seq
    assert gap > 20  # the frames before the buffer are lost, as on a camera
    assert [f.seq for f in late] == list(range(late[0].seq, late[0].seq + 4))


@pytest.fixture(scope="module")
def circle_cell():
    from service.sim.cell import CellConfig, SimCell

    return SimCell(CellConfig())  # the circle program: the frames show a motion


@pytest.mark.slow
def test_sim_source_frames_carry_the_truth_and_the_pipeline_measures_them(circle_cell):
    cell = circle_cell
    cam = opened("sim", CameraSettings(frame_rate_hz=50.0), cell=cell, n_frames=3)
    try:
        frames = [cam.fetch(timeout_s=1.0) for _ in range(3)]
    finally:
        cam.close()
    assert [f.meta["t_cell_s"] for f in frames] == pytest.approx([0.0, 0.02, 0.04])  # at the frame period
    measurer = FrameMeasurer(cell.camera, cell.field)
    for f in frames:
        T_true = np.asarray(f.meta["T_field_camera"])
        np.testing.assert_allclose(T_true, cell.T_field_camera(f.meta["t_cell_s"]), atol=1e-9)
        result = measurer.measure(f.image, f.meta["t_cell_s"]).result
        assert isinstance(result, PoseResult), result
        dt_mm, _ = pose_difference(result.T_field_camera, T_true)
        assert dt_mm < 5 * np.linalg.norm(result.sigma_position_mm)
        assert result.n_coded >= 25
    moved_mm, _ = pose_difference(
        np.asarray(frames[0].meta["T_field_camera"]), np.asarray(frames[2].meta["T_field_camera"])
    )
    assert moved_mm > 1.0  # 40 ms of the 190 mm/s circle


def test_sim_source_keeps_its_rendered_exposure_and_a_closed_render_stops():
    cam = opened("sim", CameraSettings(exposure_us=1500.0), cell_config={"program": "hold"}, n_frames=2)
    try:
        assert cam.fetch(timeout_s=1.0).exposure_us == 1500.0
        with pytest.raises(FeatureUnsupported, match="rendered at 1500 µs"):
            cam.configure(CameraSettings(exposure_us=2000.0))
    finally:
        cam.close()
    # closed from another thread while rendering: the render is cancelled, the owner told at once
    cam = make_camera("replay", source="sim", cell_config={"program": "hold"}, n_frames=500)
    cam.open()
    threading.Timer(0.3, cam.close).start()
    t0 = time.monotonic()
    with pytest.raises(DriverDisconnected, match="closed while"):
        cam.configure(CameraSettings())
    assert time.monotonic() - t0 < 5.0  # rendering all 500 would take ~20 s


def test_a_cell_the_render_child_cannot_build_is_reported():
    cam = make_camera("replay", source="sim", cell_config={"robot": "nope"}, n_frames=2)
    cam.open()
    with pytest.raises(DriverInitError, match="could not render the simulated cell's frames: ValueError: robot must"):
        cam.configure(CameraSettings())
    cam.close()


def test_the_service_hands_a_sim_replay_its_simulated_cell(folder):
    from service.runtime.cell_runtime import CellRuntime
    from service.settings import CameraConfig, Settings

    runtime = CellRuntime(Settings())
    # built without validation: CameraConfig.driver must list "replay" for a configuration file to name it
    sim = CameraConfig.model_construct(driver="replay", options={"source": "sim", "n_frames": 4})
    name, options = runtime.camera_driver(sim)
    assert name == "replay" and options["cell"] is runtime.cell and options["n_frames"] == 4
    recorded = CameraConfig.model_construct(driver="replay", options={"source": str(folder)})
    assert runtime.camera_driver(recorded) == ("replay", {"source": str(folder)})
