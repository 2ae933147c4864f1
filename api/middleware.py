"""The HTTP edge: what is refused from the headers alone, and the headers every response carries.

One pure ASGI middleware (not Starlette's ``BaseHTTPMiddleware``, which buffers
responses and does not see WebSockets), outside the routes, in this order:

1. ``Host`` (HTTP and WebSocket): a name that is not in ``server.allowed_hosts``
   gets 400 ``host_not_allowed``. This is the DNS-rebinding guard: a page on
   ``evil.example`` whose name is re-pointed at the cell PC still sends
   ``Host: evil.example``. IP addresses and the bound host always pass (a
   rebinding page reaches the service only under a DNS name); a request
   without ``Host`` (HTTP/1.0) passes too, since browsers always send one.
   Two ``Host`` headers get 400 too (RFC 9112). Starlette's
   ``TrustedHostMiddleware`` does the same check but answers in plain text and
   knows no IP rule; ours answers with the one error body.
2. ``Origin`` (WebSocket only, before the handshake is accepted): absent (PLC
   gateways, Python clients), same-origin (the ``Host`` the browser asked) or in
   ``server.cors_origins``; anything else, ``null`` included, gets 403
   ``origin_not_allowed``. Browsers let any page open a WebSocket anywhere, so
   without this a page on another origin could read the pose stream.
3. The bearer token, for every method but GET, HEAD and OPTIONS (the routes'
   ``Authorized`` dependency checks it again): a request without it gets 401
   at once, from its headers, and its body is never read; ``Connection: close``
   makes uvicorn close the connection instead of reading the body to reuse it.
   curl (``Expect: 100-continue``) then sends no body at all; clients that send
   it at once (httpx, browsers) read the 401 and stop when the socket closes.
4. The body size: a ``Content-Length`` above ``server.max_body_bytes`` gets 413
   at once; a chunked body is counted while the route reads it and is cut with
   413 at the limit (the route then sees a disconnect, and its own answer is
   dropped).

Every HTTP response leaving the service, refusals included, gets the security
headers below and ``Cache-Control: no-store`` when it is JSON (measurements
are live data). The Content-Security-Policy fits the dashboard (its own
scripts, styles and images, blob: frame images, a WebSocket to the host it was
loaded from); a response that brings its own policy (``/docs``) keeps it.
"""

from __future__ import annotations

import ipaddress
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.errors import body as error_body
from api.security import UNAUTHORIZED, token_matches
from service.core.results import Reason
from service.settings import ServerSettings

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SECURITY_HEADERS: list[tuple[bytes, bytes]] = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
]
_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    "connect-src 'self'{ws}; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
# a Host header as RFC 9110 allows it: reg-name or IPv4, or [IPv6], then an optional port
_HOST_RE = re.compile(r"(?P<name>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._~!$&'()*+,;=%-]+)(?::(?P<port>[0-9]{1,5}))?")


def split_host(value: str) -> tuple[str, int | None] | None:
    """``Host`` header value -> (lower-case name, port or None); None when malformed.

    >>> split_host("Cell.Example:8000"), split_host("[::1]:80"), split_host("a b")
    (('cell.example', 8000), ('[::1]', 80), None)
    """
    m = _HOST_RE.fullmatch(value.strip())
    if m is None:
        return None
    name = m["name"].lower()
    if name.startswith("["):
        try:
            ipaddress.IPv6Address(name[1:-1])
        except ValueError:
            return None
    return name, int(m["port"]) if m["port"] else None


def is_ip_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name.strip("[]"))
    except ValueError:
        return False
    return True


def _origin_netloc(origin: str) -> tuple[str, str, int] | None:
    """``Origin`` header -> (scheme, host, port with the scheme's default filled in); None if not http(s)."""
    scheme, sep, rest = origin.strip().lower().partition("://")
    if not sep or scheme not in ("http", "https") or "/" in rest:
        return None
    parsed = split_host(rest)
    if parsed is None:
        return None
    name, port = parsed
    return scheme, name, port if port is not None else (443 if scheme == "https" else 80)


@dataclass(frozen=True)
class EdgeRules:
    max_body_bytes: int
    allowed_hosts: tuple[str, ...]  # lower-case names; "*" accepts any
    cors_origins: tuple[str, ...]  # exact origins; "*" accepts any
    bound_host: str = ""

    @classmethod
    def of(cls, server: ServerSettings) -> EdgeRules:
        """From ``ServerSettings`` (names and origins compared in lower case, as browsers send them)."""
        return cls(
            max_body_bytes=server.max_body_bytes,
            allowed_hosts=tuple(h.strip().lower() for h in server.allowed_hosts),
            cors_origins=tuple(o.strip().rstrip("/").lower() for o in server.cors_origins),
            bound_host=server.host.strip().lower(),
        )

    def host_allowed(self, host: str | None) -> bool:
        if "*" in self.allowed_hosts or host is None:
            return True
        parsed = split_host(host)
        if parsed is None:
            return False
        name = parsed[0]
        return is_ip_address(name) or name in self.allowed_hosts or name == self.bound_host.lower()

    def origin_allowed(self, origin: str | None, host: str | None, scope: Scope) -> bool:
        if origin is None:
            return True
        if "*" in self.cors_origins or origin.strip().rstrip("/").lower() in self.cors_origins:
            return True
        o = _origin_netloc(origin)
        parsed = split_host(host) if host else None
        if o is None or parsed is None:
            return False
        scheme, name, port = o
        default = 443 if scope.get("scheme") in ("https", "wss") else 80
        return (name, port) == (parsed[0], parsed[1] if parsed[1] is not None else default)


