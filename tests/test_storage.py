"""MeasurementStore on real SQLite files with its real writer thread, and a real kill -9."""

from __future__ import annotations

import csv
import io
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from service.core.measurement import Deviation, Flange, Measurement
from service.core.results import Failure, PoseResult, Reason, TargetObservation
from service.store.measurements import MeasurementStore, StorageError, StoreFull
from service.store.rows import CSV_COLUMNS, SCHEMA_VERSION

REPO = Path(__file__).resolve().parents[1]
T0 = datetime(2025, 3, 1, 12, 0, 0, tzinfo=UTC)


def result(
    n: int,
    *,
    ok: bool = True,
    camera: str = "cam0",
    t_wall: datetime | None = None,
    n_targets: int = 5,
    rms_px: float = 0.05,
    sigma_position_mm: np.ndarray | None = None,
    t_host_ns: int | None = 1,
    flange: Flange | None = None,
) -> Measurement:
    """A frame's measurement numbered ``seq = n``: a pose at x = 100 + n, y = 2n mm, or a failure."""
    t = t_wall or datetime.now(UTC)
    t_unix_ns = int(t.timestamp()) * 1_000_000_000 + t.microsecond * 1000
    if not ok:
        return Measurement(
            camera, Failure(Reason.too_few_targets, "only 3 targets, at least 6 needed"), t_unix_ns, seq=n
        )
    T = np.eye(4)
    T[:3, 3] = [100.0 + n, 2.0 * n, 1500.0]
    targets = tuple(
        TargetObservation(f"{'C' if k % 3 == 0 else 'U'}{k}", (10.0 * k, 5.0 * k), (0.01, -0.02), k % 3 == 0)
        for k in range(n_targets)
    )
    sigma = np.full(3, 0.01) if sigma_position_mm is None else sigma_position_mm
    pose = PoseResult(T, sigma, np.full(3, 0.001), rms_px, rms_px, targets)
    return Measurement(camera, pose, t_unix_ns, t_host_ns, seq=n, flange=flange)


@pytest.fixture
def open_store(tmp_path):
    """Factory of started stores in tmp_path; every store is closed at the end even if the test fails."""
    stores: list[MeasurementStore] = []

    def make(name: str = "m.db", cls: type[MeasurementStore] = MeasurementStore, start: bool = True, **kw):
        s = cls(tmp_path / name, **kw)
        stores.append(s)
        if start:
            s.start()
        return s

    try:
        yield make
    finally:
        for s in stores:
            s.close(timeout_s=2.0)


def test_rows_written_in_batches_are_all_readable_after_close(open_store, tmp_path):
    store = open_store(batch_max=16, flush_interval_s=0.05)
    seqs = [store.add_measurement(result(n)) for n in range(500)]
    store.close()
    stats = store.stats()
    assert stats["written"] == 500 and stats["queued"] == 0
    assert 500 / 16 <= stats["batches"] < 250  # batched, not one transaction per row
    assert seqs == list(range(seqs[0], seqs[0] + 500))

    reopened = open_store(start=False)
    rows = reopened.measurements(limit=1000, oldest_first=True)
    assert [r["id"] for r in rows] == seqs  # the sequence number is the row id
    assert [r["result"]["seq"] for r in rows] == list(range(500))
    assert reopened.count() == 500
    assert reopened.add_measurement(result(500)) == seqs[-1] + 1  # numbering continues across opens


def test_database_is_in_wal_mode_with_schema_version(open_store, tmp_path):
    open_store()
    with sqlite3.connect(tmp_path / "m.db") as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"measurements", "events"} <= tables


def test_wait_written_acknowledges_without_waiting_for_the_flush_interval(open_store):
    store = open_store(flush_interval_s=10.0)
    t = time.monotonic()
    seq = store.add_measurement(result(0))
    assert store.wait_written(seq, timeout_s=5.0)
    assert time.monotonic() - t < 1.0
    with pytest.raises(ValueError, match="never issued"):
        store.wait_written(seq + 1, timeout_s=0.1)


def test_the_exposure_to_commit_latency_is_reported(open_store):
    store = open_store(flush_interval_s=0.0)
    assert store.stats()["commit_latency_ms"] is None
    exposed = datetime.now(UTC) - timedelta(milliseconds=200)  # as if the frame was exposed 0.2 s ago
    seqs = [store.add_measurement(result(n, t_wall=exposed)) for n in range(20)]
    assert store.wait_written(seqs[-1], timeout_s=5.0)
    latency = store.stats()["commit_latency_ms"]
    assert latency["n"] == 20 and 200.0 <= latency["p50"] <= latency["p99"] <= latency["max"] < 5000.0


