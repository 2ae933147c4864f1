"""The measurement worker: owns the devices, measures every frame, publishes results.

Threads (one owner per device, python-can / Opentrons style):

- one acquisition thread per camera (``service.runtime.acquisition.CameraChannel``);
- the robot driver's own reader thread, plus a small supervisor here that re-opens the robot when its link drops;
- one processing thread that takes the newest frame of each camera, pairs it
  with the robot's pose at the exposure instant, measures it (ROI tracking,
  full frame on loss) and publishes the result to subscribers (the API's
  WebSocket fan-out), to waiting triggered requests and to the store. A frame
  whose measurement runs in a child with room for it is handed over by its
  camera's thread as it arrives (``service.runtime.hand_over``).

Nothing here raises on bad data: every frame gives a
:class:`~service.core.measurement.Measurement`, a failure with a ``reason`` when it
could not be measured; the same frozen object goes to every consumer.

What a client sees during a fault. A camera that is disconnected, failed or stalled gets an outage
result (``"ok": false``, ``camera_disconnected``) at once and then once a second, to the stream, to
waiting requests and as its newest result; a robot outage leaves the camera pose and says why the
flange part is missing. :meth:`Worker.current` marks a result older than a few frame periods
``"stale": true`` with its age. A triggered measurement is answered with the row's sequence number in
the store; the API acknowledges it only once that row is committed (:meth:`Worker.wait_stored`), so
the processing thread never waits for the disk.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.base import DriverError, Frame, RobotDriver, TriggerMode
from drivers.registry import make_camera, make_robot
from service.core.measurement import Measurement
from service.core.results import Failure, Reason
from service.pipeline.brightness import Brightness
from service.runtime.acquisition import CameraChannel, DeviceState, Wakeup
from service.runtime.arm import ArmLease
from service.runtime.calibration_state import CalibrationState
from service.runtime.cell_runtime import CellRuntime, with_stated_latencies
from service.runtime.cpus import CpuPlan, keep_to, plan_for
from service.runtime.exposure import ExposureControl, ExposureLimits
from service.runtime.faults import fault_target
from service.runtime.hand_over import HandOver
from service.runtime.handeye_session import HandEyeSession
from service.runtime.measure_process import MeasureProcessError
from service.runtime.processor import CameraProcessor, Pending
from service.runtime.rig_combiner import RIG, RigCombiner
from service.runtime.session_store import SessionStore
from service.runtime.solver_process import SolverProcess
from service.settings import CameraConfig, ProcessingConfig, Settings
from service.store.measurements import StorageError

log = logging.getLogger(__name__)

Subscriber = Callable[[Measurement], None]

RECONNECT_MAX_S = 1.0  # longest wait between reconnection attempts: a device is back within ~1 s of return
OUTAGE_REPEAT_S = 1.0  # an outage result is repeated this often while a camera is down
# the cameras' states are looked at this often, not at every result (at 500 Hz that was ~5 % of the
# processing thread); an outage's first result is at most this late
OUTAGE_CHECK_S = 0.02
STALE_PERIODS = 5  # a result older than this many frame periods is stale ...
STALE_MIN_S = 0.5  # ... and never younger than this (scheduling jitter on a loaded machine)


@dataclass(frozen=True)
class Answer:
    """A triggered measurement: its result, and the store's sequence number of its row (None: not queued)."""

    result: Measurement
    stored_seq: int | None = None
    storage_error: str = ""


