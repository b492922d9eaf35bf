"""`baking.plan_lattice.PlanLattice`: a bake's lattice held over its plan's texels only
gives the lattice a dense one gives, to the bit, and is saved, resumed and refined alike."""

import dataclasses

import numpy as np

from isolume.baking import BakeConfig, Lattice, bake
from isolume.baking.bake import Baker
from isolume.baking.lattice import open_lattice
from isolume.baking.plan_lattice import PlanLattice
from isolume.volumes.synthetic import make

FIELDS = ("values", "samples", "second", "active", "facing")


def _same(a: Lattice, b: Lattice) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _baked(packed: bool, config: BakeConfig, volume) -> Baker:
    baker = Baker(volume, config, workers=2, packed=packed)
    try:
        baker.run()
    finally:
        baker.close()
    return baker


def test_a_lattice_over_the_plan_is_the_dense_lattice_to_the_bit(tmp_path):
    """Irradiance (with the sun in the lattice) and SH: the packed baker's lattice, made
    dense and through its file, equals the dense baker's; it holds the plan's texels
    only."""
    volume = make("shells", 24)
    for config in (BakeConfig(samples=6, bounces=1, env="sky:sun=3"),
                   BakeConfig(mode="sh", sh_order=3, samples=6, bounces=1)):
        dense, packed = _baked(False, config, volume), _baked(True, config, volume)
        assert isinstance(packed.lattice, PlanLattice)
        assert packed.lattice.values.shape[0] == len(packed.plan.ids) < dense.lattice.samples.size
        _same(packed.lattice.dense(), dense.lattice)
        packed.lattice.save(tmp_path / "p.npz")
        dense.lattice.save(tmp_path / "d.npz")
        _same(Lattice.load(tmp_path / "p.npz"), Lattice.load(tmp_path / "d.npz"))


def test_a_bake_resumed_from_its_file_reads_its_texels_into_the_plan(tmp_path):
    """Resumed from a file of fewer samples (explicit max_move: the levels do not depend
    on the samples), the plan's texels start from the file's and end as an uninterrupted
    bake's; `fill_from` takes exactly the file's computed texels."""
    config = BakeConfig(samples=12, bounces=1, env="constant:1,1,1", max_move=0.5)
    volume = make("shells", 24)
    path = tmp_path / "l.npz"
    first = bake(volume, dataclasses.replace(config, samples=5), out=path, workers=2)
    baker = Baker(volume, config, workers=2, packed=True,
                  resume=open_lattice(path, volume)[0])
    baker.close()
    np.testing.assert_array_equal(baker.lattice.samples,
                                  first.samples.reshape(-1)[baker.plan.ids])
    np.testing.assert_array_equal(baker.lattice.values,
                                  first.values.reshape(-1, 3)[baker.plan.ids])
    resumed = bake(volume, config, out=path, workers=2, dense=False)
    assert isinstance(resumed, PlanLattice)  # what `isolume bake` keeps: no dense arrays
    np.testing.assert_array_equal(resumed.ids, baker.plan.ids)
    resumed = resumed.dense()
    whole = bake(volume, config, workers=2)
    np.testing.assert_allclose(resumed.values, whole.values, rtol=2e-6, atol=1e-6)
    assert (resumed.samples[resumed.active] == 12).all()
    _same(Lattice.load(path), resumed)
