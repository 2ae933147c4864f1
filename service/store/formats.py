"""Readers and writers of posecell's files (DESIGN sections 2-4): the only file I/O of the engine.

Every reader raises :class:`FormatError` with one sentence naming the file and
what is wrong, so the CLI and the API can show it as it is.

The calibration readers (camera, field, hand-eye, rig) are strict, because an
upload over the API is stored and then measured with: every number must be
finite (Python's ``json`` reads ``NaN`` and ``Infinity``, JSON has neither), of
the right type (a distortion coefficient is one number, a code a whole number)
and within the physical limits below; beyond them a value is a typo or a unit
mistake, not a camera. Writers write standard JSON only.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.core.pose.intersection import Rig
from service.core.targets.defects import DefectMap
from service.core.targets.detect_types import CENTRES
from service.core.targets.field import Field


class FormatError(ValueError):
    """A file could not be read as what it should be."""


MAX_IMAGE_PX = 100_000  # width and height of a camera.json
MAX_PIXEL_SIZE_MM = 1.0
MAX_C_MM = 1000.0  # principal distance
MAX_PRINCIPAL_POINT_MM = 1000.0  # |x0_mm|, |y0_mm|
MAX_DISTORTION = 1e6  # |K1|, |K2|, |K3|, |P1|, |P2|, |B1|, |B2| (per mm^2, mm^4, ...: generous for any lens)
MAX_COORDINATE_MM = 1e6  # target coordinates and translations of a transform: a kilometre
MAX_DIAMETER_MM = 1000.0
MAX_CODE = 1_000_000


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _is_finite_number(v: Any) -> bool:
    # math.isfinite would raise OverflowError on an int beyond a float (JSON may carry 1 with 400 zeros)
    return _is_number(v) and (isinstance(v, int) or math.isfinite(v))


def _interval(lo: float, hi: float, lo_open: bool) -> str:
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"


def _number(source: str, name: str, v: Any, lo: float, hi: float, unit: str = "", *, lo_open: bool = False) -> float:
    """``v`` as a float, or a ``FormatError`` saying which range ``name`` must lie in."""
    ok = _is_finite_number(v) and (lo < v if lo_open else lo <= v) and v <= hi
    if not ok:
        unit = f" {unit}" if unit else ""
        raise FormatError(f"{source}: {name} must be a number in {_interval(lo, hi, lo_open)}{unit}, not {v!r}")
    return float(v)


def _whole(source: str, name: str, v: Any, lo: int, hi: int) -> int:
    """``v`` as an int (a float with no fraction, as other tools write, passes), or a ``FormatError``."""
    ok = _is_finite_number(v) and (isinstance(v, int) or v.is_integer()) and lo <= v <= hi
    if not ok:
        raise FormatError(f"{source}: {name} must be a whole number in [{lo}, {hi}], not {v!r}")
    return int(v)


def reject_non_finite(data: Any, source: str) -> None:
    """Raise ``FormatError`` naming a NaN or infinity anywhere in parsed JSON ``data`` (JSON has neither)."""
    stack: list[tuple[str, Any]] = [("", data)]
    while stack:  # not recursive: the nesting is the sender's choice
        where, v = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            raise FormatError(f"{source}: {where or 'the value'} is {v!r}; numbers must be finite")
        if isinstance(v, dict):
            stack.extend((f"{where}.{k}" if where else str(k), x) for k, x in v.items())
        elif isinstance(v, list | tuple):
            stack.extend((f"{where}[{i}]", x) for i, x in enumerate(v))


def null_for_unknown(data: Any) -> Any:
    """``data`` with every NaN or infinity replaced by None (JSON ``null``): how a result file says
    "not determined" (e.g. the sigma of a target left with fewer than two rays)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, Mapping):
        return {k: null_for_unknown(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [null_for_unknown(v) for v in data]
    return null_for_unknown(data.tolist()) if hasattr(data, "tolist") else data  # numpy arrays and scalars


def _read_text(path: str | os.PathLike[str]) -> str:
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise FormatError(f"{p}: is a directory, not a file") from None
    except UnicodeDecodeError:
        raise FormatError(f"{p}: not a UTF-8 text file") from None
    except OSError as e:
        raise FormatError(f"{p}: cannot be read ({e.strerror})") from None


def read_json(path: str | os.PathLike[str]) -> Any:
    text = _read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(f"{path}: malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None


def fsync_dir(directory: str | os.PathLike[str]) -> None:
    """Sync a directory: a rename or removal in it survives a power cut only once this returns."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_json_atomic(path: str | os.PathLike[str], data: Any) -> None:
    """Write JSON through a temporary file, fsync, rename and fsync the directory, so a crash never
    leaves half a file and a power cut after it returns never the old one.

    Raises ``FormatError`` (and leaves ``path`` as it was) when ``data`` holds a NaN or an infinity.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2, allow_nan=False)  # NaN and Infinity are not JSON
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
        fsync_dir(p.parent)
    except ValueError as e:
        Path(tmp).unlink(missing_ok=True)
        raise FormatError(f"{p}: not written, the data is not standard JSON ({e})") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# -- camera.json -------------------------------------------------------------


def _check_camera(data: Any, source: str) -> None:
    """Types and ranges of the camera.json keys that are present (from_dict reports missing ones)."""
    if not isinstance(data, dict):
        raise FormatError(f"{source}: a camera must be a JSON object")
    reject_non_finite(data, source)
    for name in ("width", "height"):
        if name in data:
            _whole(source, name, data[name], 1, MAX_IMAGE_PX)
    if "pixel_size_mm" in data:
        ps = data["pixel_size_mm"]
        if isinstance(ps, list | tuple) and len(ps) != 2:
            raise FormatError(f"{source}: pixel_size_mm must be a number or [x, y] in mm, not {ps!r}")
        for v in ps if isinstance(ps, list | tuple) else [ps]:
            _number(source, "pixel_size_mm", v, 0.0, MAX_PIXEL_SIZE_MM, "mm", lo_open=True)
    if "c_mm" in data:
        _number(source, "c_mm", data["c_mm"], 0.0, MAX_C_MM, "mm", lo_open=True)
    for name in ("x0_mm", "y0_mm"):
        if name in data:
            _number(source, name, data[name], -MAX_PRINCIPAL_POINT_MM, MAX_PRINCIPAL_POINT_MM, "mm")
    for name in PARAMETER_NAMES[3:]:
        if name in data:
            _number(source, name, data[name], -MAX_DISTORTION, MAX_DISTORTION)
    sigma = data.get("sigma")
    if sigma is not None:
        if not isinstance(sigma, dict):
            raise FormatError(f"{source}: sigma must be an object of standard deviations, not {sigma!r}")
        for name, v in sigma.items():
            if not (_is_number(v) and v >= 0):
                raise FormatError(f"{source}: sigma.{name} must be a non-negative number, not {v!r}")


def camera_from_json(data: Any, source: str = "camera") -> BrownFraser:
    _check_camera(data, source)
    try:
        return BrownFraser.from_dict(data)
    except ValueError as e:
        raise FormatError(f"{source}: {e}") from None


def read_camera(path: str | os.PathLike[str]) -> BrownFraser:
    return camera_from_json(read_json(path), str(path))


def calibrated_centre(camera_data: Any) -> str | None:
    """What a camera.json's self-calibration measured the targets' centres as ("edge" or "centroid",
    ``calibration.centre``), None when it does not say (older files, observations given)."""
    cal = camera_data.get("calibration") if isinstance(camera_data, dict) else None
    centre = cal.get("centre") if isinstance(cal, dict) else None
    return centre if centre in CENTRES else None


def centre_mismatch(calibrated: str | None, measuring: str) -> str | None:
    """The warning for a camera calibrated with one centre estimator and measuring with the other
    (their systematic differences on real targets reach hundredths of a pixel); None when they agree
    or the calibration does not say."""
    if calibrated is None or calibrated == measuring:
        return None
    return (
        f"the camera was calibrated with {calibrated} centres and measures with {measuring} centres: "
        f'set centre = "{calibrated}" (--centre {calibrated}) or calibrate the camera again'
    )


def write_camera(path: str | os.PathLike[str], camera: BrownFraser, **extra: Any) -> None:
    d = camera.to_dict()
    d.update(extra)
    write_json_atomic(path, d)


# -- field.json / field.csv --------------------------------------------------


def field_from_json(data: Any, source: str = "field") -> Field:
    if not isinstance(data, dict) or not isinstance(data.get("targets"), list):
        raise FormatError(f"{source}: a field must be an object with a 'targets' list")
    ids: list[str] = []
    xyz: list[list[float]] = []
    codes: list[int] = []
    diam: list[float] = []
    normals: list[list[float]] = []
    reject_non_finite(data, source)
    for k, t in enumerate(data["targets"]):
        if not isinstance(t, dict) or "id" not in t or "xyz" not in t:
            raise FormatError(f"{source}: target #{k} needs an 'id' and an 'xyz'")
        tid = t["id"]
        if isinstance(tid, bool) or not isinstance(tid, str | int) or tid == "":
            raise FormatError(f"{source}: target #{k} has a malformed 'id' (want a non-empty string), not {tid!r}")
        where = f"target {tid!r}"
        p = t["xyz"]
        if not isinstance(p, list | tuple) or len(p) != 3 or not all(_is_number(v) for v in p):
            raise FormatError(f"{source}: {where} has a malformed 'xyz' (want 3 finite numbers, mm), not {p!r}")
        ids.append(str(tid))
        xyz.append([_number(source, f"{where} xyz", v, -MAX_COORDINATE_MM, MAX_COORDINATE_MM, "mm") for v in p])
        code = t.get("code")
        codes.append(-1 if code is None else _whole(source, f"{where} code", code, 0, MAX_CODE))
        d = t.get("diameter_mm")
        diam.append(
            math.nan
            if d is None
            else _number(source, f"{where} diameter_mm", d, 0.0, MAX_DIAMETER_MM, "mm", lo_open=True)
        )
        nrm = t.get("normal", [0.0, 0.0, 1.0])
        if not isinstance(nrm, list | tuple) or len(nrm) != 3 or not all(_is_number(v) for v in nrm):
            raise FormatError(f"{source}: {where} has a malformed 'normal' (want 3 finite numbers), not {nrm!r}")
        normal = [_number(source, f"{where} normal", v, -1e6, 1e6) for v in nrm]
        if not math.hypot(*normal) > 1e-9:
            raise FormatError(f"{source}: {where} has a zero 'normal' (want the direction its print faces)")
        normals.append(normal)
    try:
        return Field(
            name=str(data.get("name", Path(source).stem)),
            ids=tuple(ids),
            xyz=np.array(xyz, dtype=np.float64).reshape(-1, 3),
            codes=np.array(codes, dtype=np.int64),
            diameters_mm=np.array(diam, dtype=np.float64),
            # without any "normal" the field lies in its x-y plane: no normals kept
            normals=np.array(normals).reshape(-1, 3) if any("normal" in t for t in data["targets"]) else None,
        )
    except ValueError as e:
        raise FormatError(f"{source}: {e}") from None


def field_to_json(field: Field) -> dict[str, Any]:
    targets = []
    for i, tid in enumerate(field.ids):
        t: dict[str, Any] = {"id": tid}
        if field.codes[i] >= 0:
            t["code"] = int(field.codes[i])
        t["xyz"] = [round(float(v), 6) for v in field.xyz[i]]
        if math.isfinite(field.diameters_mm[i]):
            t["diameter_mm"] = float(field.diameters_mm[i])
        if field.normals is not None:
            t["normal"] = [round(float(v), 9) for v in field.normals[i]]
        targets.append(t)
    return {"name": field.name, "targets": targets}


def field_from_csv(text: str, source: str = "field.csv") -> Field:
    """CSV rows ``id,x,y,z[,code,diameter_mm[,nx,ny,nz]]`` (the normal: the side the target's print
    faces, as field.json's ``normal``); a header row and ``#`` comments are skipped."""
    targets = []
    for row in csv.reader(io.StringIO(text)):
        if not row or row[0].strip().startswith("#"):
            continue
        cells = [c.strip() for c in row]
        try:
            xyz = [float(v) for v in cells[1:4]]
        except (ValueError, IndexError):
            if not targets and cells[0].lower() in ("id", "name"):
                continue  # header
            raise FormatError(f"{source}: row {row!r} is not 'id,x,y,z[,code,diameter_mm[,nx,ny,nz]]'") from None
        t: dict[str, Any] = {"id": cells[0], "xyz": xyz}
        try:
            if len(cells) > 4 and cells[4] not in ("", "-"):
                t["code"] = int(cells[4])
            if len(cells) > 5 and cells[5] != "":
                t["diameter_mm"] = float(cells[5])
            if len(cells) > 6 and any(cells[6:]):
                if len(cells) != 9:
                    raise ValueError
                t["normal"] = [float(v) for v in cells[6:9]]
        except ValueError:
            raise FormatError(
                f"{source}: row {row!r} has a code that is not a whole number, a diameter that is not a number "
                "or a normal that is not three numbers"
            ) from None
        targets.append(t)
    return field_from_json({"name": Path(source).stem, "targets": targets}, source)


#: Coded-target numbers of the AICON 14-bit family (service.core.targets.codes_micmac): 1..516.
AICON_MAX_CODE = 516


def field_from_aicon_txt(
    text: str,
    source: str = "points.txt",
    *,
    coded_diameter_mm: float = math.nan,
    uncoded_diameter_mm: float = math.nan,
    max_code: int = AICON_MAX_CODE,
) -> Field:
    """An AICON-style point list, as MicMac's ``Positions-3D-14bit_lookup.txt``.

    Whitespace-separated rows ``name X Y Z [more columns]``, X, Y, Z in mm; the
    columns after Z (AICON's "fix" flags and counts) are ignored, as MMVII's
    ``ImportGCP ... NXYZ`` ignores them; blank lines and ``#`` comments are skipped.
    A name that is a whole number in 1..``max_code`` is a coded target whose code
    is that number (the AICON number of the 14-bit family, read with
    ``service.core.targets.codes.AICON14``); any other name (AICON's uncoded points,
    e.g. 2001, 2002, ...) is an uncoded target. The file holds no target sizes:
    pass them, or leave them NaN for the pipeline's defaults.
    """
    targets = []
    for k, line in enumerate(text.splitlines(), start=1):
        cells = line.split("#", 1)[0].split()
        if not cells:
            continue
        try:
            xyz = [float(v) for v in cells[1:4]]
            if len(xyz) != 3:
                raise ValueError
        except ValueError:
            raise FormatError(f"{source}: line {k} is not 'name X Y Z ...' (mm): {line.strip()!r}") from None
        t: dict[str, Any] = {"id": cells[0], "xyz": xyz}
        coded = cells[0].isdigit() and 1 <= int(cells[0]) <= max_code
        if coded:
            t["code"] = int(cells[0])
        diameter = coded_diameter_mm if coded else uncoded_diameter_mm
        if math.isfinite(diameter):
            t["diameter_mm"] = float(diameter)
        targets.append(t)
    if not targets:
        raise FormatError(f"{source}: no target rows 'name X Y Z ...' found")
    return field_from_json({"name": Path(source).stem, "targets": targets}, source)


def read_field(path: str | os.PathLike[str]) -> Field:
    """field.json, field.csv (:func:`field_from_csv`) or an AICON point list .txt (:func:`field_from_aicon_txt`)."""
    suffix = str(path).lower()
    if suffix.endswith(".csv"):
        return field_from_csv(_read_text(path), str(path))
    if suffix.endswith(".txt"):
        return field_from_aicon_txt(_read_text(path), str(path))
    return field_from_json(read_json(path), str(path))


def write_field(path: str | os.PathLike[str], field: Field) -> None:
    write_json_atomic(path, field_to_json(field))


# -- image observations ------------------------------------------------------


def observations_from_json(data: Any, source: str = "points") -> tuple[list[str], np.ndarray]:
    """``[{"id": .., "uv": [u, v]}, ...]`` -> (ids, uv (N, 2) px)."""
    if isinstance(data, dict) and "points" in data:
        data = data["points"]
    if not isinstance(data, list):
        raise FormatError(f"{source}: expected a list of {{'id': ..., 'uv': [u, v]}}")
    ids: list[str] = []
    uv: list[list[float]] = []
    for k, o in enumerate(data):
        try:
            p = [float(v) for v in o["uv"]]
            if len(p) != 2 or not all(math.isfinite(v) for v in p):
                raise ValueError
            ids.append(str(o["id"]))
            uv.append(p)
        except (TypeError, ValueError, KeyError):
            raise FormatError(f"{source}: point #{k} is not {{'id': ..., 'uv': [u, v]}}") from None
    return ids, np.array(uv, dtype=np.float64).reshape(-1, 2)


def read_observations(path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray]:
    return observations_from_json(read_json(path), str(path))


class ImageObservations(NamedTuple):
    """One image's identified targets in a multi-image observations file (calibration input).

    ``camera`` (int) and ``epoch`` (str) are set for the images of a camera rig.
    """

    name: str
    ids: list[str]
    uv: np.ndarray
    camera: int | None = None
    epoch: str | None = None


def image_observations_from_json(data: Any, source: str = "observations") -> list[ImageObservations]:
    """``{"images": [{"name": .., "points": [{"id": .., "uv": [u, v]}, ...]}, ...]}``; a rig's images
    also carry ``"camera": k`` and ``"epoch": "..."`` (images of one exposure share it)."""
    if not isinstance(data, dict) or not isinstance(data.get("images"), list):
        raise FormatError(f"{source}: expected {{'images': [{{'name': ..., 'points': [...]}}, ...]}}")
    out = []
    for k, im in enumerate(data["images"]):
        if not isinstance(im, dict) or "points" not in im:
            raise FormatError(f"{source}: image #{k} needs 'points'")
        name = str(im.get("name", f"image{k}"))
        ids, uv = observations_from_json(im["points"], f"{source}: image {name!r}")
        camera = im.get("camera")
        if camera is not None and (not isinstance(camera, int) or camera < 0):
            raise FormatError(f"{source}: image {name!r} has a malformed 'camera' (want an index 0, 1, ...)")
        epoch = im.get("epoch")
        out.append(ImageObservations(name, ids, uv, camera, None if epoch is None else str(epoch)))
    if not out:
        raise FormatError(f"{source}: no images")
    return out


def read_image_observations(path: str | os.PathLike[str]) -> list[ImageObservations]:
    return image_observations_from_json(read_json(path), str(path))


def image_observations_to_json(images: list[ImageObservations]) -> dict[str, Any]:
    out = []
    for im in images:
        d: dict[str, Any] = {"name": im.name}
        if im.camera is not None:
            d["camera"] = int(im.camera)
        if im.epoch is not None:
            d["epoch"] = im.epoch
        d["points"] = [
            {"id": t, "uv": [round(float(q[0]), 5), round(float(q[1]), 5)]}
            for t, q in zip(im.ids, np.asarray(im.uv).reshape(-1, 2), strict=True)
        ]
        out.append(d)
    return {"images": out}


def matrix4_from_json(value: Any, what: str) -> np.ndarray:
    """A 4x4 transform (mm) from nested lists of numbers; translations within a kilometre."""
    if not isinstance(value, np.ndarray):
        rows = value if isinstance(value, list | tuple) else []
        if len(rows) != 4 or not all(isinstance(r, list | tuple) and len(r) == 4 for r in rows):
            raise FormatError(f"{what} must be a 4x4 matrix (4 lists of 4 numbers)")
        if not all(_is_number(v) for r in rows for v in r):
            raise FormatError(f"{what} must hold numbers only, not strings, booleans or nulls")
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise FormatError(f"{what} is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FormatError(f"{what} must be a 4x4 matrix of finite numbers, got shape {T.shape}")
    if np.max(np.abs(T)) > MAX_COORDINATE_MM:
        raise FormatError(f"{what} has a value beyond ±{MAX_COORDINATE_MM:g} mm")
    return T


def rig_from_json(data: Any, source: str = "rig") -> Rig:
    """A camera rig (``rig.json``: ``cameras`` and their ``T_master_camera``), checked as strictly as a camera."""
    if not isinstance(data, dict) or data.get("model", "rig") != "rig":
        raise FormatError(f"{source}: a rig must be a JSON object with model 'rig'")
    reject_non_finite(data, source)
    cameras, T = data.get("cameras"), data.get("T_master_camera")
    if not isinstance(cameras, list) or not isinstance(T, list) or len(cameras) != len(T):
        raise FormatError(f"{source}: a rig needs a 'cameras' list and a 'T_master_camera' list of the same length")
    cams = [camera_from_json(c, f"{source}: camera {k}") for k, c in enumerate(cameras)]
    Ts = [matrix4_from_json(t, f"{source}: T_master_camera[{k}]") for k, t in enumerate(T)]
    try:
        return Rig(tuple(cams), np.array(Ts).reshape(-1, 4, 4))
    except ValueError as e:
        raise FormatError(f"{source}: {e}") from None


def read_handeye_samples(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """``[{"T_base_flange": 4x4, "T_field_camera": 4x4}, ...]`` (mm) -> two (M, 4, 4) stacks."""
    data = read_json(path)
    if isinstance(data, dict) and "samples" in data:
        data = data["samples"]
    if not isinstance(data, list) or not data:
        raise FormatError(f"{path}: expected a non-empty list of samples")
    A, B = [], []
    for k, s in enumerate(data):
        if not isinstance(s, dict) or "T_base_flange" not in s or "T_field_camera" not in s:
            raise FormatError(f"{path}: sample #{k} needs 'T_base_flange' and 'T_field_camera'")
        A.append(matrix4_from_json(s["T_base_flange"], f"{path}: sample #{k} T_base_flange"))
        B.append(matrix4_from_json(s["T_field_camera"], f"{path}: sample #{k} T_field_camera"))
    return np.array(A), np.array(B)


# -- rig pairing: which images were exposed together --------------------------


def rig_pairs_from_csv(text: str, n_cameras: int, source: str = "pairs.csv") -> list[list[str]]:
    """Rows of ``n_cameras`` image paths, one row per epoch (camera 0's image first); ``#`` comments
    and blank rows are skipped. Each row must name exactly one image per camera."""
    rows = []
    for k, row in enumerate(csv.reader(io.StringIO(text))):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if len(cells) != n_cameras or not all(cells):
            raise FormatError(
                f"{source}: row {k + 1} names {len([c for c in cells if c])} images, but the rig has "
                f"{n_cameras} cameras (one image per camera, comma-separated)"
            )
        rows.append(cells)
    if not rows:
        raise FormatError(f"{source}: no pairs")
    return rows


def read_rig_pairs(path: str | os.PathLike[str], n_cameras: int) -> list[list[str]]:
    return rig_pairs_from_csv(_read_text(path), n_cameras, str(path))


def image_timestamps_from_csv(text: str, source: str = "timestamps.csv") -> dict[str, int]:
    """Exposure times of a camera folder's images: a header ``name,t_ns`` (whole nanoseconds) or
    ``name,t_s`` (seconds), then one row per image file name; -> {file name: t_ns}. Any clock will do,
    as long as every camera's is the same one."""
    reader = csv.reader(io.StringIO(text))
    header = [c.strip().lower() for c in next(reader, [])]
    if len(header) != 2 or header[0] != "name" or header[1] not in ("t_ns", "t_s"):
        raise FormatError(f"{source}: the first row must be the header 'name,t_ns' or 'name,t_s'")
    out: dict[str, int] = {}
    for k, row in enumerate(reader):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        try:
            if len(cells) != 2:
                raise ValueError
            t = int(cells[1]) if header[1] == "t_ns" else round(float(cells[1]) * 1e9)
        except (ValueError, OverflowError):
            raise FormatError(f"{source}: row {k + 2} is not 'name,{header[1]}'") from None
        if cells[0] in out:
            raise FormatError(f"{source}: image {cells[0]!r} has two timestamps")
        out[cells[0]] = t
    return out


def read_image_timestamps(path: str | os.PathLike[str]) -> dict[str, int]:
    return image_timestamps_from_csv(_read_text(path), str(path))


# -- defects.json ------------------------------------------------------------


def read_defects(path: str | os.PathLike[str]) -> DefectMap:
    """A sensor's defect pixels (``posecell calibrate defects``)."""
    try:
        return DefectMap.from_dict(read_json(path), str(path))
    except FormatError:
        raise
    except ValueError as e:
        raise FormatError(str(e)) from None


def write_defects(path: str | os.PathLike[str], defects: DefectMap, **extra: Any) -> None:
    write_json_atomic(path, defects.to_dict(**extra))


# -- images ------------------------------------------------------------------


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """A grey image (H, W) uint8 or uint16 from PNG, TIFF or PGM; colour is converted to grey."""
    import cv2  # only the image verbs need OpenCV's codecs

    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: no such file")
    image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(f"{p}: cannot be read as an image (PNG, TIFF or PGM, 8 or 16 bit)")
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    if image.dtype not in (np.uint8, np.uint16):
        raise FormatError(f"{p}: pixel type {image.dtype} is not supported (8 or 16 bit grey)")
    return image


def write_image(path: str | os.PathLike[str], image: np.ndarray) -> None:
    import cv2

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(p), image):
        raise FormatError(f"{p}: could not write the image")
