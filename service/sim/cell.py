"""The simulated cell: an arm carrying the reference camera over the reference target plate.

As in the paper, the camera is mounted on the moving robot and looks down at
targets fixed on the floor. The robot controller plans and reports with its
nominal kinematic model; the arm itself is a perturbed copy
(:func:`service.sim.robot.perturbed`), so the pose the camera sees and the one
the controller reports differ by ~1-2 mm, which is what posecell measures.

Frames (DESIGN section 1)::

    base    robot base, z up; the plate lies in front of the robot (+x) on the floor:
            kr15 standing on the floor, plate centre 1050 mm ahead; ur10e on a
            700 mm pedestal, plate centre 750 mm ahead
    flange  the arm's flange, tool axis z pointing down at the plate during the programs
    camera  on the flange, ~80 mm off the tool axis and 65 mm ahead of the flange
            face, its optical axis within 3.6 deg of the tool axis
    field   the reference plate (service.sim.scene), turned 93 deg about the
            vertical and tilted 0.2 deg, its targets facing up

Everything is deterministic given ``CellConfig.seed``; randomness at run time
(encoder noise, image noise, sampled poses) comes from the caller's generator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from service.core.geometry.frames import apply_T, inv_T, make_T
from service.core.results import Reason, SolveError
from service.core.robot.kinematics import KinematicModel, nominal_model
from service.core.targets.codes import RING_OUTER
from service.sim.render import RenderedFrame, RenderSettings, render_frame
from service.sim.robot import JointTrajectory, aim_flange, iso230_circle, perturbed, trajectory_through_poses
from service.sim.scene import reference_camera, reference_field, reference_pose

Array = NDArray[np.float64]

ROBOTS = ("kr15", "ur10e")
PROGRAMS = ("circle", "random", "hold")

# where each arm stands relative to the plate: (plate centre in base mm, home joints deg)
_LAYOUT: dict[str, tuple[tuple[float, float, float], tuple[float, ...]]] = {
    "kr15": ((1050.0, 0.0, 0.0), (0.0, -50.0, 80.0, 0.0, 60.0, 0.0)),
    "ur10e": ((750.0, 0.0, -700.0), (0.0, -80.0, -110.0, -80.0, 90.0, 0.0)),
}
_PLATE_YAW_DEG = 93.0
_PLATE_TILT_DEG = (0.2, 0.1)  # about base x and y: a plate on a floor that is not quite level
_T_FLANGE_CAMERA = make_T(Rotation.from_euler("ZYX", [90.0, 2.0, -3.0], degrees=True).as_matrix(), [78.0, -12.0, 65.0])
_MIN_DEXTERITY_MM = 50.0
_RENDER_DEFAULT = RenderSettings()


@dataclass(frozen=True)
class CellConfig:
    """What the simulated cell is; JSON-friendly (``to_dict`` / ``from_dict``).

    ``robot`` "kr15" | "ur10e"; ``error_scale`` multiplies the true arm's
    geometric errors (0: the arm is its nominal model); ``encoder_noise_rad``
    RMS per joint of the reported joint positions; ``program`` "circle" (the
    ISO 230-4 circle: ``circle_radius_mm``, ``circle_laps`` laps of
    ``circle_period_s``, flange ``camera_height_mm`` + ~65 mm above the plate,
    camera aimed at the plate centre), "random" (``n_random_poses`` views of
    the plate from :meth:`SimCell.reachable_view_poses`, resting
    ``dwell_s`` at each, looping back to the first) or "hold" (still over the
    plate centre); ``scene`` "reference" (the camera and plate of
    :mod:`service.sim.scene`).

    With the defaults (seed 0, kr15, error_scale 1) the true flange lies
    1.45 / 1.70 / 1.79 mm (min / median / max over 500 instants of the circle
    program) from the commanded one; the geometric errors act mostly as an
    offset over a 600 mm circle. Over seeds 0-9 the median runs from 0.5 to
    2.0 mm for the kr15 (1.7, 0.5, 2.0, 1.6, 1.3, 0.5, 0.9, 0.9, 1.0, 1.2)
    and from 1.0 to 1.8 mm for the ur10e (seed 0: 0.66 / 1.09 / 1.41 mm).
    Along the circle the camera sees the plate centre from 1043-1044 mm at
    view angles of 70-78.5 deg, with all 30 coded and 200 uncoded targets
    fully in view, for both arms.
    """

    seed: int = 0
    robot: str = "kr15"
    error_scale: float = 1.0
    encoder_noise_rad: float = 1e-5
    program: str = "circle"
    circle_radius_mm: float = 300.0
    circle_laps: int = 10
    circle_period_s: float = 10.0
    camera_height_mm: float = 1000.0
    n_random_poses: int = 12
    dwell_s: float = 1.0
    scene: str = "reference"

    def __post_init__(self) -> None:
        if self.robot not in ROBOTS:
            raise ValueError(f"robot must be one of {ROBOTS}, got {self.robot!r}")
        if self.program not in PROGRAMS:
            raise ValueError(f"program must be one of {PROGRAMS}, got {self.program!r}")
        if self.scene != "reference":
            raise ValueError(f"scene must be 'reference', got {self.scene!r}")
        if not (self.error_scale >= 0 and self.encoder_noise_rad >= 0 and self.dwell_s >= 0):
            raise ValueError("error_scale, encoder_noise_rad and dwell_s must be non-negative")
        if not (self.circle_radius_mm > 0 and self.circle_period_s > 0 and self.circle_laps >= 1):
            raise ValueError("circle_radius_mm and circle_period_s must be positive, circle_laps >= 1")
        if not (self.camera_height_mm > 0 and self.n_random_poses >= 1):
            raise ValueError("camera_height_mm must be positive and n_random_poses >= 1")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CellConfig:
        """From a dict of some or all fields; unknown keys raise ``ValueError`` naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown cell config keys {unknown}; known: {sorted(known)}")
        return cls(**d)


