"""The lattice a bake fills, held over its plan's texels only.

A bake's lattice has values only at the plan's active texels (`baking.plan.Plan.ids`,
sorted): 9–32 % of the box on the scans measured, 41 M of 134 M texels on a 512³ foot CT.
`PlanLattice` keeps its arrays in plan order — row p is the texel ``ids[p]`` — so its
memory follows the active texels (23 bytes each in irradiance), where a `baking.Lattice`
dense over the box takes 23 bytes per texel of the box. It is saved as it is held (the
file keeps the active or computed texels only, `baking.lattice_file`), resumed from a file
by reading only its texels, and made dense (`dense`) only when the bake returns.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from isolume.baking.config import BakeConfig
from isolume.baking.lattice import (
    Lattice,
    LatticeGeometry,
    file_meta,
    lattice_kind,
)
from isolume.baking.lattice_file import LatticeFile, write_rows


class PlanLattice:
    """A lattice's arrays at (T,) texels only, in the order of their sorted flat ids.

    Attributes:
        geometry: texel placement (the whole lattice's).
        ids: (T,) sorted unique flat [z, y, x] ids of the texels (the plan's).
        values: (T, C) float32 mean estimates; samples (T,) uint32; second (T,) float32;
            facing (T, 2) uint8: as `baking.Lattice`'s at those texels.
        meta, config: as `baking.Lattice`'s.
    """

    def __init__(self, geometry: LatticeGeometry, ids: np.ndarray, channels: int,
                 meta: dict[str, Any], config: BakeConfig | None = None) -> None:
        self.geometry: LatticeGeometry = geometry
        self.meta: dict[str, Any] = meta
        self.config: BakeConfig | None = config
        self.ids: np.ndarray = np.asarray(ids)
        count = len(self.ids)
        self.values: np.ndarray = np.zeros((count, channels), np.float32)
        self.samples: np.ndarray = np.zeros(count, np.uint32)
        self.second: np.ndarray = np.zeros(count, np.float32)
        self.facing: np.ndarray = np.zeros((count, 2), np.uint8)

    @property
    def kind(self) -> str:
        return lattice_kind(self.meta)

    def fill_from(self, file: LatticeFile) -> None:
        """Take the texels of `file` (a lattice of the same box) that are among `ids`. Its
        other texels are left out: a bake resumes only with the plan it was made with
        (`baking.bake`)."""
        kept = ("values", "samples", "second", "facing")
        read, arrays = file.read_texels(self.ids.astype(np.int64), kept)
        rows = np.searchsorted(self.ids, read)
        for name in kept:
            getattr(self, name)[rows] = arrays[name]

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write atomically to `path`, as `baking.Lattice.save` would write `dense()`."""
        write_rows(path, self.geometry.shape, self.ids,
                   {"values": self.values, "samples": self.samples, "second": self.second,
                    "active": np.broadcast_to(True, len(self.ids)), "facing": self.facing},
                   file_meta(self.meta, self.geometry, self.config))

    def dense(self) -> Lattice:
        """The `baking.Lattice` dense over the box (the texels not held: zero, inactive)."""
        lattice = Lattice.empty(self.geometry, self.values.shape[1], self.meta, self.config)
        lattice.values.reshape(-1, self.values.shape[1])[self.ids] = self.values
        lattice.samples.reshape(-1)[self.ids] = self.samples
        lattice.second.reshape(-1)[self.ids] = self.second
        lattice.facing.reshape(-1, 2)[self.ids] = self.facing
        lattice.active.reshape(-1)[self.ids] = True
        return lattice
