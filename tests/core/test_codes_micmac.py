"""The MMVII / AICON 14-bit family, checked against MicMac's own table and real images.

The images are MicMac's ``Circ-Code-Target`` data set (../shared/data/micmac-circ-code-target).
Each case below is a target whose name is known independently of this module: its
image position fits the panel coordinates of ``Positions-3D-14bit_lookup.txt``
under that name (a homography from the panel plane to the image, fitted on all the
targets of the image, passes within 4 px of it).
"""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

from service.core.targets.codes_micmac import (
    N_BITS,
    RING_INNER,
    RING_OUTER,
    bits_of,
    code_words,
    codes,
    name_from_bits,
)
from tests.conftest import shared_data

DATA = "micmac-circ-code-target"

# (image, approximate centre of the central disk in px, name in Positions-3D-14bit_lookup.txt)
CASES = [
    ("043_0019_Scaled.tif", (777, 1025), "3"),
    ("043_0019_Scaled.tif", (779, 819), "13"),
    ("043_0019_Scaled.tif", (781, 621), "23"),
    ("043_0019_Scaled.tif", (606, 426), "32"),
    ("043_0019_Scaled.tif", (1132, 456), "35"),
    ("043_0009_Scaled.tif", (652, 388), "11"),
    ("043_0009_Scaled.tif", (782, 495), "21"),
    ("043_0009_Scaled.tif", (1340, 584), "49"),  # a period-7 word
    ("043_0027_Scaled.tif", (374, 740), "63"),
]


def test_family_is_mmvii_14bit_lookup_table():
    # sha1 of the comma-joined second column of MMVII-RessourceDir/CodeCircTaget/14bit_lookup.txt
    # (micmacIGN/micmac), whose first column is 1..516 in order.
    words = code_words()
    joined = ",".join(map(str, words)).encode()
    assert len(words) == 516
    assert hashlib.sha1(joined).hexdigest() == "163f097c3ed767e01857e28284b556c8940e860e"
    assert [n for n, _ in codes()] == [str(i) for i in range(1, 517)]


def test_every_roll_of_every_code_reads_back():
    for name, _ in codes():
        for roll in range(N_BITS):
            got = name_from_bits(np.roll(bits_of(name), roll))
            assert got is not None and got[0] == name
            assert np.array_equal(np.roll(bits_of(name), got[1]), np.roll(bits_of(name), roll))


def test_single_bit_errors_are_never_read_as_a_code():
    for name, _ in codes()[::7]:
        for k in range(N_BITS):
            b = bits_of(name)
            b[k] = ~b[k]
            assert name_from_bits(b) is None


def _read_ring(img: np.ndarray, centre: tuple[int, int]) -> np.ndarray:
    """14 bits, counter-clockwise on screen, of the target whose disk is near ``centre``."""
    x0, y0 = centre[0] - 40, centre[1] - 40
    crop = img[y0 : y0 + 80, x0 : x0 + 80]
    _, bw = cv2.threshold(crop, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    _, lab = cv2.connectedComponents(bw)
    disk = (lab == lab[40, 40]).astype(np.uint8)
    assert lab[40, 40] != 0, "the given centre is not on a bright disk"
    contours, _ = cv2.findContours(disk, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    (cx, cy), (w, h), ang = cv2.fitEllipse(max(contours, key=len))
    u = np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))])
    v = np.array([-u[1], u[0]])
    per = 8
    t = -2 * np.pi * np.arange(N_BITS * per) / (N_BITS * per)  # minus: counter-clockwise on screen

    def ring(r: float, angles: np.ndarray) -> np.ndarray:
        p = np.array([cx + x0, cy + y0]) + r * (
            (w / 2) * np.cos(angles)[:, None] * u + (h / 2) * np.sin(angles)[:, None] * v
        )
        m = p.astype(np.float32)
        return cv2.remap(img.astype(np.float32), m[None, :, 0], m[None, :, 1], cv2.INTER_LINEAR)[0]

    radii = np.linspace(RING_INNER + 0.3, RING_OUTER - 0.3, 4)
    prof = np.mean([ring(r, t) for r in radii], axis=0)
    threshold = 0.5 * (np.median(ring(0.5, t)) + np.median(ring(0.5 * (1 + RING_INNER), t)))

    def sectors(phase: int) -> np.ndarray:  # (14, per - 2): each sector without its edges
        return np.roll(prof, -phase).reshape(N_BITS, per)[:, 1:-1]

    best = min(range(per), key=lambda ph: sectors(ph).std(axis=1).sum())
    return sectors(best).mean(axis=1) > threshold


@pytest.mark.parametrize(("image", "centre", "name"), CASES)
def test_real_target_reads_as_its_name(image, centre, name):
    folder = shared_data(DATA)
    img = cv2.imread(str(folder / "images" / image), cv2.IMREAD_GRAYSCALE)
    assert img is not None
    bits = _read_ring(img, centre)
    got = name_from_bits(bits)
    assert got is not None, f"read {bits.astype(int)}, no code"
    assert got[0] == name
    # the same bits handed over as a clockwise reading give the mirrored word's name
    mirrored = name_from_bits(bits[::-1], clockwise=True)
    assert mirrored is not None and mirrored[0] == name


def test_real_targets_read_clockwise_give_wrong_names():
    # the reading sense is not a convention one may pick: read clockwise, most targets
    # decode to another valid name
    folder = shared_data(DATA)
    wrong = 0
    for image, centre, name in CASES:
        img = cv2.imread(str(folder / "images" / image), cv2.IMREAD_GRAYSCALE)
        got = name_from_bits(_read_ring(img, centre)[::-1])
        wrong += got is None or got[0] != name
    assert wrong >= len(CASES) - 3


def test_names_are_coded_targets_of_the_panel():
    folder = shared_data(DATA)
    text = (folder / "Positions-3D-14bit_lookup.txt").read_text()
    names = [line.split()[0] for line in text.splitlines() if line.strip()]
    coded = [n for n in names if int(n) <= len(code_words())]
    assert coded == [str(i) for i in range(2, 75)]  # 2..74 coded; 2001..2166 uncoded dots
    assert all(name in names for _, _, name in CASES)
