"""CalibrationStore on a real directory: versions, rollback, interrupted writes, refused input."""

from __future__ import annotations

import hashlib
import json
import os
import threading

import pytest

from service.store import calibrations as calibstore
from service.store.calibrations import CalibrationError, CalibrationKind, CalibrationMissing, CalibrationStore


def camera(c_mm: float) -> dict:
    return {
        "model": "brown-fraser",
        "width": 1300,
        "height": 1030,
        "pixel_size_mm": [0.0067, 0.0067],
        "c_mm": c_mm,
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


@pytest.fixture
def store(tmp_path):
    return CalibrationStore(tmp_path / "calib")


def test_put_makes_a_new_current_version_and_keeps_the_previous(store):
    assert store.put("camera", camera(12.0), note="factory") == 1
    assert store.put(CalibrationKind.camera, camera(12.05), note="recalibrated") == 2
    assert store.get("camera") == camera(12.05)
    assert store.get("camera", version=1) == camera(12.0)
    assert json.loads((store.directory / "camera.json").read_text()) == camera(12.05)
    assert json.loads((store.directory / "history" / "camera.v1.json").read_text()) == camera(12.0)


def test_versions_list_time_note_checksum_and_which_is_current(store):
    store.put("field", {"name": "A", "targets": []}, note="first")
    store.put("field", {"name": "B", "targets": []})
    v = store.versions("field")
    assert [e["version"] for e in v] == [1, 2]
    assert [e["current"] for e in v] == [False, True]
    assert v[0]["note"] == "first" and v[0]["t_wall"].endswith("Z")
    assert v[1]["sha256"] == hashlib.sha256((store.directory / "field.json").read_bytes()).hexdigest()
    assert store.versions("handeye") == [] and store.current_version("handeye") is None


def test_rollback_makes_an_old_version_current_as_a_new_version(store):
    for c in (12.0, 12.1, 12.2):
        store.put("camera", camera(c))
    assert store.rollback("camera", 1) == 4
    assert store.get("camera") == camera(12.0)
    v = store.versions("camera")
    assert [e["current"] for e in v] == [False, False, False, True]
    assert v[-1]["note"] == "rollback to version 1" and v[-1]["sha256"] == v[0]["sha256"]
    assert store.current_version("camera") == 4
    with pytest.raises(CalibrationMissing, match="version 9 does not exist"):
        store.rollback("camera", 9)


def test_a_stray_temp_file_from_a_crash_before_the_rename_does_not_affect_get(tmp_path):
    store = CalibrationStore(tmp_path / "calib")
    store.put("camera", camera(12.0))
    # what a crash between writing the temp file and os.replace leaves behind
    stray = store.directory / ".camera.json.k3j9x1.tmp"
    stray.write_text('{"model": "brown-fraser", "c_mm": 99')
    assert store.get("camera") == camera(12.0)
    assert store.kinds_present() == ["camera"]

    reopened = CalibrationStore(tmp_path / "calib")  # a restart cleans up
    assert not stray.exists()
    assert reopened.get("camera") == camera(12.0)
    assert reopened.put("camera", camera(12.1)) == 2


def test_a_failed_rename_leaves_the_previous_version_current(store, monkeypatch):
    store.put("camera", camera(12.0))
    real_replace = os.replace

    def crash_on_current(src, dst):
        if str(dst).endswith(os.sep + "camera.json"):
            raise OSError(5, "Input/output error")
        real_replace(src, dst)

    monkeypatch.setattr(calibstore.os, "replace", crash_on_current)
    with pytest.raises(OSError):
        store.put("camera", camera(13.0))
    monkeypatch.setattr(calibstore.os, "replace", real_replace)

    assert store.get("camera") == camera(12.0)
    assert store.current_version("camera") == 1
    assert not list(store.directory.glob(".*.tmp"))  # the temp file was removed
    assert store.put("camera", camera(12.5)) == 3  # the half-done version's number is not reused
    assert store.get("camera") == camera(12.5)


def test_unknown_kind_and_non_integer_versions_are_refused_before_any_path_is_built(store):
    store.put("camera", camera(12.0))
    for kind in ("../camera", "camera/../../etc/passwd", "Camera", "lens", ""):
        with pytest.raises(CalibrationError, match="unknown calibration kind"):
            store.put(kind, camera(12.0))
        with pytest.raises(CalibrationError, match="unknown calibration kind"):
            store.get(kind)
    for version in ("1", "../1", 0, -1, True, 1.0):
        with pytest.raises(CalibrationError, match="positive integer"):
            store.get("camera", version=version)
    assert sorted(p.name for p in store.directory.iterdir()) == [".lock", "camera.json", "history"]


def test_missing_calibration_is_a_key_error_with_a_clear_sentence(store):
    with pytest.raises(KeyError) as e:
        store.get("handeye")
    assert isinstance(e.value, CalibrationMissing)
    assert str(e.value).startswith("no handeye calibration is stored yet")
    store.put("handeye", {"X": [], "Z": []})
    with pytest.raises(CalibrationMissing, match=r"version 3 does not exist \(stored: 1\)"):
        store.get("handeye", version=3)


def test_payloads_that_are_not_json_objects_are_refused(store):
    for bad in ([1, 2, 3], "camera", {"c_mm": float("nan")}, {"c_mm": object()}):
        with pytest.raises(CalibrationError):
            store.put("camera", bad)
    with pytest.raises(CalibrationError, match="note"):
        store.put("camera", camera(12.0), note="x" * 2000)
    assert store.kinds_present() == []


def test_a_history_file_changed_after_storing_is_detected(store):
    store.put("rig", {"cameras": ["a", "b"]})
    store.put("rig", {"cameras": ["a", "c"]})
    (store.directory / "history" / "rig.v1.json").write_text('{"cameras": ["x"]}\n')
    with pytest.raises(CalibrationError, match="sha256"):
        store.get("rig", version=1)
    assert store.get("rig", version=2) == {"cameras": ["a", "c"]}


def test_concurrent_puts_get_distinct_versions(store):
    got: list[int] = []
    lock = threading.Lock()

    def writer(w: int) -> None:
        for i in range(5):
            v = store.put("field", {"name": f"w{w}-{i}", "targets": []})
            with lock:
                got.append(v)

    threads = [threading.Thread(target=writer, args=(w,)) for w in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
    assert sorted(got) == list(range(1, 21))
    current = store.get("field")["name"]
    assert store.get("field", version=store.current_version("field"))["name"] == current
    assert [e["version"] for e in store.versions("field")] == list(range(1, 21))


def test_kinds_present_lists_stored_kinds_in_enum_order(store):
    store.put("rig", {})
    store.put("camera", camera(12.0))
    assert store.kinds_present() == ["camera", "rig"]
