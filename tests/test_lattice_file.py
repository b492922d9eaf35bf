"""`baking.lattice_file`: a lattice file holds its active or computed texels only, written
and read a slab at a time; a display reads the texels it is asked for."""

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from isolume.baking import BakeConfig, BakeError, Lattice, bake, lattice_file
from isolume.baking.lattice import LatticeGeometry
from isolume.baking.view_texels import LatticeOnFile
from isolume.volumes.errors import WriteError
from isolume.volumes.synthetic import make


@pytest.fixture
def small_slabs(monkeypatch):
    """Slabs of 3 z-layers of the 11 × 13 boxes below: several slabs, a short last one."""
    monkeypatch.setattr(lattice_file, "SLAB_TEXELS", 3 * 11 * 13)


def _random_lattice(channels: int = 3, seed: int = 0, config=None) -> Lattice:
    """A (10, 11, 13) lattice: 30 % of texels active, 70 % of those computed, one computed
    texel outside the active set (a lazy bake's previews can leave those), random arrays;
    irradiance (3 `channels`) or coloured SH transfer of order 3 (27)."""
    rng = np.random.default_rng(seed)
    geometry = LatticeGeometry((10, 11, 13), (0.0, 0.0, 0.0), (1.0, 1.1, 1.3))
    meta = {"kind": "irradiance"} if channels == 3 else {"kind": "sh", "sh_order": 3}
    lattice = Lattice.empty(geometry, channels, meta, config=config)
    lattice.active[...] = rng.random(geometry.shape) < 0.3
    computed = lattice.active & (rng.random(geometry.shape) < 0.7)
    computed[9, 10, 12] = True
    n = int(computed.sum())
    lattice.samples[computed] = rng.integers(1, 200, n)
    lattice.values[computed] = rng.random((n, channels))
    lattice.second[computed] = rng.random(n)
    lattice.facing[computed] = rng.integers(1, 255, (n, 2))
    return lattice


