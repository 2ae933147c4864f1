"""The frames on their way to the cameras' measurements: which are in flight, and who begins them.

A frame is begun (handed to its camera's measurement, :meth:`CameraProcessor.begin`) by one of two
threads:

- its camera's acquisition thread, as it arrives (:meth:`HandOver.begin_at_once`, the
  :class:`~service.runtime.acquisition.CameraChannel`'s ``on_frame``), when the measurement runs
  in a child that is set up and can take one more frame (``[processing] direct_hand_over``). At
  500 Hz the processing thread's wake-up between a frame's arrival and its hand-over was 0.25 ms
  of the median exposure -> WebSocket and 1-1.6 ms of the slowest hundredth, and frames that
  came while it finished the last result waited in the slot, where the next replaced them;
- else the processing thread, from the camera's one-frame slot (:meth:`HandOver.hand_over`).

Both check, take and begin with the wake-up's lock held, so a child never gets a frame more than
it has room for and frames are begun in the order they came (a frame begun by its camera drops
the older one in its slot). The processing thread collects the outcomes oldest first.
"""

from __future__ import annotations

import select
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping

from drivers.base import Frame
from service.core.measurement import Measurement
from service.runtime.acquisition import CameraChannel, Wakeup
from service.runtime.measure_process import MEASURE_TIMEOUT_S
from service.runtime.processor import CameraProcessor, Pending

InFlight = tuple[str, Frame, Pending | Measurement]  # camera, frame, its measurement begun (or its failure)


class HandOver:
    """The frames in flight, oldest first (see the module docstring)."""

    def __init__(
        self,
        cameras: Mapping[str, CameraChannel],
        processors: Mapping[str, CameraProcessor],
        wakeup: Wakeup,
        direct: Callable[[], bool],
        on_error: Callable[[str, Exception], Measurement],
        ready: threading.Event,
        stopping: threading.Event,
    ) -> None:
        self._cameras = cameras
        self._processors = processors
        self._wakeup = wakeup
        self._direct = direct  # the current settings' direct_hand_over
        self._on_error = on_error  # a frame that could not be begun: its failed result
        self.in_flight: deque[InFlight] = deque()  # guarded by the wake-up's lock
        self.ready = ready  # the measurers are built: before, no camera's thread begins a frame
        self.stopping = stopping
        self.by_camera = 0  # frames their camera's thread began
        # the poll sets of wait_for_outcome, kept while its connection is the same: made per call (as
        # multiprocessing.connection.wait does, Connection.poll too) they were ~9 and ~15 % of the
        # processing thread's time at 500 Hz
        self._poll: tuple[int, int, select.poll, select.poll] | None = None

    def pop(self) -> InFlight | None:
        with self._wakeup:
            return self.in_flight.popleft() if self.in_flight else None

    def collect(self, processor: CameraProcessor, pending: Pending) -> None:
        """The outcome of the oldest frame, once :meth:`wait_for_outcome` has returned."""
        with self._wakeup:  # the camera's thread may be handing the child its next frame
            processor.collect(pending)

    def hand_over(self, wait_s: float) -> None:
        """Begin the newest waiting frames while every camera's measurement can take one more;
        with nothing in flight, wait up to ``wait_s`` for a frame.

        A frame is taken from its slot only when it can be begun at once: one held back would
        be older than the slot's newest by the time it is.
        """
        depth = min((p.depth for p in self._processors.values()), default=1)
        with self._wakeup:
            while len(self.in_flight) < depth and all(p.can_begin() for p in self._processors.values()):
                got = self._take_frame()
                if got is None:
                    if wait_s <= 0 or self.in_flight or self.stopping.is_set():
                        return
                    self._wakeup.wait(wait_s)  # a frame, a frame begun by its camera or a state change wakes it
                    wait_s = 0.0
                    continue
                self.in_flight.append(self._begin(*got))
                wait_s = 0.0

    def begin_at_once(self, name: str, frame: Frame) -> bool:
        """The camera's thread's hand-over: begin the frame now if its measurement runs in a child
        that is set up and can take it (True); else (False) the frame goes to the slot."""
        processor = self._processors.get(name)
        if processor is None or not self.ready.is_set() or self.stopping.is_set() or not self._direct():
            return False
        with self._wakeup:
            if len(self.in_flight) >= processor.depth or not all(p.begins_at_once() for p in self._processors.values()):
                return False
            ch = self._cameras.get(name)
            if ch is not None and ch.slot.take() is not None:  # older, and never to be begun after this one
                ch.counters.dropped += 1
            self.in_flight.append(self._begin(name, frame))
            self.by_camera += 1
            # an idle processing thread waits for this outcome from now on; one waiting for an older
            # outcome has nothing to do before it (a wake-up a frame, ~0.1 ms of its CPU at 500 Hz)
            self._wakeup.notify_waiters()
        return True

    def wait_for_outcome(self, processor: CameraProcessor) -> None:
        """Wait until the oldest frame's outcome can be collected; a frame arriving in a slot
        meanwhile is handed over at once (it would otherwise wait for this one's outcome, flange
        and fan-out)."""
        with self._wakeup:
            conn = processor.waitable()
        if conn is None:
            return
        deadline = time.monotonic() + MEASURE_TIMEOUT_S
        try:
            fd = conn.fileno()
            answered, poller = self._poll_sets(fd)
            while not answered.poll(0) and (remaining_s := deadline - time.monotonic()) > 0:
                self._wakeup.drain()
                self.hand_over(0.0)
                ready = poller.poll(max(1, int(remaining_s * 1e3 + 1)))  # ms, rounded up
                if not ready or any(f == fd for f, _ in ready):  # an answer, a closed pipe, or the timeout
                    return
        except (OSError, EOFError, ValueError):
            return  # the child went away (its connection closed): collect() says so

    def _poll_sets(self, fd: int) -> tuple[select.poll, select.poll]:
        """Poll sets of the connection ``fd`` alone (is the answer there?) and of it with the
        wake-up's pipe (wait for either), made again for another child."""
        wake = self._wakeup.fileno()
        if self._poll is None or self._poll[:2] != (fd, wake):
            answered, either = select.poll(), select.poll()
            answered.register(fd, select.POLLIN)
            either.register(fd, select.POLLIN)
            either.register(wake, select.POLLIN)
            self._poll = (fd, wake, answered, either)
        return self._poll[2], self._poll[3]

    def _take_frame(self) -> tuple[str, Frame] | None:
        for name, ch in self._cameras.items():
            frame = ch.slot.take()
            if frame is not None:
                return name, frame
        return None

    def _begin(self, name: str, frame: Frame) -> InFlight:
        try:
            return name, frame, self._processors[name].begin(frame)
        except Exception as e:
            return name, frame, self._on_error(name, e)
