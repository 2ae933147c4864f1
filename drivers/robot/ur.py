"""Universal Robots over RTDE: ``ur_rtde``'s receive interface in a child process.

Why a child process. ``RTDEReceiveInterface``'s constructor holds the GIL
while it connects: the whole process freezes for milliseconds normally, 2.5 s
when the controller sends no data and forever when something accepts the
connection but never answers. So the client lives in its own process (the
``spawn`` context; ``rtde_receive`` is imported only there), which

- polls the client every ``min(period / 2, 1 ms)``, so a package is seen at
  most 1 ms after ``ur_rtde`` got it (about 6 % of a core at 125 Hz, most of
  it ``ur_rtde``'s own 10 kHz receive loop), and reads timestamp -> TCP pose
  -> joints -> timestamp again, retrying when the timestamp changed in
  between, since the getters are not atomic;
- stamps each new sample with ``time.monotonic_ns()`` at detection (the
  monotonic clock is system-wide, so the pipe's delay adds no latency), and
  raises its own scheduling priority (nice -10) when the process may, since a
  starved reader loses packages (``ur_rtde`` keeps only the newest);
- treats a timestamp that has not moved for ``max(0.2 s, 20 periods)`` or
  ``isConnected()`` false as a dead link and builds a new client every
  ``reconnect_interval_s`` (a new client rather than ``reconnect()``, which
  resets the frequency to the controller's default).

The parent runs one reader thread that converts at the boundary and keeps
``history_s`` of samples in a :class:`drivers.history.RobotHistory` (``.history``,
which the pairing reads). If the child hangs in a
constructor for more than ``connect_timeout_s`` the thread kills it and
starts another.

Units and frames at the boundary. RTDE's ``actual_TCP_pose`` is
``[x, y, z, rx, ry, rz]`` in m and a rotation vector, the *TCP* in the base
frame, with the TCP offset configured on the controller already applied. It
becomes ``T_base_tcp`` in mm (:func:`service.core.geometry.frames.T_from_ur_pose`) and
then ``T_base_flange = T_base_tcp @ inv_T(T_flange_tcp)``, where
``T_flange_tcp`` (4, 4) mm must be the TCP offset set on the controller
(PolyScope's "Installation > TCP"; convert its m/rotation-vector values with
``T_from_ur_pose``). Leave it ``None`` only when the controller's TCP is zero;
the value used is in ``info.T_flange_tcp``. Joint positions (rad) pass through.

``ur_rtde``'s receive interface always uses TCP port 30004; another port is
refused at construction. Like anything started with multiprocessing's
``spawn``, the program's main module must be safe to import (its work under
``if __name__ == "__main__":``); uvicorn, pytest and console scripts are.
"""

from __future__ import annotations

import atexit
import importlib.util
import logging
import multiprocessing
import os
import struct
import threading
import time
import traceback
import weakref
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from drivers.base import DriverDisconnected, DriverInitError, DriverUnavailable, RobotInfo, RobotSample
from drivers.history import RobotHistory
from service.core.geometry.frames import T_from_ur_pose, check_T, inv_T

log = logging.getLogger(__name__)

RTDE_PORT = 30004
STALE_AFTER_S = 0.5  # latest() refuses a sample older than this
_MAX_POLL_PERIOD_S = 1e-3  # bounds the delay between a package's arrival and its host time stamp
_VARIABLES = ["timestamp", "actual_TCP_pose", "actual_q"]

# child -> parent messages: one kind byte + body
_SAMPLE = struct.Struct("<qd6d6d")  # t_host_ns, t_robot_s, pose (m, rotvec), q (rad)
_K_SAMPLE, _K_UP, _K_DOWN, _K_CONNECTING, _K_FATAL = b"S", b"U", b"D", b"C", b"F"

_OPEN_ROBOTS: weakref.WeakSet[URRobot] = weakref.WeakSet()


@atexit.register
def _close_open_robots() -> None:
    # Runs before multiprocessing's own exit hook (atexit is LIFO), so no reader thread
    # mistakes the children being reaped at exit for a crash and spawns new ones.
    for robot in list(_OPEN_ROBOTS):
        robot.close()


# --- child process ------------------------------------------------------------------------------


