"""The service's configuration: one TOML file plus ``POSECELL_*`` environment overrides.

Every key is documented in ``deploy/posecell.example.toml``; a test checks that
the example parses to exactly these defaults. With no file at all the service
runs the simulated cell, so ``posecell serve`` works out of the box.

Environment overrides use ``__`` between levels, e.g.
``POSECELL_SERVER__PORT=8080`` or ``POSECELL_ROBOT__DRIVER=ur``. The settings
object is built once, in ``load_settings``, and passed down explicitly.

These models are the one schema of every knob: the file, the environment, the
runtime file of ``PUT /config`` and that route's patch models (derived from
them) all obey the same limits. Every number must be finite (TOML's ``inf`` and
``nan``, JSON's ``Infinity`` and ``NaN`` are refused) and lie in a physical
range, stated with its unit in the field's description so that OpenAPI shows it.

Every model is frozen (lists are tuples), as Prefect's server settings are: a
configuration change builds a new :class:`Settings` (:meth:`Settings.with_camera`,
:meth:`Settings.with_processing`, :func:`with_runtime_overrides`) and its owner, the
worker, swaps it whole, so that a reader holding one never sees it change under it.
"""

from __future__ import annotations

import json
import logging
import os
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from drivers.base import CameraSettings, StrobeSettings, TriggerMode
from service.store.formats import write_json_atomic

log = logging.getLogger(__name__)


class _Section(BaseModel):
    # a misspelt key is an error, not a silent default; no number is NaN or infinite; a change is
    # a new object (model_copy), never an assignment
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class ServerSettings(_Section):
    host: str = "127.0.0.1"  # loopback unless the integrator opens it up on purpose
    port: int = Field(8000, ge=1, le=65535)
    # bearer token for state-changing requests; empty: one is generated at start and written to
    # <state_dir>/api-token (mode 0600), so nothing is ever open by default
    token: str = ""
    cors_origins: tuple[str, ...] = ()  # browser origins allowed to call the API and to open /ws/poses
    # Host header names the service answers to (against DNS rebinding); IP addresses and the bound host
    # are always accepted, since a rebinding page reaches the service only under a DNS name; "*": any
    allowed_hosts: tuple[str, ...] = ("localhost",)
    # largest request body (413 beyond): a field.json of 10 000 targets is 1.7-3.1 MB, a camera
    # self-calibration of 50 images x 500 points 1.5-3.5 MB (compact to indented JSON)
    max_body_bytes: int = Field(16 * 1024 * 1024, ge=1024)
    max_header_bytes: int = Field(16 * 1024, ge=1024)  # request line + headers (431 beyond)
    # connection timeouts: from connecting (or a request's first byte) to its last header byte; the
    # longest pause inside a request body; an idle keep-alive connection between requests
    timeout_header_s: float = Field(10.0, gt=0)
    timeout_body_s: float = Field(30.0, gt=0)
    timeout_keep_alive_s: float = Field(5.0, gt=0)
    timeout_graceful_shutdown_s: float = Field(10.0, gt=0)  # on stop, open requests get this long
    # open connections (HTTP and WebSocket) beyond this get 503 at once and are closed; keep it well
    # below LimitNOFILE of the systemd unit (8192)
    limit_concurrency: int = Field(2048, ge=1)
    backlog: int = Field(2048, ge=1)  # connections the kernel queues before the service accepts them
    ws_ping_interval_s: float = Field(20.0, gt=0)  # WebSocket keep-alive ping; no pong within the
    ws_ping_timeout_s: float = Field(20.0, gt=0)  # timeout: the client is dropped
    ws_max_message_bytes: int = Field(64 * 1024, ge=1024)  # largest message a WebSocket client may send
    # permessage-deflate on /ws/poses: off by default. Each connection compresses every message
    # again in its own zlib context, so it costs CPU per client and message (on a cell's LAN the
    # bandwidth it saves is not short); turn it on for clients behind a slow link
    ws_compression: bool = False
    # a /ws/poses client whose socket has taken nothing for this long (it stopped reading and the
    # buffers are full) is disconnected; the ping above finds one that stopped earlier
    ws_stall_timeout_s: float = Field(10.0, gt=0, le=3600)


class StrobeConfig(_Section):
    enabled: bool = True
    line: str = "Line1"
    source: str = "ExposureActive"
    inverted: bool = False
    delay_us: float = Field(0.0, ge=0, le=1e6, description="timer sources only: delay, µs, [0, 1 s]")
    duration_us: float | None = Field(None, gt=0, le=1e6, description="timer sources only: pulse length, µs, (0, 1 s]")


