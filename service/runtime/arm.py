"""Who moves the simulated arm now: one workflow at a time.

The accuracy tests, the robot calibration (its session, its moves and its verification) and the
hand-eye session's moves each command the simulated arm. Two at once would play two programs
into one controller, each measuring the other's motion: an accuracy test's stops would be taken
while the calibration drives the arm away, and neither would know. So each claims the arm first,
and a second one is refused with a sentence naming the first.

A claim lasts until it is released; a move that is not waited for (the hand-eye session's move
returns at once) is released with the time its motion still takes, so the lease ends when the arm
has arrived.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

ARRIVAL_MARGIN_S = 0.2  # a move commanded now starts 0.05 s on; then the controller reports it still


class ArmBusy(Exception):
    """The arm is being moved by another workflow (the message names it)."""


@dataclass
class ArmClaim:
    """One workflow's hold of the arm (what :meth:`ArmLease.claim` gives and :meth:`ArmLease.release` ends)."""

    owner: str
    until_ns: int | None = None  # released, to expire then (None: held)


class ArmLease:
    """The arm's one claim (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._claim: ArmClaim | None = None

    def claim(self, owner: str) -> ArmClaim:
        """Claim the arm for ``owner`` (a phrase: "the circle accuracy test"); raises :class:`ArmBusy`."""
        with self._lock:
            current = self._current()
            if current is not None:
                raise ArmBusy(f"the arm is being moved by {current.owner}: stop it or wait for it to end")
            self._claim = ArmClaim(owner)
            return self._claim

    def release(self, claim: ArmClaim, after_s: float = 0.0) -> None:
        """End ``claim`` now or ``after_s`` from now (when the motion it started is over)."""
        with self._lock:
            if self._claim is not claim:
                return  # already ended
            if after_s > 0:
                claim.until_ns = time.monotonic_ns() + int(after_s * 1e9)
            else:
                self._claim = None

    @property
    def moved_by(self) -> str | None:
        """The owner of the current claim, or None."""
        with self._lock:
            current = self._current()
            return None if current is None else current.owner

    def _current(self) -> ArmClaim | None:
        c = self._claim
        if c is not None and c.until_ns is not None and time.monotonic_ns() >= c.until_ns:
            self._claim = c = None
        return c
