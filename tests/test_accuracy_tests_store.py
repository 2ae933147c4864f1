"""The accuracy tests' pieces without a server: the store's tables, the segmentation of a recording,
the refusals before a test starts, and a restart in the middle of a test."""

from __future__ import annotations

import sqlite3
from types import SimpleNamespace

import numpy as np
import pytest

from service.core.accuracy.segment import at_rest, circle_directions, group_positions, rest_runs
from service.core.results import Reason
from service.runtime.accuracy_plans import flange_sigma
from service.runtime.accuracy_test import AccuracyTests, TestError, label_recording
from service.store.measurements import MeasurementStore, StorageError
from service.store.rows import SCHEMA_VERSION
from service.store.tests_store import TestStore


@pytest.fixture
def db(tmp_path):
    path = tmp_path / "m.db"
    store = MeasurementStore(path)  # migrates the file: the tests' tables come with schema version 2
    store.start()
    yield path
    store.close()


def test_tests_tables_come_with_the_measurement_databases_migrations(db):
    with sqlite3.connect(db) as conn:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION >= 2
    assert {"measurements", "events", "tests", "test_samples"} <= tables


def test_store_refuses_a_database_the_measurement_store_has_not_migrated(tmp_path):
    sqlite3.connect(tmp_path / "old.db").close()
    with pytest.raises(StorageError, match="open the measurement store on it first"):
        TestStore(tmp_path / "old.db")


def test_store_keeps_a_test_its_samples_and_report_across_connections(db):
    store = TestStore(db)
    test_id = store.create("iso9283", "program", {"cycles": 2})
    samples = [{"t_exposure_unix_ns": 10 + k, "label": "P1", "visit": k, "stop": k, "x": [1.5, np.nan]} for k in (1, 2)]
    store.add_samples(test_id, samples)
    store.update(test_id, status="done", progress=1.0, report={"poses": {"P1": {"AP_p_mm": 1.25}}})
    store.close()
    again = TestStore(db)
    t = again.get(test_id)
    assert t is not None and t["status"] == "done" and t["finished"] is not None and t["n_samples"] == 2
    assert t["params"] == {"cycles": 2} and t["report"]["poses"]["P1"]["AP_p_mm"] == 1.25
    got = again.samples(test_id)
    assert [s["visit"] for s in got] == [1, 2] and got[0]["x"] == [1.5, None]  # NaN: null, strict JSON
    again.add_samples(test_id, samples[:1], replace=True)
    assert len(again.samples(test_id)) == 1 and again.get(test_id)["n_samples"] == 1
    assert again.recent()[0]["id"] == test_id and "report" not in again.recent()[0]
    with pytest.raises(ValueError, match="status"):
        again.update(test_id, status="finished")
    again.close()


class _Worker:
    """What the runner reads of the worker: enough to refuse, and to be restarted after."""

    def __init__(self, sim: bool, handeye: bool = True) -> None:
        self.processors = {"cam0": None}
        self.calibration = SimpleNamespace(handeye=object() if handeye else None)
        self.cell = SimpleNamespace(active=sim, standins=False)
        self.robot = SimpleNamespace() if not sim else SimpleNamespace(move_to=lambda *a: 0.0)
        self.events: list[str] = []

    def event(self, level: str, kind: str, message: str) -> None:
        self.events.append(kind)


def test_program_mode_is_refused_with_a_real_robot_and_without_a_hand_eye(db):
    store = TestStore(db)
    tests = AccuracyTests(_Worker(sim=False), store)
    with pytest.raises(TestError) as e:
        tests.start("circle", {"mode": "program"})
    assert e.value.reason is Reason.unsupported and "record" in e.value.message
    with pytest.raises(TestError) as e:
        AccuracyTests(_Worker(sim=True, handeye=False), store).start("table1", {})
    assert e.value.reason is Reason.not_calibrated
    with pytest.raises(TestError) as e:
        tests.start("circle", {"laps": 0})
    assert e.value.reason is Reason.bad_input and "laps" in e.value.message
    with pytest.raises(TestError) as e:
        tests.start("circle", {"camera": "cam9", "mode": "record"})
    assert e.value.reason is Reason.not_found
    assert store.recent() == []  # nothing was stored for a refused test
    store.close()


def test_a_test_running_at_a_restart_is_marked_interrupted(db):
    store = TestStore(db)
    running = store.create("circle", "record", {})
    store.update(running, status="running", progress=0.4)
    done = store.create("table1", "program", {})
    store.update(done, status="done")
    store.close()
    worker = _Worker(sim=True)
    tests = AccuracyTests(worker, TestStore(db))  # the service starting again
    t = tests.get(running)
    assert t["status"] == "interrupted" and "stopped" in t["error"] and t["finished"] is not None
    assert tests.get(done)["status"] == "done" and "test_interrupted" in worker.events
    with pytest.raises(TestError) as e:
        tests.stop(running)
    assert e.value.reason is Reason.not_solved
    tests.store.close()


# ---------------------------------------------------------------- segmenting a recording


