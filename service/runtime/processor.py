"""One camera's processing: frame + robot history → its :class:`~service.core.measurement.Measurement`.

The pose comes from ``service.pipeline.measure.FrameMeasurer`` (ROI tracking with a
full-frame fall-back), by default in a child process of the camera's own
(:mod:`service.runtime.measure_process`; ``[processing] measure_in``). Then the flange:

    T_base_flange_measured = T_base_field @ T_field_camera @ inv(T_flange_camera)

with the hand-eye ``X = T_flange_camera`` and the robot–world ``Z =
T_base_field``, compared with the controller's ``T_base_flange`` at the
exposure instant. The deviation is ``measured - reported`` expressed in the base
frame (mm) plus the rotation angle between them (deg). A robot that is absent,
disconnected or not paired, or a missing hand-eye, leaves the pose valid and
says why the flange part is missing (``flange_reason``).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from drivers.base import Frame, RobotDriver
from service.core._kernels import geometry_kernels
from service.core.geometry.camera_model import BrownFraser
from service.core.measurement import Flange, Measurement
from service.core.pose.timesync import TimeOffsetFit, estimate_time_offset_s
from service.core.results import Failure, PoseResult, Reason
from service.core.targets.defects import DefectMap
from service.pipeline.flange import flange_part
from service.pipeline.measure import FrameMeasurer, MeasureSettings, Outcome
from service.runtime.acquisition import DeviceState
from service.runtime.calibration_state import CalibrationState
from service.runtime.measure_process import DEPTH, MeasureProcess, Measurer
from service.runtime.pairing import FramePairer
from service.settings import CameraConfig, ProcessingConfig, Settings
from service.store import formats

log = logging.getLogger(__name__)

# significant bits of the pixel formats a camera may deliver (GenICam: unpacked, the low bits)
BIT_DEPTH = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}


def measure_settings(p: ProcessingConfig, bit_depth: int | None = None) -> MeasureSettings:
    """The measurer's settings of the ``[processing]`` options (the mapping is :meth:`MeasureSettings.from_options`)
    for frames of ``bit_depth`` significant bits (None: their dtype's)."""
    return MeasureSettings.from_options(
        bit_depth=bit_depth,
        code_family=p.code_family,
        min_contrast_dn=p.min_contrast_dn,
        min_area_px=p.min_area_px,
        max_area_px=p.max_area_px,
        min_coded=p.min_coded,
        codes_enough=p.codes_enough,
        min_targets=p.min_targets,
        sigma_px=p.sigma_px,
        max_sigma0_px=p.max_sigma0_px,
        correct_eccentricity=p.correct_eccentricity,
        roi_tracking=p.roi_tracking,
        centre=p.centre,
        max_saturated_px=p.max_saturated_px,
    )


@dataclass
class Pending:
    """A frame handed to the measurement (:meth:`CameraProcessor.begin`), its result not yet built."""

    frame: Frame
    t_exposure_ns: int
    exposure_source: str
    t_begun: float  # perf_counter s
    t_measured: float = 0.0
    outcome: Outcome | None = None
    failure: Failure | None = None  # not measurable (no calibration, not a grey image)


class CameraProcessor:
    """Measures the frames of one camera (called from the worker's processing thread only)."""

    def __init__(
        self,
        name: str,
        settings: Settings,
        calibration: CalibrationState,
        pixel_format: Callable[[], str | None] = lambda: None,
        roi: Callable[[], tuple[int, int, int, int] | None] = lambda: None,
    ) -> None:
        self.name = name
        self.pixel_format = pixel_format  # what the camera delivers, as its driver says (None: not known)
        self.roi = roi  # the window of the sensor the camera delivers (x, y, width, height px), None: all
        self._bit_depth: int | None = None  # the frames' significant bits the measurer was built for
        self._roi: tuple[int, int, int, int] | None = None  # the window the measurer was built for
        # the worker's current settings (frozen): the worker puts the new object here on a change, and
        # the measurer is rebuilt before the next frame when its processing options are another object
        self.settings = settings
        self._processing: ProcessingConfig | None = None  # what the measurer was built with
        self.calibration = calibration
        cam_cfg = next(c for c in settings.cameras if c.name == name)
        self.pairer = FramePairer(cam_cfg.transport_latency_s, settings.robot.transport_latency_s)
        self.failed_reason = ""
        self._measurer: Measurer | None = None
        self._process: MeasureProcess | None = None  # the child, kept across set-up changes
        self._cpus: frozenset[int] | None = None  # the child's CPUs (None: as it inherits them)
        self._generation = -1
        self._motion: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=600)
        self._offset: TimeOffsetFit | None = None
        self._n_since_offset = 0
        self._motion_lock = threading.Lock()  # appended by the processing thread, read by /health
        self._defects_path: Path | None = None  # the defect map the measurer was set up with
        self._defects: DefectMap | None = None  # read from it (the whole sensor's; None: none, or unreadable)
        self._setup_error: str | None = None  # why no measurer could be set up, for every frame
        # host monotonic -> wall clock, fixed at start (results carry both)
        self._wall_minus_mono_ns = time.time_ns() - time.monotonic_ns()

    def set_camera_config(self, cfg: CameraConfig) -> None:
        """The camera's new configuration (its transport latency) is in force from the next frame."""
        self.pairer.camera_latency_ns = cfg.transport_latency_s * 1e9
        self.pairer.camera_clock.reset()  # a new exposure or frame rate changes the arrival pattern

    def warm_up(self) -> None:
        """Build the measurer now (loads or compiles the numba kernels; starts the child process).

        The pairing's and the flange's compiled calls run here, in this process, whichever process
        measures: loaded at their first call they cost the first frame ~50-330 ms."""
        geometry_kernels.warm_up()
        self._current_measurer()

    def keep_child_to(self, cpus: frozenset[int] | None) -> None:
        """The CPUs of this camera's measurement child, now and for every child it starts."""
        self._cpus = cpus
        if self._process is not None:
            self._process.keep_to(cpus)

    def close(self) -> None:
        """Stop the measurement's child process (if any)."""
        if self._process is not None:
            self._process.close()
            self._process = None

    def measurement_report(self) -> dict[str, Any]:
        """Where this camera's frames are measured: ``process`` (its pid, children replaced) or ``thread``;
        the frames' bit depth the measurement was set up for (None: the image dtype's); what a
        target's centre is measured as (``centroid`` or ``edge``; None before the first set-up), what
        the camera's calibration measured it as (None: not said), and a warning when they differ."""
        if self._process is None:
            where = {"in": "thread" if self._measurer is not None else None, "pid": None, "restarts": 0}
        else:
            where = {"in": "process", "pid": self._process.pid, "restarts": self._process.restarts}
        centre = self._processing.centre if self._processing is not None else None
        calibrated = self.calibration.camera_centre
        warning = None if centre is None else formats.centre_mismatch(calibrated, centre)
        return {
            **where,
            # the sensor's defect pixels patched in each frame (None: no map configured)
            "defects": None
            if self._defects is None
            else {"file": str(self._defects_path), "pixels": len(self._defects), "dead": self._defects.n_dead},
            "bit_depth": self._bit_depth,
            "centre": centre,
            "camera_calibrated_with": calibrated,
            "warning": warning,
        }

    @property
    def depth(self) -> int:
        """Frames this camera may have handed to the measurement at once (:meth:`begin` before :meth:`collect`)."""
        return DEPTH if self.settings.processing.measure_in == "process" else 1

    def waitable(self) -> Any:
        """What the oldest begun frame's outcome arrives on (a connection to wait on), or None."""
        return None if self._process is None else self._process.waitable()

    def can_begin(self) -> bool:
        """True when :meth:`begin` can hand a frame over now."""
        return self._process is None or self._process.can_submit()

    def begins_at_once(self) -> bool:
        """True when :meth:`begin` would only hand the frame to the child process: it is running, set
        up with the current calibration and options, and can take one more. Then the camera's thread
        may begin the frame itself; otherwise the processing thread does (it may start the child)."""
        cal, processing = self.calibration, self.settings.processing
        return (
            self._process is not None
            and self._measurer is self._process
            and processing.measure_in == "process"
            and cal.generation == self._generation
            and processing is self._processing
            and BIT_DEPTH.get(self.pixel_format() or "") == self._bit_depth
            and self.roi() == self._roi
            and self._configured_defects() == self._defects_path
            and self._process.can_submit()
        )

    def _current_measurer(self) -> Measurer | None:
        cal, processing = self.calibration, self.settings.processing
        bits, roi = BIT_DEPTH.get(self.pixel_format() or ""), self.roi()
        if (
            cal.generation != self._generation
            or processing is not self._processing
            or bits != self._bit_depth
            or roi != self._roi
            or self._configured_defects() != self._defects_path
        ):
            self._generation, self._processing, self._bit_depth, self._roi = cal.generation, processing, bits, roi
            if (warning := formats.centre_mismatch(cal.camera_centre, processing.centre)) is not None:
                log.warning("camera %s: %s", self.name, warning)
            camera = cal.camera
            if camera is not None and roi is not None:
                # the calibration is the whole sensor's, the frames the window's pixels; a window the
                # calibrated sensor does not hold keeps the whole camera, and each frame says so
                with contextlib.suppress(ValueError):
                    camera = camera.cropped(*roi)
            defects = None
            try:
                defects = self._defect_map(camera, roi)
                self._setup_error = None
            except ValueError as e:
                self._setup_error = f"camera {self.name}'s defect map: {e}"
            if camera is None or cal.field is None or self._setup_error is not None:
                self._measurer = None
            elif processing.measure_in == "process":
                if self._process is None:
                    self._process = MeasureProcess(self.name)
                    self._process.keep_to(self._cpus)
                self._measurer = self._process
                try:
                    self._process.configure(camera, cal.field, measure_settings(processing, bits), defects)
                except Exception:
                    self._generation = -1  # set up again with the next frame
                    raise
            else:
                self.close()
                self._measurer = FrameMeasurer(camera, cal.field, measure_settings(processing, bits), defects)
        return self._measurer

    def _configured_defects(self) -> Path | None:
        """The camera's defect map file in the current settings (``PUT /config`` may change it)."""
        return next(c for c in self.settings.cameras if c.name == self.name).defects

    def _defect_map(self, camera: BrownFraser | None, roi: tuple[int, int, int, int] | None) -> DefectMap | None:
        """The configured defect map, read now, of the window ``roi`` of the sensor; ValueError when it
        cannot be read or is not of this camera's sensor (the measurer is set up again only when the
        configured file changes, or the calibration, the processing options, the format or the roi)."""
        path = self._configured_defects()
        self._defects_path, self._defects = path, None
        if path is None:
            return None
        self._defects = formats.read_defects(path)
        defects = self._defects if roi is None else self._defects.cropped(*roi)
        if camera is not None and (defects.width, defects.height) != (camera.width, camera.height):
            self._defects = None
            raise ValueError(
                f"{path} is of a {defects.width} x {defects.height} image, the camera's frames are "
                f"{camera.width} x {camera.height}"
            )
        return defects

    def process(self, frame: Frame, robot: RobotDriver | None, robot_state: DeviceState) -> Measurement:
        """Measure one frame now (:meth:`begin`, :meth:`collect` and :meth:`finish` in one)."""
        pending = self.begin(frame)
        self.collect(pending)
        return self.finish(pending, robot, robot_state)

    def begin(self, frame: Frame) -> Pending:
        """Hand the frame to the measurement: in a child process it is measured while this thread goes on."""
        t_exposure_ns, source = self.pairer.exposure_instant_ns(frame)
        pending = Pending(frame, t_exposure_ns, source, time.perf_counter())
        measurer = self._current_measurer()
        if measurer is None and self._setup_error is not None:
            pending.failure = Failure(Reason.bad_input, self._setup_error)
        elif measurer is None:
            missing = [k for k in ("camera", "field") if getattr(self.calibration, k) is None]
            pending.failure = Failure(Reason.not_calibrated, f"no {' and no '.join(missing)} calibration is loaded")
        elif frame.image.ndim != 2 or frame.image.size == 0:
            pending.failure = Failure(Reason.bad_image, f"frame of shape {frame.image.shape} is not a grey image")
        elif isinstance(measurer, MeasureProcess):
            measurer.submit(frame.image, t_exposure_ns * 1e-9)
        else:
            pending.outcome = measurer.measure(frame.image, t_exposure_ns * 1e-9)
        return pending

    def collect(self, pending: Pending) -> None:
        """Wait for the outcome of a frame handed to the child process (no-op when measured here);
        frames are collected in the order they were begun."""
        if pending.outcome is None and pending.failure is None and self._process is not None:
            pending.outcome = self._process.collect()
        pending.t_measured = time.perf_counter()

    def finish(self, pending: Pending, robot: RobotDriver | None, robot_state: DeviceState) -> Measurement:
        """The frame's :class:`Measurement`: its pose (collected) with the flange at its exposure."""
        frame, t_exposure_ns = pending.frame, pending.t_exposure_ns
        head = {
            "camera": self.name,
            "seq": frame.seq,
            "t_exposure_host_ns": t_exposure_ns,
            "t_unix_ns": t_exposure_ns + self._wall_minus_mono_ns,
            "exposure_source": pending.exposure_source,
        }
        if pending.failure is not None or pending.outcome is None:
            fail = pending.failure or Failure(Reason.no_frame, "the frame's measurement was not collected")
            return Measurement(result=fail, **head)
        outcome = pending.outcome
        result = outcome.result
        t2 = time.perf_counter()
        flange = None
        if isinstance(result, PoseResult):
            flange = self._flange(result, pending, robot, robot_state)
        timings = dict(outcome.timings_ms)
        # the measurement as this thread saw it (in a child process: with the frame's copy and the pipe)
        timings["measure"] = (pending.t_measured - pending.t_begun) * 1e3
        timings["flange"] = (time.perf_counter() - t2) * 1e3
        timings["processing"] = (time.perf_counter() - pending.t_begun) * 1e3
        timings["latency"] = (time.monotonic_ns() - t_exposure_ns) * 1e-6
        truth = frame.meta.get("T_field_camera")  # simulation: the truth travels with the frame
        return Measurement(
            result=result,
            mode=outcome.mode,
            timings_ms=MappingProxyType(timings),
            flange=flange,
            T_field_camera_true=None if truth is None else np.asarray(truth, dtype=np.float64),
            **head,
        )

    def _flange(
        self, result: PoseResult, pending: Pending, robot: RobotDriver | None, robot_state: DeviceState
    ) -> Flange:
        t_exposure_ns = pending.t_exposure_ns
        T_reported, why = None, ""
        if robot is None or robot_state is DeviceState.absent:
            why = "no robot is configured"
        elif robot_state is not DeviceState.ok:
            why = f"the robot is {robot_state}"
        else:
            # the instant the frame was begun with: a newer frame may have been begun since
            pairing = self.pairer.pair(pending.frame, robot.history, (t_exposure_ns, pending.exposure_source))
            T_reported, why = pairing.T_base_flange, pairing.reason
        flange = flange_part(self.calibration.handeye, result.T_field_camera, T_reported, why)
        if flange.deviation is not None and T_reported is not None and flange.T_base_flange_measured is not None:
            with self._motion_lock:
                p_measured = flange.T_base_flange_measured[:3, 3].copy()
                self._motion.append((t_exposure_ns * 1e-9, p_measured, T_reported[:3, 3].copy()))
                self._n_since_offset += 1
        return flange

    def time_offset_report(self) -> dict[str, Any] | None:
        """The residual latency seen in the motion: frame times are late by ``offset_ms``."""
        with self._motion_lock:
            due = self._n_since_offset >= 50 and len(self._motion) >= 50
            motion = list(self._motion) if due else []
            if due:
                self._n_since_offset = 0
        if due:
            t, pm, pr = (np.array(x) for x in zip(*motion, strict=True))
            try:
                self._offset = estimate_time_offset_s(t - t[0], pm, pr)
            except ValueError:
                self._offset = None
        if self._offset is None:
            return None
        return {
            "offset_ms": round(self._offset.offset_s * 1e3, 3),
            "sigma_ms": round(self._offset.sigma_s * 1e3, 3),
            "n": self._offset.n,
        }