def _child_main(host: str, frequency_hz: float, conn: Connection, reconnect_interval_s: float) -> None:
    """Entry of the RTDE child process: connect, poll, send samples, reconnect; never returns normally."""
    # ur_rtde writes to stdout/stderr from C++; drivers never print, and errors reach the parent as messages.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    try:
        # Time stamps are the product's accuracy: run ahead of image processing when allowed (CAP_SYS_NICE).
        os.nice(-10)
    except OSError:
        pass
    try:
        import rtde_receive

        _child_loop(rtde_receive, host, frequency_hz, conn, reconnect_interval_s)
    except (BrokenPipeError, EOFError, OSError):
        pass  # the parent is gone or closed the pipe
    except BaseException:
        try:
            conn.send_bytes(_K_FATAL + traceback.format_exc().encode())
        except OSError:
            pass


def _child_loop(
    rtde_receive: Any, host: str, frequency_hz: float, conn: Connection, reconnect_interval_s: float
) -> None:
    period_s = 1.0 / frequency_hz
    poll_s = min(period_s / 2, _MAX_POLL_PERIOD_S)
    stale_s = max(0.2, 20 * period_s)
    while True:
        conn.send_bytes(_K_CONNECTING)
        try:
            client = rtde_receive.RTDEReceiveInterface(host, frequency_hz, _VARIABLES)
        except RuntimeError as e:  # refused, unreachable, or a variable the controller lacks
            conn.send_bytes(_K_DOWN + str(e).encode())
            time.sleep(reconnect_interval_s)
            continue
        if not client.isConnected():
            conn.send_bytes(_K_DOWN + b"the controller accepted the connection but sent no data")
            del client
            time.sleep(reconnect_interval_s)
            continue
        conn.send_bytes(_K_UP)
        reason = _poll(client, conn, poll_s, stale_s)
        conn.send_bytes(_K_DOWN + reason.encode())
        del client  # its destructor joins the receive thread and waits 0.5 s
        time.sleep(reconnect_interval_s)


def _poll(client: Any, conn: Connection, poll_s: float, stale_s: float) -> str:
    """Send every new sample until the link dies; return why it died."""
    last_ts = None
    last_change = time.monotonic()
    next_poll = last_change
    while True:
        next_poll += poll_s
        delay = next_poll - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_poll = time.monotonic()  # fell behind: do not try to catch up with a burst
        ts = client.getTimestamp()
        t_host_ns = time.monotonic_ns()
        if ts == last_ts:
            if not client.isConnected():
                return "the controller closed the RTDE connection"
            if time.monotonic() - last_change > stale_s:
                return f"no new RTDE data for {stale_s:.2f} s"
            continue
        for _ in range(5):
            pose = client.getActualTCPPose()
            q = client.getActualQ()
            ts2 = client.getTimestamp()
            if ts2 == ts:
                break
            ts, t_host_ns = ts2, time.monotonic_ns()  # a newer package landed mid-read: read it again
        else:
            continue
        last_ts = ts
        last_change = time.monotonic()
        conn.send_bytes(_K_SAMPLE + _SAMPLE.pack(t_host_ns, ts, *pose, *q))


# --- parent -------------------------------------------------------------------------------------


