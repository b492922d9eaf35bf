"""The picture-error measure of ``isolume bench lazy`` (`app.bench.view.PixelTruth`), the
data folder of the view benchmarks (`app.bench.view.default_volume`) and ``bench bake``'s
replay."""

import json

import numpy as np
import pytest

from isolume import volumes
from isolume.baking.config import BakeConfig
from isolume.baking.lattice import Lattice, LatticeGeometry

pytest.importorskip("moderngl")


def test_picture_error_is_zero_for_the_exact_lattice_and_sees_a_wrong_one():
    """Unoccluded convex sphere under a constant sky: path tracing gives albedo·L at
    every pixel with zero variance, and a lattice holding πL everywhere shows exactly
    that; one 10 % too bright on every texel is 10 % off everywhere — hidden behind exact
    previews while they rest on more paths, and seen again in the hand-over figure, the
    picture from the texels' own samples alone (`_hand_over_figures`)."""
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
    # exact previews on more paths than the texels' own samples, 10 % too bright: shown,
    # the picture is exact; from the own samples alone (a saved lattice), 10 % off
    from isolume.app.bench.view import _hand_over_figures

    lat.samples[...] = 4
    lat.preview = np.full_like(lat.values, np.pi)
    lat.preview_paths = np.full(lat.samples.shape, 16, np.uint16)
    assert truth.error(lat) < 1e-5
    figures = {}
    _hand_over_figures(figures, lat, truth, [(1.0, 0.3, 1.0), (2.0, truth.error(lat), 1.0)])
    assert figures["own_picture_error"] == pytest.approx(0.1, rel=1e-4)
    assert figures["own_picture_rmse"] == pytest.approx(0.1, rel=1e-4)  # uniform: the same
    assert figures["least_picture_error"] < 1e-5
    assert lat.preview is not None  # the lattice itself keeps its previews


def test_the_data_folder_comes_from_the_option_the_variable_or_the_current_folder(
        tmp_path, monkeypatch):
    """--data, else $ISOLUME_DATA, else ../shared/data from the current folder; a named
    folder without the engine scan is a one-line error, the unnamed default falls back to
    the synthetic engine."""
    from isolume.app.bench.view import DATA_ENV, DEFAULT_DATA, ENGINE, default_volume
    from isolume.app.options import CLIError

    data = tmp_path / "shared" / "data"
    (data / ENGINE).parent.mkdir(parents=True)
    (data / ENGINE).write_bytes(b"")
    clone, elsewhere = tmp_path / "clone", tmp_path / "a" / "b"
    clone.mkdir()
    elsewhere.mkdir(parents=True)
    monkeypatch.delenv(DATA_ENV, raising=False)
    monkeypatch.chdir(elsewhere)
    assert default_volume(None) == "synthetic:engine"
    assert default_volume(str(data)) == str(data / ENGINE)
    monkeypatch.setenv(DATA_ENV, str(data))
    assert default_volume(None) == str(data / ENGINE)
    with pytest.raises(CLIError, match=r"^--data .*: no volumes/engine") as info:
        default_volume(str(clone))
    assert "\n" not in str(info.value)
    monkeypatch.setenv(DATA_ENV, str(clone))
    with pytest.raises(CLIError, match=rf"^\${DATA_ENV} "):
        default_volume(None)
    monkeypatch.delenv(DATA_ENV)
    monkeypatch.chdir(clone)
    assert default_volume(None) == str(DEFAULT_DATA / ENGINE)


def test_bench_bake_replays_every_ray_it_timed(tmp_path, capsys):
    """`isolume bench bake` bakes twice and replays the second bake's rays on bare Embree,
    level by level, once none of a level's chunks still runs (the steps of a level are
    traced one beside the next): it replays as many rays as the timed bake traced, and
    prints the rates."""
    from isolume.app.cli import main

    out = tmp_path / "bake.json"
    assert main(["bench", "bake", "synthetic:sphere:24", "--samples", "8", "--json",
                 str(out)]) == 0
    assert "bare embree" in capsys.readouterr().out
    figures = json.loads(out.read_text())
    assert figures["rays"] > 0
