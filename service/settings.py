"""The service's configuration: one TOML file plus ``POSECELL_*`` environment overrides.

Every key is documented in ``deploy/posecell.example.toml``; a test checks that
the example parses to exactly these defaults. With no file at all the service
runs the simulated cell, so ``posecell serve`` works out of the box.

Environment overrides use ``__`` between levels, e.g.
``POSECELL_SERVER__PORT=8080`` or ``POSECELL_ROBOT__DRIVER=ur``. The settings
object is built once, in ``load_settings``, and passed down explicitly.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from drivers.base import CameraSettings, StrobeSettings, TriggerMode


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")  # a misspelt key is an error, not a silent default


class ServerSettings(_Section):
    host: str = "127.0.0.1"  # loopback unless the integrator opens it up on purpose
    port: int = Field(8000, ge=1, le=65535)
    # bearer token for state-changing requests; empty: one is generated at start and written to
    # <state_dir>/api-token (mode 0600), so nothing is ever open by default
    token: str = ""
    cors_origins: list[str] = []


class StrobeConfig(_Section):
    enabled: bool = True
    line: str = "Line1"
    source: str = "ExposureActive"
    inverted: bool = False
    delay_us: float = Field(0.0, ge=0)
    duration_us: float | None = Field(None, gt=0)


class CameraConfig(_Section):
    name: str = "cam0"
    driver: Literal["sim", "aravis", "v4l2"] = "sim"
    options: dict[str, Any] = {}  # driver constructor options (aravis: device, packet_size, ...)
    exposure_us: float | None = Field(2000.0, gt=0)
    gain_db: float | None = None
    frame_rate_hz: float | None = Field(20.0, gt=0)
    trigger: TriggerMode = TriggerMode.FREE_RUN
    trigger_line: str = "Line0"
    pixel_format: Literal["Mono8", "Mono12", "Mono16"] | None = None
    roi: tuple[int, int, int, int] | None = None
    strobe: StrobeConfig | None = StrobeConfig()
    # smallest delay from exposure end to the frame's arrival (readout + transfer): the part of
    # the latency the clock mapping cannot see; the worker reports what remains
    transport_latency_s: float = Field(0.004, ge=0)

    def camera_settings(self) -> CameraSettings:
        strobe = None if self.strobe is None else StrobeSettings(**self.strobe.model_dump())
        return CameraSettings(
            exposure_us=self.exposure_us,
            gain_db=self.gain_db,
            frame_rate_hz=self.frame_rate_hz,
            trigger=self.trigger,
            trigger_line=self.trigger_line,
            pixel_format=self.pixel_format,
            roi=self.roi,
            strobe=strobe,
        )


class RobotConfig(_Section):
    driver: Literal["sim", "ur", "none"] = "sim"
    options: dict[str, Any] = {}  # ur: host, frequency_hz, T_flange_tcp
    transport_latency_s: float = Field(0.0, ge=0)


class ProcessingConfig(_Section):
    roi_tracking: bool = True
    # a rig's cameras are combined when their exposures lie this close (a hardware-triggered rig: ~0)
    rig_sync_tolerance_s: float = Field(0.005, gt=0)
    code_family: Literal["posecell12", "aicon14"] = "posecell12"
    min_targets: int = Field(6, ge=4)
    min_coded: int = Field(4, ge=3)
    sigma_px: float | None = Field(None, gt=0)
    max_sigma0_px: float = Field(0.5, gt=0)
    correct_eccentricity: bool = True
    min_contrast_dn: float | None = Field(None, gt=0)
    max_area_px: int | None = Field(None, gt=0)


class CalibrationConfig(_Section):
    # files imported into the calibration store at start when the store has no version yet;
    # empty with the simulated cell: the simulation's own camera and field are used
    camera_file: Path | None = None
    field_file: Path | None = None
    handeye_file: Path | None = None
    rig_file: Path | None = None  # two or more cameras: their relative orientation (posecell calibrate rig)


class StorageConfig(_Section):
    database: str = "measurements.sqlite"  # relative to state_dir
    retention_days: float | None = Field(30.0, gt=0)
    # streaming results are many; keep one every N seconds (0: all), triggered ones always
    stream_every_s: float = Field(1.0, ge=0)


class SimConfig(_Section):
    seed: int = 0
    robot: Literal["kr15", "ur10e"] = "kr15"
    program: Literal["circle", "random", "hold"] = "circle"
    error_scale: float = Field(1.0, ge=0)
    # "direct": in-process simulated drivers; "standins": the real Aravis and RTDE drivers
    # talking to the loopback stand-ins (needs Aravis and ur-rtde)
    transport: Literal["direct", "standins"] = "direct"
    # a calibrated hand-eye is given to the worker at start so that the demo shows deviations;
    # false: the service starts uncalibrated and the hand-eye workflow must be run
    preload_handeye: bool = True


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="POSECELL_", env_nested_delimiter="__", extra="forbid")

    state_dir: Path = Path("~/.local/state/posecell")
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    server: ServerSettings = ServerSettings()
    cameras: list[CameraConfig] = [CameraConfig()]
    robot: RobotConfig = RobotConfig()
    processing: ProcessingConfig = ProcessingConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    storage: StorageConfig = StorageConfig()
    sim: SimConfig = SimConfig()

    @field_validator("cameras")
    @classmethod
    def _unique_camera_names(cls, v: list[CameraConfig]) -> list[CameraConfig]:
        names = [c.name for c in v]
        if not v:
            raise ValueError("at least one camera must be configured")
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        return v

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # the environment overrides the file (given as init values by load_settings)
        return (env_settings, init_settings)

    @property
    def uses_sim(self) -> bool:
        return self.robot.driver == "sim" or any(c.driver == "sim" for c in self.cameras)

    def resolved_state_dir(self) -> Path:
        return self.state_dir.expanduser()


class SettingsError(ValueError):
    """The configuration file is missing, not TOML, or has a bad value (the message says which)."""


def load_settings(path: Path | None = None, **overrides: Any) -> Settings:
    """Settings from a TOML file (or none: the simulated cell), environment, then ``overrides``."""
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise SettingsError(f"configuration file {path} does not exist") from None
        except tomllib.TOMLDecodeError as e:
            raise SettingsError(f"configuration file {path} is not valid TOML: {e}") from None
    for key, value in overrides.items():
        if value is not None:
            section, _, name = key.partition("__")
            if name:
                data.setdefault(section, {})[name] = value
            else:
                data[key] = value
    try:
        return Settings(**data)
    except ValidationError as e:
        where = f" in {path}" if path else ""
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}" for err in e.errors(include_url=False)
        )
        raise SettingsError(f"bad configuration{where}: {problems}") from None


RUNTIME_FILE = "runtime-config.json"  # in state_dir: what PUT /config changed, re-applied at start


def runtime_sections(settings: Settings) -> dict[str, Any]:
    """The part of the settings that ``PUT /config`` may change."""
    return {
        "cameras": [c.model_dump(mode="json", exclude={"driver", "options"}) for c in settings.cameras],
        "processing": settings.processing.model_dump(mode="json"),
    }


def with_runtime_overrides(settings: Settings, overrides: dict[str, Any]) -> Settings:
    """Settings with the saved runtime changes applied (cameras matched by name; unknown names ignored)."""
    by_name = {c.get("name"): c for c in overrides.get("cameras", []) if isinstance(c, dict)}
    cameras = [
        CameraConfig.model_validate(
            {**c.model_dump(), **by_name.get(c.name, {}), "driver": c.driver, "options": c.options}
        )
        for c in settings.cameras
    ]
    saved = overrides.get("processing", {})
    processing = ProcessingConfig.model_validate({**settings.processing.model_dump(), **saved})
    return settings.model_copy(update={"cameras": cameras, "processing": processing})