def test_time_ok_camera_filters_and_paging(open_store):
    store = open_store()
    for n in range(40):  # one per minute; every 4th failed; cameras alternate
        store.add_measurement(result(n, ok=n % 4 != 0, camera=f"cam{n % 2}", t_wall=T0 + timedelta(minutes=n)))
    store.close()

    newest = store.measurements()
    assert [r["result"]["seq"] for r in newest] == list(range(39, -1, -1))  # newest first by default

    window = store.measurements(T0 + timedelta(minutes=10), T0 + timedelta(minutes=20), oldest_first=True)
    assert [r["result"]["seq"] for r in window] == list(range(10, 20))  # t_from inclusive, t_to exclusive
    assert store.count(T0 + timedelta(minutes=10), T0 + timedelta(minutes=20)) == 10

    failed = store.measurements(ok=False)
    assert [r["result"]["seq"] for r in failed] == list(range(36, -1, -4))
    assert all(r["ok"] is False and r["reason"] == "too_few_targets" for r in failed)
    assert store.count(ok=True) == 30

    cam1 = store.measurements(camera="cam1", ok=True, oldest_first=True)
    assert [r["result"]["seq"] for r in cam1] == [n for n in range(40) if n % 2 == 1 and n % 4 != 0]

    page = store.measurements(limit=5, offset=10, oldest_first=True)
    assert [r["result"]["seq"] for r in page] == list(range(10, 15))
    assert store.measurements(limit=0) == []

    with pytest.raises(ValueError, match="time zone"):
        store.measurements(t_from=datetime(2025, 3, 1, 12, 0))
    with pytest.raises(ValueError, match="limit"):
        store.measurements(limit=-1)


def test_columns_are_taken_from_the_result(open_store):
    store = open_store()
    T_base_flange_measured = np.eye(4)
    T_base_flange_measured[:3, 3] = [400.0, -50.0, 300.0]
    flange = Flange(None, T_base_flange_measured, Deviation(0.25, 0.02, np.array([0.25, 0.0, 0.0])))
    seq = store.add_measurement(
        result(1, flange=flange, t_host_ns=123_456_789, n_targets=230, sigma_position_mm=np.array([0.01, 0.01, 0.03]))
    )
    assert store.wait_written(seq, timeout_s=5.0)
    (row,) = store.measurements()
    assert row["pose_of"] == "base_flange_measured"
    assert (row["x_mm"], row["y_mm"], row["z_mm"]) == (400.0, -50.0, 300.0)
    assert (row["deviation_position_mm"], row["deviation_angle_deg"]) == (0.25, 0.02)
    assert row["n_targets"] == 230 and row["rms_px"] == 0.05 and row["t_host_ns"] == 123_456_789
    assert row["result"]["sigma_position_mm"] == [0.01, 0.01, 0.03]  # numpy serialised as lists
    assert row["t_wall"].endswith("Z")

    seq = store.add_measurement(result(2, rms_px=float("nan"), sigma_position_mm=np.array([0.01, np.inf, 0.02])))
    assert store.wait_written(seq, timeout_s=5.0)
    row = store.measurements(limit=1)[0]
    assert row["rms_px"] is None and row["result"]["sigma_position_mm"] == [0.01, None, 0.02]  # strict JSON

    with pytest.raises(TypeError, match="Measurement"):
        store.add_measurement({"ok": True, "rms_px": 0.1})  # a dict's keys would be guessed at


def test_a_failure_detail_that_has_no_json_is_kept_as_its_text(open_store):
    store = open_store()
    odd = Failure(Reason.bad_image, "odd", {"shape": np.int64(3), "what": complex(1, 2)})
    seq = store.add_measurement(Measurement("cam0", odd, time.time_ns(), 1, seq=1))
    assert store.wait_written(seq, timeout_s=5.0)
    (row,) = store.measurements()
    assert row["result"]["shape"] == 3 and row["result"]["what"] == "(1+2j)" and row["reason"] == "bad_image"


def test_csv_export_parses_back_with_the_csv_module(open_store):
    store = open_store()
    for n in range(6):
        store.add_measurement(result(n, ok=n != 3, t_wall=T0 + timedelta(seconds=n)))
    store.close()
    rows = store.measurements(oldest_first=True)
    parsed = list(csv.DictReader(io.StringIO(store.export_csv(rows))))
    assert tuple(parsed[0].keys()) == CSV_COLUMNS
    assert [int(p["id"]) for p in parsed] == [r["id"] for r in rows]
    assert [p["ok"] for p in parsed] == ["true", "true", "true", "false", "true", "true"]
    assert parsed[3]["reason"] == "too_few_targets" and parsed[3]["message"].startswith("only 3 targets")
    assert parsed[3]["x_mm"] == "" and float(parsed[4]["x_mm"]) == 104.0
    assert datetime.fromisoformat(parsed[5]["t_wall"]) == T0 + timedelta(seconds=5)


