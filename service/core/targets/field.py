"""The target field: target ids, coordinates in the field frame (mm), codes and diameters."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Field:
    """Targets fixed in the cell, in the ``field`` frame.

    ``ids`` (N,) str; ``xyz`` (N, 3) float mm; ``codes`` (N,) int, -1 for an
    uncoded target; ``diameters_mm`` (N,) float, the central measuring disk.
    """

    name: str
    ids: tuple[str, ...]
    xyz: Array
    codes: NDArray[np.int64]
    diameters_mm: Array
    index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.ids)
        if xyz.shape[0] != n:
            raise ValueError(f"field has {n} ids but {xyz.shape[0]} coordinates")
        codes = np.asarray(self.codes, dtype=np.int64).reshape(n)
        diam = np.asarray(self.diameters_mm, dtype=np.float64).reshape(n)
        if not np.all(np.isfinite(xyz)):
            raise ValueError("field coordinates must be finite")
        index = {tid: i for i, tid in enumerate(self.ids)}
        if len(index) != n:
            seen: set[str] = set()
            dup = next(t for t in self.ids if t in seen or seen.add(t))  # type: ignore[func-returns-value]
            raise ValueError(f"target id {dup!r} appears twice in the field")
        coded = codes[codes >= 0]
        if len(set(coded.tolist())) != len(coded):
            raise ValueError("two coded targets in the field carry the same code")
        object.__setattr__(self, "ids", tuple(self.ids))
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "diameters_mm", diam)
        object.__setattr__(self, "index", index)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_coded(self) -> NDArray[np.bool_]:
        return self.codes >= 0

    def indices_of(self, ids: list[str] | tuple[str, ...]) -> NDArray[np.int64]:
        """Field row of each id; raises ``KeyError`` naming the first unknown id."""
        try:
            return np.array([self.index[t] for t in ids], dtype=np.int64)
        except KeyError as e:
            raise KeyError(f"target {e.args[0]!r} is not in field {self.name!r}") from None

    def id_of_code(self) -> dict[int, str]:
        return {int(c): self.ids[i] for i, c in enumerate(self.codes) if c >= 0}

    def is_planar(self, tol_mm: float = 1e-3) -> bool:
        """Whether all targets lie in one plane within ``tol_mm``."""
        if len(self) < 4:
            return True
        centred = self.xyz - self.xyz.mean(axis=0)
        return bool(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(self)) < tol_mm)
