"""An RTDE controller stand-in on loopback: the real protocol, served from a state source.

Universal Robots' Real-Time Data Exchange (RTDE, TCP port 30004) as the public
RTDE guide describes it, enough for ``ur_rtde``'s receive interface and UR's
own Python client: every package is ``uint16 size`` (header included) +
``uint8 type`` + payload, big-endian, with the types

=====  ============================  =========================================
``V``  request protocol version      uint16 version -> uint8 accepted (only 2)
``v``  get controller version        -> uint32 major, minor, bugfix, build
``O``  setup outputs                 double Hz + "a,b,c," -> uint8 id + "T1,T2,.."
``I``  setup inputs                  "a,b," -> uint8 id + "T1,T2,.."
``S``  start / ``P`` pause           -> uint8 accepted
``U``  data package                  uint8 recipe id + the fields, both ways
``M``  text message                  uint8 len + text, uint8 len + source, uint8 level
=====  ============================  =========================================

An unknown variable name is answered with ``NOT_FOUND`` in its place, as the
controller does, and that recipe gets id 0 and is not used. The stand-in
never sends ``M`` during a handshake (``ur_rtde`` reads the next package as the
answer to its request); it sends one only for a package type it does not know
or a data package it cannot read.

Split as Opentrons splits its emulators: :class:`RtdeSession` is the pure
protocol of one connection (bytes in, bytes out, no sockets, no clocks);
:class:`RtdeServer` is a selector loop in its own thread that accepts several
clients, ticks a 500 Hz controller clock on ``time.monotonic`` and sends each
started output recipe every ``round(500 / frequency)`` ticks. The state comes
from ``state_source(t_s) -> RobotState`` with ``t_s`` the controller time in s
since :meth:`RtdeServer.start` (``origin_ns`` on ``time.monotonic_ns``), a
multiple of 2 ms; it is asked for one tick ahead, so that a package leaves at
its tick rather than after the state's computation.

What it does not model: protocol version 1 framing, ``IN_USE`` inputs,
input registers acting on anything, the real controller's network jitter and
clock drift (packages are paced by this host's clock, waking up to about
0.1 ms late), the primary/secondary/dashboard ports, and script execution.

Run one by hand::

    python -m drivers.standins.rtde_server --host 127.0.0.2 --port 30004
    python -m drivers.standins.rtde_server --state mypackage.mymodule:state_at
"""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import selectors
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from service.core.geometry.frames import T_from_ur_pose, inv_T, ur_pose_from_T

log = logging.getLogger(__name__)

# --- wire format --------------------------------------------------------------------------------

HEADER = struct.Struct(">HB")
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

EXCEPTION_MESSAGE, ERROR_MESSAGE, WARNING_MESSAGE, INFO_MESSAGE = 0, 1, 2, 3
PROTOCOL_VERSION = 2
NOT_FOUND = "NOT_FOUND"

TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_VECTOR_LEN = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _registers(prefix: str, rtde_type: str, n: int) -> dict[str, str]:
    return {f"{prefix}{i}": rtde_type for i in range(n)}


