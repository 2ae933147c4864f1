"""``posecell calibrate camera`` and ``posecell calibrate rig``: files in, files out, clear failures.

In-process (``cli.main``): a new process would spend its first seconds compiling the detector.
The images form runs on rendered images of the reference plate (service.sim) and, when
../shared/data is present, on MicMac's real Circ-Code-Target panel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cli import main as cli
from service.core.calib.rig import rig_from_dict
from service.core.geometry.camera_model import PARAMETER_NAMES, BrownFraser
from service.sim import scene
from service.sim.render import RenderSettings, render_frame
from service.store import formats
from tests.conftest import shared_data
from tests.core.test_bundle import NOISE_PX, TRUE_CAMERA, convergent_poses, field_3d, observe
from tests.core.test_rig import SECOND_CAMERA, T_MASTER_CAMERA1, rig_images

#: (view angle from the plate deg, roll deg, azimuth deg): convergent views from all sides, rolled
VIEWS = [
    (55, 0, 0),
    (55, 90, 40),
    (60, 180, 80),
    (50, 270, 120),
    (55, 0, 160),
    (60, 90, 200),
    (55, 180, 240),
    (50, 270, 280),
    (58, 45, 320),
    (52, 135, 20),
]


def write_observations(path, images) -> None:
    formats.write_json_atomic(
        path,
        formats.image_observations_to_json([formats.ImageObservations(im.name, list(im.ids), im.uv) for im in images]),
    )


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Ten rendered images of the reference plate, its field.json and a nominal start camera."""
    d = tmp_path_factory.mktemp("plate")
    rng = np.random.default_rng(31)
    plate = scene.reference_field()
    for k, (angle, roll, azimuth) in enumerate(VIEWS):
        T = scene.reference_pose(angle, 1150.0, roll, azimuth)
        formats.write_image(
            d / "images" / f"view{k:02d}.png", render_frame(TRUE_CAMERA, plate, T, RenderSettings(), rng).image
        )
    formats.write_field(d / "field.json", plate)
    formats.write_camera(
        d / "start.json", BrownFraser(TRUE_CAMERA.width, TRUE_CAMERA.height, TRUE_CAMERA.pixel_size_mm, 12.3)
    )
    return d