def test_events_are_stored_and_filtered(open_store):
    store = open_store()
    store.add_event("camera_disconnected", "camera cam0 stopped answering", level="error", details={"camera": "cam0"})
    store.add_event("camera_connected", "camera cam0 is back")
    with pytest.raises(ValueError, match="level"):
        store.add_event("x", "y", level="fatal")
    store.close()
    events = store.events()
    assert [e["kind"] for e in events] == ["camera_connected", "camera_disconnected"]
    (err,) = store.events(level="error")
    assert err["details"] == {"camera": "cam0"} and err["message"] == "camera cam0 stopped answering"


KILL_CHILD = textwrap.dedent("""
    import sys, threading
    from pathlib import Path
    import time
    import numpy as np
    from service.core.measurement import Measurement
    from service.core.results import Failure, PoseResult, Reason
    from service.store.measurements import MeasurementStore

    pose = PoseResult(np.eye(4), np.full(3, 0.01), np.full(3, 0.001), 0.05, 0.05, ())
    failure = Failure(Reason.no_frame, "-")

    store = MeasurementStore(Path(sys.argv[1]), batch_max=32, flush_interval_s=0.01, synchronous=sys.argv[2])
    store.start()

    def background_load():  # keeps transactions in flight at the moment of the kill, backlog bounded
        k = 0
        while True:
            seqs = [store.add_measurement(Measurement("bg", failure, time.time_ns(), seq=k + i)) for i in range(50)]
            k += 50
            store.wait_written(seqs[-1], 5.0)

    threading.Thread(target=background_load, daemon=True).start()
    n = 0
    while True:
        block = []
        for _ in range(10):
            block.append((store.add_measurement(Measurement("cam0", pose, time.time_ns(), 1, seq=n)), n))
            n += 1
        if store.wait_written(block[-1][0], 5.0):
            # one write per block: lines reach the pipe whole (< PIPE_BUF) or not at all
            sys.stdout.write("".join(f"{seq} {k}\\n" for seq, k in block))
            sys.stdout.flush()
""")


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
@pytest.mark.parametrize("synchronous", ["FULL", "NORMAL"])
def test_kill_9_mid_stream_loses_no_acknowledged_row_and_leaves_a_sound_database(tmp_path, synchronous):
    db = tmp_path / "m.db"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-c", KILL_CHILD, str(db), synchronous],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    try:
        reader.start()
        deadline = time.monotonic() + 10.0
        while len(lines) < 1000 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.01)
        assert proc.poll() is None, f"the writer process died by itself: {proc.stderr.read()}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        reader.join(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
        proc.stdout.close()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    acknowledged = dict(tuple(map(int, line.split())) for line in lines if line.endswith("\n"))
    assert len(acknowledged) >= 100

    with sqlite3.connect(db) as conn:
        assert conn.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        stored = dict(conn.execute("SELECT id, json_extract(result, '$.seq') FROM measurements WHERE ok = 1"))
        n_background = conn.execute("SELECT count(*) FROM measurements WHERE ok = 0").fetchone()[0]
    missing = {seq: n for seq, n in acknowledged.items() if stored.get(seq) != n}
    assert not missing, f"{len(missing)} of {len(acknowledged)} acknowledged rows lost"
    assert n_background > 0

    # the lock died with the process: the service restarts on the same file and numbering goes on
    store = MeasurementStore(db)
    try:
        store.start()
        assert store.add_measurement(result(0)) > max(acknowledged)
    finally:
        store.close()


def test_retention_deletes_old_rows_at_start_and_while_running(open_store, tmp_path):
    now = datetime.now(UTC)
    store = open_store(retention_days=None)
    for n in range(5):
        store.add_measurement(result(n, t_wall=now - timedelta(days=40, minutes=n)))
    for n in range(5, 8):
        store.add_measurement(result(n, t_wall=now - timedelta(days=1, minutes=n)))
    store.close()
    assert store.count() == 8

    store = open_store(retention_days=30.0, maintenance_interval_s=0.2)
    store.close()
    assert sorted(r["result"]["seq"] for r in store.measurements()) == [5, 6, 7]
    assert store.stats()["retention_deleted"] == 5

    store = open_store(retention_days=30.0, maintenance_interval_s=0.2)
    seq = store.add_measurement(result(8, t_wall=now - timedelta(days=31)))
    assert store.wait_written(seq, timeout_s=5.0)
    deadline = time.monotonic() + 5.0
    while store.count() != 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert store.count() == 3


