"""The picture-error measure of ``isolume bench lazy`` (`app.bench.view.PixelTruth`)."""

import numpy as np
import pytest

from isolume import volumes
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import Lattice, LatticeGeometry

pytest.importorskip("moderngl")


def test_picture_error_is_zero_for_the_exact_lattice_and_sees_a_wrong_one():
    """Unoccluded convex sphere under a constant sky: path tracing gives albedo·L at
    every pixel with zero variance, and a lattice holding πL everywhere shows exactly
    that; one 10 % too bright on every texel is 10 % off everywhere."""
    from isolume.app.bench.view import pixel_truth
    from isolume.app.render.renderer import default_camera

    vol = volumes.load("synthetic:sphere:24")
    config = BakeConfig(env="constant:1,1,1", bounces=1, albedo=(0.5, 0.5, 0.5))
    camera = default_camera(vol)
    size = (48, 48)
    pixels = np.arange(size[0] * size[1])
    truth = pixel_truth(vol, config, 0.5, camera, size, pixels, 8, workers=2)
    assert len(truth.points) > 200  # the sphere fills part of the view
    np.testing.assert_allclose(truth.luminance, 0.5, rtol=1e-6)
    assert truth.own_noise() < 1e-6
    geometry = LatticeGeometry.for_volume(vol, 1.0)
    lat = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    lat.values[...] = np.pi
    lat.samples[...] = 1
    assert truth.error(lat) < 1e-5
    lat.values[...] = 1.1 * np.pi
    assert truth.error(lat) == pytest.approx(0.1, rel=1e-4)
    lat.samples[...] = 0  # nothing shown: the picture is black, 100 % off
    assert truth.error(lat) == pytest.approx(1.0)
