"""The 14-bit ring code of AICON-style retro-reflective targets, as MicMac MMVII reads them.

This is the family that ``MMVII CodedTargetGenerateEncoding CERN 14`` selects
(file ``CERN_Nbb14_Freq14_Hamm1_Run1000_1000_SpecEncoding.xml``). MMVII does
not invent it: it takes the AICON numbering from its resource file
``MMVII-RessourceDir/CodeCircTaget/14bit_lookup.txt`` (516 lines ``number
lowest-rotation-word``). The same 516 words follow from the rule of patent
DE19733466A1, which is how they are generated here (checked against that file
word for word):

* a word is a 14-bit necklace, identified by its smallest rotation;
* its weight (number of bright sectors) is even;
* at least one pair of diametrically opposite sectors (k, k + 7) is bright;
* the all-bright ring is excluded.

Codes are numbered 1..516 in increasing order of that smallest rotation; the
number is the target's name (``Positions-3D-14bit_lookup.txt`` writes ``2``,
MMVII writes it on 3 digits, ``002``; see :func:`mmvii_name`).

Geometry, in units of the central disk radius R, target seen from its front::

    disk:       r <= 1                 bright
    gap:        1 < r < 2              dark
    code ring:  2 <= r <= 3            14 sectors of 360/14 deg; bit 1 = bright
    outside:    r > 3                  dark (the plate)

Bit k (``word >> k & 1``) is sector k; k increases counter-clockwise as the
target is seen from its front, i.e. counter-clockwise on screen in an image
whose v axis runs down (the same sense as :mod:`service.core.targets.codes`). Read
clockwise, 416 of the 516 words turn into *another valid word*, so the sense
matters; pass ``clockwise=True`` if the bits were sampled the other way round.

The family's minimum Hamming distance under rotation is 2: one wrong bit gives
an odd weight, which is no code, two wrong bits can give another code. 18 words
have period 7 (e.g. code 49, ``00000110000011``): their roll is only known
modulo 180 deg.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

N_BITS = 14
RING_INNER = 2.0
RING_OUTER = 3.0
_HALF = N_BITS // 2
_MASK = (1 << N_BITS) - 1


def _rotate(word: int, k: int) -> int:
    """Rotation by k sectors: bit i moves to bit i + k (mod 14)."""
    k %= N_BITS
    return ((word << k) | (word >> (N_BITS - k))) & _MASK


def canonical(word: int) -> int:
    """Smallest rotation of a 14-bit word.

    >>> canonical(0b11 << 9)
    3
    """
    return min(_rotate(word, k) for k in range(N_BITS))


@lru_cache(maxsize=1)
def code_words() -> tuple[int, ...]:
    """Canonical words, index ``number - 1`` (AICON / MMVII numbering).

    >>> w = code_words()
    >>> len(w), w[0], w[2], w[48], w[49], w[-1]
    (516, 129, 139, 387, 389, 8127)
    """
    words = set()
    for w in range(1, _MASK):  # 0 and the all-bright word excluded
        if bin(w).count("1") % 2:
            continue
        if not (w & (w >> _HALF) & ((1 << _HALF) - 1)):  # no opposite pair both bright
            continue
        words.add(canonical(w))
    return tuple(sorted(words))


def codes() -> list[tuple[str, int]]:
    """(name, canonical word) of every code; the name is the number as the AICON file writes it.

    >>> codes()[:2]
    [('1', 129), ('2', 135)]
    """
    return [(str(i + 1), w) for i, w in enumerate(code_words())]


def mmvii_name(name: str | int) -> str:
    """The name MMVII gives the same target: the number on 3 digits.

    >>> mmvii_name("2"), mmvii_name(516)
    ('002', '516')
    """
    return f"{int(name):03d}"


def bits_of(name: str | int) -> np.ndarray:
    """Sector bits (14,) of the code named ``name`` at roll 0.

    >>> "".join(str(int(b)) for b in bits_of("3"))
    '11010001000000'
    """
    words = code_words()
    n = int(name)
    if not 1 <= n <= len(words):
        raise ValueError(f"code {name} is outside 1..{len(words)}")
    return np.array([(words[n - 1] >> k) & 1 for k in range(N_BITS)], dtype=bool)


@lru_cache(maxsize=1)
def _table() -> dict[int, tuple[str, int]]:
    """Every rotation of every word -> (name, smallest roll giving it)."""
    table: dict[int, tuple[str, int]] = {}
    for name, w in codes():
        for k in range(N_BITS):
            table.setdefault(_rotate(w, k), (name, k))
    return table


def name_from_bits(bits: ArrayLike, clockwise: bool = False) -> tuple[str, int] | None:
    """(name, roll) of a ring read as 14 bits, or None if it is no code word.

    ``bits[i]`` is the i-th sector met going counter-clockwise (seen from the
    front) from wherever the reading started. ``roll`` is the number of sectors
    such that ``bits == np.roll(bits_of(name), roll)``, i.e. the target's
    sector 0 was read as ``bits[roll]``. For the 18 period-7 words the smaller of
    the two possible rolls is returned. ``clockwise=True`` takes bits read in
    the opposite sense; the roll is then still counted in the reading's order.

    >>> name_from_bits(np.roll(bits_of("37"), 5))
    ('37', 5)
    >>> name_from_bits(bits_of("37")[::-1], clockwise=True)
    ('37', 13)
    >>> name_from_bits(bits_of("37")[::-1])  # the same ring read the wrong way round
    ('51', 5)
    >>> b = bits_of("37"); b[0] = ~b[0]
    >>> name_from_bits(b) is None  # one bit wrong: odd weight
    True
    """
    b = np.asarray(bits, dtype=bool).reshape(N_BITS)
    if clockwise:
        b = b[::-1]
    word = int(np.sum(b.astype(np.int64) << np.arange(N_BITS)))
    hit = _table().get(word)
    if hit is None:
        return None
    name, roll = hit
    if clockwise:
        roll = (-roll - 1) % N_BITS  # position of sector 0 in the original reading order
    return name, roll