class AutoExposureConfig(_Section):
    """The exposure control on the targets' peaks (``service/runtime/exposure.py``)."""

    enabled: bool = True
    target_peak: float = Field(
        0.75, gt=0.1, lt=1, description="the brightest targets' peak above background, share of full scale, (0.1, 1)"
    )
    min_us: float = Field(20.0, gt=0, le=10_000_000, description="shortest exposure it sets, µs, (0, 10 s]")
    max_us: float = Field(
        10_000.0, gt=0, le=10_000_000, description="longest exposure it sets, µs, (0, 10 s] (motion blur grows with it)"
    )

    @model_validator(mode="after")
    def _ordered(self) -> AutoExposureConfig:
        if self.min_us > self.max_us:
            raise ValueError(f"auto_exposure.min_us ({self.min_us:g}) is above max_us ({self.max_us:g})")
        return self


_ROI_MAX_PX = 65_535
_RoiOffsetPx = Annotated[int, Field(ge=0, le=_ROI_MAX_PX)]
_RoiSizePx = Annotated[int, Field(gt=0, le=_ROI_MAX_PX)]


class CameraConfig(_Section):
    name: str = "cam0"
    driver: Literal["sim", "aravis", "v4l2", "replay"] = "sim"
    # driver constructor options (aravis: device, packet_size, ...; replay: source = "sim" or a folder, loop)
    options: dict[str, Any] = {}
    exposure_us: float | None = Field(
        2000.0, gt=0, le=10_000_000, description="exposure time, µs, (0, 10 s]; none: leave the camera's"
    )
    gain_db: float | None = Field(None, ge=-20, le=60, description="gain, dB, [-20, 60]; none: leave the camera's")
    frame_rate_hz: float | None = Field(
        20.0, ge=0.1, le=10_000, description="free-run frame rate, Hz, [0.1, 10 000]; none: leave the camera's"
    )
    trigger: TriggerMode = TriggerMode.FREE_RUN
    trigger_line: str = "Line0"
    pixel_format: Literal["Mono8", "Mono12", "Mono16"] | None = None
    roi: tuple[_RoiOffsetPx, _RoiOffsetPx, _RoiSizePx, _RoiSizePx] | None = Field(
        None, description="x, y, width, height, px: offsets [0, 65 535], sizes [1, 65 535]; none: full sensor"
    )
    strobe: StrobeConfig | None = StrobeConfig()
    # from exposure_us, the exposure follows the targets' brightness within the limits (off: fixed)
    auto_exposure: AutoExposureConfig = AutoExposureConfig()
    # smallest delay from exposure end to the frame's arrival (readout + transfer): the part of
    # the latency the clock mapping cannot see; the worker reports what remains
    transport_latency_s: float = Field(0.004, ge=0, le=1, description="readout + transfer delay, s, [0, 1]")
    # the sensor's defect pixels (posecell calibrate defects), patched in each frame before it is measured
    defects: Path | None = None

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
    driver: Literal["sim", "ur", "replay", "none"] = "sim"
    options: dict[str, Any] = {}  # ur: host, frequency_hz, T_flange_tcp; replay: source (a recording), loop
    transport_latency_s: float = Field(0.0, ge=0, le=1, description="robot sample transport delay, s, [0, 1]")


