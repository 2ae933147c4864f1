"""The host watch of the benchmarks and timed tests sees a stall of its host (here: of its own process)."""

from __future__ import annotations

import os
import signal
import time

from service.bench.stalls import STALL_MS, HostStalls, HostWatch, steal_pct


def test_a_stopped_host_is_seen_as_a_stall_at_its_time_and_length():
    with HostWatch() as watch:
        assert watch._proc is not None
        time.sleep(0.4)
        os.kill(watch._proc.pid, signal.SIGSTOP)  # as a VM whose vCPU the host takes away
        time.sleep(0.3)
        os.kill(watch._proc.pid, signal.SIGCONT)
        time.sleep(0.2)
    r = watch.result
    assert r is not None and 0.85 < r.seconds < 2.0
    long = [(t, ms) for t, ms in r.stalls if ms > 250.0]
    assert len(long) == 1, r
    t_s, ms = long[0]
    assert 0.3 < t_s < 0.6 and 250.0 < ms < 600.0  # at 0.4 s, 300 ms (a loaded host adds to both)
    assert r.max_ms >= ms and r.stalled_ms >= ms
    assert f"{ms:.0f} ms at {t_s:.1f} s" in r.sentence()


def test_the_sentence_says_when_there_was_no_stall():
    r = HostStalls(tick_ms=2.0, seconds=2.0, p99_ms=0.3, max_ms=1.2, stalls=())
    assert (
        r.sentence()
        == f"the host over 2.0 s: a 2 ms sleep woke 0.3 ms late at p99, 1.2 ms at most; no stall over {STALL_MS:.0f} ms"
    )
    assert r.stalled_ms == 0.0
    two = HostStalls(tick_ms=2.0, seconds=2.0, p99_ms=0.3, max_ms=900.0, stalls=((0.5, 400.0), (1.2, 900.0)))
    assert two.stalled_ms == 1300.0 and "2 stalls over 100 ms (400 ms at 0.5 s, 900 ms at 1.2 s)" in two.sentence()


def test_the_hypervisors_share_is_the_steal_columns_of_the_cpu_time():
    assert steal_pct([100, 0, 10, 880, 0, 0, 0, 10], [190, 0, 20, 960, 0, 0, 0, 30]) == 10.0
    assert steal_pct(None, [1] * 8) is None and steal_pct([1] * 8, [1] * 8) is None  # unknown, no time passed
    r = HostStalls(tick_ms=2.0, seconds=2.0, p99_ms=0.3, max_ms=1.2, stalls=(), steal_pct=12.5)
    assert r.sentence().startswith("the host over 2.0 s, 12.5 % of the CPUs' time stolen by the hypervisor: ")
    with HostWatch() as watch:  # on Linux, read from /proc/stat
        time.sleep(0.3)
    assert watch.result is not None and watch.result.steal_pct is not None and 0.0 <= watch.result.steal_pct <= 100.0
