"""The simulated cell behind the real protocols measures the same deviation as the simulated cell read directly.

Two workers run side by side on one seed and program: one with the in-process simulated drivers
(``sim.transport = "direct"``), one with the real Aravis and UR drivers against the loopback stand-ins
(``"standins"``). Their epochs lie milliseconds apart, so both see the arm at the same place at the same
time. After a short settling time the stand-in worker's flange deviation, compared with the direct
worker's at the same instants of the program (interpolated between its frames, which lie under a
second apart on the 10 s circle), must agree within the measurement's reported σ (the median over 40
frames, in a band of 3σ·√2: two measurements are differenced, on a host of any speed); and its frames must
have been exposed when the service says (the camera pose in the image against the cell's true camera
pose at the claimed exposure instant), where the circle's 190 mm/s turns 1 ms into 0.19 mm.

The runtime states each simulated controller's delivery delay (the stand-in's, and the direct one's
1 ms of ``drivers/robot/sim.py``) as an installation states its controller's; left at 0 the direct
worker lags by that millisecond and its own deviation is 0.2 mm off.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_receive", reason="ur-rtde is installed by deploy/dev.sh (test extras)")
pytest.importorskip("drivers.standins.gv_camera", reason="PyGObject and Aravis 0.8 (deploy/dev.sh)")

from service.core.measurement import Measurement  # noqa: E402
from service.runtime.worker import Worker  # noqa: E402
from service.settings import load_settings  # noqa: E402

RTDE_ADDRESS = "127.0.0.13"  # the tests' own loopback address (see test_ur_rtde.py for the others)
SETTLE_S = 8.0  # from the first paired stand-in frame: the clock mappings have converged by then
MIN_FRAMES = 40  # stand-in frames compared after settling (the median's own scatter: ~σ / 3)
TIMEOUT_S = 60.0
MAX_BRACKET_S = 1.0  # direct frames this close bracket a stand-in frame: interpolated within ~0.01 mm


class _Results:
    """The paired results of one worker, as (cell time s, result), collected from its processing thread."""

    def __init__(self, worker: Worker) -> None:
        self.worker = worker
        self._rows: list[tuple[float, Measurement]] = []
        self._lock = threading.Lock()
        worker.subscribe(self._add)

    def _add(self, result: Measurement) -> None:
        if result.ok and result.flange is not None and result.flange.deviation is not None:
            t_s = (result.t_exposure_host_ns - self.worker.cell.epoch_ns) * 1e-9
            with self._lock:
                self._rows.append((t_s, result))

    def arrays(self, t0_s: float = -np.inf) -> dict[str, np.ndarray]:
        with self._lock:
            rows = [(t, r) for t, r in self._rows if t >= t0_s]
        cell = self.worker.cell.cell
        t = np.array([t for t, _ in rows])
        return {
            "t_s": t,
            "position_mm": np.array([r.flange.deviation.position_mm for _, r in rows]),
            "vector_mm": np.array([r.flange.deviation.vector_mm for _, r in rows]).reshape(-1, 3),
            "sigma_mm": np.array([np.linalg.norm(r.result.sigma_position_mm) for _, r in rows]),
            # the camera pose in the image against the true one at the claimed exposure instant
            "camera_mm": np.array(
                [
                    np.linalg.norm(r.T_field_camera[:3, 3] - cell.T_field_camera(ti)[:3, 3])
                    for ti, (_, r) in zip(t, rows, strict=True)
                ]
            ),
            # the deviation the cell really has then: the true arm against the controller's belief
            "true_vector_mm": (
                cell.T_base_flange_true(t)[..., :3, 3] - cell.T_base_flange_commanded(t)[..., :3, 3]
            ).reshape(-1, 3),
        }


def _bracketed(t_s: np.ndarray, t_direct_s: np.ndarray) -> np.ndarray:
    """Which of the instants ``t_s`` lie between two direct frames at most MAX_BRACKET_S apart."""
    k = np.searchsorted(t_direct_s, t_s)
    ok = (k > 0) & (k < t_direct_s.size)
    ok[ok] = t_direct_s[k[ok]] - t_direct_s[k[ok] - 1] < MAX_BRACKET_S
    return ok


@pytest.mark.slow
def test_standins_deviation_matches_direct_mode_within_sigma(tmp_path: Path) -> None:
    workers = {}
    for mode in ("direct", "standins"):
        # both modes' latencies are stated by the runtime (service.runtime.cell_runtime)
        settings = load_settings(
            None, state_dir=tmp_path / mode, sim__transport=mode, sim__seed=0, sim__program="circle"
        )
        if mode == "direct":
            # two whole cells on one machine: the direct cell renders in its camera thread (as it did when
            # this comparison was made), not in a render child of its own, so that the stand-ins' camera
            # process keeps its exposure schedule on a loaded 2-core CI machine (a clean-clone run once saw
            # the stand-ins 0.19 mm apart, the size of a 1 ms timing error; the child renderer's own frames
            # are checked against in-process rendering in test_sim_camera_render.py)
            camera = settings.cameras[0].model_copy(update={"options": {"render": "inline"}})
            settings = settings.model_copy(update={"cameras": (camera,)})
        workers[mode] = Worker(settings, None)
    workers["standins"].cell.rtde_address = RTDE_ADDRESS
    results = {mode: _Results(w) for mode, w in workers.items()}
    settled_s = None
    try:
        for w in workers.values():
            w.start()
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            time.sleep(0.5)
            if settled_s is None:
                first = results["standins"].arrays()["t_s"]
                settled_s = first[0] + SETTLE_S if first.size else None
                continue
            s, d = results["standins"].arrays(settled_s), results["direct"].arrays(settled_s - MAX_BRACKET_S)
            if np.count_nonzero(_bracketed(s["t_s"], d["t_s"])) >= MIN_FRAMES:
                break
    finally:
        for w in workers.values():
            w.stop()
    assert settled_s is not None, "no stand-in frame was paired with the robot"
    s, d = results["standins"].arrays(settled_s), results["direct"].arrays(settled_s - MAX_BRACKET_S)
    inside = _bracketed(s["t_s"], d["t_s"])
    # the direct worker's deviation at the stand-in frames' instants
    direct_vector = np.stack([np.interp(s["t_s"][inside], d["t_s"], d["vector_mm"][:, k]) for k in range(3)], axis=1)
    difference_mm = s["position_mm"][inside] - np.linalg.norm(direct_vector, axis=1)
    # the direct worker's σ: the stand-in renders noise-free images, so its own σ is several times smaller
    sigma = max(float(np.median(s["sigma_mm"])), float(np.median(d["sigma_mm"])))
    report = {
        "n": int(inside.sum()),
        "sigma_mm": sigma,
        "median_standins_mm": float(np.median(s["position_mm"])),
        "median_direct_mm": float(np.median(d["position_mm"])),
        "median_difference_mm": float(np.median(difference_mm)),
        "p90_vector_error_standins_mm": float(
            np.percentile(np.linalg.norm(s["vector_mm"] - s["true_vector_mm"], axis=1), 90)
        ),
        "p90_vector_error_direct_mm": float(
            np.percentile(np.linalg.norm(d["vector_mm"] - d["true_vector_mm"], axis=1), 90)
        ),
        "camera_p90_standins_mm": float(np.percentile(s["camera_mm"], 90)),
        "camera_p90_direct_mm": float(np.percentile(d["camera_mm"], 90)),
    }
    print(report)  # noqa: T201 -- shown with -s
    assert report["n"] >= MIN_FRAMES, report
    # the difference of two measurements, each with its σ, has σ·√2; 3σ·√2 (0.07 mm) leaves room for the
    # median's own scatter and a slow host, whose loopback delivers the stand-ins' samples later than the
    # stated minimum (cell_runtime.STANDIN_ROBOT_LATENCY_S) by a fraction of a millisecond: observed
    # |difference| 0.024–0.033 mm with σ 0.016–0.017 mm on 2026-12-04, 0.027–0.054 mm on 2026-12-05's
    # slower host (always of one sign: the stand-ins' ~0.2 ms more). The 1 ms latency left unstated would
    # show as 0.2 mm
    assert abs(report["median_difference_mm"]) < 3 * np.sqrt(2) * sigma, report
    # frame by frame, against the cell's true deviation: within a millisecond (0.19 mm) even on a busy host
    assert report["p90_vector_error_standins_mm"] < 0.19, report
    # and the direct worker too: without its controller's 1 ms stated it would be off by 0.19 mm
    assert report["p90_vector_error_direct_mm"] < 0.19, report
    # the stand-in frames were exposed when the service says, within half a millisecond
    assert report["camera_p90_standins_mm"] < 0.1, report


def test_the_runtime_states_the_simulated_controllers_own_delay():
    import inspect

    from drivers.robot.sim import SimRobot
    from service.runtime import cell_runtime

    assert inspect.signature(SimRobot).parameters["latency_s"].default == cell_runtime.SIM_ROBOT_LATENCY_S
    settings = load_settings(None, sim__transport="direct")
    stated = cell_runtime.with_stated_latencies(settings)
    assert stated.robot.transport_latency_s == cell_runtime.SIM_ROBOT_LATENCY_S
    assert settings.robot.transport_latency_s == 0.0  # a new object: the given settings are not changed
    assert Worker(settings).settings.robot.transport_latency_s == cell_runtime.SIM_ROBOT_LATENCY_S
    standins = cell_runtime.with_stated_latencies(load_settings(None, sim__transport="standins"))
    assert standins.robot.transport_latency_s == cell_runtime.STANDIN_ROBOT_LATENCY_S
    assert standins.cameras[0].transport_latency_s == cell_runtime.STANDIN_CAMERA_LATENCY_S
    real = load_settings(None, robot__driver="none", cameras=[{"driver": "v4l2"}])
    assert cell_runtime.with_stated_latencies(real) is real
