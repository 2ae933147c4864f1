"""The warm-ups cover every image a frame can be: no frame compiles a kernel of its own.

numba compiles a kernel once per argument type: a 16-bit frame (a Mono12/16 camera) and a
read-only one (a replayed, memory-mapped frame) are other types than the 8-bit writeable frame
of the simulated cell, and a kernel met first in a frame cost that frame its compile (~10-15 s).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# in a fresh interpreter: in this one other tests have long compiled or loaded every signature
_CODE = """
import importlib, json, pkgutil
import numpy as np
from numba.core.dispatcher import Dispatcher
import service.core._kernels as kernels
from service.core.targets import decode
from service.pipeline.compile import GROUPS
from service.pipeline.measure import FrameMeasurer
from service.core.results import PoseResult
from service.sim.cell import CellConfig, SimCell

modules = [importlib.import_module(f"service.core._kernels.{m.name}") for m in pkgutil.iter_modules(kernels.__path__)]
def signatures():
    return {f"{m.__name__}.{k}": len(v.signatures) for m in modules + [decode] for k, v in vars(m).items()
            if isinstance(v, Dispatcher)}
for group in GROUPS:
    for name in group:
        importlib.import_module(name).warm_up()
cell = SimCell(CellConfig(program="hold"))
image8 = cell.render(0.0, np.random.default_rng(1)).image
before = signatures()
kinds = []
for image in (image8, image8.astype(np.uint16) * 257):
    for writeable in (True, False):
        frame = image.copy()
        frame.flags.writeable = writeable
        measurer = FrameMeasurer(cell.camera, cell.field)  # a full frame, then the ROI tracking
        for t_s in (0.0, 0.01):
            outcome = measurer.measure(frame, t_s)
            outcome.result.targets.to_json()  # the measurement process encodes them
            kinds.append([str(frame.dtype), writeable, isinstance(outcome.result, PoseResult), outcome.mode])
after = signatures()
new = {k: after[k] - before.get(k, 0) for k in after if after[k] != before.get(k, 0)}
print(json.dumps({"kinds": kinds, "new": new}))
"""


@pytest.mark.slow  # a fresh interpreter loads every kernel: ~10 s
def test_a_full_frame_of_any_depth_and_writeability_compiles_nothing_after_the_warm_ups():
    out = subprocess.run([sys.executable, "-c", _CODE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["kinds"] == [
        [dtype, writeable, True, mode]
        for dtype in ("uint8", "uint16")
        for writeable in (True, False)
        for mode in ("full", "roi")
    ], report["kinds"]
    assert report["new"] == {}, f"compiled by a frame, not by the warm-ups: {report['new']}"
