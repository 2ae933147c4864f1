"""ISO 9283 pose characteristics from attained vs commanded poses (pure: arrays in, frozen results out).

A pose ``P1 … P5`` is commanded ``n`` times (the cycles, 30 in ISO 9283); each cycle gives an
attained position ``(x_j, y_j, z_j)`` mm and orientation. Orientations are read as KUKA A, B, C
(intrinsic Z-Y'-X'', degrees, DESIGN section 1; ISO's own a, b, c name rotations about x, y, z,
here ``_a`` is KUKA's A, ``_b`` its B, ``_c`` its C). Clause numbers are those of ISO 9283:1998.

- Pose accuracy (7.2.1): the barycentre ``x̄ = (1/n) Σ x_j`` (likewise ȳ, z̄);
  ``AP_x = x̄ - x_c`` (y, z alike), ``AP_p = sqrt(AP_x² + AP_y² + AP_z²)``;
  ``AP_a = (1/n) Σ wrap(a_j - a_c)`` (b, c alike).
- Pose repeatability (7.2.2): ``l_j = |p_j - p̄|``, ``RP_l = l̄ + 3 S_l`` with
  ``S_l = sqrt(Σ (l_j - l̄)² / (n - 1))``; ``RP_a = 3 S_a`` with ``S_a`` the (n - 1) standard
  deviation of ``wrap(a_j - a_c)`` (ISO writes ``± 3 S_a``; the number here is the half-width).
- Multi-directional pose accuracy variation (7.3), cycles labelled by approach direction h:
  ``vAP_p = max_{h,k} |p̄_h - p̄_k|``, ``vAP_a = max_{h,k} |ā_h - ā_k|`` (b, c alike).
- Distance accuracy and repeatability between two poses (7.4.2, 7.4.3), cycle j of one paired
  with cycle j of the other: ``D_j = |p_1j - p_2j|``, ``D_c = |p_c1 - p_c2|``,
  ``AD_p = D̄ - D_c``; ``AD_x = mean |x_1j - x_2j| - |x_c1 - x_c2|`` (y, z alike);
  ``RD_l = 3 sqrt(Σ (D_j - D̄)² / (n - 1))`` (ISO's ``± RD``), ``RD_x`` … from ``|x_1j - x_2j|``.

Angles: the Euler angles themselves are differenced, as ISO does, each difference wrapped to
(-180, 180] before the mean, so a pose commanded at A = 179.9 deg and reached at -179.9 deg
deviates by +0.2 deg, not -359.8. Both sides are first brought to scipy's canonical triple
(|B| <= 90 deg) through their rotation matrix, so a command given as B = 100 deg is read as the
same rotation written with B = 80 deg (and A, C turned by 180 deg). The weakness of Euler
differences: near the gimbal singularity (|B| -> 90 deg) A and C are no longer separately
defined (only A - C or A + C is), so a tiny rotation of the flange can move A and C by large,
opposite amounts, and ``AP_a``, ``AP_c``, ``RP_a``, ``RP_c`` blow up while the rotation itself
is small. :attr:`PoseCharacteristics.gimbal_margin_deg` (90 - |B_c|) says how close a pose is;
below a few degrees read the rotation angle of ``R_c^T R_j`` instead.

AP, RP are computed over all the cycles given; ISO's AP and RP are unidirectional, so pass the
cycles of one approach direction for a conforming figure. The test cube and P1-P5 of ISO 9283's
clause on test poses (the cube, its diagonal plane, the five positions) come from :func:`iso9283_cube`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.accuracy.inputs import bad_input, finite
from service.core.geometry.frames import R_from_kuka_abc_deg, kuka_abc_deg_from_R

Array = NDArray[np.float64]

#: The corners of the cube that span ISO 9283's measurement plane for the pose tests.
PLANE_CORNERS = ("C1", "C2", "C7", "C8")


def wrap_deg(x: ArrayLike) -> Array:
    """Angles (deg) wrapped into (-180, 180].

    >>> wrap_deg([180.0, -180.0, 190.0, -190.0, 359.5]).tolist()
    [180.0, 180.0, -170.0, 170.0, -0.5]
    """
    return np.asarray(180.0 - np.mod(180.0 - np.asarray(x, dtype=np.float64), 360.0))


def _rotations(x: ArrayLike, name: str, n: int | None) -> Array:
    """(n, 3, 3) rotations from KUKA A, B, C deg (n, 3) or matrices (n, 3, 3); (3, 3) when n is None."""
    a = finite(x, name)
    abc_shape, R_shape = ((3,), (3, 3)) if n is None else ((n, 3), (n, 3, 3))
    if a.shape == abc_shape:
        return R_from_kuka_abc_deg(a)
    if a.shape != R_shape:
        raise bad_input(f"{name} must be KUKA A, B, C deg of shape {abc_shape} or matrices {R_shape}, got {a.shape}.")
    RtR = np.swapaxes(a, -1, -2) @ a
    if not np.allclose(RtR, np.eye(3), atol=1e-6) or np.any(np.linalg.det(a) <= 0):
        raise bad_input(f"{name} holds a matrix that is not a proper rotation.")
    return a


@dataclass(frozen=True, eq=False)
class PoseSeries:
    """One commanded pose and its attained cycles (build with :func:`pose_series`).

    ``xyz_cmd_mm`` (3,) mm, ``R_cmd`` (3, 3), ``xyz_mm`` (n, 3) mm, ``R`` (n, 3, 3), ``cycles`` (n,)
    the cycle numbers, ``approach`` (n,) the direction of approach of each cycle or None.
    """

    name: str
    xyz_cmd_mm: Array
    R_cmd: Array
    xyz_mm: Array
    R: Array
    cycles: tuple[int, ...]
    approach: tuple[str, ...] | None = None

    @property
    def n(self) -> int:
        return len(self.cycles)


def pose_series(
    name: str,
    xyz_cmd_mm: ArrayLike,
    orientation_cmd: ArrayLike,
    xyz_mm: ArrayLike,
    orientation: ArrayLike,
    approach: Sequence[str] | None = None,
    cycles: Sequence[int] | None = None,
) -> PoseSeries:
    """A checked :class:`PoseSeries`; ``SolveError(bad_input)`` for wrong shapes, NaN, n < 2.

    ``orientation_cmd`` is KUKA A, B, C deg (3,) or a matrix (3, 3); ``orientation`` is (n, 3) deg
    or (n, 3, 3); ``cycles`` defaults to 1 … n.
    """
    cmd = finite(xyz_cmd_mm, f"{name}: the commanded position")
    if cmd.shape != (3,):
        raise bad_input(f"{name}: the commanded position must have shape (3,), got {cmd.shape}.")
    p = finite(xyz_mm, f"{name}: the attained positions")
    if p.ndim != 2 or p.shape[1] != 3:
        raise bad_input(f"{name}: the attained positions must have shape (n, 3), got {p.shape}.")
    n = p.shape[0]
    if n < 2:
        raise bad_input(f"{name}: pose characteristics need at least 2 cycles, got {n}.")
    R_cmd = _rotations(orientation_cmd, f"{name}: the commanded orientation", None)
    R = _rotations(orientation, f"{name}: the attained orientations ({n} cycles)", n)
    cyc = tuple(range(1, n + 1)) if cycles is None else tuple(int(c) for c in cycles)
    if len(cyc) != n or len(set(cyc)) != n:
        raise bad_input(f"{name}: {n} cycles need {n} distinct cycle numbers, got {len(set(cyc))} of {len(cyc)}.")
    app = None if approach is None else tuple(str(a) for a in approach)
    if app is not None and len(app) != n:
        raise bad_input(f"{name}: {n} cycles need {n} approach labels, got {len(app)}.")
    return PoseSeries(name, cmd, R_cmd, p, R, cyc, app)


def series_from_table(
    pose: Sequence[str],
    cycle: Sequence[int],
    xyzabc_cmd: ArrayLike,
    xyzabc: ArrayLike,
    approach: Sequence[str] | None = None,
) -> dict[str, PoseSeries]:
    """Per pose name (in order of first appearance) its series, from rows ``pose, cycle, x_cmd_mm …
    c_cmd_deg, x_mm … c_deg`` (DESIGN section 5's CSV): ``xyzabc_cmd``, ``xyzabc`` (N, 6) mm and
    KUKA A, B, C deg. The cycles of a pose are sorted; every row of a pose must command the same pose.
    """
    cmd = finite(xyzabc_cmd, "the commanded poses")
    att = finite(xyzabc, "the attained poses")
    N = len(pose)
    for a, what in ((cmd, "commanded"), (att, "attained")):
        if a.shape != (N, 6):
            raise bad_input(f"the {what} poses must have shape ({N}, 6) for {N} rows, got {a.shape}.")
    if len(cycle) != N or (approach is not None and len(approach) != N):
        raise bad_input(f"every one of the {N} rows needs a cycle number (and an approach label if any are given).")
    names = list(dict.fromkeys(str(p) for p in pose))
    out = {}
    for name in names:
        rows = [i for i in range(N) if str(pose[i]) == name]
        rows.sort(key=lambda i: int(cycle[i]))
        c = cmd[rows]
        R_c = R_from_kuka_abc_deg(c[:, 3:])
        if not (np.allclose(c[:, :3], c[0, :3], atol=1e-6) and np.allclose(R_c, R_c[0], atol=1e-6)):
            raise bad_input(f"{name}: its rows command different poses; one pose name, one command.")
        out[name] = pose_series(
            name,
            c[0, :3],
            R_c[0],
            att[rows, :3],
            att[rows, 3:],
            None if approach is None else [str(approach[i]) for i in rows],
            [int(cycle[i]) for i in rows],
        )
    return out


def _angle_deviations_deg(s: PoseSeries) -> Array:
    """(n, 3) KUKA A, B, C of the attained minus the commanded, each wrapped to (-180, 180]."""
    return wrap_deg(kuka_abc_deg_from_R(s.R) - kuka_abc_deg_from_R(s.R_cmd))


_POSE_KEYS: tuple[str, ...] = ("AP_p_mm", "AP_x_mm", "AP_y_mm", "AP_z_mm", "AP_a_deg", "AP_b_deg", "AP_c_deg")
_POSE_KEYS += ("RP_l_mm", "RP_a_deg", "RP_b_deg", "RP_c_deg")
_VAP_KEYS: tuple[str, ...] = ("vAP_p_mm", "vAP_a_deg", "vAP_b_deg", "vAP_c_deg")


@dataclass(frozen=True)
class PoseCharacteristics:
    """ISO 9283 figures of one pose (mm, deg; RP and RD are half-widths: ISO's ``±``)."""

    name: str
    n: int
    AP_p_mm: float
    AP_x_mm: float
    AP_y_mm: float
    AP_z_mm: float
    AP_a_deg: float
    AP_b_deg: float
    AP_c_deg: float
    RP_l_mm: float
    RP_a_deg: float
    RP_b_deg: float
    RP_c_deg: float
    b_cmd_deg: float  # the commanded KUKA B: its distance from ±90 is the gimbal margin
    vAP_p_mm: float | None = None  # with two or more approach directions
    vAP_a_deg: float | None = None
    vAP_b_deg: float | None = None
    vAP_c_deg: float | None = None

    @property
    def gimbal_margin_deg(self) -> float:
        """90 - |B_c|: how far the command is from the A/C singularity of the Euler differences."""
        return 90.0 - abs(self.b_cmd_deg)

    def to_dict(self) -> dict[str, Any]:
        keys = _POSE_KEYS + (_VAP_KEYS if self.vAP_p_mm is not None else ())
        return {**{k: getattr(self, k) for k in keys}, "n": self.n}


def pose_characteristics(s: PoseSeries) -> PoseCharacteristics:
    """AP, RP (and vAP when the cycles carry two or more approach directions) of one pose."""
    bary = s.xyz_mm.mean(axis=0)
    AP = bary - s.xyz_cmd_mm
    l_j = np.linalg.norm(s.xyz_mm - bary, axis=1)
    d = _angle_deviations_deg(s)
    AP_abc = d.mean(axis=0)
    RP_abc = 3.0 * d.std(axis=0, ddof=1)
    v = None
    if s.approach is not None and len(set(s.approach)) >= 2:
        labels = list(dict.fromkeys(s.approach))
        idx = [np.array([a == h for a in s.approach]) for h in labels]
        p_h = np.array([s.xyz_mm[k].mean(axis=0) for k in idx])
        a_h = np.array([d[k].mean(axis=0) for k in idx])
        v = [max(float(np.linalg.norm(p_h[h] - p_h[k])) for h, k in combinations(range(len(labels)), 2))]
        v += (a_h.max(axis=0) - a_h.min(axis=0)).tolist()
    figures = np.r_[np.linalg.norm(AP), AP, AP_abc, l_j.mean() + 3.0 * l_j.std(ddof=1), RP_abc].tolist()
    vAP = dict(zip(_VAP_KEYS, v, strict=True)) if v is not None else {}
    b_cmd = float(kuka_abc_deg_from_R(s.R_cmd)[1])
    return PoseCharacteristics(
        name=s.name, n=s.n, b_cmd_deg=b_cmd, **dict(zip(_POSE_KEYS, figures, strict=True)), **vAP
    )


_DIST_KEYS = ("D_cmd_mm", "AD_p_mm", "AD_x_mm", "AD_y_mm", "AD_z_mm", "RD_l_mm", "RD_x_mm", "RD_y_mm", "RD_z_mm")


@dataclass(frozen=True)
class DistanceCharacteristics:
    """ISO 9283 distance accuracy and repeatability between two poses (7.4), mm."""

    pose_a: str
    pose_b: str
    n: int
    D_cmd_mm: float
    AD_p_mm: float
    AD_x_mm: float
    AD_y_mm: float
    AD_z_mm: float
    RD_l_mm: float
    RD_x_mm: float
    RD_y_mm: float
    RD_z_mm: float

    def to_dict(self) -> dict[str, Any]:
        return {**{k: getattr(self, k) for k in _DIST_KEYS}, "n": self.n}


def distance_characteristics(a: PoseSeries, b: PoseSeries) -> DistanceCharacteristics:
    """AD and RD between poses ``a`` and ``b``, cycle j of ``a`` paired with cycle j of ``b``."""
    if a.cycles != b.cycles:
        raise bad_input(f"distance {a.name}-{b.name} pairs the cycles, and the two poses have different cycles.")
    s_c = np.abs(a.xyz_cmd_mm - b.xyz_cmd_mm)  # (3,)
    D_xyz = np.abs(a.xyz_mm - b.xyz_mm)  # (n, 3)
    D = np.linalg.norm(a.xyz_mm - b.xyz_mm, axis=1)
    D_c = float(np.linalg.norm(s_c))
    AD_xyz = D_xyz.mean(axis=0) - s_c
    RD_xyz = 3.0 * D_xyz.std(axis=0, ddof=1)
    figures = np.r_[D_c, D.mean() - D_c, AD_xyz, 3.0 * D.std(ddof=1), RD_xyz].tolist()
    return DistanceCharacteristics(pose_a=a.name, pose_b=b.name, n=a.n, **dict(zip(_DIST_KEYS, figures, strict=True)))


@dataclass(frozen=True)
class Iso9283Result:
    """The figures of every pose, and of the distances asked for."""

    poses: Mapping[str, PoseCharacteristics]
    distances: tuple[DistanceCharacteristics, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """``{"poses": {"P1": {"AP_p_mm": …, …, "n": 30}, …}}`` and, if any, ``"distances": {"P2-P4": …}``."""
        out: dict[str, Any] = {"poses": {name: c.to_dict() for name, c in self.poses.items()}}
        if self.distances:
            out["distances"] = {f"{d.pose_a}-{d.pose_b}": d.to_dict() for d in self.distances}
        return out


def iso9283_result(
    series: Mapping[str, PoseSeries] | Iterable[PoseSeries], distances: Iterable[tuple[str, str]] = ()
) -> Iso9283Result:
    """Pose characteristics of every series (named by ``PoseSeries.name``) and AD, RD of each pair
    in ``distances`` (pose names, e.g. ``[("P2", "P4")]``)."""
    items = list(series.values()) if isinstance(series, Mapping) else list(series)
    by_name = {s.name: s for s in items}
    if len(by_name) != len(items):
        raise bad_input("two series carry the same pose name.")
    dist = []
    for a, b in distances:
        if a not in by_name or b not in by_name:
            raise bad_input(f"distance {a}-{b} names a pose that was not measured; poses: {sorted(by_name)}.")
        dist.append(distance_characteristics(by_name[a], by_name[b]))
    return Iso9283Result({s.name: pose_characteristics(s) for s in items}, tuple(dist))


def iso9283_dict(
    series: Mapping[str, PoseSeries] | Iterable[PoseSeries], distances: Iterable[tuple[str, str]] = ()
) -> dict[str, Any]:
    """``iso9283_result(series, distances).to_dict()``: ``{"poses": {"P1": {...}, ...}}``."""
    return iso9283_result(series, distances).to_dict()


def attained_offsets(series: Mapping[str, PoseSeries] | Iterable[PoseSeries]) -> dict[str, dict[str, Any]]:
    """Per pose (by name) its command ``xyz_cmd_mm`` (3,) and each cycle's attained position minus
    it, ``offset_um`` (n, 3) µm rounded to 1 nm, with the ``cycles``, as JSON: what the report's
    figure plots, kept beside the figures so a stored report can be drawn again from its JSON."""
    items = list(series.values()) if isinstance(series, Mapping) else list(series)
    return {
        s.name: {
            "xyz_cmd_mm": [round(float(v), 6) for v in s.xyz_cmd_mm],
            "cycles": list(s.cycles),
            "offset_um": (np.round(1e3 * (s.xyz_mm - s.xyz_cmd_mm), 3) + 0.0).tolist(),
        }
        for s in items
    }


@dataclass(frozen=True, eq=False)
class Iso9283Cube:
    """ISO 9283's test cube: ``corners`` C1 … C8 and ``poses`` P1 … P5, each (3,) mm in base.

    In the cube's own axes (origin at its centre, half edge h) C1 = (-h, -h, -h), C2 = (h, -h, -h),
    C3 = (h, h, -h), C4 = (-h, h, -h) and C5 … C8 the same four at z = +h: the plane C1-C2-C7-C8
    holds the bottom edge C1C2 and the top edge C7C8 across from it, a rectangle a by a√2 whose
    diagonals C1C7 and C2C8 are the cube's space diagonals (length a√3) and cross at its centre.
    """

    centre_mm: Array
    edge_mm: float
    R_base_cube: Array
    corner_fraction: float
    corners: Mapping[str, Array]
    poses: Mapping[str, Array]

    @property
    def diagonal_mm(self) -> float:
        """Length of the measurement plane's diagonals (a√3)."""
        return float(self.edge_mm * np.sqrt(3.0))

    def commanded_positions(self) -> Array:
        """(5, 3) mm: P1 … P5."""
        return np.array([self.poses[f"P{k}"] for k in range(1, 6)])


#: Which corner each of P2 … P5 lies near, and the corner across its diagonal.
_NEAR = {"P2": ("C1", "C7"), "P3": ("C2", "C8"), "P4": ("C7", "C1"), "P5": ("C8", "C2")}


def iso9283_cube(
    centre_mm: ArrayLike, edge_mm: float, R_base_cube: ArrayLike | None = None, corner_fraction: float = 0.1
) -> Iso9283Cube:
    """The test cube and the five test positions in its diagonal plane C1-C2-C7-C8.

    P1 is the cube's centre (where the plane's diagonals cross); P2, P3, P4, P5 lie on the
    diagonals at ``corner_fraction`` of the diagonal's length from C1, C2, C7, C8
    (``P2 = C1 + f (C7 - C1)``; ISO: 10 % ± 2 %, so ``f`` must be in [0.08, 0.12]). P2 and P4
    share the diagonal C1C7, P3 and P5 the diagonal C2C8. ``R_base_cube`` (3, 3, default the
    identity, ISO's cube with edges along the base axes) holds the cube's axes as columns.
    """
    c = finite(centre_mm, "the cube's centre")
    if c.shape != (3,):
        raise bad_input(f"the cube's centre must have shape (3,), got {c.shape}.")
    a = float(edge_mm)
    if not np.isfinite(a) or a <= 0:
        raise bad_input(f"the cube's edge must be a positive length in mm, got {edge_mm}.")
    f = float(corner_fraction)
    if not 0.08 <= f <= 0.12:
        raise bad_input(f"ISO 9283 puts P2-P5 at 10 % ± 2 % of the diagonal from the corners, got {f:.1%}.")
    R = np.eye(3) if R_base_cube is None else _rotations(R_base_cube, "the cube's orientation", None)
    h = a / 2.0
    local = {"C1": (-h, -h, -h), "C2": (h, -h, -h), "C3": (h, h, -h), "C4": (-h, h, -h)}
    local |= {f"C{k + 4}": (x, y, h) for k, (x, y, _) in enumerate(list(local.values()), start=1)}
    corners = {k: c + R @ np.array(v) for k, v in local.items()}
    poses = {"P1": c.copy()} | {p: corners[n] + f * (corners[o] - corners[n]) for p, (n, o) in _NEAR.items()}
    return Iso9283Cube(c, a, R, f, corners, poses)
