"""The sensor's defect map, taken by the service: hot pixels from dark frames, dead ones from flat frames.

    POST /calibration/camera/defects   {"camera": "cam0", "frames": 8, "light": "off", "apply": true}
    POST /calibration/camera/defects   {"camera": "cam0", "kind": "dead", "frames": 8}

Hot pixels (``kind: "hot"``, the default): the camera's strobe is switched off (its ring light
stays dark), ``frames`` frames exposed after that are taken, and the strobe is switched back on
whatever happens. The defects are found in them as ``posecell calibrate defects`` finds them
(:func:`service.core.targets.defects.find_defects`). With ``light: "as_is"`` the light is left as it
is: a capped lens, or the arm moving between the frames (targets move, defects do not). The frames
taken meanwhile give no pose: no target is lit. Dead pixels (``kind: "dead"``): the light is left on
and the frames must show an evenly lit field, a white card or a diffuser held before the lens
(:func:`~service.core.targets.defects.find_dead_pixels`; a frame that is not lit is refused, 422).

The map is written to ``<state_dir>/defects-<camera>.json`` with the camera's current map's pixels
of the other kind kept (mapping hot pixels keeps the dead ones and the other way round) and, with
``apply``, used from the next frame on (the camera's ``defects``, saved with the run-time
configuration as ``PUT /config`` saves it).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Literal

from fastapi import APIRouter, Request
from pydantic import BaseModel, ConfigDict, Field

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.core.targets.defects import SUSPECT_SHARE, DefectMap, DefectSearch, find_dead_pixels, find_defects
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
    kind: Literal["hot", "dead"] = Field(
        "hot", description="hot: pixels above their neighbours in dark frames; dead: below them in flat frames"
    )
    frames: int = Field(8, ge=5, le=100, description="frames to take, [5, 100]")
    light: Literal["off", "as_is"] | None = Field(
        None,
        description="off: the strobe switched off for the frames; as_is: the light left as it is "
        "(default: off for hot pixels, as_is for dead ones)",
    )
    apply: bool = Field(True, description="use the map from the next frame on (and save it in the configuration)")


@router.post(
    "/defects", dependencies=[Authorized], summary="Map the camera's hot (dark frames) or dead (flat frames) pixels"
)
def take_defects(request: Request, worker: WorkerDep, req: DefectsRequest | None = None) -> dict[str, Any]:
    req = req or DefectsRequest()
    light = req.light or ("off" if req.kind == "hot" else "as_is")
    if req.kind == "dead" and light == "off":
        raise ApiError(
            Reason.bad_input,
            "dead pixels show only in lit, flat frames: hold a white card before the lens under the ring "
            "light and ask with light 'as_is'",
        )
    with request.app.state.config_lock:  # no PUT /config in between: the strobe is put back as it was
        cfg = _camera(worker, req.camera)
        lit = cfg.strobe is not None and cfg.strobe.enabled
        if light == "off" and not lit:
            raise ApiError(
                Reason.unsupported,
                f"camera {cfg.name} has no strobe switching its ring light: cap the lens (or move the arm "
                "between frames) and ask with light 'as_is'",
            )
        dark = None
        if light == "off" and cfg.strobe is not None:
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
        full_dn = None if bits is None else float(2**bits - 1)
        search = find_dead_pixels if req.kind == "dead" else find_defects
        try:
            found = search(images, full_dn=full_dn)
        except ValueError as e:
            raise ApiError(Reason.bad_image, f"camera {cfg.name}: {e}") from None
        found = _of_the_sensor(worker, cfg.name, found)
        m, kept, note = _with_the_other_kind(cfg, found, req.kind == "dead")
        path = worker.settings.resolved_state_dir() / f"defects-{cfg.name}.json"
        formats.write_defects(path, m, frames=found.n_frames, threshold_dn=float(found.threshold_dn.max()))
        share = len(found.defects) / (m.width * m.height)
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
            "info",
            "calibration",
            f"camera {cfg.name}: {len(found.defects)} {req.kind} pixels mapped from {len(images)} frames",
        )
        warnings = [note] if note else []
        if req.kind == "hot" and share > SUSPECT_SHARE:
            warnings.append(f"{share:.2%} of the pixels are defects: were the targets lit, or still?")
        if req.kind == "dead" and found.unjudged:
            warnings.append(
                f"{found.unjudged} pixels were not judged: their neighbourhood was not lit in enough of the "
                "frames (light the whole field evenly)"
            )
        return {
            "ok": True,
            "camera": cfg.name,
            "kind": req.kind,
            "found": len(found.defects),
            "defects": len(m),
            "hot": len(m) - m.n_dead,
            "dead": m.n_dead,
            "kept": kept,
            "share": share,
            "frames": found.n_frames,
            "threshold_dn": [float(found.threshold_dn.min()), float(found.threshold_dn.max())],
            "file": str(path),
            "applied": applied,
            "light": light,
            "warning": "; ".join(warnings) or None,
            "strobe_restored": not restore_error,
        }


def _of_the_sensor(worker: Worker, name: str, found: DefectSearch) -> DefectSearch:
    """The search's map as the whole sensor's when the camera delivers a window of it (its ``roi``): the
    measurement crops a camera's map to its window, as it does its calibration."""
    roi, camera = worker.processors[name].roi(), worker.calibration.camera
    if roi is None or camera is None:
        return found
    return replace(found, defects=found.defects.in_sensor(roi[0], roi[1], camera.width, camera.height))


def _with_the_other_kind(cfg: CameraConfig, found: DefectSearch, dead: bool) -> tuple[DefectMap, int, str]:
    """The map ``found`` with the camera's current map's pixels of the other kind (hot when ``dead``),
    how many of those were kept, and why none were when its map could not be used."""
    if cfg.defects is None:
        return found.defects, 0, ""
    try:
        other = formats.read_defects(cfg.defects).of_kind(not dead)
        return other.merged(found.defects), len(other), ""
    except (OSError, ValueError) as e:  # FormatError is a ValueError; another sensor's map does not merge
        return found.defects, 0, f"the current map {cfg.defects} was not kept: {e}"


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
            raise ApiError(Reason.timeout, f"camera {cfg.name}: {len(images)} of {n} frames came; see /health")
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
