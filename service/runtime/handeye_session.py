"""The guided hand-eye calibration in the service: plan poses, record samples, solve, store.

1. ``start``: from the camera's current measured pose and the robot's pose at that
   frame, propose ``n`` flange poses around the field (``core.handeye_plan``).
2. The robot is moved to each (by the integrator's robot program; in the
   simulated cell the service can move it), and ``capture`` records a sample:
   the next frame's measured ``T_field_camera`` with its σ, and the robot's
   reported ``T_base_flange`` at that exposure — refused while the robot moves.
3. ``solve``: Tsai–Lenz, then the joint refinement of X and Z over all samples
   with the camera σ from the resections (``core.handeye.calibrate_handeye``),
   then the refinement on the image observations with the robot's pose errors
   as unknowns (``core.handeye_images``); residuals per sample and warnings come back; ``apply`` stores the result
   versioned and atomically, and the worker uses it from the next frame.

Samples can be exported in the format of ``posecell calibrate handeye --samples``. The session is
kept on disk (:mod:`service.runtime.session_store`): its plan and each sample are written before they
are acknowledged, and a restarted service offers it again (:meth:`HandEyeSession.restore`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from service.core.calib.handeye import calibrate_handeye, motion_quality
from service.core.calib.handeye_images import ImageSample, refine_handeye_on_images
from service.core.calib.handeye_plan import flange_poses_for_views, propose_views
from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import orientation_report, ur_pose_from_T
from service.core.measurement import iso_wall
from service.core.results import Failure, PoseResult, Reason, SolveError
from service.core.targets.field import Field

STILL_WINDOW_S = 0.3
STILL_POSITION_MM = 0.05
STILL_ANGLE_DEG = 0.01


class SessionError(Exception):
    """A step of the workflow that cannot be done now; ``reason`` is a machine-readable code."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason, self.message = reason, message

    def __reduce__(self) -> tuple[Any, ...]:  # raised in the solver process, re-raised in the service's
        return (type(self), (self.reason, self.message))