def _same(a: Lattice, b: Lattice) -> None:
    for name in ("values", "samples", "second", "active", "facing"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name


@pytest.mark.parametrize("channels", [3, 27])
def test_a_lattice_comes_back_the_same_and_its_file_holds_only_its_texels(
        tmp_path, small_slabs, channels):
    lattice = _random_lattice(channels)
    path = tmp_path / "l.npz"
    lattice.save(path)
    _same(Lattice.load(path), lattice)
    held = lattice.active | (lattice.samples > 0)
    with np.load(path) as z:
        assert z["values"].shape == (held.sum(), channels)
        assert z["facing"].shape == (held.sum(), 2)
        np.testing.assert_array_equal(np.unpackbits(z["held"], count=held.size), held.ravel())
        assert json.loads(str(z["meta"]))["format_version"] == lattice_file.FORMAT_VERSION


def test_the_held_mask_is_packed_from_the_ids_without_the_box(monkeypatch):
    """`packed_ids` gives `numpy.packbits` of the mask at the ids, for boxes of any size
    (bytes shared between slabs of ids: slabs of 5 ids), empty and full."""
    monkeypatch.setattr(lattice_file, "SLAB_TEXELS", 5)
    rng = np.random.default_rng(4)
    for size in (1, 7, 8, 9, 1000, 4099):
        for fraction in (0.0, 0.02, 0.6, 1.0):
            mask = rng.random(size) < fraction
            np.testing.assert_array_equal(
                lattice_file.packed_ids(np.flatnonzero(mask).astype(np.int32), size),
                np.packbits(mask), err_msg=f"{size} {fraction}")


def test_a_display_reads_the_computed_texels_it_asks_for(tmp_path, small_slabs):
    lattice = _random_lattice()
    path = tmp_path / "l.npz"
    lattice.save(path)
    rng = np.random.default_rng(1)
    asked = np.sort(rng.choice(lattice.samples.size, 600, replace=False))
    asked = np.union1d(asked, [0, lattice.samples.size - 1])  # both ends of the box
    opened = LatticeOnFile.open(path)
    computed = (lattice.samples > 0).ravel()
    for texels, want in ((asked, asked[computed[asked]]), (None, np.flatnonzero(computed))):
        held = opened.held(texels)
        np.testing.assert_array_equal(held.texels, want)
        np.testing.assert_array_equal(held.values, lattice.values.reshape(-1, 3)[want])
        np.testing.assert_array_equal(held.facing, lattice.facing.reshape(-1, 2)[want])
        np.testing.assert_array_equal(held.paths, lattice.samples.ravel()[want])


@pytest.mark.parametrize("slab", [100, 7])
def test_a_read_holds_a_slab_of_the_mask_however_wide_the_layers(tmp_path, monkeypatch,
                                                                  slab):
    """Slabs of `SLAB_TEXELS` flat texels, smaller than a layer of the box (11 × 13 = 143
    texels) and crossing bytes of ``held``: no mask read is longer than a slab, and the
    texels read, dense or at ids, are the lattice's."""
    lattice = _random_lattice()
    path = tmp_path / "l.npz"
    lattice.save(path)
    monkeypatch.setattr(lattice_file, "SLAB_TEXELS", slab)
    masks = []
    held_slabs = lattice_file.LatticeFile._held_slabs

    def recorded(self, zf):
        for part, mask in held_slabs(self, zf):
            masks.append(len(mask))
            yield part, mask

    monkeypatch.setattr(lattice_file.LatticeFile, "_held_slabs", recorded)
    _same(Lattice.load(path), lattice)
    computed = (lattice.samples > 0).ravel()
    asked = np.arange(3, lattice.samples.size, 5)
    read = LatticeOnFile.open(path).held(asked)
    np.testing.assert_array_equal(read.texels, asked[computed[asked]])
    np.testing.assert_array_equal(read.values, lattice.values.reshape(-1, 3)[read.texels])
    assert max(masks) == slab and sum(masks) == 2 * lattice.samples.size


def test_the_texels_read_show_what_the_whole_lattice_shows(tmp_path, small_slabs):
    """Under a sky from every direction (the trapped-texel rule applies), a `HeldLattice`
    read from the file answers `shown`, `displayed` and `displayed_facing` like the dense
    lattice over z-slabs and at index arrays — exactly zero light on 64+ paths included."""
    lattice = _random_lattice(config=BakeConfig(env="constant:1,1,1"))
    trapped = np.argwhere(lattice.samples > 0)[:5]
    lattice.samples[tuple(trapped.T)] = 64
    lattice.values[tuple(trapped.T)] = 0
    path = tmp_path / "l.npz"
    lattice.save(path)
    dense, held = Lattice.load(path), LatticeOnFile.open(path).held()
    assert held.config == lattice.config
    assert not dense.shown()[tuple(trapped.T)].any()
    rng = np.random.default_rng(2)
    at = tuple(rng.integers(0, n, 500) for n in lattice.geometry.shape)
    for region in (np.s_[2:7], at):
        np.testing.assert_array_equal(held.shown(region), dense.shown(region))
        shown = dense.shown(region)
        np.testing.assert_array_equal(held.displayed(region)[shown],
                                      dense.displayed(region)[shown])
        np.testing.assert_array_equal(held.displayed_facing(region)[shown],
                                      dense.displayed_facing(region)[shown])


def test_a_file_that_cannot_be_written_says_why_and_keeps_the_one_there(tmp_path,
                                                                         monkeypatch,
                                                                         disk_full):
    """A write that fails (a full disk) raises one line naming the file, the system's
    reason and what the path holds now; no temporary file stays, an earlier file stays
    as it was."""
    path = tmp_path / "l.npz"
    disk_full()
    with pytest.raises(WriteError, match=r"l\.npz: cannot write the lattice: No space left "
                                        r"on device; nothing was written$"):
        _random_lattice().save(path)
    assert not list(tmp_path.iterdir())
    monkeypatch.undo()
    _random_lattice().save(path)
    before = path.read_bytes()
    disk_full()
    with pytest.raises(WriteError, match=r"the file there is left as it was \(a bake resumes"):
        _random_lattice(seed=1).save(path)
    assert path.read_bytes() == before and list(tmp_path.iterdir()) == [path]


def test_a_file_of_dense_arrays_still_loads(tmp_path):
    """A file of format version 1 (every array dense over the box; ``facing`` optional)."""
    lattice = _random_lattice()
    meta = {"kind": "irradiance", "format_version": lattice_file.DENSE_VERSION,
            "shape": [10, 11, 13], "box_lo": [0, 0, 0], "box_hi": [1.0, 1.1, 1.3]}
    arrays = {n: getattr(lattice, n) for n in ("values", "samples", "second", "active")}
    np.savez_compressed(tmp_path / "old.npz", **arrays, facing=lattice.facing,
                        meta=np.array(json.dumps(meta)))
    _same(Lattice.load(tmp_path / "old.npz"), lattice)
    held = LatticeOnFile.open(tmp_path / "old.npz").held()
    np.testing.assert_array_equal(held.texels, np.flatnonzero(lattice.samples > 0))
    np.savez_compressed(tmp_path / "older.npz", **arrays, meta=np.array(json.dumps(meta)))
    assert not Lattice.load(tmp_path / "older.npz").facing.any()  # every facing unknown


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -0.5])
def test_irradiance_that_is_not_finite_or_negative_is_refused_as_it_is_read(
        tmp_path, small_slabs, bad):
    """A texel with a NaN, infinite or negative irradiance in any channel is counted once;
    the load and a display's read refuse the file in one line naming it."""
    lattice = _random_lattice()
    computed = np.argwhere(lattice.samples > 0)
    lattice.values[tuple(computed[0])] = [bad, 1.0, bad]
    lattice.values[(*computed[-1], 1)] = bad
    path = tmp_path / "l.npz"
    lattice.save(path)
    held = int((lattice.active | (lattice.samples > 0)).sum())
    for read in (lambda: Lattice.load(path), lambda: LatticeOnFile.open(path).held()):
        with pytest.raises(BakeError, match=rf"l\.npz: 2 of the {held:,} texels read hold "
                                            "NaN, infinite or negative values, expected "
                                            "finite irradiance ≥ 0"):
            read()


