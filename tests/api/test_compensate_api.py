"""`POST /compensate` over real HTTP: the commands, and 401/422 with a sentence for what it refuses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.core.geometry.so3 import rotvec_from_R
from service.core.robot.kinematics import ur5
from service.sim.robot import perturbed
from service.store.robot_model import robot_model_to_json

HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(11)
    nominal = ur5()
    corrected = replace(perturbed(nominal, rng), beta_rad=np.radians([0, 0.02, -0.03, 0, 0, 0]))
    q = np.radians(HOME_DEG) + rng.uniform(-0.3, 0.3, (5, 6))
    T = nominal.fk(q)
    rv = rotvec_from_R(T[:, :3, :3])
    targets = [
        dict(zip(("x_mm", "y_mm", "z_mm", "rx", "ry", "rz"), [*T[k, :3, 3], *rv[k]], strict=True)) for k in range(5)
    ]
    targets[0] |= {f"seed_joint_{i + 1}": float(v) for i, v in enumerate(np.degrees(q[0]))}
    model = {"ok": True, **robot_model_to_json("ur5", corrected, "hayati")}
    return corrected, nominal, T, targets, model


def test_compensate_answers_the_commands(live, case):
    corrected, nominal, T, targets, model = case
    with live.client() as c:
        r = c.post("/compensate", json={"targets": targets, "model": model})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["ok"] and body["robot"] == "ur5" and body["parameterisation"] == "hayati"
    rows = body["commands"]
    q = np.radians([[row[f"joint_{i}"] for i in range(1, 7)] for row in rows])
    assert np.abs(corrected.fk(q)[:, :3, 3] - T[:, :3, 3]).max() < 1e-3
    p_cmd = np.array([[row[k] for k in ("x_cmd_mm", "y_cmd_mm", "z_cmd_mm")] for row in rows])
    assert np.allclose(p_cmd, nominal.fk(q)[:, :3, 3], atol=1e-9)
    assert all(0.0 < row["correction_mm"] < 10.0 for row in rows)


def test_compensate_needs_the_token(live, case):
    _, _, _, targets, model = case
    with live.client(auth=False) as c:
        r = c.post("/compensate", json={"targets": targets, "model": model})
    assert r.status_code == 401 and r.json()["reason"] == "unauthorized"


def test_compensate_refuses_bad_requests_with_a_sentence(live, case):
    _, _, _, targets, model = case
    far = [dict(targets[0]), {**targets[1], "x_mm": 2500.0, "y_mm": 0.0, "z_mm": 400.0}]
    missing_rz = [{k: v for k, v in targets[1].items() if k != "rz"}]
    with live.client() as c:
        r = c.post("/compensate", json={"targets": targets})  # nothing stored in this server
        assert r.status_code == 409 and r.json()["reason"] == "not_calibrated", r.text
        assert r.json()["message"].startswith("no robot model is stored: run the robot calibration session")
        r = c.post("/compensate", json={"targets": far, "model": model})
        assert r.status_code == 422, r.text
        assert r.json()["message"].startswith("target 2 is out of reach of the corrected model: the nearest pose is")
        assert r.json()["rows"] == [2] and r.json()["reason"] == "bad_input"
        r = c.post("/compensate", json={"targets": missing_rz, "model": model})
        assert r.status_code == 422 and "rz" in r.json()["message"]
        r = c.post("/compensate", json={"targets": targets, "model": {**model, "robot": "ur3"}})
        assert r.status_code == 422 and "robot must name a known nominal model" in r.json()["message"]
        partial = [{**targets[1], "seed_joint_1": 5.0}]
        r = c.post("/compensate", json={"targets": partial, "model": model})
        assert r.status_code == 422 and "but not seed_joint_2" in r.json()["message"]


def test_the_shifts_check_answers_under_both_names_and_needs_a_stored_model(live):
    # runs before a model is stored (module order): both names refuse with the same sentence
    with live.client() as c:
        a = c.post("/calibration/robot/verify", json={})
        b = c.post("/tests/verify", json={})
    assert a.status_code == b.status_code == 409, (a.text, b.text)
    assert a.json()["reason"] == b.json()["reason"] == "not_calibrated" and a.json()["message"] == b.json()["message"]
    with live.client(auth=False) as c:
        assert c.post("/tests/verify", json={}).status_code == 401


def test_a_stored_robot_model_is_versioned_validated_and_used_when_the_body_has_none(live, case):
    corrected, _, T, targets, model = case
    with live.client() as c:
        assert c.get("/calibration/robot").status_code == 404
        r = c.put("/calibration/robot", json={**model, "model": {**model["model"], "a_mm": [0.0] * 5}})
        assert r.status_code == 422 and "model.a_mm must be a list of 6 numbers" in r.json()["message"]
        assert c.get("/calibration/robot/versions").json() == []  # nothing of the refused one stored
        v1 = c.put("/calibration/robot", json=model, params={"note": "first"}).json()["version"]
        other = {**model, "model": {**model["model"], "a_mm": (np.array(model["model"]["a_mm"]) + 5.0).tolist()}}
        v2 = c.put("/calibration/robot", json=other).json()["version"]
        assert v2 == v1 + 1 and c.get("/calibration/robot").json()["model"]["a_mm"] == other["model"]["a_mm"]
        assert c.get("/calibration").json()["robot"] == {"present": True, "version": v2, "source": "store"}
        v3 = c.post(f"/calibration/robot/rollback/{v1}").json()["version"]
        assert c.get("/calibration/robot").json()["model"]["a_mm"] == model["model"]["a_mm"]
        versions = c.get("/calibration/robot/versions").json()
        assert [v["version"] for v in versions] == [v1, v2, v3] and versions[-1]["current"]
        r = c.post("/compensate", json={"targets": targets})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["model_source"] == "stored" and body["model_version"] == v3
    q = np.radians([[row[f"joint_{i}"] for i in range(1, 7)] for row in body["commands"]])
    assert np.abs(corrected.fk(q)[:, :3, 3] - T[:, :3, 3]).max() < 1e-3  # the rolled-back (v1) model's joints
