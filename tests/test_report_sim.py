"""``posecell report sim``: an accuracy test run by a live service over HTTP, its report written."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from service.cli import main as cli
from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server

pytestmark = pytest.mark.slow  # a live service that moves the simulated arm


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("state")),
        server__port=free_port(),
        server__token="sim-token",
        cameras=[{"frame_rate_hz": 15.0}],
    )
    yield from run_server(settings)


def test_a_table1_test_in_the_simulated_cell_is_reported_with_its_truth(live: LiveServer, tmp_path, capsys):
    out = tmp_path / "t1"
    params = json.dumps({"positions": 2, "frames_per_stop": 2})
    argv = ["report", "sim", "table1", "--url", live.url, "--token", live.token, "--params", params, "-o", str(out)]
    assert cli.main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["status"] == "done" and printed["kind"] == "table1"
    stored = json.loads((out / "test.json").read_text())
    assert stored["id"] == printed["id"] and stored["details"] == printed["details"]
    report = json.loads((out / "report.json").read_text())
    assert {"report.md", "report.html", "table1.svg", "table1.png"} <= {p.name for p in out.iterdir()}
    # the same arm position visited twice: the differences are the measurement's, within a few σ
    assert len(report["rows"]) == 2
    for row in report["rows"]:
        for c in "xyz":
            assert abs(row[f"d{c}_mm"]) < 5 * row[f"sigma_{c}_mm"] + 1e-3, row


def test_the_service_refusing_the_parameters_is_one_sentence(live: LiveServer, tmp_path, capsys):
    argv = ["report", "sim", "circle", "--url", live.url, "--token", live.token, "--params", '{"radius_mm": -1}']
    assert cli.main([*argv, "-o", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "radius_mm" in err and "422" in err


def test_params_that_are_not_a_json_object_are_refused(tmp_path, capsys):
    assert cli.main(["report", "sim", "circle", "--params", "[1, 2]", "-o", str(tmp_path)]) == 2
    assert "JSON object" in capsys.readouterr().err