def test_sh_coefficients_may_be_negative_but_not_nan(tmp_path):
    lattice = _random_lattice(channels=27)
    lattice.values[lattice.samples > 0] -= 0.5
    path = tmp_path / "sh.npz"
    lattice.save(path)
    _same(Lattice.load(path), lattice)
    lattice.values[tuple(np.argwhere(lattice.samples > 0)[3])] = np.nan
    lattice.save(path)
    with pytest.raises(BakeError, match=r"1 of the \d+ texels read hold NaN or infinite values, "
                                        "expected finite SH coefficients"):
        Lattice.load(path)


def test_a_display_judges_the_values_it_reads_a_slab_at_a_time(tmp_path, small_slabs,
                                                                monkeypatch):
    """A display's read judges each slab of values as it is read (the 3-layer slabs here,
    which it reads through to the texels it asks for): a texel it does not ask for, in a
    slab it reads, still refuses the damaged file."""
    lattice = _random_lattice()
    lattice.values[tuple(np.argwhere(lattice.samples[:3] > 0)[0])] = np.nan
    path = tmp_path / "l.npz"
    lattice.save(path)
    judged = []
    bad_texels = lattice_file.bad_texels
    monkeypatch.setattr(lattice_file, "bad_texels",
                        lambda values, nonnegative: judged.append(len(values))
                        or bad_texels(values, nonnegative))
    with pytest.raises(BakeError, match=r"1 of the \d+ texels read hold NaN"):
        LatticeOnFile.open(path).held(np.arange(3 * 11 * 13, lattice.samples.size))
    held = lattice.active | (lattice.samples > 0)
    assert judged == [int(held[z:z + 3].sum()) for z in range(0, 10, 3)]


def test_bad_values_are_counted_in_texels_in_a_file_of_dense_arrays(tmp_path):
    lattice = _random_lattice()
    lattice.values[2, 3, 4] = np.nan
    meta = {"kind": "irradiance", "format_version": lattice_file.DENSE_VERSION,
            "shape": [10, 11, 13], "box_lo": [0, 0, 0], "box_hi": [1.0, 1.1, 1.3]}
    arrays = {n: getattr(lattice, n) for n in ("values", "samples", "second", "active")}
    np.savez_compressed(tmp_path / "old.npz", **arrays, meta=np.array(json.dumps(meta)))
    with pytest.raises(BakeError, match="1 of the 1,430 texels read hold NaN"):
        Lattice.load(tmp_path / "old.npz")


def test_bad_texels_judges_with_two_reductions_where_all_are_good(monkeypatch):
    values = np.random.default_rng(3).random((1000, 3)).astype(np.float32) - 0.5
    assert lattice_file.bad_texels(values, nonnegative=False) == 0
    assert lattice_file.bad_texels(values, nonnegative=True) == int((values < 0).any(1).sum())
    assert lattice_file.bad_texels(np.zeros((0, 3), np.float32), nonnegative=True) == 0
    monkeypatch.setattr(np, "isfinite", None)  # not needed where no value is bad
    assert lattice_file.bad_texels(np.abs(values), nonnegative=True) == 0


def _rewritten(path, tmp_path, name: str, array: np.ndarray | bytes):
    """A copy of the lattice file `path` with member `name` replaced by `array` (or by
    the bytes of a .npy file)."""
    with np.load(path) as z:
        members = {k: z[k] for k in z.files}
    out = tmp_path / f"bad_{name}.npz"
    if isinstance(array, bytes):
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
            for key, member in members.items():
                if key != name:
                    with zf.open(f"{key}.npy", "w") as f:
                        np.lib.format.write_array(f, member)
            zf.writestr(f"{name}.npy", array)
        return out
    members[name] = array
    np.savez_compressed(out, **members)
    return out


