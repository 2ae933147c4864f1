"""The ``/ws/poses`` fan-out: every client has its own bounded queue (Prefect style).

The worker calls ``Hub.publish_threadsafe`` from its processing thread; the
result is serialised once and handed to the event loop. A client whose queue is
full loses its *oldest* message (the newest pose matters most), the loss is
counted per client and in ``/health``, and neither the worker nor the other
clients ever wait for a slow client. A client that has not taken a message for
``stall_timeout_s`` (its socket's buffers are full: it stopped reading) is
disconnected, so a stuck dashboard cannot hold the connection and its queue
forever; that too is counted.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

from starlette.websockets import WebSocket

from service.core.measurement import Measurement


class StalledClient(Exception):
    """The client has not read for longer than the hub's stall timeout."""


@dataclass(eq=False)
class Client:
    queue: asyncio.Queue[str]
    camera: str | None = None
    min_interval_ns: int = 0  # decimation: at most one message per interval
    targets: bool = True  # False: results without the per-target list (~15 kB less per message)
    last_sent_ns: dict[str, int] = field(default_factory=dict)
    dropped: int = 0
    sent: int = 0


class Hub:
    def __init__(self, queue_size: int = 32, stall_timeout_s: float = 10.0) -> None:
        self.queue_size = queue_size
        self.stall_timeout_s = stall_timeout_s
        self.clients: set[Client] = set()
        self.dropped_total = 0
        self.stalled_disconnects = 0
        self._loop: asyncio.AbstractEventLoop | None = None

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def add(self, camera: str | None, max_rate_hz: float | None, targets: bool = True) -> Client:
        interval = int(1e9 / max_rate_hz) if max_rate_hz else 0
        client = Client(asyncio.Queue(self.queue_size), camera, interval, targets)
        self.clients.add(client)
        return client

    def remove(self, client: Client) -> None:
        self.clients.discard(client)

    def publish_threadsafe(self, result: Measurement) -> None:
        loop = self._loop
        if loop is None or loop.is_closed() or not self.clients:
            return  # nobody listens: no encoding
        text = result.json  # encoded once for every client
        lite = result.json_without_targets if any(not c.targets for c in list(self.clients)) else text
        # decimation runs on the exposure instant; an outage result has none: its publication then
        t_ns = result.t_exposure_host_ns if result.t_exposure_host_ns is not None else time.monotonic_ns()
        meta = (result.camera or None, t_ns)
        try:
            loop.call_soon_threadsafe(self._publish, (text, lite), meta)
        except RuntimeError:  # the loop closed between the check and the call (shutdown)
            pass

    def _publish(self, texts: tuple[str, str], meta: tuple[str | None, int]) -> None:
        camera, t_ns = meta
        for c in list(self.clients):
            if c.camera is not None and c.camera != camera:
                continue
            key = camera or ""
            if c.min_interval_ns and t_ns - c.last_sent_ns.get(key, -(1 << 62)) < c.min_interval_ns:
                continue
            c.last_sent_ns[key] = t_ns
            if c.queue.full():
                c.queue.get_nowait()
                c.dropped += 1
                self.dropped_total += 1
            c.queue.put_nowait(texts[0] if c.targets else texts[1])

    async def send(self, websocket: WebSocket, client: Client, text: str) -> None:
        """Send one message; raises StalledClient when the client has not read for ``stall_timeout_s``."""
        try:
            await asyncio.wait_for(websocket.send_text(text), self.stall_timeout_s)
        except TimeoutError:
            self.stalled_disconnects += 1
            raise StalledClient(
                f"WebSocket client {_peer(websocket)} read nothing for {self.stall_timeout_s:.1f} s "
                f"({client.dropped} messages dropped): disconnected"
            ) from None
        client.sent += 1

    def stats(self) -> dict[str, Any]:
        return {
            "clients": len(self.clients),
            "dropped_total": self.dropped_total,
            "stalled_disconnects": self.stalled_disconnects,
            "queue_size": self.queue_size,
            "stall_timeout_s": self.stall_timeout_s,
        }


def _peer(websocket: WebSocket) -> str:
    c = websocket.client
    return f"{c.host}:{c.port}" if c is not None else "(unknown)"
