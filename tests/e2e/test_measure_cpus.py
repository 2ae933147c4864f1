"""A fast camera's measurement child on a CPU of its own, the service's per-frame threads off it
(``measure_cpus``), in the running service, and back to shared CPUs at run time."""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
import pytest

from service.bench.child import TOKEN, health, serve_child, wait_ready
from service.bench.service import _config

pytestmark = [
    pytest.mark.slow,  # a served replay camera at 200 Hz
    pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one CPU: nothing to dedicate (tests/test_cpus.py)"),
]


def _allowed(status: Path) -> set[int]:
    """The Cpus_allowed_list of a /proc status file, e.g. "0-2,5"."""
    line = next(x for x in status.read_text().splitlines() if x.startswith("Cpus_allowed_list:"))
    cpus: set[int] = set()
    for part in line.split(":", 1)[1].strip().split(","):
        lo, _, hi = part.partition("-")
        cpus.update(range(int(lo), int(hi or lo) + 1))
    return cpus


def _threads(pid: int) -> dict[int, set[int]]:
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out[int(task.name)] = _allowed(task / "status")
        except (FileNotFoundError, ProcessLookupError):  # ended meanwhile
            continue
    return out


def test_a_fast_camera_gets_a_cpu_of_its_own_and_gives_it_back_at_run_time(tmp_path):
    allowed = sorted(os.sched_getaffinity(0))  # the served process inherits this
    config = tmp_path / "bench.toml"
    config.write_text(_config(200.0))
    with serve_child(tmp_path, config) as served:
        wait_ready(served.address, timeout_s=300.0)
        h = health(served.address)
        cpus, child = h["processing"]["cpus"], h["processing"]["measurement"]["cam0"]["pid"]
        assert cpus["measurement"] == {"cam0": allowed[-1]} and cpus["service"] == allowed[:-1], cpus
        assert _allowed(Path(f"/proc/{child}/status")) == {allowed[-1]}
        threads = _threads(served.pid)
        # the event loop (the main thread: its thread id is the process's) keeps every CPU for the fan-out
        assert threads.pop(served.pid) == set(allowed)
        # the per-frame threads (processing, the camera's, the store's writer, the simulated robot) are
        # kept off the child's CPU; threads the loop starts later (the API's workers) inherit its CPUs
        assert sum(t == set(allowed[:-1]) for t in threads.values()) >= 4, threads
        assert all(t in (set(allowed[:-1]), set(allowed)) for t in threads.values()), threads
        ok0 = h["processing"]["ok"]
        time.sleep(1.0)
        assert health(served.address)["processing"]["ok"] > ok0 + 50  # measuring at ~200 Hz meanwhile

        r = httpx.put(
            f"http://{served.address}/config",
            json={"processing": {"measure_cpus": "shared"}},
            headers={"Authorization": f"Bearer {TOKEN}"},
            timeout=10.0,
        )
        assert r.status_code == 200, r.text
        h = health(served.address)
        assert h["processing"]["cpus"]["measurement"] == {} and h["processing"]["cpus"]["service"] == allowed
        assert _allowed(Path(f"/proc/{child}/status")) == set(allowed)
        assert all(t == set(allowed) for t in _threads(served.pid).values())