class EdgeGuard:
    """See the module docstring. ``token`` returns the API token (None until the lifespan set it)."""

    def __init__(self, app: ASGIApp, rules: EdgeRules, token: Callable[[], str | None]) -> None:
        self.app, self.rules, self.token = app, rules, token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        hosts = headers.getlist("host")
        host = hosts[0] if hosts else None
        if len(hosts) > 1:  # RFC 9112 3.2: a request with two is refused (which one would a proxy use?)
            await _refuse(scope, send, 400, Reason.host_not_allowed, "the request has more than one Host header")
            return
        if not self.rules.host_allowed(host):
            await _refuse(
                scope,
                send,
                400,
                Reason.host_not_allowed,
                f"this service does not answer to the host name {host!r}; "
                "add it to server.allowed_hosts if it is the cell PC's",
            )
            return
        if scope["type"] == "websocket":
            origin = headers.get("origin")
            if not self.rules.origin_allowed(origin, host, scope):
                await _refuse(
                    scope,
                    send,
                    403,
                    Reason.origin_not_allowed,
                    f"a page from {origin!r} may not open this stream; "
                    "list its origin in server.cors_origins if it should",
                )
                return
            await self.app(scope, receive, send)
            return

        has_body = headers.get("content-length", "0") not in ("", "0") or "transfer-encoding" in headers
        if scope["method"] not in SAFE_METHODS and not token_matches(headers.get("authorization"), self.token()):
            await _refuse(
                scope,
                send,
                401,
                Reason.unauthorized,
                UNAUTHORIZED,
                close=has_body,
                extra=[(b"www-authenticate", b"Bearer")],
            )
            return
        limit = self.rules.max_body_bytes
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            await _refuse(scope, send, 413, Reason.body_too_large, _too_large(limit), close=True)
            return

        received = 0
        refused = False
        started = False

        async def counted_receive() -> Message:
            nonlocal received, refused
            message = await receive()
            if message["type"] == "http.request" and not refused:
                received += len(message.get("body", b""))
                if received > limit:
                    refused = True
                    if not started:
                        await _refuse(scope, send, 413, Reason.body_too_large, _too_large(limit), close=True)
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the route's own answer to the cut body; the 413 went out already
            if message["type"] == "http.response.start":
                started = True
                message = {**message, "headers": _with_security_headers(message.get("headers", []), host)}
            await send(message)

        try:
            await self.app(scope, counted_receive if has_body else receive, guarded_send)
        except Exception:
            if not refused:
                raise  # a route reading a cut body may fail on the disconnect: that is not an error


def _too_large(limit: int) -> str:
    return f"the request body is larger than {limit} bytes (server.max_body_bytes)"


def content_security_policy(host: str | None) -> str:
    """The dashboard's policy; the stream's WebSocket is allowed to the host the page came from."""
    parsed = split_host(host) if host else None
    ws = ""
    if parsed is not None:  # echoed only once the value is known to be a plain host[:port]
        hostport = parsed[0] + (f":{parsed[1]}" if parsed[1] is not None else "")
        ws = f" ws://{hostport} wss://{hostport}"
    return _CSP.format(ws=ws)


def _with_security_headers(raw: Any, host: str | None) -> list[tuple[bytes, bytes]]:
    headers = list(raw)
    names = {k.lower() for k, _ in headers}
    headers += [h for h in SECURITY_HEADERS if h[0] not in names]
    if b"content-security-policy" not in names:
        headers.append((b"content-security-policy", content_security_policy(host).encode("latin-1")))
    if b"cache-control" not in names and any(
        k.lower() == b"content-type" and v.startswith(b"application/json") for k, v in headers
    ):
        headers.append((b"cache-control", b"no-store"))
    return headers


async def _refuse(
    scope: Scope,
    send: Send,
    status: int,
    reason: str,
    message: str,
    close: bool = False,
    extra: list[tuple[bytes, bytes]] | None = None,
) -> None:
    """The one error body, sent before the route runs (for a WebSocket: instead of the handshake)."""
    payload = json.dumps(error_body(reason, message)).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(payload)).encode()), *(extra or [])]
    if close:
        headers.append((b"connection", b"close"))
    host = Headers(scope=scope).get("host")
    if scope["type"] == "websocket":
        if "websocket.http.response" not in scope.get("extensions", {}):
            await send({"type": "websocket.close", "code": 1008, "reason": reason})  # the server answers 403
            return
        await send({"type": "websocket.http.response.start", "status": status, "headers": headers})
        await send({"type": "websocket.http.response.body", "body": payload})
        return
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": _with_security_headers(headers, host if reason != "host_not_allowed" else None),
        }
    )
    await send({"type": "http.response.body", "body": payload})
