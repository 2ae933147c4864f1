"""The robot calibration session in the service: plan, visit, record at rest, identify, validate, store; verify.

1. ``start``: plan ``n_poses`` views of the field spread over the joint space (D-optimal among
   reachable candidates, :mod:`service.core.robot.calibration_plan`) and ``n_holdout`` random
   others for validation, and report the plan's observability (the identification Jacobian's
   condition, the parameters frozen because the model or these poses cannot separate them).
   Planning runs in the solver process.
2. The arm visits each pose: mode ``program`` (the simulated cell only) moves it (``move`` one
   pose, or ``run`` all of them in a thread with progress, then solves); mode ``record``: the
   integrator's program moves a real robot, and ``capture`` is called at each resting pose.
   A sample is taken at rest only and averages ``frames_per_pose`` measured frames
   (:mod:`service.runtime.robot_capture`).
3. ``solve`` (solver process): Hayati-β identification of positions and orientations from the
   calibration samples, before/after on the hold-out samples (nominal vs measured, corrected
   vs measured); ``save`` stores the model versioned as calibration kind ``robot``.

:func:`verify` re-visits stored poses (or, in record mode, measures where the robot rests) and
reports the drift of the measured flange from what the stored model predicts at the joints.

The session is kept on disk (:mod:`service.runtime.session_store`): the plan and each sample are
written before they are acknowledged. A service that stops during a run (a restart, a power cut)
offers the session again as ``interrupted`` with every sample it had; ``run`` then visits only the
poses not yet recorded.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.core.measurement import iso_wall
from service.core.results import Reason
from service.core.robot.kinematics import nominal_model
from service.runtime.arm import ArmBusy, ArmClaim
from service.runtime.handeye_session import SessionError
from service.runtime.robot_capture import RobotSample, capture, move_joints, sim_cell
from service.runtime.robot_solve import plan_poses, pose_errors, solve_robot
from service.runtime.solver_process import SolverCrashed
from service.store.formats import FormatError
from service.store.measurements import StorageError
from service.store.tests_store import TestStore

log = logging.getLogger(__name__)

MIN_POSES = 12  # 6 equations a pose, ~30 parameters, twice as many equations as parameters, and a margin


class StartParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["program", "record"] = Field(
        "program", description="program: posecell moves the simulated arm; record: the robot's own program runs"
    )
    n_poses: int = Field(24, ge=1, le=200, description="calibration poses (at least 12; 24 or more advised)")
    n_holdout: int = Field(6, ge=0, le=100, description="validation poses, not used in the fit")
    seed: int = Field(0, ge=0, description="which of the planner's random views")
    frames_per_pose: int = Field(2, ge=1, le=50, description="frames averaged at each pose")
    robot: str | None = Field(None, description="the nominal model (kr15, ur10e, ur5); default the simulated cell's")
    camera: str | None = None


class VerifyParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: Literal["program", "record"] = Field(
        "program", description="program: the simulated arm re-visits stored poses; record: measure where it rests"
    )
    n_poses: int = Field(4, ge=1, le=20, description="program mode: stored poses re-visited")
    frames_per_pose: int = Field(2, ge=1, le=50)
    threshold_mm: float = Field(0.1, gt=0, le=100, description="largest position drift accepted, mm")
    threshold_deg: float = Field(0.02, gt=0, le=10, description="largest orientation drift accepted, deg")
    camera: str | None = None


@dataclass
class RobotSession:
    params: StartParams
    camera: str
    robot: str
    T_base_flange: np.ndarray  # (n, 4, 4) mm, planned; the last n_holdout are validation poses
    q_rad: np.ndarray  # (n, 6) nominal joints there
    observability: dict[str, Any]
    n_candidates: int
    samples: list[RobotSample] = field(default_factory=list)
    result: dict[str, Any] | None = None
    saved_version: int | None = None
    status: str = "planned"  # planned | running | solving | solved | failed | cancelled | interrupted
    progress: float = 0.0
    message: str = "planned: move to the poses and record a sample at each"
    error: str | None = None
    skipped: list[dict[str, Any]] = field(default_factory=list)  # poses of a run that could not be measured
    created_wall: str = field(default_factory=lambda: iso_wall(time.time_ns()))
    restored: bool = False  # read back from disk at the service's start
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    cancel: threading.Event = field(default_factory=threading.Event, repr=False)
    stopping: bool = False  # the service is stopping: a run it cancels is interrupted, not cancelled
    thread: threading.Thread | None = None

    def to_state(self) -> dict[str, Any]:
        """What :meth:`restore` needs."""
        with self.lock:
            samples = [x.to_state() for x in self.samples]
            skipped = list(self.skipped)
        return {
            "params": self.params.model_dump(),
            "camera": self.camera,
            "robot": self.robot,
            "T_base_flange": self.T_base_flange.tolist(),
            "q_rad": self.q_rad.tolist(),
            "observability": self.observability,
            "n_candidates": self.n_candidates,
            "samples": samples,
            "result": self.result,
            "saved_version": self.saved_version,
            "status": self.status,
            "progress": self.progress,
            "message": self.message,
            "error": self.error,
            "skipped": skipped,
            "created": self.created_wall,
        }

    @classmethod
    def restore(cls, state: dict[str, Any]) -> RobotSession:
        """The session :meth:`to_state` wrote; one that was running or solving is ``interrupted``.
        Raises ``KeyError``, ``TypeError`` or ``ValueError`` (pydantic's too) on a state that is not one."""
        samples = [RobotSample.from_state(d) for d in state["samples"]]
        status, message = str(state["status"]), str(state["message"])
        if status in ("running", "solving", "interrupted"):
            status = "interrupted"
            message = (
                f"interrupted: the service stopped during the run; {len(samples)} samples are kept. "
                "Run again to visit the poses not yet recorded, or solve"
            )
        return cls(
            params=StartParams.model_validate(state["params"]),
            camera=str(state["camera"]),
            robot=str(state["robot"]),
            T_base_flange=np.asarray(state["T_base_flange"], dtype=np.float64).reshape(-1, 4, 4),
            q_rad=np.asarray(state["q_rad"], dtype=np.float64).reshape(-1, 6),
            observability=dict(state["observability"]),
            n_candidates=int(state["n_candidates"]),
            samples=samples,
            result=state.get("result"),
            saved_version=state.get("saved_version"),
            status=status,
            progress=float(state["progress"]),
            message=message,
            error=state.get("error"),
            skipped=list(state.get("skipped") or []),
            created_wall=str(state["created"]),
            restored=True,
        )

    @property
    def n_poses(self) -> int:
        return self.params.n_poses

    def is_holdout(self, pose: int | None) -> bool:
        return pose is not None and pose >= self.n_poses

    def summary(self) -> dict[str, Any]:
        with self.lock:
            samples = list(self.samples)
        proposals = [
            {
                "pose": k,
                "holdout": self.is_holdout(k),
                "T_base_flange": T.tolist(),
                "joints_deg": np.degrees(q).round(4).tolist(),
                "recorded": any(s.pose == k for s in samples),
            }
            for k, (T, q) in enumerate(zip(self.T_base_flange, self.q_rad, strict=True))
        ]
        return {
            "mode": self.params.mode,
            "robot": self.robot,
            "camera": self.camera,
            "created": self.created_wall,
            "status": self.status,
            "progress": round(self.progress, 4),
            "progress_message": self.message,
            "error": self.error,
            "n_poses": self.n_poses,
            "n_holdout": self.params.n_holdout,
            "n_candidates": self.n_candidates,
            "observability": self.observability,
            "proposals": proposals,
            "skipped": list(self.skipped),
            "n_samples": len(samples),
            "samples": [s.to_dict() for s in samples],
            "result": None if self.result is None else {k: v for k, v in self.result.items() if k != "model_file"},
            "saved_version": self.saved_version,
            "restored": self.restored,
        }


class RobotCalibration:
    """The one robot calibration session of ``worker``'s cell, and the verification against the stored model."""

    def __init__(
        self, worker: Any, on_verified: Callable[[dict[str, Any]], None] | None = None, tests: TestStore | None = None
    ) -> None:
        self.worker = worker
        # told of every verification's outcome (the plant's MQTT <prefix>/tests, beside the accuracy tests)
        self.on_verified = on_verified
        self.tests = tests  # where each verification is kept (kind "verify"), listed with the accuracy tests
        self.store = getattr(worker, "sessions", None)  # the session on disk (none: in memory only)
        self._busy = threading.Lock()  # one thing moves the arm or solves at a time
        self._save_lock = threading.Lock()
        self.session: RobotSession | None = self._restored()

    # --- kept across restarts ----------------------------------------------------------------------

    def _restored(self) -> RobotSession | None:
        if self.store is None or (state := self.store.load("robot")) is None:
            return None
        try:
            s = RobotSession.restore(state)
        except (KeyError, TypeError, ValueError) as e:
            self.store.set_aside("robot", f"{type(e).__name__}: {e}")
            return None
        self.worker.event(
            "info",
            "session_restored",
            f"robot calibration session of {s.created_wall} restored ({s.status}) with {len(s.samples)} samples",
        )
        return s

    def _persist(self, s: RobotSession) -> None:
        """Write the session (raises ``SessionError`` storage_unavailable)."""
        if self.store is not None:
            with self._save_lock:  # one write at a time, each of the state it read: never out of order
                self.store.save("robot", s.to_state())

    def _persist_quietly(self, s: RobotSession) -> str:
        """Write the session where a failure must not stop what called it (a run goes on, a stored
        model stays stored): "" or why not, said as an event too."""
        try:
            self._persist(s)
        except SessionError as e:
            self.worker.event("warning", "session_not_stored", e.message)
            return e.message
        return ""

    # --- start ---------------------------------------------------------------------------------

    def start(self, body: dict[str, Any] | None) -> RobotSession:
        p = StartParams.model_validate(body or {})
        w = self.worker
        cal = w.calibration
        if cal.camera is None or cal.field is None or cal.handeye is None:
            raise SessionError(
                Reason.not_calibrated, "the session measures the flange: camera, field and hand-eye calibrations first"
            )
        camera = p.camera or next(iter(w.processors), None)
        if camera is None or camera not in w.processors:
            raise SessionError(Reason.not_found, f"no camera named {camera!r}")
        cell = sim_cell(w)
        if p.mode == "program" and cell is None:
            raise SessionError(
                Reason.unsupported,
                "mode 'program' moves the arm, which posecell does only in the simulated cell; "
                "with a real robot use mode 'record' and move it with its own program",
            )
        robot = p.robot or (w.cell.cell.config.robot if w.cell.active else None)
        if robot is None:
            raise SessionError(Reason.bad_input, "name the robot's nominal model ('robot': kr15, ur10e or ur5)")
        try:
            nominal = nominal_model(robot)
        except ValueError as e:
            raise SessionError(Reason.bad_input, str(e)) from None
        if p.n_poses < MIN_POSES:
            raise SessionError(
                Reason.poor_motion,
                f"{p.n_poses} poses cannot determine the arm's ~30 kinematic errors (6 equations a pose, twice as "
                f"many equations as parameters needed): plan at least {MIN_POSES}, 24 or more advised",
            )
        if w.robot is None or not w.robot.connected:
            raise SessionError(Reason.robot_disconnected, "the robot is not connected: its joints seed the plan")
        q_seed = w.robot.latest().q_rad
        if not self._busy.acquire(blocking=False):
            raise SessionError(Reason.busy, "the robot calibration is moving the arm or solving; wait for it")
        try:
            plan = w.solver.run(
                plan_poses,
                nominal,
                cal.camera,
                cal.field,
                cal.handeye.T_base_field,
                cal.handeye.T_flange_camera,
                np.asarray(q_seed, dtype=np.float64),
                p.n_poses,
                p.n_holdout,
                p.seed,
            )
        except SolverCrashed as e:
            raise SessionError(Reason.solver_unavailable, f"{e}; start the session again") from None
        finally:
            self._busy.release()
        session = RobotSession(
            p, camera, robot, plan["T_base_flange"], plan["q_rad"], plan["observability"], plan["n_candidates"]
        )
        self._persist(session)  # a plan that is not stored is not started (it replaces the one on disk)
        self.session = session
        w.event("info", "robot_calibration", f"robot calibration session planned: {p.n_poses} + {p.n_holdout} poses")
        return self.session

    def get(self) -> RobotSession:
        if self.session is None:
            raise SessionError(
                Reason.not_found, "no robot calibration session; start one with POST /calibration/robot/session"
            )
        return self.session

    def discard(self) -> None:
        s = self.session
        if s is not None and s.thread is not None:
            s.cancel.set()
            s.thread.join(timeout=30.0)
        self.session = None
        if s is not None and self.store is not None:
            self.store.discard("robot")

    # --- visiting and recording ------------------------------------------------------------------

    def _move(self, s: RobotSession, k: int, cancel: threading.Event | None = None) -> float:
        if not 0 <= k < len(s.T_base_flange):
            raise SessionError(Reason.not_found, f"no pose #{k}; the plan has {len(s.T_base_flange)}")
        return move_joints(self.worker, s.q_rad[k], cancel)

    def _exclusive(self, s: RobotSession) -> None:
        if s.status in ("running", "solving") or not self._busy.acquire(blocking=False):
            raise SessionError(Reason.busy, "the robot calibration is moving the arm or solving; wait for it")

    def move(self, k: int) -> float:
        s = self.get()
        self._exclusive(s)
        try:
            arm = self._claim_arm(f"the robot calibration's move to pose #{k}")
            try:
                return self._move(s, k)
            finally:
                self.worker.arm.release(arm)
        finally:
            self._busy.release()

    def capture(self, pose: int | None) -> RobotSample:
        s = self.get()
        if pose is not None and not 0 <= pose < len(s.T_base_flange):
            raise SessionError(Reason.not_found, f"no pose #{pose}; the plan has {len(s.T_base_flange)}")
        self._exclusive(s)
        try:
            sample = capture(self.worker, s.camera, s.params.frames_per_pose, pose, s.is_holdout(pose))
        finally:
            self._busy.release()
        with s.lock:
            before = (list(s.samples), s.result)
            s.samples = [x for x in s.samples if pose is None or x.pose != pose] + [sample]
            s.result = None
        self._persist_or_undo(s, before, "the sample is not recorded")
        return sample

    def remove(self, index: int) -> None:
        s = self.get()
        with s.lock:
            if not 0 <= index < len(s.samples):
                raise SessionError(Reason.not_found, f"no sample #{index}; there are {len(s.samples)}")
            before = (list(s.samples), s.result)
            del s.samples[index]
            s.result = None
        self._persist_or_undo(s, before, "the sample is not removed")

    def _persist_or_undo(
        self, s: RobotSession, before: tuple[list[RobotSample], dict[str, Any] | None], what: str
    ) -> None:
        """Store the change, or undo it and say so: a change is acknowledged only once it is stored."""
        try:
            self._persist(s)
        except SessionError as e:
            with s.lock:
                s.samples, s.result = before
            raise SessionError(e.reason, f"{what}: {e.message}") from None

    # --- solving and storing -------------------------------------------------------------------------

    def _solve(self, s: RobotSession) -> dict[str, Any]:
        with s.lock:
            samples = list(s.samples)
        if not samples:
            raise SessionError(
                Reason.poor_motion, "no samples are recorded yet: record a sample at each planned pose first"
            )
        q = np.array([x.q_rad for x in samples])
        T = np.array([x.T_base_flange_measured for x in samples])
        holdout = np.array([x.holdout for x in samples])
        sp = float(np.median([np.linalg.norm(x.sigma_position_mm) for x in samples]))
        sr = float(np.median([np.linalg.norm(x.sigma_rotation_deg) for x in samples]))
        try:
            out: dict[str, Any] = self.worker.solver.run(
                solve_robot, s.robot, nominal_model(s.robot), q, T, holdout, sp, sr
            )
        except SolverCrashed as e:
            raise SessionError(Reason.solver_unavailable, f"{e}; the samples are kept, solve again") from None
        with s.lock:
            s.result = out
        return out

    def solve(self) -> dict[str, Any]:
        s = self.get()
        self._exclusive(s)
        try:
            out = self._solve(s)
            s.status, s.message, s.error = "solved", "solved: save it to use it", None
            self._persist(s)  # the result is the samples' (solved again if lost): a 503 says it is not kept
        finally:
            self._busy.release()
        return {k: v for k, v in out.items() if k != "model_file"}

    def save(self, note: str = "") -> int | None:
        s = self.get()
        if s.result is None:
            raise SessionError(Reason.not_solved, "solve the session before saving its model")
        payload = {**s.result["model_file"], "note": note or f"robot calibration session of {s.created_wall}"}
        try:
            version = self.worker.calibration.update("robot", payload, note=payload["note"][:1000])
        except FormatError as e:
            raise SessionError(Reason.bad_input, f"the identified model is not stored: {e}") from None
        s.saved_version = version
        self.worker.event("info", "calibration_changed", f"robot model version {version} from a calibration session")
        self._persist_quietly(s)  # the model is stored (versioned) whatever becomes of the session's file
        return version

    # --- the simulated cell's one call -----------------------------------------------------------------

    def run(self) -> RobotSession:
        """Program mode: visit every planned pose, record, solve; in a thread, with progress."""
        s = self.get()
        if s.params.mode != "program":
            raise SessionError(
                Reason.unsupported, "run is for mode 'program' (the simulated cell); record samples instead"
            )
        self._exclusive(s)
        try:
            arm = self._claim_arm("the robot calibration session")
        except SessionError:
            self._busy.release()
            raise
        # an interrupted run goes on where it stopped: the poses already recorded are not visited again
        resume = s.status == "interrupted"
        s.status, s.progress, s.error = "running", 0.0, None
        s.cancel.clear()
        self._persist_quietly(s)
        s.thread = threading.Thread(target=self._run, args=(s, arm, resume), name="robot-calibration", daemon=True)
        s.thread.start()
        return s

    def _claim_arm(self, owner: str) -> ArmClaim:
        try:
            return self.worker.arm.claim(owner)
        except ArmBusy as e:
            raise SessionError(Reason.busy, str(e)) from None

    def _run(self, s: RobotSession, arm: ArmClaim, resume: bool = False) -> None:
        try:
            n = len(s.T_base_flange)
            with s.lock:
                recorded = {x.pose for x in s.samples} if resume else set()
            for k in range(n):
                if k in recorded:
                    continue
                s.progress, s.message = k / (n + 1), f"pose {k + 1} of {n}{' (hold-out)' if s.is_holdout(k) else ''}"
                self._move(s, k, s.cancel)
                try:
                    sample = capture(self.worker, s.camera, s.params.frames_per_pose, k, s.is_holdout(k))
                except SessionError as e:  # one pose that cannot be measured does not end the session:
                    # it is named, and the solve refuses if too few are left
                    s.skipped.append({"pose": k, "reason": str(e.reason), "message": e.message})
                    continue
                with s.lock:
                    s.samples = [x for x in s.samples if x.pose != k] + [sample]
                self._persist_quietly(s)  # the run goes on; the event says when a sample is not kept
            self.worker.arm.release(arm)  # the solve does not move it
            s.status, s.progress, s.message = "solving", n / (n + 1), "identifying the kinematic errors"
            self._solve(s)
            s.status, s.progress, s.message = "solved", 1.0, "solved: save it to use it"
        except SessionError as e:
            cancelled = s.cancel.is_set()
            if cancelled and s.stopping:  # the service stops: offered again, as interrupted, at its start
                s.status, s.error, s.message = "interrupted", None, "interrupted: the service stopped"
            else:
                s.status = "cancelled" if cancelled else "failed"
                s.error = None if cancelled else e.message
                s.message = s.status if cancelled else f"failed: {e.message}"
        except Exception as e:  # a bug must not leave the session "running"
            log.exception("robot calibration run")
            s.status, s.error, s.message = "failed", f"internal error: {e!r}", "failed"
        finally:
            if not (s.stopping and s.status == "failed"):
                self._persist_quietly(s)
            self.worker.arm.release(arm)
            self._busy.release()

    # --- verification --------------------------------------------------------------------------------

    def verify(self, body: dict[str, Any] | None) -> dict[str, Any]:
        p = VerifyParams.model_validate(body or {})
        w = self.worker
        model = w.calibration.robot
        if model is None:
            raise SessionError(
                Reason.not_calibrated,
                "no robot model is stored to verify: run the robot calibration session and save it first",
            )
        camera = p.camera or next(iter(w.processors), None)
        if camera is None or camera not in w.processors:
            raise SessionError(Reason.not_found, f"no camera named {camera!r}")
        if p.mode == "program" and sim_cell(w) is None:
            raise SessionError(
                Reason.unsupported,
                "mode 'program' moves the arm, which posecell does only in the simulated cell; with a real robot "
                "stop it at a stored pose (or any pose) and verify with mode 'record'",
            )
        stored = [
            np.asarray(x["q_rad"], dtype=np.float64) for x in (w.calibration.payload("robot") or {}).get("poses", [])
        ]
        if p.mode == "program" and not stored:
            raise SessionError(
                Reason.bad_input, "the stored robot model carries no poses to re-visit (not from a session)"
            )
        picks = (
            np.unique(np.linspace(0, len(stored) - 1, min(p.n_poses, len(stored))).round().astype(int))
            if stored
            else np.zeros(0, dtype=int)
        )
        if not self._busy.acquire(blocking=False):
            raise SessionError(Reason.busy, "the robot calibration is moving the arm or solving; wait for it")
        samples: list[tuple[int | None, RobotSample]] = []
        try:
            if p.mode == "record":
                samples.append((None, capture(w, camera, p.frames_per_pose)))
            else:
                arm = self._claim_arm("the robot model's verification")
                try:
                    for k in picks:
                        move_joints(w, stored[int(k)])
                        samples.append((int(k), capture(w, camera, p.frames_per_pose)))
                finally:
                    w.arm.release(arm)
        finally:
            self._busy.release()
        q = np.array([x.q_rad for _, x in samples])
        T_meas = np.array([x.T_base_flange_measured for _, x in samples])
        drift = pose_errors(model.corrected.fk(q), T_meas)
        nominal_err = pose_errors(model.nominal.fk(q), T_meas)
        ok = drift["position_max_mm"] <= p.threshold_mm and drift["orientation_max_deg"] <= p.threshold_deg
        poses = [
            {
                "stored_pose": k,
                "position_mm": dp,
                "orientation_deg": dr,
                "joints_deg": np.degrees(x.q_rad).round(4).tolist(),
            }
            for (k, x), dp, dr in zip(samples, drift["per_pose_mm"], drift["per_pose_deg"], strict=True)
        ]
        verdict = "ok" if ok else "drifted"
        w.event(
            "info" if ok else "warning",
            "robot_verify",
            f"robot model version {w.calibration.versions.get('robot')} verified: {verdict}, "
            f"drift {drift['position_max_mm']:.3f} mm / {drift['orientation_max_deg']:.4f} deg at most",
        )
        out = {
            "ok": True,
            "verdict": verdict,
            "model_version": w.calibration.versions.get("robot"),
            "threshold_mm": p.threshold_mm,
            "threshold_deg": p.threshold_deg,
            "drift": {k: v for k, v in drift.items() if not k.startswith("per_pose")},
            "nominal": {k: v for k, v in nominal_err.items() if not k.startswith("per_pose")},
            "poses": poses,
        }
        out["test_id"], out["storage_error"] = self._keep(p, out)
        if self.on_verified is not None:
            message: dict[str, Any] = {
                "kind": "verify",
                "status": "done",
                "mode": p.mode,
                "t_wall": iso_wall(time.time_ns()),
                "id": out["test_id"],
            }
            message["report"] = {k: v for k, v in out.items() if k not in ("ok", "poses", "test_id", "storage_error")}
            try:
                self.on_verified(message)
            except Exception:  # the plant's publisher never fails the check itself
                log.exception("publishing the verification")
        return out

    def _keep(self, p: VerifyParams, out: dict[str, Any]) -> tuple[int | None, str]:
        """Store the verification with its per-pose drift (committed), so that the shift's checks have a
        history (``GET /tests``, ``GET /tests/{id}/report.json``): (its id, "") or (None, why not).

        A store that refuses does not undo the check the arm has made: the answer says it is not kept."""
        if self.tests is None:
            return None, "no tests store"
        report = {k: v for k, v in out.items() if k != "ok"}
        try:
            test_id = self.tests.create("verify", p.mode, p.model_dump())
            self.tests.update(test_id, status="done", progress=1.0, progress_message=out["verdict"], report=report)
        except StorageError as e:
            self.worker.event("warning", "robot_verify_not_stored", f"the verification was not stored: {e}")
            return None, str(e)
        return test_id, ""

    def close(self) -> None:
        """The service stops: a run is stopped and the session kept on disk as it stands (interrupted)."""
        s = self.session
        if s is not None and s.thread is not None and s.thread.is_alive():
            s.stopping = True
            s.cancel.set()
            s.thread.join(timeout=30.0)
