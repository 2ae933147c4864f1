"""The robot's accuracy tests end to end over HTTP in the simulated cell (``/tests``).

The simulated cell knows the truth: every measured frame carries the true camera pose, so the
true flange pose at the same exposure is known, and the cell's two kinematic models (the
controller's nominal one and the perturbed true arm) give the arm's kinematic error at any
commanded pose. The bounds below come from the σ the measurements themselves report:

- circle: a figure built from extremes of the radial profile (G, F, H) moves by at most twice
  the largest radial error of a point, so |measured - true| <= 2 * k * σ_point,max with
  σ_point,max the largest 3-D σ of a point's flange position and k = 4 (a point beyond 4 σ has
  a chance of 6e-5; a run has ~200 points);
- ISO 9283: AP is a mean over the cycles' stops, each a mean of frames: its σ per pose is the
  one the report states (``sigma_barycentre_mm``), and the test allows 4 of it.
"""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import numpy as np
import pytest

from service.core.geometry.frames import R_from_kuka_abc_deg, make_T
from service.settings import load_settings
from service.workflows.reports import circle_report, iso9283_report, table1_report
from tests.api.conftest import free_port, run_server

K_SIGMA = 4.0
# A stop is seen from one camera pose: its measured barycentre carries that view's bias, which no
# averaging of its frames removes (the simulated cell's pose error a view: 0.01-0.03 mm, `posecell
# bench speed`). At P3 it is 0.023-0.029 mm, 3.2-4.1 sigma of the frames' scatter alone (3.2 before the
# renders shaded each target with the light across it); the AP bound counts it, 1 sigma of 0.01 mm.
VIEW_BIAS_MM = 0.01


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    state = tmp_path_factory.mktemp("state-tests")
    settings = load_settings(
        None,
        state_dir=str(state),
        server__port=free_port(),
        server__token="t",
        cameras=[{"frame_rate_hz": 15.0}],
    )
    yield from run_server(settings)


def _ready(live):
    live.wait_for(lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 2, timeout_s=180.0, what="the cell")


def _wait_done(c, test_id, timeout_s):
    """Poll the test until it ends; the progress seen on the way (fraction, sentence)."""
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        t = c.get(f"/tests/{test_id}").json()
        seen.append((t["status"], t["progress"], t["progress_message"], t["n_samples"]))
        if t["status"] not in ("queued", "running"):
            return t, seen
        time.sleep(0.25)
    raise AssertionError(f"test {test_id} did not end within {timeout_s} s; last: {seen[-1]}")


def _csv(text):
    return list(csv.DictReader(io.StringIO(text)))


def test_requests_are_checked_before_anything_moves(cell):
    _ready(cell)
    with cell.client(auth=False) as anon:
        assert anon.post("/tests/circle", json={}).status_code == 401
        assert anon.get("/tests").status_code == 200  # reading needs no token, like the other GETs
    with cell.client() as c:
        r = c.post("/tests/circle", json={"radius_mm": -5})
        assert r.status_code == 422 and r.json()["reason"] == "bad_input" and "radius_mm" in r.json()["message"]
        r = c.post("/tests/iso9283", json={"cycles": 30, "speed": 3})
        assert r.status_code == 422 and "speed" in r.json()["message"]
        r = c.post("/tests/circle", json={"radius_mm": 900})  # the camera would lose the plate
        assert r.status_code == 422 and ("view" in r.json()["message"] or "reach" in r.json()["message"]), r.text
        assert c.post("/tests/pendulum", json={}).status_code == 422
        for path in ("/tests/999", "/tests/999/report.json", "/tests/999/report", "/tests/999/samples"):
            r = c.get(path)
            assert r.status_code == 404 and r.json()["reason"] == "not_found", path
        assert c.post("/tests/999/stop").status_code == 404


