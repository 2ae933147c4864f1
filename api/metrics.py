"""Prometheus text format (version 0.0.4) of the worker's counters and gauges.

Written out directly: a handful of families with labels, no client-library
registry whose process-global state would leak between app instances in tests.
"""

from __future__ import annotations

from typing import Any

from api.ws import Hub


def _line(name: str, value: float | int | None, **labels: str) -> str:
    if value is None:
        return ""
    lab = ",".join(f'{k}="{str(v).replace(chr(34), chr(39))}"' for k, v in labels.items())
    return f"{name}{{{lab}}} {float(value):.6g}\n" if lab else f"{name} {float(value):.6g}\n"


def prometheus_text(worker: Any, hub: Hub) -> str:
    h = worker.health()
    out: list[str] = []

    def family(name: str, kind: str, help_text: str, rows: list[str]) -> None:
        out.append(f"# HELP {name} {help_text}\n# TYPE {name} {kind}\n")
        out.extend(r for r in rows if r)

    cams = h["cameras"]
    family(
        "posecell_camera_up",
        "gauge",
        "1 when the camera delivers frames",
        [_line("posecell_camera_up", c["state"] == "ok", camera=n) for n, c in cams.items()],
    )
    for key, kind, text in (
        ("frames", "counter", "frames received"),
        ("dropped", "counter", "frames replaced before processing (consumer too slow)"),
        ("timeouts", "counter", "fetch timeouts in free run"),
        ("disconnects", "counter", "camera link losses"),
        ("seq_gaps", "counter", "frames missing from the camera's frame counter"),
        ("fps", "gauge", "frame rate"),
    ):
        name = f"posecell_camera_{key}" + ("_total" if kind == "counter" else "")
        family(name, kind, text, [_line(name, c.get(key), camera=n) for n, c in cams.items()])
    family(
        "posecell_robot_up",
        "gauge",
        "1 when the robot link is up",
        [_line("posecell_robot_up", h["robot"]["state"] == "ok")],
    )
    p = h["processing"]
    for key in ("results", "ok", "failed", "roi", "full", "stored", "triggered"):
        name = f"posecell_results_{key}_total"
        family(name, "counter", f"measurement results ({key})", [_line(name, p[key])])
    family(
        "posecell_latency_ms",
        "gauge",
        "median exposure-to-result latency over the last 200 frames",
        [_line("posecell_latency_ms", p["latency_ms_median"])],
    )
    family(
        "posecell_processing_ms",
        "gauge",
        "median processing time per frame over the last 200 frames",
        [_line("posecell_processing_ms", p["processing_ms_median"])],
    )
    measurement = p.get("measurement") or {}
    family(
        "posecell_measure_process_restarts_total",
        "counter",
        "measurement child processes replaced after dying or hanging",
        [
            _line("posecell_measure_process_restarts_total", m.get("restarts", 0), camera=n)
            for n, m in measurement.items()
            if m.get("in") == "process"
        ],
    )
    ws = hub.stats()
    family("posecell_ws_clients", "gauge", "connected WebSocket clients", [_line("posecell_ws_clients", ws["clients"])])
    family(
        "posecell_ws_dropped_total",
        "counter",
        "WebSocket messages dropped for slow clients",
        [_line("posecell_ws_dropped_total", ws["dropped_total"])],
    )
    family(
        "posecell_ws_sent_direct_total",
        "counter",
        "WebSocket messages written straight to the socket (the others went through the client's queue)",
        [_line("posecell_ws_sent_direct_total", ws.get("sent_direct", 0))],
    )
    st = h.get("storage") or {}
    for key in ("queued", "written", "dropped"):
        if key in st:
            name = f"posecell_storage_{key}" + ("" if key == "queued" else "_total")
            family(name, "gauge" if key == "queued" else "counter", f"measurement rows {key}", [_line(name, st[key])])
    return "".join(out)
