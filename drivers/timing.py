"""Host timing shared by drivers and stand-ins: a thread's scheduling priority, real-time stamps on the monotonic clock.

A time stamp taken by a thread that woke late is late by as much, and on a busy
host (image processing on every core) that is milliseconds. The threads that
take stamps therefore run at a raised priority where the process may raise it
(CAP_SYS_NICE; nice is per thread on Linux and a new thread inherits its
creator's, so a library's thread is raised by creating it inside
:func:`thread_nice`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator

log = logging.getLogger(__name__)

__all__ = ["arrival_ns", "thread_nice"]

MAX_QUEUED_NS = 1_000_000_000  # a reception stamp older than this when its frame is taken is not trusted


@contextlib.contextmanager
def thread_nice(nice: int | None) -> Iterator[bool]:
    """Run the block with this thread's nice value at ``nice`` (None: unchanged); yields whether it was set."""
    if nice is None:
        yield False
        return
    tid = threading.get_native_id()
    try:
        before = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except OSError:  # lowering it needs CAP_SYS_NICE: the block runs at the priority it has
        yield False
        return
    try:
        yield True
    finally:
        try:
            os.setpriority(os.PRIO_PROCESS, tid, before)
        except OSError:
            log.warning("could not restore the priority of thread %d", tid)


def arrival_ns(t_taken_ns: int, t_received_real_ns: int, real_minus_mono_ns: int) -> int:
    """A frame's arrival on the monotonic clock: its reception stamp (real-time clock) where it can be trusted.

    ``t_taken_ns`` (monotonic) is when the frame was taken from the library's queue, the upper
    bound and the fall-back: for a missing stamp (0), one later than that, or one more than
    ``MAX_QUEUED_NS`` older.

    >>> arrival_ns(5_000_000, 1_000_003_000_000, 1_000_000_000_000)  # received 2 ms before it was taken
    3000000
    >>> arrival_ns(5_000_000, 0, 1_000_000_000_000)  # no reception stamp
    5000000
    """
    if t_received_real_ns <= 0:
        return t_taken_ns
    t_ns = t_received_real_ns - real_minus_mono_ns
    return t_ns if 0 <= t_taken_ns - t_ns < MAX_QUEUED_NS else t_taken_ns
