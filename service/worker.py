"""The measurement worker: owns the devices, measures every frame, publishes results.

Threads (one owner per device, python-can / Opentrons style):

- one acquisition thread per camera (``service.acquisition.CameraChannel``);
- the robot driver's own reader thread, plus a small supervisor here that
  re-opens the robot when its link drops;
- one processing thread that takes the newest frame of each camera, pairs it
  with the robot's pose at the exposure instant, measures it (ROI tracking,
  full frame on loss) and publishes the result to subscribers (the API's
  WebSocket fan-out), to waiting triggered requests and to the store.

Nothing here raises on bad data: every frame gives a result dict, with
``"ok": false`` and a ``reason`` when it could not be measured.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.base import DriverError, Frame, RobotDriver
from drivers.registry import make_camera, make_robot
from service.acquisition import CameraChannel, DeviceState
from service.calibration_state import CalibrationState
from service.cell_runtime import CellRuntime
from service.core.results import Failure, Reason
from service.measure_frame import CameraProcessor
from service.rig_processing import RIG, RigCombiner
from service.settings import CameraConfig, ProcessingConfig, Settings
from service.storage import StorageError

log = logging.getLogger(__name__)

Subscriber = Callable[[dict[str, Any]], None]


class Worker:
    """Runs the cell (see the module docstring). ``start()`` returns at once; devices come up in the background."""

    def __init__(self, settings: Settings, store: Any = None, calibration: CalibrationState | None = None) -> None:
        self.settings = settings
        self.store = store
        self.cell = CellRuntime(settings)  # the simulated cell and its stand-ins, when configured
        self.calibration = calibration or CalibrationState(settings, None, self.cell)
        self._wakeup = threading.Condition()
        self._stop = threading.Event()
        self.cameras: dict[str, CameraChannel] = {}
        self.processors: dict[str, CameraProcessor] = {}
        self.robot: RobotDriver | None = None
        self.robot_state = DeviceState.absent if settings.robot.driver == "none" else DeviceState.starting
        self.robot_error = ""
        self._subscribers: list[Subscriber] = []
        self._waiters: list[tuple[str | None, int, concurrent.futures.Future[dict[str, Any]]]] = []
        self._lock = threading.Lock()
        self.latest: dict[str, dict[str, Any]] = {}
        self.latest_frame: dict[str, tuple[Frame, dict[str, Any]]] = {}
        self._latency_ms: deque[float] = deque(maxlen=200)
        self._processing_ms: deque[float] = deque(maxlen=200)
        self.counters = {"results": 0, "ok": 0, "failed": 0, "roi": 0, "full": 0, "stored": 0, "triggered": 0}
        self._last_stored_ns = 0
        self._threads: list[threading.Thread] = []
        self.started_ns = time.monotonic_ns()
        self.processing_ready = False
        self.rig = RigCombiner([c.name for c in settings.cameras], settings.processing.rig_sync_tolerance_s)
        self.handeye_session: Any = None  # service.handeye_session.HandEyeSession while one runs

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
        with self._lock:
            for _, _, fut in self._waiters:
                fut.set_result(Failure(Reason.no_frame, "the service is shutting down").to_dict())
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
        ch = CameraChannel(cfg.name, driver, cfg.camera_settings(), self._wakeup, self.event)
        self.cameras[cfg.name] = ch
        self.processors[cfg.name] = CameraProcessor(cfg.name, self.settings, self.calibration)
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
                try:
                    self.robot.close()
                    self.robot.open()
                    self._set_robot_state(DeviceState.ok)
                    retry_s = 0.5
                except DriverError as e:
                    self._set_robot_state(DeviceState.disconnected, str(e))
                    self._stop.wait(retry_s)
                    retry_s = min(5.0, retry_s * 2)
                    continue
            elif self.robot_state is not DeviceState.ok:
                self._set_robot_state(DeviceState.ok)
            self._stop.wait(0.2)

    def _set_robot_state(self, state: DeviceState, error: str = "") -> None:
        if state != self.robot_state:
            self.event("info" if state is DeviceState.ok else "warning", f"robot_{state}", f"robot: {error or state}")
        self.robot_state, self.robot_error = state, error

    # --- run-time changes (from the API's threads) ----------------------------------------------

    def reconfigure_camera(self, cfg: CameraConfig) -> str:
        """Apply new camera settings in the camera's thread; "" or the driver's error sentence."""
        ch = self.cameras.get(cfg.name)
        if ch is None:
            return f"camera {cfg.name} is not running"
        if ch.state is not DeviceState.ok:
            ch.settings = cfg.camera_settings()  # applied when it (re)connects
            return ""
        error = ch.request_settings(cfg.camera_settings())
        if not error:
            self.processors[cfg.name].set_camera_config(cfg)
        return error

    def update_processing(self, processing: ProcessingConfig) -> None:
        self.settings.processing = processing
        self.calibration.touch()  # processors rebuild their measurers before the next frame

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

    def request_measurement(self, camera: str | None = None) -> concurrent.futures.Future[dict[str, Any]]:
        """A future for the result of the next frame exposed after now (software-triggered if so configured)."""
        fut: concurrent.futures.Future[dict[str, Any]] = concurrent.futures.Future()
        if camera is not None and camera not in self.processors and camera != RIG:
            raise KeyError(camera)
        names = [camera] if camera and camera != RIG else list(self.processors)
        for name in names:
            reason = self._camera_unavailable(name)
            if reason is not None:
                fut.set_result(reason)
                return fut
        with self._lock:
            self._waiters.append((camera, time.monotonic_ns(), fut))
        for name in names:
            if name in self.cameras:
                self.cameras[name].request_trigger()
        return fut

    def _camera_unavailable(self, name: str) -> dict[str, Any] | None:
        ch = self.cameras.get(name)
        if ch is None:
            return self._failure(name, Reason.camera_disconnected, self.processors[name].failed_reason)
        if ch.state is DeviceState.ok:
            return None
        if ch.state is DeviceState.starting:
            return None  # it may come up within the caller's timeout
        return self._failure(name, Reason.camera_disconnected, ch.last_error or f"camera {name} is {ch.state}")

    def _failure(self, camera: str, reason: Reason, message: str) -> dict[str, Any]:
        d = Failure(reason, message).to_dict()
        d.update(camera=camera, t_wall=_wall_now())
        return d

    # --- processing ------------------------------------------------------------------------------

    def _next_frame(self) -> tuple[str, Frame] | None:
        with self._wakeup:
            for _ in range(2):
                for name, ch in self.cameras.items():
                    frame = ch.slot.take()
                    if frame is not None:
                        return name, frame
                if self._stop.is_set():
                    return None
                self._wakeup.wait(0.5)
        return None

    def _process_loop(self) -> None:
        # build the measurers first: the compiled kernels load (or, on a fresh install, compile for
        # a minute) here, while /health says "initializing", not inside the first frame's latency
        for proc in self.processors.values():
            try:
                proc.warm_up()
            except Exception:
                log.exception("preparing the measurer of camera %s", proc.name)
        self.processing_ready = True
        self.event("info", "processing_ready", "processing is ready")
        while not self._stop.is_set():
            got = self._next_frame()
            if got is None:
                continue
            name, frame = got
            try:
                result = self.processors[name].process(frame, self.robot, self.robot_state)
            except Exception as e:  # a bug must not stop the cell: report it as a failed frame
                log.exception("processing a frame of camera %s", name)
                result = self._failure(name, Reason.bad_image, f"internal error while measuring: {e!r}")
            self._publish(name, frame, result)
            if len(self.cameras) >= 2 and self.calibration.rig is not None:
                combined = self.rig.add(result, self.calibration.rig, self.calibration.field, self.calibration.handeye)
                if combined is not None:
                    self._publish(RIG, frame, combined)

    def _rig_active(self) -> bool:
        return len(self.cameras) >= 2 and self.calibration.rig is not None

    def _publish(self, name: str, frame: Frame, result: dict[str, Any]) -> None:
        c = self.counters
        c["results"] += 1
        c["ok" if result.get("ok") else "failed"] += 1
        if result.get("mode") in ("roi", "full"):
            c[result["mode"]] += 1
        timings = result.get("timings_ms", {})
        if "latency" in timings:
            self._latency_ms.append(timings["latency"])
        if "processing" in timings:
            self._processing_ms.append(timings["processing"])
        self.latest[name] = result
        self.latest_frame[name] = (frame, result)
        t_exposure = result.get("t_exposure_host_ns", frame.t_host_ns)
        with self._lock:
            subscribers = list(self._subscribers)
            # a request for "any camera" is answered by the rig's result when a rig is calibrated
            answers_any = name == (RIG if self._rig_active() else name)
            waiting = [w for w in self._waiters
                       if (w[0] == name or (w[0] is None and answers_any)) and t_exposure >= w[1]]
            self._waiters = [w for w in self._waiters if w not in waiting]
        stored_seq = None
        if waiting or self._due_for_storage(frame):
            stored_seq = self._store(result, triggered=bool(waiting))
        for _, _, fut in waiting:
            c["triggered"] += 1
            if stored_seq is not None and self.store is not None:
                # acknowledged = committed: a kill -9 after the reply loses nothing
                self.store.wait_written(stored_seq, timeout_s=2.0)
            if not fut.done():
                fut.set_result(result)
        for callback in subscribers:
            try:
                callback(result)
            except Exception:
                log.exception("a result subscriber failed")

    def _due_for_storage(self, frame: Frame) -> bool:
        every_ns = self.settings.storage.stream_every_s * 1e9
        return self.store is not None and frame.t_host_ns - self._last_stored_ns >= every_ns

    def _store(self, result: dict[str, Any], triggered: bool) -> int | None:
        if self.store is None:
            return None
        self._last_stored_ns = time.monotonic_ns()
        try:
            seq = int(self.store.add_measurement({**result, "triggered": triggered}))
        except StorageError as e:  # a full queue (disk far behind): counted by the store, reported here
            log.warning("measurement not stored: %s", e)
            return None
        self.counters["stored"] += 1
        return seq

    # --- reports ---------------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        cams = {name: ch.snapshot() for name, ch in self.cameras.items()}
        for name, proc in self.processors.items():
            if name not in cams:
                cams[name] = {"state": str(DeviceState.failed), "error": proc.failed_reason}
        robot: dict[str, Any] = {"state": str(self.robot_state), "error": self.robot_error}
        if self.robot is not None:
            robot.update(driver=self.robot.info.driver, rate_hz=self.robot.info.rate_hz)
        states = [c["state"] for c in cams.values()]
        if self.robot_state is not DeviceState.absent:
            states.append(robot["state"])
        if not self.processing_ready:
            status = "initializing"
        elif all(s == "ok" for s in states):
            status = "ok"
        elif any(s == "starting" for s in states) and (time.monotonic_ns() - self.started_ns) < 30e9:
            status = "initializing"
        else:
            status = "degraded"
        return {
            "ok": status == "ok",
            "status": status,
            "uptime_s": round((time.monotonic_ns() - self.started_ns) * 1e-9, 1),
            "cameras": cams,
            "robot": robot,
            "calibration": self.calibration.summary(),
            "processing": {
                **self.counters,
                "latency_ms_median": _median(self._latency_ms),
                "processing_ms_median": _median(self._processing_ms),
                "time_offset": {n: p.time_offset_report() for n, p in self.processors.items()},
            },
            "storage": self.store.stats() if self.store is not None else None,
        }


def _median(values: deque[float]) -> float | None:
    return round(float(np.median(list(values))), 3) if values else None


def _wall_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime()) + f".{int(time.time() * 1000) % 1000:03d}Z"
