"""The robot's accuracy tests in the running service: one at a time, in a thread of their own.

:class:`AccuracyTests` starts a test (:mod:`service.runtime.accuracy_plans` says what each kind
does), runs it in a background thread and stores it (:class:`~service.store.tests_store.TestStore`):
the test's row before ``start`` returns, its progress as it goes, its raw samples about once a
second and its report at the end. It never slows the measurement: it subscribes to the worker's
results with a callback that only puts the result into a bounded queue (a full queue drops the
result and counts it), and everything else happens in the test's thread.

Mode ``program`` needs the simulated cell in this process (``sim.transport = "direct"``): the test
commands the arm through the simulated controller (``move_to``) and plays the circle's joint
trajectory on the cell. Anything else is refused (``unsupported``, HTTP 409): posecell never
commands a real robot. Mode ``record`` works with any robot: the integrator's program runs, and
the frames between start and ``stop`` are segmented from the robot's reported motion
(:mod:`service.core.accuracy.segment`). ``stop`` finishes a recording and cancels a program;
a cancelled program leaves the simulated arm holding where it was.

After a simulated program the arm holds its last pose: the cell's own looping program does not
resume (the hand-eye session's moves behave alike).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import ValidationError

from service.core.accuracy.segment import at_rest, circle_directions, group_positions, rest_runs
from service.core.geometry.frames import inv_T, rotation_angle_deg
from service.core.measurement import Measurement
from service.core.results import PoseResult, Reason, SolveError
from service.runtime.accuracy_analysis import Sample, circle_report, iso9283_report, table1_report
from service.runtime.accuracy_plans import (
    KINDS,
    PARAMS,
    REST_TOL_DEG,
    REST_TOL_MM,
    REST_WINDOW_S,
    CircleParams,
    Iso9283Params,
    PlanError,
    Stop,
    Table1Params,
    circle_plan,
    circle_trajectories,
    iso9283_stops,
    measured_flange_sigma,
    table1_stops,
)
from service.runtime.arm import ArmBusy, ArmClaim
from service.sim.robot import JointTrajectory
from service.store.measurements import StorageError
from service.store.tests_store import INTERRUPTED, TestStore

log = logging.getLogger(__name__)

BULKY = ("points", "profile", "attained")  # a report's per-point arrays (for its figures)

QUEUE_MAX = 2000  # results waiting for the test's thread (~2 min at 15 Hz): beyond, dropped and counted
FLUSH_EVERY_S = 1.0  # samples are committed in batches this often
REST_TIMEOUT_S = 10.0  # the arm must be found at rest this long after its move
FRAME_TIMEOUT_S = 5.0  # and measured frames must come within this (plus the frames' own time)
CIRCLE_DRAIN_S = 1.0  # after the circle's end, frames exposed before it are still being measured


class TestError(Exception):
    """A test that cannot be started or stopped now: ``reason`` (a :class:`Reason`) and a sentence."""

    __test__ = False

    def __init__(self, reason: Reason, message: str) -> None:
        super().__init__(message)
        self.reason, self.message = reason, message


class _Cancelled(Exception):
    pass


@dataclass
class _Run:
    id: int
    kind: str
    params: Any
    camera: str
    cancel: threading.Event = field(default_factory=threading.Event)
    finish: threading.Event = field(default_factory=threading.Event)  # record mode: stop and analyse
    shutdown: bool = False  # cancelled because the service stops: "interrupted", as after a crash
    results: queue.Queue[Measurement] = field(default_factory=lambda: queue.Queue(QUEUE_MAX))
    samples: list[Sample] = field(default_factory=list)
    unflushed: int = 0
    n_dropped: int = 0
    n_unusable: int = 0  # frames of the camera without a measured, paired flange pose
    last_problem: str = ""
    progress: float = 0.0
    message: str = "queued"
    t0_ns: int = field(default_factory=time.time_ns)
    last_flush_ns: int = 0
    centre_mm: list[float] | None = None  # the circle's nominal centre, base mm
    thread: threading.Thread | None = None
    arm: ArmClaim | None = None  # its claim of the simulated arm (program mode)

    def on_result(self, m: Measurement) -> None:  # the processing thread: never blocks
        try:
            self.results.put_nowait(m)
        except queue.Full:
            self.n_dropped += 1


class AccuracyTests:
    """Starts, runs, stops and lists the accuracy tests of ``worker``'s cell, stored in ``store``."""

    def __init__(
        self, worker: Any, store: TestStore, on_finished: Callable[[dict[str, Any]], None] | None = None
    ) -> None:
        self.worker, self.store = worker, store
        # told of every test that ends (the plant's MQTT <prefix>/tests); called in the test's thread
        self.on_finished = on_finished
        self._lock = threading.Lock()
        self._active: _Run | None = None
        n = store.mark_interrupted()
        if n:
            worker.event("warning", "test_interrupted", f"{n} accuracy test(s) were running at the last stop")

    # --- the API's calls ----------------------------------------------------------------------

    def start(self, kind: str, body: dict[str, Any] | None) -> dict[str, Any]:
        """Validate, store (committed) and start a test; its summary. Raises :class:`TestError`."""
        if kind not in KINDS:
            raise TestError(Reason.not_found, f"no test kind {kind!r}; the kinds are {', '.join(KINDS)}")
        try:
            params = PARAMS[kind].model_validate(body or {})
        except ValidationError as e:
            problems = "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}" for err in e.errors())
            raise TestError(Reason.bad_input, f"invalid {kind} test parameters: {problems}") from None
        camera = params.camera or next(iter(self.worker.processors), None)
        if camera is None or camera not in self.worker.processors:
            raise TestError(Reason.not_found, f"no camera named {camera!r}; cameras: {sorted(self.worker.processors)}")
        if self.worker.calibration.handeye is None:
            raise TestError(
                Reason.not_calibrated, "the tests measure the flange: a hand-eye calibration is needed first"
            )
        cell = self._sim_cell() if params.mode == "program" else None
        plan: Any = None
        if params.mode == "program":
            if cell is None:
                raise TestError(
                    Reason.unsupported,
                    "mode 'program' moves the arm, which posecell does only in the simulated cell (sim.transport "
                    "= 'direct'); with a real robot start its own program and use mode 'record'",
                )
            try:
                plan = self._plan(cell, kind, params)
            except PlanError as e:
                raise TestError(Reason.bad_input, str(e)) from None
        with self._lock:
            if self._active is not None:
                raise TestError(
                    Reason.busy, f"test {self._active.id} ({self._active.kind}) is running; stop it or wait for it"
                )
            arm = None
            if params.mode == "program":
                try:
                    arm = self.worker.arm.claim(f"the {kind} accuracy test")
                except ArmBusy as e:
                    raise TestError(Reason.busy, str(e)) from None
            try:
                test_id = self.store.create(kind, params.mode, {**params.model_dump(), "camera": camera})
            except BaseException:
                if arm is not None:
                    self.worker.arm.release(arm)
                raise
            run = _Run(test_id, kind, params, camera, arm=arm)
            self._active = run
        run.thread = threading.Thread(target=self._run, args=(run, cell, plan), name=f"test-{test_id}", daemon=True)
        run.thread.start()
        self.worker.event("info", "test_started", f"accuracy test {test_id} ({kind}, {params.mode}) started")
        return self.get(test_id)

    def stop(self, test_id: int) -> dict[str, Any]:
        """Record mode: finish and analyse; program mode: cancel. A finished test is left as it is."""
        test = self.get(test_id)
        run = self._active
        if run is None or run.id != test_id:
            raise TestError(Reason.not_solved, f"test {test_id} is {test['status']}, not running")
        (run.finish if run.params.mode == "record" else run.cancel).set()
        if run.thread is not None:
            run.thread.join(timeout=30.0)
        return self.get(test_id, full=True)

    def get(self, test_id: int, full: bool = False) -> dict[str, Any]:
        test = self.store.get(test_id, full=full)
        if test is None:
            raise TestError(Reason.not_found, f"no accuracy test {test_id}")
        run = self._active
        if run is not None and run.id == test_id and test["status"] in ("queued", "running"):
            test.update(progress=round(run.progress, 4), progress_message=run.message, n_samples=len(run.samples))
            test["n_dropped"] = run.n_dropped
        return test

    def recent(self, limit: int = 100) -> list[dict[str, Any]]:
        """The tests newest first, a running one with its live progress."""
        tests = self.store.recent(limit)
        run = self._active
        for t in tests:
            if run is not None and t["id"] == run.id and t["status"] in ("queued", "running"):
                t.update(progress=round(run.progress, 4), progress_message=run.message, n_samples=len(run.samples))
        return tests

    def close(self, timeout_s: float = 10.0) -> None:
        """Cancel a running test (the service is stopping) and wait for its thread."""
        run = self._active
        if run is not None:
            run.shutdown = True
            run.cancel.set()
            if run.thread is not None:
                run.thread.join(timeout=timeout_s)

    # --- the test's thread --------------------------------------------------------------------

    def _sim_cell(self) -> Any:
        """The simulated cell, if this process runs it and its controller (the only robot posecell moves)."""
        rt = self.worker.cell
        robot = self.worker.robot
        if not rt.active or rt.standins or robot is None or not callable(getattr(robot, "move_to", None)):
            return None
        return rt.cell

    @staticmethod
    def _plan(cell: Any, kind: str, params: Any) -> Any:
        if kind == "circle":
            return circle_plan(cell, params)
        if kind == "iso9283":
            return iso9283_stops(cell, params)
        return table1_stops(cell, params)

    def _run(self, run: _Run, cell: Any, plan: Any) -> None:
        status, error, report, details = "failed", None, None, None
        unsubscribe = self.worker.subscribe(run.on_result)
        # every stop and lap is measured alike: the exposure the control settled on before the test
        self.worker.hold_exposure(f"accuracy test {run.id} ({run.kind}) is running")
        try:
            self.store.update(run.id, status="running", progress_message="starting")
            if run.params.mode == "record":
                self._record(run)
            elif run.kind == "circle":
                self._program_circle(run, cell, plan)
            else:
                self._program_stops(run, plan)
            unsubscribe()
            self._set(run, 1.0, "analysing")
            report, details = self._analyse(run)
            status = "done"
        except _Cancelled:
            status, error = ("interrupted", INTERRUPTED) if run.shutdown else ("cancelled", "stopped on request")
            if cell is not None:
                self._hold(cell)
        except (SolveError, PlanError) as e:
            error = getattr(e, "message", None) or str(e)
        except StorageError as e:
            error = f"the test's data could not be stored: {e}"
        except Exception as e:  # a bug must not leave the test "running"
            log.exception("accuracy test %d", run.id)
            error = f"internal error: {e!r}"
        finally:
            unsubscribe()
            self.worker.hold_exposure("")
            if run.arm is not None:
                self.worker.arm.release(run.arm)  # held still by _hold if it was stopped
        if details is not None:
            details.update(n_dropped=run.n_dropped, n_unusable=run.n_unusable)
        try:
            self._flush(run)
            self.store.update(
                run.id,
                status=status,
                progress=1.0 if status == "done" else run.progress,
                progress_message=status if status != "failed" else f"failed: {error}",
                error=error,
                report=report,
                details=details,
            )
        except StorageError as e:
            log.error("accuracy test %d could not be stored: %s", run.id, e)
        with self._lock:
            self._active = None
        self.worker.event(
            "info" if status == "done" else "warning",
            "test_finished",
            f"accuracy test {run.id} ({run.kind}) {status}{f': {error}' if error else ''}",
        )
        if self.on_finished is not None:
            # the figures without the raw points (those are GET /tests/{id}/report.json's)
            figures = {k: v for k, v in (report or {}).items() if k not in BULKY}
            message = {"id": run.id, "kind": run.kind, "status": status, "error": error, "report": figures}
            try:
                self.on_finished({**message, "details": details})
            except Exception:
                log.exception("telling of the end of accuracy test %d", run.id)

    def _analyse(self, run: _Run) -> tuple[dict[str, Any], dict[str, Any]]:
        p = run.params
        if run.kind == "circle":
            report, details = circle_report(run.samples, p.radius_mm, run.centre_mm)
        elif run.kind == "iso9283":
            report, details = iso9283_report(run.samples)
        else:
            report, details = table1_report(run.samples)
        return report, details

    # --- samples --------------------------------------------------------------------------------

    def _set(self, run: _Run, progress: float, message: str) -> None:
        run.progress, run.message = float(np.clip(progress, 0.0, 1.0)), message

    def _flush(self, run: _Run) -> None:
        if run.unflushed:
            batch = run.samples[len(run.samples) - run.unflushed :]
            self.store.add_samples(run.id, batch)
            run.unflushed = 0
            self.store.update(run.id, progress=run.progress, progress_message=run.message)

    def _sample(self, run: _Run, m: Measurement) -> Sample | None:
        """The sample of a result of the test's camera, or None (counted) when it has no measured flange."""
        if m.camera != run.camera or m.is_outage:
            return None
        f = m.flange
        if not m.ok or not isinstance(m.result, PoseResult) or f is None or f.T_base_flange_measured is None:
            run.n_unusable += 1
            run.last_problem = m.message or (f.message if f is not None else "") or "no measured flange pose"
            return None
        if f.T_base_flange is None:
            run.n_unusable += 1
            run.last_problem = f.message or "no robot pose at the exposure"
            return None
        handeye = self.worker.calibration.handeye
        sp, sr = measured_flange_sigma(m.result, handeye.T_flange_camera, handeye.T_base_field)
        t_ns = int(m.t_unix_ns)
        s: Sample = {
            "t_exposure_unix_ns": t_ns,
            "t_s": (t_ns - run.t0_ns) * 1e-9,
            "t_exposure_host_ns": m.t_exposure_host_ns,
            "label": None,
            "visit": None,
            "stop": None,
            "camera": m.camera,
            "T_base_flange_measured": f.T_base_flange_measured.tolist(),
            "T_base_flange_reported": f.T_base_flange.tolist(),
            "sigma_position_mm": sp.tolist(),
            "sigma_rotation_deg": sr.tolist(),
            "rms_px": float(m.result.rms_px),
        }
        cell = self._sim_cell() if m.T_field_camera_true is not None else None
        if cell is not None:  # the simulation's truth: the true arm's flange at the true exposure
            T_true = cell.T_base_field @ m.T_field_camera_true @ inv_T(cell.T_flange_camera)
            s["T_base_flange_true"] = T_true.tolist()
        return s

    def _add(self, run: _Run, s: Sample) -> None:
        run.samples.append(s)
        run.unflushed += 1
        if time.monotonic_ns() - run.last_flush_ns > FLUSH_EVERY_S * 1e9:
            self._flush(run)
            run.last_flush_ns = time.monotonic_ns()

    def _next(self, run: _Run, timeout_s: float) -> Sample | None:
        """The next usable sample of the test's camera, or None after ``timeout_s``; raises when cancelled."""
        deadline = time.monotonic() + timeout_s
        while True:
            if run.cancel.is_set():
                raise _Cancelled
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                m = run.results.get(timeout=min(remaining, 0.1))
            except queue.Empty:
                continue
            s = self._sample(run, m)
            if s is not None:
                return s

    def _wait(self, run: _Run, seconds: float) -> None:
        """Let ``seconds`` pass, discarding the frames of that time (the arm moves)."""
        deadline = time.monotonic() + seconds
        while (remaining := deadline - time.monotonic()) > 0:
            self._next(run, remaining)

    # --- program mode (the simulated cell) --------------------------------------------------------

    def _cell_now_s(self) -> float:
        return (time.monotonic_ns() - self.worker.cell.epoch_ns) * 1e-9

    def _hold(self, cell: Any) -> None:
        t = self._cell_now_s() + 0.05
        q = cell.q_at(t)
        cell.command_trajectory(JointTrajectory(np.array([0.0, 1.0]), np.array([q, q])), t)

    def _move_and_settle(self, run: _Run, T_base_flange: np.ndarray, speed_mm_s: float) -> int:
        """Move the simulated arm, wait until the controller reports it at rest; that instant (host ns)."""
        duration_s = self.worker.robot.move_to(T_base_flange, speed_mm_s)
        self._wait(run, duration_s + 0.05)
        deadline = time.monotonic() + REST_TIMEOUT_S
        while time.monotonic() < deadline:
            now = time.monotonic_ns()
            recent = self.worker.robot.samples_between(now - int(REST_WINDOW_S * 1e9), now)
            if len(recent) >= 2:
                last = recent[-1].T_base_flange
                spread_mm = max(float(np.linalg.norm(r.T_base_flange[:3, 3] - last[:3, 3])) for r in recent)
                spread_deg = max(rotation_angle_deg(last[:3, :3].T @ r.T_base_flange[:3, :3]) for r in recent)
                if spread_mm < REST_TOL_MM and spread_deg < REST_TOL_DEG:
                    return now
            self._wait(run, 0.05)
        raise PlanError(f"the arm was not reported at rest within {REST_TIMEOUT_S:g} s of its move")

    def _collect_stop(self, run: _Run, stop: Stop, k: int, n_frames: int, t_from_ns: int) -> None:
        got = 0
        deadline = time.monotonic() + FRAME_TIMEOUT_S + n_frames
        while got < n_frames:
            s = self._next(run, max(0.0, deadline - time.monotonic()))
            if s is None:
                raise PlanError(
                    f"stop {k + 1} ({stop.label}, visit {stop.visit}): {got} of {n_frames} frames measured within "
                    f"{FRAME_TIMEOUT_S + n_frames:g} s ({run.last_problem or 'no frames came'})"
                )
            if s["t_exposure_host_ns"] is None or s["t_exposure_host_ns"] < t_from_ns:
                continue  # exposed before the arm was found at rest
            s.update(label=stop.label, visit=stop.visit, stop=k, T_base_flange_cmd=stop.T_base_flange_cmd.tolist())
            self._add(run, s)
            got += 1

    def _program_stops(self, run: _Run, stops: list[Stop]) -> None:
        p: Iso9283Params | Table1Params = run.params
        for k, stop in enumerate(stops):
            self._set(run, k / len(stops), f"stop {k + 1} of {len(stops)}: {stop.label}, visit {stop.visit}")
            self._move_and_settle(run, stop.T_base_flange_cmd, p.speed_mm_s)
            self._wait(run, p.dwell_s)
            self._collect_stop(run, stop, k, p.frames_per_stop, time.monotonic_ns())

    def _program_circle(self, run: _Run, cell: Any, plan: Any) -> None:
        p: CircleParams = run.params
        run.centre_mm = plan.T_base_centre[:3, 3].tolist()
        self._set(run, 0.0, "moving to the circle's start")
        self._move_and_settle(run, plan.T_base_flange_start, 250.0)
        t0 = self._cell_now_s() + 0.2  # the trajectory is planned from the joints there, then played
        ccw, cw = circle_trajectories(cell, plan, cell.q_at(t0))
        cell.command_trajectory(ccw, t0)
        cell.command_trajectory(cw, t0 + ccw.duration_s)
        t1 = t0 + ccw.duration_s
        t2 = t1 + cw.duration_s
        epoch_ns = self.worker.cell.epoch_ns
        while (now := self._cell_now_s()) < t2 + CIRCLE_DRAIN_S:
            phase, t_in = ("counter-clockwise", now - t0) if now < t1 else ("clockwise", now - t1)
            lap = min(max(int(t_in / plan.period_s) + 1, 1), p.laps)
            self._set(run, (now - t0) / (t2 - t0), f"{phase}, lap {lap} of {p.laps}")
            s = self._next(run, 0.1)
            if s is None or s["t_exposure_host_ns"] is None:
                continue
            t = (s["t_exposure_host_ns"] - epoch_ns) * 1e-9
            if not t0 <= t < t2:
                continue
            label, t_in = ("ccw", t - t0) if t < t1 else ("cw", t - t1)
            s.update(label=label, visit=int(t_in / plan.period_s) + 1)
            self._add(run, s)

    # --- record mode (any robot) ------------------------------------------------------------------

    def _record(self, run: _Run) -> None:
        p = run.params
        run.centre_mm = p.centre_mm if isinstance(p, CircleParams) else None
        while not run.finish.is_set():
            self._set(run, 0.0, f"recording: {len(run.samples)} frames; POST /tests/{run.id}/stop to finish")
            s = self._next(run, 0.2)
            if s is not None:
                self._add(run, s)
        self._set(run, 1.0, "segmenting")
        self._flush(run)
        try:
            label_recording(run.kind, run.samples, p)
        finally:  # the labels found (or None, if segmenting failed) replace the raw rows' blanks
            self.store.add_samples(run.id, run.samples, replace=True)


