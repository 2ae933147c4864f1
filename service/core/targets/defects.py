"""A sensor's defect pixels: found in a stack of frames, and patched before a frame is measured.

A hot pixel (dark current, a pixel stuck high) sits at the same place in every frame. The
measurement takes a lone bright pixel for a speck, but inside a target's window it is part of the
window's moments and edges: on the reference scene with 0.05 % of the pixels hot (669 of them,
at 250 DN) 125 of ~9 000 centres moved by more than 0.05 px (up to 0.19), and ROI tracking, whose
windows refuse a second bright blob, lost 21 of 226 targets a frame. A dead pixel (no response, a
pixel stuck low) is a hole in a disk it falls on: with 0.05 % of the pixels dead, 119 of ~3 600
centres moved by more than 0.05 px (up to 0.18; 2 without them). Patched from their good
neighbours, such pixels cost the measurement nothing (``tests/core/test_defects.py``).

Hot pixels are found from frames in which the sensor's own defects are the only thing that stays
put: frames with the ring light off or the lens capped (at the working exposure and gain), or
frames from several views (targets move from frame to frame, defects do not). A pixel is hot where
it stands above the median of its 3 x 3 neighbourhood by more than ``k_sigma`` times the frame's
noise (and ``min_dn``) in at least ``min_fraction`` of the frames (:func:`find_defects`). Dark
frames cannot show a dead pixel: it is found in flat frames, an evenly lit field (a white card or
a diffuser before the lens under the ring light), where it lies below its neighbourhood's median by
``k_sigma`` noise sigmas and by ``min_drop`` of the level there (:func:`find_dead_pixels`). One map
holds both kinds (:meth:`DefectMap.merged`); each is patched alike. Pure computation: no I/O.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core._kernels.defects_kernel import patch_kernel

FORMAT = "posecell.defects/1"
K_SIGMA = 8.0  # above the neighbourhood's median, in the frame's noise sigmas
MIN_DN = 12.0  # and at least this many 8-bit DN (scaled to the image's full scale)
MIN_FRACTION = 0.8  # of the frames
# below this many frames a moving target's pixel can stand out in most of them
MIN_FRAMES = 5
# more defects than this share of the pixels is no sensor's: most likely the frames' targets did not move
SUSPECT_SHARE = 0.002
MIN_DROP = 0.3  # a dead pixel lies this share of the local level below its neighbours' median, at least
# a flat frame: its median pixel at least this share of full scale (a dead pixel must have light to miss),
# and at most this share of its pixels clipped (a clipped field hides a weak pixel's loss)
FLAT_MIN_LEVEL = 0.1
FLAT_MAX_CLIPPED = 0.05
_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))  # (dv, du)
_PAIRS = np.array([[0, 7], [1, 6], [2, 5], [3, 4]])  # opposite neighbours: two diagonals, vertical, horizontal


@dataclass(frozen=True, eq=False)
class DefectMap:
    """Defect pixels ``uv`` (K, 2) int, px (u right, v down), of a ``width`` x ``height`` sensor;
    ``dead`` (K,) which of them are dead (dark) pixels, the others hot (None: none dead)."""

    width: int
    height: int
    uv: NDArray[np.intp]
    dead: NDArray[np.bool_] | None = None
    # per defect: its flat index, its 8 neighbours' and their weights in the mean of its good ones
    # (1/n for each of its n good neighbours inside the image; 0 for the others)
    _flat: NDArray[np.intp] = field(init=False, repr=False)
    _neighbours: NDArray[np.intp] = field(init=False, repr=False)
    _weights: NDArray[np.float64] = field(init=False, repr=False)
    _pair_a: NDArray[np.intp] = field(init=False, repr=False)  # (K, 4): the pairs of opposite neighbours
    _pair_b: NDArray[np.intp] = field(init=False, repr=False)
    _pair_good: NDArray[np.bool_] = field(init=False, repr=False)  # (K, 4): both of a pair are good

    def __post_init__(self) -> None:
        uv = np.asarray(self.uv, dtype=np.intp).reshape(-1, 2)
        if uv.size and (uv.min() < 0 or uv[:, 0].max() >= self.width or uv[:, 1].max() >= self.height):
            raise ValueError(f"defect pixels must lie in the {self.width} x {self.height} sensor")
        object.__setattr__(self, "uv", uv)
        dead = np.zeros(len(uv), dtype=bool) if self.dead is None else np.asarray(self.dead, dtype=bool).reshape(-1)
        if dead.shape != (len(uv),):
            raise ValueError(f"dead has {dead.size} flags for {len(uv)} defect pixels")
        object.__setattr__(self, "dead", dead)
        u8 = uv[:, :1] + np.array([du for _, du in _OFFSETS])  # (K, 8): the neighbours, maybe outside
        v8 = uv[:, 1:] + np.array([dv for dv, _ in _OFFSETS])
        nu, nv = np.clip(u8, 0, self.width - 1), np.clip(v8, 0, self.height - 1)
        inside = (u8 == nu) & (v8 == nv)
        flat = uv[:, 1] * self.width + uv[:, 0]
        defect = np.zeros(self.width * self.height, dtype=bool)
        defect[flat] = True
        neighbours = nv * self.width + nu
        good = (inside & ~defect[neighbours]).astype(np.float64)
        n = good.sum(axis=1, keepdims=True)
        object.__setattr__(self, "_flat", flat)
        object.__setattr__(self, "_neighbours", neighbours)
        object.__setattr__(self, "_weights", good / np.maximum(n, 1.0))
        object.__setattr__(self, "_pair_a", np.ascontiguousarray(neighbours[:, _PAIRS[:, 0]]))
        object.__setattr__(self, "_pair_b", np.ascontiguousarray(neighbours[:, _PAIRS[:, 1]]))
        object.__setattr__(self, "_pair_good", (good[:, _PAIRS[:, 0]] > 0) & (good[:, _PAIRS[:, 1]] > 0))

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @property
    def n_dead(self) -> int:
        return int(np.count_nonzero(np.asarray(self.dead)))

    def merged(self, other: DefectMap) -> DefectMap:
        """Both maps' defects (of one sensor), each pixel once: dead where either says so."""
        if (other.width, other.height) != (self.width, self.height):
            raise ValueError(
                f"a {other.width} x {other.height} sensor's defects cannot join a {self.width} x {self.height} one's"
            )
        flat = np.concatenate([self.flat, other.flat])
        dead = np.concatenate([np.asarray(self.dead), np.asarray(other.dead)])
        order = np.lexsort((~dead, flat))  # per pixel its dead entry first, then unique keeps it
        flat, dead = flat[order], dead[order]
        first = np.r_[True, flat[1:] != flat[:-1]]
        flat, dead = flat[first], dead[first]
        return DefectMap(self.width, self.height, np.stack([flat % self.width, flat // self.width], axis=1), dead)

    def of_kind(self, dead: bool) -> DefectMap:
        """The map of its dead (``dead``) or of its hot pixels alone."""
        keep = np.asarray(self.dead) == dead
        return DefectMap(self.width, self.height, self.uv[keep], np.full(int(keep.sum()), dead))

    @property
    def flat(self) -> NDArray[np.intp]:
        """The defects' indices into a flattened (C order) frame."""
        return self._flat

    def patch(self, image: NDArray[Any], out: NDArray[Any] | None = None) -> NDArray[Any]:
        """``image`` with each defect replaced from its good neighbours (:meth:`_patch`), in
        ``out`` (same shape and type, C-contiguous; reused frame after frame) or a
        new array. The image itself is not changed."""
        if image.shape != (self.height, self.width):
            raise ValueError(
                f"the defect map is of a {self.width} x {self.height} sensor, the frame "
                f"{image.shape[1] if image.ndim > 1 else '?'} x {image.shape[0]}"
            )
        if out is None or out.shape != image.shape or out.dtype != image.dtype or not out.flags.c_contiguous:
            out = np.empty_like(image, order="C")
        np.copyto(out, image)
        self._patch(out.reshape(-1))
        return out

    def _patch(self, flat: NDArray[Any]) -> NDArray[Any]:
        """Patch the defects of the flattened frame ``flat`` in place; returns their old values. Each
        defect's value: the mean of the pair of opposite good neighbours that differ least (across an
        edge the pair along it: a defect on a disk's edge then moves its centre by thousandths of a
        pixel, where the mean of all eight moved it by 0.014 px), else the mean of its good
        neighbours (a corner, a cluster), else its own."""
        saved = np.empty(self._flat.size, dtype=flat.dtype)
        patch_kernel(
            flat, self._flat, self._pair_a, self._pair_b, self._pair_good, self._neighbours, self._weights, saved
        )
        return saved

    @contextmanager
    def patched_in_place(self, image: NDArray[Any]) -> Iterator[NDArray[Any]]:
        """``image`` patched as :meth:`patch` patches it, for the duration of the block: in place
        when it is a writeable C-contiguous array (its defects' values are put back when the block
        ends: ~10 us for 670 defects, where a copy of a 1.3 MP frame adds ~0.1 ms), else in a copy."""
        if not (image.flags.writeable and image.flags.c_contiguous):
            yield self.patch(image)
            return
        if image.shape != (self.height, self.width):
            self.patch(image)  # raises, saying which sizes differ
        flat = image.reshape(-1)
        saved = self._patch(flat)
        try:
            yield image
        finally:
            flat[self._flat] = saved

    def cropped(self, x: int, y: int, width: int, height: int) -> DefectMap:
        """The map of a window of the sensor (a camera's ``roi``): its defects, in the window's pixels."""
        if x < 0 or y < 0 or x + width > self.width or y + height > self.height:
            raise ValueError(f"the window {x}, {y}, {width} x {height} leaves the {self.width} x {self.height} sensor")
        uv = self.uv - (x, y)
        keep = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
        return DefectMap(width, height, uv[keep], np.asarray(self.dead)[keep])

    def in_sensor(self, x: int, y: int, width: int, height: int) -> DefectMap:
        """This map of a window of the sensor (a camera's ``roi`` at ``x``, ``y``) as the whole ``width`` x
        ``height`` sensor's: what :meth:`cropped` takes back to the window."""
        if x < 0 or y < 0 or x + self.width > width or y + self.height > height:
            raise ValueError(f"the window {x}, {y}, {self.width} x {self.height} leaves the {width} x {height} sensor")
        return DefectMap(width, height, self.uv + (x, y), self.dead)

    def to_dict(self, **extra: Any) -> dict[str, Any]:
        """Every defect in ``pixels`` (what a reader patches), the dead ones also in ``dead_pixels``."""
        d: dict[str, Any] = {"format": FORMAT, "width": self.width, "height": self.height, "pixels": self.uv.tolist()}
        if self.n_dead:
            d["dead_pixels"] = self.uv[np.asarray(self.dead)].tolist()
        return {**d, **extra}

    @staticmethod
    def from_dict(data: Any, source: str = "defects") -> DefectMap:
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError(f"{source}: not a posecell defect map (want an object with 'format': '{FORMAT}')")
        try:
            width, height = int(data["width"]), int(data["height"])
            uv = np.array(data["pixels"], dtype=np.intp).reshape(-1, 2)
            dead_uv = np.array(data.get("dead_pixels", []), dtype=np.intp).reshape(-1, 2)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{source}: 'width', 'height' and 'pixels' ([[u, v], ...]) are needed ({e})") from None
        if width <= 0 or height <= 0:
            raise ValueError(f"{source}: width and height must be positive, got {width} x {height}")
        keys = uv[:, 1] * width + uv[:, 0]
        dead_keys = dead_uv[:, 1] * width + dead_uv[:, 0]
        if not np.isin(dead_keys, keys).all():
            raise ValueError(f"{source}: every one of 'dead_pixels' must be one of 'pixels' too")
        try:
            return DefectMap(width, height, uv, np.isin(keys, dead_keys))
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None


@dataclass(frozen=True)
class DefectSearch:
    """What :func:`find_defects` found and how: the map, the frames, the threshold per frame (DN) and
    how many pixels stood out in some frames but not in enough of them."""

    defects: DefectMap
    n_frames: int
    threshold_dn: NDArray[np.float64]
    sometimes: int
    unjudged: int = 0  # flat frames: pixels whose neighbourhood was lit in too few of them to judge


def find_defects(
    frames: Sequence[NDArray[Any]],
    *,
    full_dn: float | None = None,
    k_sigma: float = K_SIGMA,
    min_dn: float = MIN_DN,
    min_fraction: float = MIN_FRACTION,
) -> DefectSearch:
    """The pixels that stand above their 3 x 3 neighbourhood's median in at least ``min_fraction``
    of ``frames`` (see the module docstring). ``full_dn``: the frames' saturation level (default:
    their type's maximum), which scales ``min_dn`` (8-bit DN)."""
    import cv2  # only the search needs OpenCV (its 3 x 3 median); a map is read and applied without

    shape, full = _check_frames(frames, full_dn, min_fraction, "to tell a defect from a target")
    floor = min_dn * full / 255.0
    count = np.zeros(shape, dtype=np.uint16)
    thresholds = []
    for f in frames:
        # OpenCV's 3 x 3 median takes 8 and 16 bits alike; the residual in float32
        residual = f.astype(np.float32) - cv2.medianBlur(f, 3).astype(np.float32)
        # the noise of the residual from its central part (MAD): targets and defects are far outside it
        sigma = 1.4826 * float(np.median(np.abs(residual[::4, ::4])))
        threshold = max(floor, k_sigma * sigma)
        thresholds.append(threshold)
        count += residual > threshold
    need = int(np.ceil(min_fraction * len(frames)))
    v, u = np.nonzero(count >= need)
    return DefectSearch(
        DefectMap(shape[1], shape[0], np.stack([u, v], axis=1)),
        len(frames),
        np.array(thresholds),
        int(np.count_nonzero((count > 0) & (count < need))),
    )


def find_dead_pixels(
    flats: Sequence[NDArray[Any]],
    *,
    full_dn: float | None = None,
    k_sigma: float = K_SIGMA,
    min_drop: float = MIN_DROP,
    min_fraction: float = MIN_FRACTION,
) -> DefectSearch:
    """The pixels that lie below their 3 x 3 neighbourhood's median by ``k_sigma`` times the frame's
    noise and by ``min_drop`` of that median in at least ``min_fraction`` of the flat frames
    ``flats`` (an evenly lit field: see the module docstring); ValueError for a frame that is not
    lit or is clipped. Judged only where the neighbourhood is lit (its median at least FLAT_MIN_LEVEL
    of full scale) in enough frames; the others are counted (``unjudged``). ``full_dn`` as for
    :func:`find_defects`. The map's pixels are all dead."""
    import cv2

    shape, full = _check_frames(flats, full_dn, min_fraction, "to tell a dead pixel from noise")
    count, lit = np.zeros(shape, dtype=np.uint16), np.zeros(shape, dtype=np.uint16)
    thresholds = []
    for k, f in enumerate(flats):
        level = float(np.median(f[::4, ::4]))
        clipped = float(np.count_nonzero(f[::4, ::4] >= full)) / f[::4, ::4].size
        if level < FLAT_MIN_LEVEL * full:
            raise ValueError(
                f"flat frame {k + 1} is not lit (its median pixel {level:g} DN, under {FLAT_MIN_LEVEL:.0%} of "
                f"{full:g}): a flat frame shows an evenly lit field, e.g. a white card before the lens under "
                "the ring light"
            )
        if clipped > FLAT_MAX_CLIPPED:
            raise ValueError(
                f"flat frame {k + 1} is clipped ({clipped:.0%} of its pixels at {full:g} DN): shorten the exposure "
                "so that the field lies well below full scale"
            )
        median = cv2.medianBlur(f, 3).astype(np.float32)
        # below the neighbours: the residual's noise from its central part (MAD), as for hot pixels;
        # judged only where the neighbourhood is lit (a shadow's dim pixels cannot tell a dead one)
        residual = median - f.astype(np.float32)
        sigma = 1.4826 * float(np.median(np.abs(residual[::4, ::4])))
        thresholds.append(k_sigma * sigma)
        judged = median >= FLAT_MIN_LEVEL * full
        lit += judged
        count += judged & (residual > k_sigma * sigma) & (residual > min_drop * median)
    need = int(np.ceil(min_fraction * len(flats)))
    v, u = np.nonzero(count >= need)
    return DefectSearch(
        DefectMap(shape[1], shape[0], np.stack([u, v], axis=1), np.ones(u.size, dtype=bool)),
        len(flats),
        np.array(thresholds),
        int(np.count_nonzero((count > 0) & (count < need))),
        int(np.count_nonzero(lit < need)),
    )


def _check_frames(
    frames: Sequence[NDArray[Any]], full_dn: float | None, min_fraction: float, what: str
) -> tuple[tuple[int, ...], float]:
    """The frames' shape and full scale; ValueError for too few frames, mixed or non-grey ones."""
    if len(frames) < MIN_FRAMES:
        raise ValueError(f"{len(frames)} frames: at least {MIN_FRAMES} are needed {what}")
    shape = frames[0].shape
    if any(f.shape != shape or f.ndim != 2 or f.dtype not in (np.uint8, np.uint16) for f in frames):
        raise ValueError("the frames must be 2-D uint8 or uint16 images of one size")
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must lie in (0, 1], got {min_fraction}")
    return shape, float(full_dn if full_dn is not None else np.iinfo(frames[0].dtype).max)