# The controller's output names and types (RTDE guide, e-Series 5.x).
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    **{
        n: "VECTOR6D"
        for n in (
            "target_q",
            "target_qd",
            "target_qdd",
            "target_current",
            "target_moment",
            "actual_q",
            "actual_qd",
            "actual_current",
            "actual_current_window",
            "joint_control_output",
            "actual_TCP_pose",
            "actual_TCP_speed",
            "actual_TCP_force",
            "target_TCP_pose",
            "target_TCP_speed",
            "joint_temperatures",
            "actual_joint_voltage",
            "ft_raw_wrench",
            "payload_inertia",
            "target_current_window",
            "actual_qdd",
        )
    },
    **{n: "VECTOR3D" for n in ("actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog")},
    **{
        n: "DOUBLE"
        for n in (
            "actual_execution_time",
            "speed_scaling",
            "target_speed_fraction",
            "actual_momentum",
            "actual_main_voltage",
            "actual_robot_voltage",
            "actual_robot_current",
            "standard_analog_input0",
            "standard_analog_input1",
            "standard_analog_output0",
            "standard_analog_output1",
            "io_current",
            "tool_analog_input0",
            "tool_analog_input1",
            "tool_output_current",
            "tool_temperature",
            "tcp_force_scalar",
            "payload",
            "joint_position_deviation_ratio",
            "collision_detection_ratio",
            "speed_scaling_combined",
        )
    },
    **{n: "INT32" for n in ("robot_mode", "safety_mode", "safety_status", "tool_output_voltage")},
    **{
        n: "UINT32"
        for n in (
            "robot_status_bits",
            "safety_status_bits",
            "runtime_state",
            "analog_io_types",
            "tool_mode",
            "tool_analog_input_types",
            "output_bit_registers0_to_31",
            "output_bit_registers32_to_63",
            "input_bit_registers0_to_31",
            "input_bit_registers32_to_63",
            "script_control_line",
        )
    },
    **{n: "UINT64" for n in ("actual_digital_input_bits", "actual_digital_output_bits")},
    **{n: "UINT8" for n in ("tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode")},
    "joint_mode": "VECTOR6INT32",
    **_registers("output_int_register_", "INT32", 48),
    **_registers("output_double_register_", "DOUBLE", 48),
    **_registers("input_int_register_", "INT32", 48),
    **_registers("input_double_register_", "DOUBLE", 48),
    **{f"output_bit_register_{i}": "BOOL" for i in range(64, 128)},
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
}

INPUT_TYPES: dict[str, str] = {
    **{
        n: "UINT8"
        for n in (
            "standard_digital_output_mask",
            "standard_digital_output",
            "configurable_digital_output_mask",
            "configurable_digital_output",
            "tool_digital_output_mask",
            "tool_digital_output",
            "standard_analog_output_mask",
            "standard_analog_output_type",
        )
    },
    **{n: "DOUBLE" for n in ("standard_analog_output_0", "standard_analog_output_1", "speed_slider_fraction")},
    "speed_slider_mask": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
    **_registers("input_int_register_", "INT32", 48),
    **_registers("input_double_register_", "DOUBLE", 48),
    **{f"input_bit_register_{i}": "BOOL" for i in range(64, 128)},
}


class ProtocolError(Exception):
    """The byte stream cannot be RTDE (a size below the header); the connection is dropped."""


def pack_package(kind: int, payload: bytes = b"") -> bytes:
    """One RTDE package: ``>HB`` header (size includes the 3 header bytes) + payload."""
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def split_packages(buffer: bytearray) -> list[tuple[int, bytes]]:
    """Remove every complete package from ``buffer`` and return ``(type, payload)`` pairs."""
    out: list[tuple[int, bytes]] = []
    while len(buffer) >= HEADER.size:
        size, kind = HEADER.unpack_from(buffer)
        if size < HEADER.size:
            raise ProtocolError(f"package size {size} is smaller than the header")
        if len(buffer) < size:
            break
        out.append((kind, bytes(buffer[HEADER.size : size])))
        del buffer[:size]
    return out


