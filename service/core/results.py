"""Results and failures shared by the engine, the worker, the API and the CLI.

A failed measurement is a value (DESIGN section 4): ``ok = False`` with a
machine-readable :class:`Reason` and a sentence for a person. Solvers in the
core raise :class:`SolveError` for input they cannot solve; the pipeline turns
it into a :class:`Failure`. Programmer errors (wrong shapes) stay exceptions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property, lru_cache
from typing import Any, overload

import numpy as np
import orjson


class Reason(StrEnum):
    """Why a measurement or a solve failed; the same codes in CLI, REST, WebSocket and database."""

    too_few_targets = "too_few_targets"
    degenerate_geometry = "degenerate_geometry"
    behind_camera = "behind_camera"
    no_convergence = "no_convergence"
    bad_image = "bad_image"
    bad_input = "bad_input"
    no_frame = "no_frame"
    camera_disconnected = "camera_disconnected"
    robot_disconnected = "robot_disconnected"
    not_calibrated = "not_calibrated"
    poor_motion = "poor_motion"
    initializing = "initializing"
    timeout = "timeout"
    stale = "stale"  # the newest result is older than a few frame periods: nothing current to serve
    storage_unavailable = "storage_unavailable"  # measured, but not committed: not acknowledged
    solver_unavailable = "solver_unavailable"  # the child process of the long solves died during one
    # the service's refusals of a request (api/errors.STATUS: every reason's HTTP status)
    not_found = "not_found"
    not_solved = "not_solved"  # a session applied before it was solved
    robot_moving = "robot_moving"  # a hand-eye sample needs the arm at rest
    unsupported = "unsupported"  # the camera lacks the feature or the value
    unauthorized = "unauthorized"
    host_not_allowed = "host_not_allowed"
    origin_not_allowed = "origin_not_allowed"
    body_too_large = "body_too_large"
    header_too_large = "header_too_large"
    busy = "busy"  # the connection limit is reached
    method_not_allowed = "method_not_allowed"
    http_error = "http_error"


class SolveError(Exception):
    """A solver could not produce a trustworthy answer from its input."""

    def __init__(self, reason: Reason, message: str, details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message
        self.details = details or {}

    def __reduce__(self) -> tuple[Any, ...]:  # raised in the solver process, re-raised in the service's
        return (type(self), (self.reason, self.message, self.details))


@dataclass(frozen=True)
class Failure:
    """A measurement that did not give a pose."""

    reason: Reason
    message: str
    details: dict[str, Any] | None = None

    ok: bool = False

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"ok": False, "reason": str(self.reason), "message": self.message}
        if self.details:
            d.update(self.details)
        return d

    @classmethod
    def from_error(cls, e: SolveError) -> Failure:
        return cls(reason=e.reason, message=e.message, details=e.details or None)


@dataclass(frozen=True)
class TargetObservation:
    """One identified target in one image: measured ``uv`` px and its adjustment residual px."""

    id: str
    uv: tuple[float, float]
    residual_px: tuple[float, float]
    coded: bool
    used: bool = True


@dataclass(frozen=True, eq=False)
class TargetTable(Sequence[TargetObservation]):
    """A frame's identified targets as arrays (the pipeline's form: no Python object per target).

    A sequence of :class:`TargetObservation` for whoever iterates it; the encoding, the counts and
    the rejected list read the arrays.
    """

    ids: tuple[str, ...]
    uv_px: Any  # (N, 2) float
    residual_px: Any  # (N, 2) float
    coded: Any  # (N,) bool
    used: Any  # (N,) bool

    def __len__(self) -> int:
        return len(self.ids)

    @overload
    def __getitem__(self, i: int) -> TargetObservation: ...
    @overload
    def __getitem__(self, i: slice) -> Sequence[TargetObservation]: ...
    def __getitem__(self, i: int | slice) -> TargetObservation | Sequence[TargetObservation]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        u, r = self.uv_px[i], self.residual_px[i]
        return TargetObservation(
            self.ids[i], (float(u[0]), float(u[1])), (float(r[0]), float(r[1])), bool(self.coded[i]), bool(self.used[i])
        )

    def to_json(self) -> str:
        """The JSON text of :meth:`to_list` (the same text orjson writes of it), built from two
        encodings of the coordinate arrays instead of a dict per target: the per-target objects
        were most of a frame's encoding time on the service's hot path. Encoded once, kept with
        the table (and pickled with it: a measurement process sends it encoded)."""
        return self._json

    @cached_property
    def _json(self) -> str:
        n = len(self.ids)
        if n == 0:
            return "[]"
        uv = np.asarray(self.uv_px, dtype=np.float64).reshape(n, 2)
        res = np.asarray(self.residual_px, dtype=np.float64).reshape(n, 2)
        from service.core._kernels import json_kernel, kernel_array  # numba: not for every importer of results

        if np.abs(uv).max() < json_kernel.LIMIT and np.abs(res).max() < json_kernel.LIMIT:  # finite, not huge
            uv, res = kernel_array(uv), kernel_array(res)
            used = kernel_array(self.used, np.bool_)
            return json_kernel.targets_json(orjson.dumps(self.ids), uv, res, used).decode()
        uv_text, res_text = _rows_json(uv, n), _rows_json(res, n)
        return (
            "["
            + ",".join(
                f'{{"id":{_id_json(i)},"uv":[{q}],"residual_px":[{e}]{"}" if u else _REJECTED_TAIL}'
                for i, q, e, u in zip(self.ids, uv_text, res_text, self.used.tolist(), strict=True)
            )
            + "]"
        )

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled as three byte strings and the JSON text if made: a measurement process sends a
        table every frame, and pickle's way (a string object per id, each array rebuilt through
        numpy's reducer) was a tenth of that process's time at 500 frames/s."""
        n = len(self.ids)
        numbers = np.empty((n, 4))
        numbers[:, :2], numbers[:, 2:] = np.reshape(self.uv_px, (n, 2)), np.reshape(self.residual_px, (n, 2))
        flags = np.empty((n, 2), dtype=np.bool_)
        flags[:, 0], flags[:, 1] = self.coded, self.used
        text = self.__dict__.get("_json")  # the cached encoding, made on the sending side
        return (_table_from_wire, (orjson.dumps(self.ids), numbers.tobytes(), flags.tobytes(), text))

    def to_list(self) -> list[dict[str, Any]]:
        uv = np.round(self.uv_px, 4).tolist()
        res = np.round(self.residual_px, 4).tolist()
        return [
            {"id": i, "uv": q, "residual_px": e} if u else {"id": i, "uv": q, "residual_px": e, "rejected": True}
            for i, q, e, u in zip(self.ids, uv, res, self.used.tolist(), strict=True)
        ]


