"""`posecell calibrate robot` on a simulated arm written to CSV, and its refusal of bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from service.core.robot.kinematics import kr15
from service.sim.robot import perturbed

POSECELL = Path(sys.executable).with_name("posecell")


def _write(path, q_rad, p_mm):
    lines = ["joint_1,joint_2,joint_3,joint_4,joint_5,joint_6,x_mm,y_mm,z_mm"]
    lines += [",".join(f"{v:.9f}" for v in (*np.degrees(q), *p)) for q, p in zip(q_rad, p_mm, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_calibrate_robot_recovers_the_simulated_arm(tmp_path):
    rng = np.random.default_rng(3)
    nominal, true = kr15(), perturbed(kr15(), rng)
    lo, hi = nominal.q_limits_rad[:, 0] * 0.6, nominal.q_limits_rad[:, 1] * 0.6
    q = rng.uniform(lo, hi, (120, 6))
    tool = np.array([0.0, 0.0, 50.0])
    p = np.array([T[:3, :3] @ tool + T[:3, 3] for T in true.fk(q)]) + rng.normal(0, 0.02, (120, 3))
    _write(tmp_path / "cal.csv", q[:100], p[:100])
    _write(tmp_path / "test.csv", q[100:], p[100:])
    r = subprocess.run(
        [
            str(POSECELL),
            "calibrate",
            "robot",
            "--robot",
            "kr15",
            "--samples",
            str(tmp_path / "cal.csv"),
            "--test",
            str(tmp_path / "test.csv"),
            "--tool-mm",
            *map(str, tool),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert 0.3 < out["test"]["nominal_mm"]["mean_mm"]  # the arm's errors, with the base fitted
    assert 0.005 < out["test"]["corrected_mm"]["mean_mm"] < 0.08  # down to the 0.02 mm noise


def test_calibrate_robot_refuses_a_file_without_joint_columns(tmp_path):
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    r = subprocess.run(
        [str(POSECELL), "calibrate", "robot", "--robot", "ur5", "--samples", str(tmp_path / "bad.csv")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "joint_1" in r.stderr and "Traceback" not in r.stderr
