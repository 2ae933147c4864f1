"""``posecell bench``: named benchmark sections, each printing a markdown table."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable


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
    return bench_service.run(rates_hz=rates, clients=clients, seconds=args.seconds)


SECTIONS: dict[str, Callable[[argparse.Namespace], str]] = {
    "accuracy": _accuracy,
    "speed": _speed,
    "faults": _faults,
    "service": _service,
}


def run_bench(args: argparse.Namespace) -> int:
    names = args.sections or list(SECTIONS)
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        print(f"posecell bench: unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}", file=sys.stderr)
        return 2
    for name in names:
        t0 = time.perf_counter()
        text = SECTIONS[name](args)
        sys.stdout.write(f"## {name}\n\n{text}\n\n_(section took {time.perf_counter() - t0:.1f} s)_\n\n")
        sys.stdout.flush()
    return 0
