"""Noise-driven sampling (`baking.adaptive`): the ladder, the judgement, the same bits for
any workers and across an interruption, and the noise it leaves."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from isolume.app.options import ADAPTIVE_MIN_SAMPLES
from isolume.baking import BakeConfig, Lattice, bake
from isolume.baking.adaptive import (
    ROUND_KEY,
    RoundState,
    ladder,
    neighbour_variance,
    path_spread,
    path_variance,
    still_going,
)
from isolume.baking.config import (
    DEFAULT_SAMPLES,
    DEFAULT_TEXEL_ERROR,
    NODE_PATHS,
    TEXEL_PLAN_SAMPLES,
    TEXEL_SAMPLES,
)
from isolume.baking.lattice import TRAPPED_PATHS, standard_error
from isolume.volumes.synthetic import make

CONFIG = BakeConfig(samples=8, bounces=1, env="sky:sun=3", target_error=0.1, max_samples=128,
                    max_move=0.5)
"""A small adaptive bake: a sun's bounces make the noise differ from texel to texel."""
NONE = np.zeros(5, bool)
"""No texel without light."""


def _same_bits(a: Lattice, b: Lattice) -> None:
    for name in ("values", "second", "samples", "facing"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_the_ladder_doubles_up_to_the_most():
    assert ladder(16, 16) == [16]
    assert ladder(16, 100) == [16, 32, 64, 100]
    assert ladder(8, 64) == [8, 16, 32, 64]


def test_a_round_state_survives_its_record():
    going = np.random.default_rng(1).random(1001) < 0.3
    state = RoundState(0.1, 16, 512, group=3, rung=2, brightness=0.7, spread=0.4, going=going)
    back = RoundState.resumed(state.record(), 0.1, 16, 512)
    assert (back.group, back.rung, back.brightness, back.spread) == (3, 2, 0.7, 0.4)
    np.testing.assert_array_equal(back.going, going)
    assert RoundState.resumed(state.record(), 0.05, 16, 512).group == 0  # another target
    finished = dataclasses.replace(state, finished=True).record()
    assert RoundState.resumed(finished, 0.1, 16, 512).finished  # done: nothing to do
    assert not RoundState.resumed(finished, 0.05, 16, 512).finished  # a lower target


def test_paths_follow_the_spread_until_the_group_meets_the_target():
    """n* = spread · mean spread / (target · brightness)²: a texel goes on while doubling
    keeps it within √2 of n*; the texels so sampled leave the group's root-mean-square
    standard error at the target within the ladder's rounding (2^¼)."""
    spread = np.array([0.0, 0.5, 1.0, 2.0, 4.0])
    brightness, target = 2.0, 0.1
    need = spread * spread.mean() / (target * brightness) ** 2
    for samples in (16, 64, 256, 1024):
        n = np.full(5, samples)
        np.testing.assert_array_equal(
            still_going(spread, n, brightness, spread.mean(), target, 4096, NONE, 0),
            n * np.sqrt(2) < need)
    n = np.full(5, 16)
    while (go := still_going(spread, n, brightness, spread.mean(), target, 4096, NONE,
                             0)).any():
        n = np.where(go, 2 * n, n)
    used = spread > 0
    rms = np.sqrt(np.mean(np.where(used, spread ** 2 / n, 0.0)))
    assert rms <= 2 ** 0.25 * target * brightness
    assert (np.diff(n[used]) >= 0).all()  # more spread, more paths
    assert not still_going(spread, np.full(5, 64), brightness, spread.mean(), target, 64,
                           NONE, 0).any()


def test_a_texel_without_light_goes_on_until_it_can_be_called_trapped():
    dark = np.array([True, False])
    spread = np.zeros(2)
    going = [still_going(spread, np.full(2, n), 1.0, 1.0, 0.1, 4096, dark, 64)
             for n in (16, 32, 64)]
    assert [g.tolist() for g in going] == [[True, False], [True, False], [False, False]]
    assert not still_going(spread, np.full(2, 16), 1.0, 1.0, 0.1, 4096, dark, 0).any()


def test_a_texel_whose_paths_agreed_by_chance_is_judged_by_its_neighbours():
    """A texel with no spread among noisy neighbours takes their median spread; among
    quiet ones it keeps its own."""
    shape = (5, 5, 5)
    ids = np.arange(125)
    variance = np.full(125, 4.0)
    centre = np.ravel_multi_index((2, 2, 2), shape)
    variance[centre] = 0.0
    assert neighbour_variance(ids, variance, shape, np.array([centre]))[0] == 4.0
    quiet = np.zeros(125)
    assert neighbour_variance(ids, quiet, shape, np.array([centre]))[0] == 0.0
    lonely = neighbour_variance(np.array([centre]), np.zeros(1), shape, np.array([0]))
    assert lonely[0] == 0.0  # no neighbour in the group
    luminance = np.ones(125)
    second = 1 + variance * 15 / 16  # 16 samples: unbiased variance 4, 0 at the centre
    samples = np.full(125, 16)
    np.testing.assert_allclose(path_variance(luminance, second, samples), variance)
    spread = path_spread(luminance, second, samples, ids, shape, np.array([centre]))
    assert spread[0] == 2.0


def test_an_adaptive_bake_is_the_same_bits_on_any_number_of_workers():
    vol = make("shells", 24)
    one = bake(vol, CONFIG, workers=1)
    two = bake(vol, CONFIG, workers=2)
    _same_bits(one, two)
    counts = one.samples[one.samples > 0]
    assert counts.min() == 8 and counts.max() > 16  # it did adapt
    dark = (one.samples > 0) & ~one.values.any(axis=-1)
    assert dark.any() and (one.samples[dark] >= TRAPPED_PATHS).all()  # tellable as trapped
    assert one.meta[ROUND_KEY]["finished"]


def test_an_interrupted_adaptive_bake_resumes_to_the_same_bits(tmp_path, monkeypatch):
    """Cut in a later round of a group, the file keeps the round's decisions; the resumed
    bake makes the same ones and ends with the uninterrupted lattice to the bit."""
    from isolume.baking.backend import ThreadBackend

    vol = make("shells", 24)
    whole = bake(vol, CONFIG, workers=2)
    original = ThreadBackend._submit_level
    calls = {"n": 0}

    def interrupting(self, *args):
        calls["n"] += 1
        if calls["n"] == 5:  # past the first round of the first group
            raise KeyboardInterrupt
        return original(self, *args)

    monkeypatch.setattr(ThreadBackend, "_submit_level", interrupting)
    path = tmp_path / "cut.npz"
    with pytest.raises(KeyboardInterrupt):
        bake(vol, CONFIG, out=path, workers=2)
    cut = Lattice.load(path, vol)
    record = cut.meta[ROUND_KEY]
    assert not record["finished"] and record["rung"] > 0
    assert 0 < (cut.samples > 0).sum() < (whole.samples > 0).sum()
    monkeypatch.setattr(ThreadBackend, "_submit_level", original)
    done = bake(vol, CONFIG, out=path, workers=1)
    _same_bits(done, whole)


def test_a_lower_target_adds_paths_to_a_finished_file(tmp_path):
    vol = make("shells", 24)
    path = tmp_path / "l.npz"
    first = bake(vol, dataclasses.replace(CONFIG, target_error=0.2), out=path, workers=2)
    again = bake(vol, dataclasses.replace(CONFIG, target_error=0.2), out=path, workers=2)
    _same_bits(again, first)  # finished: the same bake adds nothing
    second = bake(vol, CONFIG, out=path, workers=2)
    computed = first.samples > 0
    assert (second.samples[computed] >= first.samples[computed]).all()
    assert second.samples.sum() > first.samples.sum()
    assert second.meta["stats"]["paths"] == second.samples.sum()


def test_the_noise_left_follows_the_target_and_paths_follow_the_spread():
    """Over the lit texels: the root-mean-square standard error over the mean brightness
    is about the target (the ladder's rounding, the estimates' own noise and the levels'
    different light: within 1.5×) and halves with the target (0.35–0.7×: where the
    minimum binds, less); texels whose paths spread more got more paths (rank correlation
    > 0.5)."""
    from isolume.baking.lattice import LUMINANCE

    vol = make("shells", 24)
    noise, lattices = [], []
    for target in (0.1, 0.05):
        lattice = bake(vol, dataclasses.replace(CONFIG, target_error=target,
                                                max_samples=4096), workers=2)
        lit = (lattice.samples > 0) & lattice.values.any(axis=-1)
        error = standard_error(lattice.values, lattice.samples, lattice.second,
                               "irradiance")[lit].astype(np.float64)
        luminance = lattice.values[lit][:, :3] @ LUMINANCE
        noise.append(float(np.sqrt(np.mean(error ** 2)) / np.mean(luminance)))
        lattices.append((lattice, lit, error))
    assert noise[0] < 1.5 * 0.1 and noise[1] < 1.5 * 0.05
    assert 0.35 < noise[1] / noise[0] < 0.7
    lattice, lit, error = lattices[1]
    samples = lattice.samples[lit].astype(np.float64)
    spread = error * np.sqrt(samples)
    rank = np.corrcoef(np.argsort(np.argsort(spread)), np.argsort(np.argsort(samples)))[0, 1]
    assert rank > 0.5


@pytest.mark.parametrize("config, planned", [
    (BakeConfig(samples=16), 16),
    (BakeConfig(samples=TEXEL_SAMPLES, texel_error=0.02), TEXEL_PLAN_SAMPLES),
    (BakeConfig(samples=8, texel_error=0.05), TEXEL_PLAN_SAMPLES),
    (BakeConfig(samples=64, texel_error=0.02), NODE_PATHS * 64),
    (BakeConfig(samples=16, target_error=0.05), 400),
])
def test_the_level_plan_is_sized_for_the_paths_the_picture_rests_on(config, planned):
    """A uniform bake's plan: its paths; a texel bake's: its nodes' paths, at least
    `TEXEL_PLAN_SAMPLES` (a filled texel mixes several nodes); a noise target's: 1 / E²."""
    assert config.plan_samples == planned


@pytest.mark.parametrize("words, expected", [
    ([], (TEXEL_SAMPLES, None, DEFAULT_TEXEL_ERROR)),
    (["--mode", "sh"], (DEFAULT_SAMPLES, None, None)),
    (["--samples", "100"], (100, None, None)),
    (["--samples", "64", "--mode", "sh"], (64, None, None)),
    (["--texel-error", "0.05"], (TEXEL_SAMPLES, None, 0.05)),
    (["--texel-error", "0.05", "--samples", "32"], (32, None, 0.05)),
    (["--target-error", "0.05"], (ADAPTIVE_MIN_SAMPLES, 0.05, None)),
    (["--target-error", "0.05", "--samples", "32"], (32, 0.05, None)),
])
def test_the_command_line_bakes_exact_samples_only_when_it_names_them(words, expected):
    """``bake`` alone (irradiance): a texel error at its paths; ``--samples N`` alone:
    exactly N paths a texel, every texel traced; an SH bake alone: exactly the default;
    ``--texel-error`` / ``--target-error``: their own defaults unless ``--samples`` says —
    as the command parses them into its `BakeConfig`."""
    from isolume.app.cli import build_parser
    from isolume.app.options import bake_config

    args = build_parser().parse_args(["bake", "v.raw", "--out", "l.npz", *words])
    config = bake_config(args)
    assert (config.samples, config.target_error, config.texel_error) == expected


def test_the_bake_command_says_what_a_target_traced(tmp_path, capsys):
    from isolume.app.cli import main

    out = tmp_path / "l.npz"
    assert main(["bake", "synthetic:sphere:16", "--target-error", "0.2", "--bounces", "1",
                 "--out", str(out), "--workers", "2"]) == 0
    said = capsys.readouterr().out
    lattice = Lattice.load(out)
    paths = int(lattice.samples.sum())
    assert f"noise target 0.2: {paths:,} paths" in said
    assert lattice.config.target_error == 0.2 and lattice.samples.max() >= 16
