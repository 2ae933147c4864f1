"""The target field: target ids, coordinates in the field frame (mm), codes, diameters and, for a
field on several surfaces (a cell's floor and walls), the normal of each target's plane."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Field:
    """Targets fixed in the cell, in the ``field`` frame.

    ``ids`` (N,) str; ``xyz`` (N, 3) float mm; ``codes`` (N,) int, -1 for an
    uncoded target; ``diameters_mm`` (N,) float, the central measuring disk; ``normals`` (N, 3)
    unit vectors, the side of each target's plane its print faces (None: +z for every target, a
    field on one plane). A disk's image depends on its plane: the perspective shift of its centre
    (eccentricity) and the ellipse that ROI tracking predicts for its ring's mask.
    """

    name: str
    ids: tuple[str, ...]
    xyz: Array
    codes: NDArray[np.int64]
    diameters_mm: Array
    normals: Array | None = None
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
        if self.normals is not None:
            normals = np.asarray(self.normals, dtype=np.float64)
            if normals.shape != (n, 3):
                raise ValueError(f"field has {n} targets but normals of shape {normals.shape}")
            length = np.linalg.norm(normals, axis=1)
            if not np.all(np.isfinite(length) & (length > 1e-9)):
                raise ValueError("a target's normal must be a finite, non-zero vector")
            object.__setattr__(self, "normals", normals / length[:, None])
        object.__setattr__(self, "index", index)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_coded(self) -> NDArray[np.bool_]:
        return self.codes >= 0

    @property
    def has_normals(self) -> bool:
        """Whether some target's plane is not the field's x-y plane (normals given, not all +z)."""
        return self.normals is not None and not bool(np.all(self.normals[:, 2] > 1.0 - 1e-12))

    def normal_rows(self, rows: NDArray[np.int64]) -> Array | None:
        """The normals (k, 3) of the field rows ``rows``; None where the field is on one plane (+z)."""
        return self.normals[rows] if self.has_normals and self.normals is not None else None

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
