"""``posecell bench``: named benchmark sections, each printing a markdown table."""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path


def _accuracy(args: argparse.Namespace) -> str:
    from service.bench import accuracy as bench_accuracy

    return bench_accuracy.run(trials=args.trials, seed=args.seed)


def _speed(args: argparse.Namespace) -> str:
    from service.bench import speed as bench_speed

    return bench_speed.run(n_frames=args.frames, seed=args.seed, conditions_frames=args.condition_frames)


def _faults(args: argparse.Namespace) -> str:
    from service.bench import faults as bench_faults

    return bench_faults.run(rounds=args.rounds)


def _service(args: argparse.Namespace) -> str:
    from service.bench import service as bench_service

    rates = tuple(float(r) for r in args.rates.split(","))
    clients = bench_service.parse_clients(args.clients)
    return bench_service.run(rates_hz=rates, clients=clients, seconds=args.seconds, centre=args.centre)


def _host(args: argparse.Namespace) -> str:
    from service.bench import host as bench_host

    return bench_host.run(n_frames=args.frames, seed=args.seed)


def _real(args: argparse.Namespace) -> str:
    from service.bench import real as bench_real

    return bench_real.run(data=args.data, camera=args.camera)


def _independent(args: argparse.Namespace) -> str:
    from service.bench import independent as bench_independent

    return bench_independent.run(n_frames=args.sheet_frames, seed=args.seed, tracked_frames=args.tracked_frames)


def _ab(args: argparse.Namespace) -> str:
    from service.bench import ab as bench_ab

    return bench_ab.run(against=args.against, seed=args.seed)


SECTIONS: dict[str, Callable[[argparse.Namespace], str]] = {
    "accuracy": _accuracy,
    "speed": _speed,
    "faults": _faults,
    "service": _service,
    "host": _host,
    "real": _real,
    "independent": _independent,
    "ab": _ab,
}
ON_REQUEST = ("ab",)  # not among "all": it needs --against


def host_line() -> str:
    """Which machine and libraries a run's figures come from: the speed of this work follows the CPU
    (the same code measured 3.2 ms full frame on one 2-core VM and 9 ms on another), so a table
    without its host is not a figure."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = f", load {os.getloadavg()[0]:.1f} at the start"
    except OSError:
        load = ""
    libs = []
    for name, dist in (("NumPy", "numpy"), ("numba", "numba"), ("OpenCV", "opencv-python-headless")):
        try:
            libs.append(f"{name} {metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            continue
    return f"host: {model}, {os.cpu_count()} cores{load}; Python {platform.python_version()}, {', '.join(libs)}"


def run_bench(args: argparse.Namespace) -> int:
    names = args.sections or [n for n in SECTIONS if n not in ON_REQUEST]
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        print(f"posecell bench: unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}", file=sys.stderr)
        return 2
    if "ab" in names:
        if not getattr(args, "against", None):
            print("posecell bench ab: say which revision or tree to compare with: --against REV|DIR", file=sys.stderr)
            return 2
        from service.bench.ab import other_side

        try:  # before any section runs: a wrong revision is told at once
            other_side(args.against)
        except ValueError as e:
            print(f"posecell bench ab: {e}", file=sys.stderr)
            return 2
    sys.stdout.write(f"_{host_line()}_\n\n")
    for name in names:
        t0 = time.perf_counter()
        text = SECTIONS[name](args)
        sys.stdout.write(f"## {name}\n\n{text}\n\n_(section took {time.perf_counter() - t0:.1f} s)_\n\n")
        sys.stdout.flush()
    return 0
