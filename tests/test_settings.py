"""Configuration: the example file documents exactly the defaults; files, environment and bad values."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from service.settings import (
    RUNTIME_FILE,
    CameraConfig,
    ProcessingConfig,
    Settings,
    SettingsError,
    apply_runtime_file,
    load_settings,
    save_runtime_file,
    with_runtime_overrides,
)

EXAMPLE = Path(__file__).resolve().parents[1] / "deploy" / "posecell.example.toml"


def test_example_configuration_parses_to_exactly_the_defaults():
    assert load_settings(EXAMPLE).model_dump() == Settings().model_dump()


def test_every_key_of_the_settings_is_documented_in_the_example():
    text = EXAMPLE.read_text()
    for section, model in Settings.model_fields.items():
        assert section in text, section
        sub = model.annotation
        fields = getattr(sub, "model_fields", None) or getattr(getattr(sub, "__args__", [None])[0], "model_fields", {})
        for key in fields:
            assert f"{key} " in text or f"{key}=" in text, f"{section}.{key} is not documented in {EXAMPLE.name}"


def test_environment_overrides_the_file(tmp_path, monkeypatch):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[server]\nport = 9001\nhost = "0.0.0.0"\n[robot]\ndriver = "none"\n')
    monkeypatch.setenv("POSECELL_SERVER__PORT", "9100")
    s = load_settings(cfg)
    assert s.server.port == 9100 and s.server.host == "0.0.0.0" and s.robot.driver == "none"


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[server]\nport = 70000\n", "server.port"),
        ("[server]\nprot = 8000\n", "server.prot"),  # a misspelt key is an error, not a silent default
        ("[[cameras]]\nname='a'\n[[cameras]]\nname='a'\n", "unique"),
        ("[cameras.strobe\n", "not valid TOML"),
        ('[[cameras]]\ndriver = "gige"\n', "cameras.0.driver"),
        ('[processing]\ncentre = "median"\n', "processing.centre"),
    ],
)
def test_bad_configuration_is_refused_with_the_key_named(tmp_path, text, needle):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(SettingsError, match=needle.replace(".", r"\.")):
        load_settings(cfg)


def test_missing_configuration_file_is_a_clear_error(tmp_path):
    with pytest.raises(SettingsError, match="does not exist"):
        load_settings(tmp_path / "nope.toml")


def test_runtime_overrides_change_camera_and_processing_but_never_the_driver():
    s = Settings()
    s2 = with_runtime_overrides(
        s, {"cameras": [{"name": "cam0", "exposure_us": 900.0, "driver": "aravis"}], "processing": {"min_targets": 9}}
    )
    assert s2.cameras[0].exposure_us == 900.0 and s2.cameras[0].driver == "sim"
    assert s2.processing.min_targets == 9


def test_example_toml_is_valid_toml_with_one_camera():
    data = tomllib.loads(EXAMPLE.read_text())
    assert len(data["cameras"]) == 1


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[[cameras]]\nexposure_us = inf\n", "cameras.0.exposure_us"),  # TOML has inf and nan literals
        ("[[cameras]]\ngain_db = nan\n", "cameras.0.gain_db"),
        ("[[cameras]]\nexposure_us = 1e300\n", "cameras.0.exposure_us"),
        ("[[cameras]]\nframe_rate_hz = 1e-9\n", "cameras.0.frame_rate_hz"),
        ("[[cameras]]\nroi = [0, 0, 0, 64]\n", "cameras.0.roi"),
        ("[[cameras]]\n[cameras.strobe]\ndelay_us = 1e7\n", "cameras.0.strobe.delay_us"),
        ("[processing]\nsigma_px = 11.0\n", "processing.sigma_px"),
        ("[processing]\nmax_area_px = 1000000000000\n", "processing.max_area_px"),
        ("[storage]\nretention_days = 1e9\n", "storage.retention_days"),
        ("[robot]\ntransport_latency_s = -inf\n", "robot.transport_latency_s"),
    ],
)
def test_non_finite_and_out_of_range_numbers_in_the_file_are_refused(tmp_path, text, needle):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(SettingsError, match=needle.replace(".", r"\.")):
        load_settings(cfg)


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        ({"cameras": [{"name": "cam0", "exposure_us": float("inf")}]}, "cameras.cam0.exposure_us"),
        ({"processing": {"max_sigma0_px": float("nan")}}, "processing.max_sigma0_px"),
        ({"cameras": {"cam0": {}}}, "list of objects"),
        ({"processing": [1]}, "must be an object"),
        ({"cameras": [], "server": {"port": 1}}, "only 'cameras' and 'processing'"),
        ([1, 2], "must be an object"),
    ],
)
def test_runtime_overrides_that_break_a_limit_or_the_shape_are_refused(overrides, needle):
    with pytest.raises(SettingsError, match=needle):
        with_runtime_overrides(Settings(), overrides)


class Events:
    def __init__(self):
        self.events = []

    def add_event(self, kind, message, level="info"):
        self.events.append((kind, level, message))


def test_saved_runtime_file_is_standard_json_and_applied_at_the_next_start(tmp_path):
    s = Settings(state_dir=tmp_path)
    s = s.with_camera(s.cameras[0].model_copy(update={"exposure_us": 900.0}))
    s = s.with_processing(s.processing.model_copy(update={"min_targets": 9}))
    save_runtime_file(s)
    text = (tmp_path / RUNTIME_FILE).read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))
    events = Events()
    s2 = apply_runtime_file(Settings(state_dir=tmp_path), events)
    assert s2.cameras[0].exposure_us == 900.0 and s2.processing.min_targets == 9
    assert events.events == [] and (tmp_path / RUNTIME_FILE).read_text() == text


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('{"cameras": [{"name": "cam0", "exposure_us": Infinity}]}', "cameras.cam0.exposure_us"),
        ('{"processing": {"min_targets": 2}}', "processing.min_targets"),
        ('{"cameras": [{"name": "cam0"', "not JSON"),
        ("[1, 2]", "must be an object"),
        (b"\xff\xfe{}", "not UTF-8"),
    ],
)
def test_a_runtime_file_that_does_not_validate_is_set_aside_and_not_applied(tmp_path, text, needle):
    path = tmp_path / RUNTIME_FILE
    original = text if isinstance(text, bytes) else text.encode()
    path.write_bytes(original)
    events = Events()
    s = apply_runtime_file(Settings(state_dir=tmp_path), events)
    assert s.model_dump() == Settings(state_dir=tmp_path).model_dump()
    assert not path.exists()
    (aside,) = tmp_path.glob(f"{RUNTIME_FILE}.rejected-*")
    assert aside.read_bytes() == original  # kept for the operator
    ((kind, level, message),) = events.events
    assert kind == "runtime_config_rejected" and level == "warning"
    assert needle in message and aside.name in message


def test_no_runtime_file_leaves_the_settings_as_they_are(tmp_path):
    events = Events()
    assert (
        apply_runtime_file(Settings(state_dir=tmp_path), events).model_dump()
        == Settings(state_dir=tmp_path).model_dump()
    )
    assert events.events == []


@pytest.mark.parametrize(
    "change",
    [
        lambda s: setattr(s, "log_level", "debug"),
        lambda s: setattr(s, "processing", ProcessingConfig()),
        lambda s: setattr(s.processing, "min_targets", 9),
        lambda s: setattr(s.cameras[0], "exposure_us", 900.0),
        lambda s: setattr(s.cameras[0].strobe, "enabled", False),
        lambda s: setattr(s.robot, "transport_latency_s", 0.001),
        lambda s: setattr(s.server, "port", 9000),
        lambda s: s.cameras.__setitem__(0, CameraConfig()),  # a tuple: no item assignment
        lambda s: s.server.allowed_hosts.append("example.org"),  # a tuple: no append
    ],
)
def test_settings_cannot_be_changed_in_place(change):
    s = Settings()
    before = s.model_dump()
    with pytest.raises((ValueError, TypeError, AttributeError)):
        change(s)
    assert s.model_dump() == before


def test_a_change_is_a_new_settings_object_and_the_old_one_keeps_its_values():
    old = Settings()
    new = old.with_camera(old.cameras[0].model_copy(update={"exposure_us": 900.0}))
    new = new.with_processing(new.processing.model_copy(update={"min_targets": 9}))
    assert (new.cameras[0].exposure_us, new.processing.min_targets) == (900.0, 9)
    assert (old.cameras[0].exposure_us, old.processing.min_targets) == (2000.0, 6)
    assert isinstance(new.cameras, tuple) and new.server is old.server  # the untouched sections are shared


def test_with_camera_refuses_an_unknown_camera_and_another_driver():
    s = Settings()
    with pytest.raises(KeyError, match="cam9"):
        s.with_camera(CameraConfig(name="cam9"))
    with pytest.raises(ValueError, match="driver"):
        s.with_camera(CameraConfig(driver="aravis"))
    with pytest.raises(ValueError, match="driver"):
        s.with_camera(CameraConfig(options={"seed": 3}))


def test_runtime_overrides_keep_a_variable_of_the_environment_from_undoing_them(monkeypatch):
    # a change is never validated as a whole Settings again: that would read the environment again
    monkeypatch.setenv("POSECELL_PROCESSING__MIN_TARGETS", "8")
    s = load_settings(None)
    assert s.processing.min_targets == 8
    assert with_runtime_overrides(s, {"processing": {"min_targets": 9}}).processing.min_targets == 9


def test_processing_refuses_area_limits_out_of_order(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[processing]\nmin_area_px = 500\nmax_area_px = 400\n")
    with pytest.raises(SettingsError, match="min_area_px 500 is larger than max_area_px 400"):
        load_settings(cfg)


def test_auto_exposure_refuses_limits_out_of_order(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[[cameras]]\nname = "cam0"\n[cameras.auto_exposure]\nmin_us = 5000\nmax_us = 100\n')
    with pytest.raises(SettingsError, match=r"auto_exposure.min_us \(5000\) is above max_us \(100\)"):
        load_settings(cfg)


def test_the_centre_estimator_reaches_the_measurer(tmp_path):
    from service.runtime.processor import measure_settings

    cfg = tmp_path / "centroid.toml"
    cfg.write_text('[processing]\ncentre = "centroid"\n')
    assert measure_settings(load_settings(cfg).processing).detect.centre == "centroid"
    assert measure_settings(load_settings(None).processing).detect.centre == "edge"
