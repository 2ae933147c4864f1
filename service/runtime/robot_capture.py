"""A robot calibration sample: the arm at rest, its flange measured through the camera and the hand-eye.

What the robot calibration session (:mod:`service.runtime.robot_calibration`) and its verification
record at each pose, and the simulated arm's moves between them:

- :func:`capture` takes a sample at rest only (the reported flange's mean over the first and over
  the last third of 0.3 s within 0.05 mm / 0.01°). It averages ``frames`` measured frames: the
  measured flange pose (camera + hand-eye), the reported one, and the joints at each exposure
  (the mean of the controller's samples within ±0.1 s of it, refused if they spread by more than
  1e-4 rad: at rest they agree to the encoder noise, so no interpolation is needed), with the σ
  of the mean. A frame that fails is tried again, as an operator would press again.
- :func:`move_joints` moves the simulated arm (the only one posecell moves) and returns at rest.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.core.geometry.frames import rotation_angle_deg
from service.core.geometry.so3 import R_from_rotvec, rotvec_between
from service.core.measurement import iso_wall
from service.core.results import PoseResult, Reason
from service.runtime.accuracy_plans import REST_TOL_DEG, REST_TOL_MM, REST_WINDOW_S, measured_flange_sigma
from service.runtime.handeye_session import SessionError
from service.sim.robot import JointTrajectory

JOINT_WINDOW_NS = 100_000_000  # at rest, the controller's samples this close to an exposure give its joints
JOINT_REST_RAD = 1e-4  # their spread at rest (encoder noise ~1e-5 rad); more: the arm moved
REST_TIMEOUT_S = 10.0
RETRIES = 3  # a failed frame of a sample is tried again this often
RETRY_WAIT_S = 0.3
FRAME_TIMEOUT_S = 5.0
JOINT_SPEED_DEG_S = 120.0  # the simulated arm's joint moves (a UR10e's base and shoulder limit; a KR15's is 156)


@dataclass
class RobotSample:
    pose: int | None  # the planned pose it was taken at, if any
    holdout: bool
    q_rad: np.ndarray  # (6,) joints at the exposures, mean
    T_base_flange_reported: np.ndarray  # (4, 4) mm, mean
    T_base_flange_measured: np.ndarray  # (4, 4) mm, mean
    sigma_position_mm: list[float]  # of the mean, base axes
    sigma_rotation_deg: list[float]
    n_frames: int
    t_wall: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "pose": self.pose,
            "holdout": self.holdout,
            "joints_deg": np.degrees(self.q_rad).round(6).tolist(),
            "T_base_flange_reported": self.T_base_flange_reported.tolist(),
            "T_base_flange_measured": self.T_base_flange_measured.tolist(),
            "sigma_position_mm": self.sigma_position_mm,
            "sigma_rotation_deg": self.sigma_rotation_deg,
            "n_frames": self.n_frames,
            "t_wall": self.t_wall,
        }

    def to_state(self) -> dict[str, Any]:
        """:meth:`to_dict` with the joints as measured (rad, not rounded), for the stored session."""
        return {**self.to_dict(), "q_rad": self.q_rad.tolist()}

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> RobotSample:
        return cls(
            pose=None if d["pose"] is None else int(d["pose"]),
            holdout=bool(d["holdout"]),
            q_rad=np.asarray(d["q_rad"], dtype=np.float64).reshape(-1),
            T_base_flange_reported=np.asarray(d["T_base_flange_reported"], dtype=np.float64).reshape(4, 4),
            T_base_flange_measured=np.asarray(d["T_base_flange_measured"], dtype=np.float64).reshape(4, 4),
            sigma_position_mm=[float(v) for v in d["sigma_position_mm"]],
            sigma_rotation_deg=[float(v) for v in d["sigma_rotation_deg"]],
            n_frames=int(d["n_frames"]),
            t_wall=str(d["t_wall"]),
        )


def _mean_T(Ts: list[np.ndarray]) -> np.ndarray:
    """Mean of nearby poses: positions averaged, rotations averaged in the tangent space of the first."""
    R0 = Ts[0][:3, :3]
    w = np.mean([rotvec_between(R0, T[:3, :3]) for T in Ts], axis=0)
    out = np.eye(4)
    out[:3, :3] = R0 @ R_from_rotvec(w)
    out[:3, 3] = np.mean([T[:3, 3] for T in Ts], axis=0)
    return out


def sim_cell(worker: Any) -> Any:
    """The simulated cell, if this process runs it and its controller (the only robot posecell moves)."""
    rt, robot = worker.cell, worker.robot
    if not rt.active or rt.standins or robot is None or not callable(getattr(robot, "move_to", None)):
        return None
    return rt.cell


def wait_at_rest(worker: Any, cancel: threading.Event | None = None, timeout_s: float = REST_TIMEOUT_S) -> None:
    """Until the controller reports the flange still (REST_TOL_MM / REST_TOL_DEG over REST_WINDOW_S)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cancel is not None and cancel.is_set():
            raise SessionError(Reason.not_solved, "cancelled")
        if at_rest(worker):
            return
        time.sleep(0.05)
    raise SessionError(Reason.robot_moving, f"the robot was not reported at rest within {timeout_s:g} s")


