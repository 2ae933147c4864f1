"""Frames of more than 8 bits: a 12-bit camera's values end at 4095 in their uint16.

The detector's levels (``min_contrast_dn`` in 8-bit DN) scale with the saturation level, which was
the dtype's maximum: a Mono12 frame (GenICam: unpacked, the low 12 bits; Aravis delivers it so, and
the simulated camera renders it so) was judged against 65535, its targets 16 times too faint, and
gave no pose with the default settings. The saturation level now comes from the frames' bit depth:
in the service from the pixel format the camera's driver reports, in ``posecell measure`` and
``posecell calibrate`` from ``--bit-depth``. (The real panel's images as 12-bit frames: the
degradations test of ``tests/test_real_panel.py``.)
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.cli import main as cli
from service.core.results import PoseResult
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose
from service.store import formats
from tests.api.conftest import live_settings, run_server


def _frame(bits: int) -> np.ndarray:
    s = RenderSettings(bit_depth=bits, exposure_scale=0.8)
    return render_frame(reference_camera(), reference_field(), reference_pose(), s, np.random.default_rng(0)).image


def test_the_bit_depth_sets_the_saturation_level():
    assert MeasureSettings.from_options().detect.saturation_dn is None  # the dtype's maximum
    assert MeasureSettings.from_options(bit_depth=12).detect.saturation_dn == 4095.0
    for bad in (7, 17):
        with pytest.raises(ValueError, match="bit_depth"):
            MeasureSettings.from_options(bit_depth=bad)


@pytest.mark.parametrize("bits", [8, 10, 12, 16])
def test_frames_of_every_depth_are_measured_given_their_depth(bits):
    image = _frame(bits)
    assert image.max() < 2**bits
    result = FrameMeasurer(reference_camera(), reference_field(), MeasureSettings.from_options(bit_depth=bits))
    pose = result.measure(image).result
    assert isinstance(pose, PoseResult) and pose.n_coded == 30 and pose.n_uncoded == 200, pose
    if bits in (10, 12):  # against the dtype's 65535 the targets are too faint: why the depth is needed
        assert not FrameMeasurer(reference_camera(), reference_field()).measure(image).result.ok


def test_measure_verb_reads_12_bit_images_with_their_bit_depth(tmp_path, capsys):
    formats.write_camera(tmp_path / "camera.json", reference_camera())
    field = tmp_path / "field.json"
    field.write_text(json.dumps(formats.field_to_json(reference_field())))
    formats.write_image(tmp_path / "f.png", _frame(12))
    args = ["measure", "--camera", str(tmp_path / "camera.json"), "--field", str(field)]
    assert cli.main([*args, "--bit-depth", "12", str(tmp_path / "f.png")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] and out["n_coded"] == 30, out
    assert cli.main([*args, str(tmp_path / "f.png")]) == 1  # read as a 16-bit image: too faint
    capsys.readouterr()


def test_the_service_follows_the_pixel_format_its_camera_reports(tmp_path):
    settings = live_settings(tmp_path, cameras=[{"frame_rate_hz": 15.0, "pixel_format": "Mono16"}])
    for server in run_server(settings):
        server.wait_for(lambda h: h["processing"]["ok"] >= 5, 120.0, "poses from the Mono16 camera")
        with server.client() as c:  # at run time: the measurement is set up again for 12 bits
            assert c.put("/config", json={"cameras": {"cam0": {"pixel_format": "Mono12"}}}).status_code == 200
            before = c.get("/health").json()["processing"]
        after = server.wait_for(
            lambda h: h["processing"]["ok"] >= before["ok"] + 10, 60.0, "poses from the Mono12 camera"
        )["processing"]
        assert after["failed"] - before["failed"] <= 2, (before, after)  # a frame or two of the change
        assert after["measurement"]["cam0"]["bit_depth"] == 12
        with server.client() as c:
            assert c.get("/health").json()["cameras"]["cam0"]["pixel_format"] == "Mono12"
