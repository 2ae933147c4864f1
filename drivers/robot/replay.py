"""The replay robot: a recording's ``robot.csv`` played in step with its frames.

``[robot] driver = "replay"``, ``options = { source = "<state dir>/recordings/<id>" }`` (the
recording's folder, or its ``robot.csv``), with the cameras as ``driver = "replay"``,
``options = { source = "<that folder>/<camera>", timing = "recorded" }``. Each sample is appended
to the history at the host instant :mod:`drivers.replay_clock` gives its recorded time, the clock
the replayed frames are stamped on, so the service pairs every frame with the robot samples it was
recorded with and the flange deviations of a replay are those of the session. A sample keeps its
recorded pose, joints and controller time (plus the recording's span on each later pass).

Each pass plays the samples from half a frame interval before the first frame to half one after
the last, so passes join without a sample out of order. ``loop = false`` stops after one pass
(the robot then reads as disconnected, as a controller that stopped answering).

Not modelled: the link's latency and jitter (the recorded arrival times are replayed as they were).
"""

from __future__ import annotations

import csv
import io
import threading
import time
from pathlib import Path

import numpy as np

from drivers.base import DriverDisconnected, DriverInitError, RobotInfo, RobotSample
from drivers.history import RobotHistory
from drivers.replay_clock import LEAD_S, ReplayClock, clock_of, recording_of
from service.core.geometry.so3 import T_from_rotvec

STALE_S = 0.5  # no sample for this long: the link reads as down
_POSE = ("x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")


def read_robot_csv(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A recording's robot.csv: t_host_ns (K,), t_robot_s (K,) NaN where none, T_base_flange (K, 4, 4),
    q_rad (K, 6)."""
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))))
        t = np.array([int(r["t_host_ns"]) for r in rows], dtype=np.int64)
        t_robot = np.array([float(r["t_robot_s"]) if r["t_robot_s"] else np.nan for r in rows])
        pose = np.array([[float(r[k]) for k in _POSE] for r in rows]).reshape(-1, 6)
        q = np.array([[float(r[f"q{i}_rad"]) for i in range(1, 7)] for r in rows]).reshape(-1, 6)
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise DriverInitError(f"{path} cannot be read as a recording's robot samples ({e})") from None
    if t.size < 2 or np.any(np.diff(t) <= 0):
        raise DriverInitError(f"{path} needs at least two samples in increasing time order")
    return t, t_robot, np.asarray(T_from_rotvec(pose[:, 3:], pose[:, :3])), q


class ReplayRobot:
    """A recording's robot samples on the replay clock (see the module docstring)."""

    def __init__(self, source: str | Path, loop: bool = True, history_s: float = 10.0) -> None:
        self.source = Path(source).expanduser()
        self.loop = bool(loop)
        self.history_s = float(history_s)
        self._history = RobotHistory(2)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rate_hz = 0.0

    @property
    def info(self) -> RobotInfo:
        return RobotInfo("replay", f"replay of {self.source}", str(self.source), self._rate_hz)

    @property
    def history(self) -> RobotHistory:
        return self._history

    @property
    def connected(self) -> bool:
        latest = self._history.latest()
        fresh = latest is not None and time.monotonic_ns() - latest.t_host_ns < STALE_S * 1e9
        return self._thread is not None and fresh

    def open(self) -> None:
        if self._thread is not None:
            return
        recording = recording_of(self.source)
        t, t_robot, T, q = read_robot_csv(recording / "robot.csv")
        clock = clock_of(recording)
        self._rate_hz = float(1e9 / np.median(np.diff(t)))
        self._history = RobotHistory(max(2, int(self.history_s * self._rate_hz)))
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, args=(clock, t, t_robot, T, q), name="replay-robot", daemon=True
        )
        self._thread.start()
        deadline = time.monotonic() + LEAD_S + 2.0  # the first sample plays shortly before the first frame
        while self._history.latest() is None:
            if time.monotonic() > deadline or not self._thread.is_alive():
                self.close()
                raise DriverInitError(f"the replay robot of {self.source} produced no sample")
            time.sleep(0.005)

    def latest(self) -> RobotSample:
        if self._thread is None:
            raise DriverDisconnected(f"the replay robot of {self.source} is not open")
        sample = self._history.latest()
        if sample is None or time.monotonic_ns() - sample.t_host_ns > STALE_S * 1e9:
            raise DriverDisconnected(f"the replay robot of {self.source} has no current sample")
        return sample

    def samples_between(self, t0_host_ns: int, t1_host_ns: int) -> list[RobotSample]:
        return self._history.samples_between(t0_host_ns, t1_host_ns)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    # --- the reader ---------------------------------------------------------------------------

    def _run(self, clock: ReplayClock, t: np.ndarray, t_robot: np.ndarray, T: np.ndarray, q: np.ndarray) -> None:
        # a pass plays [t0 - margin, t0 + span - margin), margin half a frame interval: the samples
        # around every frame, and consecutive passes join in order
        margin = clock.step_ns // 2
        keep = (t >= clock.t0_ns - margin) & (t < clock.t0_ns + clock.span_ns - margin)
        t, t_robot, T, q = t[keep], t_robot[keep], T[keep], q[keep]
        if t.size == 0:
            return
        span_s = clock.span_ns * 1e-9
        n_pass, m = 0, 0
        # a robot opened late starts where the clock is, as a controller already running would
        now = time.monotonic_ns()
        behind = now - int(self.history_s * 1e9)
        while self.loop and clock.host_ns(int(t[-1]), n_pass) < behind:
            n_pass += 1
        while not self._stop.is_set():
            due = int(clock.host_ns(int(t[m]), n_pass))
            wait_ns = due - time.monotonic_ns()
            if wait_ns > 0:
                self._stop.wait(min(wait_ns * 1e-9, 0.05))
                continue
            t_r = None if np.isnan(t_robot[m]) else float(t_robot[m]) + n_pass * span_s
            self._history.append(RobotSample(T[m], q[m], due, t_r))
            m += 1
            if m == t.size:
                if not self.loop:
                    return
                m, n_pass = 0, n_pass + 1
