"""A camera's defect map in the running service (``[[cameras]] defects``): patched in every frame, said in
/health; a map that does not fit the camera fails each frame with a sentence naming it."""

from __future__ import annotations

import json

import numpy as np
from websockets.sync.client import connect

from service.core.geometry.frames import pose_difference
from service.core.targets.defects import DefectMap
from service.store import formats
from tests.api.conftest import live_settings, run_server


def _map(path, width: int = 1300, height: int = 1030, n: int = 300) -> None:
    rng = np.random.default_rng(3)
    uv = np.unique(np.stack([rng.integers(0, width, n), rng.integers(0, height, n)], axis=1), axis=0)
    formats.write_defects(path, DefectMap(width, height, uv))


def test_the_service_patches_a_cameras_defects_and_says_so(tmp_path):
    _map(tmp_path / "defects.json")
    cameras = [{"frame_rate_hz": 15.0, "defects": str(tmp_path / "defects.json")}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        health = server.wait_for(lambda h: h["processing"]["ok"] >= 5, 120.0, "poses with the defect map")
        report = health["processing"]["measurement"]["cam0"]
        assert report["defects"] == {"file": str(tmp_path / "defects.json"), "pixels": 300, "dead": 0}, report
        with connect(f"{server.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
            for _ in range(3):
                msg = json.loads(ws.recv(timeout=10))
                assert msg["ok"], msg
                d_mm = pose_difference(np.array(msg["T_field_camera"]), np.array(msg["truth"]["T_field_camera"]))[0]
                assert d_mm < 0.5, d_mm


def test_a_defect_map_of_another_sensor_fails_each_frame_saying_why(tmp_path):
    _map(tmp_path / "defects.json", width=1000, height=800)
    cameras = [{"frame_rate_hz": 15.0, "defects": str(tmp_path / "defects.json")}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        with connect(f"{server.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
            msg = json.loads(ws.recv(timeout=30))
        assert not msg["ok"] and msg["reason"] == "bad_input", msg
        assert "camera cam0's defect map" in msg["message"] and "1000 x 800 image" in msg["message"], msg
        with server.client() as c:
            assert c.get("/health").json()["processing"]["ok"] == 0


def test_a_defect_map_is_set_at_run_time_and_one_that_cannot_be_read_is_refused(tmp_path):
    _map(tmp_path / "defects.json")
    for server in run_server(live_settings(tmp_path / "state", cameras=[{"frame_rate_hz": 15.0}])):
        with server.client() as c:
            before = c.get("/config").json()
            assert before["cameras"][0]["defects"] is None
            r = c.put("/config", json={"cameras": {"cam0": {"defects": str(tmp_path / "missing.json")}}})
            assert r.status_code == 422 and "missing.json" in r.json()["message"], r.text
            assert c.get("/config").json() == before  # refused: nothing changed
            r = c.put("/config", json={"cameras": {"cam0": {"defects": str(tmp_path / "defects.json")}}})
            assert r.status_code == 200 and r.json()["cameras"][0]["defects"] == str(tmp_path / "defects.json")
        health = server.wait_for(
            lambda h: (h["processing"]["measurement"]["cam0"]["defects"] or {}).get("pixels") == 300,
            60.0,
            "the map in use",
        )
        ok = health["processing"]["ok"]
        server.wait_for(lambda h: h["processing"]["ok"] >= ok + 3, 60.0, "poses with the map")
        with server.client() as c:
            assert c.put("/config", json={"cameras": {"cam0": {"defects": None}}}).status_code == 200
        server.wait_for(lambda h: h["processing"]["measurement"]["cam0"]["defects"] is None, 60.0, "no map")


def test_the_service_maps_its_cameras_hot_pixels_from_dark_frames_and_puts_the_light_back(tmp_path):
    """A simulated camera whose sensor has 0.05 % of its pixels hot: the strobe off for the frames, every
    hot pixel found and none else, the map in use and saved, the strobe on again and poses as before."""
    from service.sim.render import hot_pixel_indices

    cameras = [{"frame_rate_hz": 15.0, "options": {"hot_pixels": 5e-4, "seed": 3}}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        server.wait_for(lambda h: h["processing"]["ok"] >= 3, 120.0, "poses before")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"frames": 6})
            assert r.status_code == 200, r.text
            out = r.json()
            config = c.get("/config").json()["cameras"][0]
        expected = hot_pixel_indices(1030, 1300, 5e-4, 3)
        assert out["defects"] == expected.size and out["applied"] and out["strobe_restored"], out
        saved = formats.read_defects(out["file"])
        assert np.array_equal(np.sort(saved.flat), expected)  # every hot pixel, and nothing else
        assert config["defects"] == out["file"] and config["strobe"]["enabled"], config
        saved_config = json.loads((server.settings.resolved_state_dir() / "runtime-config.json").read_text())
        assert saved_config["cameras"][0]["defects"] == out["file"]
        health = server.wait_for(lambda h: h["processing"]["measurement"]["cam0"]["defects"] is not None, 30.0, "map")
        ok = health["processing"]["ok"]
        server.wait_for(lambda h: h["processing"]["ok"] >= ok + 3, 60.0, "poses again, the light back on")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"camera": "cam9"})
            assert r.status_code == 404 and "cam9" in r.json()["message"], r.text


def test_a_camera_without_a_strobe_is_asked_for_a_capped_lens(tmp_path):
    cameras = [{"frame_rate_hz": 15.0, "strobe": None}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        server.wait_for(lambda h: h["cameras"]["cam0"]["state"] == "ok", 60.0, "the camera")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"frames": 5})
        assert r.status_code == 409 and "light 'as_is'" in r.json()["message"], r.text


