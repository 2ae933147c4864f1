"""A bundle network's inputs and datum: points and observations from a target field and identified images.

Both adjustments of images of a target field build their network here, so they read their
inputs, tie it to the field frame and report their precision in one way: the camera's
self-calibration (:mod:`service.core.calib.bundle`) and the rig's
(:mod:`service.core.calib.rig`, whose fixed field is a datum of control points, every field
target fixed).

- :func:`collect`: the network's points (the field's targets that an image sees, in the
  field's order, then the new ones in the order first seen) and its observations, with
  the checks on every image (a target named twice, non-finite pixels);
- :func:`datum_rows`: the datum (:class:`Datum`: control points, or inner constraints on
  the nominal field) and the scale bars as rows of
  :class:`~service.core.calib.bundle_solve.NetworkInput`, each refused with a
  ``SolveError(bad_input)`` sentence naming what is wrong (a scale bar's target no
  image saw, a bar without a positive distance and sigma, too few control points);
- :func:`interior_sigmas`, :func:`point_sigmas`, :func:`network_field`: the adjusted
  network's cameras, targets and their standard deviations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.calib.bundle_solve import NetworkSolution
from service.core.geometry.camera_model import PARAMETER_NAMES
from service.core.results import Reason, SolveError
from service.core.targets.field import Field

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class ImagePoints:
    """Identified targets in one image: ``ids`` (n,), measured pixels ``uv`` (n, 2) px, and an
    optional start pose ``T_field_camera`` (4, 4) (e.g. the pipeline's resection)."""

    name: str
    ids: tuple[str, ...]
    uv: Array
    T_field_camera: Array | None = None


@dataclass(frozen=True)
class ScaleBar:
    """A known distance between two targets (a scale bar), mm, with its standard deviation (> 0)."""

    id_a: str
    id_b: str
    distance_mm: float
    sigma_mm: float = 0.01


@dataclass(frozen=True)
class Datum:
    """How the adjustment is tied to the field frame.

    ``control``: ids of control points whose field coordinates define the frame
    (at least 3, not collinear); ``control_sigma_mm`` 0 fixes them, > 0 weights them.
    With no control points: inner constraints on the nominal coordinates of every
    observed field target (a free network), with the scale of the nominal field
    unless ``scale_bars`` give it.
    """

    control: tuple[str, ...] = ()
    control_sigma_mm: float = 0.0
    scale_bars: tuple[ScaleBar, ...] = ()

    def describe(self) -> dict[str, Any]:
        if self.control:
            d: dict[str, Any] = {
                "kind": "control points",
                "control": list(self.control),
                "control_sigma_mm": self.control_sigma_mm,
            }
        else:
            d = {
                "kind": "inner constraints on the nominal field",
                "scale": "scale bars" if self.scale_bars else "nominal field",
            }
        if self.scale_bars:
            d["scale_bars"] = [
                {"ids": [b.id_a, b.id_b], "distance_mm": b.distance_mm, "sigma_mm": b.sigma_mm} for b in self.scale_bars
            ]
        return d


def check_free(free: Sequence[str]) -> tuple[str, ...]:
    """The free interior parameters in :data:`PARAMETER_NAMES` order; ``ValueError`` for an unknown name."""
    unknown = [n for n in free if n not in PARAMETER_NAMES]
    if unknown:
        raise ValueError(f"unknown camera parameters {unknown}; choose from {list(PARAMETER_NAMES)}")
    return tuple(n for n in PARAMETER_NAMES if n in set(free))


# -- points and observations ---------------------------------------------------------------


@dataclass
class Network:
    """The network's points and observations.

    ``ids`` (N,) its points: the observed field targets, then the new ones; ``nominal``
    (N, 3) mm their field coordinates (NaN for new points), ``codes`` and ``diameters``
    the field's (-1 and NaN for new points); ``image``, ``point`` (M,) and ``uv`` (M, 2) px
    every observation.
    """

    ids: list[str]
    nominal: Array
    codes: list[int]
    diameters: list[float]
    image: IntArray
    point: IntArray
    uv: Array

    @property
    def index(self) -> dict[str, int]:
        """Point index of each id."""
        return {t: i for i, t in enumerate(self.ids)}


def collect(field: Field, images: Sequence[ImagePoints]) -> Network:
    """The network of ``images`` of ``field`` (see :class:`Network`).

    Raises ``SolveError(bad_input)`` for an image that names a target twice or has non-finite
    pixel coordinates, ``ValueError`` for one whose ids and pixels differ in number.
    """
    order: dict[str, int] = {}
    observed = {t for im in images for t in im.ids}
    ids = [t for t in field.ids if t in observed]
    for im in images:
        for t in im.ids:
            if t not in field.index and t not in order:
                order[t] = len(order)
    ids += sorted(order, key=order.__getitem__)
    index = {t: i for i, t in enumerate(ids)}
    nominal = np.full((len(ids), 3), np.nan)
    codes, diameters = [], []
    for i, t in enumerate(ids):
        if t in field.index:
            row = field.index[t]
            nominal[i] = field.xyz[row]
            codes.append(int(field.codes[row]))
            diameters.append(float(field.diameters_mm[row]))
        else:
            codes.append(-1)
            diameters.append(float("nan"))
    image, point, uv = [], [], []
    for j, im in enumerate(images):
        q = np.asarray(im.uv, dtype=np.float64).reshape(-1, 2)
        if len(q) != len(im.ids):
            raise ValueError(f"image {im.name!r} has {len(im.ids)} ids but {len(q)} points")
        if len(set(im.ids)) != len(im.ids):
            raise SolveError(Reason.bad_input, f"Image {im.name!r} names a target twice.")
        if not np.all(np.isfinite(q)):
            raise SolveError(Reason.bad_input, f"Image {im.name!r} has non-finite pixel coordinates.")
        image += [j] * len(q)
        point += [index[t] for t in im.ids]
        uv.append(q)
    return Network(
        ids,
        nominal,
        codes,
        diameters,
        np.array(image, dtype=np.int64),
        np.array(point, dtype=np.int64),
        np.concatenate(uv) if uv else np.zeros((0, 2)),
    )


def left_out_warnings(net: Network, points: Array) -> list[str]:
    """A sentence for every point without start coordinates (NaN rows of ``points`` (N, 3))."""
    return [
        f"target {net.ids[i]!r} is seen in fewer than two oriented images and is left out"
        for i in np.flatnonzero(~np.all(np.isfinite(points), axis=1)).tolist()
    ]


# -- the datum ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class DatumRows:
    """A datum as the rows of :class:`~service.core.calib.bundle_solve.NetworkInput`.

    ``points`` (N, 3) mm: the start values, fixed control points at their field coordinates;
    ``point_free`` (N,): the unknown points; ``control``: point index -> (xyz (3,) mm, sigma mm);
    ``inner``: (point indices, nominal xyz (n, 3) mm, n_gauge 6 or 7) or None; ``bars``:
    (a, b, distance mm, sigma mm).
    """

    points: Array
    point_free: NDArray[np.bool_]
    control: dict[int, tuple[Array, float]]
    inner: tuple[IntArray, Array, int] | None
    bars: tuple[tuple[int, int, float, float], ...]


def datum_rows(datum: Datum, field: Field, net: Network, points: Array) -> DatumRows:
    """The rows of ``datum`` for the network ``net`` with start coordinates ``points`` (N, 3) mm
    (NaN for points left out).

    Raises
    ------
    SolveError
        ``bad_input``, in a sentence naming the culprit: control points not in the field, fewer
        than 3 observed non-collinear control points (or field targets, for inner constraints),
        a scale bar's target that no image saw or that has no coordinates, a scale bar without
        a positive distance and sigma.
    """
    p0 = np.array(points, dtype=np.float64)
    known = np.all(np.isfinite(p0), axis=1)
    index = net.index
    point_free = np.ones(len(net.ids), bool)
    control: dict[int, tuple[Array, float]] = {}
    inner = None
    if datum.control:
        missing = [t for t in datum.control if t not in field.index]
        if missing:
            raise SolveError(Reason.bad_input, f"Control points {missing[:5]} are not in the field.")
        rows = np.array([index[t] for t in datum.control if t in index and known[index[t]]], dtype=np.int64)
        if len(rows) < 3 or np.linalg.matrix_rank(p0[rows] - p0[rows].mean(0), tol=1e-6) < 2:
            raise SolveError(Reason.bad_input, "The datum needs at least 3 observed, non-collinear control points.")
        for i in rows:
            control[int(i)] = (net.nominal[i], float(datum.control_sigma_mm))
            if datum.control_sigma_mm <= 0:
                point_free[i] = False
                p0[i] = net.nominal[i]
    else:
        rows = np.flatnonzero(np.isfinite(net.nominal).all(axis=1) & known)
        if len(rows) < 3 or np.linalg.matrix_rank(net.nominal[rows] - net.nominal[rows].mean(0), tol=1e-6) < 2:
            raise SolveError(Reason.bad_input, "Inner constraints need at least 3 non-collinear field targets.")
        inner = (rows, net.nominal[rows], 6 if datum.scale_bars else 7)
    bars = []
    for b in datum.scale_bars:
        name = f"Scale bar {b.id_a}-{b.id_b}"
        for t in (b.id_a, b.id_b):
            details = {"scale_bar": [b.id_a, b.id_b], "target": t}
            if t not in index:
                raise SolveError(Reason.bad_input, f"{name}: target {t!r} is not seen in any image.", details)
            if not known[index[t]]:
                raise SolveError(
                    Reason.bad_input,
                    f"{name}: target {t!r} is seen in fewer than two oriented images, so it has no coordinates.",
                    details,
                )
        if not b.sigma_mm > 0 or not b.distance_mm > 0:
            raise SolveError(Reason.bad_input, f"{name} needs a positive distance and sigma.")
        bars.append((index[b.id_a], index[b.id_b], float(b.distance_mm), float(b.sigma_mm)))
    return DatumRows(p0, point_free, control, inner, tuple(bars))


# -- the adjusted network ----------------------------------------------------------------------


def interior_sigmas(sol: NetworkSolution, k: int, free: Sequence[str]) -> dict[str, float]:
    """Standard deviation of each of camera ``k``'s parameters (0 where fixed), their units."""
    sd = {n: 0.0 for n in PARAMETER_NAMES}
    cols = sol.model.int_cols[k]
    sd.update({n: float(v) for n, v in zip(free, np.sqrt(np.diag(sol.Q)[cols]) * sol.sigma0, strict=True)})
    return sd


def point_sigmas(sol: NetworkSolution, point_free: NDArray[np.bool_]) -> Array:
    """Standard deviations (N, 3) mm of the adjusted points: 0 for fixed ones, NaN for free ones
    that were not adjusted (left out, or too few rays after rejections)."""
    cols = sol.model.point_col
    sig = np.where(np.asarray(point_free, bool)[:, None], np.nan, 0.0) * np.ones((len(cols), 3))
    adjusted = cols >= 0
    q = np.diag(sol.Q)[cols[adjusted][:, None] + np.arange(3)]
    sig[adjusted] = np.sqrt(np.clip(q, 0.0, None)) * sol.sigma0
    return sig


def adjusted_points(points: Array) -> NDArray[np.bool_]:
    """Which of the network's points (N, 3) mm have coordinates: a new point seen in fewer than two
    images, or left with fewer than two rays by the rejections, has none (NaN)."""
    return np.asarray(np.all(np.isfinite(points), axis=1))


def network_field(name: str, net: Network, points: Array, given: Field | None = None) -> Field:
    """The network's points ``points`` (N, 3) mm that have coordinates (:func:`adjusted_points`) as a
    field (new points with code -1); the normals of the ``given`` field's targets carried over (a new
    point's: +z)."""
    keep = adjusted_points(points)
    ids = tuple(i for i, k in zip(net.ids, keep, strict=True) if k)
    normals = None
    if given is not None and given.normals is not None:
        normals = np.array([given.normals[given.index[i]] if i in given.index else (0.0, 0.0, 1.0) for i in ids])
    return Field(
        name=name,
        ids=ids,
        xyz=points[keep],
        codes=np.array(net.codes, dtype=np.int64)[keep],
        diameters_mm=np.array(net.diameters)[keep],
        normals=normals.reshape(-1, 3) if normals is not None else None,
    )
