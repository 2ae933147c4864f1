"""The calibration readers refuse non-finite numbers, wrong types and absurd magnitudes, naming the key."""

from __future__ import annotations

import copy
import json
import math
import os
import re

import numpy as np
import pytest

from service.runtime.calibration_state import CalibrationState, validate
from service.settings import Settings
from service.store import formats
from service.store.calibrations import CalibrationStore
from service.store.formats import FormatError

CAMERA = {  # DESIGN section 2
    "model": "brown-fraser",
    "width": 1300,
    "height": 1030,
    "pixel_size_mm": [0.0067, 0.0067],
    "c_mm": 12.0,
    "x0_mm": 0.0,
    "y0_mm": 0.0,
    "K1": 0.0,
    "K2": 0.0,
    "K3": 0.0,
    "P1": 0.0,
    "P2": 0.0,
    "B1": 0.0,
    "B2": 0.0,
}
FIELD = {  # DESIGN section 3
    "name": "floor-plate-A",
    "targets": [
        {"id": "C7", "code": 7, "xyz": [120.0, 80.0, 0.0], "diameter_mm": 10.0},
        {"id": "P101", "xyz": [150.0, 80.0, 0.0], "diameter_mm": 6.0},
    ],
}
EYE = np.eye(4).tolist()


def _with(data, key, value):
    out = copy.deepcopy(data)
    node = out
    for k in key[:-1]:
        node = node[k]
    node[key[-1]] = value
    return out


def test_the_design_examples_are_read():
    cam = formats.camera_from_json(CAMERA)
    assert cam.width == 1300 and cam.c_mm == 12.0
    field = formats.field_from_json(FIELD)
    assert field.ids == ("C7", "P101") and list(field.codes) == [7, -1]


@pytest.mark.parametrize(
    ("key", "value", "needle"),
    [
        (("c_mm",), 1e308, "c_mm must be a number in (0, 1000] mm"),
        (("c_mm",), math.nan, "c_mm is nan"),
        (("c_mm",), "12", "c_mm must be a number"),
        (("K1",), [1, 2], "K1 must be a number"),
        (("K1",), math.nan, "K1 is nan"),
        (("K2",), 1e300, "K2 must be a number in [-1e+06, 1e+06]"),
        (("B1",), True, "B1 must be a number"),
        (("x0_mm",), -5e3, "x0_mm must be a number in [-1000, 1000] mm"),
        (("width",), 1300.5, "width must be a whole number in [1, 100000]"),
        (("width",), 10**9, "width must be a whole number"),
        (("width",), 10**400, "width must be a whole number"),  # beyond a float: no OverflowError
        (("c_mm",), 10**400, "c_mm must be a number"),
        (("height",), "1030", "height must be a whole number"),
        (("pixel_size_mm",), [0.0067, math.inf], "pixel_size_mm[1] is inf"),
        (("pixel_size_mm",), [0.0067], "pixel_size_mm must be a number or [x, y]"),
        (("pixel_size_mm",), 2.0, "pixel_size_mm must be a number in (0, 1] mm"),
        (("sigma",), {"c_mm": -1.0}, "sigma.c_mm must be a non-negative number"),
        (("calibration",), {"rms": [math.nan]}, "calibration.rms[0] is nan"),  # unknown keys are stored too
    ],
)
def test_camera_refuses_bad_values_naming_the_key(key, value, needle):
    with pytest.raises(FormatError, match=re.escape(needle)):
        formats.camera_from_json(_with(CAMERA, key, value), "camera.json")


def test_camera_accepts_whole_floats_for_the_image_size_and_one_number_for_square_pixels():
    cam = formats.camera_from_json({**CAMERA, "width": 1300.0, "pixel_size_mm": 0.005})
    assert cam.width == 1300 and isinstance(cam.width, int) and cam.pixel_size_mm == (0.005, 0.005)


