"""What the service promises under faults, over real HTTP/WebSocket against the simulated cell.

- acknowledged (POST /measure 200) means committed and fsynced; a locked or failing database is a
  503 ``storage_unavailable`` and ``/health`` says why;
- a device outage is reported within 1 s, no pose is served as current during it, and the cell is
  back to ``ok`` with fresh poses within 3 s of the device's return (faults through ``/sim/faults``);
- a WebSocket client that stops reading is disconnected.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import sqlite3
import subprocess
import sys
import time

import pytest
from websockets.sync.client import connect

from service.settings import load_settings
from tests.api.conftest import free_port, run_server


def _wait_ok(live):
    return live.wait_for(
        lambda h: h["status"] == "ok" and h["processing"]["ok"] >= 3, timeout_s=180.0, what="a running cell"
    )


def _fault(live, device, action, **extra):
    with live.client() as c:
        r = c.post("/sim/faults", json={"device": device, "action": action, **extra})
    assert r.status_code == 200, r.text
    return r.json()


def _database(live):
    return live.settings.resolved_state_dir() / live.settings.storage.database


# ------------------------------------------------------------------ acknowledged = stored


def _hold_write_lock(path):
    """Another process holding SQLite's write lock (a backup, an operator's sqlite3 shell)."""
    code = (
        "import sqlite3, sys\n"
        f"c = sqlite3.connect({str(path)!r}, isolation_level=None)\n"
        "c.execute('BEGIN IMMEDIATE')\n"
        "print('locked', flush=True)\n"
        "sys.stdin.readline()\n"
    )
    p = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None and p.stdout.readline().strip() == "locked"
    return p


def test_a_measurement_is_not_acknowledged_while_another_process_holds_the_database_lock(live):
    _wait_ok(live)
    locker = _hold_write_lock(_database(live))
    try:
        with live.client() as c:
            t0 = time.monotonic()
            r = c.post("/measure", json={"timeout_s": 3})
            elapsed = time.monotonic() - t0
            body = r.json()
            assert r.status_code == 503, body
            assert body["ok"] is False and body["reason"] == "storage_unavailable"
            assert "not" in body["message"] and "database" in body["message"]
            assert elapsed < 5.0
            h = c.get("/health").json()
        assert h["status"] == "degraded" and h["ok"] is False
        assert h["storage"]["state"] == "degraded" and "locked" in h["storage"]["error"]
        assert any("storage" in p for p in h["problems"])
    finally:
        assert locker.stdin is not None
        locker.stdin.write("\n")
        locker.stdin.flush()
        locker.wait(timeout=10)
    live.wait_for(lambda h: h["storage"]["state"] == "ok", timeout_s=10.0, what="storage back")
    with live.client() as c:
        r = c.post("/measure", json={"timeout_s": 5})
    assert r.status_code == 200, r.text
    m = r.json()
    # acknowledged: the row is in the file, read by another connection, with the id the reply gave
    with sqlite3.connect(_database(live)) as db:
        row = db.execute("SELECT t_host_ns FROM measurements WHERE id = ?", (m["measurement_id"],)).fetchone()
    assert row is not None and row[0] == m["t_exposure_host_ns"]


# ------------------------------------------------------------------ device outages through /sim/faults


def test_fault_injection_needs_the_token_and_refuses_unknown_devices(live):
    with live.client(auth=False) as c:
        r = c.post("/sim/faults", json={"device": "camera", "action": "unplug"})
    assert r.status_code == 401 and r.json()["reason"] == "unauthorized"
    with live.client() as c:
        for bad in (
            {"device": "laser", "action": "unplug"},
            {"device": "camera", "action": "explode"},
            {"device": "camera", "action": "unplug", "camera": "nope"},
        ):
            r = c.post("/sim/faults", json=bad)
            assert 400 <= r.status_code < 500 and r.json()["ok"] is False, (bad, r.text)


def _ws_first_message(live, timeout_s=5.0):
    with connect(f"{live.ws_url}/ws/poses?targets=false", open_timeout=10) as ws:
        return json.loads(ws.recv(timeout=timeout_s))


# from plugging the camera back to a fresh pose: a reconnection within 1 s, the simulated camera's
# render child started, a full frame measured (0.7-0.8 s on the README's host; 3.0 s seen on a slow
# 2-core VM under the whole suite)
RECOVERY_S = 5.0


@pytest.mark.slow
def test_a_camera_outage_is_reported_within_a_second_and_no_pose_is_served_as_current(live):
    _wait_ok(live)
    t_unplug = time.monotonic()
    _fault(live, "camera", "unplug")
    try:
        h = live.wait_for(lambda h: h["cameras"]["cam0"]["state"] != "ok", timeout_s=5.0, what="outage seen")
        assert time.monotonic() - t_unplug < 1.0
        assert h["status"] == "degraded" and h["cameras"]["cam0"]["error"]
        time.sleep(0.5)  # longer than a few frame periods at 15 Hz
        with live.client() as c:
            r = c.get("/poses/latest")
        latest = r.json()
        assert r.status_code == 503 and latest["ok"] is False, latest
        assert latest["reason"] in ("camera_disconnected", "stale")
        first = _ws_first_message(live)
        assert first["ok"] is False and first["reason"] in ("camera_disconnected", "stale")
    finally:
        _fault(live, "camera", "plug")
    t_plug = time.monotonic()
    live.wait_for(lambda h: h["status"] == "ok", timeout_s=5.0, what="back to ok")
    with live.client() as c:
        while True:
            r = c.get("/poses/latest")
            if r.status_code == 200 and r.json()["ok"] and r.json()["stale"] is False:
                break
            assert time.monotonic() - t_plug < RECOVERY_S, r.text
            time.sleep(0.05)
    assert r.json()["age_s"] < 0.5
    assert time.monotonic() - t_plug < RECOVERY_S


@pytest.mark.slow
def test_a_camera_that_stops_delivering_frames_makes_the_newest_pose_stale(live):
    _wait_ok(live)
    _fault(live, "camera", "stall")
    try:
        # the frame in flight when the stall began still arrives; from then on, the newest result
        # ages and is no longer served as current after 5 frame periods (at least 0.5 s)
        deadline = time.monotonic() + 2.0
        with live.client() as c:
            while (r := c.get("/poses/latest")).status_code == 200:
                assert time.monotonic() < deadline, r.json()
                time.sleep(0.02)
        latest = r.json()
        assert r.status_code == 503 and latest["ok"] is False, latest
        # stale after 5 frame periods (at least 0.5 s), reported stalled after 10 (at least 1 s)
        if latest["reason"] == "stale":
            assert latest["stale"] is True and latest["age_s"] >= 0.5
            assert latest["T_field_camera"] is not None  # the old pose is shown, marked, for diagnosis
        else:
            assert latest["reason"] == "camera_disconnected" and latest["camera_state"] == "stalled", latest
        first = _ws_first_message(live)
        assert first["ok"] is False and (first["stale"] is True or first["camera_state"] == "stalled")
        h = live.wait_for(lambda h: h["cameras"]["cam0"]["state"] == "stalled", timeout_s=3.0, what="stall seen")
        assert h["status"] == "degraded"
    finally:
        _fault(live, "camera", "plug")
    live.wait_for(lambda h: h["status"] == "ok", timeout_s=5.0, what="back to ok")


@pytest.mark.slow
def test_garbled_frames_give_failures_not_poses(live):
    _wait_ok(live)
    _fault(live, "camera", "garble")
    try:
        time.sleep(0.3)
        with live.client() as c:
            r = c.post("/measure", json={"timeout_s": 5})
        m = r.json()
        assert r.status_code == 200 and m["ok"] is False and m["reason"] != "stale", m  # a measured failure
    finally:
        _fault(live, "camera", "plug")
    # a frame exposed after the request may have been rendered (garbled) before the plug: the
    # poses come back within a few frames
    deadline = time.monotonic() + 5.0
    with live.client() as c:
        while not c.post("/measure", json={"timeout_s": 5}).json()["ok"]:
            assert time.monotonic() < deadline, "no pose after the garbled frames ended"


@pytest.mark.slow
def test_a_robot_outage_is_reported_within_a_second_and_recovers_within_three(live):
    _wait_ok(live)
    t_unplug = time.monotonic()
    _fault(live, "robot", "unplug")
    try:
        h = live.wait_for(lambda h: h["robot"]["state"] != "ok", timeout_s=5.0, what="robot outage seen")
        assert time.monotonic() - t_unplug < 1.0 and h["status"] == "degraded"
        with live.client() as c:
            m = c.post("/measure", json={"timeout_s": 5}).json()
        # the camera pose is current; the flange part says why it is missing
        assert m["ok"] is True and m["deviation"] is None and m["flange_reason"] == "robot_disconnected"
        time.sleep(3.0)  # a long outage must not lengthen the recovery (reconnection back-off)
    finally:
        _fault(live, "robot", "plug")
    t_plug = time.monotonic()
    live.wait_for(lambda h: h["status"] == "ok", timeout_s=5.0, what="robot back")
    with live.client() as c:
        while True:
            m = c.get("/poses/latest").json()
            if m.get("ok") and m.get("deviation") is not None and not m["stale"]:
                break
            assert time.monotonic() - t_plug < 3.0, m
            time.sleep(0.05)


def test_every_result_carries_its_exposure_instant_on_the_wall_clock(live):
    _wait_ok(live)
    with live.client() as c:
        before = time.time_ns()
        m = c.post("/measure", json={"timeout_s": 5}).json()
        after = time.time_ns()
    assert before - 0.5e9 < m["t_exposure_unix_ns"] < after
    # the same instant as the monotonic stamp, on the other clock
    offset = time.time_ns() - time.monotonic_ns()
    assert abs((m["t_exposure_unix_ns"] - m["t_exposure_host_ns"]) - offset) < 5e6


def test_fault_injection_is_not_found_when_the_cell_is_not_simulated(tmp_path):
    settings = load_settings(
        None,
        state_dir=str(tmp_path),
        server__port=free_port(),
        server__token="t",
        cameras=[{"driver": "v4l2", "options": {"device": str(tmp_path / "no-such-video-device")}}],
        robot__driver="none",
    )
    assert not settings.uses_sim
    for live in run_server(settings):
        with live.client() as c:
            r = c.post("/sim/faults", json={"device": "camera", "action": "unplug"})
        assert r.status_code == 404 and r.json()["ok"] is False


# ------------------------------------------------------------------ a client that stops reading


def _raw_websocket(url_host, port, path):
    """A WebSocket handshake on a raw socket with a tiny receive buffer, then never a read."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((url_host, port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        (
            f"GET {path} HTTP/1.1\r\nHost: {url_host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert b" 101 " in head.split(b"\r\n")[0], head
    return s


