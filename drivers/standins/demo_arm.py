"""A built-in state source for the RTDE stand-in: a UR5e-like arm moving smoothly.

:class:`DemoArm` is a ``state_source`` for :class:`drivers.standins.rtde_server.RtdeServer`: a
smooth joint motion around a working pose, through the nominal UR5e kinematics
(:func:`T_base_flange_from_q`), reported as the controller would, TCP offset included. It is what
``python -m drivers.standins.rtde_server`` serves unless given ``--state``, and what the driver
tests check the UR driver against; a module of its own because it is kinematics, not networking.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from drivers.standins.rtde_protocol import RobotState
from service.core.geometry.frames import inv_T, ur_pose_from_T

# UR5e nominal standard DH: a, d in mm, alpha in rad (Universal Robots' published values).
UR5E_DH_A_MM = np.array([0.0, -425.0, -392.2, 0.0, 0.0, 0.0])
UR5E_DH_D_MM = np.array([162.5, 0.0, 0.0, 133.3, 99.7, 99.6])
UR5E_DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])


def T_base_flange_from_q(q_rad: Sequence[float]) -> np.ndarray:
    """Forward kinematics of the nominal UR5e (standard DH), flange in base, (4, 4) mm."""
    T = np.eye(4)
    for theta, a, d, alpha in zip(q_rad, UR5E_DH_A_MM, UR5E_DH_D_MM, UR5E_DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )
    return T


class DemoArm:
    """A smooth joint motion around a UR5e working pose, reported as the controller would.

    ``T_flange_tcp`` (4, 4) mm is the TCP offset "configured on the controller":
    ``actual_TCP_pose`` is the flange pose times it, so a driver must remove it
    to get the flange back.
    """

    Q_HOME_RAD = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    AMPLITUDE_RAD = np.array([0.5, 0.25, 0.3, 0.4, 0.4, 0.8])
    FREQUENCY_HZ = np.array([0.11, 0.07, 0.13, 0.17, 0.19, 0.23])

    def __init__(self, T_flange_tcp: np.ndarray | None = None) -> None:
        self.T_flange_tcp = np.eye(4) if T_flange_tcp is None else np.asarray(T_flange_tcp, dtype=np.float64)

    def q_rad(self, t_s: float) -> np.ndarray:
        return self.Q_HOME_RAD + self.AMPLITUDE_RAD * np.sin(2 * np.pi * self.FREQUENCY_HZ * t_s)

    def qd_rad_s(self, t_s: float) -> np.ndarray:
        w = 2 * np.pi * self.FREQUENCY_HZ
        return self.AMPLITUDE_RAD * w * np.cos(w * t_s)

    def T_base_flange(self, t_s: float) -> np.ndarray:
        return T_base_flange_from_q(self.q_rad(t_s))

    def T_base_tcp(self, t_s: float) -> np.ndarray:
        return self.T_base_flange(t_s) @ self.T_flange_tcp

    def __call__(self, t_s: float) -> RobotState:
        q = self.q_rad(t_s)
        T_base_tcp = T_base_flange_from_q(q) @ self.T_flange_tcp
        pose = ur_pose_from_T(T_base_tcp)
        h = 1e-4  # central difference for the TCP twist; exact enough for a stand-in
        T0, T1 = self.T_base_tcp(t_s - h), self.T_base_tcp(t_s + h)
        v_m_s = (T1[:3, 3] - T0[:3, 3]) / (2 * h) / 1000.0
        w_rad_s = ur_pose_from_T(T1 @ inv_T(T0))[3:] / (2 * h)  # rotation in the base frame
        qd = self.qd_rad_s(t_s)
        return RobotState(
            actual_TCP_pose=tuple(pose),
            target_TCP_pose=tuple(pose),
            actual_q=tuple(q),
            target_q=tuple(q),
            actual_qd=tuple(qd),
            target_qd=tuple(qd),
            actual_TCP_speed=(*v_m_s, *w_rad_s),
            timestamp=t_s,
        )