@pytest.mark.parametrize(
    ("key", "value", "needle"),
    [
        (("targets", 1, "code"), 7.5, "target 'P101' code must be a whole number"),
        (("targets", 1, "code"), "8", "target 'P101' code must be a whole number"),
        (("targets", 1, "code"), True, "target 'P101' code must be a whole number"),
        (("targets", 1, "code"), 10**30, "target 'P101' code must be a whole number in [0, 1000000]"),
        (("targets", 1, "code"), 10**400, "target 'P101' code must be a whole number in [0, 1000000]"),
        (("targets", 1, "code"), -3, "target 'P101' code must be a whole number"),
        (("targets", 1, "diameter_mm"), [1], "target 'P101' diameter_mm must be a number"),
        (("targets", 1, "diameter_mm"), "6", "target 'P101' diameter_mm must be a number"),
        (("targets", 1, "diameter_mm"), math.nan, "targets[1].diameter_mm is nan"),
        (("targets", 1, "diameter_mm"), 1e300, "diameter_mm must be a number in (0, 1000] mm"),
        (("targets", 1, "diameter_mm"), 0, "diameter_mm must be a number in (0, 1000] mm"),
        (("targets", 1, "xyz"), [1e300, 0.0, 0.0], "target 'P101' xyz must be a number in [-1e+06, 1e+06] mm"),
        (("targets", 1, "xyz"), ["1", 0.0, 0.0], "target 'P101' has a malformed 'xyz'"),
        (("targets", 1, "xyz"), [1.0, 0.0], "target 'P101' has a malformed 'xyz'"),
        (("targets", 1, "id"), ["P", 101], "target #1 has a malformed 'id'"),
        (("targets", 1, "id"), "", "target #1 has a malformed 'id'"),
        (("targets", 1, "normal"), [0.0, 1.0], "target 'P101' has a malformed 'normal'"),
        (("targets", 1, "normal"), [0.0, "1", 0.0], "target 'P101' has a malformed 'normal'"),
        (("targets", 1, "normal"), [0.0, 0.0, 0.0], "target 'P101' has a zero 'normal'"),
        (("targets", 1, "normal"), [10**400, 0.0, 0.0], "target 'P101' normal must be a number in [-1e+06, 1e+06]"),
    ],
)
def test_field_refuses_bad_values_naming_the_target(key, value, needle):
    with pytest.raises(FormatError, match=re.escape(needle)):
        formats.field_from_json(_with(FIELD, key, value), "field.json")


def test_field_accepts_a_whole_float_code_and_a_null_diameter():
    field = formats.field_from_json(
        _with(_with(FIELD, ("targets", 1, "code"), 8.0), ("targets", 1, "diameter_mm"), None)
    )
    assert field.codes[1] == 8 and math.isnan(field.diameters_mm[1])


def test_field_normals_are_read_made_unit_and_written_back():
    # a field on a floor and a wall: each target's plane, the side its print faces
    plain = formats.field_from_json(FIELD)
    assert plain.normals is None and not plain.has_normals  # no "normal": one plane, as before
    walled = formats.field_from_json(_with(FIELD, ("targets", 1, "normal"), [0.0, -2.0, 0.0]))
    assert walled.has_normals and np.allclose(walled.normals, [[0, 0, 1], [0, -1, 0]])
    assert walled.normal_rows(np.array([1])).tolist() == [[0.0, -1.0, 0.0]]
    again = formats.field_from_json(json.loads(json.dumps(formats.field_to_json(walled))))
    assert np.allclose(again.normals, walled.normals) and again.ids == walled.ids
    # every normal +z: the field is on one plane, nothing to do per target
    flat = formats.field_from_json(_with(FIELD, ("targets", 0, "normal"), [0.0, 0.0, 3.0]))
    assert flat.normals is not None and not flat.has_normals and flat.normal_rows(np.array([0, 1])) is None
    assert "normal" not in json.dumps(formats.field_to_json(plain))


def test_field_csv_takes_a_normal_after_the_diameter():
    field = formats.field_from_csv("id,x,y,z,code,diameter_mm,nx,ny,nz\nC7,0,0,0,7,10\nW1,0,300,50,,6,0,-1,0\n")
    assert field.has_normals and np.allclose(field.normals, [[0, 0, 1], [0, -1, 0]])
    with pytest.raises(FormatError, match="a normal that is not three numbers"):
        formats.field_from_csv("W1,0,300,50,,6,0,-1\n")


@pytest.mark.parametrize("row", ["P1,1,2,3,7.5,6", "P1,1,2,3,7,six", "P1,1,2,inf"])
def test_field_csv_with_a_bad_cell_is_a_format_error(row):
    with pytest.raises(FormatError, match=re.escape("field.csv")):
        formats.field_from_csv(f"id,x,y,z,code,diameter_mm\n{row}\n")


@pytest.mark.parametrize(
    ("value", "needle"),
    [
        ([[1.0, 0.0, 0.0, 1e300], *EYE[1:]], "beyond"),
        ([[1.0, 0.0, 0.0, 10**400], *EYE[1:]], "4x4 matrix of numbers"),
        ([[1.0, 0.0, 0.0, "12.5"], *EYE[1:]], "numbers only"),
        ([[True, 0.0, 0.0, 0.0], *EYE[1:]], "numbers only"),
        ([[1.0, 0.0, 0.0, None], *EYE[1:]], "numbers only"),
        (EYE[:3], "4x4"),
        ("eye", "4x4"),
    ],
)
def test_matrix_refuses_strings_booleans_and_absurd_translations(value, needle):
    with pytest.raises(FormatError, match=needle):
        formats.matrix4_from_json(value, "T_flange_camera")