def _meta(meta: dict, **changes) -> np.ndarray:
    """The meta member of a file with `changes` made to its `meta`."""
    return np.array(json.dumps(dict(meta, **changes)))


def test_a_file_that_disagrees_with_itself_is_refused_in_one_line(tmp_path):
    lattice = _random_lattice()
    path = tmp_path / "l.npz"
    lattice.save(path)
    with np.load(path) as z:
        values, samples, meta = z["values"], z["samples"], json.loads(str(z["meta"]))
    bad = {
        "one row too many": ("values", np.concatenate([values, values[:1]]),
                             r"values of shape \(\d+, 3\) and type float32 does not match"),
        "another type": ("samples", samples.astype(np.int64),
                         r"samples of shape \(\d+,\) and type int64 does not match the "
                         r"lattice \(expected \(\d+\) of uint32\)"),
        "a later version": ("meta", np.array(json.dumps(dict(meta, format_version=9))),
                            r"lattice format version 9, this isolume reads 1 and 2"),
        "no shape": ("meta", np.array(json.dumps({"format_version": 2})),
                     r"not a readable isolume lattice"),
        "a box that lies": ("meta", np.array(json.dumps(dict(meta, shape=[10**5] * 3))),
                            r"a lattice of \(100000, 100000, 100000\) texels needs 2\.3e\+07 "
                            r"GB dense, more than the"),
    }
    second = np.load(path)["second"].copy()
    second[[0, 1]] = np.nan, -5.0
    held = np.load(path)["held"].copy()
    held[-1] |= 0x01  # 1430 texels: the last byte's two last bits pad it
    bad.update({
        "box_lo of two numbers": ("meta", _meta(meta, box_lo=[0.0, 0.0]),
                                  r"lattice box_lo \[0\.0, 0\.0\]: expected three finite "
                                  "numbers"),
        "box_lo of words": ("meta", _meta(meta, box_lo=["a", "b", "c"]), "box_lo"),
        "box_lo NaN": ("meta", _meta(meta, box_lo=[float("nan"), 0, 0]), "box_lo"),
        "box_hi below box_lo": ("meta", _meta(meta, box_hi=[-1.0, 1.1, 1.3]),
                                r"expected each coordinate of box_hi above box_lo's"),
        "a shape of fractions": ("meta", _meta(meta, shape=[10.9, 11, 13]),
                                 r"lattice shape \[10\.9, 11, 13\]: expected three whole"),
        "an unknown kind": ("meta", _meta(meta, kind="bogus"),
                            "lattice kind 'bogus': expected one of irradiance, sh"),
        "five channels of irradiance": ("values", np.ones((len(values), 5), np.float32),
                                        "kind irradiance with 5 values a texel: expected 3$"),
        "a config of another isolume": ("meta", _meta(meta, config={"nonsense": 1}),
                                        "a bake config this isolume cannot read"),
        "a config version of words": ("meta", _meta(meta, config={}, config_version="x"),
                                      "bake config version 'x': expected a whole number"),
        "a config that is a list": ("meta", _meta(meta, config=[1, 2]),
                                    "expected a mapping of settings"),
        "second moments NaN and negative": (
            "second", second, r"2 of the \d+ texels read hold NaN, infinite or negative "
                              "second moments, expected finite second moments ≥ 0"),
        "a held bit past the box": ("held", held, "held marks texels past the last of the "
                                                  "box's 1,430"),
    })
    for case, (name, array, message) in bad.items():
        with pytest.raises(BakeError, match=message) as caught:
            Lattice.load(_rewritten(path, tmp_path, name, array))
        assert "\n" not in str(caught.value), case
    header = io.BytesIO()
    np.lib.format.write_array(header, values)
    with pytest.raises(BakeError, match=r"values\.npy goes on past the \(\d+, 3\) array"):
        Lattice.load(_rewritten(path, tmp_path, "values", header.getvalue() + bytes(64)))
    lying = _rewritten(path, tmp_path, "meta",
                       np.array(json.dumps(dict(meta, shape=[10**5] * 3))))
    with pytest.raises(BakeError, match=r"bad_meta\.npz: held of shape \(\d+,\) and type uint8 "
                                        r"does not match the lattice \(expected "
                                        r"\(125000000000000\) of uint8\)$"):
        LatticeOnFile.open(lying).held()  # a display reads a slab at a time: refused, not made


