"""The sensor's defect map, taken by the service from dark frames.

    POST /calibration/camera/defects   {"camera": "cam0", "frames": 8, "light": "off", "apply": true}

The camera's strobe is switched off (its ring light stays dark), ``frames`` frames exposed after
that are taken, and the strobe is switched back on whatever happens. The defects are found in them
as ``posecell calibrate defects`` finds them (:func:`service.core.targets.defects.find_defects`),
written to ``<state_dir>/defects-<camera>.json`` and, with ``apply``, used from the next frame on
(the camera's ``defects``, saved with the run-time configuration as ``PUT /config`` saves it). With
``light: "as_is"`` the light is left as it is: a capped lens, or the arm moving between the frames
(targets move, defects do not). The frames taken meanwhile give no pose: no target is lit.
"""

from __future__ import annotations

import time
from typing import Any, Literal

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.core.targets.defects import SUSPECT_SHARE, find_defects
from service.runtime.acquisition import DeviceState
from service.runtime.processor import BIT_DEPTH
from service.runtime.worker import Worker
from service.settings import CameraConfig, save_runtime_file
from service.store import formats

router = APIRouter(prefix="/calibration/camera", tags=["camera calibration"])

POLL_S = 0.01


class DefectsRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    camera: str | None = Field(None, description="the camera (default: the first)")
    frames: int = Field(8, ge=5, le=100, description="dark frames to take, [5, 100]")
    light: Literal["off", "as_is"] = Field(
        "off", description="off: the strobe switched off for the frames; as_is: the light left as it is"
    )
    apply: bool = Field(True, description="use the map from the next frame on (and save it in the configuration)")


@router.post("/defects", dependencies=[Authorized], summary="Map the camera's hot pixels from dark frames")
def take_defects(request: Request, worker: WorkerDep, req: DefectsRequest | None = None) -> dict[str, Any]:
    req = req or DefectsRequest()
    with request.app.state.config_lock:  # no PUT /config in between: the strobe is put back as it was
        cfg = _camera(worker, req.camera)
        lit = cfg.strobe is not None and cfg.strobe.enabled
        if req.light == "off" and not lit:
            raise ApiError(
                Reason.unsupported,
                f"camera {cfg.name} has no strobe switching its ring light: cap the lens (or move the arm "
                "between frames) and ask with light 'as_is'",
            )
        dark = None
        if req.light == "off" and cfg.strobe is not None:
            dark = cfg.model_copy(update={"strobe": cfg.strobe.model_copy(update={"enabled": False})})
        t_dark_ns = time.monotonic_ns()
        if dark is not None and (error := worker.reconfigure_camera(dark)):
            raise ApiError(Reason.unsupported, f"camera {cfg.name}: {error}")
        try:
            images = _frames_after(worker, cfg, t_dark_ns, req.frames)
        finally:
            restore_error = worker.reconfigure_camera(cfg) if dark is not None else ""
        if restore_error:
            worker.event(
                "warning", "camera", f"camera {cfg.name}: its strobe could not be switched on again: {restore_error}"
            )
        bits = BIT_DEPTH.get(worker.processors[cfg.name].pixel_format() or "")
        try:
            found = find_defects(images, full_dn=None if bits is None else float(2**bits - 1))
        except ValueError as e:
            raise ApiError(Reason.bad_image, f"camera {cfg.name}: {e}") from None
        m = found.defects
        path = worker.settings.resolved_state_dir() / f"defects-{cfg.name}.json"
        formats.write_defects(path, m, frames=found.n_frames, threshold_dn=float(found.threshold_dn.max()))
        share = len(m) / (m.width * m.height)
        applied = False
        if req.apply:
            now = next(c for c in worker.settings.cameras if c.name == cfg.name)
            if error := worker.reconfigure_camera(now.model_copy(update={"defects": path})):
                raise ApiError(Reason.unsupported, f"camera {cfg.name}: the map is in {path}, not in use: {error}")
            try:
                save_runtime_file(worker.settings)
            except OSError as e:  # as PUT /config: what cannot be saved is not made
                worker.reconfigure_camera(now)
                raise ApiError(
                    Reason.storage_unavailable,
                    f"the map is in {path}, but the configuration could not be saved ({e.strerror or e}), "
                    "so it is not in use",
                ) from None
            applied = True
        worker.event(
            "info", "calibration", f"camera {cfg.name}: {len(m)} defect pixels mapped from {len(images)} frames"
        )
        return {
            "ok": True,
            "camera": cfg.name,
            "defects": len(m),
            "share": share,
            "frames": found.n_frames,
            "threshold_dn": [float(found.threshold_dn.min()), float(found.threshold_dn.max())],
            "file": str(path),
            "applied": applied,
            "light": req.light,
            "warning": (
                f"{share:.2%} of the pixels are defects: were the targets lit, or still?"
                if share > SUSPECT_SHARE
                else None
            ),
            "strobe_restored": not restore_error,
        }


def _camera(worker: Worker, name: str | None) -> CameraConfig:
    names = [c.name for c in worker.settings.cameras]
    name = name or names[0]
    if name not in names:
        raise ApiError(Reason.not_found, f"no camera named {name!r}; cameras: {sorted(names)}")
    ch = worker.cameras.get(name)
    if ch is None or ch.state is not DeviceState.ok:
        raise ApiError(Reason.camera_disconnected, f"camera {name} is not delivering frames; see /health")
    return worker.settings.cameras[names.index(name)]


def _frames_after(worker: Worker, cfg: CameraConfig, t_ns: int, n: int) -> list[Any]:
    """``n`` frames of ``cfg``'s camera exposed wholly after ``t_ns`` (host monotonic), copied."""
    exposure_ns = int((cfg.exposure_us or 0.0) * 1e3)
    rate = cfg.frame_rate_hz or 1.0
    deadline = time.monotonic() + 10.0 + 3.0 * n / rate
    images: list[Any] = []
    seen: set[int] = set()
    while len(images) < n:
        if time.monotonic() > deadline:
            raise ApiError(Reason.timeout, f"camera {cfg.name}: {len(images)} of {n} dark frames came; see /health")
        latest = worker.latest_frame.get(cfg.name)
        if latest is not None:
            frame, result = latest
            t_exposure = result.t_exposure_host_ns
            # the exposure's middle, a half exposure after the strobe was switched off at the least
            if frame.seq not in seen and t_exposure is not None and t_exposure - exposure_ns // 2 > t_ns:
                seen.add(frame.seq)
                images.append(frame.image.copy())
        time.sleep(POLL_S)
    return images