def label_recording(kind: str, samples: list[Sample], p: Any) -> None:
    """Label a recording in place from the robot's reported motion (:mod:`service.core.accuracy.segment`):
    circle directions and runs, or stops grouped into poses (named P1 … by first visit) or positions."""
    if len(samples) < 3:
        raise SolveError(Reason.bad_input, f"{len(samples)} frames recorded; nothing to segment")
    t = np.array([s["t_s"] for s in samples])
    T = np.array([s["T_base_flange_reported"] for s in samples])
    rest = at_rest(t, T[:, :3, 3], T[:, :3, :3], tol_mm=REST_TOL_MM, tol_deg=REST_TOL_DEG)
    if kind == "circle":
        directions = circle_directions(T[:, :3, 3], ~rest)
        run_no, prev = 0, None
        for s, d in zip(samples, directions, strict=True):
            if d is not None and d != prev:
                run_no += 1
            prev = d if d is not None else prev
            s.update(label=d, visit=run_no if d is not None else None)
        return
    runs = rest_runs(rest, p.frames_per_stop)
    if not runs:
        raise SolveError(
            Reason.bad_input,
            f"the robot never rested for {p.frames_per_stop} frames (within {REST_TOL_MM} mm, {REST_TOL_DEG} deg)",
        )
    centres = np.array([T[a:b, :3, 3].mean(axis=0) for a, b in runs])
    groups = group_positions(centres, p.pose_tol_mm)
    visits: dict[int, int] = {}
    for k, ((a, b), g) in enumerate(zip(runs, groups, strict=True)):
        visits[g] = visits.get(g, 0) + 1
        label = f"P{g + 1}" if kind == "iso9283" else str(g + 1)
        for s in samples[a:b]:
            s.update(label=label, visit=visits[g], stop=k)
