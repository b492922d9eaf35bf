"""volumes/orientation.py: samples reordered onto world axes keep their world positions;
``--up`` turns a volume so that the named axis points up."""

import itertools

import numpy as np
import pytest

from isolume import volumes
from isolume.volumes.core import Volume, VolumeError
from isolume.volumes.orientation import nearest_axes, place, turn_up, up_rotation


def _world_samples(data, spacing, origin, directions):
    """(N, 3) world positions and (N,) values of every sample, sorted by position."""
    k, j, i = np.indices(data.shape)
    index = np.stack([i, j, k], -1).reshape(-1, 3) * np.asarray(spacing)
    points = np.asarray(origin) + index @ np.asarray(directions).T
    order = np.lexsort(np.round(points, 6).T)
    return points[order], data.reshape(-1)[order]


@pytest.mark.parametrize("perm", list(itertools.permutations(range(3))))
def test_every_signed_permutation_keeps_each_sample_in_place(perm):
    data = np.random.default_rng(1).random((4, 5, 6)).astype(np.float32)
    spacing, origin = (1.0, 2.0, 3.0), (10.0, -20.0, 30.0)
    for signs in itertools.product((1, -1), repeat=3):
        d = np.zeros((3, 3))
        for a in range(3):
            d[perm[a], a] = signs[a]
        placed = place(data, spacing, origin, d)
        assert placed.residual_deg == 0
        want = _world_samples(data, spacing, origin, d)
        got = _world_samples(placed.data, placed.spacing, placed.origin, np.eye(3))
        np.testing.assert_allclose(got[0], want[0], atol=1e-9)
        np.testing.assert_array_equal(got[1], want[1])


def test_oblique_axes_go_to_the_nearest_world_axes():
    angle = np.radians(20)
    c, s = np.cos(angle), np.sin(angle)
    tilted = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])  # 20° about z
    assert nearest_axes(tilted) == ((0, 1, 2), (1, 1, 1))
    swapped = tilted @ np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
    assert nearest_axes(swapped) == ((1, 0, 2), (1, 1, -1))
    placed = place(np.zeros((2, 3, 4), np.float32), (1, 1, 1), (0, 0, 0), tilted)
    assert placed.residual_deg == pytest.approx(20)
    with pytest.raises(VolumeError, match="not three independent"):
        place(np.zeros((2, 2, 2)), (1, 1, 1), (0, 0, 0), np.ones((3, 3)))


@pytest.mark.parametrize("axis", volumes.UP_AXES)
def test_up_turns_the_named_axis_up_without_mirroring(axis):
    r = up_rotation(axis)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)  # a turn, never a mirror image
    sign = -1.0 if axis.startswith("-") else 1.0
    named = sign * np.eye(3)["xyz".index(axis[-1])]
    np.testing.assert_allclose(r @ named, (0, 0, 1), atol=1e-12)
    # a volume whose values grow along the named axis grows along world z after the turn
    k, j, i = np.indices((5, 6, 7), dtype=np.float32)
    ramp = sign * {"x": i, "y": j, "z": k}[axis[-1]]
    turned = turn_up(Volume(ramp, spacing=(1.0, 2.0, 3.0)), axis)
    if axis != "z":
        assert turned.placement == f"turned so that its {axis} axis points up"
    diff = np.diff(turned.data, axis=0)
    assert (diff > 0).all()
    assert np.allclose(np.diff(turned.data, axis=1), 0) and np.allclose(
        np.diff(turned.data, axis=2), 0)


def test_up_keeps_the_side_that_faces_the_default_camera_for_minus_z():
    """−z turns about y: what faced −y (the default camera) still does."""
    np.testing.assert_allclose(up_rotation("-z") @ (0, -1, 0), (0, -1, 0))


def test_bad_up_axis_is_one_line():
    with pytest.raises(VolumeError, match="--up 'w': expected one of x, y, z, -x, -y, -z"):
        up_rotation("w")