def text_message(message: str, source: str = "posecell-rtde-standin", level: int = ERROR_MESSAGE) -> bytes:
    """An ``M`` package in protocol 2 layout (lengths are uint8, so texts are cut at 255 bytes)."""
    m, s = message.encode()[:255], source.encode()[:255]
    return pack_package(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


# --- robot state --------------------------------------------------------------------------------

_ZERO6 = (0.0,) * 6


@dataclass(frozen=True)
class RobotState:
    """What the controller reports at one instant, in the controller's units.

    actual_TCP_pose, target_TCP_pose : (6,) m and rotation vector rad, the TCP in base
    actual_q, target_q : (6,) rad; actual_qd, target_qd : (6,) rad/s
    actual_TCP_speed : (6,) m/s and rad/s
    timestamp : s since the controller started; None lets the server fill in its tick time
    extra : any other RTDE output by name (e.g. ``{"output_int_register_0": 3}``)
    Outputs neither here nor in ``extra`` are sent as zeros of their type.
    """

    actual_TCP_pose: Sequence[float] = _ZERO6
    actual_q: Sequence[float] = _ZERO6
    actual_qd: Sequence[float] = _ZERO6
    target_q: Sequence[float] = _ZERO6
    target_qd: Sequence[float] = _ZERO6
    actual_TCP_speed: Sequence[float] = _ZERO6
    target_TCP_pose: Sequence[float] = _ZERO6
    timestamp: float | None = None
    robot_mode: int = 7  # ROBOT_MODE_RUNNING
    safety_mode: int = 1  # SAFETY_MODE_NORMAL
    runtime_state: int = 2  # PLAYING
    robot_status_bits: int = 0b0011  # power on, program running
    safety_status_bits: int = 0b1  # normal mode
    joint_mode: Sequence[int] = (253,) * 6  # JOINT_RUNNING_MODE
    speed_scaling: float = 1.0
    target_speed_fraction: float = 1.0
    extra: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))


StateSource = Callable[[float], RobotState]


@dataclass
class Recipe:
    """One configured output or input recipe of a connection."""

    recipe_id: int
    names: list[str]
    types: list[str]
    frequency_hz: float = 0.0
    decimation: int = 1  # send every n-th controller tick
    next_tick: int = 0

    def __post_init__(self) -> None:
        self.struct = struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types))


def _zero(rtde_type: str) -> Any:
    n = _VECTOR_LEN.get(rtde_type)
    if n:
        return (0.0 if rtde_type.endswith("D") else 0,) * n
    return 0.0 if rtde_type == "DOUBLE" else (False if rtde_type == "BOOL" else 0)


def serialize_outputs(recipe: Recipe, state: RobotState | Mapping[str, Any], t_s: float) -> bytes:
    """The ``U`` package of ``recipe`` for ``state`` (a :class:`RobotState` or a name -> value mapping)."""
    values: list[Any] = [recipe.recipe_id]
    is_map = isinstance(state, Mapping)
    extra: Mapping[str, Any] = {} if is_map else state.extra  # type: ignore[union-attr]
    for name, rtde_type in zip(recipe.names, recipe.types, strict=True):
        if is_map:
            v = state.get(name)  # type: ignore[union-attr]
        else:
            v = getattr(state, name, None)
            if v is None:
                v = extra.get(name)
        if v is None:
            v = t_s if name == "timestamp" else _zero(rtde_type)
        if rtde_type in _VECTOR_LEN:
            values.extend(v)
        else:
            values.append(v)
    return pack_package(DATA_PACKAGE, recipe.struct.pack(*values))


# --- one connection, pure -----------------------------------------------------------------------


