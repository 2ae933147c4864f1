"""The arm's lease: one workflow moves the simulated arm at a time (service/runtime/arm.py)."""

from __future__ import annotations

import threading
import time

import pytest

from service.runtime.arm import ArmBusy, ArmLease


def test_a_second_claim_is_refused_naming_the_first_until_it_is_released():
    arm = ArmLease()
    first = arm.claim("the circle accuracy test")
    assert arm.moved_by == "the circle accuracy test"
    with pytest.raises(ArmBusy, match=r"^the arm is being moved by the circle accuracy test: stop it or wait"):
        arm.claim("the robot calibration session")
    arm.release(first)
    assert arm.moved_by is None
    second = arm.claim("the robot calibration session")
    arm.release(first)  # an ended claim released again does not end the current one
    assert arm.moved_by == "the robot calibration session"
    arm.release(second)


def test_a_claim_released_with_its_motion_left_ends_when_the_arm_has_arrived():
    arm = ArmLease()
    claim = arm.claim("the hand-eye session's move to proposal #3")
    arm.release(claim, after_s=0.3)
    with pytest.raises(ArmBusy, match=r"proposal #3"):
        arm.claim("the table1 accuracy test")
    time.sleep(0.35)
    assert arm.moved_by is None
    arm.release(arm.claim("the table1 accuracy test"))


def test_of_many_threads_claiming_at_once_exactly_one_wins():
    arm, won, barrier = ArmLease(), [], threading.Barrier(8)

    def contend(k: int) -> None:
        barrier.wait()
        try:
            arm.claim(f"workflow {k}")
            won.append(k)
        except ArmBusy:
            pass

    threads = [threading.Thread(target=contend, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(won) == 1 and arm.moved_by == f"workflow {won[0]}"
