"""The typed measurement: its wire form, its variants (frame, outage, stale) and its encoding once."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from service.core.measurement import Deviation, Flange, Measurement, RigPose, iso_wall
from service.core.results import Failure, PoseResult, Reason, TargetObservation

T_UNIX_NS = 1_764_000_000_123_456_789  # 2025-11-24T16:00:00.123Z


def _pose(sigma: np.ndarray | None = None) -> PoseResult:
    T = np.eye(4)
    T[:3, 3] = [10.123456789012, -20.0, 1500.0]
    targets = (
        TargetObservation("C1", (100.123456, 200.5), (0.01, -0.02), coded=True),
        TargetObservation("U7", (300.0, 400.0), (0.3, 0.4), coded=False, used=False),
    )
    return PoseResult(T, np.full(3, 0.01) if sigma is None else sigma, np.full(3, 0.001), 0.05, 0.051, targets)


def _frame(result, **kw) -> Measurement:
    return Measurement("cam0", result, T_UNIX_NS, t_exposure_host_ns=5_000_000_000, seq=42, **kw)


def test_a_pose_becomes_the_design_section_4_result_with_its_timing_and_flange():
    T_measured = np.eye(4)
    T_measured[:3, 3] = [400.0, 0.0, 300.0]
    flange = Flange(np.eye(4), T_measured, Deviation(0.5, 0.01, np.array([0.3, 0.4, 0.0])))
    m = _frame(_pose(), mode="roi", timings_ms={"detect": 1.23456}, flange=flange, exposure_source="device")
    d = json.loads(m.json)
    assert d["ok"] is True and d["camera"] == "cam0" and d["seq"] == 42 and d["mode"] == "roi"
    assert d["t_exposure_host_ns"] == 5_000_000_000 and d["t_exposure_unix_ns"] == T_UNIX_NS
    assert d["t_wall"] == "2025-11-24T16:00:00.123Z" == iso_wall(T_UNIX_NS)
    assert d["T_field_camera"][0][3] == 10.123456789  # rounded to what the pose resolves
    assert d["n_coded"] == 1 and d["n_uncoded"] == 0 and d["rejected"] == ["U7"]
    assert d["targets"][1] == {"id": "U7", "uv": [300.0, 400.0], "residual_px": [0.3, 0.4], "rejected": True}
    assert d["deviation"] == {"position_mm": 0.5, "angle_deg": 0.01, "vector_mm": [0.3, 0.4, 0.0]}
    assert d["T_base_flange_measured"][0][3] == 400.0 and "flange_reason" not in d
    assert d["timings_ms"] == {"detect": 1.235}
    assert m.n_targets == 1 and m.T_field_camera is not None and m.reason is None


def test_the_two_variants_are_encoded_once_and_differ_only_by_the_target_list():
    m = _frame(_pose())
    assert m.json is m.json  # cached: every WebSocket client gets the same text
    full, lite = json.loads(m.json), json.loads(m.json_without_targets)
    assert "targets" in full and "targets" not in lite
    assert {k: v for k, v in full.items() if k != "targets"} == lite


def test_a_missing_flange_part_says_why():
    m = _frame(_pose(), flange=Flange(None, None, None, Reason.not_calibrated, "no hand-eye calibration"))
    d = m.to_dict()
    assert d["T_base_flange"] is None and d["deviation"] is None
    assert d["flange_reason"] == "not_calibrated" and d["flange_message"] == "no hand-eye calibration"


def test_an_infinite_sigma_is_null_in_strict_json():
    m = _frame(_pose(sigma=np.array([0.01, np.inf, np.nan])))
    assert json.loads(m.json)["sigma_position_mm"] == [0.01, None, None]
    bad = _frame(Failure(Reason.degenerate_geometry, "flat", {"condition": math.inf, "values": [1.0, math.nan]}))
    d = json.loads(bad.json)
    assert d["condition"] is None and d["values"] == [1.0, None]


def test_an_outage_notice_has_no_exposure():
    m = Measurement("cam1", Failure(Reason.camera_disconnected, "unplugged"), time.time_ns(), camera_state="stalled")
    d = m.to_dict()
    assert m.is_outage and m.t_exposure_unix_ns is None
    assert d["ok"] is False and d["reason"] == "camera_disconnected" and d["camera_state"] == "stalled"
    assert "t_exposure_host_ns" not in d and "t_exposure_unix_ns" not in d and d["t_wall"].endswith("Z")


@pytest.mark.parametrize("result", [_pose(), Failure(Reason.too_few_targets, "3 targets")], ids=["pose", "failure"])
def test_a_stale_result_keeps_its_values_and_says_it_is_not_current(result):
    m = _frame(result)
    stale = m.as_stale(2.5, "the newest result of cam0 is 2.5 s old")
    d = stale.to_dict()
    assert not stale.ok and stale.reason is Reason.stale
    assert d["ok"] is False and d["reason"] == "stale" and d["stale"] is True and d["age_s"] == 2.5
    assert d["message"] == "the newest result of cam0 is 2.5 s old"
    if isinstance(result, Failure):
        assert d["measured_reason"] == "too_few_targets"
    else:
        assert d["T_field_camera"] == m.to_dict()["T_field_camera"] and "measured_reason" not in d
    assert m.ok is isinstance(result, PoseResult) and "stale" not in m.to_dict()  # the original is unchanged
    served = m.served(0.01).to_dict()
    assert served["stale"] is False and served["age_s"] == 0.01


def test_the_rig_pose_names_its_cameras_and_intersected_points():
    rig = RigPose(np.eye(4), np.full(3, 0.02), np.full(3, 0.002), 0.01, 0.04, 25, 5, 20)
    d = Measurement("rig", rig, T_UNIX_NS, 1, mode="intersection", cameras=("left", "right")).to_dict()
    assert d["cameras"] == ["left", "right"] and d["n_intersected"] == 25 and d["n_coded"] == 5
    assert d["rms_mm"] == 0.01 and "targets" not in d


def test_a_measurement_cannot_be_changed():
    m = _frame(_pose())
    with pytest.raises(AttributeError):
        m.camera = "other"  # type: ignore[misc]


def test_the_target_tables_json_is_the_text_of_its_list():
    import orjson

    from service.core.results import TargetTable

    table = TargetTable(
        ("1", 'odd "id"', "U7"),
        np.array([[10.123456, 20.0], [1e-9, -3.00005], [np.nan, 4.0]]),
        np.array([[0.01, -0.02], [np.inf, 0.0], [0.5, 0.25]]),
        np.array([True, True, False]),
        np.array([True, False, True]),
    )
    assert table.to_json() == orjson.dumps(table.to_list()).decode()
    parsed = orjson.loads(table.to_json())
    assert parsed[1]["rejected"] is True and "rejected" not in parsed[0]
    assert parsed[2]["uv"][0] is None and parsed[1]["residual_px"][0] is None  # no JSON for NaN, inf
    empty = TargetTable((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0, bool))
    assert empty.to_json() == "[]"


@pytest.mark.parametrize("with_covariance", [True, False])
def test_a_pose_and_its_target_table_cross_a_process_boundary_unchanged(rng, with_covariance):
    """The measurement process pickles every frame's result in its own compact form: what arrives
    is the same pose, precision and targets, with the targets' JSON made on the sending side."""
    import pickle

    from service.core.results import PoseResult, TargetTable

    n = 7
    table = TargetTable(
        tuple(f"T{k}" for k in range(n - 1)) + ('odd "id"',),
        rng.normal(500, 200, (n, 2)),
        rng.normal(0, 0.05, (n, 2)),
        rng.random(n) < 0.5,
        rng.random(n) < 0.8,
    )
    text = table.to_json()
    pose = PoseResult(
        rng.normal(size=(4, 4)),
        rng.random(3),
        rng.random(3),
        np.float64(0.021),
        0.034,
        table,
        n_iter=3,
        covariance=rng.normal(size=(6, 6)) if with_covariance else None,
    )
    back = pickle.loads(pickle.dumps(pose, protocol=pickle.HIGHEST_PROTOCOL))
    for name in ("T_field_camera", "sigma_position_mm", "sigma_rotation_deg"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pose, name))
    assert (back.covariance is None) == (not with_covariance)
    if with_covariance:
        np.testing.assert_array_equal(back.covariance, pose.covariance)
    assert (back.rms_px, back.sigma0_px, back.n_iter, back.ok) == (0.021, 0.034, 3, True)
    t = back.targets
    assert isinstance(t, TargetTable) and t.ids == table.ids
    for name in ("uv_px", "residual_px", "coded", "used"):
        np.testing.assert_array_equal(getattr(t, name), getattr(table, name))
    assert "_json" in t.__dict__ and t.to_json() == text  # sent encoded, not encoded again
    assert back.to_dict() == pose.to_dict()
    fresh = pickle.loads(pickle.dumps(TargetTable(table.ids, table.uv_px, table.residual_px, table.coded, table.used)))
    assert "_json" not in fresh.__dict__ and fresh.to_json() == text  # not encoded: encoded where needed