class Worker:
    """Runs the cell (see the module docstring). ``start()`` returns at once; devices come up in the background."""

    def __init__(
        self,
        settings: Settings,
        store: Any = None,
        calibration: CalibrationState | None = None,
        *,
        calib_store: Any = None,
    ) -> None:
        # the current settings, the one copy the service reads (the API too): frozen, swapped whole by
        # reconfigure_camera and update_processing; with the simulated devices' delivery delays stated
        self.settings = settings = with_stated_latencies(settings)
        self._settings_lock = threading.Lock()  # a change is a read-modify-write of self.settings
        self.store = store
        self.cell = CellRuntime(settings, on_event=self.event)  # the simulated cell and its stand-ins
        # built once: from the stored calibrations (``calib_store``), else the settings' and the simulated cell's
        self.calibration = calibration or CalibrationState(settings, calib_store, self.cell)
        self._wakeup = Wakeup()
        self._stop = threading.Event()
        self.cameras: dict[str, CameraChannel] = {}
        self.processors: dict[str, CameraProcessor] = {}
        self.exposure: dict[str, ExposureControl] = {}  # per camera with automatic exposure
        self.arm = ArmLease()  # the workflow moving the simulated arm now (one at a time)
        self.exposure_hold = ""  # why the exposure control holds still (an accuracy test runs), or ""
        self.brightness: dict[str, Brightness] = {}  # per camera, its last measured frame's targets
        self.robot: RobotDriver | None = None
        self.robot_state = DeviceState.absent if settings.robot.driver == "none" else DeviceState.starting
        self.robot_error = ""
        self._subscribers: list[Subscriber] = []
        self._waiters: list[tuple[str | None, int, concurrent.futures.Future[Answer]]] = []
        self._lock = threading.Lock()
        self.latest: dict[str, Measurement] = {}
        # per camera: host ns the newest result's data is from (its exposure; an outage result: its
        # publication) and whether it is an outage notice
        self._latest_t_ns: dict[str, tuple[int, bool]] = {}
        self._outage_published_ns: dict[str, tuple[str, int]] = {}
        self._outages_checked_ns = 0
        self._allowed_cpus = frozenset(os.sched_getaffinity(0))  # before any is kept to some of them
        self.cpu_plan: CpuPlan | None = None
        self.latest_frame: dict[str, tuple[Frame, Measurement]] = {}
        self._latency_ms: deque[float] = deque(maxlen=200)
        self._processing_ms: deque[float] = deque(maxlen=200)
        self.counters = {
            "results": 0,
            "ok": 0,
            "failed": 0,
            "roi": 0,
            "full": 0,
            "stored": 0,
            "triggered": 0,
            "not_stored": 0,
            "outage_results": 0,
        }
        self._last_stored_ns = 0
        self._threads: list[threading.Thread] = []
        self.started_ns = time.monotonic_ns()
        self._processing_ready = threading.Event()  # the cameras fetch from then on
        self.rig = RigCombiner([c.name for c in settings.cameras], settings.processing.rig_sync_tolerance_s)
        # the calibration sessions on disk beside the measurements (a worker without storage keeps them
        # in memory): each change written before it is acknowledged, offered again after a restart
        self.sessions = SessionStore(
            settings.resolved_state_dir() / "sessions" if store is not None else None, self.event
        )
        self.handeye_session: HandEyeSession | None = self._restored_handeye()
        self.solver = SolverProcess()  # the API's long solves; its child starts with the first session or solve
        self.hand_over = HandOver(
            self.cameras,
            self.processors,
            self._wakeup,
            lambda: self.settings.processing.direct_hand_over,
            self._internal_failure,
            self._processing_ready,
            self._stop,
        )

    def _restored_handeye(self) -> HandEyeSession | None:
        state = self.sessions.load("handeye")
        if state is None:
            return None
        try:
            session = HandEyeSession.restore(state, self.sessions)
        except (KeyError, TypeError, ValueError) as e:
            self.sessions.set_aside("handeye", f"{type(e).__name__}: {e}")
            return None
        self.event(
            "info",
            "session_restored",
            f"hand-eye session of {session.created_wall} restored with {len(session.samples)} samples",
        )
        return session

    @property
    def processing_ready(self) -> bool:
        """True once the measurers are built (the compiled kernels loaded)."""
        return self._processing_ready.is_set()

    # --- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        self.cell.start()
        for cfg in self.settings.cameras:
            self._add_camera(cfg)
        if self.settings.robot.driver != "none":
            t = threading.Thread(target=self._supervise_robot, name="robot-supervisor", daemon=True)
            t.start()
            self._threads.append(t)
        t = threading.Thread(target=self._process_loop, name="processing", daemon=True)
        t.start()
        self._threads.append(t)
        self.event("info", "started", "worker started")

    def stop(self) -> None:
        self._stop.set()
        with self._wakeup:
            self._wakeup.notify_all()
        for ch in self.cameras.values():
            ch.stop()
        for t in self._threads:
            t.join(timeout=5.0)
        if self.robot is not None:
            try:
                self.robot.close()
            except DriverError as e:
                log.warning("closing robot: %s", e)
        self.cell.stop()
        self.solver.stop()
        for proc in self.processors.values():
            proc.close()
        self._wakeup.close()
        with self._lock:
            for _, _, fut in self._waiters:
                if not fut.done():
                    fut.set_result(Answer(self._failure(None, Reason.no_frame, "the service is shutting down")))
            self._waiters.clear()

    def _add_camera(self, cfg: CameraConfig) -> None:
        name, options = self.cell.camera_driver(cfg)
        try:
            driver = make_camera(name, **options)
        except (DriverError, TypeError, ValueError) as e:
            # a missing SDK or bad options do not get better by retrying: report, keep the rest running
            self.event("error", "camera_failed", f"camera {cfg.name}: {e}")
            self.processors[cfg.name] = CameraProcessor(cfg.name, self.settings, self.calibration)
            self.processors[cfg.name].failed_reason = str(e)
            return
        ch = CameraChannel(
            cfg.name,
            driver,
            cfg.camera_settings(),
            self._wakeup,
            self.event,
            self._processing_ready,
            on_frame=self.hand_over.begin_at_once,
        )
        self.cameras[cfg.name] = ch
        self._set_exposure_control(cfg)
        self.processors[cfg.name] = CameraProcessor(
            cfg.name, self.settings, self.calibration, pixel_format=lambda: ch.pixel_format, roi=lambda: ch.settings.roi
        )
        ch.start()

    def _supervise_robot(self) -> None:
        retry_s = 0.5
        while not self._stop.is_set():
            if self.robot is None:
                try:
                    name, options = self.cell.robot_driver()
                    self.robot = make_robot(name, **options)
                except (DriverError, TypeError, ValueError) as e:
                    self._set_robot_state(DeviceState.failed, str(e))
                    return
            if not self.robot.connected:
                if self.robot_state is DeviceState.ok:  # say so before reconnecting: a quick reopen hides it
                    self._set_robot_state(DeviceState.disconnected, self._robot_link_error())
                try:
                    self.robot.close()
                    self.robot.open()
                    self._set_robot_state(DeviceState.ok)
                    retry_s = 0.5
                except DriverError as e:
                    self._set_robot_state(DeviceState.disconnected, str(e))
                    self._stop.wait(retry_s)
                    retry_s = min(RECONNECT_MAX_S, retry_s * 2)
                    continue
            elif self.robot_state is not DeviceState.ok:
                self._set_robot_state(DeviceState.ok)
            self._stop.wait(0.2)

    def _robot_link_error(self) -> str:
        assert self.robot is not None
        try:
            self.robot.latest()
        except DriverError as e:
            return str(e)
        return "the robot's link dropped"

    def _set_robot_state(self, state: DeviceState, error: str = "") -> None:
        if state != self.robot_state:
            self.event("info" if state is DeviceState.ok else "warning", f"robot_{state}", f"robot: {error or state}")
        self.robot_state, self.robot_error = state, error

    # --- the exposure control ----------------------------------------------------------------------

    def _set_exposure_control(self, cfg: CameraConfig) -> None:
        """(Re)start the camera's exposure control from its configured exposure, or drop it."""
        auto = cfg.auto_exposure
        if not auto.enabled or cfg.exposure_us is None:
            self.exposure.pop(cfg.name, None)
            return
        max_us = auto.max_us
        if cfg.trigger is TriggerMode.FREE_RUN and cfg.frame_rate_hz:
            max_us = min(max_us, 0.9e6 / cfg.frame_rate_hz)  # the exposure must fit in the frame period
        limits = ExposureLimits(target_peak=auto.target_peak, min_us=auto.min_us, max_us=max(auto.min_us, max_us))
        self.exposure[cfg.name] = ExposureControl(limits, cfg.exposure_us)

    def hold_exposure(self, why: str) -> None:
        """Hold every camera's exposure where it is while ``why`` (non-empty) lasts; "" releases it.

        A test comparing poses taken minutes apart must take them alike: a step between two visits
        of a position changes which disks clip and moves the pose by tens of µm (seen: 4 σ)."""
        if why and not self.exposure_hold:
            held = ", ".join(f"{n} at {c.exposure_us:.0f} us" for n, c in self.exposure.items()) or "none on"
            self.event("info", "exposure_held", f"automatic exposure held ({held}): {why}")
        elif not why and self.exposure_hold:
            self.event("info", "exposure_released", "automatic exposure follows the targets again")
        self.exposure_hold = why

    def _steer_exposure(self, name: str, frame: Frame, pending: Pending) -> None:
        if pending.outcome is not None and pending.outcome.brightness is not None:
            self.brightness[name] = pending.outcome.brightness
        control, ch = self.exposure.get(name), self.cameras.get(name)
        if control is None or ch is None or pending.outcome is None or self.exposure_hold:
            return
        if ch.exposure_refused:  # the device cannot take it (a replay, a camera without manual exposure)
            self.exposure.pop(name, None)
            self.event("warning", "exposure_auto_off", f"camera {name}: automatic exposure off: {ch.exposure_refused}")
            return
        before_us = control.exposure_us
        step = control.observe(frame.exposure_us, pending.outcome.brightness)
        if step is not None:
            ch.request_exposure(step.exposure_us)
            self.event(
                "info", "exposure", f"camera {name}: exposure {before_us:.0f} -> {step.exposure_us:.0f} us ({step.why})"
            )

    # --- run-time changes (from the API's threads) ----------------------------------------------

    def reconfigure_camera(self, cfg: CameraConfig) -> str:
        """Apply new camera settings in the camera's thread; "" or the driver's error sentence.

        Applied, :attr:`settings` becomes a new object with ``cfg`` for that camera; refused (the
        error sentence), nothing changes. ``cfg`` must name a configured camera with its driver.
        """
        with self._settings_lock:
            new = self.settings.with_camera(cfg)
            ch = self.cameras.get(cfg.name)
            if ch is None:
                return f"camera {cfg.name} is not running"
            if ch.state is not DeviceState.ok:
                ch.settings = cfg.camera_settings()  # applied when it (re)connects
            else:
                error = ch.request_settings(cfg.camera_settings())
                if error:
                    return error
            self.processors[cfg.name].set_camera_config(cfg)
            self._set_exposure_control(cfg)
            self.settings = new
            for proc in self.processors.values():
                proc.settings = new
        return ""

    def update_processing(self, processing: ProcessingConfig) -> None:
        """Measure with ``processing`` from the next frame on (:attr:`settings` becomes a new object)."""
        with self._settings_lock:
            self.settings = new = self.settings.with_processing(processing)
            for proc in self.processors.values():
                proc.settings = new  # it rebuilds its measurer: the processing options are another object
            self._plan_cpus()

    # --- events, subscribers ---------------------------------------------------------------------

    def event(self, level: str, kind: str, message: str) -> None:
        getattr(log, "info" if level == "info" else "warning")(message)
        if self.store is not None:
            self.store.add_event(kind, message, level=level)

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(result)`` from the processing thread for every result; returns the unsubscriber."""
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    # --- triggered measurement -------------------------------------------------------------------

    def request_measurement(self, camera: str | None = None) -> concurrent.futures.Future[Answer]:
        """A future for the result of the next frame exposed after now (software-triggered if so configured).

        It is answered by an outage result as soon as the camera is found down while waiting.
        """
        fut: concurrent.futures.Future[Answer] = concurrent.futures.Future()
        if camera is not None and camera not in self.processors and camera != RIG:
            raise KeyError(camera)
        names = [camera] if camera and camera != RIG else list(self.processors)
        for name in names:
            reason = self._camera_unavailable(name)
            if reason is not None:
                fut.set_result(Answer(reason))
                return fut
        with self._lock:
            self._waiters.append((camera, time.monotonic_ns(), fut))
        for name in names:
            if name in self.cameras:
                self.cameras[name].request_trigger()
        return fut

    def wait_stored(self, answer: Answer, timeout_s: float) -> tuple[bool, str]:
        """Wait until the answer's row is committed (and fsynced); ``(True, "")`` or ``(False, why)``."""
        if self.store is None:
            return True, ""  # a worker without a store (tests, the CLI) has nothing to acknowledge
        if answer.stored_seq is None:
            return False, f"the measurement could not be queued for storage: {answer.storage_error}"
        if self.store.wait_written(answer.stored_seq, max(0.0, timeout_s)):
            return True, ""
        _, why = self.store.health()
        return False, (
            f"the measurement was not committed to the database within {timeout_s:.1f} s"
            f"{f': {why}' if why else ''}; it is not acknowledged (it is kept queued and written "
            "when the database accepts writes again)"
        )

    def _camera_unavailable(self, name: str) -> Measurement | None:
        ch = self.cameras.get(name)
        if ch is None:
            return self._failure(name, Reason.camera_disconnected, self.processors[name].failed_reason)
        if ch.state is DeviceState.ok:
            return None
        if ch.state is DeviceState.starting:
            return None  # it may come up within the caller's timeout
        return self._failure(name, Reason.camera_disconnected, ch.last_error or f"camera {name} is {ch.state}")

    def _failure(self, camera: str | None, reason: Reason, message: str, state: str | None = None) -> Measurement:
        """A result without a frame (an outage, a shutdown): stamped now."""
        return Measurement(camera or "", Failure(reason, message), time.time_ns(), camera_state=state)

    # --- fault injection (the simulated cell only) -----------------------------------------------

    def inject_fault(self, device: str, action: str, camera: str | None = None) -> str:
        """Unplug, plug, stall or garble a simulated device; returns a sentence of what was done.

        Raises LookupError when there is no simulated device to act on, ValueError for an unknown action.
        """
        target, what = fault_target(device, action, camera, self.cameras, self.robot, self.settings.sim.transport)
        getattr(target, action)()
        self.event("warning" if action != "plug" else "info", "sim_fault", f"simulated fault: {what} {action}")
        return f"{what}: {action}"

    # --- processing ------------------------------------------------------------------------------

    def _plan_cpus(self) -> None:
        """Keep each measurement child and the service's threads to their CPUs (``measure_cpus``)."""
        plan = plan_for(self.settings, list(self.cameras), self._allowed_cpus)
        if plan != self.cpu_plan:
            keep_to(plan, self.processors)
            if plan.children or self.cpu_plan is not None:  # said when CPUs are dedicated or change
                self.event("info", "cpus", f"CPUs: {plan.why}")
            self.cpu_plan = plan

    def _process_loop(self) -> None:
        with self._settings_lock:  # before the children start: the fork server and they inherit the service's CPUs
            self._plan_cpus()
        # build the measurers first: the compiled kernels load (or, on a fresh install, compile for
        # a minute) here, while /health says "initializing", not inside the first frame's latency
        for proc in self.processors.values():
            try:
                proc.warm_up()
            except Exception:
                log.exception("preparing the measurer of camera %s", proc.name)
        self._processing_ready.set()
        self.event("info", "processing_ready", "processing is ready")
        # frames handed to the measurement (child processes), oldest first: while one is measured
        # the next waits in its child's pipe, and each is finished here (flange, storage, fan-out)
        # while the child measures the next
        hand = self.hand_over
        while not self._stop.is_set():
            self._publish_outages()
            hand.hand_over(0.0 if hand.in_flight else 0.25)
            oldest = hand.pop()
            if oldest is None:
                continue
            name, frame, pending = oldest
            processor = self.processors[name]
            if isinstance(pending, Pending):
                hand.wait_for_outcome(processor)
                try:
                    hand.collect(processor, pending)
                except Exception as e:
                    pending = self._internal_failure(name, e)
            if processor.depth > 1:  # measured elsewhere: the next frame goes before this one is finished
                hand.hand_over(0.0)
            if isinstance(pending, Pending):
                try:
                    result = processor.finish(pending, self.robot, self.robot_state)
                except Exception as e:
                    result = self._internal_failure(name, e)
                self._steer_exposure(name, frame, pending)
            else:
                result = pending
            self._outage_published_ns.pop(name, None)
            self._publish(name, result, frame)
            if len(self.cameras) >= 2 and self.calibration.rig is not None:
                combined = self.rig.add(result, self.calibration.rig, self.calibration.field, self.calibration.handeye)
                if combined is not None:
                    self._publish(RIG, combined, frame)

    def _internal_failure(self, name: str, e: Exception) -> Measurement:
        """A frame that could not be measured for a reason of ours (a bug, a lost child): a failed result."""
        if isinstance(e, MeasureProcessError):
            return self._failure(name, Reason.bad_image, str(e))  # said and logged by the child's keeper
        log.error("processing a frame of camera %s", name, exc_info=e)  # a bug must not stop the cell
        return self._failure(name, Reason.bad_image, f"internal error while measuring: {e!r}")

    def _camera_outage(self, name: str) -> tuple[str, str] | None:
        """(state, sentence) of a camera that cannot deliver measurable frames now, else None."""
        ch = self.cameras.get(name)
        if ch is None:
            return str(DeviceState.failed), self.processors[name].failed_reason or f"camera {name} failed to start"
        state, error = ch.effective_state()
        if state in (str(DeviceState.ok), str(DeviceState.starting), str(DeviceState.stopped)):
            return None
        return state, error or f"camera {name} is {state}"

    def _publish_outages(self) -> None:
        now = time.monotonic_ns()
        if now - self._outages_checked_ns < OUTAGE_CHECK_S * 1e9:
            return
        self._outages_checked_ns = now
        for name in self.processors:
            outage = self._camera_outage(name)
            if outage is None:
                continue
            state, error = outage
            last = self._outage_published_ns.get(name)
            if last is not None and last[0] == state and now - last[1] < OUTAGE_REPEAT_S * 1e9:
                continue
            self._outage_published_ns[name] = (state, now)
            result = self._failure(name, Reason.camera_disconnected, error, state)
            self.counters["outage_results"] += 1
            self._publish(name, result, None)

    def _rig_active(self) -> bool:
        return len(self.cameras) >= 2 and self.calibration.rig is not None

    def _publish(self, name: str, result: Measurement, frame: Frame | None) -> None:
        """Hand one result to waiting requests, the store and the subscribers (``frame`` None: an outage)."""
        c = self.counters
        now = time.monotonic_ns()
        if frame is not None:
            c["results"] += 1
            c["ok" if result.ok else "failed"] += 1
            if result.mode in ("roi", "full"):
                c[result.mode] += 1
            timings = result.timings_ms
            if "latency" in timings:
                self._latency_ms.append(timings["latency"])
            if "processing" in timings:
                self._processing_ms.append(timings["processing"])
            self.latest_frame[name] = (frame, result)
            t_data = result.t_exposure_host_ns if result.t_exposure_host_ns is not None else frame.t_host_ns
        else:
            t_data = now
        with self._lock:
            self.latest[name] = result
            self._latest_t_ns[name] = (t_data, frame is None)
            subscribers = list(self._subscribers)
            # a request for "any camera" is answered by the rig's result when a rig is calibrated
            answers_any = name == (RIG if self._rig_active() else name)
            waiting = [
                w
                for w in self._waiters
                if (w[0] == name or (w[0] is None and answers_any)) and (frame is None or t_data >= w[1])
            ]
            self._waiters = [w for w in self._waiters if w not in waiting]
        answer = Answer(result)
        if frame is not None and (waiting or self._due_for_storage(frame)):
            answer = self._store(result, triggered=bool(waiting))
        for _, _, fut in waiting:
            c["triggered"] += 1
            if not fut.done():
                fut.set_result(answer)
        for callback in subscribers:
            try:
                callback(result)
            except Exception:
                log.exception("a result subscriber failed")

    def _due_for_storage(self, frame: Frame) -> bool:
        every_ns = self.settings.storage.stream_every_s * 1e9
        return self.store is not None and frame.t_host_ns - self._last_stored_ns >= every_ns

    def _store(self, result: Measurement, triggered: bool) -> Answer:
        if self.store is None:
            return Answer(result)
        self._last_stored_ns = time.monotonic_ns()
        try:
            seq = int(self.store.add_measurement(result, triggered=triggered))
        except (StorageError, ValueError, TypeError) as e:  # a full queue (disk far behind), a closed store
            self.counters["not_stored"] += 1
            log.warning("measurement not stored: %s", e)
            return Answer(result, None, str(e))
        self.counters["stored"] += 1
        return Answer(result, seq)

    # --- the newest result, marked by its age -----------------------------------------------------

    def stale_after_s(self, name: str) -> float:
        """Age beyond which a camera's (or the rig's) newest result is no longer current."""
        rates = [c.frame_rate_hz for c in self.settings.cameras if name in (c.name, RIG) and c.frame_rate_hz]
        return max(STALE_MIN_S, STALE_PERIODS / min(rates)) if rates else STALE_MIN_S

    def current(self, camera: str | None = None) -> Measurement | None:
        """The newest result of ``camera`` (or the newest of all), served with its ``age_s``.

        A result older than :meth:`stale_after_s` is served :meth:`~Measurement.as_stale` (``ok``
        false, reason ``stale``, a sentence, the measured values kept for diagnosis); an outage
        result is always current (it says what is wrong now).
        """
        with self._lock:
            entries = [(n, r, *self._latest_t_ns[n]) for n, r in self.latest.items() if camera in (None, n)]
        if not entries:
            return None
        name, result, t_data_ns, is_outage = max(entries, key=lambda e: e[2])
        age_s = max(0.0, (time.monotonic_ns() - t_data_ns) * 1e-9)
        if is_outage or age_s <= self.stale_after_s(name):
            return result.served(age_s)
        outage = self._camera_outage(name) if name in self.processors else None
        why = f": {outage[1]}" if outage else ""
        return result.as_stale(age_s, f"the newest result of {name} is {age_s:.1f} s old, no longer current{why}")

    # --- reports ---------------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """Device, storage and processing states; ``problems`` says in sentences what is not ok."""
        cams = {name: ch.snapshot() for name, ch in self.cameras.items()}
        for name, cam in cams.items():
            control = self.exposure.get(name)
            cam["auto_exposure"] = {
                "on": control is not None,
                "steps": control.steps if control else 0,
                "held": self.exposure_hold or None,
            }
            if (b := self.brightness.get(name)) is not None:  # the last measured frame's
                cam.update(b.health())
        for name, proc in self.processors.items():
            if name not in cams:
                cams[name] = {"state": str(DeviceState.failed), "error": proc.failed_reason}
        robot: dict[str, Any] = {
            "state": str(self.robot_state),
            "error": self.robot_error,
            "moved_by": self.arm.moved_by,
        }
        if self.robot is not None:
            robot.update(driver=self.robot.info.driver, rate_hz=self.robot.info.rate_hz)
        states = [c["state"] for c in cams.values()]
        problems = [
            f"camera {n}: {c.get('error') or c['state']}"
            for n, c in cams.items()
            if c["state"] not in ("ok", "starting")
        ]
        if self.robot_state is not DeviceState.absent:
            states.append(robot["state"])
            if self.robot_state not in (DeviceState.ok, DeviceState.starting):
                problems.append(f"robot: {self.robot_error or self.robot_state}")
        storage = self.store.stats() if self.store is not None else None
        if storage is not None:
            states.append(storage["state"])
            if storage["state"] != "ok":
                problems.append(f"storage: {storage['error']}")
        if not self.processing_ready:
            status = "initializing"
        elif all(s == "ok" for s in states):
            status = "ok"
        elif not problems and any(s == "starting" for s in states) and (time.monotonic_ns() - self.started_ns) < 30e9:
            status = "initializing"
        else:
            status = "degraded"
        return {
            "ok": status == "ok",
            "status": status,
            "problems": problems,
            "uptime_s": round((time.monotonic_ns() - self.started_ns) * 1e-9, 1),
            "cameras": cams,
            "robot": robot,
            "calibration": self.calibration.summary(),
            "processing": {
                **self.counters,
                "handed_over_by_camera": self.hand_over.by_camera,  # the rest: by the processing thread
                "latency_ms_median": _median(self._latency_ms),
                "processing_ms_median": _median(self._processing_ms),
                "time_offset": {n: p.time_offset_report() for n, p in self.processors.items()},
                "measurement": {n: p.measurement_report() for n, p in self.processors.items()},
                "cpus": None if self.cpu_plan is None else self.cpu_plan.to_dict(),
            },
            "storage": storage,
        }


def _median(values: deque[float]) -> float | None:
    return round(float(np.median(list(values))), 3) if values else None