def test_handeye_refuses_a_nan_anywhere():
    with pytest.raises(FormatError, match=re.escape("handeye.json: note is nan")):
        validate("handeye", {"T_flange_camera": EYE, "T_base_field": EYE, "note": math.nan})


def _rig(**camera1):
    T1 = np.eye(4)
    T1[0, 3] = 250.0
    return {
        "model": "rig",
        "master": 0,
        "cameras": [CAMERA, {**CAMERA, **camera1}],
        "T_master_camera": [EYE, T1.tolist()],
    }


def test_rig_cameras_are_checked_like_a_camera():
    assert validate("rig", _rig()).n_cameras == 2
    with pytest.raises(FormatError, match=re.escape("rig.json: camera 1: K1 must be a number")):
        validate("rig", _rig(K1=[1, 2]))
    with pytest.raises(FormatError, match=re.escape("rig.json: cameras[1].c_mm is inf")):
        validate("rig", _rig(c_mm=math.inf))
    with pytest.raises(FormatError, match=re.escape("rig.json: T_master_camera[1] has a value beyond")):
        validate("rig", {**_rig(), "T_master_camera": [EYE, [[1.0, 0, 0, 1e9], *EYE[1:]]]})


def test_write_json_atomic_refuses_nan_and_leaves_the_old_file(tmp_path):
    path = tmp_path / "runtime.json"
    formats.write_json_atomic(path, {"a": 1.0})
    with pytest.raises(FormatError, match="not standard JSON"):
        formats.write_json_atomic(path, {"a": math.inf})
    assert json.loads(path.read_text()) == {"a": 1.0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runtime.json"]  # no temporary file left


def test_write_json_atomic_syncs_the_file_and_then_its_directory(tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    formats.write_json_atomic(tmp_path / "sub" / "state.json", {"a": 1})
    # the data under its temporary name, then the directory that holds the rename
    assert len(synced) == 2 and synced[1] == str(tmp_path / "sub"), synced
    assert synced[0].startswith(str(tmp_path / "sub" / ".state.json."))


def test_a_refused_upload_stores_nothing(tmp_path):
    store = CalibrationStore(tmp_path / "calibration")
    state = CalibrationState(Settings(state_dir=tmp_path), store, None)
    assert state.update("camera", CAMERA, note="first") == 1
    generation = state.generation
    for data, note in ((_with(CAMERA, ("K1",), math.nan), ""), (CAMERA, "x" * 1001)):
        with pytest.raises(FormatError):
            state.update("camera", data, note=note)
    assert [v["version"] for v in store.versions("camera")] == [1]
    assert state.generation == generation and state.camera == formats.camera_from_json(CAMERA)


def test_a_result_file_says_not_determined_as_null_and_reads_back(tmp_path):
    from service.sim.scene import reference_camera

    cam = reference_camera().to_dict()
    cam["calibration"] = {
        "targets": [{"id": "7", "n_rays": 1, "rms_px": float("nan"), "sigma_mm": [float("nan")] * 3}],
        "sigma0_px": 0.03,
    }
    with pytest.raises(formats.FormatError, match="not standard JSON"):
        formats.write_json_atomic(tmp_path / "bad.json", cam)
    formats.write_json_atomic(tmp_path / "camera.json", formats.null_for_unknown(cam))
    text = (tmp_path / "camera.json").read_text()
    assert "NaN" not in text and '"rms_px": null' in text
    assert formats.read_camera(tmp_path / "camera.json").c_mm == reference_camera().c_mm


def test_a_camera_calibrated_with_the_other_centres_is_warned_of(tmp_path):
    # what a camera.json says its calibration measured the targets' centres as; the service reports
    # a mismatch with what it measures with, and says how to mend it
    said = {**CAMERA, "calibration": {"sigma0_px": 0.014, "centre": "centroid"}}
    assert formats.calibrated_centre(said) == "centroid"
    assert formats.calibrated_centre(CAMERA) is None  # older files, observations given: not said
    assert formats.calibrated_centre({**CAMERA, "calibration": {"centre": "median"}}) is None
    assert formats.centre_mismatch("centroid", "centroid") is None
    assert formats.centre_mismatch(None, "edge") is None
    warning = formats.centre_mismatch("centroid", "edge")
    assert warning is not None and 'centre = "centroid"' in warning and "calibrate the camera again" in warning
    state = CalibrationState(Settings(state_dir=tmp_path), CalibrationStore(tmp_path / "calibration"), None)
    state.update("camera", said)
    assert state.camera_centre == "centroid"
    state.update("camera", CAMERA)
    assert state.camera_centre is None
