"""The running service measures with the centre estimator its [processing] names, changed at run time."""

from __future__ import annotations

from tests.api.conftest import live_settings, run_server


def test_the_service_switches_to_centroids_at_run_time(tmp_path):
    settings = live_settings(tmp_path, cameras=[{"frame_rate_hz": 15.0}])
    for server in run_server(settings):
        health = server.wait_for(lambda h: h["processing"]["ok"] >= 5, 120.0, "poses with edge centres")
        assert health["processing"]["measurement"]["cam0"]["centre"] == "edge"  # the default
        with server.client() as c:
            r = c.put("/config", json={"processing": {"centre": "centroid"}})
            assert r.status_code == 200, r.text
            assert c.put("/config", json={"processing": {"centre": "median"}}).status_code == 422
            before = c.get("/health").json()["processing"]
        after = server.wait_for(lambda h: h["processing"]["ok"] >= before["ok"] + 10, 60.0, "poses with centroids")[
            "processing"
        ]
        assert after["measurement"]["cam0"]["centre"] == "centroid"
        assert after["failed"] - before["failed"] <= 2, (before, after)
