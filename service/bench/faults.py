"""``posecell bench faults``: how fast the running service notices a fault and recovers from it.

It starts ``posecell serve`` on the simulated cell in a child process (a free
loopback port, the real HTTP API), injects each fault through ``POST
/sim/faults`` (or, for storage, another process holding SQLite's write lock)
and measures from the outside, as a client would:

- *reported*: from the fault to ``/health`` naming it;
- *back*: from the device's return to ``/health`` ``ok`` and a fresh pose in ``/poses/latest``;
- *refused*: ``POST /measure`` while the database is locked, until its 503 ``storage_unavailable``.

Every figure is the median and the worst of ``rounds`` repetitions.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from service.bench.child import serve_child

POLL_S = 0.01


def _until(predicate: Callable[[], bool], timeout_s: float, t0: float | None = None) -> float:
    """Seconds from ``t0`` (default: now) until predicate() holds; raises TimeoutError."""
    t0 = time.monotonic() if t0 is None else t0
    while not predicate():
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"no change within {timeout_s} s")
        time.sleep(POLL_S)
    return time.monotonic() - t0


def run(rounds: int = 5) -> str:
    import httpx

    rows: dict[str, list[float]] = {}

    def add(name: str, seconds: float) -> None:
        rows.setdefault(name, []).append(seconds * 1e3)

    with tempfile.TemporaryDirectory() as state, serve_child(Path(state)) as served:
        url, token = served.url, served.token
        c = httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=10.0)

        def health() -> dict[str, Any]:
            try:
                return c.get("/health").json()
            except httpx.TransportError:  # still starting
                return {"status": "starting"}

        def fresh_pose(need_deviation: bool = False) -> bool:
            r = c.get("/poses/latest")
            m = r.json()
            return (
                r.status_code == 200
                and m.get("ok")
                and not m.get("stale")
                and (not need_deviation or m.get("deviation") is not None)
            )

        def fault(device: str, action: str) -> None:
            c.post("/sim/faults", json={"device": device, "action": action}).raise_for_status()

        _until(lambda: health()["status"] == "ok" and fresh_pose(True), timeout_s=300.0)
        db = Path(state) / "measurements.sqlite"  # the default storage.database in the state dir
        for _ in range(rounds):
            for device, action, seen in (
                ("camera", "unplug", lambda h: h["cameras"]["cam0"]["state"] != "ok"),
                ("camera", "stall", lambda h: h["cameras"]["cam0"]["state"] != "ok"),
                ("robot", "unplug", lambda h: h["robot"]["state"] != "ok"),
            ):
                time.sleep(1.0)
                t0 = time.monotonic()
                fault(device, action)
                if action == "stall":
                    add(
                        "camera stall: newest pose no longer served as current",
                        _until(lambda: not fresh_pose(), 10.0, t0),
                    )
                add(f"{device} {action}: reported in /health", _until(lambda s=seen: s(health()), 10.0, t0))
                time.sleep(2.0)  # an outage of some seconds (reconnection back-off at its longest)
                t0 = time.monotonic()
                fault(device, "plug")
                add(
                    f"{device} {action}: back to ok with a fresh pose",
                    _until(lambda d=device: health()["status"] == "ok" and fresh_pose(d == "robot"), 15.0, t0),
                )
            time.sleep(1.0)
            locker = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    "import sqlite3, sys\n"
                    f"c = sqlite3.connect({str(db)!r}, isolation_level=None)\nc.execute('BEGIN IMMEDIATE')\n"
                    "print('locked', flush=True)\nsys.stdin.readline()\n",
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
            assert locker.stdout is not None and locker.stdin is not None
            locker.stdout.readline()
            t0 = time.monotonic()
            answer: dict[str, Any] = {}

            def measure(answer: dict[str, Any] = answer, t0: float = t0) -> None:
                with httpx.Client(base_url=url, headers=c.headers, timeout=10.0) as c2:
                    r = c2.post("/measure", json={"timeout_s": 1.0})
                answer.update(r=r, s=time.monotonic() - t0)

            waiter = threading.Thread(target=measure)
            waiter.start()
            add("database locked: reported in /health", _until(lambda: health()["storage"]["state"] != "ok", 10.0, t0))
            waiter.join()
            r = answer["r"]
            if r.status_code != 503 or r.json().get("reason") != "storage_unavailable":
                raise RuntimeError(f"POST /measure with the database locked answered {r.status_code}: {r.text[:200]}")
            add("database locked: POST /measure (timeout_s 1) refused with 503", answer["s"])
            locker.stdin.write("\n")
            locker.stdin.flush()
            locker.wait(timeout=10)
            t0 = time.monotonic()
            _until(lambda: health()["storage"]["state"] == "ok", 10.0)
            r = c.post("/measure", json={"timeout_s": 5.0})
            if r.status_code == 200:
                add("database unlocked: until a POST /measure is acknowledged", time.monotonic() - t0)
        c.close()
    lines = ["| fault → what a client sees | median ms | worst ms |", "|---|---:|---:|"]
    for name, values in rows.items():
        lines.append(f"| {name} | {statistics.median(values):.0f} | {max(values):.0f} |")
    lines.append(
        f"\n{rounds} rounds; the simulated cell at 20 Hz, `posecell serve` in a child process, "
        f"a client polling every {POLL_S * 1e3:.0f} ms (`posecell bench faults --rounds {rounds}`)."
    )
    return "\n".join(lines)