def test_calibrate_camera_from_images_writes_a_camera_the_pipeline_reads(rendered, capsys):
    out, refined = rendered / "camera.json", rendered / "refined.json"
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(rendered / "field.json"),
            "--camera",
            str(rendered / "start.json"),
            "-o",
            str(out),
            "--field-out",
            str(refined),
            str(rendered / "images"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "measuring [" in captured.err and "adjusting 10 images" in captured.err  # the progress
    line = json.loads(captured.out)
    assert line["ok"] and line["n_images"] == 10
    camera = formats.read_camera(out)  # the pipeline's reader
    data = json.loads(out.read_text())
    for name in PARAMETER_NAMES:  # every parameter within 3 sigma of the renderer's camera
        assert abs(getattr(camera, name) - getattr(TRUE_CAMERA, name)) < 3 * data["sigma"][name], name
    cal = data["calibration"]
    assert 0.005 < cal["sigma0_px"] < 0.05  # rendered blur and noise: a few hundredths of a pixel
    assert len(cal["images"]) == 10 and all(0.005 < im["rms_px"] < 0.06 for im in cal["images"])
    assert len(cal["correlation"]["matrix"]) == 10 and cal["free"] == list(PARAMETER_NAMES)
    assert {"rejected", "targets", "warnings", "datum", "redundancy"} <= set(cal)
    field = formats.read_field(refined)
    targets = json.loads(refined.read_text())["targets"]
    assert len(field) == 230 and all(len(t["sigma_mm"]) == 3 and t["n_rays"] >= 2 for t in targets)


def test_calibrate_camera_from_observations_with_fixed_parameters(tmp_path, capsys, rng):
    field = field_3d(rng)
    formats.write_field(tmp_path / "field.json", field)
    write_observations(tmp_path / "obs.json", observe(rng, field, convergent_poses(rng, 12)))
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(tmp_path / "field.json"),
            "--observations",
            str(tmp_path / "obs.json"),
            "--c-mm",
            "12.3",
            "--pixel-size-mm",
            "0.0067",
            "--image-size",
            "1300x1030",
            "--fix",
            "K3,B1,B2",
            "--sigma-px",
            str(NOISE_PX),
            "-q",
            "-o",
            str(tmp_path / "camera.json"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert all("warning:" in line for line in captured.err.splitlines())  # -q: no progress, warnings only
    data = json.loads((tmp_path / "camera.json").read_text())
    assert data["K3"] == data["B1"] == data["B2"] == 0.0 and data["sigma"]["K3"] == 0.0
    assert data["calibration"]["fixed"] == ["K3", "B1", "B2"]
    assert 0.7 * NOISE_PX < data["calibration"]["sigma0_px"] < 1.5 * NOISE_PX  # K3, B1, B2 missing: a bit more


def test_too_few_images_fail_with_one_sentence_and_the_advice(tmp_path, capsys, rng):
    field = field_3d(rng)
    formats.write_field(tmp_path / "field.json", field)
    write_observations(tmp_path / "obs.json", observe(rng, field, convergent_poses(rng, 2)))
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(tmp_path / "field.json"),
            "--observations",
            str(tmp_path / "obs.json"),
            "--camera",
            str(_camera_file(tmp_path)),
            "-o",
            str(tmp_path / "camera.json"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 1
    err = [line for line in captured.err.splitlines() if line.startswith("posecell calibrate camera:")]
    assert len(err) == 1 and "at least 3" in err[0] and "rolled by 90" in err[0]
    assert json.loads(captured.out)["reason"] == "degenerate_geometry"
    assert not (tmp_path / "camera.json").exists()


def test_images_parallel_to_the_plate_fail_with_the_reason(tmp_path, capsys, rng):
    plate = scene.reference_field()
    poses = [scene.reference_pose(90.0, 1000.0 + 40 * k, 90.0 * k, 0.0, (25.0 * k, 0, 0)) for k in range(6)]
    formats.write_field(tmp_path / "field.json", plate)
    write_observations(tmp_path / "obs.json", observe(rng, plate, poses))
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(tmp_path / "field.json"),
            "--observations",
            str(tmp_path / "obs.json"),
            "--camera",
            str(_camera_file(tmp_path)),
            "-q",
            "-o",
            str(tmp_path / "camera.json"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 1 and "head-on" in captured.err and "convergent" in captured.err


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--fix", "K9"], "unknown camera parameter"),
        (["--scale-bar", "T1,T2"], "scale bar"),
        (["--image-size", "1300"], "WIDTHxHEIGHT"),
        (["--camera", "missing.json"], "no such file"),
    ],
)
def test_bad_options_exit_2_with_one_sentence(tmp_path, capsys, rng, extra, words):
    field = field_3d(rng, 20)
    formats.write_field(tmp_path / "field.json", field)
    write_observations(tmp_path / "obs.json", observe(rng, field, convergent_poses(rng, 4)))
    args = [
        "calibrate",
        "camera",
        "--field",
        str(tmp_path / "field.json"),
        "--observations",
        str(tmp_path / "obs.json"),
        "-q",
        "-o",
        str(tmp_path / "c.json"),
    ]
    if "--camera" not in extra:
        args += ["--c-mm", "12", "--pixel-size-mm", "0.0067", "--image-size", "1300x1030"]
    code = cli.main(args + extra)
    captured = capsys.readouterr()
    assert code == 2 and words in captured.err and "Traceback" not in captured.err


def test_malformed_observations_file_exits_2(tmp_path, capsys, rng):
    formats.write_field(tmp_path / "field.json", field_3d(rng, 10))
    (tmp_path / "obs.json").write_text('{"images": [{"name": "a", "points": [{"id": "T1"}]}]}')
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(tmp_path / "field.json"),
            "--observations",
            str(tmp_path / "obs.json"),
            "--camera",
            str(_camera_file(tmp_path)),
            "-o",
            str(tmp_path / "c.json"),
        ]
    )
    assert code == 2 and "point #0" in capsys.readouterr().err