def test_a_map_whose_configuration_cannot_be_saved_is_not_put_in_use(tmp_path, monkeypatch):
    import api.routes.defects as route

    def full_disk(settings) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(route, "save_runtime_file", full_disk)
    for server in run_server(live_settings(tmp_path / "state", cameras=[{"frame_rate_hz": 15.0}])):
        server.wait_for(lambda h: h["cameras"]["cam0"]["state"] == "ok", 60.0, "the camera")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"frames": 5})
            assert r.status_code == 503 and "No space left on device" in r.json()["message"], r.text
            assert "not in use" in r.json()["message"]
            config = c.get("/config").json()["cameras"][0]
        assert config["defects"] is None and config["strobe"]["enabled"], config


def test_the_service_maps_dead_pixels_from_flat_frames_and_keeps_the_hot_ones(tmp_path):
    """A replayed recording of a white card before the lens under the ring light (flat frames, 600
    pixels dead), the camera's map of hot pixels in use: every dead pixel found and none else, the
    hot ones kept beside them, the new map in use; flat frames asked for with the light off refused."""
    import cv2

    rng = np.random.default_rng(5)
    n = 1030 * 1300
    dead = np.unique(rng.integers(0, n, 600))
    (tmp_path / "flat").mkdir()
    for k in range(6):
        f = rng.normal(140.0, 6.0, n)
        f[dead] = rng.uniform(0, 5, dead.size)
        cv2.imwrite(
            str(tmp_path / "flat" / f"{k:03d}.png"), np.clip(np.rint(f), 0, 255).astype(np.uint8).reshape(1030, 1300)
        )
    _map(tmp_path / "hot.json")
    hot = formats.read_defects(tmp_path / "hot.json")
    camera = {"driver": "replay", "frame_rate_hz": 15.0, "strobe": None, "options": {"source": str(tmp_path / "flat")}}
    cameras = [{**camera, "defects": str(tmp_path / "hot.json")}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        server.wait_for(lambda h: h["cameras"]["cam0"]["state"] == "ok", 60.0, "the camera")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"kind": "dead", "light": "off"})
            assert r.status_code == 422 and "light 'as_is'" in r.json()["message"], r.text
            r = c.post("/calibration/camera/defects", json={"kind": "dead", "frames": 5})
            assert r.status_code == 200, r.text
            out = r.json()
        saved = formats.read_defects(out["file"])
        assert np.array_equal(np.sort(saved.of_kind(dead=True).flat), dead)  # every dead pixel, and nothing else
        assert set(saved.of_kind(dead=False).flat.tolist()) == set(hot.flat.tolist()) - set(dead.tolist())
        assert out["kind"] == "dead" and out["found"] == dead.size and out["kept"] == len(hot), out
        assert (out["dead"], out["hot"]) == (dead.size, len(saved) - dead.size) and out["applied"], out
        health = server.wait_for(
            lambda h: (h["processing"]["measurement"]["cam0"]["defects"] or {}).get("file") == out["file"],
            30.0,
            "the new map in use",
        )
        assert health["processing"]["measurement"]["cam0"]["defects"]["dead"] == dead.size


def test_a_map_taken_of_a_cameras_window_is_kept_as_the_whole_sensors(tmp_path):
    """A camera delivering a window of its sensor (``roi``): the map the service takes of its frames is
    written as the whole sensor's, as the measurement crops it, and the poses go on with it."""
    roi = [200, 150, 800, 600]
    cameras = [{"frame_rate_hz": 15.0, "roi": roi, "options": {"hot_pixels": 5e-4, "seed": 3}}]
    for server in run_server(live_settings(tmp_path / "state", cameras=cameras)):
        server.wait_for(lambda h: h["processing"]["ok"] >= 3, 120.0, "poses of the window")
        with server.client() as c:
            r = c.post("/calibration/camera/defects", json={"frames": 5})
            assert r.status_code == 200, r.text
            out = r.json()
        saved = formats.read_defects(out["file"])
        assert (saved.width, saved.height) == (1300, 1030) and len(saved) == out["found"] > 100, out
        u, v = saved.uv.T
        assert u.min() >= 200 and u.max() < 1000 and v.min() >= 150 and v.max() < 750
        health = server.wait_for(
            lambda h: (h["processing"]["measurement"]["cam0"]["defects"] or {}).get("pixels") == len(saved),
            30.0,
            "the map in use",
        )
        ok = health["processing"]["ok"]
        server.wait_for(lambda h: h["processing"]["ok"] >= ok + 3, 60.0, "poses of the window with the map")