class ProcessingConfig(_Section):
    roi_tracking: bool = True
    # "process": each camera's frames are measured in a child process of their own (the measurement
    # does not wait for the interpreter lock behind acquisition, storage and the fan-out); "thread":
    # in the service's processing thread (one process, e.g. to profile it)
    measure_in: Literal["process", "thread"] = "process"
    # with "process": the camera's own thread hands each frame to the child as it arrives, instead of
    # waking the processing thread to do it (false: always through the processing thread)
    direct_hand_over: bool = True
    # with "process": "dedicated" keeps each camera's child on a CPU of its own and the service's
    # threads off those CPUs (when one CPU is left for them); "auto" does so from 100 frames/s in
    # all; "shared": every CPU for everything (service/runtime/cpus.py)
    measure_cpus: Literal["auto", "dedicated", "shared"] = "auto"
    # a rig's cameras are combined when their exposures lie this close (a hardware-triggered rig: ~0)
    rig_sync_tolerance_s: float = Field(0.005, gt=0, le=1, description="rig exposure pairing window, s, (0, 1]")
    code_family: Literal["posecell12", "aicon14"] = "posecell12"
    min_targets: int = Field(6, ge=4, le=100_000, description="targets needed for a pose, [4, 100 000]")
    min_coded: int = Field(4, ge=3, le=100_000, description="coded targets needed for a pose, [3, 100 000]")
    codes_enough: int = Field(
        12,
        ge=0,
        le=100_000,
        description="full frame: rings read until this many coded targets are named, the others named "
        "from their pose, [0, 100 000]; 0: every ring",
    )
    sigma_px: float | None = Field(
        None, gt=0, le=10, description="a-priori image precision, px, (0, 10]; none: from the detector"
    )
    max_sigma0_px: float = Field(0.5, gt=0, le=100, description="largest accepted sigma0 of a pose, px, (0, 100]")
    correct_eccentricity: bool = True
    # what a target's centre is measured as: the centre of the disk's ellipse fitted to its half-level
    # edge (twice as consistent on real panels), or the intensity centroid (~1 us a target less)
    centre: Literal["centroid", "edge"] = "edge"
    max_saturated_px: int | None = Field(
        None,
        ge=0,
        le=100_000_000,
        description="none: targets clipped at the saturation level are measured (and counted as saturated); "
        "a number: a target with more pixels at the saturation level than this is rejected, [0, 10^8]",
    )
    min_contrast_dn: float | None = Field(
        None,
        gt=0,
        le=65_535,
        description=("detection threshold above the local background, DN, (0, 65 535]; none: the detector's"),
    )
    min_area_px: int | None = Field(
        None, gt=0, le=100_000_000, description="smallest target image, px, (0, 10^8]; none: the detector's (6)"
    )
    max_area_px: int | None = Field(
        None, gt=0, le=100_000_000, description="largest target image, px, (0, 10^8]; none: the detector's (5000)"
    )

    @model_validator(mode="after")
    def _area_limits_in_order(self) -> ProcessingConfig:
        if self.min_area_px is not None and self.max_area_px is not None and self.min_area_px > self.max_area_px:
            raise ValueError(f"min_area_px {self.min_area_px} is larger than max_area_px {self.max_area_px}")
        return self


class CalibrationConfig(_Section):
    # files imported into the calibration store at start when the store has no version yet;
    # empty with the simulated cell: the simulation's own camera and field are used
    camera_file: Path | None = None
    field_file: Path | None = None
    handeye_file: Path | None = None
    rig_file: Path | None = None  # two or more cameras: their relative orientation (posecell calibrate rig)


class StorageConfig(_Section):
    database: str = "measurements.sqlite"  # relative to state_dir
    retention_days: float | None = Field(
        30.0,
        gt=0,
        le=36_500,
        description=("measurements and events older than this are deleted, days, (0, 36 500]; none: kept"),
    )
    # streaming results are many; keep one every N seconds (0: all), triggered ones always
    stream_every_s: float = Field(1.0, ge=0, le=86_400, description="stored streaming interval, s, [0, 86 400]")


class SimConfig(_Section):
    seed: int = 0
    robot: Literal["kr15", "ur10e"] = "kr15"
    program: Literal["circle", "random", "hold"] = "circle"
    error_scale: float = Field(1.0, ge=0, le=100, description="scale of the simulated robot's errors, [0, 100]")
    # "direct": in-process simulated drivers; "standins": the real Aravis and RTDE drivers
    # talking to the loopback stand-ins (needs Aravis and ur-rtde)
    transport: Literal["direct", "standins"] = "direct"
    # a calibrated hand-eye is given to the worker at start so that the demo shows deviations;
    # false: the service starts uncalibrated and the hand-eye workflow must be run
    preload_handeye: bool = True


_MQTT_TOPIC_WILDCARDS = ("+", "#")


