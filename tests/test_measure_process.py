"""The measurement in a child process: the same outcomes as in this one; a dead, hung or failing child
costs a frame with a sentence, never the stream."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from service.bench.speed import frames_along_path
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


def test_a_larger_frame_than_the_buffer_gets_a_larger_buffer(frames, child):
    small = frames[0].image
    big = np.zeros((small.shape[0] * 2, small.shape[1] * 2), small.dtype)
    big[: small.shape[0], : small.shape[1]] = small
    assert child.measure(small).mode == "full"
    out = child.measure(big)  # the same targets at the top left of a four times larger frame
    assert isinstance(out.result, PoseResult) and len(out.result.targets) > 100
    assert child.restarts == 0


def test_a_killed_child_costs_one_frame_with_a_sentence_and_the_next_frame_has_a_new_one(frames, child):
    assert isinstance(child.measure(frames[0].image, 0.0).result, PoseResult)
    first = child.pid
    assert first is not None
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


def test_one_frame_at_a_time_and_nothing_to_collect_without_a_frame(frames, child):
    with pytest.raises(MeasureProcessError, match="no frame was submitted"):
        child.collect()
    child.submit(frames[0].image)
    with pytest.raises(MeasureProcessError, match="already being measured"):
        child.submit(frames[1].image)
    assert isinstance(child.collect().result, PoseResult)


def test_no_shared_buffer_file_is_left_behind(frames):
    before = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    process = MeasureProcess("cam0")
    process.configure(reference_camera(), reference_field(), MeasureSettings())
    process.measure(frames[0].image)
    process.close()
    after = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    assert not {n for n in after - before if n.startswith("posecell-frames-")}
