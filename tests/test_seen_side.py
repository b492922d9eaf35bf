"""The view's traced GI lights each texel where the eye sees the surface.

Phantoms where the light on the two sides of the displayed surface differs by far: a solid
cut open by the volume's border, so that the eye looks in through the open face and sees
the surface from its high-value side, with a shelf close below it that shades its low
side; a one-voxel wall; granular fill. Each view-GI picture is compared with
`isolume reference` (per-pixel paths started on the side the eye sees). A constant sky
and no bounces make both nearly noise-free: the sky is the only light and a texel's value
is the visible fraction of it, averaged over its paths (64 per texel, 256 per pixel: a
standard error of a few per cent per texel, far less over a picture's mean).
"""

import numpy as np
import pytest

from isolume.app.render.offscreen import render_volume
from isolume.app.render.renderer import default_camera
from isolume.app.render.settings import RenderSettings
from isolume.baking import BakeConfig
from isolume.baking.reference import render_reference
from isolume.volumes import Volume

SIZE = (64, 64)
SKY = BakeConfig(samples=64, bounces=0, env="constant:1,1,1", seed=5)


def _volume(data: np.ndarray, name: str) -> Volume:
    return Volume(data.astype(np.float32), name=name, source=name)


def _cut_open_slab(n: int = 32) -> Volume:
    """A slab filling z ≥ 16 up to the top border (open there: the eye from above sees its
    bottom face from inside, the high-value side), and a shelf at z 9–12 below it that
    hides most of the sky from the bottom face's low side."""
    z = np.arange(n)[:, None, None] * np.ones((1, n, n))
    data = ((z >= 16) | ((z >= 9) & (z <= 12))).astype(np.float32)
    return _volume(data, "cut-open slab")


def _granular(n: int = 32) -> Volume:
    """A ball of grains: random voxels inside a sphere, one in two full."""
    rng = np.random.default_rng(11)
    z, y, x = np.mgrid[:n, :n, :n] - (n - 1) / 2
    inside = x * x + y * y + z * z < (0.35 * n) ** 2
    return _volume(inside & (rng.random((n, n, n)) < 0.5), "granular")


