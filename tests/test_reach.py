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

