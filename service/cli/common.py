"""What every ``posecell`` verb shares: the exit codes, the two errors a verb raises for ``main`` to report,
and the two ways it writes (one JSON line on stdout, one sentence on stderr).

Only the standard library and :mod:`service.core.results` (itself standard library only) are imported here:
every verb module imports this one while the parser is built, before it is known which verb runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, TypeAlias

from service.core.results import SolveError

EXIT_FAILED = 1  # the input was fine, the measurement or calibration failed
EXIT_BAD_INPUT = 2  # a usage or file problem, as argparse's own usage errors

# what ``build_parser`` hands to each verb module's ``add_parser``
Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


class CliError(Exception):
    """A problem the user can fix; the message is shown as it is."""


class Failed(Exception):
    """A solve that failed inside ``posecell <name>``: ``main`` prints its Failure JSON and the reason."""

    def __init__(self, name: str, error: SolveError) -> None:
        super().__init__(error.message)
        self.name = name
        self.error = error


@contextmanager
def solving(name: str) -> Iterator[None]:
    """Around the solve of a verb whose failure is a result: a SolveError in it becomes :class:`Failed`.

    Only the solve itself: a SolveError elsewhere in the verb is reported by ``main`` as one sentence
    without the JSON line, as for the verbs whose output is not a single result.
    """
    try:
        yield
    except SolveError as e:
        raise Failed(name, e) from e


def print_json(obj: Any) -> None:
    """One JSON line on stdout, flushed: a reader of the pipe sees each result as it comes."""
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def print_err(line: str) -> None:
    """One line on stderr: messages, warnings and progress, never results."""
    print(line, file=sys.stderr)  # noqa: T201 -- the console script's one writer of stderr
