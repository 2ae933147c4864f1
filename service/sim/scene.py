"""The reference scene of DESIGN section 7: camera, target plate and viewing poses.

Benchmarks, the simulated camera driver and tests build their scenes here, so
every builder is deterministic (no randomness, no hidden state) and documented.

Geometry of the default scene::

    plate: field z = 0 plane, targets facing +z, centred on the field origin;
           a regular grid of 230 target centres spanning 640 x 500 mm
           (30 coded on an evenly spread 6 x 5 sub-grid, 200 uncoded).
    view:  at 1000 mm the reference camera (c = 12 mm, 1300 x 1030 px of 6.7 um)
           sees about 703 x 553 mm of the plate (8.71 x 6.90 mm sensor / 12 mm,
           a little less at the edges with this lens), so the whole plate,
           code rings included, is in view head-on.

The camera looks at the plate from the +z side; head-on with no roll its x axis
is field +x and its y axis field -y (field +y points up in the image).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from service.core.geometry.camera_model import BrownFraser
from service.core.geometry.frames import make_T
from service.core.targets.codes import n_codes
from service.core.targets.field import Field

Array = NDArray[np.float64]


def reference_camera() -> BrownFraser:
    """The DESIGN section 7 camera: 1300 x 1030 px, 6.7 um pixels, c = 12 mm.

    The distortion is that of a real 12 mm C-mount lens (about 28 px of radial
    correction in the corners, small decentring and affinity) and equals the
    ``reference_camera`` fixture in ``tests/conftest.py``.

    >>> reference_camera().width, reference_camera().c_mm
    (1300, 12.0)
    """
    return BrownFraser(
        width=1300,
        height=1030,
        pixel_size_mm=(0.0067, 0.0067),
        c_mm=12.0,
        x0_mm=0.031,
        y0_mm=-0.024,
        K1=-1.1e-3,
        K2=3.0e-6,
        K3=-1.0e-8,
        P1=2.0e-5,
        P2=-1.5e-5,
        B1=1.0e-4,
        B2=-5.0e-5,
    )


def _grid_shape(n: int, aspect: float) -> tuple[int, int]:
    """Columns and rows (nx, ny) of the smallest near-square grid with nx * ny >= n and nx / ny ~ aspect."""
    nx = max(1, round(math.sqrt(n * aspect)))
    ny = max(1, math.ceil(n / nx))
    return nx, ny


def reference_field(
    n_coded: int = 30,
    n_uncoded: int = 200,
    size_mm: tuple[float, float] = (640.0, 500.0),
    coded_diameter_mm: float = 10.0,
    uncoded_diameter_mm: float = 6.0,
    name: str = "reference-plate",
) -> Field:
    """A planar plate of targets in the field z = 0 plane (targets facing +z).

    The ``n_coded + n_uncoded`` target centres lie on one regular grid of
    ``nx x ny`` slots spanning ``size_mm`` (x, y) and centred on the field
    origin, with ``nx / ny`` close to the plate's aspect ratio. Coded targets
    take the slots of an evenly spread ``kx x ky`` sub-grid (a 6 x 5 sub-grid
    for 30, roughly 110 x 100 mm apart on the default plate, so any view of
    about 250 x 250 mm of the plate holds at least 4 of them); they carry codes
    ``1..n_coded`` in raster order (x fastest, from -x, -y) with ids ``"C<code>"``.
    Uncoded targets ``"P1".."P<n_uncoded>"`` take the remaining slots in raster
    order; if there are more slots than targets, the empty ones are spread
    evenly over the raster.

    Parameters
    ----------
    n_coded, n_uncoded : int
        Number of coded (at most the size of the code family) and uncoded targets.
    size_mm : (2,) float, mm
        Extent of the grid of target centres along field x and y.
    coded_diameter_mm, uncoded_diameter_mm : float, mm
        Central disk diameters; a coded target's ring reaches 3.2 times its disk radius.
    name : str
        The field's name.

    Returns
    -------
    Field
        Targets in the field frame, mm.

    >>> f = reference_field()
    >>> len(f), int(f.is_coded.sum()), f.ids[0]
    (230, 30, 'P1')
    """
    if n_coded < 0 or n_uncoded < 0 or n_coded + n_uncoded < 1:
        raise ValueError(f"need at least one target, got {n_coded} coded and {n_uncoded} uncoded")
    if n_coded > n_codes():
        raise ValueError(f"only {n_codes()} codes exist, asked for {n_coded} coded targets")
    width, height = (float(s) for s in size_mm)
    if not (width > 0 and height > 0):
        raise ValueError(f"size_mm must be positive, got {size_mm}")
    n_total = n_coded + n_uncoded
    aspect = width / height
    nx, ny = _grid_shape(n_total, aspect)
    xs = (np.arange(nx) - (nx - 1) / 2) * (width / max(nx - 1, 1))
    ys = (np.arange(ny) - (ny - 1) / 2) * (height / max(ny - 1, 1))

    is_coded_slot = np.zeros((ny, nx), dtype=bool)
    if n_coded:
        kx, ky = _grid_shape(n_coded, aspect)
        kx, ky = min(kx, nx), min(ky, ny)
        while kx * ky < n_coded:  # only for tiny grids, where kx or ky hit nx or ny
            kx, ky = (kx + 1, ky) if kx < nx else (kx, ky + 1)
        # centres of kx equal partitions keep coded targets off the plate border
        cols = np.floor((np.arange(kx) + 0.5) * nx / kx).astype(int)
        rows = np.floor((np.arange(ky) + 0.5) * ny / ky).astype(int)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        is_coded_slot[rr.ravel()[:n_coded], cc.ravel()[:n_coded]] = True

    ids: list[str] = []
    xyz: list[tuple[float, float, float]] = []
    codes: list[int] = []
    diameters: list[float] = []
    free = [(r, c) for r in range(ny) for c in range(nx) if not is_coded_slot[r, c]]
    keep: list[int] = np.round(np.linspace(0, len(free) - 1, n_uncoded)).astype(int).tolist() if n_uncoded else []
    uncoded_slots = {free[k] for k in keep}
    code = 0
    n_p = 0
    for r in range(ny):
        for c in range(nx):
            if is_coded_slot[r, c]:
                code += 1
                ids.append(f"C{code}")
                codes.append(code)
                diameters.append(coded_diameter_mm)
            elif (r, c) in uncoded_slots:
                n_p += 1
                ids.append(f"P{n_p}")
                codes.append(-1)
                diameters.append(uncoded_diameter_mm)
            else:
                continue
            xyz.append((float(xs[c]), float(ys[r]), 0.0))
    return Field(
        name=name,
        ids=tuple(ids),
        xyz=np.array(xyz),
        codes=np.array(codes, dtype=np.int64),
        diameters_mm=np.array(diameters),
    )


def reference_pose(
    view_angle_deg: float = 90.0,
    distance_mm: float = 1000.0,
    roll_deg: float = 0.0,
    azimuth_deg: float = 0.0,
    look_at_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Array:
    """``T_field_camera`` (4, 4) of a camera looking at a point of the z = 0 plate.

    The optical axis passes through ``look_at_mm`` at ``distance_mm`` from the
    projection centre and makes ``view_angle_deg`` with the plate plane, as in
    the paper's Table 2: 90 is head-on, 60 a 30 degree tilt. Head-on with zero
    roll and azimuth the camera's x axis is field +x and its y axis field -y.
    A smaller view angle tilts the camera about the field x axis towards -y
    (the camera moves to -y and looks towards +y); ``azimuth_deg`` then turns
    that whole pose about the field z axis through ``look_at_mm``, and
    ``roll_deg`` turns the camera about its own optical axis (positive from the
    image's +x towards +y).

    Parameters
    ----------
    view_angle_deg : float, degrees in (0, 90]
    distance_mm : float, mm > 0
    roll_deg, azimuth_deg : float, degrees
    look_at_mm : (3,) float, mm, field frame

    Returns
    -------
    (4, 4) float
        ``T_field_camera``.

    >>> np.round(reference_pose()[:3, 3], 6).tolist()
    [0.0, 0.0, 1000.0]
    """
    if not 0.0 < view_angle_deg <= 90.0:
        raise ValueError(f"view_angle_deg must lie in (0, 90], got {view_angle_deg}")
    if not distance_mm > 0.0:
        raise ValueError(f"distance_mm must be positive, got {distance_mm}")
    R_head_on = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T_head_on = make_T(R_head_on, [0.0, 0.0, distance_mm])
    tilt = Rotation.from_euler("x", 90.0 - view_angle_deg, degrees=True).as_matrix()
    turn = Rotation.from_euler("z", azimuth_deg, degrees=True).as_matrix()
    roll = Rotation.from_euler("z", roll_deg, degrees=True).as_matrix()
    T_field_lookat = make_T(turn @ tilt, look_at_mm)
    return T_field_lookat @ T_head_on @ make_T(roll, np.zeros(3))
