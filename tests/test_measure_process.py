"""The measurement in a child process: the same outcomes as in this one; a dead, hung or failing child
costs a frame with a sentence, never the stream."""

from __future__ import annotations

import os
import signal
import tempfile
import time
from dataclasses import replace

import numpy as np
import pytest

from service.bench.speed import frames_along_path
from service.core.geometry.camera_model import BrownFraser
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.runtime.measure_process import MeasureProcess, MeasureProcessError
from service.sim.scene import reference_camera, reference_field

pytestmark = pytest.mark.slow  # child processes and rendered frames

DT_S = 0.004  # frame period of the tracked sequence (250 Hz)


@pytest.fixture(scope="module")
def frames():
    return frames_along_path(12, seed=3)


@pytest.fixture
def child():
    process = MeasureProcess("cam0")
    process.configure(reference_camera(), reference_field(), MeasureSettings())
    yield process
    process.close()


def test_the_child_gives_the_outcomes_measured_here_frame_by_frame_with_tracking(frames, child):
    here = FrameMeasurer(reference_camera(), reference_field(), MeasureSettings())
    modes = []
    for k, frame in enumerate(frames):
        local, remote = here.measure(frame.image, k * DT_S), child.measure(frame.image, k * DT_S)
        assert remote.mode == local.mode
        assert isinstance(remote.result, PoseResult) and isinstance(local.result, PoseResult)
        np.testing.assert_array_equal(remote.result.T_field_camera, local.result.T_field_camera)
        assert remote.result.targets.ids == local.result.targets.ids
        assert "_json" in vars(remote.result.targets)  # encoded in the child, not in this process
        assert remote.result.targets.to_json() == local.result.targets.to_json()
        modes.append(remote.mode)
    assert modes[0] == "full" and modes.count("roi") >= len(frames) - 2  # its ROI tracking state is its own
    assert child.pid is not None and child.pid != os.getpid()


def _larger(camera: BrownFraser, scale: int = 2) -> BrownFraser:
    """A sensor ``scale`` times as wide and high whose top-left window is ``camera`` (a camera whose
    ROI grew: its frames outgrow the shared buffer)."""
    w, h = camera.width * scale, camera.height * scale
    px, py = camera.pixel_size_mm
    return replace(
        camera,
        width=w,
        height=h,
        x0_mm=camera.x0_mm - ((w - 1) / 2 - (camera.width - 1) / 2) * px,
        y0_mm=camera.y0_mm - ((h - 1) / 2 - (camera.height - 1) / 2) * py,
    )


def test_a_larger_frame_than_the_buffer_gets_a_larger_buffer(frames, child):
    small = frames[0].image
    big = np.zeros((small.shape[0] * 2, small.shape[1] * 2), small.dtype)
    big[: small.shape[0], : small.shape[1]] = small
    window = _larger(reference_camera()).cropped(0, 0, 1300, 1030)
    assert (window.x0_mm, window.y0_mm) == pytest.approx((reference_camera().x0_mm, reference_camera().y0_mm))
    assert child.measure(small).mode == "full"
    child.configure(_larger(reference_camera()), reference_field(), MeasureSettings())
    out = child.measure(big)  # the same targets at the top left of a four times larger frame
    assert isinstance(out.result, PoseResult) and len(out.result.targets) > 100
    assert child.restarts == 0


def test_a_killed_child_costs_one_frame_with_a_sentence_and_the_next_frame_has_a_new_one(frames, child):
    assert isinstance(child.measure(frames[0].image, 0.0).result, PoseResult)
    first = child.pid
    assert first is not None
    os.kill(first, signal.SIGSTOP)  # stopped, it cannot answer before it is killed
    child.submit(frames[1].image, DT_S)
    os.kill(first, signal.SIGKILL)
    with pytest.raises(MeasureProcessError, match=r"camera cam0 died \(exit code -9\); a new one starts"):
        child.collect()
    out = child.measure(frames[2].image, 2 * DT_S)
    assert isinstance(out.result, PoseResult) and out.mode == "full"  # tracking starts again
    assert child.pid not in (None, first) and child.restarts == 1