class URRobot:
    """A UR controller read over RTDE (see the module docstring for the process split and frames).

    Parameters
    ----------
    host : the controller's address.
    port : must be 30004 (``ur_rtde`` fixes it).
    frequency_hz : asked output rate, 125 Hz (CB3) or up to 500 Hz (e-Series).
    T_flange_tcp : (4, 4) mm, the TCP offset configured on the controller; None means it is zero.
    history_s : how much history ``samples_between`` can reach.
    reconnect_interval_s : wait between connection attempts after a lost link.
    open_timeout_s : how long ``open`` waits for the first sample.
    connect_timeout_s : a connection attempt that hangs longer restarts the child process.
    """

    def __init__(
        self,
        host: str,
        port: int = RTDE_PORT,
        frequency_hz: float = 500.0,
        T_flange_tcp: Any = None,
        history_s: float = 10.0,
        reconnect_interval_s: float = 1.0,
        open_timeout_s: float = 5.0,
        connect_timeout_s: float = 5.0,
    ) -> None:
        if port != RTDE_PORT:
            raise ValueError(f"ur_rtde's receive interface always connects to port {RTDE_PORT}, not {port}")
        if not 0.0 < frequency_hz <= 500.0:
            raise ValueError(f"frequency_hz must be in (0, 500], got {frequency_hz}")
        self.host = host
        self.port = port
        self.frequency_hz = float(frequency_hz)
        self.T_flange_tcp = np.eye(4) if T_flange_tcp is None else check_T(T_flange_tcp, "T_flange_tcp").copy()
        self._T_tcp_flange = inv_T(self.T_flange_tcp)
        self.history_s = history_s
        self.reconnect_interval_s = reconnect_interval_s
        self.open_timeout_s = open_timeout_s
        self.connect_timeout_s = connect_timeout_s

        self._lock = threading.Lock()
        self._child_lock = threading.Lock()
        self._history = RobotHistory(max(2, int(history_s * self.frequency_hz * 1.1) + 16))
        self._link_up = False
        self._link_reason = "not opened"
        self._connecting_since_ns: int | None = None
        self._first_sample = threading.Event()
        self._first_failure: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._proc: Any = None
        self._conn: Connection | None = None
        self.stats = {"samples": 0, "links_up": 0, "links_lost": 0, "child_restarts": 0}

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def info(self) -> RobotInfo:
        return RobotInfo(
            driver="ur",
            model="Universal Robots (RTDE)",
            address=self.address,
            rate_hz=self.frequency_hz,
            T_flange_tcp=tuple(tuple(float(v) for v in row) for row in self.T_flange_tcp),
        )

    @property
    def history(self) -> RobotHistory:
        return self._history

    @property
    def connected(self) -> bool:
        sample = self._history.latest()
        fresh = sample is not None and time.monotonic_ns() - sample.t_host_ns < STALE_AFTER_S * 1e9
        return self._link_up and fresh

    # -- lifecycle --

    def open(self) -> None:
        """Start the RTDE child and wait for the first sample; raises ``DriverInitError`` if none comes."""
        if self._thread is not None:
            return
        if importlib.util.find_spec("rtde_receive") is None:
            raise DriverUnavailable("the UR driver needs the ur-rtde package (module rtde_receive), not installed")
        self._stop.clear()
        self._first_sample.clear()
        self._first_failure = None
        self._history.clear()
        T_from_ur_pose(np.zeros(6))  # loads the compiled rotation here, not while the first sample waits
        self._spawn_child()
        self._thread = threading.Thread(target=self._read_loop, name=f"ur-rtde-{self.host}", daemon=True)
        self._thread.start()
        _OPEN_ROBOTS.add(self)
        deadline = time.monotonic() + self.open_timeout_s
        # until a *fresh* sample: on a busy host the first ones can be handled after they went stale,
        # and open() returning means connected
        while time.monotonic() < deadline and not self.connected and self._first_failure is None:
            self._first_sample.wait(0.02)
            if self._first_sample.is_set():
                time.sleep(0.002)
        if not self._first_sample.is_set():
            why = self._first_failure or f"nothing within {self.open_timeout_s:g} s"
            self.close()
            raise DriverInitError(f"no RTDE controller answered at {self.address} ({why})")

    def close(self) -> None:
        """Kill the child at once, stop the reader thread; idempotent."""
        self._stop.set()
        self._kill_child()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._kill_child()  # one the reader thread may have spawned while we were stopping it
        _OPEN_ROBOTS.discard(self)
        with self._lock:
            self._link_up = False
            self._link_reason = "closed"

    def __enter__(self) -> URRobot:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data --

    def latest(self) -> RobotSample:
        """The newest sample; ``DriverDisconnected`` when the link is down or the sample is stale."""
        now_ns = time.monotonic_ns()
        sample = self._history.latest()
        with self._lock:
            up, reason = self._link_up, self._link_reason
        if sample is None:
            raise DriverDisconnected(f"no robot sample from the UR controller at {self.address} yet ({reason})")
        age_s = (now_ns - sample.t_host_ns) * 1e-9
        if not up:
            raise DriverDisconnected(
                f"the RTDE link to the UR controller at {self.address} is down ({reason}); "
                f"last sample {age_s:.1f} s ago; reconnecting"
            )
        if age_s > STALE_AFTER_S:
            raise DriverDisconnected(f"the UR controller at {self.address} sent nothing for {age_s:.1f} s")
        return sample

    def samples_between(self, t0_host_ns: int, t1_host_ns: int) -> list[RobotSample]:
        """Buffered samples with ``t0 <= t_host_ns <= t1``, oldest first."""
        return self._history.samples_between(t0_host_ns, t1_host_ns)

    # -- child management (reader thread and open/close) --

    def _spawn_child(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        recv_end, send_end = ctx.Pipe(duplex=False)
        proc = ctx.Process(
            target=_child_main,
            name=f"ur-rtde-{self.host}",
            args=(self.host, self.frequency_hz, send_end, self.reconnect_interval_s),
            daemon=True,
        )
        proc.start()
        send_end.close()  # the child holds the only writer, so its death shows as EOF here
        with self._child_lock:
            self._proc, self._conn = proc, recv_end
        self._connecting_since_ns = time.monotonic_ns()  # spawning counts as connecting for the watchdog

    def _kill_child(self) -> None:
        with self._child_lock:  # close() and the reader thread may both get here
            proc, conn = self._proc, self._conn
            self._proc = self._conn = None
        if proc is not None:
            proc.terminate()
            proc.join(timeout=1.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=1.0)
            try:
                proc.close()
            except ValueError:
                log.error("the RTDE child for %s (pid %s) did not die", self.address, proc.pid)
        if conn is not None:
            conn.close()

    def _read_loop(self) -> None:
        n_warned = 0
        while not self._stop.is_set():
            conn = self._conn
            try:
                if conn is None or not conn.poll(0.05):
                    self._watchdog()
                    continue
                msg = conn.recv_bytes()
            except (EOFError, OSError):
                if self._stop.is_set():
                    break
                self._restart_child(f"the RTDE child process ended (exit code {self._child_exitcode()})")
                continue
            try:
                self._on_message(msg)
            except Exception:
                if n_warned < 5:
                    log.exception("bad message from the RTDE child")
                    n_warned += 1

    def _watchdog(self) -> None:
        since = self._connecting_since_ns
        if since is not None and time.monotonic_ns() - since > self.connect_timeout_s * 1e9:
            self._restart_child(f"a connection attempt hung for more than {self.connect_timeout_s:g} s")

    def _restart_child(self, reason: str) -> None:
        self._set_down(reason)
        if self._stop.is_set():
            return
        log.warning("restarting the RTDE child for %s: %s", self.address, reason)
        self._kill_child()
        self.stats["child_restarts"] += 1
        # A child that dies at once must not turn into a spawn storm.
        if not self._stop.wait(self.reconnect_interval_s):
            self._spawn_child()

    def _child_exitcode(self) -> int | None:
        proc = self._proc
        if proc is None:
            return None
        proc.join(timeout=0.5)
        return proc.exitcode

    def _set_down(self, reason: str) -> None:
        with self._lock:
            if self._link_up:
                self.stats["links_lost"] += 1
                log.warning("RTDE link to %s lost: %s", self.address, reason)
            self._link_up = False
            self._link_reason = reason
        if not self._first_sample.is_set() and self._first_failure is None and reason:
            self._first_failure = reason

    def _on_message(self, msg: bytes) -> None:
        kind, body = msg[:1], msg[1:]
        if kind == _K_SAMPLE:
            self._on_sample(*_unpack_sample(body))
        elif kind == _K_CONNECTING:
            self._connecting_since_ns = time.monotonic_ns()
        elif kind == _K_UP:
            self._connecting_since_ns = None
            with self._lock:
                self._link_up = True
                self._link_reason = "connected"
            self.stats["links_up"] += 1
            log.info("RTDE link to %s up at %g Hz", self.address, self.frequency_hz)
        elif kind == _K_DOWN:
            self._connecting_since_ns = None
            self._set_down(body.decode(errors="replace"))
        elif kind == _K_FATAL:
            log.error("the RTDE child for %s failed:\n%s", self.address, body.decode(errors="replace"))
            self._set_down("the RTDE client process failed")

    def _on_sample(self, t_host_ns: int, t_robot_s: float, pose: tuple[float, ...], q: tuple[float, ...]) -> None:
        T_base_flange = T_from_ur_pose(pose) @ self._T_tcp_flange
        self._history.append(
            RobotSample(T_base_flange=T_base_flange, q_rad=np.array(q), t_host_ns=t_host_ns, t_robot_s=t_robot_s)
        )
        self.stats["samples"] += 1
        self._first_sample.set()


def _unpack_sample(body: bytes) -> tuple[int, float, tuple[float, ...], tuple[float, ...]]:
    v = _SAMPLE.unpack(body)
    return v[0], v[1], v[2:8], v[8:14]
