"""What the worker currently measures with: camera model, field, hand-eye; versioned and swappable.

It also holds the corrected robot model (kind ``robot``, the ``m.json`` of ``posecell calibrate
robot`` or of the service's robot calibration session), which the measurement does not use: a
new one does not make the processors rebuild their measurers.

Sources, in order: the calibration store (the versions the service saved), the
files named in the configuration (imported into the store at the first start),
and, for the simulated cell, the simulation's own camera and field. A change
(an upload, a finished calibration) bumps ``generation`` so that each camera's
processor rebuilds its measurer before the next frame.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import check_T
from service.core.pose.intersection import Rig
from service.core.targets.field import Field
from service.settings import Settings
from service.store import formats
from service.store.calibrations import CalibrationError
from service.store.robot_model import RobotModelFile, robot_model_from_json

KINDS = ("camera", "field", "handeye", "rig", "robot")
MEASURING_KINDS = ("camera", "field", "handeye", "rig")  # a change of these rebuilds the measurers


@dataclass(frozen=True)
class HandEye:
    T_flange_camera: np.ndarray  # X, mm
    T_base_field: np.ndarray  # Z, mm


def validate(kind: str, data: Any) -> Any:
    """The engine object of a calibration payload, or ``formats.FormatError`` saying what is wrong."""
    if kind == "camera":
        return formats.camera_from_json(data, "camera.json")
    if kind == "field":
        return formats.field_from_json(data, "field.json")
    if kind == "handeye":
        if not isinstance(data, dict):
            raise formats.FormatError("handeye.json: must be an object with T_flange_camera and T_base_field")
        formats.reject_non_finite(data, "handeye.json")
        try:
            X = check_T(formats.matrix4_from_json(data.get("T_flange_camera"), "T_flange_camera"), "T_flange_camera")
            Z = check_T(formats.matrix4_from_json(data.get("T_base_field"), "T_base_field"), "T_base_field")
        except ValueError as e:
            raise formats.FormatError(f"handeye.json: {e}") from None
        return HandEye(X, Z)
    if kind == "rig":
        return formats.rig_from_json(data, "rig.json")
    if kind == "robot":
        return robot_model_from_json(data, "robot.json")
    raise formats.FormatError(f"unknown calibration kind {kind!r}; one of {KINDS}")


class CalibrationState:
    def __init__(self, settings: Settings, store: Any, cell: Any) -> None:
        self._store = store
        self._lock = threading.Lock()
        self.generation = 0
        self.camera: BrownFraser | None = None
        self.camera_centre: str | None = None  # what the camera's calibration measured centres as (if said)
        self.field: Field | None = None
        self.handeye: HandEye | None = None
        self.rig: Rig | None = None
        self.robot: RobotModelFile | None = None
        self._robot_payload: dict[str, Any] | None = None  # what was put, for a download without a store
        self.versions: dict[str, int | None] = dict.fromkeys(KINDS)
        self.sources: dict[str, str] = dict.fromkeys(KINDS, "missing")
        self._load(settings, cell)

    def _load(self, settings: Settings, cell: Any) -> None:
        files = {
            "camera": settings.calibration.camera_file,
            "field": settings.calibration.field_file,
            "handeye": settings.calibration.handeye_file,
            "rig": settings.calibration.rig_file,
            "robot": None,  # only the store: a model comes from a session or an upload
        }
        sim = cell.defaults() if cell is not None and cell.active else {}
        for kind in KINDS:
            data, version, source = None, None, "missing"
            if self._store is not None and kind in self._store.kinds_present():
                data = self._store.get(kind)
                version = self._store.versions(kind)[-1]["version"]
                source = "store"
            elif files[kind] is not None:
                data = formats.read_json(files[kind])
                source = f"file {files[kind]}"
            elif kind in sim:
                data = sim[kind]
                source = "simulated cell"
            if data is None:
                continue
            obj = validate(kind, data)
            if self._store is not None and version is None:
                version = self._store.put(kind, data, note=f"imported from {source}")
            self._set(kind, obj, version, source, data)

    def _set(self, kind: str, obj: Any, version: int | None, source: str, data: Any) -> None:
        with self._lock:
            setattr(self, kind, obj)
            if kind == "camera":
                self.camera_centre = formats.calibrated_centre(data)
            self.versions[kind] = version
            self.sources[kind] = source
            if kind in MEASURING_KINDS:
                self.generation += 1

    def update(self, kind: str, data: Any, note: str = "") -> int | None:
        """Validate, store (versioned, atomic) and use a new calibration; returns its version.

        Raises ``formats.FormatError`` for anything the checks or the store refuse (bad values, a
        note over 1000 characters); nothing is then stored or changed.
        """
        obj = validate(kind, data)
        try:
            version = self._store.put(kind, data, note=note) if self._store is not None else None
        except CalibrationError as e:  # the store's input checks (its disk errors are OSError)
            raise formats.FormatError(f"{kind}.json: {e}") from None
        if kind == "robot":
            self._robot_payload = dict(data)
        self._set(kind, obj, version, "store" if self._store is not None else "memory", data)
        return version

    def payload(self, kind: str) -> Any:
        """The current calibration file content (what a download returns)."""
        if kind not in KINDS:
            raise KeyError(kind)
        if self._store is not None and kind in self._store.kinds_present():
            return self._store.get(kind)
        obj = getattr(self, kind)
        if obj is None:
            raise KeyError(kind)
        if kind == "camera":
            return obj.to_dict()
        if kind == "rig":
            return {
                "model": "rig",
                "master": 0,
                "cameras": [c.to_dict() for c in obj.cameras],
                "T_master_camera": obj.T_master_camera.tolist(),
            }
        if kind == "field":
            return formats.field_to_json(obj)
        if kind == "robot":
            return self._robot_payload
        return {"T_flange_camera": obj.T_flange_camera.tolist(), "T_base_field": obj.T_base_field.tolist()}

    def summary(self) -> dict[str, Any]:
        return {
            kind: {
                "present": getattr(self, kind) is not None,
                "version": self.versions[kind],
                "source": self.sources[kind],
            }
            for kind in KINDS
        }
