"""The simulated robot controller: the simulated cell's arm, reported at a fixed rate.

A reader thread produces a sample every controller tick, as RTDE does: the
*nominal* flange pose of the (noisy) encoder joints, the controller's own
timestamp (seconds since its start, on a clock with an offset and a drift
against the host), and an arrival time ``latency_s`` (+ exponential jitter)
after the tick. The camera of the same cell sees the *true* pose, so the
difference is the robot model error posecell is there to measure.

``unplug()`` / ``plug()`` drop and restore the link for tests and the demo.
Not modelled: the controller's interpolation between ticks, speed scaling,
protective stops.
"""

from __future__ import annotations

import heapq
import threading
import time

import numpy as np

from drivers.base import DriverDisconnected, DriverInitError, RobotInfo, RobotSample
from drivers.history import RobotHistory
from service.sim.cell import CellConfig, SimCell

STALE_S = 0.5  # a newest sample older than this means the link is down


class SimRobot:
    """A robot of the simulated cell (see the module docstring).

    Parameters
    ----------
    cell : the shared simulated cell (the camera driver must see the same one)
    epoch_ns : host monotonic time of the cell's t = 0, shared with the camera driver
    rate_hz : controller reporting rate (RTDE: 125 or 500 Hz)
    """

    def __init__(
        self,
        cell: SimCell | None = None,
        cell_config: dict[str, object] | None = None,
        epoch_ns: int | None = None,
        rate_hz: float = 500.0,
        latency_s: float = 0.001,
        jitter_s: float = 0.0002,
        clock_offset_s: float = 86.0,
        clock_drift_ppm: float = -20.0,
        history_s: float = 10.0,
        seed: int = 2,
    ) -> None:
        self._cell = cell if cell is not None else SimCell(CellConfig(**(cell_config or {})))
        self.epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)
        self.rate_hz = float(rate_hz)
        self.latency_ns = int(latency_s * 1e9)
        self.jitter_ns = float(jitter_s * 1e9)
        self.clock_offset_s = clock_offset_s
        self.clock_rate = 1.0 + clock_drift_ppm * 1e-6
        self._rng = np.random.default_rng(seed)  # the encoders' noise
        self._jitter = np.random.default_rng([seed, 1])  # the delivery's, drawn apart: a tick ahead
        self._history = RobotHistory(max(2, int(history_s * rate_hz)))
        self._plugged = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def info(self) -> RobotInfo:
        model = f"simulated {self._cell.config.robot}"
        return RobotInfo(driver="sim", model=model, address="sim", rate_hz=self.rate_hz)

    @property
    def cell(self) -> SimCell:
        return self._cell

    @property
    def history(self) -> RobotHistory:
        return self._history

    @property
    def connected(self) -> bool:
        latest = self._history.latest()
        return (
            self._plugged
            and self._thread is not None
            and latest is not None
            and time.monotonic_ns() - latest.t_host_ns < STALE_S * 1e9
        )

    def open(self) -> None:
        if not self._plugged:
            raise DriverInitError("simulated robot controller is unplugged")
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-robot", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 2.0
        while self._history.latest() is None:
            if time.monotonic() > deadline:
                self.close()
                raise DriverInitError("simulated robot controller produced no sample within 2 s")
            time.sleep(0.001)

    def latest(self) -> RobotSample:
        sample = self._history.latest()
        if self._thread is None:
            raise DriverDisconnected("the simulated robot controller is not open")
        if not self._plugged or sample is None or time.monotonic_ns() - sample.t_host_ns > STALE_S * 1e9:
            raise DriverDisconnected("the simulated robot controller does not answer")
        return sample

    def samples_between(self, t0_host_ns: int, t1_host_ns: int) -> list[RobotSample]:
        return self._history.samples_between(t0_host_ns, t1_host_ns)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def move_to(self, T_base_flange: np.ndarray, speed_mm_s: float = 250.0) -> float:
        """Simulation only: move the arm to a flange pose (planned like a linear move); returns its duration s.

        Real robots are moved by the integrator's robot program; the service never commands them.
        """
        t_now_s = (time.monotonic_ns() - self.epoch_ns) * 1e-9
        return self._cell.command_move(T_base_flange, t_now_s + 0.05, speed_mm_s)

    def unplug(self) -> None:
        self._plugged = False

    def plug(self) -> None:
        self._plugged = True

    # --- the controller ---------------------------------------------------------------------

    def _run(self) -> None:
        # One wake-up per report, at its arrival: each tick's arrival is drawn a tick ahead, and its
        # report (the arm at the tick) computed when it arrives. Waking at the tick too, to compute it
        # then, doubled the thread's wake-ups (a tenth of a core at 500 Hz on a 2-vCPU host).
        period_ns = int(1e9 / self.rate_hz)
        k = (time.monotonic_ns() - self.epoch_ns) // period_ns + 1
        in_flight: list[tuple[int, int]] = []  # (arrival ns, tick), a heap
        ahead = _Ahead()
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if now - (self.epoch_ns + k * period_ns) > 100_000_000:  # fell far behind (busy machine)
                k = (now - self.epoch_ns) // period_ns
            while self.epoch_ns + k * period_ns <= now + period_ns:  # the ticks up to the next one
                arrival = (
                    self.epoch_ns + k * period_ns + self.latency_ns + int(self._jitter.exponential(self.jitter_ns))
                )
                heapq.heappush(in_flight, (arrival, k))
                k += 1
            while in_flight and in_flight[0][0] <= now:
                _, tick = heapq.heappop(in_flight)
                t_tick_ns = self.epoch_ns + tick * period_ns
                T, q = ahead.report(self._cell, tick, period_ns * 1e-9, self._rng)
                t_robot_s = (t_tick_ns * 1e-9 - self.clock_offset_s) * self.clock_rate
                t_cell_s = (t_tick_ns - self.epoch_ns) * 1e-9
                if self._plugged:  # stamped on receipt, like a real reader thread (scheduling jitter included)
                    self._history.append(RobotSample(T, q, time.monotonic_ns(), t_robot_s, {"t_cell_s": t_cell_s}))
            delay = (in_flight[0][0] - time.monotonic_ns()) * 1e-9
            if delay > 0:  # a sleep, not the stop event's wait: 21 against 50 us of CPU a wake-up here
                time.sleep(min(delay, 0.01))  # close() waits at most this for the loop to see the stop


AHEAD_TICKS = 8  # reports computed together: one vectorised forward kinematics instead of eight


class _Ahead:
    """The controller's next reports, computed a few ticks at a time (at 500 Hz one tick's forward
    kinematics cost a tenth of the service's interpreter time); a new command to the cell makes
    them be computed again, so a report never lags a commanded motion."""

    def __init__(self) -> None:
        self.k0, self.T, self.q = 0, np.zeros((0, 4, 4)), np.zeros((0, 6))
        self.commands: object = None

    def report(self, cell: SimCell, k: int, period_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        i = k - self.k0
        if cell.commands is not self.commands or not 0 <= i < len(self.T):
            self.commands, self.k0, i = cell.commands, k, 0
            self.T, self.q = cell.robot_report((k + np.arange(AHEAD_TICKS)) * period_s, rng)
        return self.T[i], self.q[i]
