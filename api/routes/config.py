"""``GET/PUT /config``: camera exposure, gain, frame rate, trigger, strobe and processing options at run time.

Changes are validated with the same models as the configuration file, applied
by each camera's owner thread (a feature the camera lacks is a 409 with the
driver's sentence, and nothing is changed), and saved in the state directory so
that they survive a restart.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from drivers.base import TriggerMode
from service.core.results import Reason
from service.formats import write_json_atomic
from service.settings import RUNTIME_FILE, CameraConfig, ProcessingConfig, runtime_sections

router = APIRouter(tags=["configuration"])


class _Patch(BaseModel):
    model_config = ConfigDict(extra="forbid")


class StrobePatch(_Patch):
    enabled: bool | None = None
    line: str | None = None
    source: str | None = None
    inverted: bool | None = None
    delay_us: float | None = Field(None, ge=0)
    duration_us: float | None = Field(None, gt=0)


class CameraPatch(_Patch):
    exposure_us: float | None = Field(None, gt=0)
    gain_db: float | None = None
    frame_rate_hz: float | None = Field(None, gt=0)
    trigger: TriggerMode | None = None
    trigger_line: str | None = None
    pixel_format: str | None = None
    roi: tuple[int, int, int, int] | None = None
    strobe: StrobePatch | None = None
    transport_latency_s: float | None = Field(None, ge=0)


class ProcessingPatch(_Patch):
    roi_tracking: bool | None = None
    code_family: str | None = None
    min_targets: int | None = None
    min_coded: int | None = None
    sigma_px: float | None = None
    max_sigma0_px: float | None = None
    correct_eccentricity: bool | None = None
    min_contrast_dn: float | None = None
    max_area_px: int | None = None


class ConfigPatch(_Patch):
    cameras: dict[str, CameraPatch] = {}
    processing: ProcessingPatch | None = None


@router.get("/config", summary="The run-time configurable part of the configuration")
def get_config(request: Request) -> dict[str, Any]:
    return runtime_sections(request.app.state.settings)


@router.put("/config", dependencies=[Authorized], summary="Change camera and processing options (partial update)")
def put_config(request: Request, worker: WorkerDep, patch: ConfigPatch) -> dict[str, Any]:
    settings = request.app.state.settings
    names = {c.name: i for i, c in enumerate(settings.cameras)}
    new_cameras: dict[str, CameraConfig] = {}
    try:
        for name, cp in patch.cameras.items():
            if name not in names:
                raise ApiError("not_found", f"no camera named {name!r}; cameras: {sorted(names)}")
            old = settings.cameras[names[name]]
            changes = cp.model_dump(exclude_unset=True)
            if "strobe" in changes:
                base = old.strobe.model_dump() if old.strobe is not None else {}
                changes["strobe"] = {**base, **(changes["strobe"] or {})}
            new_cameras[name] = CameraConfig.model_validate({**old.model_dump(), **changes})
        processing = None
        if patch.processing is not None:
            processing = ProcessingConfig.model_validate(
                {**settings.processing.model_dump(), **patch.processing.model_dump(exclude_unset=True)})
    except ValidationError as e:
        problems = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors(include_url=False))
        raise ApiError(Reason.bad_input, f"invalid configuration: {problems}") from None
    for name, cfg in new_cameras.items():
        error = worker.reconfigure_camera(cfg)
        if error:
            raise ApiError("unsupported", f"camera {name}: {error}", status=409)
        settings.cameras[names[name]] = cfg
    if processing is not None:
        worker.update_processing(processing)
    state_dir = settings.resolved_state_dir()
    write_json_atomic(state_dir / RUNTIME_FILE, runtime_sections(settings))
    return runtime_sections(settings)


def load_runtime_overrides(state_dir: Any) -> dict[str, Any]:
    try:
        data = json.loads((state_dir / RUNTIME_FILE).read_text(encoding="utf-8"))
    except (FileNotFoundError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}
