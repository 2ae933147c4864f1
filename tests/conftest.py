"""Shared fixtures: the reference camera of DESIGN section 7 and the path to the real data sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.core.geometry.camera_model import BrownFraser
from service.sim import scene

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_data(name: str) -> Path:
    """Path of a real data set in ../shared/data, or skip the test saying why."""
    p = SHARED_DATA / name
    if not p.exists():
        pytest.skip(f"real data set {name!r} not found at {p} (see ../shared/data/README.md)")
    return p


@pytest.fixture
def reference_camera() -> BrownFraser:
    """1300x1030 px, 6.7 um pixels, c = 12 mm, with distortion of a real 12 mm lens (DESIGN section 7)."""
    return scene.reference_camera()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261125)