def test_garbage_file_gives_a_clear_storage_error(tmp_path):
    db = tmp_path / "m.db"
    db.write_bytes(np.random.default_rng(5).integers(0, 256, 8192, dtype=np.uint8).tobytes())
    with pytest.raises(StorageError, match="is not a SQLite database") as e:
        MeasurementStore(db)
    assert str(db) in str(e.value) and "move it aside" in str(e.value)
    MeasurementStore(tmp_path / "fresh.db").close()  # the lock of the failed open was released

    other = tmp_path / "other.db"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE invoices (id INTEGER)")
    with pytest.raises(StorageError, match="not posecell's"):
        MeasurementStore(other)


def test_newer_schema_and_second_writer_are_refused(open_store, tmp_path):
    store = open_store()
    with pytest.raises(StorageError, match="already open"):
        MeasurementStore(tmp_path / "m.db")
    store.close()
    with sqlite3.connect(tmp_path / "m.db") as conn:
        conn.execute(f"PRAGMA user_version={SCHEMA_VERSION + 1}")
    with pytest.raises(StorageError, match="newer"):
        MeasurementStore(tmp_path / "m.db")


def test_full_queue_raises_store_full_and_counts_it(open_store):
    store = open_store(start=False, max_queue=3)
    seqs = [store.add_measurement(result(n)) for n in range(3)]
    with pytest.raises(StoreFull):
        store.add_measurement(result(3))
    assert store.stats()["dropped"] == 1 and store.stats()["queued"] == 3
    store.start()
    assert store.wait_written(seqs[-1], timeout_s=5.0)
    assert store.count() == 3


def test_close_is_idempotent_and_later_writes_are_refused(open_store):
    store = open_store()
    store.add_measurement(result(0))
    store.close()
    store.close()
    assert store.count() == 1
    with pytest.raises(StorageError, match="closed"):
        store.add_measurement(result(1))
    with pytest.raises(StorageError, match="closed"):
        store.start()


class _SmallDisk(MeasurementStore):
    """A store whose database may not grow beyond max_pages: SQLite's real 'database or disk is full'."""

    max_pages = 0

    def _write_batch(self, conn, batch, own_events):
        if self.max_pages:
            conn.execute(f"PRAGMA max_page_count={self.max_pages}")
        super()._write_batch(conn, batch, own_events)


def test_disk_full_is_recorded_and_the_writer_recovers(open_store, tmp_path):
    store = open_store(cls=_SmallDisk, start=False, flush_interval_s=0.0)
    with sqlite3.connect(tmp_path / "m.db") as conn:
        store.max_pages = conn.execute("PRAGMA page_count").fetchone()[0] + 4
    store.start()
    acknowledged = []
    for n in range(40):
        seq = store.add_measurement(result(n, n_targets=40))  # ~3 kB a row
        if not store.wait_written(seq, timeout_s=0.5):
            break
        acknowledged.append(seq)
    else:
        pytest.fail("the page limit never filled the database")
    assert "full" in store.stats()["last_error"]
    assert store.stats()["queued"] >= 1

    store.max_pages = 1_000_000  # space is freed
    assert store.wait_written(seq, timeout_s=5.0)
    store.close()
    assert {r["id"] for r in store.measurements()} == {*acknowledged, seq}
    kinds = [e["kind"] for e in store.events(oldest_first=True)]
    assert kinds == ["storage_error", "storage_recovered"]


def test_a_write_lock_held_by_another_connection_degrades_health_until_it_is_released(open_store, tmp_path):
    store = open_store(flush_interval_s=0.0)
    assert store.health() == ("ok", "") and store.stats()["state"] == "ok"
    other = sqlite3.connect(tmp_path / "m.db", isolation_level=None)
    other.execute("BEGIN IMMEDIATE")  # an operator's sqlite3 shell in the middle of a transaction
    try:
        seq = store.add_measurement(result(1))
        assert not store.wait_written(seq, timeout_s=1.5)
        state, why = store.health()
        assert state == "degraded" and "locked" in why and "retried" in why
        assert store.stats()["state"] == "degraded"
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert store.wait_written(seq, timeout_s=5.0)  # kept queued, written once the lock is gone
    assert store.health() == ("ok", "")
    assert [r["result"]["seq"] for r in store.measurements()] == [1]


def test_a_batch_is_inserted_by_one_statement_of_many_rows():
    import sqlite3

    from service.store.rows import INSERT_EVENT, insert_rows_sql

    sql = insert_rows_sql(INSERT_EVENT, 3)
    assert sql.count("(?, ?, ?, ?, ?)") == 3 and sql.count("INSERT") == 1
    conn = sqlite3.connect(":memory:")
    conn.execute("CREATE TABLE events (t_wall, level, kind, message, details)")
    rows = [("t", "info", f"k{i}", "m", None) for i in range(3)]
    conn.execute(sql, [v for r in rows for v in r])
    assert conn.execute("SELECT kind FROM events ORDER BY rowid").fetchall() == [("k0",), ("k1",), ("k2",)]
