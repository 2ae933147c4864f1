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

from collections.abc import Callable
from dataclasses import dataclass
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


# -- code families ----------------------------------------------------------


@dataclass(frozen=True)
class CodeFamily:
    """A ring code the reader (:mod:`service.core.targets.decode`) can decode.

    Every family shares the layout of a bright disk (r <= R), a dark gap and a
    ring of ``n_bits`` equal sectors numbered counter-clockwise as the target
    is seen from its front, bit 1 = bright; codes are numbered 1..N in the order
    of ``code_words()``, each word the smallest rotation of its ring pattern.

    name : str
        Short name, as the CLI's ``--code-family`` takes it.
    n_bits : int
        Sectors in the ring.
    ring_inner, ring_outer : float
        The ring's edges, in disk radii.
    ring_radii : tuple of float, even length
        Radii (disk radii) at which the ring is sampled, inside the ring with a
        margin for blur and ellipse error; the first half are "inner", the rest "outer".
    code_words : callable
        Returns the canonical words, index ``code - 1`` (cached by its module).
    """

    name: str
    n_bits: int
    ring_inner: float
    ring_outer: float
    ring_radii: tuple[float, ...]
    code_words: Callable[[], tuple[int, ...]]

    def __post_init__(self) -> None:
        r = self.ring_radii
        if not (len(r) >= 2 and len(r) % 2 == 0 and self.ring_inner < min(r) and max(r) < self.ring_outer):
            raise ValueError(
                f"{self.name}: ring_radii {r} must be an even number of radii inside "
                f"[{self.ring_inner}, {self.ring_outer}]"
            )

    @property
    def n_codes(self) -> int:
        return len(self.code_words())


@lru_cache(maxsize=8)
def family_word_table(family: CodeFamily) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(code, roll in sectors) of every ``family.n_bits``-bit word: two read-only (2**n_bits,) arrays.

    Code 0 means the word is no code. A word with a period (possible in some
    families, e.g. the 14-bit words of period 7) gets its smallest roll.

    >>> code, roll = family_word_table(POSECELL12)
    >>> bool(np.array_equal(code, word_table()[0]) and np.array_equal(roll, word_table()[1]))
    True
    """
    n = family.n_bits
    mask = (1 << n) - 1
    code = np.zeros(1 << n, dtype=np.int64)
    roll = np.zeros(1 << n, dtype=np.int64)
    for i, w in enumerate(family.code_words()):
        for k in reversed(range(n)):  # the smallest roll is written last and wins
            r = ((w << k) | (w >> (n - k))) & mask
            code[r], roll[r] = i + 1, k
    code.flags.writeable = False
    roll.flags.writeable = False
    return code, roll


def _aicon14_words() -> tuple[int, ...]:
    from service.core.targets import codes_micmac  # generating its 516 words takes ~0.1 s: only when asked

    return codes_micmac.code_words()


#: posecell's own 12-bit family (this module): ring 2.0-3.2 R.
POSECELL12 = CodeFamily("posecell12", N_BITS, RING_INNER, RING_OUTER, (2.3, 2.5, 2.7, 2.9), code_words)
#: The AICON / MicMac MMVII "CERN 14" family (:mod:`service.core.targets.codes_micmac`): ring 2.0-3.0 R,
#: code = the AICON number. Sampled at 2.25-2.75 R as MMVII does: the ring's outer edge is 3.0 R.
AICON14 = CodeFamily("aicon14", 14, 2.0, 3.0, (2.25, 2.4167, 2.5833, 2.75), _aicon14_words)
#: The families by name.
FAMILIES = {f.name: f for f in (POSECELL12, AICON14)}
