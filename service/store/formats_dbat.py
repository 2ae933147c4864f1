"""Readers of a PhotoModeler export and of DBAT's files, converted to posecell's conventions.

DBAT (the Damped Bundle Adjustment Toolbox, Börlin & Grussenmeyer) reads projects
exported from PhotoModeler; its demo data set (``../shared/data/dbat-camcal``)
is posecell's reference check for the self-calibrating bundle adjustment.

Conventions of the files, and what posecell makes of them:

- PhotoModeler's image coordinates are pixels from the image *corner*, u right and
  v down: the centre of the top-left pixel is (0.5, 0.5). posecell puts that
  centre at (0, 0) (DESIGN section 2), so ``uv = uv_pm - 0.5``.
- Object coordinates are in the project's unit; the DBAT demo's is the metre
  (its report: "Object space unit (ou): m"), read here as ``unit_mm = 1000``.
- The PhotoModeler header holds the camera: c, principal point (mm from the image
  corner), format size (mm), K1-K3, P1, P2. The format size gives the pixel size.
- DBAT's "Backward (Photogrammetry) model 3" corrects measured coordinates as
  posecell does, ideal = measured + Δ(K1-K3, P1, P2), in a frame with y up and
  with a pixel aspect ``(1 + as)`` on x. Its reported K and P act with posecell's
  signs; the y flip only turns the sign of P2 (the x y cross terms):
  ``K_posecell = K_dbat``, ``P1_posecell = P1_dbat``, ``P2_posecell = -P2_dbat``.
  Its aspect is posecell's B1 to first order (B1 is estimated, on the pixel size of
  PhotoModeler's format). Its principal point is reported in mm of its nominal
  (y) pixel size from the image corner: ``u_pp = px / pixel_height``. Both readings
  are checked by the comparison itself: with DBAT's own pixel sizes every other
  parameter agrees to 0.05 sigma, and the principal point with this reading to
  0.002 px, where dividing px by the scaled pixel width would put it 0.44 px off.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from service.core.calib.bundle import ImagePoints
from service.core.geometry.camera_model import BrownFraser
from service.core.targets.field import Field
from service.store.formats import FormatError

#: PhotoModeler's pixel coordinates minus posecell's: the image corner is PM's origin.
PM_PIXEL_OFFSET = 0.5


@dataclass(frozen=True)
class PhotoModelerProject:
    """What a PhotoModeler export holds, in posecell's conventions (mm, posecell pixels).

    ``camera``: PhotoModeler's camera solution (c, principal point, format, K1-K3,
    P1, P2 as PhotoModeler signs them; see the module docstring). ``images``: the
    observations of each image. ``object_points``: PhotoModeler's adjusted points, mm.
    ``sigma_px``: the observations' a-priori standard deviation.
    """

    title: str
    width: int
    height: int
    camera: BrownFraser
    pm_camera: dict[str, float]
    images: tuple[ImagePoints, ...]
    object_points: Field
    sigma_px: float


def _floats(line: str) -> list[float] | None:
    try:
        return [float(v) for v in line.split()]
    except ValueError:
        return None


def _text(path: str | os.PathLike[str]) -> str:
    try:
        return Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise FormatError(f"{path}: cannot be read ({e.strerror})") from None


def read_pm_export(path: str | os.PathLike[str], unit_mm: float = 1000.0) -> PhotoModelerProject:
    """Read a PhotoModeler export as DBAT's ``loadpm`` does (object unit ``unit_mm`` mm)."""
    lines = _text(path).splitlines()
    if len(lines) < 6:
        raise FormatError(f"{path}: too short for a PhotoModeler export")
    head = _floats(lines[1])
    cam = _floats(lines[3])
    if head is None or len(head) < 4 or cam is None or len(cam) < 10:
        raise FormatError(f"{path}: lines 2 and 4 are not a PhotoModeler export header")
    width, height = int(head[2]), int(head[3])
    c, xp, yp, fw, fh = cam[:5]
    pm = dict(
        zip(
            ("c_mm", "xp_mm", "yp_mm", "format_width_mm", "format_height_mm", "K1", "K2", "K3", "P1", "P2"),
            cam[:10],
            strict=True,
        )
    )
    psx, psy = fw / width, fh / height
    camera = BrownFraser(
        width,
        height,
        (psx, psy),
        c,
        x0_mm=(xp / psx - PM_PIXEL_OFFSET - (width - 1) / 2) * psx,
        y0_mm=(yp / psy - PM_PIXEL_OFFSET - (height - 1) / 2) * psy,
    )
    names: dict[int, str] = {}
    image_line = re.compile(r"^\s*(\d+)\s+(\S*[A-Za-z]\S*)\s*$")
    k = 5
    # one block per image: name, exterior orientation, its sigmas, a blank line, camera, its sigmas
    while k < len(lines):
        m = image_line.match(lines[k])
        if m is None:
            if lines[k].strip():
                break
            k += 1
            continue
        names[int(m.group(1))] = m.group(2).replace("\\", "/").rsplit("/", 1)[-1]
        k += 6
    points: list[tuple[str, list[float]]] = []
    marks: list[tuple[int, str, float, float, float]] = []
    for line in lines[k:]:
        v = _floats(line)
        if v is None:
            raise FormatError(f"{path}: unexpected line {line.strip()!r} after the image blocks")
        if len(v) == 7:  # object point: id, X, Y, Z and their sigmas
            points.append((str(int(v[0])), [x * unit_mm for x in v[1:4]]))
        elif len(v) == 6:  # observation: image, point id, u, v px and their sigmas
            marks.append((int(v[0]), str(int(v[1])), v[2], v[3], v[4]))
    if not names or not marks:
        raise FormatError(f"{path}: no images or no image observations found")
    images = []
    for j in sorted(names):
        rows = [m for m in marks if m[0] == j]
        uv = np.array([[m[2], m[3]] for m in rows]).reshape(-1, 2) - PM_PIXEL_OFFSET
        images.append(ImagePoints(names[j], tuple(m[1] for m in rows), uv))
    sig = sorted({m[4] for m in marks})
    field = Field(
        name=Path(path).stem,
        ids=tuple(p[0] for p in points),
        xyz=np.array([p[1] for p in points]).reshape(-1, 3),
        codes=np.full(len(points), -1),
        diameters_mm=np.full(len(points), math.nan),
    )
    return PhotoModelerProject(
        str(lines[0]).strip(),
        width,
        height,
        camera,
        pm,
        tuple(images),
        field,
        float(sig[0]) if len(sig) == 1 else float(np.median([m[4] for m in marks])),
    )


