"""``GET/PUT /config``: camera exposure, gain, frame rate, trigger, strobe and processing options at run time.

Changes are validated with the same models as the configuration file (the patch
models below are derived from them, so the limits and their units are written
once, in ``service/settings.py``, and OpenAPI shows them), applied by each
camera's owner thread (a feature the camera lacks is a 409 with the driver's
sentence, and nothing is changed), and saved in the state directory so that
they survive a restart. A refused request changes nothing: not the worker, not
the saved file. A request is applied whole or not at all: every value is
validated first, then the cameras are reconfigured one by one; when one refuses
(409), or the file cannot be written, the cameras already changed get their
previous configuration again. Each change makes a new frozen ``Settings`` that
the worker swaps in whole (``worker.settings``, the one copy the API reads); one
request at a time changes them (``app.state.config_lock``).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from api.deps import SettingsDep, WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.runtime.worker import Worker
from service.settings import (
    CameraConfig,
    ProcessingConfig,
    Settings,
    StrobeConfig,
    runtime_sections,
    save_runtime_file,
    validation_problems,
)
from service.store import formats

router = APIRouter(tags=["configuration"])


class _Patch(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _patch_of(
    model: type[BaseModel],
    name: str,
    *,
    exclude: frozenset[str] = frozenset(),
    replace: dict[str, Any] | None = None,
) -> type[_Patch]:
    """``model`` with every field optional (``None``: unchanged), keeping its limits and descriptions."""
    fields: dict[str, Any] = {}
    for key, info in model.model_fields.items():
        if key in exclude:
            continue
        annotation = (replace or {}).get(key, info.annotation) | None
        if info.metadata:  # the limits: gt, le, ...
            annotation = Annotated[annotation, *info.metadata]
        fields[key] = (annotation, Field(None, description=info.description))
    return create_model(name, __base__=_Patch, __module__=__name__, **fields)


StrobePatch = _patch_of(StrobeConfig, "StrobePatch")
# name and driver pick the device: the configuration file's business, not a run-time change
CameraPatch = _patch_of(
    CameraConfig, "CameraPatch", exclude=frozenset({"name", "driver", "options"}), replace={"strobe": StrobePatch}
)
# the rig's pairing window is set when the worker starts
ProcessingPatch = _patch_of(ProcessingConfig, "ProcessingPatch", exclude=frozenset({"rig_sync_tolerance_s"}))


class ConfigPatch(_Patch):
    cameras: dict[str, CameraPatch] = {}  # type: ignore[valid-type]
    processing: ProcessingPatch | None = None  # type: ignore[valid-type]


@router.get("/config", summary="The run-time configurable part of the configuration")
def get_config(settings: SettingsDep) -> dict[str, Any]:
    return runtime_sections(settings)


@router.put("/config", dependencies=[Authorized], summary="Change camera and processing options (partial update)")
def put_config(request: Request, worker: WorkerDep, patch: ConfigPatch) -> dict[str, Any]:
    with request.app.state.config_lock:
        before = worker.settings
        cameras, processing = _validated(before, patch)
        changed: list[CameraConfig] = []  # the previous configuration of each camera reconfigured
        try:
            for cfg in cameras:
                error = worker.reconfigure_camera(cfg)
                if error:
                    raise ApiError(Reason.unsupported, f"camera {cfg.name}: {error}", status=409)
                changed.append(next(c for c in before.cameras if c.name == cfg.name))
            if processing is not None:
                worker.update_processing(processing)
            try:
                save_runtime_file(worker.settings)
            except OSError as e:
                raise ApiError(
                    Reason.storage_unavailable, f"the change could not be saved ({e.strerror or e}), so it is not made"
                ) from None
        except ApiError as e:
            problems = _restore(worker, before, changed)
            if problems:
                e.message = f"{e.message}; restoring the previous configuration failed: {'; '.join(problems)}"
            raise
        return runtime_sections(worker.settings)


def _validated(settings: Settings, patch: Any) -> tuple[list[CameraConfig], ProcessingConfig | None]:
    """The new configuration of each camera ``patch`` names, and the new processing options (None: not
    changed), validated against the models' limits; raises ApiError (404, 422) and changes nothing."""
    names = [c.name for c in settings.cameras]
    cameras: list[CameraConfig] = []
    try:
        for name, cp in patch.cameras.items():
            if name not in names:
                raise ApiError(Reason.not_found, f"no camera named {name!r}; cameras: {sorted(names)}")
            old = settings.cameras[names.index(name)]
            changes = cp.model_dump(exclude_unset=True)
            if "strobe" in changes:
                base = old.strobe.model_dump() if old.strobe is not None else {}
                changes["strobe"] = {**base, **(changes["strobe"] or {})}
            cfg = CameraConfig.model_validate({**old.model_dump(), **changes})
            if "defects" in changes and cfg.defects is not None:
                try:  # a map that cannot be read is refused now, not found out frame by frame
                    formats.read_defects(cfg.defects)
                except ValueError as e:
                    raise ApiError(Reason.bad_input, f"camera {name}: {e}") from None
            cameras.append(cfg)
        processing = None
        if patch.processing is not None:
            processing = ProcessingConfig.model_validate(
                {**settings.processing.model_dump(), **patch.processing.model_dump(exclude_unset=True)}
            )
    except ValidationError as e:
        raise ApiError(Reason.bad_input, f"invalid configuration: {validation_problems(e)}") from None
    return cameras, processing


def _restore(worker: Worker, before: Settings, cameras: list[CameraConfig]) -> list[str]:
    """Give ``cameras`` (their previous configuration) and the processing options of ``before`` back to
    the worker, the last changed first; the sentence of each camera that refuses its old values."""
    problems = []
    for cfg in reversed(cameras):
        error = worker.reconfigure_camera(cfg)
        if error:
            problems.append(f"camera {cfg.name}: {error}")
    if worker.settings.processing is not before.processing:
        worker.update_processing(before.processing)
    return problems
