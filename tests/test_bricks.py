"""The sparse lattice textures: bricks, their slots in the atlas and what the shader reads
through the indirection (`app.render.bricks`, `app.render.lattice_gl`)."""

from __future__ import annotations

import numpy as np
import pytest

from isolume.app.render.bricks import (
    BRICK,
    STORED,
    AtlasLayout,
    assemble_layer,
    block_region,
    brick_grid,
    needed_bricks,
)


def _needed_brute(shown: np.ndarray) -> np.ndarray:
    """Bricks that hold the lower corner of a cell (texel ≤ n − 2 along each axis) and
    whose 9³ block (its 8³ texels and the next texel on each high side) holds a shown
    texel, by looking at every brick."""
    out = np.zeros(brick_grid(shown.shape), bool)
    for b in np.ndindex(out.shape):
        lo = [BRICK * v for v in b]
        base = all(v <= n - 2 for v, n in zip(lo, shown.shape, strict=True))
        out[b] = base and shown[lo[0]:lo[0] + STORED, lo[1]:lo[1] + STORED,
                                lo[2]:lo[2] + STORED].any()
    return out


@pytest.mark.parametrize("shape", [(8, 8, 8), (9, 17, 23), (2, 31, 16), (40, 3, 25),
                                   (17, 9, 33)])
def test_needed_bricks_are_those_whose_block_holds_a_shown_texel(shape):
    rng = np.random.default_rng(sum(shape))
    for density in (0.0, 0.002, 0.02, 0.5):
        shown = rng.random(shape) < density
        got = needed_bricks(shown.__getitem__, shape)
        np.testing.assert_array_equal(got, _needed_brute(shown))


def test_a_texel_on_a_brick_face_needs_the_bricks_below_it_too():
    """Texel (8, 8, 8) is the first of brick (1, 1, 1) and in the aprons of its seven lower
    neighbours: a cell with its lower corner in any of them reads it."""
    shown = np.zeros((20, 20, 20), bool)
    shown[8, 8, 8] = True
    needed = needed_bricks(shown.__getitem__, shown.shape)
    assert needed.sum() == 8 and needed[:2, :2, :2].all()
    # a lattice of 9 texels: texel 8 is only ever read through brick 0's apron
    corner = np.zeros((9, 9, 9), bool)
    corner[8, 8, 8] = True
    needed = needed_bricks(corner.__getitem__, corner.shape)
    assert needed.sum() == 1 and needed[0, 0, 0]


def test_blocks_are_read_with_their_apron_and_clamped_at_the_edge():
    shape = (10, 12, 17)
    grid = np.arange(np.prod(shape)).reshape(shape)
    bricks = np.array([[0, 0, 0], [1, 1, 2]])
    blocks = grid[block_region(bricks, shape)]
    assert blocks.shape == (2, STORED, STORED, STORED)
    np.testing.assert_array_equal(blocks[0], grid[:9, :9, :9])
    z, y, x = (np.minimum(np.arange(lo, lo + STORED), n - 1)
               for lo, n in zip((8, 8, 16), shape, strict=True))
    np.testing.assert_array_equal(blocks[1], grid[np.ix_(z, y, x)])


def test_the_atlas_places_each_slot_once_within_its_size():
    for slots in (1, 2, 7, 100, 1000, 5001):
        layout = AtlasLayout.for_slots(slots, 2048)
        assert layout.capacity >= slots
        corners = layout.corners(np.arange(layout.capacity))
        assert len({tuple(c) for c in corners}) == layout.capacity
        assert (corners < np.array(layout.dims[::-1])).all()
        assert max(layout.texels_xyz) <= 2048
    with pytest.raises(ValueError, match="do not fit"):
        AtlasLayout.for_slots(10**6, 64)


def test_an_atlas_grows_only_as_far_as_gl_allows():
    """Room to grow is given up before the slots in use: 56³ slots fit 512 texels a
    side."""
    assert AtlasLayout.with_room(1000, 1250, 512).capacity >= 1250
    full = AtlasLayout.with_room(101_614, 203_228, 512)
    assert 101_614 <= full.capacity <= 56**3 and max(full.texels_xyz) <= 512
    with pytest.raises(ValueError, match="do not fit"):
        AtlasLayout.with_room(56**3 + 1, 56**3 + 1, 512)


def test_an_assembled_layer_holds_each_block_at_its_slot():
    layout = AtlasLayout((2, 3, 4))
    per = layout.dims[1] * layout.dims[2]
    rng = np.random.default_rng(2)
    blocks = rng.random((per, STORED, STORED, STORED, 2))
    layer = assemble_layer(blocks, layout)
    assert layer.shape == (STORED, 3 * STORED, 4 * STORED, 2)
    for s, (x, y, _) in enumerate(layout.corners(np.arange(per))):
        got = layer[:, y * STORED:(y + 1) * STORED, x * STORED:(x + 1) * STORED]
        np.testing.assert_array_equal(got, blocks[s])
