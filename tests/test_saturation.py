"""Overexposed frames: targets whose flat tops clip at the saturation level.

Retro-reflective targets under a ring light clip at the first generous exposure. Every disk with
more than two pixels at full scale was rejected as saturated, so an overexposed frame gave no pose
at all (2.6 times the exposure: 0 of 230 targets; a 2 % overexposure of the independent sheet lost
107 of 246). Clipping flattens a symmetric plateau symmetrically, so the centre holds: such disks are
now measured, counted as saturated (the exposure control, the output, ``/health``) and rejected only
when asked (``max_saturated_px``, for a sensor whose charge blooms).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from pydantic import ValidationError

from service.bench.speed import frames_along_path
from service.cli import main as cli
from service.core.geometry.frames import pose_difference
from service.core.results import Failure, PoseResult
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.settings import ProcessingConfig
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose
from service.store import formats

OVER = RenderSettings(exposure_scale=2.6)  # the reference scene's disks peak at ~2.6 x full scale


def _overexposed(seed: int = 0):  # type: ignore[no-untyped-def]
    T = reference_pose(view_angle_deg=70.0, distance_mm=1000.0)
    return render_frame(reference_camera(), reference_field(), T, OVER, np.random.default_rng(seed))


def test_an_overexposed_frame_is_measured_as_well_as_a_good_one():
    frame = _overexposed()
    assert np.mean(frame.image[frame.image > 128] == 255) > 0.5  # most target pixels clip
    outcome = FrameMeasurer(reference_camera(), reference_field()).measure(frame.image)
    pose = outcome.result
    assert isinstance(pose, PoseResult), pose
    assert pose.n_coded == 30 and pose.n_uncoded >= 195
    d_mm, d_deg = pose_difference(pose.T_field_camera, frame.T_field_camera)
    assert d_mm < 0.05 and d_deg < 0.005 and pose.sigma0_px < 0.5
    truth = dict(zip(frame.ids, frame.uv_true, strict=True))
    err = np.array([np.subtract(t.uv, truth[t.id]) for t in pose.targets])
    assert np.sqrt(np.mean(err**2)) < 0.05  # px
    b = outcome.brightness
    assert b is not None and b.n_saturated >= 200 and "shorten the exposure" in b.saturation_note


def test_rejecting_saturated_targets_when_asked_says_why_the_frame_failed():
    strict = MeasureSettings.from_options(max_saturated_px=2)
    outcome = FrameMeasurer(reference_camera(), reference_field(), strict).measure(_overexposed().image)
    assert isinstance(outcome.result, Failure)
    assert outcome.rejections is not None and outcome.rejections["saturated"] >= 200
    assert "saturated at 255 DN: shorten the exposure" in outcome.result.message


def test_roi_tracking_holds_the_clipped_targets():
    # a saturated ROI window was "not found": tracking lost every clipped target and fell back
    frames = frames_along_path(12, seed=3, settings=OVER)
    tracker = FrameMeasurer(reference_camera(), reference_field())
    outcomes = [tracker.measure(f.image, t_s=0.004 * k) for k, f in enumerate(frames)]
    assert [o.mode for o in outcomes[1:]] == ["roi"] * 11
    for frame, o in zip(frames[1:], outcomes[1:], strict=True):
        assert isinstance(o.result, PoseResult) and len(o.result.targets) >= 220
        assert pose_difference(o.result.T_field_camera, frame.T_field_camera)[0] < 0.05
        assert o.brightness is not None and o.brightness.n_saturated >= 150


def test_measure_verb_counts_the_saturated_targets(tmp_path, capsys):
    formats.write_camera(tmp_path / "camera.json", reference_camera())
    field = tmp_path / "field.json"
    field.write_text(json.dumps(formats.field_to_json(reference_field())))
    formats.write_image(tmp_path / "over.png", _overexposed().image)
    args = ["measure", "--camera", str(tmp_path / "camera.json"), "--field", str(field), str(tmp_path / "over.png")]
    assert cli.main(args) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["ok"] and out["targets_saturated"] >= 200
    assert "targets saturated at 255 DN" in captured.err
    assert cli.main([*args[:-1], "--max-saturated-px", "2", args[-1]]) != 0
    out = json.loads(capsys.readouterr().out)
    assert not out["ok"] and "saturated" in out["message"]


def test_the_service_option_is_checked():
    assert ProcessingConfig().max_saturated_px is None
    assert ProcessingConfig(max_saturated_px=0).max_saturated_px == 0
    with pytest.raises(ValidationError, match="max_saturated_px"):
        ProcessingConfig(max_saturated_px=-1)
    with pytest.raises(ValueError, match="max_saturated_px"):
        MeasureSettings.from_options(max_saturated_px=-3)
