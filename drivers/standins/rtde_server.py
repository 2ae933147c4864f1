"""An RTDE controller stand-in on loopback: the real protocol, served from a state source.

Universal Robots' Real-Time Data Exchange (RTDE, TCP port 30004), enough for ``ur_rtde``'s
receive interface and UR's own Python client. Split as Opentrons splits its emulators: the
protocol of one connection is :class:`~drivers.standins.rtde_protocol.RtdeSession` (pure: bytes
in, bytes out, no sockets, no clocks); :class:`RtdeServer`, here, is a selector loop in its own
thread that accepts several clients, ticks a 500 Hz controller clock on ``time.monotonic`` and
sends each started output recipe every ``round(500 / frequency)`` ticks. The state comes
from ``state_source(t_s) -> RobotState`` with ``t_s`` the controller time in s
since :meth:`RtdeServer.start` (``origin_ns`` on ``time.monotonic_ns``), a
multiple of 2 ms; it is asked for one tick ahead, so that a package leaves at
its tick rather than after the state's computation.

What it does not model: protocol version 1 framing, ``IN_USE`` inputs,
input registers acting on anything, the real controller's network jitter and
clock drift (packages are paced by this host's clock, waking up to about
0.1 ms late), the primary/secondary/dashboard ports, and script execution.

Run one by hand (it serves :class:`~drivers.standins.demo_arm.DemoArm` unless given ``--state``)::

    python -m drivers.standins.rtde_server --host 127.0.0.2 --port 30004
    python -m drivers.standins.rtde_server --state mypackage.mymodule:state_at
"""

from __future__ import annotations

import argparse
import importlib
import logging
import selectors
import signal
import socket
import threading
import time
from typing import Any

from drivers.standins.demo_arm import DemoArm
from drivers.standins.rtde_protocol import ProtocolError, RtdeSession, StateSource
from service.core.geometry.frames import T_from_ur_pose

log = logging.getLogger(__name__)

_MAX_PENDING_BYTES = 1 << 16  # a client that stops reading loses data packages, as on the controller


class _Client:
    def __init__(self, sock: socket.socket, session: RtdeSession) -> None:
        self.sock = sock
        self.session = session
        self.outbuf = bytearray()