class RtdeSession:
    """The controller side of one RTDE connection: feed it bytes, send what it returns.

    ``controller_version`` is what ``v`` answers (``ur_rtde`` picks 500 Hz for
    major > 3); ``base_rate_hz`` is the controller's real-time loop (500 Hz on
    e-Series), the highest output frequency.
    """

    def __init__(
        self, controller_version: tuple[int, int, int, int] = (5, 11, 0, 0), base_rate_hz: float = 500.0
    ) -> None:
        self.controller_version = controller_version
        self.base_rate_hz = base_rate_hz
        self.protocol_version = 1
        self.started = False
        self.outputs: dict[int, Recipe] = {}
        self.inputs: dict[int, Recipe] = {}
        self.received_inputs: dict[str, Any] = {}
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Consume bytes from the client; return the packages to send back. Raises ``ProtocolError``."""
        self._buffer += data
        replies: list[bytes] = []
        for kind, payload in split_packages(self._buffer):
            replies.extend(self.handle(kind, payload))
        return replies

    def handle(self, kind: int, payload: bytes) -> list[bytes]:
        """Answer one package."""
        if kind == REQUEST_PROTOCOL_VERSION:
            ok = len(payload) == 2 and struct.unpack(">H", payload)[0] == PROTOCOL_VERSION
            if ok:
                self.protocol_version = PROTOCOL_VERSION
            return [pack_package(kind, bytes([ok]))]
        if kind == GET_URCONTROL_VERSION:
            return [pack_package(kind, struct.pack(">IIII", *self.controller_version))]
        if kind == SETUP_OUTPUTS:
            return [self._setup_outputs(payload)]
        if kind == SETUP_INPUTS:
            return [self._setup_inputs(payload)]
        if kind == START:
            self.started = bool(self.outputs or self.inputs)
            for r in self.outputs.values():
                r.next_tick = 0
            return [pack_package(kind, bytes([self.started]))]
        if kind == PAUSE:
            self.started = False
            return [pack_package(kind, b"\x01")]
        if kind == DATA_PACKAGE:
            return self._input_data(payload)
        if kind == TEXT_MESSAGE:
            log.info("RTDE client says: %r", payload[1 : 1 + payload[0]] if payload else b"")
            return []
        name = chr(kind) if 32 <= kind < 127 else "?"
        return [text_message(f"unknown package type {name!r} (0x{kind:02x}) ignored")]

    @staticmethod
    def _names(raw: bytes) -> list[str]:
        return [n for n in raw.decode("ascii", errors="replace").strip().split(",") if n]

    def _setup_outputs(self, payload: bytes) -> bytes:
        if len(payload) < 8:
            return pack_package(SETUP_OUTPUTS, b"\x00")
        (frequency_hz,) = struct.unpack_from(">d", payload)
        names = self._names(payload[8:])
        types = [OUTPUT_TYPES.get(n, NOT_FOUND) for n in names]
        reply_types = ",".join(types).encode()
        valid = (
            names
            and NOT_FOUND not in types
            and not self.started
            and len(self.outputs) < 255
            and math.isfinite(frequency_hz)
            and 0.0 < frequency_hz <= self.base_rate_hz
        )
        if not valid:
            log.warning("output recipe refused (frequency %r Hz, types %s)", frequency_hz, types)
            return pack_package(SETUP_OUTPUTS, b"\x00" + reply_types)
        recipe_id = len(self.outputs) + 1
        decimation = max(1, round(self.base_rate_hz / frequency_hz))
        self.outputs[recipe_id] = Recipe(recipe_id, names, types, frequency_hz, decimation)
        return pack_package(SETUP_OUTPUTS, bytes([recipe_id]) + reply_types)

    def _setup_inputs(self, payload: bytes) -> bytes:
        names = self._names(payload)
        types = [INPUT_TYPES.get(n, NOT_FOUND) for n in names]
        reply_types = ",".join(types).encode()
        if not names or NOT_FOUND in types or self.started or len(self.inputs) >= 255:
            return pack_package(SETUP_INPUTS, b"\x00" + reply_types)
        recipe_id = len(self.inputs) + 1
        self.inputs[recipe_id] = Recipe(recipe_id, names, types)
        return pack_package(SETUP_INPUTS, bytes([recipe_id]) + reply_types)

    def _input_data(self, payload: bytes) -> list[bytes]:
        recipe = self.inputs.get(payload[0]) if payload else None
        if recipe is None or len(payload) != recipe.struct.size:
            return [text_message(f"data package for unknown input recipe or of wrong size ({len(payload)} B)")]
        values = iter(recipe.struct.unpack(payload)[1:])
        for name, rtde_type in zip(recipe.names, recipe.types, strict=True):
            n = _VECTOR_LEN.get(rtde_type)
            self.received_inputs[name] = tuple(next(values) for _ in range(n)) if n else next(values)
        return []

    def due_outputs(self, tick: int, state: RobotState | Mapping[str, Any], t_s: float) -> list[bytes]:
        """Data packages of the started output recipes due at controller tick ``tick``."""
        if not self.started:
            return []
        out = []
        for r in self.outputs.values():
            if tick >= r.next_tick:
                out.append(serialize_outputs(r, state, t_s))
                r.next_tick = (tick // r.decimation + 1) * r.decimation
        return out

    def wants_output(self, tick: int) -> bool:
        return self.started and any(tick >= r.next_tick for r in self.outputs.values())


# --- the server ---------------------------------------------------------------------------------

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


# --- a built-in state source: a UR5e-like arm moving smoothly -----------------------------------

# UR5e nominal standard DH: a, d in mm, alpha in rad (Universal Robots' published values).
UR5E_DH_A_MM = np.array([0.0, -425.0, -392.2, 0.0, 0.0, 0.0])
UR5E_DH_D_MM = np.array([162.5, 0.0, 0.0, 133.3, 99.7, 99.6])
UR5E_DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])


def T_base_flange_from_q(q_rad: Sequence[float]) -> np.ndarray:
    """Forward kinematics of the nominal UR5e (standard DH), flange in base, (4, 4) mm."""
    T = np.eye(4)
    for theta, a, d, alpha in zip(q_rad, UR5E_DH_A_MM, UR5E_DH_D_MM, UR5E_DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )
    return T


class DemoArm:
    """A smooth joint motion around a UR5e working pose, reported as the controller would.

    ``T_flange_tcp`` (4, 4) mm is the TCP offset "configured on the controller":
    ``actual_TCP_pose`` is the flange pose times it, so a driver must remove it
    to get the flange back.
    """

    Q_HOME_RAD = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    AMPLITUDE_RAD = np.array([0.5, 0.25, 0.3, 0.4, 0.4, 0.8])
    FREQUENCY_HZ = np.array([0.11, 0.07, 0.13, 0.17, 0.19, 0.23])

    def __init__(self, T_flange_tcp: np.ndarray | None = None) -> None:
        self.T_flange_tcp = np.eye(4) if T_flange_tcp is None else np.asarray(T_flange_tcp, dtype=np.float64)

    def q_rad(self, t_s: float) -> np.ndarray:
        return self.Q_HOME_RAD + self.AMPLITUDE_RAD * np.sin(2 * np.pi * self.FREQUENCY_HZ * t_s)

    def qd_rad_s(self, t_s: float) -> np.ndarray:
        w = 2 * np.pi * self.FREQUENCY_HZ
        return self.AMPLITUDE_RAD * w * np.cos(w * t_s)

    def T_base_flange(self, t_s: float) -> np.ndarray:
        return T_base_flange_from_q(self.q_rad(t_s))

    def T_base_tcp(self, t_s: float) -> np.ndarray:
        return self.T_base_flange(t_s) @ self.T_flange_tcp

    def __call__(self, t_s: float) -> RobotState:
        q = self.q_rad(t_s)
        T_base_tcp = T_base_flange_from_q(q) @ self.T_flange_tcp
        pose = ur_pose_from_T(T_base_tcp)
        h = 1e-4  # central difference for the TCP twist; exact enough for a stand-in
        T0, T1 = self.T_base_tcp(t_s - h), self.T_base_tcp(t_s + h)
        v_m_s = (T1[:3, 3] - T0[:3, 3]) / (2 * h) / 1000.0
        w_rad_s = ur_pose_from_T(T1 @ inv_T(T0))[3:] / (2 * h)  # rotation in the base frame
        qd = self.qd_rad_s(t_s)
        return RobotState(
            actual_TCP_pose=tuple(pose),
            target_TCP_pose=tuple(pose),
            actual_q=tuple(q),
            target_q=tuple(q),
            actual_qd=tuple(qd),
            target_qd=tuple(qd),
            actual_TCP_speed=(*v_m_s, *w_rad_s),
            timestamp=t_s,
        )


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
