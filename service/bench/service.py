"""``posecell bench service``: the running service end to end, measured from the outside.

For each frame rate and number of WebSocket clients it starts ``posecell serve``
in a child process (real HTTP and WebSocket on loopback, storage on: every
result committed) with the ``replay`` camera (the simulated cell's path
rendered once, ahead, in another process, so the renderer does not compete with
the measurement; played back and forth, ``loop = "bounce"``, because at a wrap from
the last frame to the first the ROI tracking loses the targets and two full frames
would be 2 % of the frames: the p99) and the simulated robot. After a warm-up the clients read
``/ws/poses`` for ``seconds``: one of them (the probe) in this process, stamping
every message on arrival; the others in a process of their own, so that their
reading does not delay the probe's stamps. They are lean RFC 6455 clients
(:mod:`service.bench.ws_load`: the handshake, every byte read, pings answered,
payloads skipped by length), so that on a machine with few cores they take as
little as they can from the service they measure. Reported per row:

- *results/s*: messages the probe received per second;
- *lost*: frames exposed in the window whose result never reached the probe
  (gaps in ``seq``: frames the measurement could not keep up with, plus
  messages dropped for a slow client);
- *exposure → WebSocket* p50/p99/max: the probe's arrival (host wall clock)
  minus the message's ``t_exposure_unix_ns`` — what a client sees;
- *exposure → SQLite commit* p99: from the store's own count (``/health``);
- *CPU/frame*: the user + system CPU time of the service's process and the
  processes under it (the measurement's children, the replay's renderer) over the
  window, divided by the frames it measured (acquisition, measurement, fan-out,
  storage).

And where each message's exposure → WebSocket time went (:data:`STAGES`, p50 and p99 over the
window), from the stage times the service puts in every message (``timings_ms``) and the probe's
arrival stamp: so a slow p99 names its stage.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from service.bench.child import health, serve_child, wait_ready
from service.bench.stalls import TICK_S, HostStalls, HostWatch
from service.bench.ws_load import read_streams
from service.core.targets.detect_types import DetectSettings

RATES_HZ = (100, 250, 500, 1000)
# where a message's exposure -> WebSocket time goes, from its timings_ms and the probe's arrival
STAGES = (
    ("to hand-over", "exposure to the frame's hand-over to the measurement (delivery, the camera's thread)"),
    ("to the child and back", "the frame to the child and its outcome back, waiting behind another frame"),
    ("child", "the child's measurement (ROI windows, resection, the targets' JSON)"),
    ("finish", "the flange pose and the result"),
    ("fan-out", "publication, the event loop's write, the socket and the client"),
)
CLIENTS = ((1, False), (50, False), (50, True))  # (clients, the others than the probe take pose-only messages)
_CLOCK_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def _config(rate_hz: float, centre: str | None = None) -> str:
    processing = "" if centre is None else f'\n[processing]\ncentre = "{centre}"\n'
    return f"""
[[cameras]]
name = "cam0"
driver = "replay"
frame_rate_hz = {rate_hz}
options = {{ source = "sim", loop = "bounce" }}

[storage]
stream_every_s = 0.0  # every result committed
{processing}"""


def _cpu_s(pid: int) -> float:
    """User + system CPU time of ``pid`` and every process under it (the measurement children), s."""
    stats: dict[int, tuple[int, float]] = {}  # pid -> (parent pid, its CPU s)
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended while we looked
            continue
        stats[int(entry.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) * _CLOCK_TICK_S)
    tree, grew = {pid}, True
    while grew:
        below = {p for p, (parent, _) in stats.items() if parent in tree} - tree
        tree |= below
        grew = bool(below)
    return sum(stats[p][1] for p in tree if p in stats)


def _int_after(data: bytes, key: bytes) -> int | None:
    """The integer after ``"key":`` in a message, without parsing the whole JSON (the probe keeps up)."""
    i = data.find(key)
    if i < 0:
        return None
    i += len(key)
    while i < len(data) and data[i : i + 1] == b" ":
        i += 1
    j = i
    while j < len(data) and (data[j : j + 1].isdigit() or data[j : j + 1] == b"-"):
        j += 1
    return int(data[i:j]) if j > i else None


async def _probe(address: str, seconds: float) -> list[tuple[int, int, int, bytes]]:
    """Read ``/ws/poses`` for ``seconds``: (arrival ns, exposure ns, seq, timings JSON) of every message."""
    from websockets.asyncio.client import connect

    probe: list[tuple[int, int, int, bytes]] = []
    stop_at = time.monotonic() + seconds
    async with connect(f"ws://{address}/ws/poses?camera=cam0", max_size=None) as ws:
        await ws.recv()  # the newest result at connection: not part of the window
        while (left := stop_at - time.monotonic()) > 0:
            try:
                data = await asyncio.wait_for(ws.recv(decode=False), left)
            except TimeoutError:
                break
            t_ns = time.time_ns()
            assert isinstance(data, bytes)
            exposure, seq = _int_after(data, b'"t_exposure_unix_ns":'), _int_after(data, b'"seq":')
            if exposure is not None and seq is not None:
                probe.append((t_ns, exposure, seq, _timings(data)))
    return probe


def _timings(data: bytes) -> bytes:
    """The message's ``"timings_ms":{...}`` object, unparsed (parsed after the window: the probe keeps up)."""
    i = data.find(b'"timings_ms":{')
    j = data.find(b"}", i) if i >= 0 else -1
    return data[i + 13 : j + 1] if j > i else b"{}"


