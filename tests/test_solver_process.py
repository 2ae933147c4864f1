"""The solver process: answers, errors and a crash come back to the caller; a crash is not the end."""

from __future__ import annotations

import os

import pytest

from service.core.results import Reason, SolveError
from service.runtime.handeye_session import SessionError, solve_samples
from service.runtime.solver_process import SolverCrashed, SolverProcess


def _pid() -> int:
    return os.getpid()


def _die() -> None:
    os._exit(3)


def _refuse() -> None:
    raise SolveError(Reason.degenerate_geometry, "all points on a line", {"n": 3})


@pytest.mark.slow  # over 3 s: Monte Carlo, repeated calibrations or child processes
def test_solves_run_in_a_child_and_its_errors_and_crashes_come_back():
    solver = SolverProcess()
    try:
        child = solver.run(_pid)
        assert child != os.getpid()
        # the product's own errors keep their reason, message and details across the process boundary
        with pytest.raises(SolveError) as e:
            solver.run(_refuse)
        assert e.value.reason is Reason.degenerate_geometry and e.value.details == {"n": 3}
        with pytest.raises(SessionError) as s:
            solver.run(solve_samples, [])
        assert s.value.reason == Reason.poor_motion and "at least 3" in s.value.message
        with pytest.raises(SolverCrashed, match="_die"):
            solver.run(_die)
        # the next solve gets a new child
        assert solver.run(_pid) not in (child, os.getpid())
    finally:
        solver.stop()
