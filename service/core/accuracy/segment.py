"""Segmenting a recorded stream into the stops and laps of an accuracy test (pure: arrays in, labels out).

With a real robot posecell does not command the motion: the integrator's program runs and the
service records every measured frame between ``start`` and ``stop``. Which frames belong to
which pose or direction is read from the robot's *reported* flange poses (the controller's
own, noise of its encoders only), never from the measured ones, so the labels do not depend
on what is being measured:

- at rest: a frame whose reported pose differs from its neighbours' (the frames before and
  after it, if no further than ``max_gap_s``) by less than ``tol_mm`` and ``tol_deg``; a stop
  is a run of at least ``min_frames`` frames at rest (:func:`rest_runs`);
- poses: the stops' mean reported positions grouped greedily, a stop joining the first group
  whose first stop lies within ``tol_mm`` of it, else opening a new one; groups are numbered
  in order of first visit (:func:`group_positions`);
- circle directions: the frames that move, each turning about the normal of the least-squares
  plane of the moving points: ``ccw`` when ``n · ((p - c) × v) > 0`` with ``c`` their centroid
  and ``v`` the central difference of the neighbours' positions; the normal is turned towards
  +z of the base (for a vertical plane towards +x, then +y), so "ccw" is counter-clockwise seen
  from above, as the circle analysis reads it (:func:`circle_directions`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.accuracy.inputs import bad_input, finite
from service.core.geometry.so3 import angle_between

Array = NDArray[np.float64]


def _positions(p_mm: ArrayLike, name: str = "p_mm") -> Array:
    return finite(p_mm, name, (None, 3))


def at_rest(
    t_s: ArrayLike,
    p_mm: ArrayLike,
    R: ArrayLike | None = None,
    tol_mm: float = 0.05,
    tol_deg: float = 0.01,
    max_gap_s: float = 0.5,
) -> NDArray[np.bool_]:
    """(N,) bool: frame i is at rest (see the module docstring).

    Parameters
    ----------
    t_s : (N,) float, s, increasing
    p_mm : (N, 3) float, mm — the reported flange positions
    R : (N, 3, 3) float, optional — the reported orientations
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    p = _positions(p_mm)
    if t.shape != (len(p),):
        raise bad_input(f"t_s must have shape ({len(p)},), not {t.shape}")
    n = len(p)
    if n < 2:
        return np.zeros(n, dtype=bool)
    still = np.linalg.norm(np.diff(p, axis=0), axis=1) < tol_mm  # (N-1,) between i and i+1
    if R is not None:
        Rs = np.asarray(R, dtype=np.float64).reshape(n, 3, 3)
        still &= np.degrees(angle_between(Rs[:-1], Rs[1:])) < tol_deg
    still &= np.diff(t) <= max_gap_s  # a gap in the stream says nothing about rest
    before = np.concatenate([[False], still])
    after = np.concatenate([still, [False]])
    # both neighbours still, or the stream's end beside one still neighbour
    out = before & after
    out[0] = bool(after[0])
    out[-1] = bool(before[-1])
    return out


def rest_runs(mask: ArrayLike, min_frames: int = 3) -> list[tuple[int, int]]:
    """The runs ``(i0, i1)`` (i1 exclusive) of True in ``mask`` (N,) at least ``min_frames`` long, in order."""
    m = np.asarray(mask, dtype=bool).reshape(-1)
    if min_frames < 1:
        raise bad_input(f"min_frames must be >= 1, not {min_frames}")
    edges = np.flatnonzero(np.diff(np.concatenate([[0], m.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= min_frames]


def group_positions(p_mm: ArrayLike, tol_mm: float = 5.0) -> list[int]:
    """Per stop (K, 3) mm its group 0, 1, … in order of first visit (see the module docstring)."""
    p = _positions(p_mm)
    if not tol_mm > 0:
        raise bad_input(f"tol_mm must be positive, not {tol_mm}")
    firsts: list[Array] = []
    out = []
    for q in p:
        k = next((i for i, f in enumerate(firsts) if np.linalg.norm(q - f) < tol_mm), None)
        if k is None:
            firsts.append(q)
            k = len(firsts) - 1
        out.append(k)
    return out


def circle_directions(p_mm: ArrayLike, moving: ArrayLike) -> list[str | None]:
    """Per frame ``"ccw"``, ``"cw"`` or None (at rest, or at either end of the stream).

    ``p_mm`` (N, 3) mm are the reported positions in time order, ``moving`` (N,) bool which
    frames move. Fewer than 3 moving frames: all None.
    """
    p = _positions(p_mm)
    mv = np.asarray(moving, dtype=bool).reshape(-1)
    if mv.shape != (len(p),):
        raise bad_input(f"moving must have shape ({len(p)},), not {mv.shape}")
    out: list[str | None] = [None] * len(p)
    idx = np.flatnonzero(mv)
    if len(idx) < 3:
        return out
    q = p[idx]
    c = q.mean(axis=0)
    normal = np.linalg.svd(q - c, full_matrices=False)[2][-1]
    for axis in (2, 0, 1):  # towards +z of the base, else +x, else +y
        if abs(normal[axis]) > 1e-6:
            normal = normal * np.sign(normal[axis])
            break
    for i in idx:
        if i == 0 or i == len(p) - 1:
            continue
        v = p[i + 1] - p[i - 1]
        turn = float(normal @ np.cross(p[i] - c, v))
        out[i] = "ccw" if turn > 0 else "cw" if turn < 0 else None
    return out
