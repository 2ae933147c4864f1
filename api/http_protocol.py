"""uvicorn's httptools protocol with the connection timeouts and limits it lacks.

uvicorn times out only an idle keep-alive connection, and only after a first
response: a socket that connects and sends nothing, or trickles a header a
byte at a time (slowloris), or stops in the middle of a body, is held open for
ever, and with httptools there is no limit on the size of the request headers
(``h11_max_incomplete_event_size`` applies to h11 only). A few hundred such
sockets from one client exhausted the service's file descriptors. This
subclass adds, per connection:

- a **header deadline** (``timeout_header_s``), armed when the connection opens
  and when a keep-alive request begins, and cancelled when the request's last
  header byte arrives. It is a deadline, not an idle timer, so trickling bytes
  does not extend it;
- a **body idle timeout** (``timeout_body_s``): the longest pause between two
  pieces of a request body. It does not run while uvicorn has paused reading
  because the application has not consumed what arrived (not the client's
  fault);
- a **header size limit** (``max_header_bytes``, request line + headers):
  beyond it, 431 and close;
- a **connection limit** (``limit_concurrency``): a connection that arrives
  when that many are open gets 503 and is closed at once, so that idle sockets
  beyond the limit do not hold file descriptors until their header deadline
  (uvicorn itself answers 503 only once a request has arrived).

When the timer fires the connection is closed without an answer (nginx does the
same; the client has not finished asking). After a WebSocket upgrade the
WebSocket protocol takes over, with its ping timeout.
"""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from api.errors import body as error_body
from service.core.results import Reason

log = logging.getLogger(__name__)
Phase = Literal["idle", "header", "body"]


@dataclass(frozen=True)
class ConnectionLimits:
    timeout_header_s: float = 10.0
    timeout_body_s: float = 30.0
    max_header_bytes: int = 16 * 1024
    limit_concurrency: int | None = None


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """See the module docstring; use :func:`guarded_protocol` to bind the limits."""

    limits: ClassVar[ConnectionLimits] = ConnectionLimits()
    _last_refusal_log: ClassVar[float] = -1e9

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._timer: asyncio.TimerHandle | None = None
        self._phase: Phase = "idle"
        self._header_bytes = 0
        self._header_too_large = False

    # -- timers --------------------------------------------------------------------------------------------

    def _arm(self, phase: Phase, delay_s: float) -> None:
        self._disarm()
        self._phase = phase
        self._timer = self.loop.call_later(delay_s, self._expired)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._phase = "idle"

    def _expired(self) -> None:
        self._timer = None
        if self._phase == "body" and self.flow is not None and self.flow.read_paused:
            self._arm("body", self.limits.timeout_body_s)  # the application is behind, not the client
            return
        if not self.transport.is_closing():
            log.debug(
                "closing %s: no complete request %s within %.1f s",
                self.client,
                self._phase,
                self.limits.timeout_header_s if self._phase == "header" else self.limits.timeout_body_s,
            )
            self.transport.close()

    # -- the connection ------------------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        limit = self.limits.limit_concurrency
        if limit is not None and len(self.connections) >= limit:
            now = self.loop.time()
            if now - GuardedHttpToolsProtocol._last_refusal_log > 10.0:  # a flood must not flood the journal
                GuardedHttpToolsProtocol._last_refusal_log = now
                log.warning(
                    "refusing connections (from %s first): %d are open (server.limit_concurrency)",
                    self.client,
                    len(self.connections) - 1,
                )
            self._answer(
                503,
                "Service Unavailable",
                Reason.busy,
                f"the service has {limit} connections open (server.limit_concurrency); try again",
            )
            return
        self._arm("header", self.limits.timeout_header_s)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        super().handle_websocket_upgrade()

    def send_400_response(self, msg: str) -> None:
        if self._header_too_large:
            self._answer(
                431,
                "Request Header Fields Too Large",
                Reason.header_too_large,
                f"the request line and headers exceed {self.limits.max_header_bytes} bytes (server.max_header_bytes)",
            )
            return
        super().send_400_response(msg)

    def _answer(self, status: int, phrase: str, reason: str, message: str) -> None:
        """A response written by the protocol itself (no application involved), then close."""
        payload = json.dumps(error_body(reason, message)).encode()
        head = [f"HTTP/1.1 {status} {phrase}".encode()]
        head += [name + b": " + value for name, value in self.server_state.default_headers]
        head += [
            b"content-type: application/json",
            b"content-length: " + str(len(payload)).encode(),
            b"connection: close",
            b"x-content-type-options: nosniff",
        ]
        self.transport.write(b"\r\n".join(head) + b"\r\n\r\n" + payload)
        self.transport.close()

    # -- parser callbacks ----------------------------------------------------------------------------------

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._header_bytes = 0
        if self._phase != "header":  # the first request's deadline runs from the connection's opening
            self._arm("header", self.limits.timeout_header_s)

    def _count_header(self, n: int) -> None:
        self._header_bytes += n
        if self._header_bytes > self.limits.max_header_bytes:
            self._header_too_large = True
            # raised into httptools: feed_data stops and raises HttpParserCallbackError, which uvicorn
            # answers through send_400_response (above: 431)
            raise ValueError("request header too large")

    def on_url(self, url: bytes) -> None:
        self._count_header(len(url))
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._count_header(len(name) + len(value) + 4)
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()
        if not (self.parser.should_upgrade() and self._should_upgrade()):
            self._arm("body", self.limits.timeout_body_s)  # on_message_complete ends it (at once without a body)

    def on_body(self, body: bytes) -> None:
        if self._phase == "body":
            self._arm("body", self.limits.timeout_body_s)
        super().on_body(body)

    def on_message_complete(self) -> None:
        if self._phase == "body":
            self._disarm()
        super().on_message_complete()


def guarded_protocol(limits: ConnectionLimits) -> type[GuardedHttpToolsProtocol]:
    """The protocol class to give ``uvicorn.Config(http=...)``, with these limits bound."""
    return type("GuardedHttpToolsProtocol", (GuardedHttpToolsProtocol,), {"limits": limits})
