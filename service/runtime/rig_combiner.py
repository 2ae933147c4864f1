"""Forward intersection with a calibrated rig: the paper's second set-up, in the running service.

Each camera's frame is measured on its own first (targets found and identified
by the usual pipeline); the results of all cameras exposed at the same instant
(within ``sync_tolerance_s``, a hardware-triggered rig exposes together) are
then combined: every target seen by two or more cameras is intersected in the
master camera's frame and the rig's pose in the field follows from the
intersected points (``core.intersection.pose_from_intersection``). The result
is published as camera ``"rig"``: ``T_field_camera`` is the master camera's
pose, so the hand-eye of the master camera gives the flange.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.core.measurement import Measurement, RigPose
from service.core.pose.intersection import Rig, pose_from_intersection
from service.core.results import Failure, PoseResult, Reason, SolveError
from service.core.targets.field import Field
from service.pipeline.flange import flange_part

RIG = "rig"


class RigCombiner:
    def __init__(self, cameras: list[str], sync_tolerance_s: float = 0.005) -> None:
        self.cameras = cameras  # rig order: cameras[0] is the master
        self.tolerance_ns = int(sync_tolerance_s * 1e9)
        self._latest: dict[str, Measurement] = {}
        self._last_emitted_ns = -1

    def add(self, m: Measurement, rig: Rig | None, field: Field | None, handeye: Any) -> Measurement | None:
        """Record one camera's result; the rig's result when every camera has one of the same instant."""
        if rig is None or field is None or m.camera not in self.cameras or m.t_exposure_host_ns is None:
            return None
        self._latest[m.camera] = m
        if len(self._latest) < len(self.cameras):
            return None
        latest = [self._latest[c] for c in self.cameras]
        t = [int(r.t_exposure_host_ns or 0) for r in latest]
        if max(t) - min(t) > self.tolerance_ns or min(t) <= self._last_emitted_ns:
            return None
        self._last_emitted_ns = max(t)
        return self._combine(latest, rig, field, handeye)

    def _combine(self, results: list[Measurement], rig: Rig, field: Field, handeye: Any) -> Measurement:
        master = results[0]
        head: dict[str, Any] = {
            "camera": RIG,
            "seq": master.seq,
            "t_exposure_host_ns": master.t_exposure_host_ns,
            "t_unix_ns": master.t_unix_ns,
            "mode": "intersection",
            "cameras": tuple(self.cameras),
            "T_field_camera_true": master.T_field_camera_true,
        }
        failed = next((r for r in results if not isinstance(r.result, PoseResult)), None)
        if failed is not None:
            reason = failed.reason or Reason.too_few_targets
            return Measurement(result=Failure(reason, f"camera {failed.camera}: {failed.message or 'no pose'}"), **head)
        poses = [r.result for r in results if isinstance(r.result, PoseResult)]
        ids = sorted({t.id for p in poses for t in p.targets if t.used})
        index = {tid: i for i, tid in enumerate(ids)}
        uv = np.full((len(poses), len(ids), 2), np.nan)
        for k, p in enumerate(poses):
            for t in p.targets:
                if t.used:
                    uv[k, index[t.id]] = t.uv
        try:
            res = pose_from_intersection(rig, field.xyz[field.indices_of(ids)], list(uv))
        except SolveError as e:
            return Measurement(result=Failure.from_error(e), **head)
        coded = [bool(field.is_coded[field.index[t]]) for t in ids]
        pose = RigPose(
            T_field_camera=res.T_field_master,
            sigma_position_mm=res.sigma_position_mm,
            sigma_rotation_deg=res.sigma_rotation_deg,
            rms_mm=float(res.rms_mm),
            rms_px=float(res.intersection.rms_px),
            n_intersected=int(res.n_points),
            n_coded=sum(coded),
            n_uncoded=len(coded) - sum(coded),
        )
        reported = master.flange.T_base_flange if master.flange is not None else None
        why = master.flange.message if master.flange is not None else "no robot pose at the exposure"
        flange = flange_part(handeye, res.T_field_master, reported, why)
        return Measurement(result=pose, flange=flange, **head)
