"""The simulated cell as the service runs it: one SimCell shared by the simulated drivers.

With ``sim.transport = "direct"`` the simulated drivers (``drivers/camera/sim.py``,
``drivers/robot/sim.py``) read the cell in-process. Both share the cell and its
epoch (the host monotonic time of the cell's t = 0), so the camera sees the arm
where the controller says it is, up to the arm's model errors.

With ``sim.transport = "standins"`` the service runs its *real* drivers against
protocol stand-ins of the same cell, each in a process of its own
(``python -m drivers.standins.sim_cell``, see there why): the Aravis driver
against Aravis's fake GigE Vision camera on 127.0.0.1 (the only loopback address
of an interface, which the fake camera needs), and the UR driver (ur_rtde in its
child process) against the RTDE stand-in on an address of its own. Both get the
epoch, so they show one motion.

A watchdog thread restarts a stand-in whose process ended (a crash, a kill),
with the same cell and epoch, and reports it through ``on_event(level, kind,
message)`` (the worker's event log) as ``standin_died`` and ``standin_restarted``;
restarts back off from 1 s to 30 s while a stand-in keeps dying.

The simulated devices' delivery delays, which the clock mappings cannot see, are
stated as an installation states its own devices': :func:`with_stated_latencies`
gives the settings with them, and the worker is built with those (settings are
frozen: nothing here changes the settings it was given).
"""

from __future__ import annotations

import json
import logging
import select
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from service.settings import CameraConfig, Settings
from service.sim.cell import CellConfig, SimCell
from service.store.formats import field_to_json

log = logging.getLogger(__name__)

GV_ADDRESS = "127.0.0.1"  # Aravis's fake camera needs an address of an interface: lo has only this one
RTDE_ADDRESS = "127.0.0.20"  # ur_rtde's port is fixed (30004): an address of its own, clear of the tests'
READY_TIMEOUT_S = 90.0  # a stand-in's start: the camera's waits up to 60 s for another user of its address
WATCH_PERIOD_S = 0.5
RESTART_BACKOFF_S = (1.0, 30.0)
# the stand-ins' smallest delivery delays on loopback, which the clock mappings cannot see (measured on
# a loaded 2-core host: a frame's leader 0.25-0.3 ms after its exposure, a package 0.2 ms after its tick)
STANDIN_CAMERA_LATENCY_S = 0.0003
STANDIN_ROBOT_LATENCY_S = 0.0002
# the in-process simulated controller's delivery delay (drivers/robot/sim.py, SimRobot's latency_s)
SIM_ROBOT_LATENCY_S = 0.001

EventSink = Callable[[str, str, str], None]


def with_stated_latencies(settings: Settings) -> Settings:
    """``settings`` with the simulated devices' delivery delays stated (a new object; the same if none is simulated).

    The in-process simulated controller delivers its samples ``SIM_ROBOT_LATENCY_S`` late (without it
    stated the simulated cell's deviation carries a lag bias: 0.19 mm on the 190 mm/s circle); with
    ``sim.transport = "standins"`` the loopback stand-ins deliver frames ``STANDIN_CAMERA_LATENCY_S``
    and samples ``STANDIN_ROBOT_LATENCY_S`` after their instants. Real devices keep what is configured.
    """
    if not settings.uses_sim:
        return settings
    out = settings
    standins = settings.sim.transport == "standins"
    if settings.robot.driver == "sim":
        latency_s = STANDIN_ROBOT_LATENCY_S if standins else SIM_ROBOT_LATENCY_S
        out = out.model_copy(update={"robot": out.robot.model_copy(update={"transport_latency_s": latency_s})})
    if standins:
        # frames rendered ahead leave right after their exposure: copy and loopback transfer
        for c in settings.cameras:
            if c.driver == "sim":
                out = out.with_camera(c.model_copy(update={"transport_latency_s": STANDIN_CAMERA_LATENCY_S}))
    return out


def _log_event(level: str, kind: str, message: str) -> None:
    log.log(logging.INFO if level == "info" else logging.WARNING, "%s: %s", kind, message)