def _stops_stream(rng, poses_mm, frames_at_rest=5, frames_moving=4, noise_mm=0.005):
    """Reported flange positions at 10 Hz: rest at each pose, then a straight move to the next."""
    t, p = [], []
    for a, b in zip(poses_mm, [*poses_mm[1:], poses_mm[0]], strict=True):
        for _ in range(frames_at_rest):
            p.append(a + rng.normal(0, noise_mm, 3))
        for s in np.linspace(0, 1, frames_moving + 2)[1:-1]:
            p.append(a + s * (b - a))
    t = np.arange(len(p)) * 0.1
    return t, np.array(p)


def test_rest_runs_find_each_stop_of_a_recording(rng):
    poses = [np.array(v, dtype=float) for v in ([0, 0, 0], [100, 0, 0], [0, 100, 50])]
    t, p = _stops_stream(rng, poses * 2)
    runs = rest_runs(at_rest(t, p, tol_mm=0.05), min_frames=3)
    assert len(runs) == 6
    centres = np.array([p[a:b].mean(axis=0) for a, b in runs])
    assert group_positions(centres, tol_mm=5.0) == [0, 1, 2, 0, 1, 2]
    assert np.allclose(centres[:3], poses, atol=0.01)


def test_circle_directions_follow_the_turn_seen_from_above(rng):
    phi = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    ring = np.stack([100 * np.cos(phi), 100 * np.sin(phi), np.full_like(phi, 800.0)], axis=1)
    p = np.vstack([ring, ring[::-1]]) + rng.normal(0, 0.01, (80, 3))
    d = circle_directions(p, np.ones(80, dtype=bool))
    assert d[0] is None and d[-1] is None
    assert d[1:39] == ["ccw"] * 38 and d[41:79] == ["cw"] * 38


def test_label_recording_names_iso9283_poses_by_first_visit(rng):
    poses = [np.array(v, dtype=float) for v in ([0, 0, 800], [80, 80, 720], [-80, -80, 880])]
    t, p = _stops_stream(rng, poses * 3)
    samples = [
        {"t_s": ti, "T_base_flange_reported": np.vstack([np.c_[np.eye(3), pi], [0, 0, 0, 1]]).tolist()}
        for ti, pi in zip(t, p, strict=True)
    ]
    label_recording("iso9283", samples, SimpleNamespace(frames_per_stop=3, pose_tol_mm=5.0))
    stops = {}
    for s in samples:
        if s.get("stop") is not None:
            stops.setdefault(s["stop"], (s["label"], s["visit"]))
    assert list(stops.values()) == [(f"P{k}", c) for c in (1, 2, 3) for k in (1, 2, 3)]


def test_flange_sigma_grows_with_the_lever_of_the_rotation():
    T_fc = np.eye(4)
    X = np.eye(4)
    X[:3, 3] = [0.0, 0.0, 100.0]  # the camera 100 mm along the flange's z: the flange 100 mm behind it
    sp, sr = flange_sigma(T_fc, [0.01, 0.01, 0.01], [0.001, 0.0, 0.0], X, np.eye(4))
    lever = np.radians(0.001) * 100.0  # a rotation about x moves a point 100 mm along z in y
    assert sp[1] == pytest.approx(np.hypot(0.01, lever)) and sp[0] == pytest.approx(0.01)
    assert sr.tolist() == pytest.approx([0.001, 0.0, 0.0])


def test_flange_sigma_with_the_resections_covariance_is_the_scatter_of_the_flange():
    from service.core.geometry import so3
    from service.core.geometry.frames import inv_T

    rng = np.random.default_rng(5)
    T_fc = so3.T_from_rotvec([2.9, 0.3, -0.2], [150.0, -80.0, 1000.0])  # looking down at the field
    X = so3.T_from_rotvec([0.0, 0.0, 0.4], [30.0, -20.0, 120.0])
    Z = so3.T_from_rotvec([0.1, -0.05, 1.2], [900.0, 200.0, -300.0])
    # a camera's typical covariance: a sideways shift and a tilt explain the image alike: the
    # centre's error follows the rotation's about the target ~1000 mm ahead (dt = -[v]x dθ + noise)
    D = np.diag([1e-4, 1e-4, 3e-5]) ** 2
    K = -so3.skew(T_fc[:3, :3] @ np.array([0.0, 0.0, 1000.0]))
    N = np.diag([0.004, 0.004, 0.01]) ** 2
    cov = np.block([[D, D @ K.T], [K @ D, K @ D @ K.T + N]])
    draws = rng.multivariate_normal(np.zeros(6), cov, size=20_000)
    flange = []
    for d in draws:
        T = np.eye(4)
        T[:3, :3] = so3.R_from_rotvec(d[:3]) @ T_fc[:3, :3]  # the resection's convention: on the left
        T[:3, 3] = T_fc[:3, 3] + d[3:]
        flange.append((Z @ T @ inv_T(X))[:3, 3])
    scatter = np.std(np.array(flange), axis=0)
    sp, _ = flange_sigma(T_fc, np.sqrt(np.diag(cov)[3:]), np.degrees(np.sqrt(np.diag(cov)[:3])), X, Z, cov)
    assert sp == pytest.approx(scatter, rel=0.03)
    diag, _ = flange_sigma(T_fc, np.sqrt(np.diag(cov)[3:]), np.degrees(np.sqrt(np.diag(cov)[:3])), X, Z)
    assert np.max(np.abs(diag / scatter - 1)) > 0.1  # without the correlation it is another figure
