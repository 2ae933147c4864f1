"""Shared fixtures: the reference camera of DESIGN section 7 and the path to the real data sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.core.geometry.camera_model import BrownFraser
from service.sim import scene

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# The quick loop (`deploy/dev.sh test -m "not slow"`) leaves out the tests marked slow one by one
# (over 10 s) and these modules as a whole: they start real servers, processes, stand-ins or a
# browser, or read the real data sets, at 1-8 s a test. `deploy/dev.sh test` (CI) runs everything.
SLOW_MODULES = (
    "tests/e2e/",
    "tests/api/test_api.py",
    "tests/api/test_accuracy_tests.py",
    "tests/api/test_handeye_workflow.py",
    "tests/api/test_http_hardening.py",
    "tests/api/test_reliability.py",
    "tests/api/test_rig_mode.py",
    "tests/api/test_validation.py",
    "tests/drivers/test_aravis.py",
    "tests/drivers/test_cell_runtime_standins.py",
    "tests/drivers/test_sim_cell_standins.py",
    "tests/drivers/test_standins_deviation.py",
    "tests/drivers/test_ur_child_restart.py",
    "tests/drivers/test_ur_rtde.py",
    "tests/drivers/test_pairing.py",
    "tests/test_cli.py",
    "tests/test_calibrate_camera_cli.py",
    "tests/test_calibrate_rig_cli.py",
    "tests/test_calibrate_robot.py",
    "tests/test_ur5_laser_tracker.py",
    "tests/test_ur5_compensation.py",
    "tests/api/test_compensate_api.py",
    "tests/api/test_robot_calibration.py",
    "tests/test_real_panel.py",
    "tests/test_dbat_reference.py",
    "tests/test_dbat_images.py",
    "tests/test_independent_images.py",
)


def pytest_configure(config: pytest.Config) -> None:
    from service.pipeline.compile import refresh_kernel_caches

    refresh_kernel_caches()  # a kernel module edited since the caches were made: recompile, not load stale code


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        # the driver contracts run once per driver: the stand-in drivers' cases start processes
        if item.nodeid.startswith(SLOW_MODULES) or "-standin]" in item.nodeid:
            item.add_marker(pytest.mark.slow)


def shared_data(name: str) -> Path:
    """Path of a real data set in ../shared/data, or skip the test saying why."""
    p = SHARED_DATA / name
    if not p.exists():
        pytest.skip(f"real data set {name!r} not found at {p} (see ../shared/data/README.md)")
    return p


@pytest.fixture
def reference_camera() -> BrownFraser:
    """1300x1030 px, 6.7 um pixels, c = 12 mm, with distortion of a real 12 mm lens (DESIGN section 7)."""
    return scene.reference_camera()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261125)
