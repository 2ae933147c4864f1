"""Does this machine's second CPU slow the first? The ROI frame's CPU time alone and beside a busy neighbour.

The service's figures at 500 Hz need the measurement child's core and most of another: the
child's ROI frame, the processing, camera and event-loop threads. Where the CPUs are one core's
hyperthreads, or a VM's vCPUs that the host shares, a busy neighbour CPU slows the child's every
frame, and the service's budget there is nearer one core than two. This section measures it:
the same ROI frame's CPU time on one CPU, alone and with a process on another CPU running a
Python loop (the kind of work the service's other threads do) or streaming memory, in
interleaved rounds so that the machine's drift slows every row alike. (On 2026-12-05's third
host a first, uninterleaved try suggested 2x; interleaved, the rows agreed within a few percent
while the frame itself drifted between 0.65 and 1.4 ms within the hour: the host's own load.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np

from service.bench.speed import frames_along_path
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.scene import reference_camera, reference_field

ROUNDS = 15
# the neighbours: a Python loop (the interpreter's work, as the service's threads do) and numpy
# streaming 64 MB (memory bandwidth), each pinned to its CPU by itself
NEIGHBOURS = {
    "a Python loop": "while True: pass",
    "streaming memory": "import numpy as np\na = np.ones(8 << 20)\nwhile True: a += 1.0",
}


def _neighbour(code: str, cpu: int) -> subprocess.Popen[bytes]:
    pinned = f"import os\nos.sched_setaffinity(0, {{{cpu}}})\n{code}"
    return subprocess.Popen([sys.executable, "-c", pinned], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def run(n_frames: int, seed: int) -> str:
    cpus = sorted(os.sched_getaffinity(0))
    frames = frames_along_path(24, seed)
    # forward and back along the path, 4 ms apart: tracked in ROI mode throughout but for a frame
    # or two at each turn (those are not counted)
    tour = [f.image for f in frames] + [f.image for f in frames[-2:0:-1]]
    measurer = FrameMeasurer(reference_camera(), reference_field(), MeasureSettings())
    clock = iter(range(1 << 62))

    def roi_frames_us(n: int) -> list[float]:
        out: list[float] = []
        while len(out) < n:
            k = next(clock)
            t0 = time.thread_time()
            outcome = measurer.measure(tour[k % len(tour)], t_s=k * 0.004)
            if outcome.mode == "roi":
                out.append((time.thread_time() - t0) * 1e6)
        return out

    roi_frames_us(20)  # warm: the kernels loaded, the caches filled
    if len(cpus) < 2:
        alone_us = np.median(roi_frames_us(n_frames))
        return f"One CPU ({cpus}): no neighbour to measure against. ROI frame {alone_us:.0f} us of CPU."
    mine, other = cpus[0], cpus[1]
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {mine})
    # the neighbours run throughout, stopped but for their turns (SIGSTOP/SIGCONT: no start-up
    # in the rounds, which are short so that the machine's drift falls on every row alike)
    neighbours = {name: _neighbour(code, other) for name, code in NEIGHBOURS.items()}
    rows: dict[str, list[float]] = {"alone": [], **{name: [] for name in NEIGHBOURS}}
    per_round = max(1, n_frames // ROUNDS)
    try:
        time.sleep(0.5)  # started (numpy imported, the array made)
        for proc in neighbours.values():
            proc.send_signal(signal.SIGSTOP)
        for _ in range(ROUNDS):
            for name in rows:
                proc = neighbours.get(name)
                if proc is not None:
                    proc.send_signal(signal.SIGCONT)
                    time.sleep(0.02)  # running on its CPU
                try:
                    rows[name] += roi_frames_us(per_round)
                finally:
                    if proc is not None:
                        proc.send_signal(signal.SIGSTOP)
    finally:
        for proc in neighbours.values():
            proc.kill()
            proc.wait()
        os.sched_setaffinity(0, before)
    alone = float(np.median(rows["alone"]))
    lines = [
        f"ROI frames of the reference scene (~230 windows, resection, result) on CPU {mine}, CPU time per frame; "
        f"the neighbour on CPU {other}; {n_frames} frames a row, in {ROUNDS} interleaved rounds.",
        "",
        f"| CPU {other} runs | median us | p90 us | × alone |",
        "|---|---:|---:|---:|",
    ]
    for name, us in rows.items():
        med = float(np.median(us))
        lines.append(
            f"| {'nothing' if name == 'alone' else name} | {med:.0f} | {np.quantile(us, 0.9):.0f} | {med / alone:.2f} |"
        )
    slowed = float(np.median(rows["a Python loop"])) / alone
    if slowed > 1.3:
        verdict = (
            "its CPUs share a core (hyperthreads, or a VM's vCPUs the host shares): budget the service here as "
            "about one core, not two."
        )
    elif slowed < 1.1:
        verdict = "its CPUs are separate cores."
    else:
        verdict = "some sharing, or the machine's own drift: run it again."
    lines += ["", f"Beside a busy neighbour this CPU's frame takes {slowed:.2f}× its time alone: {verdict}"]
    return "\n".join(lines)
