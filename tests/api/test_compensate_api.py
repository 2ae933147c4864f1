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
        r = c.post("/compensate", json={"targets": targets})
        assert r.status_code == 422 and "send the corrected robot model" in r.json()["message"]
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
