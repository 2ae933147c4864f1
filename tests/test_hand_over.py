"""The camera's thread hands each frame to its measurement child as it arrives
(``[processing] direct_hand_over``), one thread wake-up before the processing thread could."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from drivers.base import Frame
from service.core.measurement import Measurement
from service.runtime.acquisition import CameraChannel
from service.runtime.processor import Pending
from service.runtime.worker import Worker
from service.settings import load_settings


def _replay_worker(tmp_path, rate_hz: float, direct: bool) -> Worker:
    settings = load_settings(None, state_dir=str(tmp_path))
    cam = settings.cameras[0].model_copy(
        update={
            "driver": "replay",
            "frame_rate_hz": rate_hz,
            "options": {"source": "sim", "n_frames": 20, "loop": "bounce"},
        }
    )
    processing = settings.processing.model_copy(update={"direct_hand_over": direct})
    return Worker(settings.model_copy(update={"cameras": [cam], "processing": processing}))


def _run(worker: Worker, seconds: float) -> list[Measurement]:
    got: list[Measurement] = []
    worker.subscribe(got.append)
    worker.start()
    try:
        deadline = time.monotonic() + 90.0  # the replay renders its frames, the child loads the kernels
        while not any(m.ok for m in got) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert any(m.ok for m in got), "no pose from the replayed cell within 90 s"
        n0 = len(got)
        time.sleep(seconds)
        return got[n0:]
    finally:
        worker.stop()


@pytest.mark.parametrize("direct", [True, False], ids=["by the camera's thread", "by the processing thread"])
def test_frames_are_begun_where_configured_all_measured_in_order(tmp_path, direct):
    worker = _replay_worker(tmp_path, 200.0, direct)
    results = _run(worker, 1.5)
    assert len(results) > 50  # of ~300 frames: a loaded 2-core machine still keeps a good part
    # no frame is handed to a child that has two already (the two threads check and begin under one lock)
    assert all(m.ok for m in results), {m.reason: m.message for m in results if not m.ok}
    seqs = [m.seq for m in results]
    assert all(b > a for a, b in itertools.pairwise(seqs)), "results out of frame order"
    by_camera = worker.health()["processing"]["handed_over_by_camera"]
    if direct:
        # the camera's thread begins a frame whenever the child has room: all but those arriving while
        # two are in flight (or during a full frame), which the processing thread begins from the slot.
        # On an idle host that is 98 % of them; under the whole suite on a slow 2-core host the child
        # falls behind and 47 % was seen (without the option: none)
        assert by_camera >= 0.25 * worker.counters["results"]
    else:
        assert by_camera == 0


class _ChildReady:
    """A processor whose measurement child is set up and has room (the hand-over's only question)."""

    depth = 2

    def begins_at_once(self) -> bool:
        return True

    def can_begin(self) -> bool:
        return True

    def begin(self, frame: Frame) -> Pending:
        return Pending(frame, frame.t_host_ns, "arrival", 0.0)


def _frame(seq: int) -> Frame:
    return Frame(np.zeros((4, 4), np.uint8), seq, None, time.monotonic_ns(), 1000.0)


def test_a_frame_begun_by_its_camera_drops_the_older_one_waiting_in_its_slot(tmp_path):
    # the older frame would otherwise be begun after it by the processing thread: results out of order
    worker = Worker(load_settings(None, state_dir=str(tmp_path)))
    hand = worker.hand_over
    ch = CameraChannel("cam0", None, worker.settings.cameras[0].camera_settings(), worker._wakeup, worker.event)  # type: ignore[arg-type]
    worker.cameras["cam0"] = ch
    worker.processors["cam0"] = _ChildReady()  # type: ignore[assignment]
    worker._processing_ready.set()
    ch.slot.put(_frame(1))
    assert hand.begin_at_once("cam0", _frame(2))
    assert ch.slot.take() is None and ch.counters.dropped == 1
    assert [f.seq for _, f, _ in hand.in_flight] == [2]
    assert hand.begin_at_once("cam0", _frame(3))
    assert not hand.begin_at_once("cam0", _frame(4))  # two in flight: to the slot, for the processing thread
    assert [f.seq for _, f, _ in hand.in_flight] == [2, 3]
    worker.settings = worker.settings.with_processing(
        worker.settings.processing.model_copy(update={"direct_hand_over": False})
    )
    hand.in_flight.clear()
    assert not hand.begin_at_once("cam0", _frame(5))  # switched off at run time