def test_a_hung_child_is_replaced_after_the_timeout(frames, child):
    child.measure_timeout_s = 1.0
    hung = child.pid
    assert hung is not None
    os.kill(hung, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        with pytest.raises(MeasureProcessError, match="did not answer within 1 s"):
            child.measure(frames[0].image)
        assert time.monotonic() - t0 < 5.0
    finally:
        try:
            os.kill(hung, signal.SIGCONT)
        except ProcessLookupError:
            pass  # killed by the replacement, as it should be
    assert isinstance(child.measure(frames[0].image).result, PoseResult) and child.pid != hung


def test_an_error_in_the_child_comes_back_as_a_sentence_and_the_child_stays(frames, child):
    pid = child.pid
    bad = child.measure(np.zeros((4, 4, 3), np.float32))  # not a grey image: a failure, not an error
    assert not bad.result.ok and bad.result.reason == "bad_image"
    with pytest.raises(MeasureProcessError, match=r"camera cam0 failed: ValueError.*unknown request 'frobnicate'"):
        child._call(("frobnicate",), 5.0)  # what any exception in the child becomes
    assert child.pid == pid and child.restarts == 0
    assert isinstance(child.measure(frames[0].image).result, PoseResult)


def test_two_frames_in_flight_are_answered_in_order_and_a_third_waits(frames, child):
    with pytest.raises(MeasureProcessError, match="no frame was submitted"):
        child.collect()
    here = FrameMeasurer(reference_camera(), reference_field(), MeasureSettings())
    expected = [here.measure(f.image, k * DT_S) for k, f in enumerate(frames[:4])]
    child.submit(frames[0].image, 0.0)
    child.submit(frames[1].image, DT_S)
    assert not child.can_submit()
    with pytest.raises(MeasureProcessError, match="2 frames are already being measured"):
        child.submit(frames[2].image, 2 * DT_S)
    got = [child.collect()]
    child.submit(frames[2].image, 2 * DT_S)  # the slot of the first is free again
    got.append(child.collect())
    child.submit(frames[3].image, 3 * DT_S)
    got += [child.collect(), child.collect()]
    for g, e in zip(got, expected):
        assert g.mode == e.mode
        np.testing.assert_array_equal(g.result.T_field_camera, e.result.T_field_camera)


def test_a_larger_frame_while_another_is_in_flight_gets_a_new_buffer_and_both_are_right(frames, child):
    small = frames[0].image
    big = np.zeros((small.shape[0] * 2, small.shape[1] * 2), small.dtype)
    big[: small.shape[0], : small.shape[1]] = frames[1].image
    child.measure(small)  # the buffer is sized for the small frames
    child.submit(small)
    child.configure(_larger(reference_camera()), reference_field(), MeasureSettings())  # the ROI grew
    child.submit(big)  # read by the child from the new buffer, after the first from the old one
    first, second = child.collect(), child.collect()
    assert isinstance(first.result, PoseResult) and isinstance(second.result, PoseResult)
    here = FrameMeasurer(reference_camera(), reference_field(), MeasureSettings())
    np.testing.assert_array_equal(first.result.T_field_camera, here.measure(small).result.T_field_camera)
    here = FrameMeasurer(_larger(reference_camera()), reference_field(), MeasureSettings())
    np.testing.assert_array_equal(second.result.T_field_camera, here.measure(big).result.T_field_camera)


def test_frames_in_flight_when_the_child_dies_each_fail_with_the_sentence(frames, child):
    child.measure(frames[0].image)
    pid = child.pid
    os.kill(pid, signal.SIGSTOP)  # stopped, it cannot answer before it is killed
    child.submit(frames[1].image)
    child.submit(frames[2].image)
    os.kill(pid, signal.SIGKILL)
    for _ in range(2):
        with pytest.raises(MeasureProcessError, match="died"):
            child.collect()
    with pytest.raises(MeasureProcessError, match="no frame was submitted"):
        child.collect()
    assert isinstance(child.measure(frames[3].image).result, PoseResult) and child.restarts == 1


def test_a_set_up_that_fails_in_the_child_is_told_with_every_frame_until_a_good_one(frames, child):
    child.configure(reference_camera(), "not a field", MeasureSettings())  # type: ignore[arg-type]
    for _ in range(2):
        with pytest.raises(MeasureProcessError, match="the setup failed"):
            child.measure(frames[0].image)
    child.configure(reference_camera(), reference_field(), MeasureSettings())
    assert isinstance(child.measure(frames[0].image).result, PoseResult) and child.restarts == 0


def test_no_shared_buffer_file_is_left_behind(frames, monkeypatch):
    # the buffers this process makes, by name (other processes, e.g. another test worker's service,
    # make and remove theirs in /dev/shm meanwhile)
    made: list[str] = []
    real_mkstemp = tempfile.mkstemp

    def mkstemp(*args, **kwargs):
        fd, path = real_mkstemp(*args, **kwargs)
        made.append(path)
        return fd, path

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    process = MeasureProcess("cam0")
    process.configure(reference_camera(), reference_field(), MeasureSettings())
    process.measure(frames[0].image)
    process.close()
    buffers = [p for p in made if os.path.basename(p).startswith("posecell-frames-")]
    assert buffers and not [p for p in buffers if os.path.exists(p)], buffers


def test_a_child_that_cannot_be_started_is_a_sentence_for_every_frame_and_one_log_line(monkeypatch, caplog):
    from service.runtime import measure_process

    def no_processes():
        raise OSError(11, "Resource temporarily unavailable")  # EAGAIN: fork refused

    monkeypatch.setattr(measure_process, "_fork_server", no_processes)
    process = MeasureProcess("cam0")
    with caplog.at_level("ERROR", logger="service.runtime.measure_process"):
        for _ in range(3):
            with pytest.raises(MeasureProcessError, match=r"camera cam0 could not be started.*temporarily unavailable"):
                process.configure(reference_camera(), reference_field(), MeasureSettings())
    assert sum("could not be started" in r.getMessage() for r in caplog.records) == 1
    assert process.pid is None


@pytest.mark.parametrize("request_", [("ping",), ("measure", 0, (4, 4), "|u1", None)])
def test_a_child_whose_parent_has_gone_ends_quietly_instead_of_with_a_broken_pipe(request_, monkeypatch):
    """At the service's shutdown the parent closes its end while a frame may be in flight: the
    child's answer then meets a closed pipe, and it returns (exit code 0) without a traceback."""
    import multiprocessing

    from service.runtime import measure_process

    monkeypatch.setattr(measure_process.signal, "signal", lambda *a: None)  # the test runner's Ctrl-C stays
    parent, child_end = multiprocessing.Pipe()
    parent.send(request_)  # answered: "ok" for the ping, an error (no set-up yet) for the frame
    parent.close()
    measure_process.serve(child_end)  # returns; before, the answer raised BrokenPipeError
    child_end.close()