def test_a_bake_is_checked_against_its_volume_before_its_texels_are_read(tmp_path):
    """A lattice of another volume is refused from its metadata alone: its texels are not
    read (here they could not be)."""
    path = tmp_path / "s.npz"
    bake(make("sphere", 16), BakeConfig(samples=2, bounces=0), out=path)
    with np.load(path) as z:
        broken = _rewritten(path, tmp_path, "values", z["values"][:1])
    for read in (lambda: Lattice.load(broken, make("torus", 16)),
                 lambda: LatticeOnFile.open(broken, make("torus", 16))):
        with pytest.raises(BakeError, match="not for 'torus'"):
            read()
    with pytest.raises(BakeError, match="values of shape"):
        Lattice.load(broken, make("sphere", 16))


def test_a_lattice_is_refused_for_its_volume_placed_or_spaced_otherwise(tmp_path):
    """The same samples at another origin (the light would be looked up a shift away) or
    with other spacing are refused, each naming the option that differs."""
    from dataclasses import replace

    vol = make("sphere", 16)
    path = tmp_path / "s.npz"
    bake(vol, BakeConfig(samples=2, bounces=0), out=path)
    Lattice.load(path, vol)
    with pytest.raises(BakeError, match=r"first sample at -0.5,-0.5,-0.5, here at 100,0,0: .* the "
                                        r"--origin \(and --up\) the bake was given$"):
        Lattice.load(path, replace(vol, origin=(100.0, 0.0, 0.0)))
    spaced = replace(vol, spacing=(1.0, 1.0, 3.0))
    for read in (lambda: Lattice.load(path, spaced), lambda: LatticeOnFile.open(path, spaced)):
        with pytest.raises(BakeError, match=r"voxels are 0.0666667,0.0666667,0.0666667 apart, "
                                            r"here 1,1,3: load it with the --spacing the "
                                            r"bake was given$"):
            read()


def test_a_box_larger_than_memory_is_refused_before_it_is_made(tmp_path, monkeypatch):
    """Read dense, the (10, 11, 13) box of 3 channels needs 1430 × 23 bytes; with less
    memory available the load names both figures, and a display still reads its texels."""
    lattice = _random_lattice()
    path = tmp_path / "l.npz"
    lattice.save(path)
    monkeypatch.setattr(lattice_file, "available_memory", lambda: 1430 * 23 - 1)
    with pytest.raises(BakeError, match=r"l\.npz: a lattice of \(13, 11, 10\) texels needs "
                                        r"3\.29e-05 GB dense, more than the 3\.29e-05 GB"):
        Lattice.load(path)
    assert len(LatticeOnFile.open(path).held().texels) == (lattice.samples > 0).sum()
    monkeypatch.setattr(lattice_file, "available_memory", lambda: 1430 * 23)
    _same(Lattice.load(path), lattice)


def test_the_viewers_shared_lattice_is_read_from_the_file_in_place(tmp_path, small_slabs):
    """`view --lattice FILE`: the shared arrays a lazy bake extends are filled from the
    file a slab at a time (no private copy of the box first): the lattice `Lattice.load`
    reads, with its config."""
    from isolume.app.viewer.bake_client import SharedLattice

    lattice = _random_lattice(config=BakeConfig(env="constant:1,1,1"))
    lattice.meta["channels"] = 3
    path = tmp_path / "l.npz"
    lattice.save(path)
    opened = LatticeOnFile.open(path)
    shared = SharedLattice.create(opened.geometry, 3, opened.meta, opened)
    try:
        _same(shared.lattice, lattice)
        assert shared.lattice.config == lattice.config
        assert not shared.lattice.preview_paths.any()
    finally:
        shared.close()


def test_the_writing_thread_deflates_queued_pieces_instead_of_waiting(tmp_path, monkeypatch):
    """While the oldest piece is not deflated yet, the thread writing the member deflates
    the newest one no pool thread has started: with slow pool threads it does some of
    the work itself, and the file is the same bytes as one thread's."""
    import threading
    import time

    from isolume.volumes import cores

    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    lattice = _random_lattice(seed=5)
    path1 = tmp_path / "one.npz"
    cores.use(1)
    try:
        lattice.save(path1)
    finally:
        cores.use(None)
    deflated, here = lattice_file._deflated, []

    def slow_on_the_pool(piece, runs, batch):
        if threading.current_thread() is threading.main_thread():
            here.append(len(piece))
        else:
            time.sleep(0.002)
        return deflated(piece, runs, batch)

    monkeypatch.setattr(lattice_file, "_deflated", slow_on_the_pool)
    cores.use(2)
    try:
        lattice.save(tmp_path / "two.npz")
    finally:
        cores.use(None)
    assert len(here) > 0
    assert (tmp_path / "two.npz").read_bytes() == path1.read_bytes()


