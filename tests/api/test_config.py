"""``PUT /config`` on a cell of two simulated cameras: a new Settings swapped whole, all of a request or nothing."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from service.settings import RUNTIME_FILE, CameraConfig, load_settings
from tests.api.conftest import LiveServer, free_port, run_server

pytestmark = pytest.mark.slow  # a real server and two rendering cameras


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    cameras = [
        CameraConfig(name="cam0", frame_rate_hz=5.0),
        CameraConfig(name="cam1", frame_rate_hz=5.0, options={"seed": 7, "serial": "SIM-0002"}),
    ]
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("state-config")),
        server__port=free_port(),
        server__token="t",
        sim__program="hold",
        cameras=cameras,
    )
    yield from run_server(settings)


def _cameras_ok(live: LiveServer) -> None:
    # a camera not yet connected takes any value (it is applied when it connects): wait for both
    live.wait_for(
        lambda h: all(h["cameras"].get(n, {}).get("state") == "ok" for n in ("cam0", "cam1")),
        timeout_s=120.0,
        what="both cameras connected",
    )


def _state(live: LiveServer, c: Any) -> tuple[Any, ...]:
    """What a PUT may change: the API's answer, the saved file, the channels' and drivers' settings, the worker's."""
    path = live.settings.resolved_state_dir() / RUNTIME_FILE
    channels = live.worker.cameras
    return (
        c.get("/config").json(),
        path.read_bytes() if path.exists() else None,
        {n: ch.settings for n, ch in channels.items()},
        {n: ch.driver._settings for n, ch in channels.items()},  # the simulated camera's own
        live.worker.settings.model_dump(),
    )


def test_a_change_swaps_the_settings_and_a_reader_of_the_old_object_sees_the_old_values(two_cameras):
    live = two_cameras
    _cameras_ok(live)
    old = live.worker.settings
    with live.client() as c:
        r = c.put("/config", json={"cameras": {"cam1": {"exposure_us": 1500.0}}, "processing": {"min_targets": 7}})
        assert r.status_code == 200, r.text
        status = c.get("/status").json()["config"]
    new = live.worker.settings
    assert new is not old
    assert (old.cameras[1].exposure_us, old.processing.min_targets) == (2000.0, 6)  # never changed in place
    assert (new.cameras[1].exposure_us, new.processing.min_targets) == (1500.0, 7)
    assert new.cameras[0] is old.cameras[0]  # what the request did not name is the same object
    assert all(p.settings is new for p in live.worker.processors.values())
    assert live.worker.cameras["cam1"].driver._settings.exposure_us == 1500.0
    assert status["cameras"][1]["exposure_us"] == 1500.0 and status["processing"]["min_targets"] == 7
    with pytest.raises(ValueError, match="frozen"):
        new.processing.min_targets = 8  # type: ignore[misc]


def test_a_camera_refusing_leaves_every_camera_and_the_processing_as_they_were(two_cameras):
    live = two_cameras
    _cameras_ok(live)
    with live.client() as c:
        # a saved runtime file exists, so that "unchanged" means the same bytes, not "still absent"
        assert c.put("/config", json={"cameras": {"cam0": {"exposure_us": 2000.0}}}).status_code == 200
        before = _state(live, c)
        old = live.worker.settings
        patch = {
            "cameras": {"cam0": {"exposure_us": 1234.0}, "cam1": {"strobe": {"source": "Bogus"}}},
            "processing": {"min_targets": 8},
        }
        r = c.put("/config", json=patch)
        assert r.status_code == 409, r.text
        assert r.json()["reason"] == "unsupported" and "cam1" in r.json()["message"]
        assert "Bogus" in r.json()["message"] and "restoring" not in r.json()["message"]
        assert _state(live, c) == before  # cam0, reconfigured first, has its previous exposure again
        assert live.worker.settings.model_dump() == old.model_dump()
        # and the cell still takes a good change
        assert c.put("/config", json={"cameras": {"cam0": {"exposure_us": 1800.0}}}).status_code == 200
        assert live.worker.cameras["cam0"].driver._settings.exposure_us == 1800.0


def test_an_unknown_camera_or_a_bad_value_in_any_camera_changes_nothing(two_cameras):
    live = two_cameras
    _cameras_ok(live)
    with live.client() as c:
        before = _state(live, c)
        r = c.put("/config", json={"cameras": {"cam0": {"exposure_us": 1100.0}, "cam7": {"exposure_us": 900.0}}})
        assert r.status_code == 404 and "cam7" in r.json()["message"]
        r = c.put("/config", json={"cameras": {"cam0": {"exposure_us": 1100.0}, "cam1": {"gain_db": 500}}})
        assert r.status_code == 422 and "gain_db" in r.json()["message"]
        r = c.put("/config", json={"processing": {"min_area_px": 900, "max_area_px": 800}})
        assert r.status_code == 422 and "min_area_px 900 is larger than max_area_px 800" in r.json()["message"]
        assert _state(live, c) == before
