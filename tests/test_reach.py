"""`volumes.reach.BoxReach`: which parts of a volume connect to the box's faces, and the
side probes it spares (`baking.sides`)."""

import numpy as np
import pytest
from test_sides import _ball

from isolume import volumes
from isolume.baking import BakeConfig
from isolume.baking.sides import level_surface, open_rays, probe_offset
from isolume.volumes import Volume, load
from isolume.volumes.reach import BoxReach


def _shell_and_slab(dtype) -> Volume:
    """A closed spherical shell (radii 5–7 voxels, value 200) around a cavity (0), and a
    slab (200) the box's bottom face cuts (z ≤ 3), in air (0): 32³."""
    z, y, x = np.mgrid[:32, :32, :32].astype(np.float64)
    r = np.sqrt((x - 16) ** 2 + (y - 16) ** 2 + (z - 18) ** 2)
    solid = ((r >= 5) & (r <= 7)) | (z <= 3)
    return Volume((200 * solid).astype(dtype), name="shell", source="shell")


def _at(voxels_zyx) -> np.ndarray:
    """(N, 3) world xyz of (N, 3) voxel indices z, y, x (unit spacing, origin 0)."""
    return np.asarray(voxels_zyx, np.float64)[:, ::-1]


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_a_closed_shell_and_its_cavity_cannot_see_the_box_a_cut_slab_can(dtype):
    """At the level 100, a ray on the high side of the shell (inside its wall) or on the
    low side inside its cavity meets the surface before it leaves the box — the flood
    proves both closed — while the slab's inside leaves through the bottom face and the
    air through any face. Integer samples flood on their values, float ones on 4096
    levels rounded towards "may leave"; the answers are the same."""
    volume = _shell_and_slab(dtype)
    up, down = BoxReach.of(volume, up=True), BoxReach.of(volume, up=False)
    wall, cavity, slab, air = _at([(18, 16, 22)]), _at([(18, 16, 16)]), _at([(1, 9, 9)]), \
        _at([(28, 3, 3)])
    assert not up.may_open(volume, wall, 100.0)[0]
    assert not down.may_open(volume, cavity, 100.0)[0]
    assert up.may_open(volume, slab, 100.0)[0] and down.may_open(volume, air, 100.0)[0]
    assert up.may_open(volume, wall, 0.0)[0]  # at the bottom of the range: nothing closed
    assert up.may_open(volume, np.full((1, 3), np.nan), 100.0)[0]  # nothing proven


def test_no_side_a_probe_leaves_from_is_proven_closed():
    """The flood over-connects, never under-connects: on the synthetic engine (bores,
    folds, the box's cut) and on a closed ball, at a level between samples, every point
    whose high side some of 16 probe rays leave from is one the flood says may open; and
    it proves the ball's inside closed, where no probe leaves either."""
    config = BakeConfig(env="sky:sun=6,sun_az=-150,sun_el=40", seed=3)
    closed = 0
    for volume, level in ((load("synthetic:engine:40"), 0.3019), (_ball(), 0.5)):
        scene = level_surface(volume, level)
        rng = np.random.default_rng(1)
        points = scene.vertices[rng.choice(len(scene.vertices), 800, replace=False)]
        points = points.astype(np.float64)
        _, high, _ = open_rays(scene, volume, config, np.arange(len(points)), points, level,
                               False)
        normals = volumes.normals_at(volume, points).astype(np.float64)
        inside = points - probe_offset(volume, config) * normals
        may = BoxReach.of(volume, up=True).may_open(volume, inside, level)
        assert may[high > 0].all()
        closed += int((~may).sum())
    assert closed >= 400  # the ball's 800 points, less those near nothing



