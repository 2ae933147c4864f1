"""posecell's coded target: a central measuring disk and a concentric code ring.

The design is the Schneider / van den Heuvel type the paper names (section 4.2).
Geometry, in the target's own plane (mm, origin at the disk centre, the target's
local x and y axes lying in the field plane; for a plate, the field's x and y)::

    disk:       r <= R                       (R = diameter_mm / 2; always bright)
    code ring:  RING_INNER * R <= r <= RING_OUTER * R, split into N_BITS sectors;
                sector k spans angles [k, k+1) * 360/N_BITS deg measured from local +x
                towards local +y; bit k = 1 means that sector is bright.

Code family: 12-bit words that are *aperiodic necklaces of even weight*. A code
is identified by its rotation class (the decoder never knows the target's
roll), represented by the smallest integer among its rotations. Even weight is
rotation invariant, so any single bit error yields an odd-weight word, which no
code is: one bit error is always detected, never read as another code. Aperiodic
words read the same under exactly one rotation per sector step, so the roll
angle is determined too. Codes are numbered 1..N in increasing canonical value.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

N_BITS = 12
RING_INNER = 2.0
RING_OUTER = 3.2
# Runs of equal bits make the ring easy to segment; forbid runs longer than this
# so that at least one transition falls in every third of the ring.
MAX_RUN = N_BITS // 2


def _rotations(word: int) -> list[int]:
    mask = (1 << N_BITS) - 1
    return [((word << k) | (word >> (N_BITS - k))) & mask for k in range(N_BITS)]


def canonical(word: int) -> int:
    """Smallest rotation of a ``N_BITS``-bit word: the identity of a ring pattern under roll.

    >>> canonical(0b000000000011) == canonical(0b110000000000)
    True
    """
    return min(_rotations(word))


def _max_circular_run(word: int) -> int:
    bits = [(word >> k) & 1 for k in range(N_BITS)]
    if all(b == bits[0] for b in bits):
        return N_BITS
    start = next(k for k in range(N_BITS) if bits[k] != bits[k - 1])
    best = run = 0
    for i in range(N_BITS):
        b = bits[(start + i) % N_BITS]
        run = run + 1 if i > 0 and b == bits[(start + i - 1) % N_BITS] else 1
        best = max(best, run)
    return best


@lru_cache(maxsize=1)
def code_words() -> tuple[int, ...]:
    """Canonical words of the code family, index ``code - 1``.

    >>> len(code_words()) >= 100
    True
    """
    words = set()
    for w in range(1, (1 << N_BITS) - 1):
        if bin(w).count("1") % 2:
            continue
        rots = _rotations(w)
        if len(set(rots)) != N_BITS:  # periodic: roll would be ambiguous
            continue
        if _max_circular_run(w) > MAX_RUN:
            continue
        words.add(min(rots))
    return tuple(sorted(words))


def n_codes() -> int:
    return len(code_words())


def bits_of(code: int) -> NDArray[np.bool_]:
    """Sector bits (N_BITS,) of ``code`` (1-based); bit k is sector k.

    >>> bits_of(1).shape
    (12,)
    """
    words = code_words()
    if not 1 <= code <= len(words):
        raise ValueError(f"code {code} is outside 1..{len(words)}")
    w = words[code - 1]
    return np.array([(w >> k) & 1 for k in range(N_BITS)], dtype=bool)


@lru_cache(maxsize=1)
def _code_of_word() -> dict[int, tuple[int, int]]:
    """Every rotation of every code word -> (code, rotation steps)."""
    table: dict[int, tuple[int, int]] = {}
    for i, w in enumerate(code_words()):
        for k, r in enumerate(_rotations(w)):
            table[r] = (i + 1, k)
    return table


def code_from_bits(bits: NDArray[np.bool_]) -> tuple[int, int] | None:
    """(code, roll in sectors) of a read bit pattern, or None if it is no code (e.g. one bit wrong).

    >>> code_from_bits(bits_of(7))[0]
    7
    """
    b = np.asarray(bits, dtype=bool).reshape(N_BITS)
    word = int(np.sum(b.astype(np.int64) << np.arange(N_BITS)))
    return _code_of_word().get(word)


@lru_cache(maxsize=1)
def word_table() -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(code, roll in sectors) of every ``N_BITS``-bit word, two read-only (2**N_BITS,) arrays.

    Code 0 means the word is no code. The vectorised form of :func:`code_from_bits`:
    ``code[word]`` with ``word = sum(bits[k] << k)``.

    >>> code, roll = word_table()
    >>> int(code[code_words()[6]]), int(roll[code_words()[6]])
    (7, 0)
    """
    code = np.zeros(1 << N_BITS, dtype=np.int64)
    roll = np.zeros(1 << N_BITS, dtype=np.int64)
    for word, (c, k) in _code_of_word().items():
        code[word] = c
        roll[word] = k
    code.flags.writeable = False
    roll.flags.writeable = False
    return code, roll


def bright_runs(code: int) -> list[tuple[int, int]]:
    """Runs of bright sectors of ``code``: (first sector, number of sectors), wrapping past 0.

    Drawing a run as one shape avoids the hairline seams that anti-aliased
    renderers and printers leave between adjacent shapes.

    >>> sum(n for _, n in bright_runs(7)) == int(bits_of(7).sum())
    True
    """
    b = bits_of(code)
    # Start scanning just after a dark sector so that no run is split at sector 0.
    start = int(np.flatnonzero(~b)[0]) + 1
    runs: list[tuple[int, int]] = []
    k = 0
    while k < N_BITS:
        s = (start + k) % N_BITS
        if b[s]:
            n = 0
            while k < N_BITS and b[(start + k) % N_BITS]:
                n += 1
                k += 1
            runs.append((s, n))
        else:
            k += 1
    return runs
