"""The worker owns the settings in force: frozen, swapped whole on a change; one mapping of the measure options.

No device is started: a worker of a cell without simulated devices, with stand-in camera channels
where a test needs one.
"""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
from typing import Any

import pytest

from service.cli.main import build_parser
from service.core.targets.codes import AICON14
from service.core.targets.detect import DetectSettings
from service.pipeline.measure import MeasureSettings
from service.runtime import cell_runtime
from service.runtime import processor as processor_module
from service.runtime.acquisition import DeviceState
from service.runtime.processor import CameraProcessor, measure_settings
from service.runtime.worker import Worker
from service.settings import ProcessingConfig, Settings, load_settings


class StandInChannel:
    """A camera channel's face to the worker: its state and the settings requests it answers."""

    def __init__(self, state: DeviceState = DeviceState.ok, error: str = "") -> None:
        self.state, self.error, self.settings, self.requests = state, error, None, []

    def request_settings(self, settings: Any) -> str:
        self.requests.append(settings)
        return self.error


def _real_cell(tmp_path: Any) -> Settings:
    cameras = [{"name": "cam0", "driver": "v4l2"}, {"name": "cam1", "driver": "v4l2"}]
    return load_settings(None, state_dir=str(tmp_path), robot__driver="none", cameras=cameras)


@pytest.fixture
def worker(tmp_path: Any) -> Worker:
    w = Worker(_real_cell(tmp_path))
    for name in ("cam0", "cam1"):
        w.cameras[name] = StandInChannel()
        w.processors[name] = CameraProcessor(name, w.settings, w.calibration)
    return w


def test_a_processing_change_is_a_new_settings_object_and_a_reader_of_the_old_one_sees_the_old_values(worker):
    old = worker.settings
    worker.update_processing(old.processing.model_copy(update={"min_targets": 9}))
    assert worker.settings is not old and worker.settings.processing.min_targets == 9
    assert old.processing.min_targets == 6  # the object a reader holds never changes
    assert all(p.settings is worker.settings for p in worker.processors.values())


def test_a_camera_change_swaps_the_settings_and_a_refused_one_changes_nothing(worker):
    old = worker.settings
    cfg = old.cameras[1].model_copy(update={"exposure_us": 900.0, "transport_latency_s": 0.002})
    assert worker.reconfigure_camera(cfg) == ""
    assert worker.settings.cameras[1].exposure_us == 900.0 and old.cameras[1].exposure_us == 2000.0
    assert worker.processors["cam1"].pairer.camera_latency_ns == pytest.approx(2e6)
    assert worker.cameras["cam1"].requests[-1].exposure_us == 900.0
    applied = worker.settings
    worker.cameras["cam0"].error = "the camera has no line source Bogus"
    refused = old.cameras[0].model_copy(update={"exposure_us": 700.0})
    assert worker.reconfigure_camera(refused) == "the camera has no line source Bogus"
    assert worker.settings is applied


def test_a_camera_that_is_not_connected_gets_its_settings_when_it_connects(worker):
    worker.cameras["cam0"] = StandInChannel(DeviceState.disconnected)
    cfg = worker.settings.cameras[0].model_copy(update={"exposure_us": 800.0})
    assert worker.reconfigure_camera(cfg) == ""
    assert worker.cameras["cam0"].settings.exposure_us == 800.0 and worker.cameras["cam0"].requests == []
    assert worker.settings.cameras[0].exposure_us == 800.0


def test_a_camera_that_failed_to_start_refuses_and_changes_nothing(worker):
    del worker.cameras["cam1"]
    old = worker.settings
    assert "not running" in worker.reconfigure_camera(old.cameras[1].model_copy(update={"exposure_us": 900.0}))
    assert worker.settings is old


@pytest.mark.parametrize("measure_in", ["thread", "process"])
def test_the_processor_rebuilds_its_measurer_when_the_processing_options_are_swapped(worker, monkeypatch, measure_in):
    built: list[MeasureSettings] = []
    # what the processor builds its measurer with, recorded (camera and field are placeholders here)
    monkeypatch.setattr(processor_module, "FrameMeasurer", lambda camera, field, s, defects: built.append(s) or s)
    monkeypatch.setattr(
        processor_module.MeasureProcess, "configure", lambda self, camera, field, s, defects: built.append(s)
    )
    worker.update_processing(worker.settings.processing.model_copy(update={"measure_in": measure_in}))
    worker.calibration.camera, worker.calibration.field = object(), object()
    proc = worker.processors["cam0"]
    proc.warm_up()
    proc.warm_up()  # nothing changed: the same measurer
    worker.update_processing(worker.settings.processing.model_copy(update={"max_sigma0_px": 0.8}))
    proc.warm_up()
    assert [s.max_sigma0_px for s in built] == [0.5, 0.8]
    assert proc.measurement_report()["in"] == measure_in