def stage_ms(arrival_ns: int, exposure_ns: int, timings: dict[str, float]) -> tuple[float, ...] | None:
    """One message's exposure -> WebSocket time split into :data:`STAGES`, ms (None: not all timings)."""
    try:
        latency, processing = timings["latency"], timings["processing"]
        measure, child = timings["measure"], timings["child"]
    except KeyError:
        return None
    total = (arrival_ns - exposure_ns) * 1e-6
    return (latency - processing, measure - child, child, processing - measure, total - latency)


LOAD_NICE = 10  # the load clients' niceness: on a machine of few cores they yield to the service and the probe


def _load_process(address: str, n_clients: int, seconds: float, pose_only: bool) -> None:
    # the 49 other clients stand for clients on other machines: here they share the service's cores,
    # and reading 49 streams they would take one from it; at a lower priority they read what the
    # cores leave (a client that falls behind loses messages for itself: the service never waits)
    os.nice(LOAD_NICE)
    query = "camera=cam0&targets=false" if pose_only else "camera=cam0"
    read_streams(address, f"/ws/poses?{query}", n_clients, seconds)


def _clients(
    address: str, n_clients: int, seconds: float, pose_only: bool = False
) -> list[tuple[int, int, int, bytes]]:
    """The probe's messages while ``n_clients - 1`` other clients read too (in a spawned process;
    ``pose_only``: they subscribe with ``targets=false``, as a PLC or an MES would)."""
    if n_clients <= 1:
        return asyncio.run(_probe(address, seconds))
    load = multiprocessing.get_context("spawn").Process(
        target=_load_process, args=(address, n_clients - 1, seconds + 1.0, pose_only), daemon=True
    )
    load.start()
    try:
        time.sleep(1.0)  # the load clients connected (a spawned interpreter starts in ~0.5 s)
        return asyncio.run(_probe(address, seconds))
    finally:
        load.join(timeout=10.0)
        if load.is_alive():
            load.kill()


