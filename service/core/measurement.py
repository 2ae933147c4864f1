"""One measured frame, typed, from the processor to every boundary (DESIGN section 4).

The processor (one camera) and the rig combiner (several) build a
:class:`Measurement`; the worker hands the same frozen object to waiting
requests, to the store and to the WebSocket fan-out. Nothing downstream parses
it back: the pose, its σ, the targets, the pairing with the robot, the flange
and the deviation are arrays and numbers here, at full precision. It becomes
JSON once per message variant (with or without the per-target list), rounded
to what the measurement resolves, in :meth:`Measurement.to_dict` — the only
place that knows the wire spelling of a result.

Three kinds share the type: a frame's result (``t_exposure_host_ns`` set, a
pose or a failure), an outage notice (a camera that cannot deliver frames: no
exposure, ``camera_state`` says why) and the newest result served late
(:meth:`Measurement.as_stale`: values kept, ``ok`` false, reason ``stale``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from functools import cached_property, lru_cache
from types import MappingProxyType
from typing import Any

import numpy as np
import orjson
from numpy.typing import NDArray

from service.core.results import Failure, PoseResult, Reason, TargetTable

Array = NDArray[np.float64]


def _r(x: Any, nd: int) -> float:
    return round(float(x), nd)


def _round_T(T: Array) -> list[list[float]]:
    # one numpy call, not 16 builtin rounds: three or four poses per message (the hot path's encoding)
    rounded: list[list[float]] = np.round(np.asarray(T, dtype=np.float64), 9).tolist()
    return rounded


def iso_wall(t_unix_ns: int) -> str:
    """ISO 8601 UTC with milliseconds, e.g. ``2026-12-01T22:40:41.123Z``."""
    secs, ns = divmod(int(t_unix_ns), 1_000_000_000)
    return f"{_iso_second(secs)}.{ns // 1_000_000:03d}Z"


@lru_cache(maxsize=4)
def _iso_second(secs: int) -> str:
    # a stream's results share their second: formatted once, not per message (~30 us each at 500 Hz)
    return datetime.fromtimestamp(secs, UTC).strftime("%Y-%m-%dT%H:%M:%S")


@dataclass(frozen=True)
class Deviation:
    """Measured minus reported flange pose: distance mm, angle deg, and the position vector mm (base)."""

    position_mm: float
    angle_deg: float
    vector_mm: Array

    def to_dict(self) -> dict[str, Any]:
        return {
            "position_mm": _r(self.position_mm, 4),
            "angle_deg": _r(self.angle_deg, 5),
            "vector_mm": [_r(v, 4) for v in self.vector_mm],
        }


@dataclass(frozen=True)
class Flange:
    """The robot's part of a pose: the flange the controller reported at the exposure, the one measured
    through the hand-eye calibration, their deviation; ``reason``/``message`` say why a part is missing."""

    T_base_flange: Array | None = None  # reported by the controller, (4, 4) mm
    T_base_flange_measured: Array | None = None  # (4, 4) mm
    deviation: Deviation | None = None
    reason: Reason | None = None
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "T_base_flange": None if self.T_base_flange is None else _round_T(self.T_base_flange),
            "T_base_flange_measured": (
                None if self.T_base_flange_measured is None else _round_T(self.T_base_flange_measured)
            ),
            "deviation": None if self.deviation is None else self.deviation.to_dict(),
        }
        if self.reason is not None:
            d.update(flange_reason=str(self.reason), flange_message=self.message)
        return d


@dataclass(frozen=True)
class RigPose:
    """The rig's pose from intersected targets: the master camera's ``T_field_camera`` with its σ."""

    T_field_camera: Array  # (4, 4) mm, the master camera
    sigma_position_mm: Array  # (3,)
    sigma_rotation_deg: Array  # (3,)
    rms_mm: float  # of the intersected points against the field
    rms_px: float  # of the intersection's image residuals
    n_intersected: int
    n_coded: int
    n_uncoded: int

    ok: bool = True

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": True,
            "T_field_camera": _round_T(self.T_field_camera),
            "sigma_position_mm": [_r(v, 6) for v in self.sigma_position_mm],
            "sigma_rotation_deg": [_r(v, 8) for v in self.sigma_rotation_deg],
            "rms_mm": _r(self.rms_mm, 6),
            "rms_px": _r(self.rms_px, 5),
            "n_intersected": self.n_intersected,
            "n_coded": self.n_coded,
            "n_uncoded": self.n_uncoded,
        }


Result = PoseResult | RigPose | Failure


@dataclass(frozen=True)
class Measurement:
    """One result of the service (see the module docstring); build it once, never change it."""

    camera: str
    result: Result
    t_unix_ns: int  # wall clock of what the result is about: the exposure, or an outage's finding
    t_exposure_host_ns: int | None = None  # host monotonic clock; None: an outage notice, no frame
    seq: int | None = None  # the camera's frame number
    exposure_source: str | None = None  # how the exposure instant was found (pairing)
    mode: str | None = None  # "roi", "full" or "intersection"
    timings_ms: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    flange: Flange | None = None  # None: no pose to take a flange from
    T_field_camera_true: Array | None = None  # the simulation's truth, travelling with its frame
    cameras: tuple[str, ...] = ()  # the rig's cameras, master first
    camera_state: str | None = None  # an outage notice: the camera's state
    age_s: float | None = None  # set when served as the newest result
    stale_message: str | None = None  # set by as_stale: too old to be current

    # --- what a consumer asks --------------------------------------------------------------------

    @property
    def ok(self) -> bool:
        return self.result.ok and self.stale_message is None

    @property
    def reason(self) -> Reason | None:
        """Why there is no current pose (``stale`` wins over the frame's own reason)."""
        if self.stale_message is not None:
            return Reason.stale
        return self.result.reason if isinstance(self.result, Failure) else None

    @property
    def message(self) -> str:
        if self.stale_message is not None:
            return self.stale_message
        return self.result.message if isinstance(self.result, Failure) else ""

    @property
    def is_outage(self) -> bool:
        return self.t_exposure_host_ns is None

    @property
    def T_field_camera(self) -> Array | None:
        return None if isinstance(self.result, Failure) else self.result.T_field_camera

    @property
    def t_exposure_unix_ns(self) -> int | None:
        return None if self.is_outage else self.t_unix_ns

    @property
    def n_targets(self) -> int | None:
        r = self.result
        return None if isinstance(r, Failure) else r.n_coded + r.n_uncoded

    def served(self, age_s: float) -> Measurement:
        """This result served as the newest one, ``age_s`` after its data."""
        return replace(self, age_s=age_s)

    def as_stale(self, age_s: float, message: str) -> Measurement:
        """Served too late to be current: ``ok`` false, reason ``stale``, the values kept for diagnosis."""
        return replace(self, age_s=age_s, stale_message=message)

    # --- the wire form (DESIGN section 4), once per variant --------------------------------------

    def to_dict(self, targets: bool = True) -> dict[str, Any]:
        """The wire form as a new dict (exactly what :attr:`json` says: finite, rounded)."""
        parsed: dict[str, Any] = orjson.loads(self.json if targets else self.json_without_targets)
        return parsed

    @cached_property
    def json(self) -> str:
        """Compact JSON text of the whole result: the WebSocket message, the stored row's result."""
        return _dumps(self._wire)

    @cached_property
    def json_without_targets(self) -> str:
        return _dumps({k: v for k, v in self._wire.items() if k != "targets"})

    @cached_property
    def _wire(self) -> dict[str, Any]:
        if isinstance(self.result, PoseResult) and isinstance(self.result.targets, TargetTable):
            d = self.result.to_dict(targets=False)
            d["targets"] = orjson.Fragment(self.result.targets.to_json())  # no dict per target
        else:
            d = self.result.to_dict()
        if self.camera:
            d["camera"] = self.camera
        if self.seq is not None:
            d["seq"] = self.seq
        if not self.is_outage:
            d["t_exposure_host_ns"] = self.t_exposure_host_ns
            d["t_exposure_unix_ns"] = self.t_unix_ns  # a client can measure latency
        d["t_wall"] = iso_wall(self.t_unix_ns)
        if self.exposure_source is not None:
            d["exposure_source"] = self.exposure_source
        if self.mode is not None:
            d["mode"] = self.mode
        if self.cameras:
            d["cameras"] = list(self.cameras)
        if self.camera_state is not None:
            d["camera_state"] = self.camera_state
        if self.flange is not None:
            d.update(self.flange.to_dict())
        if self.timings_ms:
            d["timings_ms"] = {k: _r(v, 3) for k, v in self.timings_ms.items()}
        if self.T_field_camera_true is not None:
            d["truth"] = {"T_field_camera": _round_T(self.T_field_camera_true)}
        if self.age_s is not None:
            d.update(age_s=round(self.age_s, 3), stale=self.stale_message is not None)
        if self.stale_message is not None:
            if isinstance(self.result, Failure):
                d["measured_reason"] = str(self.result.reason)
            d.update(ok=False, reason=str(Reason.stale), message=self.stale_message)
        return d


def _dumps(d: dict[str, Any]) -> str:
    # orjson: one pass in C, a tenth of the standard encoder's time on a frame's targets (the hot
    # path's largest cost after the measurement). NaN and infinities (a σ of an unobservable
    # direction is infinite) have no JSON: orjson writes them as null, as DESIGN section 4 says.
    return orjson.dumps(d, default=_null, option=_OPTIONS).decode()


_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def _null(o: Any) -> Any:
    if hasattr(o, "tolist"):  # a NumPy value in a failure's details
        return o.tolist()
    return repr(o)  # anything else a failure's details carry: its text, never a lost result
