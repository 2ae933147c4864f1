"""The OPC UA server with a real asyncua client: the newest result's variables, ``Measure`` with the
user ``posecell`` and the API token, and what an anonymous client may not do."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Iterator
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto import cert_gen
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

from service.core.results import Reason
from service.plant.opcua import FAULT_CODES, OpcUaServer
from service.settings import load_settings
from tests.api.conftest import LiveServer, free_port, run_server

pytestmark = pytest.mark.slow  # a real service with its OPC UA server in this module

TOKEN = "test-token"
NS = "urn:posecell"


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = load_settings(
        None,
        state_dir=str(tmp_path_factory.mktemp("state")),
        server__port=free_port(),
        server__token=TOKEN,
        cameras=[{"frame_rate_hz": 15.0}],
        opcua={"endpoint": f"opc.tcp://127.0.0.1:{free_port()}", "update_rate_hz": 20.0},
    )
    for server in run_server(settings):
        server.wait_for(
            lambda h: h["status"] == "ok" and h.get("opcua", {}).get("state") == "running",
            what="the cell measuring and the OPC UA server running",
        )
        yield server


def _run(coro: Any) -> Any:
    return asyncio.run(asyncio.wait_for(coro, 30))


async def _client(live: LiveServer, user: str | None = None, password: str | None = None) -> Client:
    client = Client(live.settings.opcua.endpoint, timeout=10)
    if user is not None:
        client.set_user(user)
        client.set_password(password or "")
    await client.connect()
    return client


async def _node(client: Client, path: str) -> Any:
    ns = await client.get_namespace_index(NS)
    return client.get_node(ua.NodeId(f"Posecell.{path}", ns))


def test_an_anonymous_client_reads_the_deviation_of_the_newest_result(live: LiveServer):
    async def read() -> tuple[dict[int, tuple[float, float]], dict[str, Any]]:
        client = await _client(live)
        try:
            names = ("ResultSeq", "DeviationPosition_mm", "DeviationAngle_deg", "ResultOk", "T_base_flange_measured")
            nodes = [await _node(client, f"Cameras.cam0.{n}") for n in names]
            cell = [await _node(client, n) for n in ("Ready", "Busy", "Fault", "FaultCode", "VisionState")]
            seen: dict[int, tuple[float, float]] = {}
            via_http: dict[int, tuple[float, float]] = {}
            with live.client(auth=False) as http:
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and not (seen.keys() & via_http.keys()):
                    seq, dev, ang, ok, T = await client.read_values(nodes)
                    if ok:  # a frame that failed (a loaded machine) has NaN deviations: compare the next
                        assert len(T) == 16 and all(math.isfinite(v) for v in T)
                        seen[seq] = (dev, ang)
                    d = http.get("/poses/latest").json()
                    via_http[d["seq"]] = (d["deviation"]["position_mm"], d["deviation"]["angle_deg"])
                    await asyncio.sleep(0.01)
            # the handshake follows /health: a camera that stalled a moment on a loaded machine shows
            # as Fault 1 until it recovers, so read it once the cell is healthy
            live.wait_for(lambda h: h.get("status") == "ok", timeout_s=30, what="the cell healthy")
            deadline = time.monotonic() + 5
            while True:
                values = await client.read_values(cell)
                states = dict(zip(("Ready", "Busy", "Fault", "FaultCode", "VisionState"), values))
                if states["Ready"] or time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.1)
            return {s: seen[s] for s in seen.keys() & via_http.keys()} | {-1: via_http}, states
        finally:
            await client.disconnect()

    common, states = _run(read())
    via_http = common.pop(-1)
    assert common, "the OPC UA server and /poses/latest never showed the same result within 10 s"
    for seq, (dev, ang) in common.items():
        # JSON rounds to 4 (mm) and 5 (deg) decimals; OPC UA carries the doubles
        assert dev == pytest.approx(via_http[seq][0], abs=1e-4) and dev > 0
        assert ang == pytest.approx(via_http[seq][1], abs=1e-5)
    assert states == {"Ready": True, "Busy": False, "Fault": False, "FaultCode": 0, "VisionState": "Operational"}


def test_measure_with_the_user_posecell_and_the_token_returns_a_stored_result(live: LiveServer):
    async def measure() -> tuple[list[Any], int, bool]:
        client = await _client(live, "posecell", TOKEN)
        try:
            before = await (await _node(client, "Cameras.cam0.ResultSeq")).read_value()
            cell = client.get_node(ua.NodeId("Posecell", await client.get_namespace_index(NS)))
            ns = await client.get_namespace_index(NS)
            out = await cell.call_method(f"{ns}:Measure", ua.Variant("cam0", ua.VariantType.String), 2.0)
            valid = await (await _node(client, "ResultValid")).read_value()
            return out, before, valid
        finally:
            await client.disconnect()

    out, seq_before, valid = _run(measure())
    ok, reason, message, seq, measurement_id, dev, ang, T, t_exposure = out
    assert ok and reason == "" and message == "", (reason, message)
    assert seq > seq_before, "the result of a frame exposed after the call"
    assert measurement_id >= 1 and dev > 0 and math.isfinite(ang) and len(T) == 16
    assert valid, "ResultValid after a good measurement"
    # the same row as the REST API's history
    with live.client() as http:
        rows = http.get("/measurements", params={"limit": 50}).json()
    row_ids = [r["id"] for r in rows["measurements"]]
    assert measurement_id in row_ids, row_ids[:5]


def test_an_anonymous_client_may_not_call_measure_nor_write(live: LiveServer):
    async def attempt() -> None:
        client = await _client(live)
        try:
            ns = await client.get_namespace_index(NS)
            cell = client.get_node(ua.NodeId("Posecell", ns))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await cell.call_method(f"{ns}:Measure", "cam0", 2.0)
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await (await _node(client, "Ready")).write_value(False)
        finally:
            await client.disconnect()

    _run(attempt())


def test_the_password_never_crosses_in_clear_and_an_encrypted_channel_is_offered(live: LiveServer, tmp_path):
    key = live.settings.resolved_state_dir() / "opcua" / "server-key.pem"
    assert key.exists() and key.stat().st_mode & 0o077 == 0, "the server's key is for its owner only"

    async def check() -> tuple[list[Any], Any]:
        client = Client(live.settings.opcua.endpoint, timeout=10)
        endpoints = await client.connect_and_get_server_endpoints()
        # a client of its own certificate, on the SignAndEncrypt endpoint, as the user posecell
        client_key, client_cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"
        await cert_gen.setup_self_signed_certificate(
            client_key,
            client_cert,
            "urn:test:plc",
            "localhost",
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "plc"},
        )
        secure = Client(live.settings.opcua.endpoint, timeout=10)
        secure.application_uri = "urn:test:plc"
        await secure.set_security(
            SecurityPolicyBasic256Sha256, str(client_cert), str(client_key), mode=ua.MessageSecurityMode.SignAndEncrypt
        )
        secure.set_user("posecell")
        secure.set_password(TOKEN)
        await secure.connect()
        try:
            ready = await (await _node(secure, "Ready")).read_value()
        finally:
            await secure.disconnect()
        return endpoints, ready

    endpoints, ready = _run(check())
    modes = {e.SecurityMode for e in endpoints}
    assert modes == {ua.MessageSecurityMode.None_, ua.MessageSecurityMode.SignAndEncrypt}
    plain = next(e for e in endpoints if e.SecurityMode == ua.MessageSecurityMode.None_)
    user_token = next(t for t in plain.UserIdentityTokens if t.TokenType == ua.UserTokenType.UserName)
    assert user_token.SecurityPolicyUri == SecurityPolicyBasic256Sha256.URI, "the password is encrypted"
    assert ready is True


def test_a_wrong_password_is_refused_at_connection(live: LiveServer):
    async def attempt() -> None:
        with pytest.raises(ua.UaError):
            client = await _client(live, "posecell", "not-the-token")
            await client.disconnect()

    _run(attempt())


def test_start_and_stop_an_accuracy_test_like_post_tests(live: LiveServer):
    async def scenario() -> tuple[list[Any], list[Any], list[Any], list[Any]]:
        client = await _client(live, "posecell", TOKEN)
        anonymous = await _client(live)
        try:
            ns = await client.get_namespace_index(NS)
            cell, cell_anon = (c.get_node(ua.NodeId("Posecell", ns)) for c in (client, anonymous))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await cell_anon.call_method(f"{ns}:StartTest", "circle", '{"mode": "record"}')
            started = await cell.call_method(f"{ns}:StartTest", "circle", '{"mode": "record"}')
            again = await cell.call_method(f"{ns}:StartTest", "table1", "")
            bad = await cell.call_method(f"{ns}:StartTest", "circle", "{not json")
            await asyncio.sleep(1.0)
            stopped = await cell.call_method(f"{ns}:StopTest", ua.Variant(started[3], ua.VariantType.Int64))
            return started, again, bad, stopped
        finally:
            await client.disconnect()
            await anonymous.disconnect()

    started, again, bad, stopped = _run(scenario())
    ok, reason, _, test_id, status = started
    assert ok and reason == "" and test_id >= 1 and status in ("queued", "running"), started
    assert again[:2] == [False, "busy"] and "running" in again[2], again
    assert bad[:2] == [False, "bad_input"] and bad[3] == -1, bad
    assert stopped[0] is True and stopped[3] not in ("queued", "running"), stopped
    with live.client() as http:
        assert http.get(f"/tests/{test_id}").json()["status"] == stopped[3]


def test_the_plc_starts_and_stops_a_recording_like_post_recordings(live: LiveServer):
    async def scenario() -> tuple[list[Any], ...]:
        client = await _client(live, "posecell", TOKEN)
        anonymous = await _client(live)
        try:
            ns = await client.get_namespace_index(NS)
            cell, cell_anon = (c.get_node(ua.NodeId("Posecell", ns)) for c in (client, anonymous))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await cell_anon.call_method(f"{ns}:StartRecording", "")
            started = await cell.call_method(f"{ns}:StartRecording", '{"max_frames": 1000, "label": "from the PLC"}')
            again = await cell.call_method(f"{ns}:StartRecording", "")
            bad = await cell.call_method(f"{ns}:StartRecording", '{"frames": 3}')
            await asyncio.sleep(1.0)
            stopped = await cell.call_method(f"{ns}:StopRecording", started[3])
            unknown = await cell.call_method(f"{ns}:StopRecording", "20990101-000000")
            return started, again, bad, stopped, unknown
        finally:
            await client.disconnect()
            await anonymous.disconnect()

    started, again, bad, stopped, unknown = _run(scenario())
    ok, reason, _, rec_id, state = started
    assert ok and reason == "" and rec_id and state == "recording", started
    assert again[:2] == [False, "busy"] and "being recorded already" in again[2], again
    assert bad[:2] == [False, "bad_input"] and "unknown parameter 'frames'" in bad[2], bad
    assert stopped[0] is True and stopped[3] == "stopped", stopped
    assert unknown[:2] == [False, "not_found"], unknown
    with live.client() as http:
        rec = http.get(f"/recordings/{rec_id}").json()
    assert rec["state"] == "stopped" and rec["label"] == "from the PLC" and rec["cameras"]["cam0"]["written"] >= 3


def test_an_unplugged_camera_is_a_fault_with_its_code_and_measure_says_why(live: LiveServer):
    async def read_fault(client: Client) -> tuple[bool, int, str, str]:
        names = ("Fault", "FaultCode", "FaultMessage", "Cameras.cam0.CameraState")
        return tuple(await client.read_values([await _node(client, n) for n in names]))  # type: ignore[return-value]

    async def scenario() -> None:
        client = await _client(live, "posecell", TOKEN)
        try:
            with live.client() as http:
                http.post("/sim/faults", json={"device": "camera", "action": "unplug"}).raise_for_status()
                try:
                    deadline = time.monotonic() + 10
                    while not (await read_fault(client))[0] and time.monotonic() < deadline:
                        await asyncio.sleep(0.05)
                    fault, code, message, state = await read_fault(client)
                    assert fault and code == FAULT_CODES[Reason.camera_disconnected] and "cam0" in message, message
                    assert state != "ok"
                    ns = await client.get_namespace_index(NS)
                    cell = client.get_node(ua.NodeId("Posecell", ns))
                    out = await cell.call_method(f"{ns}:Measure", "cam0", 2.0)
                    assert out[0] is False and out[1] == "camera_disconnected" and out[4] == -1, out[:5]
                    assert await (await _node(client, "ResultValid")).read_value() is False
                finally:
                    http.post("/sim/faults", json={"device": "camera", "action": "plug"}).raise_for_status()
                deadline = time.monotonic() + 15
                while (await read_fault(client))[0] and time.monotonic() < deadline:
                    await asyncio.sleep(0.05)
                assert (await read_fault(client))[:2] == (False, 0)
        finally:
            await client.disconnect()

    _run(scenario())


def test_a_taken_port_is_reported_and_the_cell_measures_on(live: LiveServer):
    second = OpcUaServer(live.settings.opcua, live.worker, TOKEN, lambda: live.worker.health())
    second.start()
    try:
        deadline = time.monotonic() + 20
        while second.stats()["state"] != "failed" and time.monotonic() < deadline:
            time.sleep(0.05)
        stats = second.stats()
        assert stats["state"] == "failed" and live.settings.opcua.endpoint in stats["last_error"], stats
    finally:
        second.stop()
    with live.client() as http:
        h = http.get("/health").json()
    assert h["status"] == "ok" and h["opcua"]["state"] == "running"