def test_recording_the_cells_own_circle_segments_it_from_the_reported_motion(cell):
    """Mode record, as with a real robot: the cell plays its own (counter-clockwise) circle program."""
    _ready(cell)
    radius = cell.worker.cell.cell.config.circle_radius_mm
    with cell.client() as c:
        r = c.post("/tests/circle", json={"mode": "record", "radius_mm": radius})
        assert r.status_code == 202, r.text
        test_id = r.json()["id"]
        assert r.json()["status"] in ("queued", "running")
        assert c.post("/tests/table1", json={}).status_code == 409  # one test at a time
        deadline = time.monotonic() + 30.0
        while (t := c.get(f"/tests/{test_id}").json())["n_samples"] < 16 and time.monotonic() < deadline:
            time.sleep(0.2)  # the frames come at the rate the machine measures them (here 3-15 Hz)
        assert t["status"] == "running" and t["n_samples"] >= 16 and "recording" in t["progress_message"]
        t = c.post(f"/tests/{test_id}/stop").json()
        assert t["status"] == "done", t
        report = c.get(f"/tests/{test_id}/report.json").json()
    assert report["G_ccw_mm"] is not None and report["G_cw_mm"] is None  # the program turns one way only
    assert report["conditions"]["n_ccw"] >= 12  # all but the ends of the recording
    with cell.client() as c:
        labels = [s["label"] for s in c.get(f"/tests/{test_id}/samples?format=json").json()["samples"]]
    assert labels[1:-1] == ["ccw"] * (len(labels) - 2)  # stored with the labels found
    truth = t["details"]["truth"]
    bound = 2 * K_SIGMA * t["details"]["sigma_point_max_mm"]
    assert abs(report["G_ccw_mm"] - truth["G_ccw_mm"]) < bound


@pytest.mark.slow  # ~17 s: the approach, one lap (6.3 s) each way at 150 mm/s, the analysis
def test_circle_program_gives_the_figures_of_the_arms_true_path(cell, tmp_path):
    _ready(cell)
    with cell.client() as c:
        r = c.post("/tests/circle", json={"radius_mm": 150, "speed_mm_s": 150, "laps": 1})
        assert r.status_code == 202, r.text
        test_id = r.json()["id"]
        t, seen = _wait_done(c, test_id, timeout_s=90)
        assert t["status"] == "done", t
        # progress was visible: fractions strictly between 0 and 1, rising, with sentences
        running = [(p, m) for s, p, m, _ in seen if s == "running" and 0 < p < 1]
        assert running and any("clockwise" in m for _, m in running)
        assert [p for p, _ in running] == sorted(p for p, _ in running)
        report = c.get(f"/tests/{test_id}/report.json").json()
        html = c.get(f"/tests/{test_id}/report")
        samples_csv = c.get(f"/tests/{test_id}/samples").text
        listed = c.get("/tests").json()["tests"]
    assert listed[0]["id"] == test_id and listed[0]["status"] == "done"
    assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
    d = t["details"]
    assert d["n_points"]["ccw"] >= 20 and d["n_points"]["cw"] >= 20
    truth = d["truth"]
    bound = 2 * K_SIGMA * d["sigma_point_max_mm"]
    for key in ("G_cw_mm", "G_ccw_mm", "G_bidirectional_mm", "H_mm", "F_max_mm", "F_min_mm"):
        assert report[key] is not None and truth[key] is not None, key
        assert abs(report[key] - truth[key]) < bound, (key, report[key], truth[key], bound)
    # the arm's own error is seen: the true path is not the nominal circle
    assert truth["G_bidirectional_mm"] > bound
    # `posecell report circle` on the exported samples gives the same figures
    path = tmp_path / "circle.csv"
    path.write_text(samples_csv)
    again = circle_report(path, 150.0, report["conditions"].get("centre_nominal_mm"))
    for key in ("G_cw_mm", "G_ccw_mm", "H_mm", "F_max_mm"):
        assert again[key] == pytest.approx(report[key], abs=1e-4), key


@pytest.mark.slow  # ~30 s: 2 cycles of the five poses, three frames at each stop
def test_iso9283_ap_of_the_simulated_arm_is_its_kinematic_error(cell, tmp_path):
    _ready(cell)
    sim = cell.worker.cell.cell
    with cell.client() as c:
        r = c.post("/tests/iso9283", json={"cycles": 2, "dwell_s": 0.1})
        assert r.status_code == 202, r.text
        t, _ = _wait_done(c, r.json()["id"], timeout_s=150)
        assert t["status"] == "done", t
        report = c.get(f"/tests/{t['id']}/report.json").json()
        rows = _csv(c.get(f"/tests/{t['id']}/samples").text)
    assert sorted(report["poses"]) == ["P1", "P2", "P3", "P4", "P5"]
    assert len(rows) == 10 and all(int(r["n_frames"]) == 3 for r in rows)
    for name, figures in report["poses"].items():
        row = next(r for r in rows if r["pose"] == name)
        abc = [float(row[k]) for k in ("a_cmd_deg", "b_cmd_deg", "c_cmd_deg")]
        T_cmd = make_T(R_from_kuka_abc_deg(abc), [float(row[k]) for k in ("x_cmd_mm", "y_cmd_mm", "z_cmd_mm")])
        # the known kinematic error there: the true arm at the joints the controller plans for the pose
        q = sim.nominal.ik(T_cmd, sim.q_home_rad)
        known = sim.true.fk(q)[:3, 3] - T_cmd[:3, 3]
        ap = np.array([figures["AP_x_mm"], figures["AP_y_mm"], figures["AP_z_mm"]])
        sigma = t["details"]["sigma_barycentre_mm"][name]
        bound = K_SIGMA * float(np.hypot(sigma, VIEW_BIAS_MM))
        assert np.linalg.norm(ap - known) < bound, (name, ap, known, bound)
        assert np.linalg.norm(known) > 10 * K_SIGMA * sigma  # the error measured is far above the noise
    # `posecell report iso9283` on the exported stops gives the same figures
    path = tmp_path / "iso.csv"
    path.write_text("\n".join([",".join(rows[0]), *[",".join(r.values()) for r in rows]]) + "\n")
    again = iso9283_report(path)
    assert again["poses"]["P1"]["AP_p_mm"] == pytest.approx(report["poses"]["P1"]["AP_p_mm"], abs=1e-4)