class SimCell:
    """The simulated cell of ``config``, playing ``trajectory`` (default: the config's program) in a loop.

    Attributes
    ----------
    camera : BrownFraser
    field : Field
    nominal, true : KinematicModel
        What the controller believes, and the arm as built.
    T_flange_camera : (4, 4) float
        The true hand-eye transform X.
    T_base_field : (4, 4) float
        The true robot-world transform Z.
    q_home_rad : (6,) float
        The home joints (IK seed of every program).
    trajectory : JointTrajectory
        Commanded joints; the arm follows them exactly.
    """

    def __init__(self, config: CellConfig | None = None, trajectory: JointTrajectory | None = None) -> None:
        self.config = config or CellConfig()
        c = self.config
        self.camera = reference_camera()
        self.field = reference_field()
        self.nominal: KinematicModel = nominal_model(c.robot)
        self.true: KinematicModel = perturbed(self.nominal, np.random.default_rng([c.seed, 0]), c.error_scale)
        plate_mm, home_deg = _LAYOUT[c.robot]
        R_plate = Rotation.from_euler("xyz", [*_PLATE_TILT_DEG, _PLATE_YAW_DEG], degrees=True).as_matrix()
        self.T_base_field = make_T(R_plate, plate_mm)
        self.T_flange_camera = _T_FLANGE_CAMERA.copy()
        self.q_home_rad = np.radians(home_deg)
        self.trajectory = trajectory if trajectory is not None else self._program()
        # commanded moves (start s, trajectory) played once after the program, each holding its end;
        # replaced as a whole tuple so that readers in other threads never see half an update
        self._moves: tuple[tuple[float, JointTrajectory], ...] = ()

    # -- programs ----------------------------------------------------------------

    def _circle_centre(self) -> Array:
        """The circle's centre frame: axes of the field, above the plate centre."""
        h = self.config.camera_height_mm + self.T_flange_camera[2, 3]
        return self.T_base_field @ make_T(np.eye(3), [0.0, 0.0, h])

    def _hold_pose(self) -> Array:
        centre = self._circle_centre()
        return aim_flange(centre[:3, 3], self.T_base_field[:3, 3], self.T_base_field[:3, 0], self.T_flange_camera)

    def _program(self) -> JointTrajectory:
        c = self.config
        if c.program == "circle":
            return iso230_circle(
                self.nominal,
                self._circle_centre(),
                self.nominal.ik(self._hold_pose(), self.q_home_rad),
                radius_mm=c.circle_radius_mm,
                laps=c.circle_laps,
                period_s=c.circle_period_s,
                look_at_base_mm=self.T_base_field[:3, 3],
                T_flange_camera=self.T_flange_camera,
            )
        if c.program == "hold":
            q = self.nominal.ik(self._hold_pose(), self.q_home_rad)
            return JointTrajectory(np.array([0.0, 1.0]), np.array([q, q]))
        poses = self.reachable_view_poses(c.n_random_poses, np.random.default_rng([c.seed, 1]))
        return trajectory_through_poses(self.nominal, poses, self.q_home_rad, dwell_s=c.dwell_s, closed=True)

    def with_program(self, trajectory: JointTrajectory) -> SimCell:
        """The same cell (robot, camera, plate) moving along ``trajectory`` instead."""
        return SimCell(self.config, trajectory)

    # -- state at a time ------------------------------------------------------------

    @property
    def commands(self) -> tuple[tuple[float, JointTrajectory], ...]:
        """The commanded motions (start s, trajectory), replaced whole by each new command: a reader
        that computed reports ahead knows by identity that they still hold."""
        return self._moves

    @property
    def duration_s(self) -> float:
        """One pass of the program (s); the cell loops it."""
        return self.trajectory.duration_s

    def q_at(self, t_s: ArrayLike) -> Array:
        """True (= commanded) joints (6,) or (M, 6) rad at ``t_s`` s: the looping program, then commanded moves."""
        t = np.asarray(t_s, dtype=np.float64)
        t0 = self.trajectory.t_s[0]
        q = self.trajectory.q_at(t0 + np.mod(t - t0, self.duration_s))
        moves = self._moves
        if not moves:
            return q
        t1 = np.atleast_1d(t)
        q1 = np.array(q, copy=True).reshape(-1, 6)
        k = np.searchsorted(np.array([m[0] for m in moves]), t1, side="right") - 1
        for i in np.unique(k[k >= 0]):
            start, traj = moves[int(i)]
            sel = k == i
            q1[sel] = traj.q_at(np.minimum(traj.t_s[0] + (t1[sel] - start), traj.t_s[-1]))
        return q1.reshape(q.shape)

    def command_move(self, T_base_flange: ArrayLike, t_start_s: float, speed_mm_s: float = 250.0) -> float:
        """Move the arm from wherever it is at ``t_start_s`` to a flange pose, and hold it there.

        Planned with the nominal model, like a controller's linear move; returns
        the move's duration (s). Raises ``SolveError`` when the pose is unreachable.
        """
        q0 = self.q_at(t_start_s)
        traj = trajectory_through_poses(
            self.nominal,
            [np.asarray(T_base_flange, dtype=np.float64)],
            q0,
            speed_mm_s=speed_mm_s,
            start_at_seed=True,
            fallback_seeds=[self.q_home_rad],  # where a cancelled program left the arm, the IK can stall
        )
        self._moves = (*[m for m in self._moves if m[0] < t_start_s], (float(t_start_s), traj))
        return float(traj.duration_s)

    def command_trajectory(self, trajectory: JointTrajectory, t_start_s: float) -> float:
        """Play ``trajectory`` (planned by the caller, e.g. the accuracy tests' programs) from ``t_start_s``
        and hold its end; returns its duration (s). Moves commanded for later are dropped, as by
        :meth:`command_move`. The caller makes it start where the arm is, or the arm jumps."""
        self._moves = (*[m for m in self._moves if m[0] < t_start_s], (float(t_start_s), trajectory))
        return float(trajectory.duration_s)

    def circle_centre(self) -> Array:
        """``T_base_centre`` (4, 4) of the circle program: the field's axes, above the plate centre."""
        return self._circle_centre()

    def hold_pose(self) -> Array:
        """``T_base_flange`` (4, 4) of the hold program: over the plate centre, the camera aimed at it."""
        return self._hold_pose()

    def T_base_flange_true(self, t_s: ArrayLike) -> Array:
        """Where the flange really is: ``true.fk(q)``, (4, 4) or (M, 4, 4)."""
        return self.true.fk(self.q_at(t_s))

    def T_base_flange_commanded(self, t_s: ArrayLike) -> Array:
        """Where the controller believes the flange is, without encoder noise: ``nominal.fk(q)``."""
        return self.nominal.fk(self.q_at(t_s))

    def robot_report(self, t_s: ArrayLike, rng: np.random.Generator | None) -> tuple[Array, Array]:
        """What the controller reports at ``t_s``: ``(T_base_flange (4, 4) mm, q_measured_rad (6,))``,
        or (M, 4, 4) and (M, 6) for M instants.

        ``q_measured = q + N(0, encoder_noise_rad)`` per joint (none when ``rng``
        is None), and the pose is the nominal model's ``fk(q_measured)``.
        """
        q = self.q_at(t_s)
        if rng is not None and self.config.encoder_noise_rad > 0:
            q = q + rng.normal(0.0, self.config.encoder_noise_rad, q.shape)
        return self.nominal.fk(q), q

    def T_field_camera(self, t_s: ArrayLike) -> Array:
        """The camera's true pose in the field, (4, 4) or (M, 4, 4): ``inv(Z) @ true.fk(q) @ X``."""
        return inv_T(self.T_base_field) @ self.T_base_flange_true(t_s) @ self.T_flange_camera

    def render(
        self,
        t_s: float,
        rng: np.random.Generator | None = None,
        settings: RenderSettings = _RENDER_DEFAULT,
        lit: bool = True,
    ) -> RenderedFrame:
        """The frame the camera takes at ``t_s`` (``rng`` None: noise-free).

        ``lit`` is the ring light's state during the exposure (the strobe);
        it overrides ``settings.lit``.
        """
        s = settings if settings.lit == lit else replace(settings, lit=lit)
        return render_frame(self.camera, self.field, self.T_field_camera(t_s), s, rng)

    # -- geometry helpers ---------------------------------------------------------

    def targets_in_view(self, T_field_camera: ArrayLike, margin_px: float = 1.0) -> tuple[int, int]:
        """Numbers of coded and uncoded targets fully in the image from ``T_field_camera``.

        A target counts when the whole pattern (disk, and code ring for a coded
        target: 16 points of its outer edge) projects inside the image by
        ``margin_px`` and the camera sees its face at an incidence under 80 deg;
        this matches :class:`RenderedFrame`'s ``fully_visible`` up to a pixel.
        """
        f = self.field
        T_camera_field = inv_T(np.asarray(T_field_camera, dtype=np.float64))
        radius = np.where(np.isfinite(f.diameters_mm), f.diameters_mm, np.where(f.is_coded, 10.0, 6.0)) / 2.0
        outer = np.where(f.is_coded, RING_OUTER * radius, radius)
        phi = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
        ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
        pts = f.xyz[:, None, :] + outer[:, None, None] * ring[None]  # (N, 16, 3), plate normal +z
        p_cam = apply_T(T_camera_field, pts.reshape(-1, 3)).reshape(len(f), 16, 3)
        centre_cam = apply_T(T_camera_field, f.xyz)
        normal_cam = T_camera_field[:3, 2]
        cos_inc = -(centre_cam @ normal_cam) / np.linalg.norm(centre_cam, axis=1)
        front = np.all(p_cam[..., 2] > 1.0, axis=1) & (cos_inc > np.cos(np.radians(80.0)))
        ok = np.zeros(len(f), dtype=bool)
        if np.any(front):
            uv = self.camera.pixel_from_camera(p_cam[front].reshape(-1, 3)).reshape(-1, 16, 2)
            ok[front] = np.all(self.camera.in_image(uv, margin_px=margin_px), axis=1)
        return int(np.sum(ok & f.is_coded)), int(np.sum(ok & ~f.is_coded))

    def reachable_view_poses(
        self,
        n: int,
        rng: np.random.Generator,
        distance_mm: tuple[float, float] = (700.0, 1300.0),
        max_tilt_deg: float = 40.0,
        roll_deg: tuple[float, float] = (-90.0, 90.0),
        min_coded: int = 6,
        min_targets: int = 30,
        max_tries: int = 2000,
    ) -> list[Array]:
        """``n`` random ``T_base_flange`` poses from which the camera sees the plate (for hand-eye calibration).

        The camera looks at a point within 100 mm of the plate centre from a
        distance uniform in ``distance_mm``, tilted from head-on by up to
        ``max_tilt_deg`` (uniform in angle) towards a uniform azimuth, and
        rolled about its axis uniformly in ``roll_deg``. A pose is kept when the
        nominal IK converges from the home joints on their branch, inside the
        joint limits (5 deg margin) and away from singularities, and when at
        least ``min_coded`` coded and ``min_targets`` targets in all are fully in view.

        Raises
        ------
        SolveError
            ``degenerate_geometry`` when fewer than ``n`` poses were found in ``max_tries``.
        """
        X_inv = inv_T(self.T_flange_camera)
        out: list[Array] = []
        for _ in range(max_tries):
            if len(out) == n:
                break
            T_fc = reference_pose(
                view_angle_deg=90.0 - rng.uniform(0.0, max_tilt_deg),
                distance_mm=rng.uniform(*distance_mm),
                roll_deg=rng.uniform(*roll_deg),
                azimuth_deg=rng.uniform(0.0, 360.0),
                look_at_mm=(*rng.uniform(-100.0, 100.0, 2), 0.0),
            )
            n_coded, n_uncoded = self.targets_in_view(T_fc)
            if n_coded < min_coded or n_coded + n_uncoded < min_targets:
                continue
            T = self.T_base_field @ T_fc @ X_inv
            try:
                q = self.nominal.ik(T, self.q_home_rad)
            except SolveError:
                continue
            if self.nominal.within_limits(q, np.radians(5.0)) and self.nominal.dexterity_mm(q) >= _MIN_DEXTERITY_MM:
                out.append(T)
        if len(out) < n:
            raise SolveError(
                Reason.degenerate_geometry,
                f"found only {len(out)} of {n} reachable views of the plate in {max_tries} tries",
            )
        return out
