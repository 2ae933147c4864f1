"""``posecell simulate``: a rendered data set with ground truth, for tests, demos and benchmarks.

Writes ``camera.json``, ``field.json``, ``frame_NNNN.png`` and ``truth.jsonl``
(one line per frame: the true ``T_field_camera`` and every target's true image
position) into a folder. Poses are seeded: random views around the plate, or the
paper's circular path (ISO 230-4: radius 300 mm) above it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.core.geometry.camera_model import BrownFraser
from service.core.targets.field import Field
from service.sim.render import RenderSettings, render_frame
from service.sim.scene import reference_camera, reference_field, reference_pose
from service.store import formats

Array = np.ndarray


def poses(path: str, n: int, rng: np.random.Generator, distance_mm: float = 1000.0) -> list[Array]:
    """``n`` camera poses ``T_field_camera``: ``random`` views or the ISO 230-4 ``circle``."""
    if path == "circle":
        out = []
        for k in range(n):
            a = 2 * np.pi * k / n
            look = (300.0 * np.cos(a), 300.0 * np.sin(a), 0.0)
            out.append(reference_pose(view_angle_deg=90.0, distance_mm=distance_mm, look_at_mm=look))
        return out
    if path == "random":
        return [
            reference_pose(
                view_angle_deg=float(rng.uniform(60.0, 90.0)),
                distance_mm=float(rng.uniform(0.85, 1.15) * distance_mm),
                roll_deg=float(rng.uniform(-180.0, 180.0)),
                azimuth_deg=float(rng.uniform(-180.0, 180.0)),
                look_at_mm=(float(rng.uniform(-150, 150)), float(rng.uniform(-100, 100)), 0.0),
            )
            for _ in range(n)
        ]
    raise ValueError(f"unknown path {path!r}: use 'random' or 'circle'")


def write_dataset(
    out_dir: str | Path,
    n_frames: int,
    path: str = "random",
    seed: int = 1,
    camera: BrownFraser | None = None,
    field: Field | None = None,
    settings: RenderSettings | None = None,
    distance_mm: float = 1000.0,
) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    camera = camera or reference_camera()
    field = field or reference_field()
    settings = settings or RenderSettings()
    rng = np.random.default_rng(seed)
    formats.write_camera(out / "camera.json", camera)
    formats.write_field(out / "field.json", field)
    with (out / "truth.jsonl").open("w", encoding="utf-8") as truth:
        for k, T in enumerate(poses(path, n_frames, rng, distance_mm)):
            frame = render_frame(camera, field, T, settings, rng)
            name = f"frame_{k:04d}.png"
            formats.write_image(out / name, frame.image)
            truth.write(
                json.dumps(
                    {
                        "image": name,
                        "T_field_camera": np.round(T, 9).tolist(),
                        "targets": [
                            {"id": i, "uv": np.round(uv, 5).tolist(), "fully_visible": bool(v)}
                            for i, uv, v in zip(frame.ids, frame.uv_true, frame.fully_visible, strict=True)
                        ],
                    }
                )
                + "\n"
            )
    return out