def test_calibrate_rig_from_observations_writes_a_rig(tmp_path, capsys, rng):
    field = field_3d(rng, 150)
    cams = (TRUE_CAMERA, SECOND_CAMERA)
    images = rig_images(rng, field, convergent_poses(rng, 6), cams, (np.eye(4), T_MASTER_CAMERA1))
    formats.write_field(tmp_path / "field.json", field)
    formats.write_json_atomic(
        tmp_path / "obs.json",
        formats.image_observations_to_json(
            [formats.ImageObservations(im.name, list(im.ids), im.uv, im.camera, im.epoch) for im in images]
        ),
    )
    for k, cam in enumerate(cams):
        formats.write_camera(tmp_path / f"cam{k}.json", cam)
    code = cli.main(
        [
            "calibrate",
            "rig",
            "--field",
            str(tmp_path / "field.json"),
            "--camera",
            str(tmp_path / "cam0.json"),
            str(tmp_path / "cam1.json"),
            "--observations",
            str(tmp_path / "obs.json"),
            "--sigma-px",
            str(NOISE_PX),
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    rig = rig_from_dict(json.loads((tmp_path / "rig.json").read_text()))
    sig = np.array(json.loads(captured.out)["sigma_position_mm"][1])
    assert np.all(np.abs(rig.T_master_camera[1][:3, 3] - T_MASTER_CAMERA1[:3, 3]) < 4 * sig)


def test_calibrate_rig_from_image_folders(tmp_path, capsys):
    rng = np.random.default_rng(8)
    plate = scene.reference_field()
    T_master = (np.eye(4), _side_by_side())
    for e, (angle, roll, azimuth) in enumerate(VIEWS[:5]):
        T_field_rig = scene.reference_pose(angle, 1150.0, roll, azimuth, (-60.0, 0.0, 0.0))
        for k in range(2):
            image = render_frame(TRUE_CAMERA, plate, T_field_rig @ T_master[k], RenderSettings(), rng).image
            formats.write_image(tmp_path / f"cam{k}" / f"shot{e}.png", image)
    formats.write_field(tmp_path / "field.json", plate)
    formats.write_camera(tmp_path / "cam.json", TRUE_CAMERA)
    code = cli.main(
        [
            "calibrate",
            "rig",
            "--field",
            str(tmp_path / "field.json"),
            "--camera",
            str(tmp_path / "cam.json"),
            str(tmp_path / "cam.json"),
            "--images",
            str(tmp_path / "cam0"),
            str(tmp_path / "cam1"),
            "-o",
            str(tmp_path / "rig.json"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    out = json.loads(captured.out)
    assert out["n_epochs"] == 5
    T = np.array(out["T_master_camera"][1])
    assert np.linalg.norm(T[:3, 3] - T_master[1][:3, 3]) < 0.5  # mm, over a 120 mm baseline


def _side_by_side() -> np.ndarray:
    """Camera 1 120 mm to the right of camera 0, turned 5 deg towards it."""
    from scipy.spatial.transform import Rotation

    from service.core.geometry.frames import make_T

    return make_T(Rotation.from_euler("y", -5.0, degrees=True).as_matrix(), [120.0, 0.0, 0.0])


def _camera_file(tmp_path: Path) -> Path:
    path = tmp_path / "start.json"
    formats.write_camera(path, BrownFraser(TRUE_CAMERA.width, TRUE_CAMERA.height, TRUE_CAMERA.pixel_size_mm, 12.3))
    return path


# -- the real panel ------------------------------------------------------------------------------

PANEL = "micmac-circ-code-target"


def test_real_panel_camera_self_calibrates_to_hundredths_of_a_pixel(tmp_path, capsys):
    # MicMac's 20 flash-lit images of the AICON panel (73 coded + 166 uncoded targets, a raised
    # block): a free network on the panel's AICON coordinates, c and the distortion from scratch.
    data = shared_data(PANEL)
    pixel_mm = 23.5 / 6000 * 3  # Nikon D5600, images scaled down 3x
    out, refined = tmp_path / "camera.json", tmp_path / "panel.json"
    code = cli.main(
        [
            "calibrate",
            "camera",
            "--field",
            str(data / "Positions-3D-14bit_lookup.txt"),
            "--c-mm",
            "24",
            "--pixel-size-mm",
            str(pixel_mm),
            "--code-family",
            "aicon14",
            "--min-contrast-dn",
            "40",
            "--min-area-px",
            "20",
            "--max-area-px",
            "1000",
            "-o",
            str(out),
            "--field-out",
            str(refined),
            str(data / "images"),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    cal = json.loads(out.read_text())
    c = cal["calibration"]
    assert len(c["images"]) == 20  # 043_0031, which MicMac rejected, too
    assert c["centre"] == "edge"  # what the measurement with this camera should use too
    # edge centres (the default): sigma0 0.014 px, each image 0.012-0.017 (intensity centroids 0.029)
    assert 0.008 < c["sigma0_px"] < 0.025
    assert all(0.008 < im["rms_px"] < 0.025 for im in c["images"]), [im["rms_px"] for im in c["images"]]
    assert c["n_observations"] > 3000 and c["n_rejected"] < 0.03 * c["n_observations"]
    assert 24.0 < cal["c_mm"] < 25.5 and cal["sigma"]["c_mm"] < 0.01  # the 24 mm lens focused at ~1 m
    assert 0.5e-4 < cal["K1"] < 5e-4
    targets = json.loads(refined.read_text())["targets"]
    assert len(targets) == 239  # every target of the panel file, unobserved ones as they were
    sig = np.array([t["sigma_mm"] for t in targets if t["n_rays"] > 0])
    assert len(sig) >= 230 and np.median(sig) < 0.02  # the panel surveyed to about 10 micrometres
