"""Two revisions head to head: the same frames' CPU time through this checkout's measurer and another's.

A change's cost is often smaller than this VM's drift (the same ROI frame's CPU time went from
1.07 to 1.72 ms within ten minutes, same code), so a figure taken before a change and one taken
after say little. Here the two are measured in turn: each in a process of its own (the other tree
first on its ``sys.path``), both on one CPU, in short interleaved rounds (who goes first
alternates), on the same frames (rendered once, by this checkout, along ``posecell bench speed``'s
path). The drift then falls on both alike, and the per-round ratio is the figure.

``against`` is a git revision (its tree is extracted with ``git archive`` into
``$XDG_CACHE_HOME/posecell/bench-ab/<commit>`` and kept: its kernels compile once, ~2 min) or a
directory holding a ``service`` package. Both sides must have ``FrameMeasurer``,
``MeasureSettings.from_options(roi_tracking=...)`` and ``service.sim.scene``'s reference camera
and field, as every revision since the first wave has.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.bench.speed import frames_along_path

ROUNDS = 30
PER_ROUND = {"roi": 40, "full": 10}  # frames a round: ~50 ms of each side's CPU
START_TIMEOUT_S = 900.0  # a tree's first start compiles its kernels (~2 min here)
REPO = Path(__file__).resolve().parents[2]

# run in each tree: loads the frames, warms both measurers, then measures "<kind> <n>" frames per
# line of stdin and answers with their CPU times, us (only frames measured in that mode count)
PROBE = """
import json, os, sys, time
import numpy as np
os.sched_setaffinity(0, {int(sys.argv[2])})
import service
from service.pipeline.measure import FrameMeasurer, MeasureSettings
from service.sim.scene import reference_camera, reference_field
tour = list(np.load(sys.argv[1]))
measurers = {
    "roi": FrameMeasurer(reference_camera(), reference_field(), MeasureSettings.from_options()),
    "full": FrameMeasurer(reference_camera(), reference_field(), MeasureSettings.from_options(roi_tracking=False)),
}
clocks = {"roi": 0, "full": 0}
def frames(kind, n):
    out = []
    while len(out) < n:
        k = clocks[kind]
        clocks[kind] = k + 1
        t0 = time.thread_time()
        outcome = measurers[kind].measure(tour[k % len(tour)], t_s=k * 0.004)
        dt = time.thread_time() - t0
        if outcome.mode == kind:
            out.append(dt * 1e6)
    return out
frames("roi", 40)
frames("full", 5)
print(json.dumps({"ready": os.path.dirname(os.path.dirname(os.path.abspath(service.__file__)))}), flush=True)
for line in sys.stdin:
    kind, n = line.split()
    print(json.dumps(frames(kind, int(n))), flush=True)
