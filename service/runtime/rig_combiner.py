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

from service.core.pose.intersection import Rig, pose_from_intersection
from service.core.results import Reason, SolveError
from service.core.targets.field import Field
from service.pipeline.flange import deviation, flange_from_camera

RIG = "rig"


class RigCombiner:
    def __init__(self, cameras: list[str], sync_tolerance_s: float = 0.005) -> None:
        self.cameras = cameras  # rig order: cameras[0] is the master
        self.tolerance_ns = int(sync_tolerance_s * 1e9)
        self._latest: dict[str, dict[str, Any]] = {}
        self._last_emitted_ns = -1

    def add(self, result: dict[str, Any], rig: Rig | None, field: Field | None, handeye: Any) -> dict[str, Any] | None:
        """Record one camera's result; the rig's result when every camera has one of the same instant."""
        name = result.get("camera")
        if rig is None or field is None or name not in self.cameras:
            return None
        self._latest[name] = result
        if len(self._latest) < len(self.cameras):
            return None
        t = [int(self._latest[c]["t_exposure_host_ns"]) for c in self.cameras]
        if max(t) - min(t) > self.tolerance_ns or min(t) <= self._last_emitted_ns:
            return None
        self._last_emitted_ns = max(t)
        return self._combine([self._latest[c] for c in self.cameras], rig, field, handeye, t[0])

    def _combine(
        self, results: list[dict[str, Any]], rig: Rig, field: Field, handeye: Any, t_ns: int
    ) -> dict[str, Any]:
        master = results[0]
        head = {
            "camera": RIG,
            "seq": master.get("seq"),
            "t_exposure_host_ns": t_ns,
            "t_wall": master.get("t_wall"),
            "mode": "intersection",
            "cameras": self.cameras,
        }
        failed = [r for r in results if not r.get("ok")]
        if failed:
            return {
                "ok": False,
                "reason": failed[0].get("reason", Reason.too_few_targets),
                "message": f"camera {failed[0].get('camera')}: {failed[0].get('message', 'no pose')}",
                **head,
            }
        ids = sorted({t["id"] for r in results for t in r["targets"] if not t.get("rejected")})
        index = {tid: i for i, tid in enumerate(ids)}
        uv = np.full((len(results), len(ids), 2), np.nan)
        for k, r in enumerate(results):
            for t in r["targets"]:
                if not t.get("rejected"):
                    uv[k, index[t["id"]]] = t["uv"]
        try:
            res = pose_from_intersection(rig, field.xyz[field.indices_of(ids)], list(uv))
        except SolveError as e:
            return {"ok": False, "reason": str(e.reason), "message": e.message, **head}
        out: dict[str, Any] = {
            "ok": True,
            **head,
            "T_field_camera": res.T_field_master.tolist(),
            "sigma_position_mm": res.sigma_position_mm.tolist(),
            "sigma_rotation_deg": res.sigma_rotation_deg.tolist(),
            "rms_mm": float(res.rms_mm),
            "rms_px": float(res.intersection.rms_px),
            "n_intersected": int(res.n_points),
            "n_coded": sum(1 for t in ids if field.is_coded[field.index[t]]),
            "n_uncoded": sum(1 for t in ids if not field.is_coded[field.index[t]]),
            "T_base_flange": master.get("T_base_flange"),
            "T_base_flange_measured": None,
            "deviation": None,
        }
        if handeye is not None:
            T_meas = flange_from_camera(handeye, res.T_field_master)
            out["T_base_flange_measured"] = T_meas.tolist()
            if master.get("T_base_flange") is not None:
                out["deviation"] = deviation(T_meas, np.asarray(master["T_base_flange"])).to_dict()
        if "truth" in master:
            out["truth"] = master["truth"]
        return out