def _read_until_closed(s, timeout_s):
    """Drain a raw socket until the server closes it; the seconds that took (fails after timeout_s)."""
    t0 = time.monotonic()
    s.settimeout(1.0)
    while time.monotonic() - t0 < timeout_s:
        try:
            if not s.recv(1 << 20):
                return time.monotonic() - t0
        except TimeoutError:
            continue
        except ConnectionResetError:
            return time.monotonic() - t0
    raise AssertionError(f"the server did not close the connection within {timeout_s} s")


@pytest.mark.slow
def test_a_websocket_client_that_stops_reading_is_disconnected(tmp_path):
    # while the socket buffers still take data, the unanswered keep-alive ping finds the client
    settings = load_settings(
        None,
        state_dir=str(tmp_path),
        server__port=free_port(),
        server__token="t",
        server__ws_ping_interval_s=1.0,
        server__ws_ping_timeout_s=1.5,
    )
    for live in run_server(settings):
        _wait_ok(live)
        hub = live.app.state.hub
        port = int(live.url.rsplit(":", 1)[1])
        with connect(f"{live.ws_url}/ws/poses?targets=false", open_timeout=10) as reader:
            s = _raw_websocket("127.0.0.1", port, "/ws/poses")  # full messages with targets, never read
            t_connected = time.monotonic()
            try:
                # ping after 1 s, no pong 1.5 s later: dropped within 4 s, with a margin for a loaded machine.
                # The reader keeps reading meanwhile: a backlog in front of its closing handshake would hold
                # the exit of the with-block for websockets' 10 s close timeout.
                registered = False
                while (n := hub.stats()["clients"]) != 1 or not registered:
                    registered |= n == 2
                    assert time.monotonic() - t_connected < 4.0, hub.stats()
                    reader.recv(timeout=5)
                for _ in range(5):
                    assert json.loads(reader.recv(timeout=5))["camera"] == "cam0"  # the other client is served
                assert hub.stats()["clients"] == 1
                _read_until_closed(s, timeout_s=20.0)
            finally:
                s.close()


def test_the_hub_disconnects_a_client_whose_send_does_not_complete():
    # once the socket buffers are full a send blocks: the hub gives up after its stall timeout
    import asyncio

    from api.ws import Hub, StalledClient

    class FullSocket:
        client = None

        async def send_text(self, text):
            await asyncio.Event().wait()  # never completes, like a peer that stopped reading

    async def scenario():
        hub = Hub(stall_timeout_s=0.2)
        client = hub.add(None, None)
        t0 = time.monotonic()
        with pytest.raises(StalledClient, match=r"read nothing for 0\.2 s"):
            await hub.send(FullSocket(), client, "{}")
        return time.monotonic() - t0, hub.stats()

    elapsed, stats = asyncio.run(scenario())
    assert 0.15 < elapsed < 1.0 and stats["stalled_disconnects"] == 1