"""


@dataclass(frozen=True)
class Side:
    name: str  # a short revision, or the directory
    tree: Path


def _git(*args: str) -> str:
    out = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise ValueError(f"git {' '.join(args)}: {out.stderr.strip() or out.returncode}")
    return out.stdout.strip()


def this_side() -> Side:
    """This checkout, named by its commit (``-dirty`` with uncommitted changes to tracked files)."""
    try:
        name = _git("rev-parse", "--short", "HEAD") + ("-dirty" if _git("status", "--porcelain", "-uno") else "")
    except (ValueError, OSError):
        name = "this checkout"
    return Side(name, REPO)


def other_side(against: str) -> Side:
    """``against`` as a tree: a directory with a ``service`` package, or a git revision's tree, extracted
    once into the cache."""
    path = Path(against).expanduser()
    if path.is_dir():
        if not (path / "service" / "__init__.py").exists():
            raise ValueError(f"{path} holds no service package (service/__init__.py)")
        return Side(str(path), path.resolve())
    try:
        commit = _git("rev-parse", "--verify", "--quiet", f"{against}^{{commit}}")
    except (ValueError, OSError) as e:
        raise ValueError(f"{against!r} is neither a directory nor a git revision of {REPO} ({e})") from None
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "posecell" / "bench-ab"
    tree = cache / commit
    if not (tree / "service" / "__init__.py").exists():
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            archive = Path(tmp) / "tree.tar"
            _git("archive", "--format=tar", "-o", str(archive), commit)
            with tarfile.open(archive) as tar:
                tar.extractall(Path(tmp) / "tree", filter="data")
            os.replace(Path(tmp) / "tree", tree)
    return Side(commit[:7], tree)


class _Probe:
    """One side's measuring process."""

    def __init__(self, side: Side, frames_path: Path, cpu: int) -> None:
        env = {**os.environ, "PYTHONPATH": str(side.tree)}
        self.side = side
        self.proc = subprocess.Popen(
            [sys.executable, "-c", PROBE, str(frames_path), str(cpu)],
            cwd=side.tree,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def ready(self) -> None:
        line = self._line()
        tree = Path(json.loads(line)["ready"]).resolve()
        if tree != self.side.tree:
            raise RuntimeError(f"{self.side.name}: its process imported service from {tree}, not {self.side.tree}")

    def frames_us(self, kind: str, n: int) -> list[float]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"{kind} {n}\n")
        self.proc.stdin.flush()
        return [float(x) for x in json.loads(self._line())]

    def _line(self) -> str:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.side.name}: its measuring process ended (exit {self.proc.wait()})")
        return line

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


def run(against: str, seed: int = 1, rounds: int = ROUNDS) -> str:
    """The section's table: this checkout against ``against`` (see the module docstring)."""
    sides = (this_side(), other_side(against))
    frames = frames_along_path(24, seed)
    # forward and back along the path, 4 ms apart: ROI mode throughout but for a frame at each turn
    tour = np.stack([f.image for f in frames] + [f.image for f in frames[-2:0:-1]])
    cpu = min(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory() as tmp:
        frames_path = Path(tmp) / "frames.npy"
        np.save(frames_path, tour)
        print(
            f"bench ab: starting {sides[0].name} and {sides[1].name} (a tree's first start compiles)", file=sys.stderr
        )
        probes = [_Probe(side, frames_path, cpu) for side in sides]
        try:
            for probe in probes:
                probe.ready()
            us: dict[str, list[list[float]]] = {kind: [[], []] for kind in PER_ROUND}
            ratios: dict[str, list[float]] = {kind: [] for kind in PER_ROUND}
            for r in range(rounds):
                for kind, n in PER_ROUND.items():
                    medians = [0.0, 0.0]
                    for i in (0, 1) if r % 2 == 0 else (1, 0):  # who goes first alternates
                        got = probes[i].frames_us(kind, n)
                        us[kind][i] += got
                        medians[i] = float(np.median(got))
                    ratios[kind].append(medians[0] / medians[1])
        finally:
            for probe in probes:
                probe.close()
    a, b = sides[0].name, sides[1].name
    lines = [
        f"Reference frames (1300×1030, ~230 targets) along `posecell bench speed`'s path; CPU time per frame, "
        f"both sides on CPU {cpu}, each in its own process; {rounds} interleaved rounds of "
        f"{PER_ROUND['roi']} ROI and {PER_ROUND['full']} full frames a side.",
        "",
        f"| frame | {a} median us | {b} median us | {a} / {b}, per round: median | interquartile |",
        "|---|---:|---:|---:|---:|",
    ]
    for kind in PER_ROUND:
        q1, q2, q3 = np.quantile(ratios[kind], [0.25, 0.5, 0.75])
        mine, theirs = (float(np.median(x)) for x in us[kind])
        name = "ROI tracking" if kind == "roi" else "full frame"
        lines.append(f"| {name} | {mine:.0f} | {theirs:.0f} | {q2:.3f} | {q1:.3f}–{q3:.3f} |")
    return "\n".join(lines)
