"""The full frame's external contours (:mod:`service.core.targets.detect_candidates`), compiled (numba).

:func:`external_contours_kernel` is ``cv2.findContours(mask, cv2.RETR_EXTERNAL,
cv2.CHAIN_APPROX_SIMPLE)`` written out: Suzuki and Abe's border following as OpenCV 4.x does it
(``contours_new.cpp``: the same raster scan, the same marks on the traced borders, the same test
for a blob inside another's hole), giving the same vertices in the same order. Its vertices go
straight into :func:`~service.core._kernels.contour_kernel.contour_stats_kernel`, so the frame's
candidates are bit for bit those of OpenCV's contours.

Why: on a 1300 x 1030 frame with ~300 blobs, ``cv2.findContours`` cost 0.7-1.2 ms, a seventh of a
frame: a padded, thresholded copy of the mask, the scan, and one numpy array per contour (then
joined). Here the scan skips empty mask 8 bytes at a time and marks the borders in the mask itself
(which the caller gives up: the foreground mask is a scratch buffer), and the vertices come out in
three arrays.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

# the mask's values while tracing: foreground (a 0/255 mask's 255, OpenCV's 1), a traced border
# pixel (OpenCV's "new" mark, +2) and a traced border pixel whose right neighbour is background
# (OpenCV's "right" mark, 2 | 0x80: negative as a signed byte)
FG, NEW, RIGHT = 255, 2, 130
# chain codes 0..7 (east, then counter-clockwise as displayed: v runs down), twice over
_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1, 1, 1, 0, -1, -1, -1, 0, 1], dtype=np.intp)
_DY = np.array([0, -1, -1, -1, 0, 1, 1, 1, 0, -1, -1, -1, 0, 1, 1, 1], dtype=np.intp)


@njit(cache=True, nogil=True, inline="always")
def _at(flat, w, h, x, y, i, s, off):
    """The mask at the chain-code ``s`` neighbour of pixel (x, y) (flat index ``i``, neighbours at
    ``off``); 0 beyond the image, which OpenCV pads with a one-pixel frame of background."""
    if not (x > 0 and y > 0 and x < w - 1 and y < h - 1):  # on the border: test the neighbour
        xn, yn = x + _DX[s], y + _DY[s]
        if xn < 0 or yn < 0 or xn >= w or yn >= h:
            return 0
    return flat[np.uint64(i + off[s])]  # unsigned: no test for a negative index


@njit(cache=True, nogil=True, error_model="numpy")
def _trace(flat, w, h, x0, y0, off, pts, n):
    """Follow the outer border that starts at pixel (x0, y0), marking it in the mask ``flat``
    (H * W,), whose chain-code neighbours are at the flat offsets ``off`` (16,); append its
    vertices (CHAIN_APPROX_SIMPLE: where the direction changes), px, to ``pts`` from row ``n``,
    growing it as needed. Returns (pts, n) after them (OpenCV's ``icvFetchContourEx`` for an outer
    border)."""
    i0 = y0 * w + x0
    s_end = 4
    s = s_end
    while True:
        s = (s - 1) & 7
        if _at(flat, w, h, x0, y0, i0, s, off) != 0 or s == s_end:
            break
    if s == s_end:  # a single pixel
        flat[i0] = RIGHT
        if n >= pts.shape[0]:
            pts = _grow(pts)
        pts[n, 0], pts[n, 1] = x0, y0
        return pts, n + 1
    i1 = i0 + off[s]
    x3, y3, i3 = x0, y0, i0
    prev_s = s ^ 4
    while True:
        s_end = s
        s = min(s, 15)
        if x3 > 0 and y3 > 0 and x3 < w - 1 and y3 < h - 1:  # away from the border: no test per neighbour
            while s < 15:
                s += 1
                if flat[np.uint64(i3 + off[s])] != 0:  # unsigned: no test for a negative index
                    break
        else:
            while s < 15:
                s += 1
                if _at(flat, w, h, x3, y3, i3, s, off) != 0:
                    break
        i4 = i3 + off[s]
        s &= 7
        if 1 <= s <= s_end:  # OpenCV's (unsigned)(s - 1) < (unsigned)s_end: the right neighbour was passed
            flat[i3] = RIGHT
        elif flat[i3] == FG:
            flat[i3] = NEW
        if s != prev_s:
            if n >= pts.shape[0]:
                pts = _grow(pts)
            pts[n, 0], pts[n, 1] = x3, y3
            n += 1
        prev_s = s
        if i4 == i0 and i3 == i1:
            break
        x3, y3, i3 = x3 + _DX[s], y3 + _DY[s], i4
        s = (s + 4) & 7
    return pts, n


@njit(cache=True, nogil=True)
def _grow(a):
    b = np.empty((2 * a.shape[0], a.shape[1]), dtype=a.dtype)
    b[: a.shape[0]] = a
    return b


@njit(cache=True, nogil=True, error_model="numpy")
def external_contours_kernel(m, words):
    """The external contours of the 0/255 mask ``m`` (H, W) uint8, as ``cv2.findContours(m,
    RETR_EXTERNAL, CHAIN_APPROX_SIMPLE)`` gives them: vertices (M, 2) int32 (u, v) px, and each
    contour's start and length in them (C,), in OpenCV's order. ``words`` is ``m``'s first
    ``m.size // 8 * 8`` bytes as uint64 (the empty mask is skipped a word at a time).

    ``m`` is overwritten: its traced border pixels are marked (:data:`NEW`, :data:`RIGHT`).
    """
    h, w = m.shape
    flat = m.reshape(-1)
    pts = np.empty((4096, 2), dtype=np.int32)
    starts = np.empty(256, dtype=np.intp)
    n, nc = 0, 0
    off = np.empty(16, dtype=np.intp)
    for k in range(16):
        off[k] = _DX[k] + _DY[k] * w
    for y in range(1, h + 1):  # padded coordinates: pixel (x - 1, y - 1)
        base = (y - 1) * w - 1  # flat index of padded (x, y) is base + x
        end = base + w + 1  # padded x < w + 1
        x, prev, lx = 1, 0, 0  # lx: OpenCV's last_pos.x, the last traced border met on the row
        while True:
            # the next x whose value differs from prev
            i = base + x
            if prev == 0:
                while i < end and (i & 7) != 0 and flat[i] == 0:
                    i += 1
                if i < end and flat[i] == 0:
                    while i + 8 <= end and words[i >> 3] == 0:
                        i += 8
                    while i < end and flat[i] == 0:
                        i += 1
            else:
                while i < end and flat[i] == prev:
                    i += 1
            if i >= end:
                break
            x = i - base
            p = flat[i]
            if prev == 0 and p == FG:  # an outer border starts here
                # ... unless the last border met on the row is an outer one whose inside this is
                last = 0 if lx < 1 else m[y - 1, lx - 1]
                if last != FG and last != NEW:
                    lx = x
                    if nc >= starts.size:
                        grown = np.empty(2 * starts.size, dtype=np.intp)
                        grown[: starts.size] = starts
                        starts = grown
                    starts[nc] = n
                    nc += 1
                    pts, n = _trace(flat, w, h, x - 1, y - 1, off, pts, n)
                    prev = m[y - 1, x - 1]
                    x += 1
                    continue
            elif p == 0 and prev == NEW:  # a hole starts here (not traced), as OpenCV notes its last border
                lx = x - 1
            prev = p
            if prev == NEW or prev == RIGHT:
                lx = x
            x += 1
    # OpenCV lists the contours last found first
    lengths = np.empty(nc, dtype=np.intp)
    out = np.empty((n, 2), dtype=np.int32)
    out_starts = np.empty(nc, dtype=np.intp)
    k = 0
    for c in range(nc - 1, -1, -1):
        s0 = starts[c]
        L = (starts[c + 1] if c + 1 < nc else n) - s0
        out[k : k + L] = pts[s0 : s0 + L]
        out_starts[nc - 1 - c] = k
        lengths[nc - 1 - c] = L
        k += L
    return out, out_starts, lengths


def words_of(mask: np.ndarray) -> np.ndarray:
    """``mask``'s (C-contiguous uint8) whole 8-byte words as uint64, sharing its memory."""
    flat = mask.reshape(-1)
    return flat[: flat.size // 8 * 8].view(np.uint64)


@lru_cache(maxsize=1)  # once per process
def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for the foreground mask."""
    m = np.zeros((16, 16), dtype=np.uint8)
    m[4:8, 4:9] = 255
    external_contours_kernel(m, words_of(m))
