"""Hostile values over real HTTP: refused with one 4xx body, and nothing of them persisted or applied.

Bodies are sent as raw JSON text because Python's ``json`` (and so Starlette's
``request.json()``) reads ``NaN``, ``Infinity`` and ``-Infinity``, which httpx's
``json=`` would refuse to send.
"""

from __future__ import annotations

import copy
import json
import time
from typing import Any

import pytest

from service.settings import RUNTIME_FILE, load_settings
from tests.api.conftest import free_port, run_server

JSON = {"Content-Type": "application/json"}


def _assert_bad_input(r: Any) -> None:
    assert r.status_code == 422, (r.status_code, r.text)
    body = r.json()
    assert set(body) == {"ok", "reason", "message"}, body
    assert body["ok"] is False and body["reason"] == "bad_input"
    assert isinstance(body["message"], str) and body["message"]


def _runtime_file(live: Any) -> bytes | None:
    path = live.settings.resolved_state_dir() / RUNTIME_FILE
    return path.read_bytes() if path.exists() else None


def _config_state(live: Any, c: Any) -> tuple[Any, ...]:
    channel = live.worker.cameras["cam0"]
    return c.get("/config").json(), _runtime_file(live), channel.settings, live.worker.settings.processing


@pytest.mark.parametrize(
    "text",
    [
        '{"cameras": {"cam0": {"exposure_us": Infinity}}}',
        '{"cameras": {"cam0": {"exposure_us": NaN}}}',
        '{"cameras": {"cam0": {"exposure_us": 1e300}}}',
        '{"cameras": {"cam0": {"gain_db": NaN}}}',
        '{"cameras": {"cam0": {"gain_db": -Infinity}}}',
        '{"cameras": {"cam0": {"gain_db": 500}}}',
        '{"cameras": {"cam0": {"frame_rate_hz": 1e-9}}}',
        '{"cameras": {"cam0": {"roi": [-1, 0, 64, 64]}}}',
        '{"cameras": {"cam0": {"roi": [0, 0, 0, 64]}}}',
        '{"cameras": {"cam0": {"roi": [0, 0, 70000, 64]}}}',
        '{"cameras": {"cam0": {"strobe": {"delay_us": 1e7}}}}',
        '{"cameras": {"cam0": {"strobe": {"duration_us": Infinity}}}}',
        '{"cameras": {"cam0": {"transport_latency_s": 5}}}',
        '{"processing": {"sigma_px": NaN}}',
        '{"processing": {"max_sigma0_px": 1e9}}',
        '{"processing": {"min_contrast_dn": 1e6}}',
        '{"processing": {"max_area_px": 1000000000000}}',
        '{"processing": {"min_targets": 100000000}}',
        '{"processing": {"max_area_px": 1%s}}' % ("0" * 400),  # an integer beyond any float
    ],
)
def test_config_refuses_non_finite_and_out_of_range_values_and_changes_nothing(live, text):
    with live.client() as c:
        # a saved runtime file exists, so that "unchanged" means the same bytes, not "still absent"
        assert c.put("/config", json={"cameras": {"cam0": {"exposure_us": 2000.0}}}).status_code == 200
        before = _config_state(live, c)
        r = c.put("/config", content=text, headers=JSON)
        _assert_bad_input(r)
        assert _config_state(live, c) == before
        assert c.get("/health").status_code == 200


def _calibration_state(live: Any, c: Any, kind: str) -> tuple[Any, ...]:
    return (
        c.get(f"/calibration/{kind}").json(),
        c.get(f"/calibration/{kind}/versions").json(),
        live.worker.calibration.generation,
    )


def _with(data: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    out = copy.deepcopy(data)
    node = out
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return out


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    ("kind", "path", "value"),
    [
        ("camera", ("c_mm",), 1e308),
        ("camera", ("c_mm",), NAN),
        ("camera", ("K1",), [1, 2]),
        ("camera", ("K1",), NAN),
        ("camera", ("K2",), 1e300),
        ("camera", ("width",), 1300.5),
        ("camera", ("width",), 10**9),
        ("camera", ("pixel_size_mm",), [0.0067, INF]),
        ("camera", ("comment",), NAN),  # readers ignore unknown keys, but they are stored: JSON has no NaN
        ("field", ("targets", 0, "code"), "seven"),
        ("field", ("targets", 0, "code"), 7.5),
        ("field", ("targets", 0, "diameter_mm"), [1]),
        ("field", ("targets", 0, "diameter_mm"), NAN),
        ("field", ("targets", 0, "diameter_mm"), 1e300),
        ("field", ("targets", 0, "xyz"), [1e300, 0.0, 0.0]),
        ("field", ("targets", 0, "code"), 10**400),
        ("handeye", ("T_flange_camera", 0, 3), 1e300),
        ("handeye", ("T_base_field", 0, 3), "12.5"),
    ],
)
def test_calibration_upload_refuses_bad_values_and_stores_nothing(live, kind, path, value):
    with live.client() as c:
        before = _calibration_state(live, c, kind)
        text = json.dumps(_with(before[0], path, value))  # NaN and Infinity as Python writes them
        r = c.put(f"/calibration/{kind}", content=text, headers=JSON)
        _assert_bad_input(r)
        assert _calibration_state(live, c, kind) == before


