"""`baking.view_texels.HeldLattice`: previews at a set of texels answer as a dense
lattice holding the same previews does."""

from __future__ import annotations

import numpy as np
import pytest

from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.view_texels import HeldLattice


def _pair(seed: int = 4):
    """A HeldLattice and a dense Lattice with the same previews at random texels (a
    tenth of them traced with no path)."""
    geometry = LatticeGeometry((11, 13, 17), (0.0,) * 3, (1.0,) * 3)
    rng = np.random.default_rng(seed)
    texels = np.sort(rng.choice(11 * 13 * 17, 400, replace=False))
    sparse = HeldLattice(geometry, texels, 3, {"kind": "irradiance"})
    dense = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    dense.preview = np.zeros((*geometry.shape, 3), np.float32)
    dense.preview_paths = np.zeros(geometry.shape, np.uint16)
    for part in np.array_split(rng.permutation(texels), 3):
        paths = np.where(rng.random(len(part)) < 0.1, 0, 64)
        values = rng.uniform(0.1, 2.0, ((paths > 0).sum(), 3))
        codes = rng.integers(1, 256, ((paths > 0).sum(), 2)).astype(np.uint8)
        for lattice in (sparse, dense):
            lattice.store_preview(part, paths, values, codes)
    return sparse, dense


def test_slabs_and_index_arrays_read_as_the_dense_lattice():
    sparse, dense = _pair()
    rng = np.random.default_rng(1)
    regions = [np.s_[0:9], np.s_[8:11], np.s_[10:20],
               tuple(rng.integers(0, n, (5, 1, 1)) for n in (11, 13, 17)),
               (rng.integers(0, 11, 50), rng.integers(0, 13, 50), rng.integers(0, 17, 50))]
    for region in regions:
        np.testing.assert_array_equal(sparse.shown(region), dense.shown(region))
        np.testing.assert_array_equal(sparse.displayed(region), dense.displayed(region))
        np.testing.assert_array_equal(sparse.displayed_facing(region),
                                      dense.displayed_facing(region))
        for lattice in (sparse, dense):  # the three from one lookup
            for got, want in zip(lattice.display(region),
                                 (lattice.shown(region), lattice.displayed_facing(region),
                                  lattice.displayed(region)), strict=True):
                assert got.dtype == want.dtype
                np.testing.assert_array_equal(got, want)
    assert sparse.shown(np.s_[:]).sum() == (sparse.paths > 0).sum() > 300
    empty = HeldLattice(sparse.geometry, np.zeros(0, np.int64), 3, {"kind": "irradiance"})
    shown, facing, values = empty.display(np.s_[2:4])
    assert not shown.any() and not facing.any() and not values.any()
    assert facing.shape == (2, 13, 17, 2) and values.shape == (2, 13, 17, 3)


def test_it_holds_only_its_texels():
    sparse, _ = _pair()
    assert sparse.values.shape == (400, 3)
    missing = np.setdiff1d(np.arange(100), sparse.texels)[:3]
    with pytest.raises(ValueError, match="does not hold"):
        sparse.store_preview(missing, np.full(3, 8), np.ones((3, 3)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="sorted"):
        HeldLattice(sparse.geometry, np.array([5, 3]), 3, {})


def test_a_view_lattice_does_not_hash_its_volume():
    """A lattice for one picture carries its volume's identity but for the hash (never
    saved: the picture need not wait for a SHA-256 of the samples), and so is refused by
    the check a lattice file gets against a volume."""
    from isolume import volumes
    from isolume.baking.config import BakeConfig
    from isolume.baking.errors import BakeError
    from isolume.baking.lattice import check_identity

    volume = volumes.load("synthetic:sphere:16")
    held = HeldLattice.for_texels(volume, BakeConfig(samples=4), np.arange(5))
    identity = held.meta["volume"]
    assert identity["hash"] is None and identity["shape"] == [16, 16, 16]
    assert identity["spacing"] == list(volume.spacing) and "hash" not in volume._cache
    with pytest.raises(BakeError, match="hash None"):
        check_identity(held.meta, volume)


def test_an_unfinished_files_texels_without_paths_show_their_neighbours_mix(tmp_path,
                                                                         monkeypatch):
    """A file whose texels at odd indices have no paths yet (the half lattice a default
    bake traces first, then cut off) shows each of them, in `LatticeOnFile.held`, as the
    trilinear mix of the half lattice around it — computed here on the dense arrays — with
    the facing of its heaviest neighbour and one path, and counts them as unbaked."""
    from isolume.baking import BakeConfig, bake
    from isolume.baking.view_texels import LatticeOnFile
    from isolume.volumes.synthetic import make

    volume = make("sphere", 16)
    lattice = bake(volume, BakeConfig(samples=2, bounces=0), workers=1)
    z, y, x = np.indices(lattice.samples.shape)
    node = (z % 2 == 0) & (y % 2 == 0) & (x % 2 == 0)
    baked = lattice.samples > 0
    lattice.samples[~node] = 0
    path = tmp_path / "cut.npz"
    lattice.save(path)
    opened = LatticeOnFile.open(path, volume)
    assert len(opened.held().texels) == np.count_nonzero(node & baked)  # computed only
    held = opened.held(fill=True)
    assert held.unbaked == np.count_nonzero(baked & ~node)
    from isolume.baking import view_texels

    monkeypatch.setattr(view_texels, "FILL_BLOCK", 7)  # in blocks: the same texels
    in_blocks = opened.held(fill=True)
    for name in ("texels", "values", "facing", "paths"):
        np.testing.assert_array_equal(getattr(in_blocks, name), getattr(held, name))
    asked = np.flatnonzero(baked.reshape(-1))[::3]  # a picture's texels: their neighbours
    part = opened.held(asked, fill=True)            # are read in the same pass
    kept = np.isin(held.texels, asked)
    np.testing.assert_array_equal(part.texels, held.texels[kept])
    for name in ("values", "facing", "paths"):
        np.testing.assert_array_equal(getattr(part, name), getattr(held, name)[kept])

    done = (lattice.samples > 0).astype(np.float64)
    sums = np.zeros((*done.shape, 3))
    weights = np.zeros(done.shape)
    padded_done = np.pad(done, 1)
    padded_values = np.pad(lattice.values.astype(np.float64), ((1, 1),) * 3 + ((0, 0),))
    shape = done.shape
    for step in np.ndindex(3, 3, 3):
        if step == (1, 1, 1):
            continue
        w = 0.5 ** np.abs(np.array(step) - 1).sum()
        window = tuple(slice(s, s + n) for s, n in zip(step, shape, strict=True))
        weights += w * padded_done[window]
        sums += w * (padded_done[window][..., None] * padded_values[window])
    want = baked & ~node & (weights > 0)
    flat = np.flatnonzero(want)
    rows = np.searchsorted(held.texels, flat)
    assert np.array_equal(held.texels[rows], flat)
    np.testing.assert_allclose(held.values[rows], (sums[want] / weights[want][:, None]),
                               rtol=1e-5)
    assert (held.paths[rows] == 1).all()
    assert len(held.texels) == np.count_nonzero(node & baked) + len(flat) == \
        np.count_nonzero(node & baked) + held.filled
    x_odd = want & (z % 2 == 0) & (y % 2 == 0) & (x % 2 == 1) & np.roll(baked, 1, axis=2)
    assert x_odd.any()
    at = np.searchsorted(held.texels, np.flatnonzero(x_odd))  # heaviest: the node at x − 1
    np.testing.assert_array_equal(held.facing[at], np.roll(lattice.facing, 1, axis=2)[x_odd])