def _reach_by_labels(rank: np.ndarray, levels: int, up: bool) -> np.ndarray:
    """An independent reach: for each level b, label the 26-connected parts of the voxels
    at or above b (at or below where not `up`) and keep those touching a face; a voxel's
    reach is the best b whose part touches one."""
    from scipy import ndimage

    inner = np.zeros(rank.shape, bool)
    inner[1:-1, 1:-1, 1:-1] = True
    out = np.full(rank.shape, -1)
    for b in (range(levels) if up else range(levels - 1, -1, -1)):
        labels, _ = ndimage.label(rank >= b if up else rank <= b, np.ones((3, 3, 3)))
        touching = np.unique(labels[~inner & (labels > 0)])
        out[np.isin(labels, touching) & (labels > 0)] = b
    return out


@pytest.mark.parametrize("up", [True, False])
def test_the_flood_is_the_best_level_at_which_each_voxel_connects_to_a_face(up, monkeypatch):
    """On random volumes of 8 values (smoothed a little, so that parts of all sizes form),
    the flood's level indices equal those of labelling every level's connected parts,
    however many voxels each of its runs takes off the queue."""
    from scipy import ndimage

    from isolume.volumes import reach

    rng = np.random.default_rng(5)
    for shape in ((9, 11, 13), (2, 7, 6), (9, 5, 2), (12, 12, 12)):
        noise = ndimage.uniform_filter(rng.random(shape), 2)
        data = np.digitize(noise, np.quantile(noise, np.linspace(0, 1, 9)[1:-1]))
        volume = Volume(data.astype(np.uint8), name="noise", source="noise")
        expected = _reach_by_labels(data, 8, up)
        for pops in (1, 7, 1 << 22):
            monkeypatch.setattr(reach, "FLOOD_POPS", pops)
            got = BoxReach.of(volume, up)
            np.testing.assert_array_equal(got.reach, expected, f"{shape}, {pops} a run")


def test_a_stopped_flood_stops_between_its_runs(monkeypatch):
    """A flood whose `stop` is set raises `FloodStopped` after its first run; the plan's
    flood ahead, left before it is asked for, stops its pool thread the same way."""
    import threading

    from isolume.volumes import reach
    from isolume.volumes.reach import FloodStopped

    stop = threading.Event()
    stop.set()
    monkeypatch.setattr(reach, "FLOOD_POPS", 100)
    with pytest.raises(FloodStopped):
        BoxReach.of(_shell_and_slab(np.uint8), True, stop)
    assert BoxReach.of(_shell_and_slab(np.uint8), True, threading.Event()).reach.shape == (32,) * 3


@pytest.mark.parametrize("threads", [1, 3])
def test_the_flood_begun_ahead_is_the_flood_and_leaving_it_early_stops_it(threads,
                                                                           monkeypatch):
    """`BoxReachAhead` gives the flood towards the side other than the normals' (begun on
    a pool thread with several threads, made when asked for with one); left before it is
    asked for, its pool thread's flood stops at its next run instead of going on for
    seconds."""
    from isolume.baking.sides import BoxReachAhead
    from isolume.volumes import cores, reach

    volume = _shell_and_slab(np.uint8)
    cores.use(threads)
    try:
        for flip in (False, True):
            config = BakeConfig(flip_normals=flip)
            with BoxReachAhead(volume, config) as ahead:
                ahead.begin()
                got = ahead.get()
            want = BoxReach.of(volume, up=not flip)
            assert got.up == want.up
            np.testing.assert_array_equal(got.reach, want.reach)
        big = Volume(np.tile(volume.data, (3, 3, 3)), name="shells", source="shells")
        monkeypatch.setattr(reach, "FLOOD_POPS", 1)  # 96³ voxels one at a time: seconds
        with BoxReachAhead(big, BakeConfig()) as ahead:
            ahead.begin()
        if threads > 1:
            assert ahead._ahead is not None
            if not ahead._ahead.future.cancelled():
                with pytest.raises(reach.FloodStopped):
                    ahead._ahead.future.result(timeout=60)
    finally:
        cores.use(None)
