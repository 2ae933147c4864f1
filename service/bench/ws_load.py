"""Lean WebSocket load clients for ``posecell bench service``: the bytes of RFC 6455, nothing more.

The benchmark's other clients stand for clients on other machines; here they share the
service's cores. A general client library costs tens of µs of Python per message (frame
parsing into objects, queues, a task switch), which for 49 clients at 500 Hz is most of a
core taken from the service being measured. These clients do what the server can tell
apart from a real client and no more: the opening handshake (RFC 6455 §4.1), reading every
byte the server sends (so TCP flow control is real: a client that falls behind fills its
socket and the server drops its oldest messages for it), answering pings with masked pongs
(§5.5.2, the server's keep-alive drops a client that does not) and a close handshake. Frame
payloads are skipped by length, never copied or decoded; written by hand because no
library skips a frame without building it.
"""

from __future__ import annotations

import base64
import os
import selectors
import socket
import struct
import time

_PING, _CLOSE = 0x9, 0x8
_BUF = 1 << 20


def _handshake(address: str, path: str) -> tuple[socket.socket, bytes]:
    """A connected socket past the opening handshake, and the bytes that came after the answer."""
    host, port = address.rsplit(":", 1)
    sock = socket.create_connection((host, int(port)), timeout=10.0)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            f"GET {path} HTTP/1.1\r\nHost: {address}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError(f"the server closed the connection during the handshake of {path}")
        head += chunk
    status = head.split(b"\r\n", 1)[0]
    if b" 101 " not in status:
        raise ConnectionError(f"the handshake of {path} was refused: {status.decode(errors='replace')}")
    sock.setblocking(False)
    return sock, head.split(b"\r\n\r\n", 1)[1]  # a first message may come with the answer


def _frame(opcode: int, payload: bytes) -> bytes:
    """A masked client frame (a client must mask, §5.3) of a short control payload."""
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return bytes([0x80 | opcode, 0x80 | len(payload)]) + mask + masked


class _Reader:
    """Walks one connection's byte stream frame by frame, skipping payloads by their length."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.skip = 0  # payload bytes of the current frame still to pass over
        self.head = b""  # a frame header split across reads
        self.control: tuple[int, int, bytearray] | None = None  # (opcode, length, payload so far)
        self.messages = 0
        self.closed = False

    def feed(self, data: bytes | memoryview) -> None:
        i, n = 0, len(data)
        while i < n:
            if self.skip:
                take = min(self.skip, n - i)
                if self.control is not None:
                    self.control[2].extend(data[i : i + take])
                i += take
                self.skip -= take
                if not self.skip:
                    self._frame_done()
                continue
            head = self.head + bytes(data[i : i + 14])  # a header is at most 14 bytes (unmasked: 10)
            need = 2 + {126: 2, 127: 8}.get(head[1] & 0x7F, 0) if len(head) >= 2 else 2
            if len(head) < need:
                self.head, i = head, n
                continue
            used = need - len(self.head)
            self.head = b""
            opcode, length = head[0] & 0x0F, head[1] & 0x7F
            if length == 126:
                length = struct.unpack_from(">H", head, 2)[0]
            elif length == 127:
                length = struct.unpack_from(">Q", head, 2)[0]
            i += used
            self.control = (opcode, length, bytearray()) if opcode >= 0x8 else None
            self.skip = length
            if not length:
                self._frame_done()

    def _frame_done(self) -> None:
        if self.control is None:
            self.messages += 1
            return
        opcode, _, payload = self.control
        self.control = None
        if opcode == _PING:
            self.sock.setblocking(True)
            self.sock.sendall(_frame(0xA, bytes(payload)))
            self.sock.setblocking(False)
        elif opcode == _CLOSE:
            self.closed = True


def read_streams(address: str, path: str, n_clients: int, seconds: float) -> int:
    """Open ``n_clients`` connections to ``path`` and read them for ``seconds``; the messages received."""
    sel = selectors.DefaultSelector()
    readers = []
    for _ in range(n_clients):
        sock, rest = _handshake(address, path)
        reader = _Reader(sock)
        reader.feed(rest)
        readers.append(reader)
        sel.register(sock, selectors.EVENT_READ, reader)
    buf = bytearray(_BUF)
    view = memoryview(buf)
    stop_at = time.monotonic() + seconds
    try:
        while (left := stop_at - time.monotonic()) > 0 and not all(r.closed for r in readers):
            for key, _ in sel.select(left):
                reader = key.data
                try:
                    n = reader.sock.recv_into(buf)
                except BlockingIOError:
                    continue
                if not n:
                    reader.closed = True
                    sel.unregister(reader.sock)
                    continue
                reader.feed(view[:n])
    finally:
        for r in readers:
            if not r.closed:
                try:
                    r.sock.setblocking(True)
                    r.sock.sendall(_frame(_CLOSE, struct.pack(">H", 1000)))
                except OSError:
                    pass
            r.sock.close()
        sel.close()
    return sum(r.messages for r in readers)