class StandInProcess:
    """One stand-in process: started from ``argv``, ready once it prints ``ready``, stopped with SIGTERM."""

    def __init__(self, name: str, argv: list[str]) -> None:
        self.name = name
        self.argv = argv
        self.proc: subprocess.Popen[str] | None = None
        self.restarts = 0

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def spawn(self) -> None:
        # its stdin is ours: when this process dies, however, the stand-in sees end-of-file and stops
        self.proc = subprocess.Popen(
            [*self.argv, "--parent-stdin"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S, cancel: threading.Event | None = None) -> None:
        """Block until the process says ``ready``; raises ``RuntimeError`` (and kills it) if it does not.

        ``cancel`` set ends the wait early (the runtime is stopping), as a failed start.
        """
        proc = self.proc
        assert proc is not None and proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        line = ""
        while (remaining := deadline - time.monotonic()) > 0 and not (cancel is not None and cancel.is_set()):
            ready, _, _ = select.select([proc.stdout], [], [], min(remaining, 0.2))
            if ready:
                line = proc.stdout.readline()  # "" when it ended before saying anything
                break
        if line.strip() != "ready":
            code = proc.poll()
            self.stop()
            why = f"exit code {code}" if code is not None else f"no answer within {timeout_s:g} s"
            raise RuntimeError(f"the {self.name} stand-in did not start ({why})")

    def exit_code(self) -> int | None:
        """None while it runs (or was never started), else how it ended."""
        return None if self.proc is None else self.proc.poll()

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                pipe.close()


class CellRuntime:
    """The simulated cell of ``settings`` (its ``sim`` section and which devices are simulated, which
    no run-time change touches) and its stand-in processes."""

    def __init__(self, settings: Settings, on_event: EventSink | None = None) -> None:
        self.settings = settings
        self.active = settings.uses_sim
        self.epoch_ns = time.monotonic_ns()
        self.on_event: EventSink = on_event or _log_event
        self._cell: SimCell | None = None
        self.rtde_address = RTDE_ADDRESS  # tests running beside a service take addresses of their own
        self.standin_processes: dict[str, StandInProcess] = {}
        self._stop = threading.Event()
        self._watchdog: threading.Thread | None = None
        self._lock = threading.Lock()  # start/stop against the watchdog's restarts

    @property
    def cell(self) -> SimCell:
        if self._cell is None:
            s = self.settings.sim
            self._cell = SimCell(CellConfig(seed=s.seed, robot=s.robot, program=s.program, error_scale=s.error_scale))
        return self._cell

    @property
    def standins(self) -> bool:
        return self.active and self.settings.sim.transport == "standins"

    def start(self) -> None:
        if not self.active:
            return
        cell = self.cell  # build it (inverse kinematics of the program) before the drivers need it
        if not self.standins:
            return
        import drivers.standins.gv_camera  # noqa: F401 -- fail here, with the reason, if Aravis is missing

        common = ["--epoch-ns", str(self.epoch_ns), "--cell", json.dumps(cell.config.to_dict())]
        module = [sys.executable, "-m", "drivers.standins.sim_cell"]
        self.standin_processes = {
            "camera": StandInProcess(
                "GigE Vision camera",
                [*module, "--serve", "camera", "--host", GV_ADDRESS, "--serial", "POSECELL-SIM", *common],
            ),
            "rtde": StandInProcess("RTDE", [*module, "--serve", "rtde", "--host", self.rtde_address, *common]),
        }
        self._stop.clear()
        with self._lock:
            try:
                for p in self.standin_processes.values():  # both start at once: each builds the cell
                    p.spawn()
                for p in self.standin_processes.values():
                    p.wait_ready(cancel=self._stop)
            except BaseException:
                for p in self.standin_processes.values():
                    p.stop()
                raise
        self._watchdog = threading.Thread(target=self._watch, name="standins-watchdog", daemon=True)
        self._watchdog.start()

    def stop(self) -> None:
        self._stop.set()
        if self._watchdog is not None:
            self._watchdog.join(timeout=10)
            self._watchdog = None
        with self._lock:
            for p in self.standin_processes.values():
                p.stop()

    # --- the watchdog ----------------------------------------------------------------------------

    def _watch(self) -> None:
        backoff = {name: RESTART_BACKOFF_S[0] for name in self.standin_processes}
        due = dict.fromkeys(self.standin_processes, 0.0)
        while not self._stop.wait(WATCH_PERIOD_S):
            for name, p in self.standin_processes.items():
                with self._lock:
                    if self._stop.is_set():
                        return
                    code = p.exit_code()
                    if p.proc is not None and code is None:
                        backoff[name] = max(RESTART_BACKOFF_S[0], backoff[name] / 2)  # ran a while: forgive
                        continue
                    if time.monotonic() < due[name]:
                        continue
                    if p.proc is not None:
                        self.on_event(
                            "warning",
                            "standin_died",
                            f"the {p.name} stand-in (pid {p.pid}) ended with exit code {code}; restarting",
                        )
                        p.stop()
                    due[name] = time.monotonic() + backoff[name]
                    backoff[name] = min(RESTART_BACKOFF_S[1], backoff[name] * 2)
                    try:
                        p.spawn()
                        p.wait_ready(cancel=self._stop)
                    except (OSError, RuntimeError) as e:
                        self.on_event("warning", "standin_failed", f"restarting the {p.name} stand-in: {e}")
                        continue
                    p.restarts += 1
                    self.on_event("info", "standin_restarted", f"the {p.name} stand-in is back (pid {p.pid})")

    # --- the drivers the service builds ------------------------------------------------------------

    def camera_driver(self, cfg: CameraConfig) -> tuple[str, dict[str, Any]]:
        """The registry name and options of a configured camera (the simulated one is substituted here)."""
        if cfg.driver == "replay" and str(cfg.options.get("source", "sim")) == "sim":
            return "replay", {"cell": self.cell, **cfg.options}  # it renders this cell's config, ahead
        if cfg.driver != "sim":
            return cfg.driver, dict(cfg.options)
        if self.standins:
            # a UDP socket: arrival stamps within ~0.3 ms (the packet-socket ring batches for 5 ms)
            return "aravis", {"device": GV_ADDRESS, "packet_size": 8192, "packet_socket": False}
        return "sim", {"cell": self.cell, "epoch_ns": self.epoch_ns, **cfg.options}

    def robot_driver(self) -> tuple[str, dict[str, Any]]:
        r = self.settings.robot
        if r.driver != "sim":
            return r.driver, dict(r.options)
        if self.standins:
            return "ur", {"host": self.rtde_address, "frequency_hz": 500.0}
        return "sim", {"cell": self.cell, "epoch_ns": self.epoch_ns, **r.options}

    def defaults(self) -> dict[str, Any]:
        """Calibrations the simulated cell knows exactly (used when nothing else is stored)."""
        cell = self.cell
        out: dict[str, Any] = {"camera": cell.camera.to_dict(), "field": field_to_json(cell.field)}
        if self.settings.sim.preload_handeye:
            out["handeye"] = {
                "T_flange_camera": cell.T_flange_camera.tolist(),
                "T_base_field": cell.T_base_field.tolist(),
                "note": "the simulated cell's true hand-eye (preload_handeye = true)",
            }
        return out
