"""The RTDE protocol of a controller stand-in, pure: bytes in, bytes out, no sockets, no clocks.

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

Here are the wire format (package framing, the controller's output and input names and types),
:class:`RobotState` (what a state source reports), :class:`Recipe` and :func:`serialize_outputs`,
and :class:`RtdeSession`, the controller side of one connection. The sockets and the 500 Hz
controller clock that serve it are :class:`drivers.standins.rtde_server.RtdeServer`'s, split as
Opentrons splits its emulators, so that the protocol can be tested without either.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

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
