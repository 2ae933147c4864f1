"""The calibration sessions' files: durable, read back whole, never half-read (real files)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.runtime.handeye_session import HandEyeSession, Sample, SessionError
from service.runtime.robot_calibration import RobotSession, StartParams
from service.runtime.robot_capture import RobotSample
from service.runtime.session_store import SessionStore, plain


def _T(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q * np.sign(np.linalg.det(q))
    T[:3, 3] = rng.normal(scale=500.0, size=3)
    return T


def _handeye(store: SessionStore | None = None) -> HandEyeSession:
    sample = Sample(
        T_base_flange=_T(1),
        T_field_camera=_T(2),
        sigma_position_mm=[0.011, 0.012, 0.031],
        sigma_rotation_deg=[0.001, 0.0012, 0.0004],
        rms_px=0.0231,
        n_targets=3,
        t_wall="2026-12-05T01:00:00.000000Z",
        camera="cam0",
        ids=["1", "2", "u7"],
        uv=np.array([[100.123456789, 200.5], [300.25, 400.0], [5.0, 6.0]]),
    )
    return HandEyeSession(camera="cam0", proposals=[_T(3), _T(4)], X_guess=_T(5), samples=[sample], store=store)


def test_a_hand_eye_session_reads_back_as_it_was_written(tmp_path):
    store = SessionStore(tmp_path / "sessions")
    s = _handeye(store)
    s.persist()
    back = HandEyeSession.restore(store.load("handeye"), store)
    assert back.restored and back.camera == "cam0" and back.created_wall == s.created_wall
    # floats survive JSON exactly (shortest repr): the restored samples solve as the originals would
    for a, b in zip(s.samples, back.samples, strict=True):
        assert np.array_equal(a.T_base_flange, b.T_base_flange) and np.array_equal(a.uv, b.uv)
        assert a.ids == b.ids and a.sigma_position_mm == b.sigma_position_mm and a.rms_px == b.rms_px
    assert all(np.array_equal(a, b) for a, b in zip(s.proposals, back.proposals, strict=True))
    assert back.summary()["samples"] == s.summary()["samples"]


def test_a_robot_session_reads_back_and_a_run_in_progress_comes_back_interrupted(tmp_path):
    store = SessionStore(tmp_path / "sessions")
    q = np.array([0.1, -1.2345678901234, 1.5, 0.0, 0.7, -0.3])
    sample = RobotSample(3, False, q, _T(6), _T(7), [0.01, 0.02, 0.03], [0.001, 0.002, 0.003], 2, "t")
    s = RobotSession(
        StartParams(n_poses=12, n_holdout=2),
        "cam0",
        "kr15",
        np.stack([_T(k) for k in range(14)]),
        np.zeros((14, 6)),
        {"condition": 47.5, "frozen": ["theta1"], "sigma": float("nan")},
        120,
        samples=[sample],
        status="running",
    )
    store.save("robot", s.to_state())
    back = RobotSession.restore(store.load("robot"))
    assert back.status == "interrupted" and "Run again to visit the poses not yet recorded" in back.message
    assert back.restored and back.params == s.params and back.n_candidates == 120
    assert np.array_equal(back.samples[0].q_rad, q)  # the joints as measured, not rounded degrees
    assert np.array_equal(back.T_base_flange, s.T_base_flange)
    assert back.observability["sigma"] is None  # NaN is not JSON: written as null
    s.status = "solved"
    store.save("robot", s.to_state())
    assert RobotSession.restore(store.load("robot")).status == "solved"


def test_a_file_that_cannot_be_read_is_set_aside_and_said(tmp_path):
    events = []
    store = SessionStore(tmp_path, lambda level, kind, message: events.append((level, kind, message)))
    (tmp_path / "handeye.json").write_text('{"schema": 1, "kind": "handeye", "state": {"camera"')  # cut short
    assert store.load("handeye") is None
    aside = list(tmp_path.glob("handeye.json.rejected-*"))
    assert len(aside) == 1 and aside[0].read_text().startswith('{"schema": 1')  # kept, not deleted
    assert events and events[0][:2] == ("error", "session_rejected") and "malformed JSON" in events[0][2]
    (tmp_path / "robot.json").write_text(json.dumps({"schema": 99, "state": {}}))
    assert store.load("robot") is None and "not a posecell session file" in events[-1][2]


def test_a_store_that_cannot_write_refuses_and_the_change_is_undone(tmp_path):
    blocked = tmp_path / "sessions"
    blocked.write_text("a file where the directory should be")  # mkdir fails as on a broken disk
    s = _handeye(SessionStore(blocked))
    with pytest.raises(SessionError) as e:
        s.remove(0)
    assert e.value.reason == "storage_unavailable" and e.value.message.startswith("the sample is not removed")
    assert len(s.samples) == 1  # not acknowledged, not done


def test_discard_removes_the_file_and_plain_makes_json(tmp_path):
    store = SessionStore(tmp_path)
    store.save("handeye", {"a": np.arange(3), "b": (np.float32(1.5), np.inf)})
    assert json.loads((tmp_path / "handeye.json").read_text())["state"] == {"a": [0, 1, 2], "b": [1.5, None]}
    store.discard("handeye")
    assert not (tmp_path / "handeye.json").exists() and store.load("handeye") is None
    assert plain({"x": [np.int64(2), float("-inf")]}) == {"x": [2, None]}
    memory = SessionStore(None)  # a worker without storage keeps sessions in memory
    memory.save("robot", {"x": 1})
    assert memory.load("robot") is None
