"""The compiled target list's text against orjson's of the same rounded numbers."""

from __future__ import annotations

import numpy as np
import orjson

from service.core._kernels.json_kernel import LIMIT, targets_json
from service.core.results import TargetTable


def _reference(ids, uv, res, used) -> bytes:
    uv, res = np.round(uv, 4).tolist(), np.round(res, 4).tolist()
    return orjson.dumps(
        [
            {"id": i, "uv": q, "residual_px": e} if u else {"id": i, "uv": q, "residual_px": e, "rejected": True}
            for i, q, e, u in zip(ids, uv, res, used, strict=True)
        ]
    )


def test_the_text_is_orjsons_for_every_magnitude_sign_and_rounding(rng):
    n = 4000
    scale = 10.0 ** rng.integers(-6, 9, (n, 2))  # 1e-6 .. 1e8: zeros, sub-unit, pixel and huge values
    uv = rng.uniform(-1, 1, (n, 2)) * scale
    res = rng.normal(0, 1, (n, 2)) * 10.0 ** rng.integers(-5, 2, (n, 2))
    # the hard cases: signed zeros, a value that rounds to -0, carries into the next integer or
    # decimal, exact 4-place decimals, halves at the 5th place, the largest allowed
    hard = [0.0, -0.0, -0.00004, 0.00005, -0.00005, 0.99996, 9.99995, 99999.99999, 1.0001, 0.1, 123.4500,
            2.5e-5, 3.00005, 0.30000000000000004, LIMIT * (1 - 1e-12), -LIMIT * (1 - 1e-12), 1234.5678]  # fmt: skip
    uv[: len(hard), 0] = hard
    res[: len(hard), 1] = hard[::-1]
    ids = [f"T{k}" for k in range(n)]
    ids[:4] = ['odd "quoted" id', "back\\slash\\", "ünïcode Ω", 'end\\"']  # escapes orjson writes
    used = rng.random(n) < 0.9
    got = targets_json(orjson.dumps(ids), uv, res, used)
    assert got == _reference(ids, uv, res, used)
    assert targets_json(b"[]", np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool)) == b"[]"


def test_a_table_outside_the_kernels_range_is_encoded_as_before():
    table = TargetTable(
        ("a", "b"),
        np.array([[2e9, 1.0], [3.0, 4.0]]),  # beyond LIMIT: orjson's own text (the kernel would overflow)
        np.array([[0.5, np.nan], [0.0, 1.0]]),
        np.ones(2, bool),
        np.array([True, False]),
    )
    assert table.to_json() == orjson.dumps(table.to_list()).decode()
    assert orjson.loads(table.to_json())[0]["uv"][0] == 2e9
