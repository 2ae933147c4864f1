"""The paper's Table 1: a robot visits K positions forward (1 … K), then in reverse (K … 1), and
each position's two measured poses are compared (pure: arrays in, a frozen result out).

The seed paper (section 3) moved a KUKA KR 125/2 to six positions and back in reverse order and
listed per position the deviation between the two visits in x, y, z (mm) and ω, φ, κ (deg), each
with the σ of its determination. Here, for a position visited at i1 < i2 with measured poses
``T_1 = T_base_flange(i1)``, ``T_2 = T_base_flange(i2)`` (4x4, mm):

- position: ``(dx, dy, dz) = t_2 - t_1``, along the base axes (the later visit minus the earlier);
- orientation (``angles="relative"``, the default): ``(dω, dφ, dκ)`` are the ω, φ, κ of the
  rotation between the visits expressed in the base axes, ``R_d = R_2 R_1ᵀ``, with ω, φ, κ as in
  :func:`service.core.geometry.frames.opk_from_R` (``R = R_x(ω) R_y(φ) R_z(κ)``). For the small
  rotations of a repeatability test they are the rotations about the base x, y, z axes, the same
  axes as a measured pose's ``sigma_rotation_deg`` (DESIGN section 4), so value and σ match;
  ``angles="difference"`` differences the two poses' own ω, φ, κ instead (wrapped to
  (-180, 180]), which mixes the axes when φ is far from 0 and breaks down near φ = ±90 deg;
- σ: the two measurements are independent, so ``σ_d = sqrt(σ_1² + σ_2²)`` per component, from
  each pose's ``sigma_position_mm`` (3,) and ``sigma_rotation_deg`` (3,).

The summary gives per component the largest ``|d|`` and the RMS ``sqrt(mean(d²))`` over the
positions, and the same for the distance ``|t_2 - t_1|``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.accuracy.inputs import bad_input, finite
from service.core.accuracy.iso9283 import wrap_deg
from service.core.geometry.frames import check_T, opk_from_R

Array = NDArray[np.float64]

#: Per row, the deviation components in the order of the paper's columns.
COMPONENTS = ("dx_mm", "dy_mm", "dz_mm", "domega_deg", "dphi_deg", "dkappa_deg")
SIGMAS = ("sigma_x_mm", "sigma_y_mm", "sigma_z_mm", "sigma_omega_deg", "sigma_phi_deg", "sigma_kappa_deg")


def forward_reverse_labels(k: int) -> list[str]:
    """Visit labels of the paper's test with ``k`` positions: ``1 … k`` then ``k … 1``.

    >>> forward_reverse_labels(3)
    ['1', '2', '3', '3', '2', '1']
    """
    return [str(i) for i in (*range(1, k + 1), *range(k, 0, -1))]


@dataclass(frozen=True)
class Table1Row:
    """One position: the later visit minus the earlier, and the σ of that difference."""

    position: str
    visits: tuple[int, int]  # indices (0-based) of the two visits in visit order
    d_mm: tuple[float, float, float]  # dx, dy, dz along the base axes
    d_deg: tuple[float, float, float]  # dω, dφ, dκ
    sigma_mm: tuple[float, float, float]
    sigma_deg: tuple[float, float, float]
    dp_mm: float  # |t_2 - t_1|

    def to_dict(self) -> dict[str, Any]:
        values = (*self.d_mm, *self.d_deg)
        sigmas = (*self.sigma_mm, *self.sigma_deg)
        return {
            "position": self.position,
            "visits": list(self.visits),
            **dict(zip(COMPONENTS, values, strict=True)),
            **dict(zip(SIGMAS, sigmas, strict=True)),
            "dp_mm": self.dp_mm,
        }


@dataclass(frozen=True)
class Table1Result:
    """The rows in order of first visit, and the summary over them."""

    rows: tuple[Table1Row, ...]
    angles: str
    max_abs: dict[str, float]  # per component of COMPONENTS and "dp_mm": the largest |d|
    rms: dict[str, float]  # per component: sqrt(mean(d²)) over the positions

    def to_dict(self) -> dict[str, Any]:
        return {
            "rows": [r.to_dict() for r in self.rows],
            "summary": {"max_abs": dict(self.max_abs), "rms": dict(self.rms)},
            "n_positions": len(self.rows),
            "angles": self.angles,
        }


def _pairs(labels: Sequence[Any]) -> list[tuple[str, int, int]]:
    """(label, first visit, second visit) per position, in order of first visit."""
    seen: dict[str, list[int]] = {}
    for i, lab in enumerate(labels):
        seen.setdefault(str(lab), []).append(i)
    wrong = {lab: len(v) for lab, v in seen.items() if len(v) != 2}
    if wrong:
        raise bad_input(f"every position must be visited exactly twice; visits per position: {wrong}.")
    return [(lab, v[0], v[1]) for lab, v in seen.items()]


def table1(
    T_base_flange: ArrayLike,
    sigma_position_mm: ArrayLike,
    sigma_rotation_deg: ArrayLike,
    labels: Sequence[Any] | None = None,
    angles: Literal["relative", "difference"] = "relative",
) -> Table1Result:
    """The paper's Table 1 from the measured poses in visit order.

    Parameters
    ----------
    T_base_flange : (m, 4, 4) float, mm
        The measured poses, in the order they were visited.
    sigma_position_mm : (m, 3) float, mm
        Each pose's σ along the base axes.
    sigma_rotation_deg : (m, 3) float, deg
        Each pose's σ of small rotations about the base axes.
    labels : (m,) position labels, optional
        Which position each visit is; every label exactly twice. Default: the paper's order
        ``1 … K, K … 1`` with ``K = m / 2`` (:func:`forward_reverse_labels`).
    angles : "relative" or "difference"
        How dω, dφ, dκ are formed (see the module docstring).

    Raises ``SolveError(bad_input)`` for wrong shapes, non-finite or negative values, poses that are
    not rigid transforms, and labels that do not pair the visits.
    """
    T = np.asarray(T_base_flange, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 2:
        raise bad_input(f"the measured poses must have shape (m, 4, 4) with m >= 2, got {T.shape}.")
    m = T.shape[0]
    for i in range(m):
        try:
            check_T(T[i], name=f"the pose of visit {i + 1}")
        except ValueError as e:
            raise bad_input(f"{e}.") from None
    s_p = finite(sigma_position_mm, f"sigma_position_mm for {m} visits", (m, 3))
    s_r = finite(sigma_rotation_deg, f"sigma_rotation_deg for {m} visits", (m, 3))
    if np.any(s_p < 0) or np.any(s_r < 0):
        raise bad_input("a standard deviation is negative.")
    if angles not in ("relative", "difference"):
        raise bad_input(f'angles must be "relative" or "difference", got {angles!r}.')
    if labels is None:
        if m % 2:
            raise bad_input(f"forward then reverse visits come in an even number, got {m}; or give the labels.")
        labels = forward_reverse_labels(m // 2)
    elif len(labels) != m:
        raise bad_input(f"{m} visits need {m} position labels, got {len(labels)}.")
    rows = []
    for lab, i1, i2 in _pairs(labels):
        d_t = T[i2, :3, 3] - T[i1, :3, 3]
        R1, R2 = T[i1, :3, :3], T[i2, :3, :3]
        if angles == "relative":
            d_r = np.degrees(opk_from_R(R2 @ R1.T))
        else:
            d_r = wrap_deg(np.degrees(opk_from_R(R2) - opk_from_R(R1)))
        sig_t = np.hypot(s_p[i1], s_p[i2])
        sig_r = np.hypot(s_r[i1], s_r[i2])
        rows.append(
            Table1Row(
                position=lab,
                visits=(i1, i2),
                d_mm=(float(d_t[0]), float(d_t[1]), float(d_t[2])),
                d_deg=(float(d_r[0]), float(d_r[1]), float(d_r[2])),
                sigma_mm=(float(sig_t[0]), float(sig_t[1]), float(sig_t[2])),
                sigma_deg=(float(sig_r[0]), float(sig_r[1]), float(sig_r[2])),
                dp_mm=float(np.linalg.norm(d_t)),
            )
        )
    D = np.array([[*r.d_mm, *r.d_deg, r.dp_mm] for r in rows])  # (K, 7)
    keys = (*COMPONENTS, "dp_mm")
    max_abs = dict(zip(keys, np.abs(D).max(axis=0).tolist(), strict=True))
    rms = dict(zip(keys, np.sqrt((D**2).mean(axis=0)).tolist(), strict=True))
    return Table1Result(tuple(rows), angles, max_abs, rms)
