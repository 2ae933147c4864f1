"""The simulated camera at 20 Hz beside a thread that holds the interpreter lock half the time, in a
process of its own: ``python -m tests.drivers.gil_load_probe`` prints one JSON line.

Why a process of its own: the measurement is of the camera and its render process under a load it
is given, not under whatever the tests before it left in the test process (in the whole suite it
lost ~2 s of frames in 4 of 5 clean-clone runs on 2026-12-05/06, and never alone or after the same
tests in a cut run: the cause is outside the camera, so the camera is measured apart from it).
"""

from __future__ import annotations

import json
import threading
import time

from drivers.base import CameraSettings, DriverTimeout, StrobeSettings
from drivers.camera.sim import SimCamera
from service.sim.cell import CellConfig, SimCell

LIT = StrobeSettings(enabled=True, line="Line1", source="ExposureActive")
READY_TIMEOUT_S = 30.0
RUN_S = 3.0


def burn_gil(stop: threading.Event) -> None:
    """The measurement thread's load: Python bytecode for 10 ms, then 10 ms asleep (the GIL half the time)."""
    while not stop.is_set():
        t_end = time.perf_counter() + 0.010
        n = 0
        while time.perf_counter() < t_end:
            n += 1
        time.sleep(0.010)


def run() -> dict[str, object]:
    """Fetch for RUN_S as the acquisition thread does; the frames' seqs and renderers, each fetch's duration."""
    cam = SimCamera(SimCell(CellConfig()))  # the circle program, as `posecell serve` runs it
    cam.open()
    stop = threading.Event()
    burner = threading.Thread(target=burn_gil, args=(stop,), daemon=True)
    seqs, renders, fetch_ms, timeouts = [], [], [], 0
    try:
        if not cam._renderer.wait_ready(READY_TIMEOUT_S):
            return {"error": f"the render process was not ready in {READY_TIMEOUT_S:g} s: {cam.render_status}"}
        cam.configure(CameraSettings(exposure_us=2000.0, frame_rate_hz=20.0, strobe=LIT))
        burner.start()
        for _ in range(4):
            cam.fetch(timeout_s=3.0)
        t0 = time.monotonic()
        while time.monotonic() - t0 < RUN_S:
            t_call = time.monotonic()
            try:
                frame = cam.fetch(timeout_s=0.1)
                seqs.append(frame.seq)
                renders.append(frame.meta["render"])
            except DriverTimeout:
                timeouts += 1
            fetch_ms.append(round((time.monotonic() - t_call) * 1e3, 1))
        elapsed_s = time.monotonic() - t0
        status = cam.render_status
    finally:
        stop.set()
        if burner.is_alive():
            burner.join()
        cam.close()
    return {
        "seqs": seqs,
        "renders": renders,
        "timeouts": timeouts,
        "elapsed_s": elapsed_s,
        "fetch_ms": fetch_ms,
        "child_ms": float(status["render_ms"]),
        "restarts": status["restarts"],
    }


if __name__ == "__main__":
    print(json.dumps(run()))  # noqa: T201 -- the test reads this line
