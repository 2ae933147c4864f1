"""Versioned calibration files (camera, field, hand-eye, rig, robot model), written atomically.

Layout of the store's directory::

    camera.json                   the current version: what the service reads
    history/camera.v1.json        every version ever put, byte for byte
    history/camera.v2.json
    history/camera.index.json     [{"version", "t_wall", "note", "sha256", "size_bytes"}, ...]

Every file is written the crash-safe way: a temporary file in the same directory,
flush + fsync, ``os.replace`` onto the final name, fsync of the directory. A put
writes the history file first, then the index, then the current file, so a crash
at any point leaves the previous current file in place and at worst a history file
that no index entry names (its version number is then skipped, never reused).
Which version is current is found by its sha256, so the index never has to be
rewritten in step with the current file.

Only the kind enum and an integer version ever become part of a path. The payloads
are checked to be JSON objects here; their content is the business of
:mod:`service.store.formats`.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import tempfile
import threading
from collections.abc import Iterator, Mapping
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Any

from service.store.formats import fsync_dir

log = logging.getLogger(__name__)

__all__ = ["CalibrationError", "CalibrationKind", "CalibrationMissing", "CalibrationStore"]

_MAX_NOTE_CHARS = 1000
_HISTORY_NAME = re.compile(r"^(?P<kind>[a-z]+)\.v(?P<version>[1-9][0-9]*)\.json$")


class CalibrationKind(StrEnum):
    """The calibration files the service keeps."""

    camera = "camera"
    field = "field"
    handeye = "handeye"
    rig = "rig"
    robot = "robot"  # the corrected kinematic model (m.json schema 2, service.store.robot_model)


class CalibrationError(Exception):
    """A calibration file is damaged, or a request to the store is malformed."""


class CalibrationMissing(CalibrationError, KeyError):
    """No calibration of that kind (or no such version) is stored."""

    def __str__(self) -> str:  # KeyError would quote the sentence
        return str(self.args[0]) if self.args else ""


def _kind(kind: CalibrationKind | str) -> CalibrationKind:
    try:
        return CalibrationKind(kind)
    except ValueError:
        raise CalibrationError(
            f"unknown calibration kind {kind!r}: expected one of {', '.join(k.value for k in CalibrationKind)}"
        ) from None


def _version(version: Any) -> int:
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise CalibrationError(f"a calibration version is a positive integer, not {version!r}")
    return version


def _write_atomic(path: Path, payload: bytes) -> None:
    """Temp file in the same directory, fsync, rename over ``path``, fsync the directory."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fchmod(f.fileno(), 0o644)  # mkstemp's 0600 would hide calibrations from the operator
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