def test_calibration_upload_refuses_a_note_over_1000_characters(live):
    with live.client() as c:
        before = _calibration_state(live, c, "handeye")
        r = c.put("/calibration/handeye", json=before[0], params={"note": "x" * 1001})
        _assert_bad_input(r)
        assert "note" in r.json()["message"]
        assert _calibration_state(live, c, "handeye") == before


@pytest.mark.parametrize("u", ["NaN", "Infinity", "1e300"])
def test_self_calibration_refuses_non_finite_or_absurd_pixel_coordinates(live, u):
    with live.client() as c:
        before = _calibration_state(live, c, "camera")
        ids = [t["id"] for t in c.get("/calibration/field").json()["targets"][:6]]
        points = ", ".join(f'{{"id": "{i}", "uv": [{u}, 100.0]}}' for i in ids)
        images = ", ".join(f'{{"name": "im{k}", "points": [{points}]}}' for k in range(4))
        r = c.post(
            "/calibration/camera/solve", params={"apply": "true"}, content=f'{{"images": [{images}]}}', headers=JSON
        )
        _assert_bad_input(r)
        assert "uv" in r.json()["message"]
        assert _calibration_state(live, c, "camera") == before


@pytest.mark.parametrize(
    ("path", "params"),
    [
        ("/measurements", {"offset": 2**63}),
        ("/measurements", {"offset": 10**30}),
        ("/measurements", {"from": "2025-01-02T03:04:05"}),
        ("/measurements", {"to": "2025-01-02T03:04:05"}),
        ("/events", {"from": "2025-01-02T03:04:05"}),
        ("/events", {"to": "2025-01-02"}),
        ("/events", {"to": "9999-12-31T23:59:59-01:00"}),  # after 9999 in UTC
    ],
)
def test_history_refuses_huge_offsets_and_times_without_a_time_zone(live, path, params):
    with live.client() as c:
        r = c.get(path, params=params)
    _assert_bad_input(r)
    if ("from" in params or "to" in params) and "9999" not in str(params):
        assert "time zone" in r.json()["message"] and "Z" in r.json()["message"]


def test_history_accepts_times_with_a_time_zone_and_the_largest_offset(live):
    with live.client() as c:
        assert c.get("/measurements", params={"from": "2025-01-02T03:04:05Z", "offset": 10**9}).status_code == 200
        assert c.get("/events", params={"to": "2999-01-02T03:04:05+01:00"}).status_code == 200


def _number_schema(prop: dict[str, Any]) -> dict[str, Any]:
    """The numeric member of a property's schema (an optional field is anyOf [number, null])."""
    members = prop.get("anyOf", [prop])
    return next(m for m in members if m.get("type") in ("number", "integer"))


def test_openapi_shows_the_physical_ranges(live):
    with live.client() as c:
        spec = c.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    camera = schemas["CameraPatch"]["properties"]
    exposure = _number_schema(camera["exposure_us"])
    assert exposure["exclusiveMinimum"] == 0 and exposure["maximum"] == 10_000_000
    assert "µs" in camera["exposure_us"]["description"]
    gain = _number_schema(camera["gain_db"])
    assert gain["minimum"] == -20 and gain["maximum"] == 60
    rate = _number_schema(camera["frame_rate_hz"])
    assert rate["minimum"] == 0.1 and rate["maximum"] == 10_000
    sigma = _number_schema(schemas["ProcessingPatch"]["properties"]["sigma_px"])
    assert sigma["exclusiveMinimum"] == 0 and sigma["maximum"] == 10
    params = {p["name"]: p for p in spec["paths"]["/measurements"]["get"]["parameters"]}
    assert params["offset"]["schema"]["maximum"] == 10**9
    params = {p["name"]: p for p in spec["paths"]["/calibration/{kind}"]["put"]["parameters"]}
    assert params["note"]["schema"]["maxLength"] == 1000


def test_a_runtime_file_that_does_not_validate_is_set_aside_with_an_event_and_not_applied(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    bad = '{"cameras": [{"name": "cam0", "exposure_us": Infinity}], "processing": {}}\n'
    (state / RUNTIME_FILE).write_text(bad)
    settings = load_settings(None, state_dir=str(state), server__port=free_port(), server__token="test-token")
    server = run_server(settings)
    srv = next(server)
    try:
        with srv.client() as c:
            assert c.get("/config").json()["cameras"][0]["exposure_us"] == 2000.0  # the default
            deadline = time.monotonic() + 10.0
            events: list[dict[str, Any]] = []
            while time.monotonic() < deadline:
                events = [e for e in c.get("/events").json()["events"] if e["kind"] == "runtime_config_rejected"]
                if events:
                    break
                time.sleep(0.1)
    finally:
        server.close()
    assert len(events) == 1 and events[0]["level"] == "warning", events
    assert "exposure_us" in events[0]["message"]
    assert not (state / RUNTIME_FILE).exists()
    aside = list(state.glob(f"{RUNTIME_FILE}.rejected-*"))
    assert len(aside) == 1 and aside[0].read_text() == bad
    assert aside[0].name in events[0]["message"]
