"""The ``/ws/poses`` fan-out: every client has its own bounded queue (Prefect style).

The worker calls ``Hub.publish_threadsafe`` from its processing thread; the
result is serialised once and handed to the event loop. A client whose queue is
full loses its *oldest* message (the newest pose matters most), the loss is
counted per client and in ``/health``, and neither the worker nor the other
clients ever wait for a slow client. A client that has not taken a message for
``stall_timeout_s`` (its socket's buffers are full: it stopped reading) is
disconnected, so a stuck dashboard cannot hold the connection and its queue
forever; that too is counted.

The fan-out writes each message's WebSocket frame once and hands the same bytes to
every client's socket that can take it now (``FrameWriter``): a server's frames are not
masked, so without compression they are the same bytes for every client. Through the
ASGI stack each send cost ~40 µs of the event loop per client and message (middleware,
encoding, framing), which at 500 results/s and 50 clients is more than the loop has. A
client whose socket is busy (its kernel buffer full), whose task still holds a message,
or whose connection negotiated compression gets the message through its queue and the
ASGI send as before, so the order and the oldest-first loss hold.
"""

from __future__ import annotations

import asyncio
import struct
import time
from dataclasses import dataclass, field
from typing import Any

from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket

from service.core.measurement import Measurement


class StalledClient(Exception):
    """The client has not read for longer than the hub's stall timeout."""


RAW_SEND = "posecell.raw_send"  # the scope key under which :class:`TapRawSend` leaves the server's send


class TapRawSend:
    """Outermost ASGI middleware: keeps the server's own ``send`` of a WebSocket in its scope (the
    middlewares inside wrap it), for :meth:`FrameWriter.of`."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            scope[RAW_SEND] = send
        await self.app(scope, receive, send)


def ws_frame(text: str) -> bytes:
    """One unmasked, unfragmented text frame (RFC 6455 5.2): what a server sends."""
    payload = text.encode()
    n = len(payload)
    if n < 126:
        head = struct.pack("!BB", 0x81, n)
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x81, 126, n)
    else:
        head = struct.pack("!BBQ", 0x81, 127, n)
    return head + payload


class FrameWriter:
    """Writes ready frames to one connection's socket, past the ASGI stack (see the module docstring)."""

    def __init__(self, protocol: Any) -> None:
        self._protocol = protocol
        self._transport = protocol.transport

    @classmethod
    def of(cls, websocket: WebSocket) -> FrameWriter | None:
        """The writer of an accepted connection served by uvicorn's websockets-sansio protocol without
        extensions (compression), else None: then every message takes the ASGI send."""
        protocol = getattr(websocket.scope.get(RAW_SEND), "__self__", None)
        conn = getattr(protocol, "conn", None)
        needed = ("transport", "writable", "close_sent", "handshake_complete")
        if conn is None or not all(hasattr(protocol, a) for a in needed) or getattr(conn, "extensions", [1]):
            return None
        return cls(protocol)

    def ready(self) -> bool:
        """Open, handshake done, and the socket not paused for a full buffer."""
        p = self._protocol
        return bool(
            p.handshake_complete and not p.close_sent and p.writable.is_set() and not self._transport.is_closing()
        )

    def write(self, frame: bytes) -> None:
        self._transport.write(frame)


@dataclass(eq=False)
class Client:
    queue: asyncio.Queue[str]
    camera: str | None = None
    min_interval_ns: int = 0  # decimation: at most one message per interval
    targets: bool = True  # False: results without the per-target list (~15 kB less per message)
    last_sent_ns: dict[str, int] = field(default_factory=dict)
    dropped: int = 0
    sent: int = 0
    writer: FrameWriter | None = None  # None: every message through the queue and the ASGI send
    busy: bool = True  # its task holds a message not yet written (at first: the newest result's backfill)


class Hub:
    def __init__(self, queue_size: int = 32, stall_timeout_s: float = 10.0) -> None:
        self.queue_size = queue_size
        self.stall_timeout_s = stall_timeout_s
        self.clients: set[Client] = set()
        self.dropped_total = 0
        self.stalled_disconnects = 0
        self.sent_direct = 0  # messages written straight to a socket, past the ASGI stack
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
        # encoded once for every client, here rather than in the loop; the variant without the
        # targets only if a client wants it now (one that connects meanwhile has it encoded there)
        texts: list[str | None] = [result.json, None]
        if any(not c.targets for c in list(self.clients)):
            texts[1] = result.json_without_targets
        # decimation runs on the exposure instant; an outage result has none: its publication then
        t_ns = result.t_exposure_host_ns if result.t_exposure_host_ns is not None else time.monotonic_ns()
        meta = (result.camera or None, t_ns)
        try:
            loop.call_soon_threadsafe(self._publish, result, texts, meta)
        except RuntimeError:  # the loop closed between the check and the call (shutdown)
            pass

    def _publish(self, result: Measurement, texts: list[str | None], meta: tuple[str | None, int]) -> None:
        camera, t_ns = meta
        frames: list[bytes | None] = [None, None]  # each variant framed once, for every client
        for c in list(self.clients):
            if c.camera is not None and c.camera != camera:
                continue
            key = camera or ""
            if c.min_interval_ns and t_ns - c.last_sent_ns.get(key, -(1 << 62)) < c.min_interval_ns:
                continue
            c.last_sent_ns[key] = t_ns
            variant = 0 if c.targets else 1
            text = texts[variant]
            if text is None:  # a client without targets connected after the result was encoded
                text = texts[1] = result.json_without_targets
            w = c.writer
            if w is not None and not c.busy and c.queue.empty() and w.ready():
                frame = frames[variant]
                if frame is None:
                    frame = frames[variant] = ws_frame(text)
                w.write(frame)
                c.sent += 1
                self.sent_direct += 1
                continue
            if c.queue.full():
                c.queue.get_nowait()
                c.dropped += 1
                self.dropped_total += 1
            c.queue.put_nowait(text)

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
            "sent_direct": self.sent_direct,
            "queue_size": self.queue_size,
            "stall_timeout_s": self.stall_timeout_s,
        }


def _peer(websocket: WebSocket) -> str:
    c = websocket.client
    return f"{c.host}:{c.port}" if c is not None else "(unknown)"
