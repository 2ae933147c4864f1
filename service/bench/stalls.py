"""The host's own stalls during a measurement: a process that only sleeps 2 ms at a time, and how late it wakes.

Why: on a VM whose vCPUs the host shares, the whole guest can stop for a moment (seen on
2026-12-06: a whole-suite run whose RTDE client read no sample in a second, a camera test that
lost 2 s of frames). A latency p99 or a frame count over such a stretch says more about the host
than about posecell. :class:`HostWatch` runs beside a benchmark row or a timed test, in a process
of its own (no interpreter lock shared with what it watches), and says how late a short sleep woke:
its p99 and its longest, and the stretches over ``STALL_MS``; and the share of the CPUs' time the
hypervisor gave to others meanwhile (``steal`` in ``/proc/stat``: a VM's slow stretch, which no
wake-up shows) — so a figure can be read against the host it was taken on.

    with HostWatch() as watch:
        ...  # the measurement
    print(watch.result.sentence())
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

STALL_MS = 100.0  # a wake-up this late is a stall of the host, not scheduling noise
TICK_S = 0.002  # the watcher's sleep: 500 wake-ups a second, ~1 % of a core taken from what it watches

# the watcher: wakes every tick (select on its stdin: the parent closing it is the stop), keeps
# each wake-up's lateness, and prints them summarised as one JSON line
_WATCHER = """
import json, select, sys, time
tick, stall_ms = float(sys.argv[1]), float(sys.argv[2])
late_ms, stalls = [], []
print("ready", flush=True)
t0 = last = time.monotonic()
while True:
    r, _, _ = select.select([sys.stdin], [], [], tick)
    now = time.monotonic()
    late = (now - last - tick) * 1e3
    late_ms.append(late)
    if late > stall_ms:
        stalls.append([round(last - t0, 3), round(late, 1)])
    last = now
    if r:
        break
late_ms.sort()
n = len(late_ms)
print(json.dumps({"seconds": now - t0, "wakes": n, "p99_ms": round(late_ms[min(n - 1, int(0.99 * n))], 2),
                  "max_ms": round(late_ms[-1], 1), "stalls": stalls}), flush=True)
"""


@dataclass(frozen=True)
class HostStalls:
    """How late a sleep of ``tick_ms`` woke during ``seconds``: p99 and longest lateness, ms, and each
    stall over STALL_MS as (seconds after the start, ms late)."""

    tick_ms: float
    seconds: float
    p99_ms: float
    max_ms: float
    stalls: tuple[tuple[float, float], ...]
    steal_pct: float | None = None  # of all the CPUs' time, taken by the hypervisor (None: not known)

    @property
    def stalled_ms(self) -> float:
        """The stalls' total, ms."""
        return sum(ms for _, ms in self.stalls)

    def sentence(self) -> str:
        steal = "" if self.steal_pct is None else f", {self.steal_pct:.1f} % of the CPUs' time stolen by the hypervisor"
        woke = f"a {self.tick_ms:g} ms sleep woke {self.p99_ms:.1f} ms late at p99"
        head = f"the host over {self.seconds:.1f} s{steal}: {woke}"
        if not self.stalls:
            return f"{head}, {self.max_ms:.1f} ms at most; no stall over {STALL_MS:.0f} ms"
        at = ", ".join(f"{ms:.0f} ms at {t:.1f} s" for t, ms in self.stalls[:5])
        more = f" and {len(self.stalls) - 5} more" if len(self.stalls) > 5 else ""
        n = len(self.stalls)
        return f"{head}; {n} stall{'s' if n > 1 else ''} over {STALL_MS:.0f} ms ({at}{more})"


class HostWatch:
    """Watches the host from a process of its own while the ``with`` block runs; ``result`` after it."""

    def __init__(self, tick_s: float = TICK_S) -> None:
        self.tick_s = tick_s
        self._proc: subprocess.Popen[str] | None = None
        self._cpu0: list[int] | None = None
        self.result: HostStalls | None = None

    def __enter__(self) -> HostWatch:
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _WATCHER, repr(self.tick_s), repr(STALL_MS)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self._proc.stdout is not None
        self._proc.stdout.readline()  # "ready": watching from here on
        self._cpu0 = _cpu_jiffies()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        cpu0, cpu1 = self._cpu0, _cpu_jiffies()
        try:
            out, _ = proc.communicate(input="stop\n", timeout=10.0)
            d = json.loads(out.strip().splitlines()[-1])
        except (subprocess.TimeoutExpired, json.JSONDecodeError, IndexError):
            proc.kill()
            proc.wait()
            return  # no figure rather than a wrong one; the measurement itself stands
        self.result = HostStalls(
            self.tick_s * 1e3,
            float(d["seconds"]),
            float(d["p99_ms"]),
            float(d["max_ms"]),
            tuple((t, ms) for t, ms in d["stalls"]),
            steal_pct(cpu0, cpu1),
        )


def _cpu_jiffies() -> list[int] | None:
    """The machine's CPU time so far by kind (``/proc/stat``'s first line: user ... steal), or None."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    except OSError:
        return None
    return [int(x) for x in fields[1:9]] if fields and fields[0] == "cpu" and len(fields) >= 9 else None


def steal_pct(before: list[int] | None, after: list[int] | None) -> float | None:
    """Steal time between two ``_cpu_jiffies`` readings, % of all the CPUs' time (None: unknown).

    >>> steal_pct([100, 0, 10, 880, 0, 0, 0, 10], [190, 0, 20, 960, 0, 0, 0, 30])
    10.0
    """
    if before is None or after is None:
        return None
    d = [b - a for a, b in zip(before, after, strict=True)]
    total = sum(d)
    return 100.0 * d[7] / total if total > 0 else None
