"""The dashboard's accuracy-tests panel and calibration cards in a real headless Chromium against the simulated cell.

A user picks a test, types its parameters, starts it (refused without the API token, with the
service's reason), watches its progress, and reads the finished test's report in the page; runs
the hand-eye calibration (proposals visited with the simulated arm, samples recorded, solved and
applied) and the robot calibration (planned, run, saved, verified) from their cards.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server
from tests.e2e.test_dashboard import Page, _chromium

pytestmark = pytest.mark.skipif(_chromium() is None, reason="Chromium is not installed (Debian package 'chromium')")

TOKEN = "tests-panel-token"


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("tests-panel-state")),
        server__port=free_port(),
        server__token=TOKEN,
        cameras=[{"frame_rate_hz": 15.0}],
    )
    servers = run_server(settings)
    server = next(servers)
    try:
        server.wait_for(
            lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="a running cell"
        )
        yield server
    finally:
        servers.close()


@pytest.fixture(scope="module")
def page(cell: LiveServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Page]:
    tmp = tmp_path_factory.mktemp("chromium-tests")
    p = Page(str(_chromium()), tmp / "profile", tmp / "chromium.log")
    try:
        p.goto(f"{cell.url}/")
        p.wait("document.querySelector('#tests-table tbody').textContent.includes('no tests yet')", "the empty list")
        yield p
    finally:
        p.close()


def _choose(page: Page, selector: str, value: str) -> None:
    page.js(
        f"(() => {{ const e = document.querySelector({json.dumps(selector)}); e.value = {json.dumps(value)};"
        " e.dispatchEvent(new Event('change')); })()"
    )


def test_a_table1_test_runs_from_the_panel_with_progress_and_its_report(page: Page, cell: LiveServer) -> None:
    _choose(page, "#test-kind", "table1")
    assert json.loads(page.js("document.getElementById('test-params').value")) == {"positions": 6}
    page.type("#test-params", '{"positions": 2, "dwell_s": 0.1}')
    page.type("#token", "")
    page.click("#test-start")
    page.wait("document.getElementById('test-failure').dataset.reason === 'unauthorized'", "the refusal")
    assert "Bearer" in page.text("#test-failure")  # the service's own sentence

    page.type("#token", TOKEN)
    page.click("#test-start")
    page.wait("document.getElementById('test-failure').hidden", "the refusal to clear")
    page.wait("document.getElementById('test-active').dataset.state === 'running'", "the test to run", 10)
    # progress is visible while it runs: the bar moves off 0 and the sentence names the stop
    page.wait("document.getElementById('test-progress').value > 0", "progress above 0", 60)
    shown = page.text("#test-progress-text")
    assert "stop" in shown and "samples" in shown, shown
    page.wait("document.getElementById('test-active').dataset.state === 'done'", "the test to finish", 120)

    test_id = int(page.js("document.getElementById('test-active').dataset.id"))
    with cell.client() as c:
        t = c.get(f"/tests/{test_id}").json()
        report = c.get(f"/tests/{test_id}/report.json").json()
    assert t["status"] == "done" and t["kind"] == "table1" and t["params"]["positions"] == 2
    row = page.js(f"""(() => {{ const r = document.querySelector('#tests-table tr[data-id="{test_id}"]');
        return [r.dataset.status, [...r.querySelectorAll('a')].map(a => a.textContent)]; }})()""")
    assert row == ["done", ["show", "JSON", "CSV"]]
    # the finished test's report is shown in the page, with its table of the two positions
    page.wait(
        "document.getElementById('test-report').contentDocument?.querySelectorAll('table').length > 0",
        "the report in its frame",
        15,
    )
    frame_text = page.js("document.getElementById('test-report').contentDocument.body.textContent")
    assert all(r["position"] in frame_text for r in report["rows"])
    assert len(report["rows"]) == 2
    page.js("0")
    assert page.exceptions == []
    urls = page.js("performance.getEntriesByType('resource').map(e => e.name)")
    assert [u for u in urls if not u.startswith((cell.url + "/", "blob:", "data:"))] == []


@pytest.mark.slow  # ~30 s: 14 poses visited and measured, the solve, 4 poses re-visited
def test_the_robot_model_card_plans_runs_saves_and_verifies_a_calibration(page: Page, cell: LiveServer) -> None:
    page.type("#token", TOKEN)
    page.wait("document.getElementById('rc-plan-text').textContent.startsWith('No session')", "the empty card")
    page.type("#rc-poses", "12")
    page.type("#rc-holdout", "2")
    page.click("#rc-plan")
    page.wait("document.getElementById('rc-active').dataset.state === 'planned'", "the plan", 60)
    with cell.client() as c:
        planned = c.get("/calibration/robot/session").json()
    assert planned["n_poses"] == 12 and planned["n_holdout"] == 2
    assert f"condition {planned['observability']['condition']}" in page.text("#rc-plan-text")
    assert page.js("document.getElementById('rc-save').disabled")  # nothing solved yet

    page.click("#rc-run")
    page.wait("document.getElementById('rc-active').dataset.state === 'running'", "the run", 10)
    page.wait("document.getElementById('rc-progress').value > 0", "progress above 0", 30)
    assert "pose" in page.text("#rc-progress-text")
    # the devices card says who moves the arm (one workflow at a time)
    facts = "document.querySelector('#robot-card .device-facts').textContent"
    page.wait(f"{facts}.includes('moved by the robot calibration session')", "the arm's owner shown", 10)
    page.wait("document.getElementById('rc-active').dataset.state === 'solved'", "the solve", 150)
    with cell.client() as c:
        result = c.get("/calibration/robot/session").json()["result"]
    before, after = result["holdout"]["before"], result["holdout"]["after"]
    shown = page.text("#rc-result")
    assert f"{before['position_mean_mm']:.3f} mm → {after['position_mean_mm']:.4f} mm mean" in shown, shown

    page.click("#rc-save")
    with cell.client() as c:
        page.wait("document.getElementById('rc-stored').textContent.includes('version')", "the stored model", 15)
        version = c.get("/calibration").json()["robot"]["version"]
    page.wait(f"document.getElementById('rc-stored').textContent.includes('version {version} ')", "its version", 10)

    page.click("#rc-verify")
    page.wait("['ok', 'drifted'].includes(document.getElementById('rc-verify-text').dataset.verdict)", "the check", 60)
    verdict = page.js("document.getElementById('rc-verify-text').dataset.verdict")
    assert page.text("#rc-verify-text").startswith(
        f"Verification of model version {version}: {verdict} — drift at most"
    )

    page.click("#rc-discard")
    page.wait("document.getElementById('rc-plan-text').textContent.startsWith('No session')", "the discarded session")
    assert page.js("document.getElementById('rc-failure').hidden")
    assert page.exceptions == []


@pytest.mark.slow  # ~20 s: six robot moves of 1-4 s each and a solve in the solver process
def test_the_hand_eye_card_visits_the_proposals_records_and_applies_the_solution(page: Page, cell: LiveServer) -> None:
    page.type("#token", TOKEN)
    page.wait("document.getElementById('he-state').textContent.startsWith('No session')", "the empty card")
    with cell.client() as c:
        version_before = c.get("/calibration").json()["handeye"]["version"]
    page.type("#he-poses", "6")
    page.click("#he-start")
    page.wait("document.querySelectorAll('#he-table tbody tr').length === 6", "the six proposals", 30)
    with cell.client() as c:
        proposals = c.get("/calibration/handeye/session").json()["proposals"]
    first = page.js("[...document.querySelectorAll('#he-table tbody tr')[0].cells].map(td => td.textContent)")
    assert first[1] == ", ".join(f"{v:.1f}" for v in proposals[0]["xyz_mm"]), first
    assert page.js("document.getElementById('he-solve').disabled")  # no samples yet

    page.click("#he-visit")
    page.wait("document.getElementById('he-state').textContent.startsWith('visiting proposal')", "the visits", 10)
    page.wait("!document.getElementById('he-solve').disabled", "the visits to end", 90)
    with cell.client() as c:
        n_samples = c.get("/calibration/handeye/session").json()["n_samples"]
    recorded = page.js("document.querySelectorAll('#he-table tbody tr[data-recorded=\"true\"]').length")
    assert n_samples >= 3 and recorded == n_samples, (n_samples, recorded)
    assert f"{n_samples} samples recorded" in page.text("#he-state")

    page.click("#he-solve")
    page.wait("!document.getElementById('he-result').hidden", "the solution", 60)
    with cell.client() as c:
        handeye = c.get("/calibration").json()["handeye"]
    assert handeye["version"] != version_before
    assert page.text("#he-result").startswith(f"Applied as hand-eye version {handeye['version']} (")

    page.click("#he-discard")
    page.wait("document.getElementById('he-state').textContent.startsWith('No session')", "the discarded session")
    assert page.exceptions == []


def _click_until(page: Page, selector: str, done: str, what: str, tries: int = 3) -> None:
    """Click, and again if the table was redrawn under the pointer (it refreshes every second)."""
    for attempt in range(tries):
        page.click(selector)
        try:
            page.wait(done, what, 5)
            return
        except AssertionError:
            if attempt == tries - 1:
                shown = page.js(
                    "[document.getElementById('rec-failure').textContent,"
                    " document.querySelector('#rec-table tbody').innerHTML]"
                )
                raise AssertionError(f"{what}: {shown}") from None


def test_a_recording_starts_stops_and_is_deleted_from_its_card(page: Page, cell: LiveServer) -> None:
    page.type("#token", TOKEN)
    page.wait("document.querySelector('#rec-table tbody').textContent.includes('no recordings yet')", "the empty list")
    page.type("#rec-frames", "100000")  # ended by the Stop button
    page.type("#rec-label", "from the card")
    page.click("#rec-start")
    running = "document.querySelector('#rec-table tr[data-state=\"recording\"]')"
    page.wait(f"{running} !== null", "the recording in the table", 10)
    rec_id = page.js(f"{running}.dataset.id")
    row = f'#rec-table tr[data-id="{rec_id}"]'
    page.wait(f"Number(document.querySelector('{row} td:nth-child(4)').textContent) >= 3", "frames written", 20)
    _click_until(page, f"{row} button", f"document.querySelector('{row}')?.dataset.state === 'stopped'", "the stop")
    with cell.client() as c:
        rec = c.get(f"/recordings/{rec_id}").json()
    assert rec["state"] == "stopped" and rec["label"] == "from the card" and rec["request"]["max_frames"] == 100000
    written = rec["cameras"]["cam0"]["written"]
    assert written >= 3 and rec["robot_samples"] > 0
    page.wait(f"document.querySelector('{row} td:nth-child(4)').textContent === '{written}'", "the count shown", 10)
    assert page.text(f"{row} td:nth-child(2)") == "from the card"
    _click_until(page, f"{row} button", f"document.querySelector('{row}') === null", "the deletion")
    with cell.client() as c:
        assert c.get(f"/recordings/{rec_id}").status_code == 404
    assert page.exceptions == []
