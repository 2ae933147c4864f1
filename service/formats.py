"""Readers and writers of posecell's files (DESIGN sections 2-4): the only file I/O of the engine.

Every reader raises :class:`FormatError` with one sentence naming the file and
what is wrong, so the CLI and the API can show it as it is.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from service.core.camera_model import BrownFraser
from service.core.field import Field


class FormatError(ValueError):
    """A file could not be read as what it should be."""


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


def write_json_atomic(path: str | os.PathLike[str], data: Any) -> None:
    """Write JSON through a temporary file, fsync and rename, so a crash never leaves half a file."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# -- camera.json -------------------------------------------------------------


def camera_from_json(data: Any, source: str = "camera") -> BrownFraser:
    try:
        return BrownFraser.from_dict(data)
    except ValueError as e:
        raise FormatError(f"{source}: {e}") from None


def read_camera(path: str | os.PathLike[str]) -> BrownFraser:
    return camera_from_json(read_json(path), str(path))


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
    for k, t in enumerate(data["targets"]):
        if not isinstance(t, dict) or "id" not in t or "xyz" not in t:
            raise FormatError(f"{source}: target #{k} needs an 'id' and an 'xyz'")
        try:
            p = [float(v) for v in t["xyz"]]
            if len(p) != 3 or not all(math.isfinite(v) for v in p):
                raise ValueError
        except (TypeError, ValueError):
            raise FormatError(f"{source}: target {t['id']!r} has a malformed 'xyz' (want 3 finite numbers)") from None
        ids.append(str(t["id"]))
        xyz.append(p)
        code = t.get("code")
        codes.append(int(code) if code is not None else -1)
        diam.append(float(t.get("diameter_mm", math.nan)))
    try:
        return Field(
            name=str(data.get("name", Path(source).stem)),
            ids=tuple(ids),
            xyz=np.array(xyz, dtype=np.float64).reshape(-1, 3),
            codes=np.array(codes, dtype=np.int64),
            diameters_mm=np.array(diam, dtype=np.float64),
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
        targets.append(t)
    return {"name": field.name, "targets": targets}


def field_from_csv(text: str, source: str = "field.csv") -> Field:
    """CSV rows ``id,x,y,z[,code,diameter_mm]``; a header row and ``#`` comments are skipped."""
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
            raise FormatError(f"{source}: row {row!r} is not 'id,x,y,z[,code,diameter_mm]'") from None
        t: dict[str, Any] = {"id": cells[0], "xyz": xyz}
        if len(cells) > 4 and cells[4] not in ("", "-"):
            t["code"] = int(cells[4])
        if len(cells) > 5 and cells[5] != "":
            t["diameter_mm"] = float(cells[5])
        targets.append(t)
    return field_from_json({"name": Path(source).stem, "targets": targets}, source)


#: Coded-target numbers of the AICON 14-bit family (service.core.codes_micmac): 1..516.
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
    ``service.core.codes.AICON14``); any other name (AICON's uncoded points,
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
        d["points"] = [{"id": t, "uv": [round(float(q[0]), 5), round(float(q[1]), 5)]}
                       for t, q in zip(im.ids, np.asarray(im.uv).reshape(-1, 2), strict=True)]
        out.append(d)
    return {"images": out}


def matrix4_from_json(value: Any, what: str) -> np.ndarray:
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(f"{what} is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FormatError(f"{what} must be a 4x4 matrix of finite numbers, got shape {T.shape}")
    return T


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
