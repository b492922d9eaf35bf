"""Where a lattice's texels live on the GPU: bricks in an atlas, through an indirection.

A lattice of (Z, Y, X) texels is cut into `BRICK`³ bricks (`baking.lattice.brick_grid`);
only the bricks a lookup can read a shown texel from get a *slot* in the atlas textures,
so texture memory follows the shown texels, not the lattice's box. A slot holds `STORED`³
texels: the brick's own and one more layer on each high side (the *apron*, a copy of the
first texels of the next bricks), so that every lookup of a cell — the eight texels
around a point, hardware trilinear included — reads one slot, chosen by the brick of the
cell's lower corner. A brick needs a slot when a texel of its `STORED`³ block is shown
(`needed_bricks`). Slot 0 stays empty (all zeros: not shown), and the indirection texture
sends every brick without a slot there.

Slots fill the atlas x first, then y, then z (`AtlasLayout`), `STORED` texels apart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from isolume.baking.lattice import BRICK, brick_grid

STORED = BRICK + 1
"""Texels per side of a slot: the brick and its apron."""
GROWTH = 1.25
"""Slots an atlas is made with, per slot needed (room for a lazy bake to grow into)."""


def cell_bricks(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """Bricks along z, y, x that hold the lower corner of a cell (texel ≤ n − 2): a last
    brick of one texel is read only through the apron of the brick below it."""
    return tuple(-(-(int(n) - 1) // BRICK) for n in shape)


def _blocks_any(mask: np.ndarray, axis: int) -> np.ndarray:
    """Along `axis` (length n) of a bool array: for each brick j, whether any of the
    elements 8j … 8j + 8 (its own and its apron) is set; length ceil(n / 8)."""
    m = np.moveaxis(mask, axis, 0)
    n = m.shape[0]
    nb = -(-n // BRICK)
    padded = np.zeros((nb * BRICK + 1, *m.shape[1:]), bool)
    padded[:n] = m
    own = padded[:nb * BRICK].reshape(nb, BRICK, *m.shape[1:]).any(axis=1)
    return np.moveaxis(own | padded[BRICK::BRICK], 0, axis)


def needed_bricks(shown: Callable[[slice], np.ndarray], shape: tuple[int, int, int]
                  ) -> np.ndarray:
    """(BZ, BY, BX) bool: the bricks whose `STORED`³ block holds a shown texel, among
    those a cell's lower corner can lie in (`cell_bricks`).

    Args:
        shown: a slice of z → (z, Y, X) bool mask of the texels shown in those layers
            (`baking.Lattice.shown`); read one row of bricks (9 z-layers) at a time.
        shape: (Z, Y, X) texels.
    """
    out = np.zeros(brick_grid(shape), bool)
    bz, by, bx = cell_bricks(shape)
    for k in range(bz):
        layers = shown(np.s_[k * BRICK:min((k + 1) * BRICK + 1, shape[0])]).any(axis=0)
        out[k, :by, :bx] = _blocks_any(_blocks_any(layers, 0), 1)[:by, :bx]
    return out


def block_region(bricks: np.ndarray, shape: tuple[int, int, int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index arrays that read the `STORED`³ blocks of (M, 3) z, y, x bricks from a
    (Z, Y, X) grid: they broadcast to (M, 9, 9, 9); apron texels past the lattice's edge
    repeat the edge texel (a lookup never reads them)."""
    steps = np.arange(STORED)
    axes = [np.minimum(bricks[:, a, None] * BRICK + steps, shape[a] - 1) for a in range(3)]
    return (axes[0][:, :, None, None], axes[1][:, None, :, None], axes[2][:, None, None, :])


@dataclass(frozen=True)
class AtlasLayout:
    """Slots of an atlas: `dims` (AZ, AY, AX) slots, slot s at x = s mod AX, then y, z.

    Attributes:
        dims: slots along z, y, x.
    """

    dims: tuple[int, int, int]

    @classmethod
    def for_slots(cls, slots: int, max_texels: int) -> AtlasLayout:
        """A near-cubic atlas of at least `slots` slots whose sides stay within
        `max_texels` (GL_MAX_3D_TEXTURE_SIZE).

        Raises:
            ValueError: when even a full atlas of that size has too few slots.
        """
        most = max_texels // STORED
        ax = min(most, max(1, int(np.ceil(slots ** (1 / 3)))))
        ay = min(most, max(1, int(np.ceil(np.sqrt(slots / ax)))))
        az = -(-slots // (ax * ay))
        if az > most:
            raise ValueError(f"{slots:,} bricks of {BRICK}³ texels do not fit a 3-D texture "
                             f"of {max_texels} texels a side ({most ** 3:,} bricks); bake "
                             "or render with a coarser lattice (--scale)")
        return cls((az, ay, ax))

    @classmethod
    def with_room(cls, used: int, room: int, max_texels: int) -> AtlasLayout:
        """An atlas of `room` slots where GL allows one (sides within `max_texels`), else
        the largest it allows; at least `used` slots.

        Raises:
            ValueError: when even the largest atlas has fewer than `used` slots.
        """
        most = (max_texels // STORED) ** 3
        return cls.for_slots(max(used, min(room, most)), max_texels)

    @property
    def capacity(self) -> int:
        return int(np.prod(self.dims))

    @property
    def texels_xyz(self) -> tuple[int, int, int]:
        """(width, height, depth) of the atlas textures in texels."""
        az, ay, ax = self.dims
        return ax * STORED, ay * STORED, az * STORED

    def corners(self, slots: np.ndarray) -> np.ndarray:
        """(N, 3) x, y, z of slots' corners, in slots (× `STORED`: texels)."""
        _, ay, ax = self.dims
        s = np.asarray(slots, np.int64)
        return np.stack([s % ax, (s // ax) % ay, s // (ax * ay)], axis=1)

    def layer_slots(self, layer: int) -> range:
        """The slots of atlas z-layer `layer` (in slots)."""
        per = self.dims[1] * self.dims[2]
        return range(layer * per, (layer + 1) * per)


def assemble_layer(blocks: np.ndarray, layout: AtlasLayout) -> np.ndarray:
    """(9, AY·9, AX·9, C) texels of one atlas z-layer from the (AY·AX, 9, 9, 9, C) blocks
    of its slots in slot order."""
    _, ay, ax = layout.dims
    c = blocks.shape[-1]
    grid = blocks.reshape(ay, ax, STORED, STORED, STORED, c)
    return grid.transpose(2, 0, 3, 1, 4, 5).reshape(STORED, ay * STORED, ax * STORED, c)