@dataclass
class Sample:
    T_base_flange: np.ndarray
    T_field_camera: np.ndarray
    sigma_position_mm: list[float]
    sigma_rotation_deg: list[float]
    rms_px: float
    n_targets: int
    t_wall: str
    camera: str
    ids: list[str] = field(default_factory=list)  # the targets used in the frame's adjustment
    uv: np.ndarray | None = None  # (N, 2) px, measured, in the whole sensor's pixels (the calibration's)

    def to_dict(self) -> dict[str, Any]:
        return {
            "points": [{"id": i, "uv": [float(u), float(v)]} for i, (u, v) in zip(self.ids, self.uv, strict=True)]
            if self.uv is not None
            else [],
            "T_base_flange": self.T_base_flange.tolist(),
            "T_field_camera": self.T_field_camera.tolist(),
            "sigma_position_mm": self.sigma_position_mm,
            "sigma_rotation_deg": self.sigma_rotation_deg,
            "rms_px": self.rms_px,
            "n_targets": self.n_targets,
            "t_wall": self.t_wall,
            "camera": self.camera,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Sample:
        """The sample :meth:`to_dict` wrote (the stored session's)."""
        points = d.get("points") or []
        return cls(
            T_base_flange=np.asarray(d["T_base_flange"], dtype=np.float64).reshape(4, 4),
            T_field_camera=np.asarray(d["T_field_camera"], dtype=np.float64).reshape(4, 4),
            sigma_position_mm=[float(v) for v in d["sigma_position_mm"]],
            sigma_rotation_deg=[float(v) for v in d["sigma_rotation_deg"]],
            rms_px=float(d["rms_px"]),
            n_targets=int(d["n_targets"]),
            t_wall=str(d["t_wall"]),
            camera=str(d["camera"]),
            ids=[str(p["id"]) for p in points],
            uv=np.array([p["uv"] for p in points], dtype=np.float64).reshape(-1, 2) if points else None,
        )


class SessionStoreLike(Protocol):
    """Where a session is kept (:class:`service.runtime.session_store.SessionStore`)."""

    def save(self, kind: str, state: dict[str, Any]) -> None: ...

    def discard(self, kind: str) -> None: ...


@dataclass
class HandEyeSession:
    camera: str
    proposals: list[np.ndarray]  # T_base_flange (4, 4) mm
    X_guess: np.ndarray
    samples: list[Sample] = field(default_factory=list)
    result: dict[str, Any] | None = None
    applied_version: int | None = None
    created_wall: str = field(default_factory=lambda: time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    restored: bool = False  # read back from disk at the service's start
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    store: SessionStoreLike | None = field(default=None, repr=False)
    # one write at a time, each of the state it read: two requests' writes never land out of order
    save_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    # --- 1. plan ------------------------------------------------------------------------------

    @classmethod
    def start(cls, worker: Any, camera: str, n_poses: int) -> HandEyeSession:
        cal = worker.calibration
        if cal.camera is None or cal.field is None:
            raise SessionError(Reason.not_calibrated, "a camera and a field calibration are needed first")
        latest = worker.latest.get(camera)
        reported = latest.flange.T_base_flange if latest is not None and latest.flange is not None else None
        if latest is None or not latest.ok or latest.T_field_camera is None or reported is None:
            raise SessionError(
                Reason.too_few_targets,
                "the camera must see the field and the robot must be connected: no measured, paired pose yet",
            )
        X_guess = cal.handeye.T_flange_camera if cal.handeye is not None else np.eye(4)
        T_fc = latest.T_field_camera
        try:
            views = propose_views(cal.camera, cal.field, T_fc, n=n_poses)
        except SolveError as e:
            raise SessionError(e.reason, e.message) from None
        poses = flange_poses_for_views(views, reported, T_fc, X_guess)
        session = cls(camera=camera, proposals=poses, X_guess=X_guess, store=getattr(worker, "sessions", None))
        session.persist()  # a plan that is not stored is not started
        return session

    # --- kept across restarts -----------------------------------------------------------------

    def to_state(self) -> dict[str, Any]:
        """What :meth:`restore` needs (the lock held by the caller or no other thread)."""
        return {
            "camera": self.camera,
            "proposals": [T.tolist() for T in self.proposals],
            "X_guess": self.X_guess.tolist(),
            "samples": [x.to_dict() for x in self.samples],
            "result": self.result,
            "applied_version": self.applied_version,
            "created": self.created_wall,
        }

    @classmethod
    def restore(cls, state: dict[str, Any], store: SessionStoreLike | None = None) -> HandEyeSession:
        """The session :meth:`to_state` wrote; raises ``KeyError``, ``TypeError`` or ``ValueError`` on
        a state that is not one."""
        return cls(
            camera=str(state["camera"]),
            proposals=[np.asarray(T, dtype=np.float64).reshape(4, 4) for T in state["proposals"]],
            X_guess=np.asarray(state["X_guess"], dtype=np.float64).reshape(4, 4),
            samples=[Sample.from_dict(d) for d in state["samples"]],
            result=state.get("result"),
            applied_version=state.get("applied_version"),
            created_wall=str(state["created"]),
            restored=True,
            store=store,
        )

    def persist(self) -> None:
        """Write the session to its store (raises ``SessionError`` storage_unavailable)."""
        if self.store is not None:
            with self.save_lock:
                with self.lock:
                    state = self.to_state()
                self.store.save("handeye", state)

    def discard(self) -> None:
        if self.store is not None:
            self.store.discard("handeye")

    # --- 2. record ----------------------------------------------------------------------------

    def capture(self, worker: Any, timeout_s: float = 5.0) -> Sample:
        robot = worker.robot
        if robot is None or not robot.connected:
            raise SessionError(Reason.robot_disconnected, "the robot is not connected")
        now = time.monotonic_ns()
        recent = robot.samples_between(now - int(STILL_WINDOW_S * 1e9), now)
        if len(recent) >= 2:
            p = np.array([s.T_base_flange[:3, 3] for s in recent])
            spread_mm = float(np.max(np.linalg.norm(p - p[-1], axis=1)))
            dR = [recent[-1].T_base_flange[:3, :3].T @ s.T_base_flange[:3, :3] for s in recent]
            spread_deg = max(float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))) for R in dR)
            if spread_mm > STILL_POSITION_MM or spread_deg > STILL_ANGLE_DEG:
                raise SessionError(
                    Reason.robot_moving,
                    f"the robot moved {spread_mm:.2f} mm in the last {STILL_WINDOW_S} s; record samples at rest",
                )
        m = worker.request_measurement(self.camera).result(timeout=timeout_s).result
        if not m.ok or isinstance(m.result, Failure):
            raise SessionError(m.reason or Reason.no_frame, m.message or "the frame was not measured")
        if m.flange is None or m.flange.T_base_flange is None:
            why = m.flange.message if m.flange is not None else "no robot pose at the frame"
            raise SessionError(Reason.robot_disconnected, why)
        pose = m.result
        used = [t for t in pose.targets if t.used] if isinstance(pose, PoseResult) else []
        # a camera's ROI frames are measured in the window's pixels: the sample keeps the sensor's, which
        # the camera calibration and the image-level refinement project into
        channel = worker.cameras.get(m.camera or "")
        roi = channel.settings.roi if channel is not None else None
        offset = np.array(roi[:2], dtype=np.float64) if roi is not None else np.zeros(2)
        sample = Sample(
            T_base_flange=m.flange.T_base_flange,
            T_field_camera=pose.T_field_camera,
            sigma_position_mm=[float(v) for v in pose.sigma_position_mm],
            sigma_rotation_deg=[float(v) for v in pose.sigma_rotation_deg],
            rms_px=float(pose.rms_px),
            n_targets=pose.n_coded + pose.n_uncoded,
            t_wall=iso_wall(m.t_unix_ns),
            camera=self.camera,
            ids=[t.id for t in used],
            uv=np.array([t.uv for t in used]).reshape(-1, 2) + offset,
        )
        with self.lock:
            before = (list(self.samples), self.result)
            self.samples.append(sample)
            self.result = None
        self._persist_or_undo(before, "the sample is not recorded")
        return sample

    def remove(self, index: int) -> None:
        with self.lock:
            if not 0 <= index < len(self.samples):
                raise SessionError(Reason.not_found, f"no sample #{index}; there are {len(self.samples)}")
            before = (list(self.samples), self.result)
            del self.samples[index]
            self.result = None
        self._persist_or_undo(before, "the sample is not removed")

    def _persist_or_undo(self, before: tuple[list[Sample], dict[str, Any] | None], what: str) -> None:
        """Store the change, or undo it and say so: a change is acknowledged only once it is stored."""
        try:
            self.persist()
        except SessionError as e:
            with self.lock:
                self.samples, self.result = before
            raise SessionError(e.reason, f"{what}: {e.message}") from None

    # --- 3. solve and apply -------------------------------------------------------------------

    def solve(
        self,
        camera: BrownFraser | None = None,
        target_field: Field | None = None,
        run: Callable[..., dict[str, Any]] | None = None,
    ) -> dict[str, Any]:
        """:func:`solve_samples` over the recorded samples, by ``run(fn, *args)`` if given (the
        service's solver process) and stored as the session's result."""
        with self.lock:
            samples = list(self.samples)
        out = (run or _call)(solve_samples, samples, camera, target_field)
        with self.lock:
            self.result = out
        self.persist()  # the result is the samples' (solved again if lost): the answer says when not stored
        return out

    def applied(self, version: int | None) -> str:
        """The result is stored as hand-eye calibration ``version``: "" once the session says so on
        disk too, else why not (the calibration store has the version whatever becomes of the
        session's file, so this is no reason to fail the call that applied it)."""
        self.applied_version = version
        try:
            self.persist()
        except SessionError as e:
            return e.message
        return ""

    def handeye_payload(self) -> dict[str, Any]:
        if self.result is None:
            raise SessionError(Reason.not_solved, "solve the session before applying it")
        return {**self.result, "note": f"hand-eye session of {self.created_wall}, {len(self.samples)} samples"}

    # --- reports ------------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        with self.lock:
            samples = list(self.samples)
            result = self.result
        quality = motion_quality(np.array([s.T_base_flange for s in samples])) if len(samples) >= 3 else None
        return {
            "camera": self.camera,
            "created": self.created_wall,
            "proposals": [
                {"T_base_flange": T.tolist(), "ur_pose_m_rotvec": ur_pose_from_T(T).tolist(), **orientation_report(T)}
                for T in self.proposals
            ],
            "n_samples": len(samples),
            "samples": [s.to_dict() for s in samples],
            "motion": quality,
            "result": result,
            "applied_version": self.applied_version,
            "X_guess": self.X_guess.tolist(),
            "restored": self.restored,
        }

    def export(self) -> dict[str, Any]:
        """The samples in the format of ``posecell calibrate handeye --samples``."""
        with self.lock:
            return {"samples": [s.to_dict() for s in self.samples]}


