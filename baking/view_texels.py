"""A lattice that holds light at a fixed set of texels only: a view's traced light, or the
texels of a lattice file that a picture reads.

One picture's light (``isolume render``, a movie's frames) needs the texels its pixels
read — a few hundred thousand of a box that may hold a hundred million. `HeldLattice`
keeps their estimates in arrays over those texels (sorted flat ids), so its memory follows
the picture, and answers what a display reads of a `baking.Lattice`:
`shown`, `displayed` and `displayed_facing` over a z-slab or at index arrays
(`app.render.lattice_gl` uploads from them, `baking.lattice.shown_lookup` looks it up on
the CPU), and `store_preview` (what `baking.preview.estimate` writes). ``export`` holds
the light of a whole surface the same way. `LatticeOnFile.held` takes the texels it is asked
for from a lattice file (their baked means, `paths` their samples), reading the file a slab
at a time: a picture of a 512³ bake reads a few hundred thousand of its 41 million active
texels.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from isolume.baking.config import BakeConfig
from isolume.baking.lattice import (
    TRAPPED_PATHS,
    LatticeGeometry,
    drop_trapped,
    lattice_kind,
    open_lattice,
    sky_everywhere,
)
from isolume.baking.lattice_file import LatticeFile

if TYPE_CHECKING:
    from isolume.volumes.core import Volume


FILL_BLOCK = 1 << 17
"""Texels without paths `LatticeOnFile` fills from their neighbours at a time."""


class HeldLattice:
    """Estimates at (K,) texels of a lattice's geometry, nothing elsewhere.

    Attributes:
        geometry: texel placement (the whole lattice's).
        texels: (K,) sorted unique flat [z, y, x] ids of the texels held.
        values: (K, C) float32 estimates (irradiance or SH transfer).
        facing: (K, 2) uint8 octahedral codes of their paths' start normals.
        paths: (K,) uint16 (previews) or uint32 (a file's samples) paths behind each
            estimate (0: none; not shown).
        meta, config: as `baking.Lattice`'s (kind, volume identity; the lighting).
        unbaked: texels asked for that the file holds without paths yet (an unfinished
            bake's; `LatticeOnFile.held`), 0 otherwise.
        filled: how many of those are held, mixed from their neighbours
            (`LatticeOnFile.held` with `fill`).
    """

    def __init__(self, geometry: LatticeGeometry, texels: np.ndarray, channels: int,
                 meta: dict[str, Any], config: BakeConfig | None = None) -> None:
        self.geometry: LatticeGeometry = geometry
        self.texels: np.ndarray = np.asarray(texels, np.int64)
        if len(self.texels) and np.any(np.diff(self.texels) <= 0):
            raise ValueError("texels must be sorted and unique")
        self.values: np.ndarray = np.zeros((len(self.texels), channels), np.float32)
        self.facing: np.ndarray = np.zeros((len(self.texels), 2), np.uint8)
        self.paths: np.ndarray = np.zeros(len(self.texels), np.uint16)
        self.meta: dict[str, Any] = meta
        self.config: BakeConfig | None = config
        self.unbaked: int = 0
        self.filled: int = 0

    @classmethod
    def for_texels(cls, volume: Volume, config: BakeConfig, texels: np.ndarray) -> HeldLattice:
        """Nothing yet at (K,) sorted flat `texels` of the lattice of `volume` baked with
        `config` (its geometry and metadata, as `baking.bake` makes them, but for the
        volume's hash: such a lattice lights one picture or mesh, and is never saved)."""
        from isolume.baking.bake import lattice_meta, path_settings

        channels = path_settings(volume, config).channels
        return cls(LatticeGeometry.for_volume(volume, config.scale), texels, channels,
                   lattice_meta(volume, config, channels, hashed=False), config)

    @property
    def kind(self) -> str:
        return lattice_kind(self.meta)

    def _rows(self, flat: np.ndarray) -> np.ndarray:
        """(N,) rows of (N,) flat texel ids in the arrays; every id must be held."""
        rows = np.searchsorted(self.texels, flat)
        if len(flat) and (rows.max() >= len(self.texels)
                          or not np.array_equal(self.texels[rows], flat)):
            raise ValueError("previews stored at texels this lattice does not hold")
        return rows

    def store_preview(self, flat: np.ndarray, paths: np.ndarray, values: np.ndarray,
                      codes: np.ndarray) -> None:
        """Store the previews of (N,) texels `flat`: (N,) `paths` behind each (0: none
        could start), and for those with paths, in order, (M, C) means and (M, 2) facing
        codes."""
        rows = self._rows(np.asarray(flat, np.int64))
        traced = rows[np.asarray(paths) > 0]
        self.values[traced] = values
        self.facing[traced] = codes
        self.paths[rows] = paths

    def _find(self, region: slice | tuple[npt.ArrayLike, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(rows, held) of the texels of `region` — a z-slab (a slice of z) or a tuple of
        z, y, x index arrays that broadcast — each of the region's shape: the row of the
        texel in the arrays, and whether it is held."""
        shape = self.geometry.shape
        if isinstance(region, slice):
            z0, z1, _ = region.indices(shape[0])
            layer = shape[1] * shape[2]
            lo, hi = np.searchsorted(self.texels, [z0 * layer, z1 * layer])
            rows = np.zeros((max(z1 - z0, 0), shape[1], shape[2]), np.int64)
            held = np.zeros(rows.shape, bool)
            local = self.texels[lo:hi] - z0 * layer
            rows.reshape(-1)[local] = np.arange(lo, hi)
            held.reshape(-1)[local] = True
            return rows, held
        flat = np.ravel_multi_index(np.broadcast_arrays(*region), shape)
        rows = np.minimum(np.searchsorted(self.texels, flat), max(len(self.texels) - 1, 0))
        held = (self.texels[rows] == flat) if len(self.texels) else np.zeros(flat.shape, bool)
        return rows, held

    def _shown(self, region: slice | tuple[npt.ArrayLike, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(rows, shown) of the texels of `region` (`_find`): shown where a preview is,
        except the trapped (`baking.lattice.TRAPPED_PATHS`)."""
        rows, held = self._find(region)
        if not len(self.texels):
            return rows, held
        paths = self.paths[rows]
        shown = held & (paths > 0)
        if not sky_everywhere(self.config):
            return rows, shown
        return rows, drop_trapped(shown, shown & (paths >= TRAPPED_PATHS),
                                  lambda at: self.values[rows[at]])

    def shown(self, region: slice | tuple[npt.ArrayLike, ...] = slice(None)) -> np.ndarray:
        """Bool mask of the texels in `region` (a z-slice, or z, y, x index arrays) that
        hold a preview, except the trapped."""
        return self._shown(region)[1]

    def displayed(self, region: slice | tuple[npt.ArrayLike, ...] = slice(None)) -> np.ndarray:
        """(…, C) float32 preview values in `region` (0 where none is shown)."""
        return self._picked(region, self.values)

    def displayed_facing(self, region: slice | tuple[npt.ArrayLike, ...] = slice(None)
                         ) -> np.ndarray:
        """(…, 2) uint8 facing codes in `region` (unknown where no preview is shown)."""
        return self._picked(region, self.facing)

    def display(self, region: slice | tuple[npt.ArrayLike, ...] = slice(None)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`shown`, `displayed_facing` and `displayed` of `region`, from one lookup of
        its texels (what an upload of a region reads)."""
        rows, shown = self._shown(region)
        return shown, _rows_shown(rows, shown, self.facing), _rows_shown(rows, shown, self.values)

    def _picked(self, region: slice | tuple[npt.ArrayLike, ...], held: np.ndarray) -> np.ndarray:
        """(…, C) rows of the (K, C) array `held` at the texels of `region` that show a
        preview, zeros elsewhere, in its type."""
        return _rows_shown(*self._shown(region), held)


def _rows_shown(rows: np.ndarray, shown: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(…, C) rows `rows` (…) of the (K, C) array `held` where `shown`, zeros elsewhere, in
    its type (all zeros where no texel is held, K = 0: `rows` then point nowhere)."""
    if not len(held):
        return np.zeros((*rows.shape, held.shape[1]), held.dtype)
    return np.where(shown[..., None], held[rows], 0).astype(held.dtype)


@dataclass(frozen=True)
class LatticeOnFile:
    """A lattice file opened and checked against its volume, no texel read: what a
    display knows of a lattice before its view says which texels it reads.

    Attributes:
        file: the opened file (`baking.lattice_file.LatticeFile`; its ``meta`` without
            the bake config's dict).
        geometry: its texel placement.
        config: its bake config, or None.
    """

    file: LatticeFile
    geometry: LatticeGeometry
    config: BakeConfig | None

    @classmethod
    def open(cls, path: str | os.PathLike[str], volume: Volume | None = None
             ) -> LatticeOnFile:
        """`path` opened; with `volume`, checked to be baked for it.

        Raises:
            BakeError: as `baking.Lattice.load`.
        """
        return cls(*open_lattice(path, volume))

    @property
    def meta(self) -> dict[str, Any]:
        """The file's metadata (as `baking.Lattice.meta`)."""
        return self.file.meta

    @property
    def kind(self) -> str:
        return lattice_kind(self.meta)

    def held(self, texels: np.ndarray | None = None, fill: bool = False) -> HeldLattice:
        """The computed texels among (K,) sorted flat ids `texels` (None: all), read from
        the file a slab at a time: their means, facings and samples (as `paths`); with
        `fill` (a display of an unfinished file), its texels among them without paths
        yet too, from their neighbours (`_fill_unbaked`), read in the same pass."""
        asked = None if texels is None else np.asarray(texels, np.int64)
        read = asked if asked is None or not fill else _with_neighbours(asked,
                                                                         self.geometry.shape)
        ids, arrays = self.file.read_texels(read)
        done = arrays["samples"] > 0
        keep = np.ones(len(ids), bool) if read is asked else np.isin(ids, asked)
        computed = done & keep
        lattice = HeldLattice(self.geometry, ids[computed], arrays["values"].shape[1],
                              self.meta, self.config)
        lattice.values = arrays["values"][computed]
        lattice.facing = arrays["facing"][computed]
        lattice.paths = arrays["samples"][computed]
        lattice.unbaked = int(np.count_nonzero(~done & keep))
        if fill and lattice.unbaked:
            self._fill_unbaked(lattice, ids[~done & keep],
                               (ids[done], arrays["values"][done], arrays["facing"][done]))
        return lattice

    def _fill_unbaked(self, lattice: HeldLattice, unbaked: np.ndarray,
                      near: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """Add to `lattice` the (U,) sorted flat ids `unbaked` (held by the file without
        paths yet: an unfinished bake's) that have computed texels among their 26
        neighbours, each the mix of those weighted as trilinear interpolation over a
        lattice of twice the spacing weighs them (½ a step along each axis they differ
        in), with the facing of the heaviest — so the half lattice that a default bake
        traces first shows as that lattice, not as dots of light on unlit texels; their
        paths 1 (shown). `near`: the (N,) sorted flat ids, (N, C) values and (N, 2)
        facings of the computed texels read with them, their neighbours among them;
        `FILL_BLOCK` texels at a time (about 2 KB of work arrays a texel)."""
        parts = [self._mixed(unbaked[lo:lo + FILL_BLOCK], *near)
                 for lo in range(0, len(unbaked), FILL_BLOCK)]
        ids = np.concatenate([part[0] for part in parts])
        if not len(ids):
            return
        order = np.argsort(np.concatenate([lattice.texels, ids]), kind="stable")
        lattice.texels = np.concatenate([lattice.texels, ids])[order]
        lattice.values = np.concatenate(
            [lattice.values, *(part[1].astype(lattice.values.dtype) for part in parts)]
        )[order]
        lattice.facing = np.concatenate([lattice.facing, *(part[2] for part in parts)])[order]
        lattice.paths = np.concatenate([lattice.paths,
                                        np.ones(len(ids), lattice.paths.dtype)])[order]
        lattice.filled = len(ids)

    def _mixed(self, unbaked: np.ndarray, ids: np.ndarray, values: np.ndarray,
               facing: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(F,) ids of the (U,) sorted flat `unbaked` with computed neighbours, (F, C)
        their mixes and (F, 2) facings (`_fill_unbaked`); the neighbours found among the
        computed texels' sorted `ids` (`values`, `facing`) by `fill_check.neighbours_of`."""
        from isolume.baking.fill_check import OFFSETS, neighbours_of

        box = tuple(self.geometry.shape)
        at = np.stack(np.unravel_index(unbaked, box), axis=1)  # (U, 3) z, y, x
        rows = neighbours_of(at, ids, box)  # (U, 26), -1: none computed
        weight = np.where(rows >= 0, 0.5 ** np.abs(OFFSETS).sum(axis=1)[None], 0.0)
        total = weight.sum(axis=1)
        filled = total > 0
        rows, weight = np.maximum(rows[filled], 0), weight[filled]
        mixed = np.einsum("un,unc->uc", weight, values[rows]) / total[filled, None]
        heaviest = rows[np.arange(len(rows)), np.argmax(weight, axis=1)]
        return unbaked[filled], mixed, facing[heaviest]


def _with_neighbours(texels: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """The (K,) sorted flat ids `texels` of a (Z, Y, X) box and their 26 neighbours,
    sorted and unique (what `LatticeOnFile.held` reads to fill its unbaked texels)."""
    from isolume.baking.fill_check import OFFSETS

    box = np.array(shape)
    at = np.stack(np.unravel_index(texels, shape), axis=1)
    steps = np.concatenate([np.zeros((1, 3), OFFSETS.dtype), OFFSETS])
    near = np.clip(at[:, None, :] + steps[None], 0, box - 1).reshape(-1, 3)
    return np.unique(np.ravel_multi_index(near.T, shape))