def test_the_worker_is_built_with_the_simulated_devices_delivery_delays_stated(tmp_path):
    settings = load_settings(None, state_dir=str(tmp_path))
    worker = Worker(settings)
    assert worker.settings.robot.transport_latency_s == cell_runtime.SIM_ROBOT_LATENCY_S
    assert settings.robot.transport_latency_s == 0.0  # what it was given is not changed
    standins = cell_runtime.with_stated_latencies(load_settings(None, sim__transport="standins"))
    assert standins.robot.transport_latency_s == cell_runtime.STANDIN_ROBOT_LATENCY_S
    assert standins.cameras[0].transport_latency_s == cell_runtime.STANDIN_CAMERA_LATENCY_S
    real = _real_cell(tmp_path)
    assert cell_runtime.with_stated_latencies(real) is real


# --- one mapping of the measure options --------------------------------------------------------


def test_the_default_options_give_the_default_measure_settings():
    assert MeasureSettings.from_options() == MeasureSettings()
    assert measure_settings(ProcessingConfig()) == MeasureSettings()


def test_every_option_reaches_the_measure_settings():
    p = ProcessingConfig(
        roi_tracking=False,
        code_family="aicon14",
        min_targets=9,
        min_coded=5,
        sigma_px=0.05,
        max_sigma0_px=0.7,
        correct_eccentricity=False,
        min_contrast_dn=30.0,
        min_area_px=12,
        max_area_px=900,
    )
    assert measure_settings(p) == MeasureSettings(
        detect=DetectSettings(min_contrast_dn=30.0, min_area_px=12, max_area_px=900),
        min_coded=5,
        min_targets=9,
        sigma_px=0.05,
        correct_eccentricity=False,
        roi=False,
        max_sigma0_px=0.7,
        code_family=AICON14,
    )


def test_the_options_are_the_processing_sections_knobs_by_name():
    # range_mm is the calibration's; bit_depth the camera's (the pixel format its driver reports)
    options = set(inspect.signature(MeasureSettings.from_options).parameters) - {"range_mm", "bit_depth"}
    # the section's other knobs say how the service runs the measurement, not how a frame is measured
    assert options == set(ProcessingConfig.model_fields) - {
        "rig_sync_tolerance_s",
        "measure_in",
        "direct_hand_over",
        "measure_cpus",
    }


@pytest.mark.parametrize(
    "argv",
    [
        ["measure", "--camera", "c.json", "--field", "f.json", "x.png"],
        ["calibrate", "camera", "--field", "f.json", "-o", "c.json", "x.png"],
        ["calibrate", "rig", "--field", "f.json", "--camera", "a.json", "b.json", "-o", "r.json"],
    ],
)
def test_the_command_lines_detector_options_are_the_processing_sections_with_its_defaults(argv):
    args = vars(build_parser().parse_args(argv))
    processing = ProcessingConfig()
    for name in ("code_family", "min_contrast_dn", "min_area_px", "max_area_px"):
        assert args[name] == getattr(processing, name), name
    if argv[0] == "measure":
        for name in ("sigma_px", "max_sigma0_px"):
            assert args[name] in (None, getattr(processing, name)), name


def test_the_processor_warm_up_loads_the_compiled_calls_this_process_makes_whichever_process_measures(tmp_path):
    # in a fresh interpreter: in this one another test may have loaded them already. Loaded at their
    # first call instead, the pairing's and the flange's kernels cost the first frame ~50-330 ms
    code = f"""
from service.core._kernels import geometry_kernels as g
from service.runtime.processor import CameraProcessor
from service.runtime.worker import Worker
from service.settings import load_settings
settings = load_settings(None, state_dir={str(tmp_path)!r}, robot__driver="none", cameras=[{{"driver": "v4l2"}}])
w = Worker(settings)
before = [len(k.signatures) for k in (g.pose_at_kernel, g.flange_kernel)]
CameraProcessor("cam0", w.settings, w.calibration).warm_up()
print(before, [len(k.signatures) for k in (g.pose_at_kernel, g.flange_kernel)])
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    before, after = (json.loads(part) for part in out.stdout.strip().replace("] [", "]|[").split("|"))
    assert before == [0, 0] and min(after) >= 1, out.stdout


def test_the_processor_reports_a_camera_calibrated_with_the_other_centres(worker, monkeypatch, caplog):
    monkeypatch.setattr(processor_module, "FrameMeasurer", lambda camera, field, s, defects: s)
    worker.update_processing(worker.settings.processing.model_copy(update={"measure_in": "thread"}))
    worker.calibration.camera, worker.calibration.field = object(), object()
    worker.calibration.camera_centre = "centroid"  # what the camera's calibration.centre said
    worker.calibration.generation += 1
    proc = worker.processors["cam0"]
    with caplog.at_level("WARNING"):
        proc.warm_up()
    report = proc.measurement_report()
    assert report["centre"] == "edge" and report["camera_calibrated_with"] == "centroid"
    assert 'centre = "centroid"' in report["warning"] and "cam0" in caplog.text
    worker.update_processing(worker.settings.processing.model_copy(update={"centre": "centroid"}))
    proc.warm_up()
    assert proc.measurement_report()["warning"] is None
