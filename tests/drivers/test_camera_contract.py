"""One contract, every camera driver: simulated, replayed, Aravis on the GV stand-in, and hardware on request."""

from __future__ import annotations

import itertools
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.base import (
    CameraDriver,
    CameraSettings,
    DriverDisconnected,
    DriverError,
    DriverTimeout,
    StrobeSettings,
    TriggerMode,
)
from drivers.registry import make_camera
from tests.drivers.conftest import camera_factories, use


def write_frames(folder: Path, n: int = 3, shape: tuple[int, int] = (48, 64), dtype: Any = np.uint8) -> list[Path]:
    """``n`` synthetic IR frames (a bright disc on a noisy dark background, moving) as PNGs in ``folder``."""
    rng = np.random.default_rng(7)
    full = np.iinfo(dtype).max
    v, u = np.mgrid[: shape[0], : shape[1]]
    paths = []
    for k in range(n):
        disc = ((u - 20 - 5 * k) ** 2 + (v - shape[0] / 2) ** 2) < 36
        image = np.clip(rng.normal(0.03 * full, 0.01 * full, shape) + 0.8 * full * disc, 0, full).astype(dtype)
        paths.append(folder / f"frame_{k:04d}.png")
        cv2.imwrite(str(paths[-1]), image)
    return paths


@contextmanager
def _replay_folder() -> Iterator[Any]:
    with tempfile.TemporaryDirectory(prefix="posecell-replay-test-") as d:
        write_frames(Path(d))
        cam = make_camera("replay", source=d)
        try:
            yield cam
        finally:
            cam.close()


@contextmanager
def _replay_sim() -> Iterator[Any]:
    cam = make_camera("replay", source="sim", n_frames=3, cell_config={"program": "hold"})
    try:
        yield cam
    finally:
        cam.close()


FACTORIES = {**camera_factories(), "replay-folder": _replay_folder, "replay-sim": _replay_sim}
LIT = StrobeSettings(enabled=True, line="Line1", source="ExposureActive")


@pytest.fixture(params=sorted(FACTORIES))
def camera(request):
    with use(FACTORIES[request.param], request.param) as cam:
        cam.open()
        yield cam


def test_camera_satisfies_the_protocol_and_describes_itself(camera):
    assert isinstance(camera, CameraDriver)
    info = camera.info
    assert info.width > 0 and info.height > 0 and info.pixel_format.startswith("Mono")
    assert info.serial


def test_free_run_frames_are_owned_grey_images_with_increasing_times(camera):
    camera.configure(CameraSettings(exposure_us=2000.0, frame_rate_hz=20.0, strobe=LIT))
    frames = [camera.fetch(timeout_s=3.0) for _ in range(4)]
    info = camera.info
    for f in frames:
        assert f.image.shape == (info.height, info.width) and f.image.dtype == np.uint8
        assert f.image.flags.owndata or f.image.base is None or f.image.flags.c_contiguous
        assert f.exposure_us == pytest.approx(2000.0, rel=0.05)
    t_host = [f.t_host_ns for f in frames]
    assert all(b > a for a, b in itertools.pairwise(t_host))
    assert abs(t_host[-1] - time.monotonic_ns()) < 2e9
    if frames[0].t_device_ns is not None:
        t_dev = [f.t_device_ns for f in frames]
        assert all(b > a for a, b in itertools.pairwise(t_dev))
    # independent: changing one frame's pixels cannot change another's (a replay lends its recording
    # read-only: then the change itself is refused)
    if frames[0].image.flags.writeable:
        frames[0].image[:] = 0
        assert frames[1].image.any()
    else:
        with pytest.raises(ValueError, match="read-only"):
            frames[0].image[:] = 0
        assert frames[0].image.any()


def test_software_trigger_gives_one_frame_per_trigger(camera):
    camera.configure(CameraSettings(trigger=TriggerMode.SOFTWARE, strobe=LIT))
    with pytest.raises(DriverTimeout):
        camera.fetch(timeout_s=0.3)  # no trigger, no frame
    camera.trigger()
    first = camera.fetch(timeout_s=3.0)
    with pytest.raises(DriverTimeout):
        camera.fetch(timeout_s=0.3)
    camera.trigger()
    second = camera.fetch(timeout_s=3.0)
    assert second.t_host_ns > first.t_host_ns


def test_fetch_honours_its_timeout(camera):
    camera.configure(CameraSettings(trigger=TriggerMode.SOFTWARE, strobe=LIT))
    t0 = time.monotonic()
    with pytest.raises(DriverTimeout):
        camera.fetch(timeout_s=0.2)
    assert 0.15 < time.monotonic() - t0 < 1.5


def test_ring_light_follows_the_strobe_setting(camera):
    if "strobe" not in camera.info.features:  # a replay: the recording's light was what it was
        pytest.skip(f"the {camera.info.driver} camera has no strobe output (not in info.features)")
    camera.configure(CameraSettings(exposure_us=2000.0, strobe=LIT))
    lit = camera.fetch(timeout_s=3.0).image
    camera.configure(CameraSettings(exposure_us=2000.0, strobe=None))
    dark = camera.fetch(timeout_s=3.0).image
    assert np.percentile(lit, 99.9) > np.percentile(dark, 99.9) + 50


def test_close_is_idempotent_and_a_closed_camera_says_so(camera):
    camera.close()
    camera.close()
    with pytest.raises(DriverError):
        camera.fetch(timeout_s=0.2)


def test_registry_reports_unknown_and_unloadable_drivers():
    from drivers.registry import CAMERAS, make_camera

    with pytest.raises(ValueError, match="unknown camera driver"):
        make_camera("nope")
    assert {"sim", "aravis", "v4l2", "replay"} <= set(CAMERAS)


def test_v4l2_camera_that_is_not_there_fails_to_open_with_a_clear_error():
    from drivers.base import DriverInitError
    from drivers.registry import make_camera

    cam = make_camera("v4l2", device="/dev/video-posecell-missing")
    with pytest.raises(DriverInitError, match="no V4L2 camera"):
        cam.open()
    with pytest.raises(DriverDisconnected):
        cam.fetch(timeout_s=0.1)  # tries to reopen, and says the device is gone
