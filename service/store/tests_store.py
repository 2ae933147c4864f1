"""The robot's accuracy tests and their raw samples, in the measurement database's file.

The tables (``tests``, ``test_samples``) are created by the measurement store's migrations
(:mod:`service.store.rows`, schema version 2), so one ``user_version`` describes the whole file
and the store is opened after :class:`~service.store.measurements.MeasurementStore`. Writes
are few and small (a test's row, its progress, a batch of samples about once a second), so
they are made synchronously by the caller's thread on one connection of this store's own,
under a lock: a method returns once its transaction is committed, with ``synchronous=FULL``
fsynced, so whatever the API acknowledges is on disk. The measurement writer and this
connection take SQLite's write lock in turn (WAL: readers never wait); ``busy_timeout`` makes
either wait for the other's short transaction instead of failing.

A test that was ``queued`` or ``running`` when the service stopped is marked ``interrupted`` by
:meth:`TestStore.mark_interrupted` at start: nothing runs it any more.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.store.formats import null_for_unknown
from service.store.measurements import StorageError
from service.store.rows import iso_utc

STATUSES = ("queued", "running", "done", "failed", "cancelled", "interrupted")
ACTIVE = ("queued", "running")
_COLUMNS = ("status", "progress", "progress_message", "finished", "error", "report", "details")
_JSON_COLUMNS = ("params", "report", "details")
_BUSY_TIMEOUT_MS = 5000
_SCHEMA_VERSION = 2  # the first version with the tests' tables
INTERRUPTED = "the service stopped while the test ran; its samples up to then are kept"


def _dumps(obj: Any) -> str:
    # strict JSON: NaN and infinities (an unobservable σ) become null
    return json.dumps(null_for_unknown(obj), separators=(",", ":"), allow_nan=False)


def _now() -> str:
    return iso_utc(datetime.now(UTC))


class TestStore:
    """The ``tests`` and ``test_samples`` tables of the database at ``path`` (see the module docstring)."""

    __test__ = False  # not a pytest test class, whatever its name

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=5.0)
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute("PRAGMA synchronous=FULL")
            self._conn.execute(f"PRAGMA busy_timeout={_BUSY_TIMEOUT_MS}")
            self._conn.execute("PRAGMA foreign_keys=ON")
            self._conn.row_factory = sqlite3.Row
            version = self._conn.execute("PRAGMA user_version").fetchone()[0]
        except sqlite3.Error as e:
            raise StorageError(f"cannot open the accuracy tests' tables in {self.path}: {e}") from e
        if version < _SCHEMA_VERSION:
            self._conn.close()
            raise StorageError(
                f"the database {self.path} has schema version {version}, without the accuracy tests' tables: "
                "open the measurement store on it first (it migrates the file)"
            )

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def _write(self, sql: str, params: tuple[Any, ...]) -> tuple[int, int]:
        """One committed statement: ``(lastrowid, rowcount)``."""
        with self._lock:
            try:
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    cur = self._conn.execute(sql, params)
                    self._conn.execute("COMMIT")
                except BaseException:
                    self._conn.execute("ROLLBACK")
                    raise
            except sqlite3.Error as e:
                raise StorageError(f"cannot write the accuracy tests' tables in {self.path}: {e}") from e
            return int(cur.lastrowid or 0), int(cur.rowcount)

    # ------------------------------------------------------------ writing

    def create(self, kind: str, mode: str, params: dict[str, Any]) -> int:
        """A new test, ``queued``; its id once committed."""
        return self._write(
            "INSERT INTO tests (kind, mode, params, status, progress, progress_message, created)"
            " VALUES (?, ?, ?, 'queued', 0, 'queued', ?)",
            (kind, mode, _dumps(params), _now()),
        )[0]

    def update(self, test_id: int, **values: Any) -> None:
        """Set some of ``status, progress, progress_message, finished, error, report, details``."""
        unknown = set(values) - set(_COLUMNS)
        if unknown:
            raise ValueError(f"unknown test columns {sorted(unknown)}; known: {_COLUMNS}")
        if "status" in values and values["status"] not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, not {values['status']!r}")
        if values.get("status") in STATUSES[2:] and "finished" not in values:
            values["finished"] = _now()
        cols = list(values)
        vals = [_dumps(values[c]) if c in _JSON_COLUMNS and values[c] is not None else values[c] for c in cols]
        self._write(f"UPDATE tests SET {', '.join(f'{c} = ?' for c in cols)} WHERE id = ?", (*vals, test_id))

    def add_samples(self, test_id: int, samples: list[dict[str, Any]], replace: bool = False) -> None:
        """Append raw samples (dicts with ``t_exposure_unix_ns``, ``label``, ``visit``, ``stop`` and the rest),
        committed, and the test's ``n_samples`` with them in one transaction. ``replace``: they replace
        the test's samples so far (a recording, once segmented, gets its labels)."""
        if not samples and not replace:
            return
        rows = [
            (
                test_id,
                int(s["t_exposure_unix_ns"]),
                s.get("label"),
                s.get("visit"),
                s.get("stop"),
                _dumps({k: v for k, v in s.items() if k not in ("t_exposure_unix_ns", "label", "visit", "stop")}),
            )
            for s in samples
        ]
        with self._lock:
            try:
                self._conn.execute("BEGIN IMMEDIATE")
                try:
                    if replace:
                        self._conn.execute("DELETE FROM test_samples WHERE test_id = ?", (test_id,))
                        self._conn.execute("UPDATE tests SET n_samples = 0 WHERE id = ?", (test_id,))
                    self._conn.executemany(
                        "INSERT INTO test_samples (test_id, t_exposure_unix_ns, label, visit, stop, sample)"
                        " VALUES (?, ?, ?, ?, ?, ?)",
                        rows,
                    )
                    self._conn.execute("UPDATE tests SET n_samples = n_samples + ? WHERE id = ?", (len(rows), test_id))
                    self._conn.execute("COMMIT")
                except BaseException:
                    self._conn.execute("ROLLBACK")
                    raise
            except sqlite3.Error as e:
                raise StorageError(f"cannot write the samples of test {test_id} in {self.path}: {e}") from e

    def mark_interrupted(self) -> int:
        """Tests left queued or running by a previous run of the service: ``interrupted``; how many."""
        return self._write(
            "UPDATE tests SET status = 'interrupted', finished = ?, progress_message = 'interrupted', error = ?"
            " WHERE status IN ('queued', 'running')",
            (_now(), INTERRUPTED),
        )[1]

    # ------------------------------------------------------------ reading

    def _select(self, sql: str, params: tuple[Any, ...]) -> list[sqlite3.Row]:
        with self._lock:
            try:
                return list(self._conn.execute(sql, params))
            except sqlite3.Error as e:
                raise StorageError(f"cannot read the accuracy tests' tables in {self.path}: {e}") from e

    @staticmethod
    def _test(row: sqlite3.Row, full: bool) -> dict[str, Any]:
        d = dict(row)
        for c in _JSON_COLUMNS:
            if c in d and d[c] is not None:
                d[c] = json.loads(d[c])
        if not full:
            d.pop("report", None)
            d.pop("details", None)
        return d

    def get(self, test_id: int, full: bool = True) -> dict[str, Any] | None:
        rows = self._select("SELECT * FROM tests WHERE id = ?", (test_id,))
        return self._test(rows[0], full) if rows else None

    def recent(self, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """Tests newest first, without their reports."""
        rows = self._select("SELECT * FROM tests ORDER BY id DESC LIMIT ? OFFSET ?", (int(limit), int(offset)))
        return [self._test(r, full=False) for r in rows]

    def samples(self, test_id: int) -> list[dict[str, Any]]:
        """The raw samples of a test in recording order, as added."""
        rows = self._select(
            "SELECT t_exposure_unix_ns, label, visit, stop, sample FROM test_samples WHERE test_id = ? ORDER BY id",
            (test_id,),
        )
        out = []
        for r in rows:
            d = {"t_exposure_unix_ns": r["t_exposure_unix_ns"], "label": r["label"], "visit": r["visit"]}
            d["stop"] = r["stop"]
            d.update(json.loads(r["sample"]))
            out.append(d)
        return out
