"""The compiled (numba) loops of the core; each module says what it computes and why by hand.

Every kernel is compiled with ``nogil=True``: the service measures in one thread while others
acquire, encode and send; a kernel that kept the interpreter's lock held them all (a fifth of the
lock's time at 500 frames/s was the ROI windows' kernel alone).

Kernels call each other across modules, which numba's disk cache does not follow:
:func:`service.pipeline.compile.refresh_kernel_caches` empties the caches when any module changed.
"""

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray


def warm_images(dtypes: tuple[type, ...], shape: tuple[int, int] = (32, 32)) -> Iterator[NDArray[Any]]:
    """A zero image of each dtype, writeable and read-only, for the warm-ups: numba compiles a kernel
    once per argument type and a read-only array is another type (a replayed or memory-mapped frame
    is read-only; without it, its first frame compiled the reader and the noise kernels, ~15 s)."""
    for dtype in dtypes:
        img: NDArray[Any] = np.zeros(shape, dtype=dtype)
        frozen = img.view()
        frozen.flags.writeable = False
        yield img
        yield frozen


def kernel_array(a: Any, dtype: Any = np.float64) -> NDArray[Any]:
    """``a`` as the one array type the kernels are compiled for: C-contiguous, writeable, ``dtype``.
    ``np.require``'s answer, in a fraction of a microsecond when ``a`` already is one (the usual
    case): its general path costs ~3.5 us, and an ROI frame asked it some fifteen times."""
    if type(a) is np.ndarray and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.require(a, dtype, ["C", "W"])


def kernel_vector(a: Any, n: int, dtype: Any = np.float64) -> NDArray[Any]:
    """``a`` (a scalar, or n values) as a kernel array (n,) of ``dtype``. Not by ``np.broadcast_to``
    when ``a`` already holds n values: its read-only view then took np.require's copy, ~7 us twice
    an ROI frame (the windows' half sizes, the disks' radii)."""
    if type(a) is np.ndarray and a.shape == (n,):
        return kernel_array(a, dtype)
    return np.full(n, a, dtype=dtype)