def read_dbat_control(path: str | os.PathLike[str], unit_mm: float = 1000.0) -> Field:
    """DBAT's control point file: ``id,label,X,Y,Z`` rows (``#`` comments), object unit ``unit_mm`` mm."""
    ids, xyz = [], []
    for k, line in enumerate(_text(path).splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            ids.append(str(int(cells[0])))
            xyz.append([float(v) * unit_mm for v in cells[-3:]])
        except (ValueError, IndexError):
            raise FormatError(f"{path}: line {k} is not 'id,label,X,Y,Z'") from None
    if not ids:
        raise FormatError(f"{path}: no control points")
    return Field(Path(path).stem, tuple(ids), np.array(xyz), np.full(len(ids), -1), np.full(len(ids), math.nan))


_REPORT_KEYS = {
    "Camera Constant": "cc",
    "px - principal point x": "px",
    "py - principal point y": "py",
    "K1 - radial distortion 1": "K1",
    "K2 - radial distortion 2": "K2",
    "K3 - radial distortion 3": "K3",
    "P1 - decentering distortion 1": "P1",
    "P2 - decentering distortion 2": "P2",
    "as - off-unit aspect parameter": "as",
    "sk - skew": "sk",
    "Pixel width": "pixel_width",
    "Pixel height": "pixel_height",
    "Image width": "image_width",
    "Image height": "image_height",
}


def read_dbat_report(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The camera of a DBAT result file: ``{name: (value, sigma or None)}`` plus ``sigma0_px`` and
    ``redundancy`` (the first camera only)."""
    out: dict[str, Any] = {}
    key = None
    for line in _text(path).splitlines():
        s = line.strip()
        if s.startswith("Sigma0 (pixels):"):
            out["sigma0_px"] = float(s.split(":")[1])
        elif s.startswith("Redundancy") and "redundancy" not in out:
            out["redundancy"] = int(s.split()[-1])
        elif s.endswith(":"):  # a heading: the camera parameters come first in the file
            key = _REPORT_KEYS.get(s.rstrip(":"))
            if key in out:
                key = None
            elif key is not None:
                out[key] = [math.nan, None]
        elif key and s.startswith("Value:"):
            out[key][0] = float(s.split()[1])
        elif key and s.startswith("Deviation:"):
            out[key][1] = float(s.split()[1])
        elif s.startswith("Photograph Standard Deviations"):
            break
    if "cc" not in out or "sigma0_px" not in out:
        raise FormatError(f"{path}: not a DBAT result file (no camera constant or sigma0)")
    return {k: (tuple(v) if isinstance(v, list) else v) for k, v in out.items()}


def posecell_parameters(report: dict[str, Any], camera: BrownFraser) -> dict[str, tuple[float, float | None]]:
    """DBAT's camera in posecell's model and units: ``{c_mm, x0_mm, y0_mm, K1..P2: (value, sigma)}``.

    ``camera`` gives posecell's pixel size and image size (e.g. :func:`read_pm_export`'s);
    DBAT's principal point (mm from the image corner, in its nominal pixel size; see the
    module docstring) becomes a pixel position and then posecell's offset from the sensor centre.
    """
    (px, spx), (py, spy) = report["px"], report["py"]
    dx = dy = report["pixel_height"][0]
    psx, psy = camera.pixel_size_mm
    u0 = px / dx - PM_PIXEL_OFFSET - (camera.width - 1) / 2
    v0 = py / dy - PM_PIXEL_OFFSET - (camera.height - 1) / 2
    sign = {"K1": 1.0, "K2": 1.0, "K3": 1.0, "P1": 1.0, "P2": -1.0}
    out: dict[str, tuple[float, float | None]] = {
        "c_mm": report["cc"],
        "x0_mm": (u0 * psx, None if spx is None else spx * psx / dx),
        "y0_mm": (v0 * psy, None if spy is None else spy * psy / dy),
    }
    for name, s in sign.items():
        v, sd = report[name]
        out[name] = (s * v, sd)
    return out
