"""The calibration sessions on disk, so that a restart loses none of what they have recorded.

A hand-eye or robot calibration session is minutes to an hour of robot motion. Each change a
client is told of (a plan, a sample recorded or removed, a solve, a store) is written before the
answer: acknowledged means stored, as for measurements. One JSON file per kind in
``<state_dir>/sessions/`` (``handeye.json``, ``robot.json``), written through a temporary file,
fsynced and renamed, then the directory fsynced (``write_json_atomic``); a discarded session's file
is removed.

At start the service reads them back. A file it cannot read is not guessed at: it is renamed
``<kind>.json.rejected-<time>`` and an event says why, so nothing is lost and no half-read
session is offered as whole.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from service.core.results import Reason
from service.runtime.handeye_session import SessionError
from service.store.formats import FormatError, fsync_dir, read_json, write_json_atomic

SCHEMA = 1
KINDS = ("handeye", "robot")

EventSink = Callable[[str, str, str], None]  # (level, kind, message): the worker's event log


def plain(x: Any) -> Any:
    """``x`` as JSON takes it: arrays and NumPy scalars as lists and numbers, tuples as lists, and
    NaN or an infinity as null (a σ that a frozen parameter does not have)."""
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist())
    if isinstance(x, np.generic):
        return plain(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


class SessionStore:
    """The sessions' files in ``directory`` (see the module docstring); ``None``: kept in memory only."""

    def __init__(self, directory: Path | None, on_event: EventSink | None = None) -> None:
        self.directory = directory
        self._on_event = on_event

    def _path(self, kind: str) -> Path:
        if kind not in KINDS:
            raise ValueError(f"unknown session kind {kind!r}")
        assert self.directory is not None
        return self.directory / f"{kind}.json"

    def save(self, kind: str, state: dict[str, Any]) -> None:
        """Write the session's state, durably, before its change is acknowledged.

        Raises :class:`SessionError` ``storage_unavailable`` when it cannot be written (a full or
        read-only disk): the change stays in memory, and the next change writes it all again."""
        if self.directory is None:
            return
        path = self._path(kind)
        try:
            write_json_atomic(path, {"schema": SCHEMA, "kind": kind, "state": plain(state)})
        except (OSError, FormatError) as e:
            raise SessionError(
                Reason.storage_unavailable,
                f"the {kind} session's change is made but not stored ({e}); it is written again with the next "
                "change, and a restart before then loses it",
            ) from None

    def load(self, kind: str) -> dict[str, Any] | None:
        """The state last saved, or None (none saved, or a file that could not be read: set aside)."""
        if self.directory is None:
            return None
        path = self._path(kind)
        if not path.exists():
            return None
        try:
            data = read_json(path)
            if not (isinstance(data, dict) and data.get("schema") == SCHEMA and isinstance(data.get("state"), dict)):
                raise FormatError(f"{path}: not a posecell session file of schema {SCHEMA}")
            return dict(data["state"])
        except FormatError as e:
            self.set_aside(kind, str(e))
            return None

    def set_aside(self, kind: str, why: str) -> None:
        """Rename the kind's file ``.rejected-<time>`` and say why (its content is not used)."""
        path = self._path(kind)
        aside = path.with_name(f"{path.name}.rejected-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}")
        with contextlib.suppress(FileNotFoundError):
            os.replace(path, aside)
        if self._on_event is not None:
            self._on_event(
                "error", "session_rejected", f"the stored {kind} session is not restored: {why}; kept as {aside}"
            )

    def discard(self, kind: str) -> None:
        """Remove the kind's file (the session was discarded)."""
        if self.directory is None:
            return
        path = self._path(kind)
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
            fsync_dir(path.parent)