class MqttConfig(_Section):
    """Publishing into the plant's MQTT broker (``service/plant/mqtt.py``); empty ``broker``: off."""

    broker: str = Field(
        "",
        pattern=r"^$|^mqtts?://[^/:\s]+(:\d{1,5})?/?$",
        description='broker URL, "mqtt://host:port" or "mqtts://host:port" (TLS); empty: no publishing',
    )
    topic_prefix: str = Field(
        "posecell", min_length=1, max_length=200, description="topics: <prefix>/<camera>/pose, <prefix>/health, ..."
    )
    client_id: str = Field("", max_length=100, description="MQTT client id; empty: posecell-<host>-<pid>-<n>")
    username: str = ""  # empty: connect without credentials
    password: str = ""
    pose_rate_hz: float = Field(
        10.0, gt=0, le=200, description="pose messages per camera, Hz, (0, 200]: the newest result each period"
    )
    health_interval_s: float = Field(
        5.0, ge=0.5, le=3600, description="retained health document period (and on change), s, [0.5, 3600]"
    )
    keepalive_s: int = Field(
        10, ge=2, le=3600, description="MQTT keep-alive, s, [2, 3600]: the broker sends the will after 1.5x this"
    )
    reconnect_min_s: float = Field(0.5, gt=0, le=60, description="first reconnection delay, s, (0, 60]")
    reconnect_max_s: float = Field(
        30.0, gt=0, le=3600, description="longest reconnection delay (doubling back-off), s, (0, 3600]"
    )
    queue_size: int = Field(
        100, ge=1, le=100_000, description="messages the client may hold while the broker is slow, [1, 100 000]"
    )

    @field_validator("topic_prefix")
    @classmethod
    def _plain_topic(cls, v: str) -> str:
        if any(c in v for c in _MQTT_TOPIC_WILDCARDS) or v.startswith("/") or v.endswith("/"):
            raise ValueError(f"topic_prefix {v!r} must not hold '+' or '#' nor start or end with '/'")
        return v

    @model_validator(mode="after")
    def _backoff_order(self) -> MqttConfig:
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s must not be smaller than reconnect_min_s")
        return self


class OpcUaConfig(_Section):
    """The OPC UA server for the cell's PLC (``service/plant/opcua.py``); empty ``endpoint``: off."""

    endpoint: str = Field(
        "",
        pattern=r"^$|^opc\.tcp://[^/:\s]+(:\d{1,5})?(/.*)?$",
        description='endpoint URL, "opc.tcp://host:port"; empty: no OPC UA server',
    )
    update_rate_hz: float = Field(
        10.0, gt=0, le=100, description="variable updates per camera, Hz, (0, 100]: the newest result each period"
    )
    namespace_uri: str = Field("urn:posecell", min_length=1, max_length=200, description="the server's own namespace")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="POSECELL_", env_nested_delimiter="__", extra="forbid", frozen=True)

    state_dir: Path = Path("~/.local/state/posecell")
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    server: ServerSettings = ServerSettings()
    cameras: tuple[CameraConfig, ...] = (CameraConfig(),)
    robot: RobotConfig = RobotConfig()
    processing: ProcessingConfig = ProcessingConfig()
    calibration: CalibrationConfig = CalibrationConfig()
    storage: StorageConfig = StorageConfig()
    sim: SimConfig = SimConfig()
    mqtt: MqttConfig = MqttConfig()
    opcua: OpcUaConfig = OpcUaConfig()

    @field_validator("cameras")
    @classmethod
    def _unique_camera_names(cls, v: tuple[CameraConfig, ...]) -> tuple[CameraConfig, ...]:
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
        """The simulated cell runs: a simulated device, or a replay of the simulated cell's frames."""
        return self.robot.driver == "sim" or any(
            c.driver == "sim" or (c.driver == "replay" and str(c.options.get("source", "sim")) == "sim")
            for c in self.cameras
        )

    def resolved_state_dir(self) -> Path:
        return self.state_dir.expanduser()

    # --- changes: a new Settings, never an assignment ----------------------------------------------
    # ``model_copy(update=...)`` does not validate, and validating a whole Settings again would read
    # the environment again (a POSECELL_* variable would undo a run-time change): the sections given
    # here are validated models, and what ties them together (the camera names) is checked here.

    def with_camera(self, camera: CameraConfig) -> Settings:
        """These settings with the camera of ``camera.name`` replaced (a new object).

        Raises ``KeyError`` for a name not configured and ``ValueError`` for another driver or other
        driver options: which device a camera is, is the configuration file's business.
        """
        names = [c.name for c in self.cameras]
        if camera.name not in names:
            raise KeyError(f"no camera named {camera.name!r}; cameras: {names}")
        i = names.index(camera.name)
        old = self.cameras[i]
        if (camera.driver, camera.options) != (old.driver, old.options):
            raise ValueError(f"camera {camera.name}: the driver and its options are changed in the configuration file")
        return self.model_copy(update={"cameras": (*self.cameras[:i], camera, *self.cameras[i + 1 :])})

    def with_processing(self, processing: ProcessingConfig) -> Settings:
        """These settings with other processing options (a new object)."""
        return self.model_copy(update={"processing": processing})


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
        raise SettingsError(f"bad configuration{where}: {validation_problems(e)}") from None


