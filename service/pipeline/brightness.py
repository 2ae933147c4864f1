"""How bright (and how sharp) a frame's targets came out: what the exposure control steers by, and
what the service tells of the exposure and the focus (no I/O)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.core.targets.detect import Blobs

# A blur sigma beyond which the targets are out of focus: accuracy falls (centres 0.03-0.04 px at
# 2.5 px against 0.01-0.02 sharp, on posecell's printed sheet through cairo and OpenCV) and coded
# targets' rings join their disks from ~2 px (README, *Out of focus*)
BLURRED_PX = 1.5


@dataclass(frozen=True)
class Brightness:
    """How bright a frame's targets came out, in the image's DN: what the exposure control steers by.

    n_measured -- disks measured unclipped (the ROI windows' or the full frame's blobs)
    peak_dn -- the 90th percentile of their brightest pixels (the brightest tenth may clip first)
    background_dn -- the median of their local backgrounds
    n_saturated -- disks clipped at the saturation level: measured (flagged) or, with
        ``max_saturated_px``, rejected (only the full frame sees those)
    full_dn -- the saturation level
    blur_px -- the median blur sigma of the unclipped disks' edges, px (a sharp image: 0.3-0.8; the
        focus, the depth of field and the motion widen it); 0 when none was measured
    """

    n_measured: int
    peak_dn: float
    background_dn: float
    n_saturated: int
    full_dn: float
    blur_px: float = 0.0

    @classmethod
    def of(cls, blobs: Blobs, n_rejected_saturated: int, full_dn: float) -> Brightness:
        clipped = int(np.count_nonzero(blobs.saturated))
        n_saturated = n_rejected_saturated + clipped
        peak_dn, background_dn, blur_px = blobs.peak_dn, blobs.background_dn, blobs.blur_px
        if clipped:  # how far below full scale the others are is what the exposure steers by
            unclipped = ~blobs.saturated
            peak_dn, background_dn, blur_px = peak_dn[unclipped], background_dn[unclipped], blur_px[unclipped]
        n = len(peak_dn)
        if n == 0:
            return cls(0, 0.0, 0.0, n_saturated, full_dn)
        k = min(n - 1, int(0.9 * n))
        peak = float(np.partition(peak_dn, k)[k])  # a partition, not a sort: ~200 disks a frame
        return cls(n, peak, _median(background_dn), n_saturated, full_dn, _median(blur_px))

    @property
    def saturation_note(self) -> str:
        """What the saturated targets mean for the user (empty without any)."""
        if not self.n_saturated:
            return ""
        seen = self.n_measured + self.n_saturated
        return (
            f"{self.n_saturated} of {seen} targets saturated at {self.full_dn:g} DN: shorten the exposure "
            "or dim the ring light"
        )

    @property
    def focus_note(self) -> str:
        """What a blur beyond BLURRED_PX means for the user (empty below it)."""
        if not self.blur_px > BLURRED_PX:
            return ""
        return (
            f"the targets' edges are blurred (sigma {self.blur_px:.1f} px): check the lens's focus and that the "
            "targets lie within its depth of field"
        )

    def health(self) -> dict[str, Any]:
        """The facts ``/health`` gives per camera of its last measured frame."""
        return {
            "targets_saturated": self.n_saturated,
            "saturation": self.saturation_note or None,
            "blur_px": round(self.blur_px, 2),
            "focus": self.focus_note or None,
        }


def _median(x: NDArray[np.float64]) -> float:
    """``np.median`` of a 1-D array by a partition about the middle: 6 us against np.median's 31 us
    for the ~230 disks of every frame (its general path copies, checks for NaN and reduces)."""
    h = len(x) // 2
    if len(x) % 2:
        return float(np.partition(x, h)[h])
    p = np.partition(x, (h - 1, h))
    return 0.5 * (float(p[h - 1]) + float(p[h]))