def _table_from_wire(ids: bytes, numbers: bytes, flags: bytes, text: str | None) -> TargetTable:
    """A :class:`TargetTable` from :meth:`TargetTable.__reduce__`'s parts (its arrays read-only views)."""
    ids_tuple = tuple(orjson.loads(ids))
    n = len(ids_tuple)
    values = np.frombuffer(numbers).reshape(n, 4)
    flag = np.frombuffer(flags, dtype=np.bool_).reshape(n, 2)
    table = TargetTable(ids_tuple, values[:, :2], values[:, 2:], flag[:, 0], flag[:, 1])
    if text is not None:
        table.__dict__["_json"] = text
    return table


_REJECTED_TAIL = ',"rejected":true}'


def _rows_json(a: Any, n: int) -> list[str]:
    """Per row of the (n, 2) array rounded to 4 decimals, its two numbers as orjson writes them
    ("u,v"; NaN and infinities as null)."""
    text = orjson.dumps(np.round(np.asarray(a, dtype=np.float64).reshape(n, 2), 4), option=orjson.OPT_SERIALIZE_NUMPY)
    return text.decode()[2:-2].split("],[")


@lru_cache(maxsize=4096)
def _id_json(target_id: str) -> str:
    return orjson.dumps(target_id).decode()  # a field's ids repeat every frame


