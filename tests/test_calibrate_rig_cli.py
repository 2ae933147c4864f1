"""``posecell calibrate rig``: which images were exposed together, never guessed.

Pairing by file name, by the frame number in the names, by timestamps (``timestamps.csv`` in each
camera folder) or by an explicit pairs file; an image without a partner or an ambiguous pair is
refused with one sentence and exit code 2 (``--drop-unpaired`` leaves such images out, and says so).
Refusals happen before an image is read, so most tests here use empty placeholder files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cli import main as cli
from service.sim import scene
from service.sim.render import RenderSettings, render_frame
from service.store import formats
from service.workflows.calibrate_rig import _rig_shots, pair_epochs
from tests.core.test_bundle import NOISE_PX, TRUE_CAMERA, convergent_poses, field_3d
from tests.core.test_rig import SECOND_CAMERA, T_MASTER_CAMERA1, rig_images


def touch(folder: Path, *names: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")
    return folder


def frames(prefix: str, numbers) -> list[str]:
    return [f"{prefix}_{n:04d}.png" for n in numbers]


def epochs_of(shots) -> list[list[str]]:
    return [[p.name for p in paths] for _, paths in shots]


# -- the pairing rules ---------------------------------------------------------------------------


def test_a_missing_frame_is_refused_not_paired_by_sorted_order(tmp_path):
    # camera 1 missed frame 3 and took a sixth: same count, so sorted order would shift epochs 3-5
    d0 = touch(tmp_path / "cam0", *frames("cam0", [1, 2, 3, 4, 5]))
    d1 = touch(tmp_path / "cam1", *frames("cam1", [1, 2, 4, 5, 6]))
    with pytest.raises(ValueError, match=r"2 images without a partner \(cam0/cam0_0003.png, cam1/cam1_0006.png\)"):
        _rig_shots([str(d0), str(d1)])


def test_names_that_pair_neither_by_name_nor_by_frame_number_are_refused(tmp_path):
    d0 = touch(tmp_path / "left", "left_a.png", "left_b.png", "left_c.png")
    d1 = touch(tmp_path / "right", "right_x.png", "right_y.png", "right_z.png")
    with pytest.raises(ValueError, match="pair neither by file name nor by frame number"):
        _rig_shots([str(d0), str(d1)])


def test_two_images_of_one_frame_in_a_camera_are_refused(tmp_path):
    d0 = touch(tmp_path / "cam0", "cam0_12.png", "cam0_0012.tif", "cam0_13.png")
    d1 = touch(tmp_path / "cam1", *frames("cam1", [12, 13]))
    with pytest.raises(ValueError, match="camera 0 has two images of frame 12"):
        _rig_shots([str(d0), str(d1)], pair_by="frame")


def test_a_missing_frame_is_left_out_when_asked_and_the_rest_pairs_by_number(tmp_path):
    d0 = touch(tmp_path / "cam0", *frames("cam0", [1, 2, 3, 4, 5]))
    d1 = touch(tmp_path / "cam1", *frames("cam1", [1, 2, 4, 5, 6]))
    shots, left_out, _ = _rig_shots([str(d0), str(d1)], drop_unpaired=True)
    assert epochs_of(shots) == [[f"cam0_{n:04d}.png", f"cam1_{n:04d}.png"] for n in (1, 2, 4, 5)]
    assert [p.name for p in left_out] == ["cam0_0003.png", "cam1_0006.png"]


def test_frame_number_is_the_number_that_varies_in_the_names():
    names = [[f"rig2_cam0_{n:05d}_raw.png" for n in (7, 8, 9)], [f"rig2_cam1_{n}_raw.png" for n in (9, 8, 7)]]
    epochs, unpaired, by = pair_epochs(names, "auto")
    assert epochs == [[0, 2], [1, 1], [2, 0]] and unpaired == [] and by == "frame"
    with pytest.raises(ValueError, match="which number"):
        pair_epochs([["a1_1.png"], ["a1_1.png"]], "frame")  # one image, two numbers: which one?


def test_same_names_pair_by_name(tmp_path):
    d0 = touch(tmp_path / "cam0", "shot_b.png", "shot_a.png")
    d1 = touch(tmp_path / "cam1", "shot_a.png", "shot_b.png")
    shots, left_out, _ = _rig_shots([str(d0), str(d1)])
    assert epochs_of(shots) == [["shot_a.png", "shot_a.png"], ["shot_b.png", "shot_b.png"]] and left_out == []


def write_timestamps(folder: Path, stamps: dict[str, float]) -> None:
    (folder / "timestamps.csv").write_text("name,t_s\n" + "".join(f"{n},{t!r}\n" for n, t in stamps.items()))


def test_pairing_by_time_within_the_tolerance(tmp_path):
    # 10 Hz; camera 1's clock 1.3 ms behind and its frame at 0.3 s lost
    d0 = touch(tmp_path / "a", *(f"img{k}.png" for k in range(5)))
    d1 = touch(tmp_path / "b", *(f"other{k}.png" for k in range(4)))
    write_timestamps(d0, {f"img{k}.png": 100.0 + 0.1 * k for k in range(5)})
    write_timestamps(d1, {f"other{k}.png": 100.0013 + 0.1 * t for k, t in enumerate((0, 1, 2, 4))})
    with pytest.raises(ValueError, match=r"without a partner \(a/img3.png\)"):
        _rig_shots([str(d0), str(d1)], pair_by="time")
    shots, left_out, _ = _rig_shots([str(d0), str(d1)], pair_by="time", drop_unpaired=True)
    assert epochs_of(shots) == [
        ["img0.png", "other0.png"],
        ["img1.png", "other1.png"],
        ["img2.png", "other2.png"],
        ["img4.png", "other3.png"],
    ]
    assert [p.name for p in left_out] == ["img3.png"]


def test_two_candidates_within_the_time_tolerance_are_refused(tmp_path):
    d0 = touch(tmp_path / "a", "a0.png", "a1.png")
    d1 = touch(tmp_path / "b", "b0.png", "b1.png", "b2.png")
    write_timestamps(d0, {"a0.png": 1.000, "a1.png": 1.100})
    write_timestamps(d1, {"b0.png": 0.999, "b1.png": 1.003, "b2.png": 1.100})
    with pytest.raises(ValueError, match=r"image a0\.png of camera 0 has 2 images of camera 1 within 0\.005 s"):
        _rig_shots([str(d0), str(d1)], pair_by="time")
    shots, left_out, _ = _rig_shots([str(d0), str(d1)], pair_by="time", time_tolerance_s=0.002, drop_unpaired=True)
    assert epochs_of(shots) == [["a0.png", "b0.png"], ["a1.png", "b2.png"]] and [p.name for p in left_out] == ["b1.png"]


def test_pairing_by_time_needs_a_timestamp_for_every_image(tmp_path):
    d0 = touch(tmp_path / "a", "a0.png", "a1.png")
    d1 = touch(tmp_path / "b", "b0.png", "b1.png")
    write_timestamps(d0, {"a0.png": 1.0})
    write_timestamps(d1, {"b0.png": 1.0, "b1.png": 1.1})
    with pytest.raises(ValueError, match=r"has no timestamp for a1\.png"):
        _rig_shots([str(d0), str(d1)], pair_by="time")


def test_explicit_pairs_file(tmp_path):
    touch(tmp_path / "cam0", "x.png", "y.png")
    touch(tmp_path / "cam1", "p.png", "q.png")
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("# camera 0, camera 1\ncam0/x.png, cam1/q.png\ncam0/y.png,cam1/p.png\n")
    shots, _, _ = _rig_shots([], pairs_file=str(pairs), n_cameras=2)
    assert epochs_of(shots) == [["x.png", "q.png"], ["y.png", "p.png"]]
    pairs.write_text("cam0/x.png,cam1/q.png\ncam0/y.png,cam1/q.png\n")
    with pytest.raises(ValueError, match="listed in two epochs"):
        _rig_shots([], pairs_file=str(pairs), n_cameras=2)
    pairs.write_text("cam0/x.png,cam1/q.png\ncam0/y.png\n")
    with pytest.raises(ValueError, match="row 2 names 1 images, but the rig has 2 cameras"):
        _rig_shots([], pairs_file=str(pairs), n_cameras=2)


# -- through posecell calibrate rig ----------------------------------------------------------------


def rig_files(tmp_path: Path, field) -> list[str]:
    formats.write_field(tmp_path / "field.json", field)
    formats.write_camera(tmp_path / "cam.json", TRUE_CAMERA)
    return [
        "calibrate",
        "rig",
        "--field",
        str(tmp_path / "field.json"),
        "--camera",
        str(tmp_path / "cam.json"),
        str(tmp_path / "cam.json"),
        "-o",
        str(tmp_path / "rig.json"),
        "-q",
    ]


def test_cli_refuses_a_missing_frame_with_exit_code_2(tmp_path, capsys):
    d0 = touch(tmp_path / "cam0", *frames("cam0", [1, 2, 3, 4]))
    d1 = touch(tmp_path / "cam1", *frames("cam1", [1, 2, 4, 5]))
    code = cli.main([*rig_files(tmp_path, scene.reference_field()), "--images", str(d0), str(d1)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "without a partner" in err and "--drop-unpaired" in err
    assert not (tmp_path / "rig.json").exists()


def test_cli_refuses_two_images_of_one_camera_in_an_epoch(tmp_path, capsys, rng):
    field = field_3d(rng, 60)
    images = rig_images(
        rng, field, convergent_poses(rng, 3), (TRUE_CAMERA, SECOND_CAMERA), (np.eye(4), T_MASTER_CAMERA1)
    )
    obs = [formats.ImageObservations(im.name, list(im.ids), im.uv, im.camera, im.epoch) for im in images]
    obs[1] = obs[1]._replace(camera=0)  # e0's second image claims camera 0 too
    formats.write_json_atomic(tmp_path / "obs.json", formats.image_observations_to_json(obs))
    code = cli.main([*rig_files(tmp_path, field), "--observations", str(tmp_path / "obs.json")])
    err = capsys.readouterr().err
    assert code == 2 and "epoch 'e0' has two images of camera 0" in err


def test_cli_rejects_pairing_options_that_do_not_apply(tmp_path, capsys):
    d0 = touch(tmp_path / "cam0", "a.png")
    d1 = touch(tmp_path / "cam1", "a.png")
    code = cli.main(
        [*rig_files(tmp_path, scene.reference_field()), "--images", str(d0), str(d1), "--time-tolerance-s", "0.01"]
    )
    assert code == 2 and "--time-tolerance-s is for --pair-by time" in capsys.readouterr().err


def test_cli_calibrates_a_rig_with_a_missing_frame_left_out(tmp_path, capsys):
    # rendered images named by frame number; camera 1 lost frame 2 and camera 0 frame 5
    rng = np.random.default_rng(8)
    plate = scene.reference_field()
    T_master = (np.eye(4), _side_by_side())
    views = [(55, 0, 0), (55, 90, 72), (60, 180, 144), (50, 270, 216), (55, 45, 288)]
    for e, (angle, roll, azimuth) in enumerate(views, start=1):
        T_field_rig = scene.reference_pose(angle, 1150.0, roll, azimuth, (-60.0, 0.0, 0.0))
        for k in range(2):
            if (k, e) in ((1, 2), (0, 5)):
                continue
            image = render_frame(TRUE_CAMERA, plate, T_field_rig @ T_master[k], RenderSettings(), rng).image
            formats.write_image(tmp_path / f"cam{k}" / f"cam{k}_frame{e:03d}.png", image)
    args = [*rig_files(tmp_path, plate), "--images", str(tmp_path / "cam0"), str(tmp_path / "cam1")]
    assert cli.main(args) == 2 and "2 images without a partner" in capsys.readouterr().err
    code = cli.main([*args, "--drop-unpaired", "--sigma-px", str(NOISE_PX)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    out = json.loads(captured.out)
    assert out["n_epochs"] == 3 and out["pairing"] == "frame"
    assert "left out 2 images without a partner (cam0/cam0_frame002.png, cam1/cam1_frame005.png)" in captured.err
    T = np.array(out["T_master_camera"][1])
    assert np.linalg.norm(T[:3, 3] - T_master[1][:3, 3]) < 0.5  # mm, over a 120 mm baseline
    rig_json = json.loads((tmp_path / "rig.json").read_text())
    assert formats.rig_from_json(rig_json, "rig.json").n_cameras == 2  # what the service's rig mode reads
    cal = rig_json["calibration"]
    assert cal["sigma_source"] == "max(formal, jackknife)" and len(cal["images_left_out"]) == 2
    assert any("left out 2 images" in w for w in cal["warnings"])


def _side_by_side() -> np.ndarray:
    """Camera 1 120 mm to the right of camera 0, turned 5 deg towards it."""
    from scipy.spatial.transform import Rotation

    from service.core.geometry.frames import make_T

    return make_T(Rotation.from_euler("y", -5.0, degrees=True).as_matrix(), [120.0, 0.0, 0.0])