def validation_problems(e: ValidationError, prefix: str = "") -> str:
    """Every bad key of a pydantic error on one line: ``cameras.0.exposure_us: Input should be ...``."""
    out = []
    for err in e.errors(include_url=False):
        where = (prefix + ".".join(str(p) for p in err["loc"])).rstrip(".")  # a model's own check: no field
        out.append(f"{where}: {err['msg']}" if where else err["msg"])
    return "; ".join(out)


RUNTIME_FILE = "runtime-config.json"  # in state_dir: what PUT /config changed, re-applied at start


def runtime_sections(settings: Settings) -> dict[str, Any]:
    """The part of the settings that ``PUT /config`` may change."""
    return {
        "cameras": [c.model_dump(mode="json", exclude={"driver", "options"}) for c in settings.cameras],
        "processing": settings.processing.model_dump(mode="json"),
    }


def with_runtime_overrides(settings: Settings, overrides: Any) -> Settings:
    """Settings with the saved runtime changes applied (cameras matched by name; unknown names ignored).

    Raises ``SettingsError`` naming the key when ``overrides`` does not have the shape of
    :func:`runtime_sections` or a value breaks a limit of the settings models.
    """
    if not isinstance(overrides, dict) or not set(overrides) <= {"cameras", "processing"}:
        raise SettingsError("runtime overrides must be an object with only 'cameras' and 'processing'")
    saved_cameras, saved = overrides.get("cameras", []), overrides.get("processing", {})
    if not isinstance(saved_cameras, list) or not all(isinstance(c, dict) for c in saved_cameras):
        raise SettingsError("runtime overrides: 'cameras' must be a list of objects")
    if not isinstance(saved, dict):
        raise SettingsError("runtime overrides: 'processing' must be an object")
    by_name = {c.get("name"): c for c in saved_cameras}
    out = settings
    for c in settings.cameras:
        try:
            camera = CameraConfig.model_validate(
                {**c.model_dump(), **by_name.get(c.name, {}), "driver": c.driver, "options": c.options}
            )
        except ValidationError as e:
            raise SettingsError(f"bad runtime overrides: {validation_problems(e, f'cameras.{c.name}.')}") from None
        out = out.with_camera(camera)
    try:
        processing = ProcessingConfig.model_validate({**settings.processing.model_dump(), **saved})
    except ValidationError as e:
        raise SettingsError(f"bad runtime overrides: {validation_problems(e, 'processing.')}") from None
    return out.with_processing(processing)


class EventSink(Protocol):
    """Where a start-up problem is recorded (``MeasurementStore``)."""

    def add_event(self, kind: str, message: str, level: str = ...) -> None: ...


def apply_runtime_file(settings: Settings, events: EventSink | None = None) -> Settings:
    """Settings with ``<state_dir>/runtime-config.json`` (what ``PUT /config`` saved) applied.

    A file that cannot be read, is not JSON or breaks a limit is never applied, even in part:
    it is renamed aside to ``runtime-config.json.rejected-<UTC time>`` (kept for the operator),
    the sentence why is logged and recorded as a ``runtime_config_rejected`` warning event, and
    ``settings`` (the configuration file's values) are returned unchanged.
    """
    path = settings.resolved_state_dir() / RUNTIME_FILE
    try:
        return with_runtime_overrides(settings, json.loads(path.read_text(encoding="utf-8")))
    except FileNotFoundError:
        return settings
    except UnicodeDecodeError:
        problem = "it is not UTF-8 text"
    except json.JSONDecodeError as e:
        problem = f"it is not JSON (line {e.lineno} column {e.colno}: {e.msg})"
    except SettingsError as e:
        problem = str(e)
    except OSError as e:
        problem = f"it cannot be read ({e.strerror})"
    aside = path.with_name(f"{path.name}.rejected-{datetime.now(UTC):%Y%m%dT%H%M%S.%fZ}")
    try:
        os.replace(path, aside)
        where = f"set aside as {aside.name}"
    except OSError as e:
        where = f"left in place ({e.strerror})"
    message = f"{path} was not applied and is {where}: {problem}; the configuration file's values apply"
    log.warning(message)
    if events is not None:
        events.add_event("runtime_config_rejected", message, level="warning")
    return settings


def save_runtime_file(settings: Settings) -> None:
    """Write what ``PUT /config`` may change to ``<state_dir>/runtime-config.json`` (standard JSON, atomic)."""
    write_json_atomic(settings.resolved_state_dir() / RUNTIME_FILE, runtime_sections(settings))
