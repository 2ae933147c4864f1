"""`posecell compensate` on files: COMMANDS.csv and URScript, model files of both schema versions, refusals."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service.cli.main import main
from service.core.geometry.so3 import R_from_rotvec, rotvec_from_R
from service.core.robot.kinematics import ur5
from service.sim.robot import perturbed
from service.store.robot_model import read_robot_model, robot_model_to_json

POSECELL = Path(sys.executable).with_name("posecell")
HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
SEEDS = [f"seed_joint_{i}" for i in range(1, 7)]


@pytest.fixture
def files(tmp_path, rng):
    nominal = ur5()
    corrected = replace(perturbed(nominal, rng), beta_rad=np.radians([0, 0.02, -0.03, 0, 0, 0]))
    model = {"ok": True, **robot_model_to_json("ur5", corrected, "hayati"), "measured_point_on_flange_mm": [0, 0, 0]}
    (tmp_path / "m.json").write_text(json.dumps(model))
    q = np.radians(HOME_DEG) + rng.uniform(-0.4, 0.4, (8, 6))
    T = nominal.fk(q)
    rv = rotvec_from_R(T[:, :3, :3])
    lines = ["x_mm,y_mm,z_mm,rx,ry,rz," + ",".join(SEEDS)]
    for k in range(8):
        seed = ",".join(f"{v:.6f}" for v in np.degrees(q[k])) if k % 2 == 0 else ",,,,,"  # odd rows: no seed
        lines.append(",".join(f"{v:.9f}" for v in (*T[k, :3, 3], *rv[k])) + "," + seed)
    (tmp_path / "targets.csv").write_text("\n".join(lines) + "\n")
    return tmp_path, nominal, corrected, T


def _read_commands(path):
    rows = list(csv.DictReader(path.open()))
    q = np.radians([[float(r[f"joint_{i}"]) for i in range(1, 7)] for r in rows])
    p_cmd = np.array([[float(r[c]) for c in ("x_cmd_mm", "y_cmd_mm", "z_cmd_mm")] for r in rows])
    rv_cmd = np.array([[float(r[c]) for c in ("rx_cmd", "ry_cmd", "rz_cmd")] for r in rows])
    return rows, q, p_cmd, rv_cmd


def test_compensate_writes_commands_that_the_corrected_model_takes_to_the_targets(files, capsys):
    d, nominal, corrected, T_target = files
    rc = main(["compensate", "--model", str(d / "m.json"), "--targets", str(d / "targets.csv"), "-o", str(d / "c.csv")])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    rows, q, p_cmd, rv_cmd = _read_commands(d / "c.csv")
    assert [int(r["target"]) for r in rows] == list(range(1, 9)) and summary["n_targets"] == 8
    # the corrected model at the output joints is on the target (CSV rounding: 1e-9 deg)
    assert np.abs(corrected.fk(q)[:, :3, 3] - T_target[:, :3, 3]).max() < 1e-3
    # the Cartesian command is the nominal model's pose of those joints
    T_nom = nominal.fk(q)
    assert np.abs(T_nom[:, :3, 3] - p_cmd).max() < 1e-5
    assert np.abs(R_from_rotvec(rv_cmd) - T_nom[:, :3, :3]).max() < 1e-8
    corr = np.array([float(r["correction_mm"]) for r in rows])
    assert np.allclose(corr, np.linalg.norm(p_cmd - T_target[:, :3, 3], axis=1), atol=1e-5)
    assert 0.2 < summary["correction_mm"]["mean"] < 5.0


def test_compensate_writes_a_urscript_movej_program(files, capsys):
    d, _, corrected, T_target = files
    args = ["compensate", "--model", str(d / "m.json"), "--targets", str(d / "targets.csv")]
    assert main([*args, "-o", str(d / "c.csv")]) == 0
    assert main([*args, "-o", str(d / "p.script"), "--format", "urscript", "--a", "0.5", "--v", "0.25"]) == 0
    text = (d / "p.script").read_text().splitlines()
    assert text[0].startswith("# posecell compensate: 8 targets, corrected ur5 model (hayati, schema 2) from m.json")
    moves = [ln.strip() for ln in text if ln.strip().startswith("movej(")]
    assert len(moves) == 8 and all(m.split(")")[0].endswith("a=0.5, v=0.25") for m in moves)
    q_script = np.array([json.loads(m[len("movej(") :].split("]")[0] + "]") for m in moves])
    _, q_csv, _, _ = _read_commands(d / "c.csv")
    assert np.allclose(q_script, q_csv, atol=1e-8)
    assert text[-2:] == ["end", "posecell_compensated()"]


def test_compensate_reads_a_schema_1_classic_dh_model_file(files, capsys):
    d, nominal, _, T_target = files
    classic = perturbed(nominal, np.random.default_rng(5))
    v1 = {  # what `posecell calibrate robot` wrote before the schema keys
        "ok": True,
        "robot": "ur5",
        "model": {
            "a_mm": classic.a_mm.tolist(),
            "alpha_rad": classic.alpha_rad.tolist(),
            "d_mm": classic.d_mm.tolist(),
            "theta_offset_rad": classic.theta_offset_rad.tolist(),
            "T_base_j0": classic.T_base_j0.tolist(),
            "T_j6_flange": classic.T_j6_flange.tolist(),
        },
        "measured_point_on_flange_mm": [0.0, 0.0, 0.0],
    }
    (d / "v1.json").write_text(json.dumps(v1))
    m = read_robot_model(d / "v1.json")
    assert m.schema_version == 1 and m.parameterisation == "dh" and not np.any(m.corrected.beta_rad)
    rc = main(
        ["compensate", "--model", str(d / "v1.json"), "--targets", str(d / "targets.csv"), "-o", str(d / "c.csv")]
    )
    assert rc == 0
    _, q, _, _ = _read_commands(d / "c.csv")
    assert np.abs(classic.fk(q)[:, :3, 3] - T_target[:, :3, 3]).max() < 1e-3


def _refused(capsys, argv, output):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert not output.exists(), "a refused file must leave no output"
    return err


def test_compensate_refuses_an_unreachable_target_naming_its_row(files, capsys):
    d = files[0]
    lines = (d / "targets.csv").read_text().splitlines()
    vals = lines[3].split(",")
    vals[:3] = ["2500", "0", "400"]  # 2.5 m out: beyond the UR5's reach
    lines[3] = ",".join(vals)
    (d / "far.csv").write_text("\n".join(lines) + "\n")
    argv = ["compensate", "--model", str(d / "m.json"), "--targets", str(d / "far.csv"), "-o", str(d / "c.csv")]
    err = _refused(capsys, argv, d / "c.csv")
    assert "target 3 is out of reach of the corrected model: the nearest pose is " in err
    assert "Traceback" not in err


def test_compensate_refuses_a_target_far_from_its_seed(files, capsys):
    d = files[0]
    lines = (d / "targets.csv").read_text().splitlines()
    vals = lines[1].split(",")
    vals[6 + 4] = f"{float(vals[6 + 4]) + 50.0:.6f}"  # seed_joint_5 50 deg off
    lines[1] = ",".join(vals)
    (d / "seed.csv").write_text("\n".join(lines) + "\n")
    argv = ["compensate", "--model", str(d / "m.json"), "--targets", str(d / "seed.csv"), "-o", str(d / "c.csv")]
    err = _refused(capsys, [*argv, "--max-seed-distance-deg", "20"], d / "c.csv")
    assert "target 1 " in err and "deg from its seed (at most 20.0 deg allowed)" in err


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("x_mm,y_mm,z_mm,rx,ry\n1,2,3,0,0\n", "needs the columns x_mm, y_mm, z_mm, rx, ry, rz"),
        ("x_mm,y_mm,z_mm,rx,ry,rz,seed_joint_1\n1,2,3,0,0,0,5\n", "give all six or none"),
        ("x_mm,y_mm,z_mm,rx,ry,rz\n400,0,400,0,0,0\n400,abc,400,0,0,0\n", "target 2 has y_mm = 'abc'"),
        ("x_mm,y_mm,z_mm,rx,ry,rz\n", "no targets"),
    ],
    ids=["missing-rz", "partial-seeds", "not-a-number", "empty"],
)
def test_compensate_refuses_malformed_targets_with_a_sentence(files, capsys, text, expected):
    d = files[0]
    (d / "bad.csv").write_text(text)
    argv = ["compensate", "--model", str(d / "m.json"), "--targets", str(d / "bad.csv"), "-o", str(d / "c.csv")]
    assert expected in _refused(capsys, argv, d / "c.csv")


def test_compensate_refuses_a_model_file_of_an_unknown_schema_version(files, capsys):
    d = files[0]
    m = json.loads((d / "m.json").read_text())
    m["schema_version"] = 3
    (d / "m3.json").write_text(json.dumps(m))
    argv = ["compensate", "--model", str(d / "m3.json"), "--targets", str(d / "targets.csv"), "-o", str(d / "c.csv")]
    assert "schema_version 3 is not one this posecell reads" in _refused(capsys, argv, d / "c.csv")


def test_compensate_console_script_exits_2_on_an_unreachable_target(files):
    d = files[0]
    (d / "far.csv").write_text("x_mm,y_mm,z_mm,rx,ry,rz\n3000,0,0,0,0,0\n")
    r = subprocess.run(
        [str(POSECELL), "compensate", "--model", str(d / "m.json"), "--targets", str(d / "far.csv"), "-o", "c.csv"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=d,
    )
    assert r.returncode == 2 and "target 1 is out of reach of the corrected model" in r.stderr
    assert not (d / "c.csv").exists() and "Traceback" not in r.stderr
