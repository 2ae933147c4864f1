"""Shared fixtures: the reference camera of DESIGN section 7 and the path to the real data sets."""

from __future__ import annotations

import fcntl
import os
import tempfile
import uuid
from collections.abc import Iterator
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


# The test command runs two workers (pytest-xdist, a file each at a time); these modules run with the
# machine to themselves: they hold the simulated cell to its real-time rate (20 Hz without a gap in
# seq, a robot outage told within a second, a broker that never slows the cell), time the host, or pin
# CPUs, which another worker's cell beside them disturbs (seen: 4 frames late at 20 Hz).
SOLO_MODULES = (
    "tests/e2e/test_serve.py",
    "tests/e2e/test_measure_cpus.py",
    "tests/e2e/test_serve_limits.py",
    "tests/drivers/test_sim_camera_render.py",
    "tests/drivers/test_exposure_change.py",
    "tests/api/test_reliability.py",
    "tests/plant/test_mqtt.py",
    "tests/test_bench_service.py",
)


@pytest.fixture(scope="module", autouse=True)
def _share_of_the_machine(request: pytest.FixtureRequest) -> Iterator[None]:
    """Under pytest-xdist, a module's hold on the machine for as long as it runs (its module
    fixtures, a running cell, inside it): shared for most, whole for SOLO_MODULES. A turnstile first,
    so that a solo module waiting for the other worker's file is not passed by that worker's next
    ones (``flock`` has no queue)."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if not run:  # one process: nothing runs beside it
        yield
        return
    base = _lock_base(run)
    solo = request.node.nodeid.startswith(SOLO_MODULES)
    with open(f"{base}.turnstile", "a") as turnstile, open(f"{base}.machine", "a") as machine:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        fcntl.flock(machine, fcntl.LOCK_EX if solo else fcntl.LOCK_SH)
        if not solo:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        yield  # both are released when the files close


def _lock_base(run: str) -> Path:
    """The path, less its suffix, of a run's two lock files (see :func:`_share_of_the_machine`)."""
    return Path(tempfile.gettempdir()) / f"posecell-tests-{run}"


def _controller(config: pytest.Config) -> bool:
    """This process hands the files to pytest-xdist's workers (it is not one of them)."""
    return bool(getattr(config.option, "numprocesses", None)) and not hasattr(config, "workerinput")


def pytest_configure(config: pytest.Config) -> None:
    from service.pipeline.compile import refresh_kernel_caches

    refresh_kernel_caches()  # a kernel module edited since the caches were made: recompile, not load stale code
    if _controller(config):
        # the files in pytest_collection_modifyitems' order: xdist's default reorders them by their
        # number of tests, which put the solo files among the others (each then held the other worker
        # at its next file's start: ~2 min of a worker's time idle in a run of 10.8 min)
        config.option.loadscopereorder = False
        # the run's id chosen here, so that the lock files named after it are removed at the end
        config.option.testrunuid = config.option.testrunuid or uuid.uuid4().hex


def pytest_unconfigure(config: pytest.Config) -> None:
    if _controller(config) and config.option.testrunuid:  # every worker has ended
        for suffix in (".turnstile", ".machine"):
            _lock_base(config.option.testrunuid).with_suffix(suffix).unlink(missing_ok=True)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        # the driver contracts run once per driver: the stand-in drivers' cases start processes
        if item.nodeid.startswith(SLOW_MODULES) or "-standin]" in item.nodeid:
            item.add_marker(pytest.mark.slow)
    # the workers take the files in this order: the long ones first (the short ones then fill the end
    # evenly), the solo ones last, together (each waits for the other worker's file to end, and that
    # worker waits while it runs); by module, so that a module's tests stay together
    items.sort(
        key=lambda item: 2 if item.nodeid.startswith(SOLO_MODULES) else 0 if item.nodeid.startswith(SLOW_MODULES) else 1
    )


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
