"""Configuration: the example file documents exactly the defaults; files, environment and bad values."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from service.settings import Settings, SettingsError, load_settings, with_runtime_overrides

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