def _call(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    return fn(*args)


def solve_samples(
    samples: list[Sample], camera: BrownFraser | None = None, target_field: Field | None = None
) -> dict[str, Any]:
    """Tsai–Lenz + pose-level refinement; then, given the camera and field, the refinement on the
    image observations with the robot's errors as unknowns (the answer when it converges)."""
    if len(samples) < 3:
        raise SessionError(
            Reason.poor_motion, f"{len(samples)} samples recorded; at least 3 are needed, 8 or more advised"
        )
    P = np.array([s.T_base_flange for s in samples])
    C = np.array([s.T_field_camera for s in samples])
    sig_pos = float(np.median([np.mean(s.sigma_position_mm) for s in samples]))
    sig_rot = float(np.median([np.mean(s.sigma_rotation_deg) for s in samples]))
    try:
        res = calibrate_handeye(
            P, C, sigma_camera_position_mm=max(sig_pos, 1e-3), sigma_camera_rotation_deg=max(sig_rot, 1e-4)
        )
    except SolveError as e:
        raise SessionError(e.reason, e.message) from None
    out = {"ok": True, **res.to_dict(), "n_samples": len(samples), "method": "pose-level"}
    if camera is not None and target_field is not None and all(s.uv is not None and len(s.ids) >= 4 for s in samples):
        img = [ImageSample(s.T_base_flange, target_field.xyz[target_field.indices_of(s.ids)], s.uv) for s in samples]
        try:
            ref = refine_handeye_on_images(
                camera,
                img,
                res.T_flange_camera,
                res.T_base_field,
                sigma_px=max(0.01, float(np.median([s.rms_px for s in samples]))),
            )
        except SolveError as e:
            out["warnings"] = [*out["warnings"], f"image-level refinement failed: {e.message}"]
        else:
            if ref.converged:
                out.update(
                    method="image-level",
                    T_flange_camera=ref.T_flange_camera.tolist(),
                    T_base_field=ref.T_base_field.tolist(),
                    sigma_flange_camera_position_mm=ref.sigma_flange_camera_position_mm.tolist(),
                    sigma_flange_camera_rotation_deg=ref.sigma_flange_camera_rotation_deg.tolist(),
                    sigma_base_field_position_mm=ref.sigma_base_field_position_mm.tolist(),
                    sigma_base_field_rotation_deg=ref.sigma_base_field_rotation_deg.tolist(),
                    robot_error_position_mm=ref.robot_error_position_mm.tolist(),
                    robot_error_rotation_deg=ref.robot_error_rotation_deg.tolist(),
                    rms_px_per_sample=ref.rms_px.tolist(),
                    sigma0_images=ref.sigma0,
                    pose_level={
                        "T_flange_camera": res.T_flange_camera.tolist(),
                        "T_base_field": res.T_base_field.tolist(),
                    },
                )
    return out