def _quantile(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def measure(
    rate_hz: float,
    n_clients: int,
    seconds: float,
    warmup_s: float = 3.0,
    pose_only: bool = False,
    centre: str | None = None,
) -> dict[str, Any]:
    """One row of the table (see the module docstring); ``centre``: ``[processing] centre`` (None: the default)."""
    with tempfile.TemporaryDirectory() as state:
        config = Path(state) / "bench.toml"
        config.write_text(_config(rate_hz, centre))
        with serve_child(Path(state), config) as served:
            return _measure(served.address, served.pid, rate_hz, n_clients, seconds, warmup_s, pose_only)


def _measure(
    address: str, pid: int, rate_hz: float, n_clients: int, seconds: float, warmup_s: float, pose_only: bool = False
) -> dict[str, Any]:
    """One row measured on a running service (its address and process id)."""
    wait_ready(address, timeout_s=300.0)
    time.sleep(warmup_s)  # the ROI tracking locked on, the clock fits settled
    h0, cpu0 = health(address), _cpu_s(pid)
    with HostWatch() as watch:  # a p99 over a stretch where the host itself stopped says so
        probe = _clients(address, n_clients, seconds, pose_only)
    h1, cpu1 = health(address), _cpu_s(pid)
    if len(probe) < 2:
        raise RuntimeError(f"{rate_hz} Hz, {n_clients} clients: the probe received {len(probe)} results")
    latency_ms = [(t - e) * 1e-6 for t, e, _, _ in probe]
    seqs = [s for _, _, s, _ in probe]
    split = [stage_ms(t, e, orjson.loads(tm)) for t, e, _, tm in probe]
    stages = np.array([x for x in split if x is not None]).reshape(-1, len(STAGES))
    span_s = (probe[-1][0] - probe[0][0]) * 1e-9
    exposed = seqs[-1] - seqs[0] + 1
    frames = h1["processing"]["results"] - h0["processing"]["results"]
    commit = (h1.get("storage") or {}).get("commit_latency_ms") or {}
    return {
        "rate_hz": rate_hz,
        "clients": n_clients,
        "pose_only": pose_only,
        "results_per_s": (len(probe) - 1) / span_s if span_s > 0 else float("nan"),
        "lost_fraction": 1.0 - len(set(seqs)) / exposed,
        "ws_p50_ms": _quantile(latency_ms, 0.5),
        "ws_p99_ms": _quantile(latency_ms, 0.99),
        "ws_max_ms": max(latency_ms),
        "commit_p99_ms": commit.get("p99", float("nan")),
        "cpu_ms_per_frame": (cpu1 - cpu0) * 1e3 / frames if frames > 0 else float("nan"),
        "processing_ms_median": h1["processing"].get("processing_ms_median"),
        # frames measured in full in the window (the ROI tracking lost): none in steady tracking
        "full_frames": h1["processing"]["full"] - h0["processing"]["full"],
        # per stage (STAGES): (p50, p99) ms
        "stages_ms": [(_quantile(list(c), 0.5), _quantile(list(c), 0.99)) for c in stages.T],
        "host": watch.result,
    }


def _host_cell(host: HostStalls) -> str:
    steal = "-" if host.steal_pct is None else f"{host.steal_pct:.1f}"
    return f"{steal} · {host.p99_ms:.1f} / {host.max_ms:.0f}"


def parse_clients(spec: str) -> tuple[tuple[int, bool], ...]:
    """``"1,50,50p"``: numbers of clients; ``p``: the others than the probe take pose-only messages."""
    out = []
    for item in spec.split(","):
        item = item.strip()
        out.append((int(item.rstrip("p")), item.endswith("p")))
    return tuple(out)


def run(
    rates_hz: tuple[float, ...] = RATES_HZ,
    clients: tuple[tuple[int, bool], ...] = CLIENTS,
    seconds: float = 10.0,
    centre: str | None = None,
) -> str:
    rows = [measure(r, n, seconds, pose_only=p, centre=centre) for r in rates_hz for n, p in clients]
    measured_as = centre or DetectSettings().centre  # None: the service's default
    lines = [
        "| camera Hz | clients | results/s | lost | exposure → WS p50 / p99 / max ms "
        "| exposure → commit p99 ms | CPU ms/frame | host: steal % · sleep late p99 / max ms |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        host = r["host"]
        lines.append(
            f"| {r['rate_hz']:.0f} | {r['clients']}{' (pose only)' if r['pose_only'] else ''} "
            f"| {r['results_per_s']:.0f} | {100 * r['lost_fraction']:.1f} % "
            f"| {r['ws_p50_ms']:.1f} / {r['ws_p99_ms']:.1f} / {r['ws_max_ms']:.1f} | {r['commit_p99_ms']:.1f} "
            f"| {r['cpu_ms_per_frame']:.2f} "
            f"| {'-' if host is None else _host_cell(host)} |"
        )
    lines += [
        "",
        "Where the exposure → WebSocket time goes, p50 / p99 ms per stage:",
        "",
        "| camera Hz | clients | " + " | ".join(name for name, _ in STAGES) + " |",
        "|---:|---:|" + "---:|" * len(STAGES),
    ]
    for r in rows:
        lines.append(
            f"| {r['rate_hz']:.0f} | {r['clients']}{' (pose only)' if r['pose_only'] else ''} | "
            + " | ".join(f"{p50:.2f} / {p99:.2f}" for p50, p99 in r["stages_ms"])
            + " |"
        )
    lines.append("")
    lines += [f"- *{name}*: {what}" for name, what in STAGES]
    lines.append(
        "- *host*: the share of the CPUs' time the hypervisor took meanwhile (steal), and how late a process "
        f"that only sleeps {TICK_S * 1e3:g} ms at a time woke (`service/bench/stalls.py`): the host's own state, "
        "whatever posecell does"
    )
    stalled = [(r, r["host"]) for r in rows if r["host"] is not None and r["host"].stalls]
    for r, host in stalled:
        lines.append(f"- {r['rate_hz']:.0f} Hz, {r['clients']} clients: {host.sentence()}")
    lines.append(
        f'\n`posecell serve` in a child process, the replay camera (`source = "sim"`), ROI tracking, '
        f"{'edge centres' if measured_as == 'edge' else 'intensity centroids'} "
        f'(`centre = "{measured_as}"`), every result stored; the probe takes every message with its '
        f"targets (~15 kB); *pose only*: the other "
        f"clients subscribe with `targets=false` (~2 kB); {seconds:.0f} s per row after a warm-up; "
        f"{os.cpu_count()} cores "
        f"(`posecell bench service --seconds {seconds:.0f}{'' if centre is None else ' --centre ' + centre}`)."
    )
    return "\n".join(lines)
