"""The accuracy analyses' input checks, once: a malformed input is ``SolveError(bad_input)`` with a
sentence naming it, whichever analysis it was given to (the CLI and the API turn that reason into
exit 2 and HTTP 422; a bare ``ValueError`` would have been an internal error there)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.core.results import Reason, SolveError

Array = NDArray[np.float64]


def bad_input(message: str) -> SolveError:
    return SolveError(Reason.bad_input, message)


def finite(x: ArrayLike, name: str, shape: tuple[int | None, ...] | None = None) -> Array:
    """``x`` as float64, every value finite; of ``shape`` when given (``None`` in it: any length)."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise bad_input(f"{name} must be numbers.") from None
    if shape is not None and (
        a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape, strict=True))
    ):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise bad_input(f"{name} must have shape {want}, not {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise bad_input(f"{name} contains NaN or infinity.")
    return a
