"""The accuracy analyses' one input check: a malformed input is bad_input with a sentence naming it."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.accuracy.inputs import finite
from service.core.accuracy.segment import group_positions
from service.core.results import Reason, SolveError


def test_finite_returns_float64_of_the_shape_asked_for():
    a = finite([[1, 2, 3], [4, 5, 6]], "p_mm", (None, 3))
    assert a.dtype == np.float64 and a.shape == (2, 3)


@pytest.mark.parametrize(
    ("x", "shape", "match"),
    [
        ([[1.0, 2.0]], (None, 3), r"p_mm must have shape \(N, 3\), not \(1, 2\)"),
        ([1.0, 2.0, 3.0], (None, 3), r"p_mm must have shape \(N, 3\), not \(3,\)"),
        ([1.0, 2.0], (3,), r"p_mm must have shape \(3,\)"),
        ([[np.nan, 0.0, 0.0]], (None, 3), "p_mm contains NaN or infinity"),
        ([["a", "b", "c"]], None, "p_mm must be numbers"),
    ],
)
def test_a_malformed_input_is_named(x, shape, match):
    with pytest.raises(SolveError, match=match) as e:
        finite(x, "p_mm", shape)
    assert e.value.reason is Reason.bad_input


def test_the_segmentation_refuses_like_the_analyses():
    with pytest.raises(SolveError, match="contains NaN") as e:
        group_positions(np.full((3, 3), np.inf))
    assert e.value.reason is Reason.bad_input