def at_rest(worker: Any) -> bool:
    """Whether the reported flange stood still over the last REST_WINDOW_S.

    The means of the window's first and last thirds are compared, not single samples: at a long
    lever the encoder noise alone (1e-5 rad, ~0.02 mm) makes two single samples differ by more
    than REST_TOL_MM now and then, while a move shifts the means at once.
    """
    now = time.monotonic_ns()
    recent = worker.robot.samples_between(now - int(REST_WINDOW_S * 1e9), now)
    if len(recent) < 6:
        return False
    third = len(recent) // 3
    first, last = recent[:third], recent[-third:]
    T0 = _mean_T([r.T_base_flange for r in first])
    T1 = _mean_T([r.T_base_flange for r in last])
    moved_deg = rotation_angle_deg(T0[:3, :3].T @ T1[:3, :3])
    return float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])) < REST_TOL_MM and moved_deg < REST_TOL_DEG


def move_joints(worker: Any, q_rad: np.ndarray, cancel: threading.Event | None = None) -> float:
    """Simulated cell only: a joint move (a ``movej``) to ``q_rad`` (6,); returns its duration s once the arm rests.

    A joint move, not a Cartesian one: the planned joints are the configuration the plan's
    observability was computed for, and the controller's IK from wherever the arm stands may
    choose another branch.
    """
    cell = sim_cell(worker)
    if cell is None:
        raise SessionError(
            Reason.unsupported,
            "this robot is moved by its own program: send it to the planned joints, then record a sample",
        )
    t0 = (time.monotonic_ns() - worker.cell.epoch_ns) * 1e-9 + 0.05
    q0 = cell.q_at(t0)
    q1 = np.asarray(q_rad, dtype=np.float64)
    duration_s = max(float(np.degrees(np.max(np.abs(q1 - q0)))) / JOINT_SPEED_DEG_S, 0.3)
    cell.command_trajectory(JointTrajectory(np.array([0.0, duration_s]), np.array([q0, q1]), mode="rest"), t0)
    time.sleep(duration_s + 0.1)
    wait_at_rest(worker, cancel)
    return duration_s


def _problem(m: Any) -> SessionError | None:
    """Why a measurement cannot be a sample's frame, or None."""
    f = m.flange
    if not m.ok or not isinstance(m.result, PoseResult) or m.t_exposure_host_ns is None:
        return SessionError(m.reason or Reason.no_frame, m.message or "the frame was not measured")
    if f is None or f.T_base_flange is None or f.T_base_flange_measured is None:
        return SessionError(
            Reason.robot_disconnected, (f.message if f is not None else "") or "no robot pose at the frame"
        )
    return None


def _next_measurement(worker: Any, camera: str) -> Any:
    """The next usable frame's measurement. A failed one (a camera stall, a gap in the robot's reports
    on a busy host, a frame the pipeline could not measure) is tried again up to RETRIES times, as an
    operator would press again, before it is the sample's failure."""
    for attempt in range(RETRIES + 1):
        try:
            m = worker.request_measurement(camera).result(timeout=FRAME_TIMEOUT_S).result
        except TimeoutError:
            raise SessionError(
                Reason.timeout, f"no frame was measured within {FRAME_TIMEOUT_S:g} s; see /health"
            ) from None
        problem = _problem(m)
        if problem is None:
            return m
        if attempt == RETRIES:
            raise problem
        time.sleep(RETRY_WAIT_S)
    raise AssertionError("unreachable")


def capture(worker: Any, camera: str, frames: int, pose: int | None = None, holdout: bool = False) -> RobotSample:
    """One sample at the robot's resting pose: ``frames`` measured frames averaged (module docstring)."""
    robot = worker.robot
    if robot is None or not robot.connected:
        raise SessionError(Reason.robot_disconnected, "the robot is not connected")
    handeye = worker.calibration.handeye
    if handeye is None:
        raise SessionError(Reason.not_calibrated, "the flange is measured through the hand-eye: calibrate it first")
    if not at_rest(worker):
        raise SessionError(
            Reason.robot_moving, f"the robot moved in the last {REST_WINDOW_S} s; record samples at rest"
        )
    measured, reported, joints, s_p, s_r = [], [], [], [], []
    for _ in range(frames):
        m = _next_measurement(worker, camera)
        f = m.flange
        t = int(m.t_exposure_host_ns)
        near = robot.samples_between(t - JOINT_WINDOW_NS, t + JOINT_WINDOW_NS)
        if not near:
            raise SessionError(Reason.robot_disconnected, "no joint sample of the robot near the exposure")
        q = np.array([s.q_rad for s in near], dtype=np.float64)
        if float(np.max(np.ptp(q, axis=0))) > JOINT_REST_RAD:
            raise SessionError(Reason.robot_moving, "the joints moved during the exposure; record samples at rest")
        joints.append(q.mean(axis=0))
        measured.append(f.T_base_flange_measured)
        reported.append(f.T_base_flange)
        sp, sr = measured_flange_sigma(m.result, handeye.T_flange_camera, handeye.T_base_field)
        s_p.append(sp)
        s_r.append(sr)
    k = np.sqrt(frames)  # σ of the mean of independent frames
    return RobotSample(
        pose=pose,
        holdout=holdout,
        q_rad=np.mean(joints, axis=0),
        T_base_flange_reported=_mean_T(reported),
        T_base_flange_measured=_mean_T(measured),
        sigma_position_mm=(np.mean(s_p, axis=0) / k).round(5).tolist(),
        sigma_rotation_deg=(np.mean(s_r, axis=0) / k).round(6).tolist(),
        n_frames=frames,
        t_wall=iso_wall(time.time_ns()),
    )
