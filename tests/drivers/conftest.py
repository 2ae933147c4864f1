"""Driver factories for the contract suites: simulation, loopback stand-ins, and real devices on request.

Real hardware joins the suites when the environment names it, as python-can's
and harvesters' test targets do:

    POSECELL_TEST_CAMERA=aravis:<device id or IP>   or   v4l2:/dev/video0
    POSECELL_TEST_ROBOT=ur:<controller IP>
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

import pytest

from drivers.registry import make_camera, make_robot

CameraFactory = Callable[[], AbstractContextManager[Any]]


@contextmanager
def _sim_camera() -> Iterator[Any]:
    from service.sim.cell import CellConfig, SimCell

    cam = make_camera("sim", cell=SimCell(CellConfig(program="hold")))
    try:
        yield cam
    finally:
        cam.close()


@contextmanager
def _hardware_camera(spec: str) -> Iterator[Any]:
    name, _, device = spec.partition(":")
    cam = make_camera(name, device=device) if device else make_camera(name)
    try:
        yield cam
    finally:
        cam.close()


def camera_factories() -> dict[str, CameraFactory]:
    out: dict[str, CameraFactory] = {"sim": _sim_camera}
    try:
        from drivers.standins.gv_camera import contract_camera  # the Aravis driver against the GV stand-in
    except ImportError as e:  # no gi/Aravis on this machine: say so in the test id
        out[f"aravis-standin-unavailable({type(e).__name__})"] = None  # type: ignore[assignment]
    else:
        out["aravis-standin"] = contract_camera
    spec = os.environ.get("POSECELL_TEST_CAMERA")
    if spec:
        out[f"hardware-{spec}"] = lambda: _hardware_camera(spec)
    return out


@contextmanager
def _sim_robot() -> Iterator[Any]:
    from service.sim.cell import CellConfig, SimCell

    robot = make_robot("sim", cell=SimCell(CellConfig()))
    try:
        yield robot
    finally:
        robot.close()


@contextmanager
def _ur_standin() -> Iterator[Any]:
    """The real ur_rtde client (in the UR driver's child process) against the RTDE stand-in."""
    from drivers.standins.demo_arm import DemoArm
    from drivers.standins.rtde_server import RtdeServer

    with RtdeServer(DemoArm(), host="127.0.0.10"):
        robot = make_robot("ur", host="127.0.0.10", frequency_hz=125.0)
        try:
            yield robot
        finally:
            robot.close()


@contextmanager
def _replay_robot() -> Iterator[Any]:
    """The replay robot, looping a 5-frame recording's 500 Hz samples."""
    import tempfile
    from pathlib import Path

    from drivers.replay_clock import forget
    from tests.drivers.recording import make_recording

    with tempfile.TemporaryDirectory() as tmp:
        folder = make_recording(Path(tmp) / "20261205-101500")
        robot = make_robot("replay", source=str(folder))
        try:
            yield robot
        finally:
            robot.close()
            forget(folder)


def robot_factories() -> dict[str, Callable[[], AbstractContextManager[Any]] | None]:
    out: dict[str, Callable[[], AbstractContextManager[Any]] | None] = {"sim": _sim_robot, "replay": _replay_robot}
    try:
        import rtde_receive  # noqa: F401 -- only to know whether the UR driver can run here
    except ImportError as e:
        out[f"ur-standin-unavailable({type(e).__name__})"] = None
    else:
        out["ur-standin"] = _ur_standin
    spec = os.environ.get("POSECELL_TEST_ROBOT")
    if spec:
        name, _, host = spec.partition(":")

        @contextmanager
        def _hw() -> Iterator[Any]:
            robot = make_robot(name, host=host)
            try:
                yield robot
            finally:
                robot.close()

        out[f"hardware-{spec}"] = _hw
    return out


def use(factory: Any, name: str) -> AbstractContextManager[Any]:
    if factory is None:
        pytest.skip(f"driver {name} cannot run here (its SDK is missing); see deploy/dev.sh")
    return factory()