class CalibrationStore:
    """Versioned, atomically written calibration files in one directory (created when missing).

    Safe to use from several threads, and from several processes (an ``flock`` on
    ``<directory>/.lock`` serialises writers; readers need no lock because files are replaced
    whole).
    """

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self._history = self.directory / "history"
        try:
            self._history.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise CalibrationError(
                f"the calibration directory {self._history} cannot be created ({e.strerror}): "
                "check that it is writable by the service user"
            ) from e
        self._thread_lock = threading.Lock()
        with self._locked():
            self._remove_stray_temp_files()

    # ------------------------------------------------------------ writing

    def put(self, kind: CalibrationKind | str, data: Mapping[str, Any], note: str = "") -> int:
        """Store ``data`` as the new current ``kind`` calibration; return its version (1, 2, ...).

        Raises
        ------
        CalibrationError : unknown kind, ``data`` not a JSON object (NaN and infinities included),
            or a note that is not a string of at most 1000 characters.
        OSError : the disk failed; the previous version stays current.
        """
        k = _kind(kind)
        if not isinstance(data, Mapping):
            raise CalibrationError(f"a {k} calibration must be a JSON object, not {type(data).__name__}")
        if not isinstance(note, str) or len(note) > _MAX_NOTE_CHARS:
            raise CalibrationError(f"a note is a string of at most {_MAX_NOTE_CHARS} characters")
        try:
            payload = (json.dumps(dict(data), indent=2, allow_nan=False, ensure_ascii=False) + "\n").encode()
        except (TypeError, ValueError) as e:
            raise CalibrationError(f"the {k} calibration is not valid JSON: {e}") from None
        with self._locked():
            index = self._read_index(k)
            on_disk = [
                int(m["version"])
                for p in self._history.iterdir()
                if (m := _HISTORY_NAME.match(p.name)) and m["kind"] == k.value
            ]
            version = max([e["version"] for e in index] + on_disk, default=0) + 1
            _write_atomic(self._history_path(k, version), payload)
            index.append(
                {
                    "version": version,
                    "t_wall": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
                    "note": note,
                    "sha256": hashlib.sha256(payload).hexdigest(),
                    "size_bytes": len(payload),
                }
            )
            _write_atomic(self._index_path(k), (json.dumps(index, indent=2) + "\n").encode())
            _write_atomic(self._current_path(k), payload)
        log.info("calibration %s version %d stored%s", k.value, version, f" ({note})" if note else "")
        return version

    def rollback(self, kind: CalibrationKind | str, version: int, note: str | None = None) -> int:
        """Make stored ``version`` current again, as a new version; return the new version."""
        k, v = _kind(kind), _version(version)
        data = self.get(k, v)
        return self.put(k, data, note if note is not None else f"rollback to version {v}")

    # ------------------------------------------------------------ reading

    def get(self, kind: CalibrationKind | str, version: int | None = None) -> dict[str, Any]:
        """The current calibration of ``kind``, or the stored ``version`` of it (a fresh dict).

        Raises
        ------
        CalibrationMissing : nothing of that kind is stored, or no such version.
        CalibrationError : unknown kind, or the file is damaged (not a JSON object, or a history file
            whose sha256 differs from the index's).
        """
        k = _kind(kind)
        if version is None:
            path = self._current_path(k)
            try:
                payload = path.read_bytes()
            except FileNotFoundError:
                raise CalibrationMissing(f"no {k.value} calibration is stored yet (in {self.directory})") from None
        else:
            v = _version(version)
            entry = next((e for e in self._read_index(k) if e["version"] == v), None)
            if entry is None:
                stored = [e["version"] for e in self._read_index(k)]
                raise CalibrationMissing(
                    f"{k.value} calibration version {v} does not exist "
                    f"(stored: {', '.join(map(str, stored)) if stored else 'none'})"
                )
            path = self._history_path(k, v)
            try:
                payload = path.read_bytes()
            except FileNotFoundError:
                raise CalibrationError(f"{path} is missing although the index lists it") from None
            if hashlib.sha256(payload).hexdigest() != entry["sha256"]:
                raise CalibrationError(f"{path} was changed after it was stored (sha256 differs from the index)")
        try:
            data = json.loads(payload)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CalibrationError(
                f"{path} is not valid JSON ({e}): roll back to a stored version or put a new one"
            ) from None
        if not isinstance(data, dict):
            raise CalibrationError(f"{path} does not hold a JSON object")
        return data

    def versions(self, kind: CalibrationKind | str) -> list[dict[str, Any]]:
        """Stored versions of ``kind``, oldest first: version, t_wall, note, sha256, size_bytes, current."""
        k = _kind(kind)
        index = self._read_index(k)
        current = self.current_version(k, index)
        return [{**e, "current": e["version"] == current} for e in index]

    def current_version(self, kind: CalibrationKind | str, _index: list[dict[str, Any]] | None = None) -> int | None:
        """Version number of the current file, or None (nothing stored, or the file matches no version)."""
        k = _kind(kind)
        try:
            digest = hashlib.sha256(self._current_path(k).read_bytes()).hexdigest()
        except FileNotFoundError:
            return None
        index = self._read_index(k) if _index is None else _index
        matches = [e["version"] for e in index if e["sha256"] == digest]
        return max(matches) if matches else None

    def kinds_present(self) -> list[str]:
        """Kinds that have a current file, in the enum's order."""
        return [k.value for k in CalibrationKind if self._current_path(k).is_file()]

    # ------------------------------------------------------------ internals

    def _current_path(self, k: CalibrationKind) -> Path:
        return self.directory / f"{k.value}.json"

    def _history_path(self, k: CalibrationKind, version: int) -> Path:
        return self._history / f"{k.value}.v{int(version)}.json"

    def _index_path(self, k: CalibrationKind) -> Path:
        return self._history / f"{k.value}.index.json"

    def _read_index(self, k: CalibrationKind) -> list[dict[str, Any]]:
        path = self._index_path(k)
        try:
            index = json.loads(path.read_bytes())
        except FileNotFoundError:
            return []
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CalibrationError(f"the calibration index {path} is damaged ({e})") from None
        if not isinstance(index, list) or not all(
            isinstance(e, dict) and isinstance(e.get("version"), int) and isinstance(e.get("sha256"), str)
            for e in index
        ):
            raise CalibrationError(f"the calibration index {path} is damaged (not a list of versions)")
        return index

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        with self._thread_lock:
            fd = os.open(self.directory / ".lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
                yield
            finally:
                os.close(fd)

    def _remove_stray_temp_files(self) -> None:
        # left by a crash between writing a temp file and renaming it; no writer runs (we hold the lock)
        for d in (self.directory, self._history):
            for p in d.glob(".*.tmp"):
                with contextlib.suppress(OSError):
                    p.unlink()
                    log.warning("removed %s, left by an interrupted calibration write", p)
