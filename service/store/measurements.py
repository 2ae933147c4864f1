"""Measurement and event history in SQLite, written by one thread in batches.

Durability. WAL mode with ``synchronous=FULL`` by default: every committed batch is
fsynced into the WAL before :meth:`MeasurementStore.wait_written` returns, so an
*acknowledged* row (``wait_written`` returned True) survives ``kill -9`` **and** a
power cut. ``synchronous="NORMAL"`` also survives a process kill (committed pages
sit in the kernel's page cache) but may lose the last transactions on power loss.
FULL costs one fsync per *batch*, not per row: rows arriving during a commit go
into the next batch (group commit), so the cost per row falls as the rate rises.
A kill at any instant leaves a consistent database (WAL rollback rules).

Queue. :meth:`~MeasurementStore.add_measurement` never blocks: it queues the (frozen)
measurement and returns its sequence number, which is also its row ``id``; the writer
thread turns it into its row, off the processing thread's path. With ``max_queue`` rows
waiting (a failing or far too slow disk) it raises :class:`StoreFull` rather than drop anything silently: the caller
knows that row is not stored (POST /measure answers 503), and ``stats()["dropped"]``
counts it. Events are diagnostic: :meth:`~MeasurementStore.add_event` counts and
logs a full queue instead of raising.

A batch is committed when ``batch_max`` rows wait, when its oldest row has waited
``flush_interval_s``, or at once when a caller waits in ``wait_written``: a triggered
measurement is acknowledged after one fsync, not after the flush interval.

Reads open their own short-lived connection; WAL lets them run beside the writer.
Listings are **newest first** unless ``oldest_first=True``. One store per file: a
second writer is refused at open (an ``flock`` on ``<db>.lock``).
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import logging
import math
import os
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Mapping
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, Literal

from service.core.measurement import Measurement
from service.store.rows import (
    CSV_COLUMNS,
    EVENT_LEVELS,
    INSERT_EVENT,
    INSERT_MEASUREMENT,
    MIGRATIONS,
    ROW_COLUMNS,
    SCHEMA_VERSION,
    check_page,
    event_row,
    insert_rows_sql,
    iso_utc,
    measurement_row,
    where_clause,
)

log = logging.getLogger(__name__)

_ROWS_PER_INSERT = 256  # x 15 columns: far below SQLite's limit of bound variables (32 766 since 3.32)

__all__ = ["MeasurementStore", "StorageError", "StoreFull"]

_RETENTION_CHUNK = 10_000
_RETENTION_MAX_CHUNKS = 20  # per run, so queued rows never wait long behind a purge
_RETRY_MAX_S = 1.0
# a lock held by another process (a backup, a sqlite3 shell) fails a commit after this long; the batch
# is then retried, and /health reports the outage from the first failure on
_BUSY_TIMEOUT_S = 0.5
_JOURNAL_SIZE_LIMIT_BYTES = 64 * 1024 * 1024

# (seq, or 0 for an event; "m" | "e"; column values), or (seq, "q", (measurement, triggered)) while queued
Item = tuple[int, str, tuple[Any, ...]]


class StorageError(Exception):
    """The measurement database cannot be opened, or the store is used after close()."""


class StoreFull(StorageError):
    """The write queue is full: the row was not accepted and will not be stored."""


# ---------------------------------------------------------------- the store


class MeasurementStore:
    """Measurements and events in one SQLite file; one writer thread, any number of readers.

    Parameters
    ----------
    path : the database file; created (with its directory) when missing.
    batch_max : rows per transaction at most.
    flush_interval_s : longest wait of a row for companions before its batch is committed.
    retention_days : measurements and events older than this are deleted at start and every
        ``maintenance_interval_s``; None keeps everything.
    max_queue : rows waiting for the writer at most; beyond it ``add_measurement`` raises StoreFull.
    synchronous : "FULL" (acknowledged rows survive power loss) or "NORMAL" (a process kill only).
    maintenance_interval_s : seconds between retention runs and WAL truncations.

    Raises
    ------
    StorageError
        The file is not a SQLite database, is someone else's, has a newer schema, cannot be
        created or written, or is already open in another store.
    """

    def __init__(
        self,
        path: Path,
        batch_max: int = 256,
        flush_interval_s: float = 0.1,
        retention_days: float | None = 30.0,
        max_queue: int = 100_000,
        *,
        synchronous: Literal["FULL", "NORMAL"] = "FULL",
        maintenance_interval_s: float = 60.0,
    ) -> None:
        if batch_max < 1 or max_queue < 1 or flush_interval_s < 0 or maintenance_interval_s <= 0:
            raise ValueError("batch_max, max_queue >= 1, flush_interval_s >= 0, maintenance_interval_s > 0")
        if retention_days is not None and retention_days <= 0:
            raise ValueError("retention_days must be positive, or None to keep everything")
        if synchronous not in ("FULL", "NORMAL"):
            raise ValueError(f"synchronous must be 'FULL' or 'NORMAL', not {synchronous!r}")
        self.path = Path(path)
        self.batch_max, self.max_queue = int(batch_max), int(max_queue)
        self.flush_interval_s, self.maintenance_interval_s = float(flush_interval_s), float(maintenance_interval_s)
        self.retention_days, self.synchronous = retention_days, synchronous

        self._lock_fd = self._acquire_writer_lock()
        try:
            self._wconn = self._open_write_connection()
            first_seq = self._last_used_id(self._wconn) + 1
        except BaseException:
            self._release_writer_lock()
            raise
        self._cond = threading.Condition()  # guards the queue and the sequence numbers
        self._pending: deque[Item] = deque()
        self._commit_latency_ms: deque[float] = deque(maxlen=5000)  # exposure -> committed, last rows
        self._next_seq, self._written_seq, self._flush_upto, self._inflight = first_seq, first_seq - 1, 0, 0
        self._stopping = self._closed = False
        self._stop_deadline = math.inf
        self._thread: threading.Thread | None = None
        self._own_events: list[tuple[Any, ...]] = []  # the writer's error events, written with the next batch
        self._counts = dict.fromkeys(
            ("written", "events_written", "batches", "dropped", "events_dropped", "abandoned", "retention_deleted"), 0
        )
        self._last_error: str | None = None
        self._last_error_t_wall: str | None = None
        self._failing_since: float | None = None  # monotonic s of the first failed commit of the current outage

    # ------------------------------------------------------------ opening

    def _acquire_writer_lock(self) -> int:
        lock_path = self.path.with_name(self.path.name + ".lock")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise StorageError(
                f"the measurement database {self.path} cannot be created ({e.strerror}): "
                f"check that {self.path.parent} is writable by the service user"
            ) from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if not isinstance(e, BlockingIOError):
                raise StorageError(f"cannot lock {lock_path} ({e.strerror}): put the database on a local disk") from e
            raise StorageError(
                f"the measurement database {self.path} is already open for writing by another "
                f"store or process (lock {lock_path}): run one posecell service per database"
            ) from None
        return fd

    def _release_writer_lock(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)  # closing drops the flock
            self._lock_fd = -1

    def _open_write_connection(self) -> sqlite3.Connection:
        conn = None
        try:
            conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=5.0)
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StorageError(
                    f"the measurement database {self.path} cannot use WAL mode (journal_mode "
                    f"is {mode}): put it on a local file system"
                )
            self._configure_write_connection(conn)
            self._migrate(conn)
            conn.execute(f"PRAGMA busy_timeout={int(_BUSY_TIMEOUT_S * 1000)}")  # opening may wait longer
            return conn
        except BaseException as e:
            if conn is not None:
                conn.close()
            if isinstance(e, sqlite3.OperationalError):  # unable to open, read-only, I/O error
                raise StorageError(
                    f"the measurement database {self.path} cannot be opened for writing ({e}): check that it "
                    f"and {self.path.parent} are writable by the service user and the disk works"
                ) from e
            if isinstance(e, sqlite3.Error):  # "file is not a database", "database disk image is malformed"
                raise StorageError(
                    f"the measurement database {self.path} is not a SQLite database or is damaged ({e}): move "
                    "it aside (keep it if it holds history you need) and the service starts a new one"
                ) from e
            raise

    def _configure_write_connection(self, conn: sqlite3.Connection) -> None:
        """Pragmas of the writer's connection."""
        conn.execute(f"PRAGMA synchronous={self.synchronous}")
        conn.execute(f"PRAGMA journal_size_limit={_JOURNAL_SIZE_LIMIT_BYTES}")

    def _migrate(self, conn: sqlite3.Connection) -> None:
        version = conn.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            raise StorageError(
                f"the measurement database {self.path} has schema version {version}, newer than "
                f"this posecell's {SCHEMA_VERSION}: upgrade posecell or move the file aside"
            )
        tables = sorted(
            r[0]
            for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")
        )
        if version == 0 and tables:
            raise StorageError(
                f"the measurement database {self.path} is a SQLite database but not posecell's "
                f"(tables {', '.join(tables)}, no schema version): move it aside or choose another path"
            )
        for v in range(version, SCHEMA_VERSION):
            conn.execute("BEGIN IMMEDIATE")
            try:
                MIGRATIONS[v](conn)
                conn.execute(f"PRAGMA user_version={v + 1}")  # transactional: a crash redoes the whole step
                conn.execute("COMMIT")
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            log.info("measurement database %s migrated to schema version %d", self.path, v + 1)

    @staticmethod
    def _last_used_id(conn: sqlite3.Connection) -> int:
        # AUTOINCREMENT's sqlite_sequence remembers ids of purged rows: sequence numbers never repeat
        row = conn.execute("SELECT seq FROM sqlite_sequence WHERE name = 'measurements'").fetchone()
        max_id = conn.execute("SELECT max(id) FROM measurements").fetchone()[0]
        return max(row[0] if row else 0, max_id or 0)

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the writer thread (idempotent while open)."""
        with self._cond:
            if self._closed or self._stopping:
                raise StorageError(f"the measurement store {self.path} is closed")
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="posecell-storage", daemon=True)
                self._thread.start()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write every queued row, commit, stop the writer and close the database (idempotent).

        If the disk keeps failing for ``timeout_s``, the rows still queued are abandoned (none was
        acknowledged), counted in ``stats()["abandoned"]`` and logged.
        """
        with self._cond:
            if self._closed:
                return
            self._stopping = True
            self._stop_deadline = time.monotonic() + timeout_s
            thread = self._thread
            self._cond.notify_all()
        if thread is None:
            self._run()  # never started: write what was queued from this thread
        else:
            thread.join(timeout_s + 5.0)
            if thread.is_alive():
                log.error("storage writer for %s did not stop within %.1f s", self.path, timeout_s + 5.0)
                return
        with self._cond:
            self._closed = True
        self._release_writer_lock()

    def __enter__(self) -> MeasurementStore:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------ writing (any thread)

    def add_measurement(self, measurement: Measurement, *, triggered: bool = False) -> int:
        """Queue one result; return its sequence number, which is its row id.

        The columns are the measurement's fields: ``t_wall`` (its wall-clock instant), ``t_host_ns``
        (the exposure on the host's clock), ``camera``, ``ok``, ``reason``, ``rms_px``, ``n_targets``,
        the translation of the measured flange (else of the camera in the field; ``pose_of`` says
        which) and the deviation; ``result`` holds its JSON (DESIGN section 4) plus ``triggered``.

        Raises
        ------
        StoreFull : ``max_queue`` rows are waiting; this one is not stored.
        StorageError : the store is closed.
        TypeError : not a :class:`~service.core.measurement.Measurement`.
        """
        if not isinstance(measurement, Measurement):
            raise TypeError(
                f"a measurement must be a service.core.measurement.Measurement, not {type(measurement).__name__}"
            )
        with self._cond:
            if self._stopping:
                raise StorageError(f"the measurement store {self.path} is closed")
            if len(self._pending) >= self.max_queue:
                self._counts["dropped"] += 1
                raise StoreFull(
                    f"{len(self._pending)} rows are waiting to be written to {self.path}; this "
                    f"measurement is not stored (last error: {self._last_error})"
                )
            seq = self._next_seq
            self._next_seq += 1
            # frozen: converted to its row by the writer thread, off the processing thread's path
            self._enqueue((seq, "q", (measurement, triggered)))
        return seq

    def add_event(self, kind: str, message: str, level: str = "info", details: Mapping[str, Any] | None = None) -> None:
        """Queue one event (``level``: debug, info, warning or error); a full queue counts and logs it."""
        row = event_row(kind, message, level, details)
        with self._cond:
            if self._stopping:
                raise StorageError(f"the measurement store {self.path} is closed")
            if len(self._pending) >= self.max_queue:
                self._counts["events_dropped"] += 1
                log.warning("storage queue full: event %s %r not stored", kind, message)
                return
            self._enqueue((0, "e", row))

    def _enqueue(self, item: Item) -> None:
        self._pending.append(item)
        if len(self._pending) in (1, self.batch_max):  # the only sizes the writer waits for
            self._cond.notify_all()

    def wait_written(self, seq: int, timeout_s: float) -> bool:
        """Wait until measurement ``seq`` is committed (and fsynced under FULL); False on timeout."""
        with self._cond:
            if seq < 1 or seq >= self._next_seq:
                raise ValueError(f"sequence number {seq} was never issued by this store")
            if self._flush_upto < seq:  # the writer commits without waiting for companions
                self._flush_upto = seq
                self._cond.notify_all()
            return self._cond.wait_for(lambda: self._written_seq >= seq, timeout_s)

    # ------------------------------------------------------------ the writer thread

    def _run(self) -> None:
        conn = self._wconn
        try:
            self._maintenance(conn)
            next_maintenance = time.monotonic() + self.maintenance_interval_s
            while True:
                queued = self._next_batch(next_maintenance)
                exposed_unix_ns = [row[0].t_unix_ns for _, tag, row in queued if tag == "q"]
                batch = [_row_of(item) for item in queued]
                if batch and self._commit_with_retry(conn, batch):
                    now_ns = time.time_ns()
                    with self._cond:
                        self._commit_latency_ms.extend((now_ns - t) * 1e-6 for t in exposed_unix_ns)
                elif self._stopping:
                    break
                if time.monotonic() >= next_maintenance:
                    self._maintenance(conn)
                    next_maintenance = time.monotonic() + self.maintenance_interval_s
            with contextlib.suppress(sqlite3.Error):
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except Exception:  # a bug, not a disk problem: say so loudly
            log.exception("storage writer for %s failed", self.path)
            raise
        finally:
            conn.close()

    def _next_batch(self, next_maintenance: float) -> list[Item]:
        with self._cond:
            while not self._pending and not self._stopping:
                if (remaining := next_maintenance - time.monotonic()) <= 0:
                    return []
                self._cond.wait(remaining)
            deadline = time.monotonic() + self.flush_interval_s
            while (
                self._pending
                and len(self._pending) < self.batch_max
                and not self._stopping
                and self._flush_upto <= self._written_seq
                and (remaining := deadline - time.monotonic()) > 0
            ):
                self._cond.wait(remaining)
            n = min(self.batch_max, len(self._pending))
            self._inflight = n
            return [self._pending.popleft() for _ in range(n)]

    def _write_batch(self, conn: sqlite3.Connection, batch: list[Item], own_events: list[tuple[Any, ...]]) -> None:
        """One transaction: the batch's rows plus the store's own events (errors, recovery)."""
        conn.execute("BEGIN")
        try:
            rows = [(seq, *row) for seq, tag, row in batch if tag == "m"]
            for i in range(0, len(rows), _ROWS_PER_INSERT):  # one statement per chunk (rows.insert_rows_sql)
                chunk = rows[i : i + _ROWS_PER_INSERT]
                conn.execute(insert_rows_sql(INSERT_MEASUREMENT, len(chunk)), [v for row in chunk for v in row])
            conn.executemany(INSERT_EVENT, [row for _, tag, row in batch if tag == "e"] + own_events)
            conn.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
            raise

    def _record_error(self, e: sqlite3.Error) -> None:
        self._last_error = f"{type(e).__name__}: {e}"
        self._last_error_t_wall = iso_utc(datetime.now(UTC))

    def _commit_with_retry(self, conn: sqlite3.Connection, batch: list[Item]) -> bool:
        """Commit ``batch``, retrying while the database refuses; False: abandoned at close."""
        delay_s, attempts, t_fail = 0.05, 0, 0.0
        while True:
            own_events = list(self._own_events)
            if attempts:  # committed with the rows, so it is stored exactly when writing works again
                own_events.append(
                    event_row(
                        "storage_recovered",
                        "writing to the measurement database works again",
                        "warning",
                        {"failed_attempts": attempts, "outage_s": round(time.monotonic() - t_fail, 3)},
                    )
                )
            try:
                self._write_batch(conn, batch, own_events)
                break
            except sqlite3.Error as e:
                attempts += 1
                self._record_error(e)
                if attempts == 1:
                    t_fail = time.monotonic()
                    with self._cond:
                        self._failing_since = t_fail
                    log.error("writing %d rows to %s failed (%s); retrying", len(batch), self.path, e)
                    self._own_events.append(
                        event_row(
                            "storage_error",
                            f"writing to the measurement database failed: {e}",
                            "error",
                            {"error": str(e), "rows_waiting": len(batch) + len(self._pending)},
                        )
                    )
                with self._cond:
                    if self._stopping and time.monotonic() >= self._stop_deadline:
                        lost = len(batch) + len(self._pending)
                        self._counts["abandoned"] += lost
                        self._pending.clear()
                        self._inflight = 0
                        log.error("closing %s: %d unacknowledged rows abandoned after %s", self.path, lost, e)
                        return False
                    self._cond.wait(delay_s)
                delay_s = min(2 * delay_s, _RETRY_MAX_S)
        if attempts:
            log.warning("writing to %s works again after %d failed attempts", self.path, attempts)
        self._own_events = []
        seqs = [seq for seq, tag, _ in batch if tag == "m"]
        with self._cond:
            self._failing_since = None
            self._written_seq = seqs[-1] if seqs else self._written_seq
            self._counts["written"] += len(seqs)
            self._counts["events_written"] += len(batch) - len(seqs) + len(own_events)
            self._counts["batches"] += 1
            self._inflight = 0
            self._cond.notify_all()
        return True

    def _maintenance(self, conn: sqlite3.Connection) -> None:
        """Retention purge in chunks, then WAL truncation; errors are recorded, never raised."""
        try:
            if self.retention_days is not None:
                cutoff = iso_utc(datetime.now(UTC) - timedelta(days=self.retention_days))
                deleted = 0
                for table in ("measurements", "events"):
                    for _ in range(_RETENTION_MAX_CHUNKS):
                        n = conn.execute(
                            f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} WHERE t_wall < ? "
                            f"ORDER BY t_wall LIMIT {_RETENTION_CHUNK})",
                            (cutoff,),
                        ).rowcount
                        deleted += n
                        if n < _RETENTION_CHUNK:
                            break
                if deleted:
                    self._counts["retention_deleted"] += deleted
                    log.info("retention: deleted %d rows older than %s from %s", deleted, cutoff, self.path)
            conn.execute("PRAGMA busy_timeout=200")  # a long reader only postpones truncation to the next run
            try:
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
            finally:
                conn.execute(f"PRAGMA busy_timeout={int(_BUSY_TIMEOUT_S * 1000)}")
        except sqlite3.Error as e:
            self._record_error(e)
            log.warning("maintenance of %s failed: %s", self.path, e)

    # ------------------------------------------------------------ reading (any thread)

    def _select(self, sql: str, params: list[Any]) -> list[dict[str, Any]]:
        try:
            # mode=rw: a reader never creates an empty database where the real one went missing
            uri = f"{self.path.absolute().as_uri()}?mode=rw"
            with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=5.0)) as conn:
                conn.execute("PRAGMA query_only=ON")
                conn.row_factory = sqlite3.Row
                return [dict(r) for r in conn.execute(sql, params)]
        except sqlite3.Error as e:
            raise StorageError(f"cannot read the measurement database {self.path}: {e}") from e

    def measurements(
        self,
        t_from: datetime | None = None,
        t_to: datetime | None = None,
        limit: int = 1000,
        offset: int = 0,
        ok: bool | None = None,
        camera: str | None = None,
        *,
        oldest_first: bool = False,
    ) -> list[dict[str, Any]]:
        """Measurements with ``t_from <= t_wall < t_to``, newest first unless ``oldest_first``.

        Each row has the columns of CSV_COLUMNS but ``message`` (``ok`` a bool) and ``result``, the
        stored result dict. Datetimes must carry a time zone.
        """
        check_page(limit, offset)
        where, params = where_clause(t_from, t_to, ok=None if ok is None else int(bool(ok)), camera=camera)
        order = "ASC" if oldest_first else "DESC"
        rows = self._select(
            f"SELECT {', '.join(ROW_COLUMNS)}, result FROM measurements{where} "
            f"ORDER BY t_wall {order}, id {order} LIMIT ? OFFSET ?",
            [*params, limit, offset],
        )
        for r in rows:
            r["ok"], r["result"] = bool(r["ok"]), json.loads(r["result"])
        return rows

    def count(
        self,
        t_from: datetime | None = None,
        t_to: datetime | None = None,
        ok: bool | None = None,
        camera: str | None = None,
    ) -> int:
        """Number of measurements matching the filters of :meth:`measurements`."""
        where, params = where_clause(t_from, t_to, ok=None if ok is None else int(bool(ok)), camera=camera)
        return int(self._select(f"SELECT count(*) AS n FROM measurements{where}", params)[0]["n"])

    def events(
        self,
        t_from: datetime | None = None,
        t_to: datetime | None = None,
        limit: int = 1000,
        offset: int = 0,
        level: str | None = None,
        kind: str | None = None,
        *,
        oldest_first: bool = False,
    ) -> list[dict[str, Any]]:
        """Events (id, t_wall, level, kind, message, details dict or None), newest first by default."""
        check_page(limit, offset)
        if level is not None and level not in EVENT_LEVELS:
            raise ValueError(f"event level {level!r} is not one of {', '.join(EVENT_LEVELS)}")
        where, params = where_clause(t_from, t_to, level=level, kind=kind)
        order = "ASC" if oldest_first else "DESC"
        rows = self._select(
            f"SELECT id, t_wall, level, kind, message, details FROM events{where} "
            f"ORDER BY t_wall {order}, id {order} LIMIT ? OFFSET ?",
            [*params, limit, offset],
        )
        for r in rows:
            r["details"] = None if r["details"] is None else json.loads(r["details"])
        return rows

    @staticmethod
    def export_csv(rows: list[dict[str, Any]]) -> str:
        """Rows of :meth:`measurements` as CSV with the header CSV_COLUMNS (``ok`` as true/false)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\r\n")
        w.writerow(CSV_COLUMNS)
        for r in rows:
            extra = {"ok": "true" if r.get("ok") else "false", "message": (r.get("result") or {}).get("message")}
            w.writerow(["" if (v := extra.get(c, r.get(c))) is None else v for c in CSV_COLUMNS])
        return buf.getvalue()

    def health(self) -> tuple[str, str]:
        """``("ok", "")``, or ``("degraded", sentence)`` while commits fail or the writer is gone."""
        with self._cond:
            failing_since, queued = self._failing_since, len(self._pending) + self._inflight
            thread, closed = self._thread, self._closed or self._stopping
        if closed:
            return "degraded", f"the measurement store {self.path} is closed"
        if thread is not None and not thread.is_alive():
            return "degraded", f"the storage writer for {self.path} has stopped (see the log); nothing is stored"
        if failing_since is not None:
            return "degraded", (
                f"writing to the measurement database has failed for "
                f"{time.monotonic() - failing_since:.1f} s ({self._last_error}); {queued} rows "
                "wait and are retried"
            )
        return "ok", ""

    def stats(self) -> dict[str, Any]:
        """Counters since open (queued, written, dropped, ...), database size, state and the last write error."""
        state, error = self.health()
        with self._cond:
            out: dict[str, Any] = {
                "state": state,
                "error": error,
                "queued": len(self._pending) + self._inflight,
                "last_written_seq": self._written_seq,
                **self._counts,
                "commit_latency_ms": _spread(self._commit_latency_ms),
            }
        size = 0
        for suffix in ("", "-wal"):
            with contextlib.suppress(OSError):
                size += os.path.getsize(f"{self.path}{suffix}")
        out.update(
            db_size_bytes=size,
            synchronous=self.synchronous,
            last_error=self._last_error,
            last_error_t_wall=self._last_error_t_wall,
        )
        return out


def _spread(values_ms: deque[float]) -> dict[str, float | int] | None:
    """p50, p99 and max of the exposure → commit latency of the last rows (their wall clock is the exposure's)."""
    if not values_ms:
        return None
    ms = sorted(values_ms)
    n = len(ms)
    return {
        "n": n,
        "p50": round(ms[n // 2], 3),
        "p99": round(ms[min(n - 1, int(0.99 * n))], 3),
        "max": round(ms[-1], 3),
    }


def _row_of(item: Item) -> Item:
    """A queued item as the row it is written as. The writer then lets the other threads run
    (``time.sleep(0)`` hands the interpreter lock over): a batch of a hundred rows built in one
    go held the lock for milliseconds, which the measurement's results waited behind."""
    seq, tag, row = item
    if tag != "q":
        return item
    out = (seq, "m", measurement_row(*row))
    time.sleep(0)
    return out
