"""Which CPUs the measurement children and the service's own threads run on (``[processing] measure_cpus``).

At hundreds of frames a second a camera's measurement child needs most of a CPU, and every
per-frame thread of the service that the scheduler puts on that CPU makes a frame wait. On a
2-CPU host at 500 Hz (`posecell bench service`, 2026-12-05), the child's CPU kept to itself and
the processing, camera, storage and robot threads on the other: one client 489-493 -> 500
results/s, frames lost 1.5-2.4 % -> 0.1-0.3 %, exposure -> WebSocket p99 9.8-10.6 -> 6.4-6.7 ms;
50 clients 433-485 -> 489-499 /s, lost 3.1-13.5 % -> 0.2-2.2 %, p99 11.4-13.5 -> 7.8-9.9 ms.
The event loop (the main thread) keeps every CPU: kept to the one left, its fan-out to 50
clients fell behind in 2 of 5 runs. At a few frames a second the split would only take a CPU
away from everything else (the simulated camera's renderer among it), so ``auto`` dedicates CPUs
from :data:`DEDICATED_FROM_HZ` of the children's frames a second on, and only while one CPU at
least is left for the service.

A thread or process started after :func:`pin_threads` inherits its creator's CPUs.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from service.runtime.processor import CameraProcessor
    from service.settings import Settings

log = logging.getLogger(__name__)

DEDICATED_FROM_HZ = 100.0  # "auto": the children's frames a second from which each gets a CPU of its own

Mode = Literal["auto", "dedicated", "shared"]


@dataclass(frozen=True)
class CpuPlan:
    """Per camera, its measurement child's CPU; the CPUs of everything else; why (a sentence)."""

    children: dict[str, int]
    service: frozenset[int]
    why: str

    def to_dict(self) -> dict[str, object]:
        return {"measurement": dict(self.children), "service": sorted(self.service), "why": self.why}


def plan_cpus(mode: Mode, cameras: Sequence[tuple[str, float | None]], allowed: Iterable[int]) -> CpuPlan:
    """The CPUs of the measurement children (``cameras``: name and frame rate, Hz, of each camera
    measured in a child) and of the service, from the CPUs the service may use.

    The children take the last CPUs, one each; an empty ``children`` shares every CPU."""
    cpus = sorted(set(allowed))
    every = frozenset(cpus)
    total_hz = sum(rate or 0.0 for _, rate in cameras)
    if mode == "shared" or not cameras:
        return CpuPlan({}, every, "shared: no measurement child" if not cameras else "shared, as configured")
    if len(cpus) <= len(cameras):
        return CpuPlan({}, every, f"shared: {len(cpus)} CPUs for {len(cameras)} measurement children and the service")
    if mode == "auto" and total_hz < DEDICATED_FROM_HZ:
        return CpuPlan({}, every, f"shared: {total_hz:g} frames/s, below the {DEDICATED_FROM_HZ:g} that dedicate CPUs")
    mine = cpus[-len(cameras) :]
    children = {name: cpu for (name, _), cpu in zip(cameras, mine, strict=True)}
    service = every - set(mine)
    listed = ", ".join(f"camera {name} on CPU {cpu}" for name, cpu in children.items())
    return CpuPlan(children, service, f"dedicated: {listed}; the service on CPUs {_ranges(service)}")


def plan_for(settings: Settings, running: Sequence[str], allowed: Iterable[int]) -> CpuPlan:
    """:func:`plan_cpus` for the running cameras (``running``: their names) measured in children."""
    processing = settings.processing
    children = [(c.name, c.frame_rate_hz) for c in settings.cameras if c.name in running]
    return plan_cpus(processing.measure_cpus, children if processing.measure_in == "process" else [], allowed)


def keep_to(plan: CpuPlan, processors: Mapping[str, CameraProcessor]) -> None:
    """The service's threads and each camera's measurement child onto the plan's CPUs. A child
    without a CPU of its own gets the service's: said explicitly, since the fork server the children
    come from keeps the CPUs it was started with."""
    # the event loop (the main thread) keeps every CPU: its fan-out to many clients needs more than
    # the one CPU a 2-CPU host leaves the service (50 clients at 500 Hz fell behind in 2 of 5 runs
    # kept to it); what it starts inherits every CPU too. The heavy per-frame threads stay off.
    pin_threads(plan.service, spare=frozenset({threading.main_thread().native_id or -1}))
    for name, proc in processors.items():
        cpu = plan.children.get(name)
        proc.keep_child_to(plan.service if cpu is None else frozenset({cpu}))


def pin_threads(cpus: frozenset[int], spare: frozenset[int] = frozenset()) -> None:
    """Every thread of this process onto ``cpus`` (Linux: affinity is a thread's; new threads and
    processes inherit their creator's), but those whose thread ids are in ``spare``."""
    for task in Path("/proc/self/task").iterdir():
        if int(task.name) in spare:
            continue
        try:
            os.sched_setaffinity(int(task.name), cpus)
        except (ProcessLookupError, FileNotFoundError):  # ended meanwhile
            continue


def pin_process(pid: int, cpus: frozenset[int]) -> None:
    """A child process onto ``cpus``; a failure is logged (the child still measures, shared)."""
    try:
        os.sched_setaffinity(pid, cpus)
    except OSError as e:
        log.warning("process %d could not be kept to CPUs %s: %s", pid, _ranges(cpus), e)


def _ranges(cpus: Iterable[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus))
