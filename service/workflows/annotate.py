"""The newest frame as an image for set-up and focus: targets circled and labelled.

Green: used in the adjustment; red: rejected as an outlier. 16-bit frames are
scaled to 8 bit; large frames are shrunk to ``max_width`` (the labels stay
readable).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

_GREEN, _RED, _YELLOW = (60, 220, 60), (40, 40, 230), (0, 215, 255)


def encode_frame(
    image: np.ndarray, result: dict[str, Any] | None, fmt: str = "jpeg", max_width: int = 1600
) -> tuple[bytes, str]:
    """Encode ``image`` (H, W) uint8/uint16, with ``result``'s targets drawn when given; (bytes, media type)."""
    img = image
    if img.dtype != np.uint8:
        peak = float(img.max()) or 1.0
        img = np.clip(img.astype(np.float32) * (255.0 / peak), 0, 255).astype(np.uint8)
    scale = min(1.0, max_width / img.shape[1])
    if scale < 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if result is not None:
        for t in result.get("targets", []):
            u, v = t["uv"][0] * scale, t["uv"][1] * scale
            colour = _RED if t.get("rejected") else _GREEN
            centre = (round(u), round(v))
            cv2.circle(bgr, centre, max(4, int(8 * scale)), colour, 1, cv2.LINE_AA)
            cv2.putText(
                bgr, t["id"], (centre[0] + 6, centre[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA
            )
        text = (
            f"{result.get('camera', '')} {result.get('mode', '')} rms {result.get('rms_px', 0):.3f} px"
            if result.get("ok")
            else f"{result.get('reason')}: {result.get('message', '')}"
        )
        cv2.putText(bgr, text, (10, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, _YELLOW, 1, cv2.LINE_AA)
    ext, media = (".png", "image/png") if fmt == "png" else (".jpg", "image/jpeg")
    ok, buf = cv2.imencode(ext, bgr)
    if not ok:
        raise ValueError(f"could not encode the frame as {fmt}")
    return buf.tobytes(), media