@dataclass(frozen=True)
class PoseResult:
    """A measured camera pose with its precision (DESIGN section 4)."""

    T_field_camera: Any  # (4, 4) float, mm
    sigma_position_mm: Any  # (3,) along the field axes
    sigma_rotation_deg: Any  # (3,) small rotations about the field axes
    rms_px: float
    sigma0_px: float
    targets: Sequence[TargetObservation]  # a tuple, or the pipeline's TargetTable
    n_iter: int = 0

    ok: bool = True
    # (6, 6) over [rotation (3) rad about the field axes, position (3) mm], as the resection gives it
    # (ResectionResult.covariance): the correlation of position and rotation the σ leave out
    covariance: Any = None

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled with its pose and precision as one byte string: numpy's reducer costs ~15 us per
        array, and a measurement process sends four of them every frame."""
        parts = [
            np.asarray(a, dtype=np.float64).reshape(k)
            for a, k in ((self.T_field_camera, 16), (self.sigma_position_mm, 3), (self.sigma_rotation_deg, 3))
        ]
        if self.covariance is not None:
            parts.append(np.asarray(self.covariance, dtype=np.float64).reshape(36))
        numbers = np.concatenate(parts).tobytes()
        return (_pose_from_wire, (numbers, float(self.rms_px), float(self.sigma0_px), self.targets, int(self.n_iter)))

    @property
    def n_coded(self) -> int:
        t = self.targets
        if isinstance(t, TargetTable):
            return int(np.count_nonzero(t.coded & t.used))
        return sum(1 for o in t if o.coded and o.used)

    @property
    def n_uncoded(self) -> int:
        t = self.targets
        if isinstance(t, TargetTable):
            return int(np.count_nonzero(~t.coded & t.used))
        return sum(1 for o in t if not o.coded and o.used)

    @property
    def rejected_ids(self) -> list[str]:
        t = self.targets
        if isinstance(t, TargetTable):
            return [t.ids[k] for k in np.flatnonzero(~t.used)]
        return [o.id for o in t if not o.used]

    def to_dict(self, targets: bool = True) -> dict[str, Any]:
        """The wire form (DESIGN section 4); ``targets=False`` leaves the target list out (the
        caller encodes it, e.g. as :meth:`TargetTable.to_json`'s text)."""
        # the per-frame hot path: builtin round on the floats, one small dict per target
        T = np.round(np.asarray(self.T_field_camera, dtype=np.float64), 9).tolist()
        return {
            "ok": True,
            "T_field_camera": T,
            "sigma_position_mm": np.round(np.asarray(self.sigma_position_mm, dtype=np.float64), 6).tolist(),
            "sigma_rotation_deg": np.round(np.asarray(self.sigma_rotation_deg, dtype=np.float64), 8).tolist(),
            "rms_px": round(float(self.rms_px), 5),
            "sigma0_px": round(float(self.sigma0_px), 5),
            "n_coded": self.n_coded,
            "n_uncoded": self.n_uncoded,
            "rejected": self.rejected_ids,
            **({} if not targets else {"targets": self._target_list()}),
        }

    def _target_list(self) -> list[dict[str, Any]]:
        return (
            self.targets.to_list()
            if isinstance(self.targets, TargetTable)
            else [
                {
                    "id": t.id,
                    "uv": [round(float(t.uv[0]), 4), round(float(t.uv[1]), 4)],
                    "residual_px": [round(float(t.residual_px[0]), 4), round(float(t.residual_px[1]), 4)],
                    **({} if t.used else {"rejected": True}),
                }
                for t in self.targets
            ]
        )


def _pose_from_wire(numbers: bytes, rms_px: float, sigma0_px: float, targets: Any, n_iter: int) -> PoseResult:
    """A :class:`PoseResult` from :meth:`PoseResult.__reduce__`'s parts (its arrays read-only views)."""
    v = np.frombuffer(numbers)
    cov = v[22:].reshape(6, 6) if v.size == 58 else None
    return PoseResult(v[:16].reshape(4, 4), v[16:19], v[19:22], rms_px, sigma0_px, targets, n_iter, True, cov)