def test_a_save_ends_while_every_pool_thread_is_busy(tmp_path, monkeypatch):
    """The writing thread does what no pool thread has begun — the pieces and the held
    mask — so a save whose pool threads are all held elsewhere ends all the same, with the
    same bytes as one thread's."""
    import threading

    from isolume.volumes import cores

    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    lattice = _random_lattice(seed=8)
    cores.use(1)
    try:
        lattice.save(tmp_path / "one.npz")
    finally:
        cores.use(None)
    cores.use(2)
    release = threading.Event()
    try:
        held = [cores.pool().submit(release.wait, 10) for _ in range(2)]
        lattice.save(tmp_path / "busy.npz")
        assert not any(h.done() for h in held)  # the pool did none of it
    finally:
        release.set()
        cores.use(None)
    assert (tmp_path / "busy.npz").read_bytes() == (tmp_path / "one.npz").read_bytes()


def test_a_failed_save_leaves_no_held_mask_to_be_made(tmp_path, monkeypatch, disk_full):
    """A save that fails before the held mask's member (a full disk) withdraws the mask
    from the pool's queue: no pool thread makes it afterwards (nor delays the stop)."""
    import threading

    from isolume.volumes import cores

    made = []
    monkeypatch.setattr(cores, "beside_call", lambda kind, work: made.append(kind))
    disk_full()
    cores.use(2)
    release = threading.Event()
    try:
        held = [cores.pool().submit(release.wait, 10) for _ in range(2)]
        with pytest.raises(WriteError):
            _random_lattice().save(tmp_path / "full.npz")
        release.set()
        for h in held:
            h.result()
        both = threading.Barrier(2)  # met once each pool thread is done with what came before
        for f in [cores.pool().submit(both.wait, 10) for _ in range(2)]:
            f.result()
    finally:
        release.set()
        cores.use(None)
    assert made == []


def test_members_deflated_in_pieces_on_threads_make_the_same_valid_file(tmp_path,
                                                                      monkeypatch):
    """A member's bytes are deflated in pieces on every core (`DEFLATE_PIECE`): the file's
    CRCs check (`zipfile.testzip`), `numpy.load` reads it, and it is the same bytes on
    one thread and on three, with pieces much smaller than a member."""
    import zipfile

    from isolume.volumes import cores

    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    lattice = _random_lattice(seed=4)
    files = []
    for threads in (1, 3):
        cores.use(threads)
        try:
            path = tmp_path / f"l{threads}.npz"
            lattice.save(path)
        finally:
            cores.use(None)
        files.append(path.read_bytes())
        with zipfile.ZipFile(path) as zf:
            assert zf.testzip() is None
            assert zf.getinfo("values.npy").compress_type == zipfile.ZIP_DEFLATED
    assert files[0] == files[1]
    with np.load(tmp_path / "l3.npz") as archive:
        held = lattice_file.held_mask({"active": lattice.active, "samples": lattice.samples})
        np.testing.assert_array_equal(archive["values"], lattice.values[held])
    _same(Lattice.load(tmp_path / "l3.npz"), lattice)


