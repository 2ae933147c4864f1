"""A frame's target list as JSON text, compiled (numba).

Every result message carries its ~230 targets (id, pixel, residual). Formatting their ~900
numbers was the measurement process's largest cost after the measurement itself: orjson
writes a float in ~65 ns and the per-target text took Python string work on top (~0.24 ms a
frame). Here the numbers are written as what they are on the wire, decimals of 4 places
(``np.round(x, 4)``), by integer arithmetic into one byte buffer: the same text orjson writes
of the rounded floats (checked in ``tests/core/kernels/test_json_kernel.py``) wherever
|x| < :data:`LIMIT`; the caller encodes other tables (NaN, huge values) as before.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit
from numpy.typing import NDArray

LIMIT = 1e9  # below it a rounded value's shortest text is its 4-place decimal, trailing zeros cut

_OPEN_UV = np.frombuffer(b',"uv":[', dtype=np.uint8)
_OPEN_RES = np.frombuffer(b'],"residual_px":[', dtype=np.uint8)
_CLOSE = np.frombuffer(b"]}", dtype=np.uint8)
_CLOSE_REJECTED = np.frombuffer(b'],"rejected":true}', dtype=np.uint8)
_OPEN_ID = np.frombuffer(b'{"id":', dtype=np.uint8)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _put(buf, k, text):
    for j in range(text.size):
        buf[k + j] = text[j]
    return k + text.size


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _number(buf, k, x):
    """Write ``np.round(x, 4)`` as orjson does ("-0.0", "12.5", "0.0001") at ``k``; returns the end."""
    q = np.rint(x * 1e4)
    if q < 0 or (q == 0 and np.copysign(1.0, q) < 0):
        buf[k] = 45  # "-"
        k += 1
        q = -q
    units = np.int64(q)
    whole, frac = units // 10000, units % 10000
    # the integer part's digits, most significant first
    digits = 1
    p = np.int64(10)
    while p <= whole:
        digits += 1
        p *= 10
    for j in range(digits - 1, -1, -1):
        buf[k + j] = 48 + whole % 10
        whole //= 10
    k += digits
    buf[k] = 46  # "."
    k += 1
    if frac == 0:
        buf[k] = 48
        return k + 1
    places = 4
    while frac % 10 == 0:
        frac //= 10
        places -= 1
    for j in range(places - 1, -1, -1):
        buf[k + j] = 48 + frac % 10
        frac //= 10
    return k + places


@njit(cache=True, nogil=True, error_model="numpy")
def targets_json_kernel(ids, uv, residual, used, open_id, open_uv, open_res, close, close_rejected):
    """The UTF-8 bytes of ``[{"id":..,"uv":[u,v],"residual_px":[ru,rv]}, ...]`` (a rejected target
    ends ``,"rejected":true}``): ``ids`` the bytes of the JSON array of the n ids (strings, as
    orjson writes them: a quote inside one is escaped), ``uv`` and ``residual`` (n, 2) px, each
    |value| < LIMIT; ``used`` (n,) bool."""
    n = uv.shape[0]
    size = ids.size + n * (open_id.size + open_uv.size + open_res.size + close_rejected.size + 4 * 16 + 2)
    buf = np.empty(size, dtype=np.uint8)
    buf[0] = 91  # "["
    k, c = 1, 1  # c: in ids, after the "[" and then after each string's ","
    for i in range(n):
        if i:
            buf[k] = 44  # ","
            k += 1
        k = _put(buf, k, open_id)
        # the id's string, quotes included: up to the first quote not escaped
        buf[k] = ids[c]
        k += 1
        c += 1
        escaped = False
        while escaped or ids[c] != 34:
            escaped = not escaped and ids[c] == 92  # a backslash escapes the next character
            buf[k] = ids[c]
            k += 1
            c += 1
        buf[k] = 34
        k += 1
        c += 2  # the closing quote and the comma
        k = _put(buf, k, open_uv)
        k = _number(buf, k, uv[i, 0])
        buf[k] = 44
        k = _number(buf, k + 1, uv[i, 1])
        k = _put(buf, k, open_res)
        k = _number(buf, k, residual[i, 0])
        buf[k] = 44
        k = _number(buf, k + 1, residual[i, 1])
        k = _put(buf, k, close if used[i] else close_rejected)
    buf[k] = 93  # "]"
    return buf[: k + 1]


def targets_json(ids: bytes, uv: NDArray[np.float64], residual: NDArray[np.float64], used: NDArray[np.bool_]) -> bytes:
    """:func:`targets_json_kernel` with the fixed pieces of text (``ids``: ``orjson.dumps`` of them)."""
    return targets_json_kernel(
        np.frombuffer(ids, dtype=np.uint8), uv, residual, used, _OPEN_ID, _OPEN_UV, _OPEN_RES, _CLOSE, _CLOSE_REJECTED
    ).tobytes()


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for the types the results pass."""
    targets_json(b'["a","b"]', np.ones((2, 2)), np.ones((2, 2)), np.ones(2, dtype=np.bool_))