@pytest.mark.slow  # ~20 s: three positions forward and back
def test_table1_program_visits_forward_then_back(cell, tmp_path):
    _ready(cell)
    with cell.client() as c:
        r = c.post("/tests/table1", json={"positions": 3, "dwell_s": 0.1})
        assert r.status_code == 202, r.text
        t, _ = _wait_done(c, r.json()["id"], timeout_s=120)
        assert t["status"] == "done", t
        report = c.get(f"/tests/{t['id']}/report.json").json()
        csv_text = c.get(f"/tests/{t['id']}/samples").text
        kinds = [e["kind"] for e in c.get("/events", params={"limit": 10_000}).json()["events"]]
    # the exposure is held while the test runs (a step between visits moved a position by 4 sigma)
    assert "exposure_held" in kinds and "exposure_released" in kinds
    assert [row["position"] for row in report["rows"]] == ["1", "2", "3"]
    truth = {row["position"]: row for row in t["details"]["truth"]["rows"]}
    for row in report["rows"]:
        # the arm returns exactly in the simulation: what differs between the visits is the noise
        for k, s in (("dx_mm", "sigma_x_mm"), ("dy_mm", "sigma_y_mm"), ("dz_mm", "sigma_z_mm")):
            assert abs(row[k] - truth[row["position"]][k]) < K_SIGMA * row[s] + 1e-6, (row, k)
    path = Path(tmp_path / "t1.csv")
    path.write_text(csv_text)
    assert table1_report(path)["rows"][0]["dx_mm"] == pytest.approx(report["rows"][0]["dx_mm"], abs=1e-4)


def test_stop_cancels_a_program(cell):
    _ready(cell)
    with cell.client() as c:
        r = c.post("/tests/iso9283", json={"cycles": 30})
        assert r.status_code == 202, r.text
        test_id = r.json()["id"]
        time.sleep(1.0)
        t = c.post(f"/tests/{test_id}/stop").json()
        assert t["status"] == "cancelled"
        assert c.get(f"/tests/{test_id}/report.json").status_code == 409
        assert c.post(f"/tests/{test_id}/stop").status_code == 409  # not running any more
        r = c.post("/tests/table1", json={"positions": 2})  # the next one may start
        assert r.status_code == 202
        assert c.post(f"/tests/{r.json()['id']}/stop").json()["status"] == "cancelled"


@pytest.mark.slow  # two service starts on one state folder
def test_a_test_running_when_the_service_stops_is_interrupted_and_kept(tmp_path):
    def settings():
        return load_settings(
            None,
            state_dir=str(tmp_path),
            server__port=free_port(),
            server__token="t",
            cameras=[{"frame_rate_hz": 15.0}],
        )

    first = run_server(settings())
    live = next(first)
    _ready(live)
    with live.client() as c:
        test_id = c.post("/tests/circle", json={"mode": "record"}).json()["id"]
        deadline = time.monotonic() + 30.0
        while c.get(f"/tests/{test_id}").json()["n_samples"] < 3 and time.monotonic() < deadline:
            time.sleep(0.3)  # samples are committed about once a second
    first.close()  # the service stops (its lifespan's shutdown) while the test records
    second = run_server(settings())
    live = next(second)
    try:
        with live.client() as c:
            t = c.get(f"/tests/{test_id}").json()
            rows = c.get(f"/tests/{test_id}/samples?format=json").json()["samples"]
            assert c.post("/tests/circle", json={"mode": "record"}).status_code == 202  # nothing blocks a new one
    finally:
        second.close()
    assert t["status"] == "interrupted" and "stopped" in t["error"]
    assert t["n_samples"] >= 3 and len(rows) == t["n_samples"]