def _thin_wall(n: int = 32) -> Volume:
    """A wall one voxel thick across the box at x = n/2."""
    data = np.zeros((n, n, n), np.float32)
    data[:, :, n // 2] = 1.0
    return _volume(data, "thin wall")


def _pictures(volume: Volume, view: tuple[float, float, float], lattice=None):
    """(picture luminance, reference luminance) over the pixels both show, linear: the
    view's traced GI under `SKY`, or `lattice`'s light where given."""
    settings = RenderSettings(size=SIZE, shading="irradiance", auto_exposure=False,
                              tonemap="clamp", albedo=SKY.albedo)
    camera = default_camera(volume, view)
    light = {"view_light": SKY} if lattice is None else {"lattice": lattice}
    frame, _ = render_volume(volume, 0.5, settings, camera=camera, workers=2, **light)
    origins, dirs = camera.primary_rays(*SIZE)
    image, _ = render_reference(volume, 0.5, origins, dirs,
                                BakeConfig(samples=256, bounces=0, env="constant:1,1,1",
                                           seed=6), workers=2)
    w, h = SIZE
    ref, mask = image.radiance.reshape(h, w, 3), image.mask.reshape(h, w)
    both = mask & frame.mask
    lum = np.array([0.2126, 0.7152, 0.0722])
    return frame.linear[both] @ lum, ref[both] @ lum


@pytest.mark.parametrize(("make", "view"), [
    (_cut_open_slab, (30.0, 60.0, 1.6)),  # from above: into the open top
    (_cut_open_slab, (30.0, -40.0, 1.6)),  # from below: the shelf's underside
    (_thin_wall, (60.0, 20.0, 1.6)),
    (_granular, (30.0, 30.0, 1.6)),
])
def test_view_gi_matches_the_reference_on_the_side_the_eye_sees(make, view):
    """Mean within 5 % of the reference and at most 0.5 % of the pixels pure black where
    the reference is lit (one pixel of the granular ball's 780 can be: the bottom of a pit
    whose opening none of a texel's 64 paths finds). Texels started from their centres
    projected onto the surface, on its low side, drew the cut-open slab at 0.25 of the
    reference from above and 0.70 from below."""
    image, ref = _pictures(make(), view)
    assert len(ref) > 500
    assert image.mean() / ref.mean() == pytest.approx(1.0, abs=0.05)
    lit = ref > 0.05 * ref.mean()
    assert (image[lit] <= 0).mean() <= 0.005


def test_each_texel_starts_from_the_nearest_point_that_reads_it():
    """`nearest_points` against a brute-force search, on small lattices whose edge texels
    are read from up to 1.5 texels away (clamped lookups) and at coarse scales."""
    from isolume.baking.lattice import LatticeGeometry, trilinear_corners
    from isolume.baking.preview import nearest_points

    rng = np.random.default_rng(2)
    for _ in range(200):
        shape = tuple(int(n) for n in rng.integers(2, 5, 3))
        geometry = LatticeGeometry(shape, (0.0, 0.0, 0.0), tuple(rng.uniform(1, 3, 3)))
        points = rng.uniform(-0.2, 1.2, (int(rng.integers(1, 12)), 3)) * geometry.hi
        texels, nearest = nearest_points(geometry, points)
        idx, _ = trilinear_corners(shape, geometry.to_texel_coords(points))
        read = (idx[..., 0] * shape[1] + idx[..., 1]) * shape[2] + idx[..., 2]
        assert np.array_equal(texels, np.unique(read))
        for texel, point in zip(texels, nearest, strict=True):
            readers = np.flatnonzero((read == texel).any(axis=1))
            gaps = np.linalg.norm(points[readers] - geometry.centres(np.array([texel])), axis=1)
            assert np.linalg.norm(points[point] - geometry.centres(np.array([texel]))) \
                == pytest.approx(gaps.min())


@pytest.mark.parametrize("threads", [1, 3])
def test_nearest_points_match_a_sort_of_every_corner_to_the_bit(threads):
    """`nearest_points` (binned, compiled, on several threads) gives what sorting every
    corner read by texel, then distance, stably, and keeping each texel's first gives —
    the first point on ties (repeated points, points on planes halfway between texel
    centres), points outside the box and not finite, lattices finer than the bins and one
    texel thick."""
    from isolume.baking.lattice import LatticeGeometry, trilinear_corners
    from isolume.baking.preview import nearest_points
    from isolume.volumes import cores

    rng = np.random.default_rng(5)
    cases = [((40, 70, 90), 30_000), ((1, 33, 17), 5_000), ((300, 200, 100), 50_000)]
    for shape, count in cases:
        geometry = LatticeGeometry(shape, (1.0, -2.0, 0.5), (31.0, 40.0, 20.0))
        points = geometry.lo + rng.uniform(-0.1, 1.1, (count, 3)) * (
            np.array(geometry.hi) - geometry.lo)
        points[: count // 10] = points[count // 10: count // 5]  # repeated points
        halfway = (np.floor(geometry.to_texel_coords(points[-500:])) + 1.0)[:, ::-1]
        points[-500:] = geometry.lo + halfway * geometry.texel_size  # equal distances
        points[1000:1003] = [[np.nan, 3.0, 4.0], [np.inf, 5.0, 1.0], [2.0, -np.inf, np.nan]]
        coords = geometry.to_texel_coords(points)
        with np.errstate(invalid="ignore"):  # NaN → int: numpy's clamps give texel 0
            idx, _ = trilinear_corners(shape, coords)
        read = ((idx[..., 0] * shape[1] + idx[..., 1]) * shape[2] + idx[..., 2]).reshape(-1)
        size = geometry.texel_size[::-1]
        gap = (((idx - coords[:, None, :]) * size) ** 2).sum(axis=2).reshape(-1) / (
            2.0 * float((size**2).sum()) + 1e-30)
        order = np.lexsort((gap, read))
        first = np.r_[True, read[order][1:] != read[order][:-1]]
        cores.use(threads)
        try:
            texels, nearest = nearest_points(geometry, points)
        finally:
            cores.use(None)
        np.testing.assert_array_equal(texels, read[order][first])
        np.testing.assert_array_equal(nearest, (order // 8)[first])
