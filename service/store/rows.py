"""The measurement database's schema, its migrations and how a result becomes a row.

Pure conversion, no connection held: the columns a listing filters and the CSV export shows
are read from a :class:`~service.core.measurement.Measurement`'s fields (nothing is guessed
from its JSON); the whole result is kept beside them as strict JSON (NaN and infinities
become null). ``service.store.measurements`` owns the connection and the writer thread.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Callable, Mapping
from datetime import UTC, datetime, timedelta
from functools import lru_cache
from typing import Any

from service.core.measurement import Measurement
from service.store.formats import null_for_unknown

EVENT_LEVELS = ("debug", "info", "warning", "error")
# measurement columns besides the whole result's JSON; also the CSV export's columns
CSV_COLUMNS = (
    "id",
    "t_wall",
    "t_host_ns",
    "camera",
    "ok",
    "reason",
    "message",
    "pose_of",
    "x_mm",
    "y_mm",
    "z_mm",
    "deviation_position_mm",
    "deviation_angle_deg",
    "rms_px",
    "n_targets",
)
ROW_COLUMNS = tuple(c for c in CSV_COLUMNS if c != "message")
# ---------------------------------------------------------------- schema and migrations


def _migrate_to_v1(conn: sqlite3.Connection) -> None:
    conn.execute("""CREATE TABLE measurements (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        t_wall TEXT NOT NULL,       -- ISO 8601 UTC, fixed width: sorts as text
        t_host_ns INTEGER,          -- time.monotonic_ns() of the frame (host clock)
        camera TEXT, ok INTEGER NOT NULL, reason TEXT,
        pose_of TEXT,               -- what x/y/z_mm are: base_flange_measured or field_camera
        x_mm REAL, y_mm REAL, z_mm REAL,
        deviation_position_mm REAL, deviation_angle_deg REAL, rms_px REAL, n_targets INTEGER,
        result TEXT NOT NULL        -- the whole result, JSON
    )""")
    conn.execute("CREATE INDEX measurements_t_wall ON measurements (t_wall)")
    conn.execute("""CREATE TABLE events (
        id INTEGER PRIMARY KEY AUTOINCREMENT, t_wall TEXT NOT NULL, level TEXT NOT NULL,
        kind TEXT NOT NULL, message TEXT NOT NULL, details TEXT  -- JSON object or NULL
    )""")
    conn.execute("CREATE INDEX events_t_wall ON events (t_wall)")


def _migrate_to_v2(conn: sqlite3.Connection) -> None:
    # the robot's accuracy tests (service.store.tests_store): kept until deleted, not purged by retention
    conn.execute("""CREATE TABLE tests (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        kind TEXT NOT NULL,         -- circle | iso9283 | table1
        mode TEXT NOT NULL,         -- program | record
        params TEXT NOT NULL,       -- JSON, as validated
        status TEXT NOT NULL,       -- queued | running | done | failed | cancelled | interrupted
        progress REAL NOT NULL DEFAULT 0, progress_message TEXT,
        created TEXT NOT NULL, finished TEXT,  -- ISO 8601 UTC
        error TEXT, n_samples INTEGER NOT NULL DEFAULT 0,
        report TEXT,                -- JSON: what `posecell report` writes as report.json
        details TEXT                -- JSON: conditions, and in the simulation the truth's analysis
    )""")
    conn.execute("""CREATE TABLE test_samples (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        test_id INTEGER NOT NULL REFERENCES tests (id) ON DELETE CASCADE,
        t_exposure_unix_ns INTEGER NOT NULL,
        label TEXT, visit INTEGER, stop INTEGER,  -- direction / pose / position; lap / cycle / visit; stop number
        sample TEXT NOT NULL        -- JSON: measured, reported (and true, commanded) flange poses, σ
    )""")
    conn.execute("CREATE INDEX test_samples_test ON test_samples (test_id, id)")


# MIGRATIONS[n] brings a database from user_version n to n + 1; append, never edit.
MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (_migrate_to_v1, _migrate_to_v2)
SCHEMA_VERSION = len(MIGRATIONS)


# ---------------------------------------------------------------- row conversion


def iso_utc(t: datetime) -> str:
    """Fixed-width ISO 8601 UTC text that sorts like the time.

    >>> iso_utc(datetime.fromisoformat("2025-01-02T04:04:05.000006+01:00"))
    '2025-01-02T03:04:05.000006Z'
    """
    if t.tzinfo is None:
        raise ValueError(f"datetime {t.isoformat()} has no time zone: give an aware datetime (e.g. UTC)")
    return t.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _json_default(o: Any) -> Any:
    if hasattr(o, "tolist"):  # numpy arrays and scalars, without importing numpy
        return o.tolist()
    if isinstance(o, datetime):
        return iso_utc(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _dumps(obj: Any) -> str:
    """Compact strict JSON; NaN and infinities (no JSON for them) become null."""
    try:
        return json.dumps(obj, default=_json_default, separators=(",", ":"), allow_nan=False)
    except ValueError:  # rare: only then pay for the walk
        return json.dumps(null_for_unknown(obj), default=_json_default, separators=(",", ":"), allow_nan=False)


def _real(x: Any) -> float | None:
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def _iso_of_unix_ns(t_ns: int) -> str:
    secs, ns = divmod(int(t_ns), 1_000_000_000)
    return iso_utc(datetime.fromtimestamp(secs, UTC) + timedelta(microseconds=ns // 1000))


def measurement_row(m: Measurement, triggered: bool) -> tuple[Any, ...]:
    """Column values (without id) of one result: read from its fields, never guessed from its JSON."""
    if not isinstance(m, Measurement):
        raise TypeError(f"a measurement must be a service.core.measurement.Measurement, not {type(m).__name__}")
    # the flange in base when hand-eye calibrated, else the camera in the field; pose_of says which
    flange = m.flange
    pose_of, T = "field_camera", m.T_field_camera
    if flange is not None and flange.T_base_flange_measured is not None:
        pose_of, T = "base_flange_measured", flange.T_base_flange_measured
    xyz = (None, None, None) if T is None else tuple(_real(v) for v in T[:3, 3])
    dev = flange.deviation if flange is not None else None
    rms_px = None if m.T_field_camera is None else getattr(m.result, "rms_px", None)
    return (
        _iso_of_unix_ns(m.t_unix_ns),
        m.t_exposure_host_ns,
        m.camera or None,
        1 if m.ok else 0,
        None if m.reason is None else str(m.reason),
        None if T is None else pose_of,
        *xyz,
        None if dev is None else _real(dev.position_mm),
        None if dev is None else _real(dev.angle_deg),
        _real(rms_px),
        m.n_targets,
        # the message's own JSON (encoded once, for the WebSocket too) with the trigger flag added
        f'{m.json[:-1]},"triggered":{"true" if triggered else "false"}}}',
    )


def event_row(kind: str, message: str, level: str, details: Mapping[str, Any] | None) -> tuple[Any, ...]:
    if level not in EVENT_LEVELS:
        raise ValueError(f"event level {level!r} is not one of {', '.join(EVENT_LEVELS)}")
    if details is not None and not isinstance(details, Mapping):
        raise TypeError(f"event details must be a dict or None, not {type(details).__name__}")
    return (iso_utc(datetime.now(UTC)), level, str(kind), str(message), None if details is None else _dumps(details))


INSERT_MEASUREMENT = (
    "INSERT INTO measurements (id, t_wall, t_host_ns, camera, ok, reason, pose_of, x_mm, y_mm, z_mm,"
    " deviation_position_mm, deviation_angle_deg, rms_px, n_targets, result)"
    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
)
INSERT_EVENT = "INSERT INTO events (t_wall, level, kind, message, details) VALUES (?, ?, ?, ?, ?)"


@lru_cache(maxsize=64)
def insert_rows_sql(insert_one: str, n_rows: int) -> str:
    """``insert_one`` (an ``INSERT … VALUES (?, …)`` of one row) for ``n_rows`` rows in one statement.

    Why: ``executemany`` steps SQLite once per row, and every step hands the interpreter's lock
    back and waits to take it again — up to the 5 ms switch interval while the measurement thread
    computes. At 400-500 frames/s, stored every one, a batch of 200 rows waited ~1 s that way;
    one statement per batch takes the lock back once.
    """
    head, _, one = insert_one.rpartition(" VALUES ")
    return f"{head} VALUES {', '.join([one] * n_rows)}"


def check_page(limit: int, offset: int) -> None:
    for name, v in (("limit", limit), ("offset", offset)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"{name} must be a non-negative integer, not {v!r}")


def where_clause(t_from: datetime | None, t_to: datetime | None, **equal: Any) -> tuple[str, list[Any]]:
    clauses = [
        ("t_wall >= ?", None if t_from is None else iso_utc(t_from)),
        ("t_wall < ?", None if t_to is None else iso_utc(t_to)),
    ]
    clauses += [(f"{column} = ?", value) for column, value in equal.items()]  # columns: ours, never input
    used = [(c, v) for c, v in clauses if v is not None]
    return (" WHERE " + " AND ".join(c for c, _ in used)) if used else "", [v for _, v in used]