class RtdeServer:
    """RTDE controller stand-in: a selector loop in its own thread serving ``state_source``.

    Parameters
    ----------
    state_source : callable ``(t_s: float) -> RobotState``; called once per controller tick
        that some client needs, with ``t_s`` the controller time (s since :meth:`start`).
    host : loopback address to listen on (several stand-ins can share port 30004 on
        different 127.0.0.x addresses).
    port : TCP port; 30004 is the only one ``ur_rtde``'s receive interface uses.
    base_rate_hz : the controller loop rate, the highest output frequency.
    """

    def __init__(
        self,
        state_source: StateSource,
        host: str = "127.0.0.1",
        port: int = 30004,
        base_rate_hz: float = 500.0,
        controller_version: tuple[int, int, int, int] = (5, 11, 0, 0),
    ) -> None:
        self.state_source = state_source
        self.host = host
        self.port = port
        self.base_rate_hz = base_rate_hz
        self.controller_version = controller_version
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._clients: dict[socket.socket, _Client] = {}
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self.packages_sent = 0
        self.origin_ns: int | None = None  # time.monotonic_ns() of controller time 0 (set by start)
        self._prepared: tuple[int, Any] | None = None  # (tick, state) computed ahead of its tick

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    def start(self) -> RtdeServer:
        """Bind and start serving; the controller clock restarts at 0. Raises ``OSError`` if the bind fails."""
        if self.running:
            return self
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        # Restarting on the same address must not wait for TIME_WAIT of the connections just closed.
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self.port))
            listener.listen(8)
        except OSError:
            listener.close()
            raise
        listener.setblocking(False)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._stop.clear()
        self.origin_ns = time.monotonic_ns()
        self._thread = threading.Thread(
            target=self._run, args=(listener,), name=f"rtde-standin-{self.host}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Close the listener and every connection at once (clients see the link drop); idempotent."""
        thread = self._thread
        if thread is None:
            return
        self._stop.set()
        if self._wake_w is not None:
            try:
                self._wake_w.send(b"x")
            except OSError:
                pass
        thread.join(timeout=5.0)
        self._thread = None
        for s in (self._wake_r, self._wake_w):
            if s is not None:
                s.close()
        self._wake_r = self._wake_w = None

    def __enter__(self) -> RtdeServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- loop --

    def _run(self, listener: socket.socket) -> None:
        sel = selectors.DefaultSelector()
        sel.register(listener, selectors.EVENT_READ, "listen")
        assert self._wake_r is not None
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        period_s = 1.0 / self.base_rate_hz
        t0 = (self.origin_ns or time.monotonic_ns()) * 1e-9
        next_tick_at = t0
        try:
            while not self._stop.is_set():
                remaining = next_tick_at - time.monotonic()
                # epoll has 1 ms resolution: select for the coarse part, sleep the last millisecond.
                events = sel.select(max(0.0, remaining - 1e-3) if remaining > 1.5e-3 else 0)
                for key, mask in events:
                    self._on_event(sel, listener, key, mask)
                remaining = next_tick_at - time.monotonic()
                if 0 < remaining <= 1.5e-3:
                    time.sleep(remaining)
                now = time.monotonic()
                if now >= next_tick_at:
                    tick = int((now - t0) / period_s)  # ticks missed under load are skipped, not queued
                    self._on_tick(sel, tick, tick * period_s)
                    next_tick_at = t0 + (tick + 1) * period_s
                    self._prepare(tick + 1, (tick + 1) * period_s)
        except Exception:
            log.exception("RTDE stand-in on %s:%d stopped by an error", self.host, self.port)
        finally:
            for c in list(self._clients.values()):
                self._drop(sel, c)
            sel.close()
            listener.close()

    def _on_event(
        self, sel: selectors.BaseSelector, listener: socket.socket, key: selectors.SelectorKey, mask: int
    ) -> None:
        if key.data == "wake":
            return
        if key.data == "listen":
            try:
                sock, peer = listener.accept()
            except OSError:
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, RtdeSession(self.controller_version, self.base_rate_hz))
            self._clients[sock] = client
            sel.register(sock, selectors.EVENT_READ, client)
            log.debug("RTDE client %s connected to %s:%d", peer, self.host, self.port)
            return
        client = key.data
        if mask & selectors.EVENT_READ:
            try:
                data = client.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data == b"":
                self._drop(sel, client)
                return
            if data:
                try:
                    replies = client.session.feed(data)
                except ProtocolError as e:
                    log.warning("dropping RTDE client: %s", e)
                    self._drop(sel, client)
                    return
                for r in replies:
                    client.outbuf += r
        if client.sock in self._clients:
            self._flush(sel, client)

    def _prepare(self, tick: int, t_s: float) -> None:
        """The state of the next tick, computed now: at the tick the package goes out at once."""
        self._prepared = None
        if any(c.session.wants_output(tick) for c in self._clients.values()):
            try:
                self._prepared = (tick, self.state_source(t_s))
            except Exception:
                log.exception("state source failed at t = %.3f s", t_s)

    def _on_tick(self, sel: selectors.BaseSelector, tick: int, t_s: float) -> None:
        due = [c for c in self._clients.values() if c.session.wants_output(tick)]
        prepared, self._prepared = self._prepared, None
        if not due:
            return
        if prepared is not None and prepared[0] == tick:
            state = prepared[1]
        else:
            try:
                state = self.state_source(t_s)
            except Exception:
                log.exception("state source failed at t = %.3f s", t_s)
                return
        for c in due:
            for pkg in c.session.due_outputs(tick, state, t_s):
                if len(c.outbuf) < _MAX_PENDING_BYTES:
                    c.outbuf += pkg
                    self.packages_sent += 1
            self._flush(sel, c)

    def _flush(self, sel: selectors.BaseSelector, client: _Client) -> None:
        if client.outbuf:
            try:
                n = client.sock.send(client.outbuf)
                del client.outbuf[:n]
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._drop(sel, client)
                return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbuf else 0)
        if sel.get_key(client.sock).events != want:
            sel.modify(client.sock, want, client)

    def _drop(self, sel: selectors.BaseSelector, client: _Client) -> None:
        self._clients.pop(client.sock, None)
        try:
            sel.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()


# --- the process: python -m drivers.standins.rtde_server --------------------------------------


def _load_source(spec: str) -> StateSource:
    module_name, _, attr = spec.partition(":")
    if not attr:
        raise SystemExit(f"--state must be 'module:function', got {spec!r}")
    fn = getattr(importlib.import_module(module_name), attr)
    if not callable(fn):
        raise SystemExit(f"{spec} is not callable")
    return fn  # type: ignore[no-any-return]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="RTDE controller stand-in on loopback (port 30004 for ur_rtde)")
    p.add_argument("--host", default="127.0.0.2")
    p.add_argument("--port", type=int, default=30004)
    p.add_argument("--state", help="state source 'module:function' taking t_s and returning a RobotState")
    p.add_argument(
        "--tcp-offset",
        nargs=6,
        type=float,
        metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
        help="the demo arm's TCP offset as UR shows it: m and rotation vector rad",
    )
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.state:
        source = _load_source(args.state)
    else:
        source = DemoArm(None if args.tcp_offset is None else T_from_ur_pose(args.tcp_offset))
    server = RtdeServer(source, host=args.host, port=args.port)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with server:
        log.info("RTDE stand-in serving on %s:%d", args.host, args.port)
        done.wait()
    log.info("RTDE stand-in stopped")


if __name__ == "__main__":
    main()
