"""``[processing] measure_cpus``: which CPUs the measurement children and the service's threads get."""

from __future__ import annotations

import os
import threading

import pytest

from service.runtime.cpus import DEDICATED_FROM_HZ, pin_threads, plan_cpus


def test_a_fast_camera_gets_the_last_cpu_and_the_service_the_others():
    plan = plan_cpus("auto", [("cam0", 500.0)], {0, 1, 2, 3})
    assert plan.children == {"cam0": 3} and plan.service == {0, 1, 2}
    assert "dedicated" in plan.why and "camera cam0 on CPU 3" in plan.why


def test_two_cameras_take_one_cpu_each_from_the_end():
    plan = plan_cpus("dedicated", [("a", 20.0), ("b", None)], {0, 1, 2})
    assert plan.children == {"a": 1, "b": 2} and plan.service == {0}


def test_auto_shares_every_cpu_below_the_rate_that_needs_one():
    plan = plan_cpus("auto", [("cam0", DEDICATED_FROM_HZ / 2), ("cam1", None)], {0, 1, 2})
    assert plan.children == {} and plan.service == {0, 1, 2} and "below" in plan.why


def test_dedicated_is_refused_when_no_cpu_would_be_left_for_the_service():
    plan = plan_cpus("dedicated", [("a", 500.0), ("b", 500.0)], {0, 1})
    assert plan.children == {} and plan.service == {0, 1}
    assert "2 CPUs for 2 measurement children" in plan.why


def test_shared_and_no_children_share_every_cpu():
    assert plan_cpus("shared", [("cam0", 1000.0)], {0, 1}).children == {}
    plan = plan_cpus("dedicated", [], {0, 1})
    assert plan.children == {} and plan.service == {0, 1} and "no measurement child" in plan.why


def test_the_plan_says_itself_for_health():
    d = plan_cpus("auto", [("cam0", 500.0)], {0, 1}).to_dict()
    assert d["measurement"] == {"cam0": 1} and d["service"] == [0] and d["why"].startswith("dedicated")


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: no subset to keep the threads to")
def test_pin_threads_moves_every_thread_of_the_process_but_the_spared_and_new_ones_inherit():
    allowed = frozenset(os.sched_getaffinity(0))
    first = frozenset({min(allowed)})
    stop = threading.Event()
    t = threading.Thread(target=stop.wait, daemon=True)
    t.start()
    try:
        pin_threads(first, spare=frozenset({t.native_id}))
        assert os.sched_getaffinity(t.native_id) == allowed
        pin_threads(first)
        assert os.sched_getaffinity(0) == first
        assert os.sched_getaffinity(t.native_id) == first
        seen: list[set[int]] = []
        later = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0)))
        later.start()
        later.join()
        assert seen == [first]
    finally:
        pin_threads(allowed)
        stop.set()
    assert os.sched_getaffinity(0) == allowed and os.sched_getaffinity(t.native_id) == allowed