def test_a_quick_save_stores_what_is_not_deflated_yet_in_a_file_that_reads_the_same(
        tmp_path, monkeypatch):
    """`quick_saves`: from the start (`now`) every member is stored; hurried half-way, the
    pieces deflated before stay deflated and the rest are stored, in one valid stream per
    member (also hurried at a moment while two pool threads deflate); either way the file
    checks and reads as the lattice, and saves after the block deflate again, the same
    bytes as before it."""
    import threading
    import zipfile

    from isolume.volumes import cores

    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    lattice = _random_lattice(seed=7)
    cores.use(1)  # pieces deflated in order: the hurry lands after the fifth
    try:
        lattice.save(tmp_path / "deflated.npz")
        with lattice_file.quick_saves(now=True):
            lattice.save(tmp_path / "stored.npz")
        deflated, count = lattice_file._deflated, []
        with lattice_file.quick_saves(now=False) as hurry:
            def hurried_after_five(piece, runs, batch):
                count.append(1)
                if len(count) == 5:
                    hurry()
                return deflated(piece, runs, batch)

            monkeypatch.setattr(lattice_file, "_deflated", hurried_after_five)
            lattice.save(tmp_path / "hurried.npz")
            monkeypatch.setattr(lattice_file, "_deflated", deflated)
        lattice.save(tmp_path / "after.npz")
    finally:
        cores.use(None)

    def sizes(name):
        with zipfile.ZipFile(tmp_path / name) as zf:
            assert zf.testzip() is None
            info = zf.getinfo("values.npy")
            return info.compress_size, info.file_size

    deflated_size, raw = sizes("deflated.npz")
    assert deflated_size < 0.9 * raw
    assert sizes("stored.npz")[0] >= raw
    assert deflated_size < sizes("hurried.npz")[0] < raw  # its first pieces deflated
    cores.use(2)  # hurried at a press while pool threads deflate: stored pieces and not
    try:
        with lattice_file.quick_saves(now=False) as hurry:
            press = threading.Timer(0.001, hurry)
            press.start()
            lattice.save(tmp_path / "pressed.npz")
            press.join()  # pressed inside the block, whenever the save ended
    finally:
        cores.use(None)
    for name in ("stored.npz", "hurried.npz", "pressed.npz"):
        sizes(name)
        _same(Lattice.load(tmp_path / name), lattice)
        with np.load(tmp_path / name) as archive:
            assert archive["values"].shape[1] == 3
    assert (tmp_path / "after.npz").read_bytes() == (tmp_path / "deflated.npz").read_bytes()


def test_quick_saves_leave_the_setting_as_they_found_it():
    """An inner block, hurried or not, gives back the outer one's setting; after the
    outermost, saves deflate."""
    with lattice_file.quick_saves(now=True):
        with lattice_file.quick_saves(now=False):
            pass
        assert lattice_file._Storing.now
    with lattice_file.quick_saves(now=False) as hurry:
        with lattice_file.quick_saves(now=True):
            assert lattice_file._Storing.now
        assert not lattice_file._Storing.now
        hurry()
        assert lattice_file._Storing.now
    assert not lattice_file._Storing.now


def test_second_moments_and_facings_are_deflated_with_runs_only(tmp_path, monkeypatch):
    """The pieces deflated with runs only are exactly the bytes of the
    `RUN_LENGTH_MEMBERS` (their .npy headers included), the others at zipfile's level."""
    import zipfile

    pieces, deflated = [], lattice_file._deflated

    def spy(piece, runs, batch):
        pieces.append((len(piece), runs))
        return deflated(piece, runs, batch)

    monkeypatch.setattr(lattice_file, "_deflated", spy)
    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    _random_lattice(seed=9).save(tmp_path / "l.npz")
    with zipfile.ZipFile(tmp_path / "l.npz") as zf:
        raw = {i.filename[:-4]: i.file_size for i in zf.infolist()}
    assert lattice_file.RUN_LENGTH_MEMBERS == {"second", "facing"}
    assert sum(n for n, runs in pieces if runs) == raw["second"] + raw["facing"]
    assert sum(n for n, runs in pieces if not runs) == sum(
        raw[m] for m in ("values", "samples", "active", "held"))


def test_a_zipfile_without_its_private_sizes_deflates_the_members_itself(tmp_path,
                                                                         monkeypatch):
    """Where zipfile's member lacks the compressor, CRC and size that the pieces need,
    zipfile deflates each member itself: a valid file of the same arrays."""
    import zipfile

    class Plain:
        """A member opened for writing, with only the public file methods."""

        def __init__(self, member):
            self.member = member

        def write(self, data):
            return self.member.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.member.__exit__(*exc)

    opened = zipfile.ZipFile.open

    def plain_open(self, name, mode="r", **kwargs):
        member = opened(self, name, mode, **kwargs)
        return Plain(member) if mode == "w" else member

    monkeypatch.setattr(lattice_file, "DEFLATE_PIECE", 777)
    lattice = _random_lattice(seed=6)
    lattice.save(tmp_path / "pieces.npz")
    monkeypatch.setattr(zipfile.ZipFile, "open", plain_open)
    lattice.save(tmp_path / "whole.npz")
    monkeypatch.undo()
    assert (tmp_path / "whole.npz").read_bytes() != (tmp_path / "pieces.npz").read_bytes()
    with zipfile.ZipFile(tmp_path / "whole.npz") as zf:
        assert zf.testzip() is None
    _same(Lattice.load(tmp_path / "whole.npz"), lattice)


