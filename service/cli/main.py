"""The ``posecell`` console script: thin verbs over the engine (DESIGN section 5).

Each verb is a module of this package with ``add_parser(subparsers)`` and the function that runs it; this
one builds the parser from them and turns what a verb raises into the output and the exit code, for all
of them in one place. Bad input never shows a traceback: it prints one sentence on stderr and exits
non-zero (2 for a usage or file problem, 1 for a measurement that failed).

The verb modules import the engine (numpy, scipy, numba) only inside the function that runs the verb,
so ``posecell --help`` and a usage error answer at once.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from service.cli import bench, calibrate, compensate, demo, measure, report, resect, serve, simulate, targets
from service.cli.common import EXIT_BAD_INPUT, EXIT_FAILED, CliError, Failed, print_err, print_json
from service.core.results import Failure, SolveError

__all__ = ["EXIT_BAD_INPUT", "EXIT_FAILED", "CliError", "build_parser", "main"]

# in the order of the help's list of verbs
VERBS = (serve, resect, calibrate, compensate, measure, simulate, targets, demo, bench, report)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="posecell",
        description="Real-time photogrammetric robot pose measurement (see README.md).",
    )
    sub = p.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for verb in VERBS:
        verb.add_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader of stdout went away (`posecell measure ... | head`): not an error
        return 0


def _run(args: argparse.Namespace) -> int:
    """Run the verb; what it raises becomes its report on stdout/stderr and the exit code."""
    run: Callable[[argparse.Namespace], int] = args.func
    # input errors are reported under the top-level verb, as they always were
    prog = f"posecell {args.verb}"
    from service.pipeline.compile import refresh_kernel_caches  # here, not at import: --help stays instant

    refresh_kernel_caches()  # before any verb loads a kernel: none from a stale cache
    try:
        return run(args)
    except Failed as e:
        # a failed solve is a result: its Failure JSON on stdout, where the success would have been
        print_json(Failure.from_error(e.error).to_dict())
        print_err(f"posecell {e.name}: {e.error.message}")
        return EXIT_FAILED
    except CliError as e:
        print_err(f"{prog}: {e}")
        return EXIT_BAD_INPUT
    except SolveError as e:
        print_err(f"{prog}: {e.message}")
        return EXIT_FAILED
    except ValueError as e:
        # formats.FormatError (a ValueError) is named only here: service.store.formats imports numpy and
        # the core, and a verb that raised one has imported it already
        from service.store.formats import FormatError

        if not isinstance(e, FormatError):
            raise
        print_err(f"{prog}: {e}")
        return EXIT_BAD_INPUT


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