def test_a_durable_write_syncs_and_removes_what_killed_writes_left(tmp_path, monkeypatch):
    """`atomic_write(..., durable=True)` (a lattice's save): the file's data and then its
    folder are flushed before it returns, and the temporary files that earlier writes of
    the same path left in this machine's processes since gone are removed — not those of
    a running process, of another machine, of another path, or of another name pattern."""
    import subprocess
    import sys

    from isolume.volumes import writing

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          check=True, capture_output=True, text=True)
    dead, alive, host = int(gone.stdout), os.getpid(), writing.HOST
    path = tmp_path / "l.npz"
    left = [tmp_path / f".l.npz.{host}-{dead}.abcd_123.npz",
            tmp_path / f".l.npz.{host}-{alive}.abcd_123.npz",
            tmp_path / f".l.npz.{host}x-{dead}.abcd_123.npz",
            tmp_path / f".m.npz.{host}-{dead}.abcd_123.npz", tmp_path / ".l.npz.abcd_123.npz"]
    for file in left:
        file.write_bytes(b"partial")
    synced = []
    monkeypatch.setattr(writing, "_flush", lambda fd: synced.append(os.readlink(
        f"/proc/self/fd/{fd}")) or os.fsync(fd))
    writing.atomic_write(path, lambda tmp: Path(tmp).write_text("whole"), durable=True)
    assert path.read_text() == "whole"
    assert [file.exists() for file in left] == [False, True, True, True, True]
    assert len(synced) == 2 and Path(synced[0]).name.startswith(f".l.npz.{host}-{alive}.")
    assert synced[1] == str(tmp_path)
    synced.clear()
    writing.atomic_write(path, lambda tmp: Path(tmp).write_text("again"))  # not durable
    assert synced == [] and left[1].exists()


def test_a_durable_write_is_not_stopped_by_leftovers_it_may_not_remove(tmp_path,
                                                                        monkeypatch):
    """A leftover this process may not remove (another user's, in a shared folder with the
    sticky bit) or a folder it may not list leaves the save to go on: the cleanup is best
    effort, the write is not."""
    import subprocess
    import sys

    from isolume.volumes import writing

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          check=True, capture_output=True, text=True)
    leftover = tmp_path / f".l.npz.{writing.HOST}-{int(gone.stdout)}.abcd_123.npz"
    leftover.write_bytes(b"partial")
    path = tmp_path / "l.npz"

    def refused(*args, **kwargs):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(Path, "unlink", refused)
    writing.atomic_write(path, lambda tmp: open(tmp, "w").write("whole"), durable=True)
    assert path.read_text() == "whole" and leftover.exists()
    monkeypatch.undo()
    monkeypatch.setattr(os, "scandir", refused)
    writing.atomic_write(path, lambda tmp: open(tmp, "w").write("again"), durable=True)
    assert path.read_text() == "again"


def test_a_file_written_whole_keeps_permissions_links_and_read_only_files(tmp_path):
    """`volumes.writing.atomic_write`: a new file gets a new file's permissions (not the
    temporary file's 0600), a rewritten one keeps its own; a symbolic link is written
    through; no temporary file shows beside it; a read-only file is refused."""
    from isolume.volumes.writing import NEW_FILE_MODE, atomic_write

    def write(text):
        return lambda tmp: open(tmp, "w").write(text)

    path = tmp_path / "a.txt"
    atomic_write(path, write("one"))
    assert os.stat(path).st_mode & 0o777 == NEW_FILE_MODE
    os.chmod(path, 0o640)
    atomic_write(path, write("two"))
    assert os.stat(path).st_mode & 0o777 == 0o640 and path.read_text() == "two"
    link = tmp_path / "link.txt"
    link.symlink_to(path)
    atomic_write(link, write("three"))
    assert link.is_symlink() and path.read_text() == "three"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "link.txt"]
    if os.geteuid() != 0:  # root may write any file
        os.chmod(path, 0o440)
        with pytest.raises(WriteError, match="Permission denied; the file there is left"):
            atomic_write(path, write("four"))
        assert path.read_text() == "three"


def test_sample_refuses_points_that_are_not_xyz_rows_in_one_line():
    """`Lattice.sample` of anything but (N, 3) points (and normals, one a point) names
    what it was given and what it takes."""
    lattice = _random_lattice()
    assert lattice.sample([[0.5, 0.5, 0.5]]).shape == (1, 3)
    for points, normals, message in (
            (np.zeros((2, 2)), None, r"points of shape \(2, 2\): expected \(N, 3\)"),
            (np.zeros(3), None, r"points of shape \(3,\): expected \(N, 3\)"),
            ("abc", None, r"points str: expected an \(N, 3\) array"),
            (np.zeros((2, 3)), np.ones((3, 3)), r"normals of shape \(3, 3\): expected \(2, 3\)")):
        with pytest.raises(BakeError, match=message):
            lattice.sample(points, normals=normals)
