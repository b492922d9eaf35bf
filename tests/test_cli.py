"""The command line: outputs, and one-line errors with exit status 2 for bad input."""

import dataclasses
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from isolume import volumes
from isolume.app.cli import main
from isolume.app.render.images import read_exr


def _run(capsys, *argv):
    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def test_info_lists_range_and_suggestions(capsys):
    status, out, _ = _run(capsys, "info", "synthetic:engine:48")
    assert status == 0
    assert "48 x 30 x 25" in out and "suggested isovalues: 0.3, 0.8" in out


def test_info_of_a_lattice_file_says_what_it_holds(tmp_path, capsys):
    """`info` of a lattice file describes the lattice — its volume, light, paths and
    whether its bake has finished — where a volume's reader named its arrays."""
    from isolume.baking import Lattice

    path = tmp_path / "l.npz"
    assert _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2", "--bounces", "0",
                "--light", "dir:0,0,1:1,1,1", "--out", str(path))[0] == 0
    status, out, err = _run(capsys, "info", str(path))
    assert status == 0, err
    assert out.startswith("l.npz: irradiance lattice\ntexels     16 × 16 × 16")
    assert "volume     'sphere' of shape [16, 16, 16]" in out
    assert "lighting   sky:sun=6,sun_az=-150,sun_el=40 + dir:0,0,1:1,1,1" in out
    assert "--samples 2 --bounces 0" in out and "finished   yes" in out
    lattice = Lattice.load(path)
    computed = np.flatnonzero(lattice.samples.reshape(-1))[:7]
    lattice.samples.reshape(-1)[computed] = 0  # as a bake stopped before them leaves them
    lattice.save(path)
    active = int(np.count_nonzero(lattice.active))
    status, out, _ = _run(capsys, "info", str(path))
    assert status == 0 and f"finished   no: 7 of {active:,} active texels have no paths" in out


def test_an_unknown_option_is_refused_by_its_command_naming_the_one_meant(capsys):
    """A misspelled option is refused with the command's usage, not the top level's, and
    the option spelled alike is named."""
    for argv, message in (
            (["render", "synthetic:sphere:16", "--isovalue", "100"],
             "isolume render: error: unrecognized arguments: --isovalue 100 (did you mean "
             "--iso?)"),
            (["bake", "synthetic:sphere:16", "--out", "x.npz", "--sampls", "3", "--bouncs=2"],
             "(did you mean --samples, --bounces?)"),
            (["render", "synthetic:sphere:16", "extra"],
             "isolume render: error: unrecognized arguments: extra\n")):
        with pytest.raises(SystemExit) as exited:
            main(argv)
        err = capsys.readouterr().err
        assert exited.value.code == 2 and message in err, err
        assert err.startswith("usage: isolume " + argv[0])


def test_texels_without_light_show_the_lattices_own_sky_tinted(tmp_path, capsys):
    """Where no texel has light yet, the lattice modes shade the surface under the
    hemisphere of the lattice's own environment, tinted (`UNBAKED_TINT`), with half the
    key light: under a constant white sky a sphere's baked radiance is albedo · 1
    everywhere, and its unbaked half's the tint times that, a little more on the key
    light's side (the local modes' dim ambient stood in before, a third of it)."""
    from isolume.baking import Lattice

    path, exr = tmp_path / "l.npz", tmp_path / "half.exr"
    assert _run(capsys, "bake", "synthetic:sphere:24", "--env", "constant:1,1,1",
                "--bounces", "0", "--samples", "4", "--out", str(path))[0] == 0
    lattice = Lattice.load(path)
    half = np.indices(lattice.samples.shape)[2] >= lattice.samples.shape[2] // 2
    lattice.samples[half] = 0
    lattice.save(path)
    status, _, err = _run(capsys, "render", "synthetic:sphere:24", "--lattice", str(path),
                          "--no-auto-exposure", "--exposure", "1", "--size", "64x64",
                          "--view", "0,0", "--out", str(exr))
    assert status == 0, err
    rgb = read_exr(exr)["RGB"]
    surface = rgb.max(axis=-1) > 0
    left, right = surface.copy(), surface.copy()
    left[:, 24:], right[:, :40] = False, False  # the baked half, the unbaked one (x: right)
    baked, unbaked = np.median(rgb[left], axis=0), np.median(rgb[right], axis=0)
    np.testing.assert_allclose(baked, 0.8, rtol=0.02)
    tint = np.array([0.8, 0.85, 1.0])  # and half the key light, which lights one side more
    assert np.all(unbaked / baked >= 0.98 * tint) and np.all(unbaked / baked <= 1.2 * tint)


def test_a_bakes_paths_a_texel_are_those_its_lattice_holds():
    """The bake's summary counts the paths traced into the lattice — its samples less the
    samples a filled texel is given without a path — so a bake interrupted and resumed
    says what one run says; the paths its runs traced (an interruption loses some) are
    said beside them."""
    from types import SimpleNamespace

    from isolume.app.commands import _held_paths
    from isolume.baking.config import BakeConfig

    samples = np.array([[32, 64, 32], [0, 32, 40]], np.uint32)
    config = BakeConfig(samples=32, texel_error=0.02)
    lattice = SimpleNamespace(samples=samples, config=config, meta={"filled": {"filled": 2}})
    assert _held_paths(lattice) == 200 - 2 * 32
    assert _held_paths(SimpleNamespace(samples=samples, config=config, meta={})) == 200


def test_render_png_and_exr(tmp_path, capsys):
    png, exr = tmp_path / "a.png", tmp_path / "a.exr"
    for out in (png, exr):
        status, text, err = _run(
            capsys, "render", "synthetic:sphere:32", "--size", "40x30", "--gl", "osmesa",
            "--out", str(out),
        )
        assert status == 0, err
        assert f"wrote {out}" in text
    rgb = read_exr(exr)["RGB"]
    assert rgb.shape == (30, 40, 3) and rgb.dtype == np.float32
    assert rgb.max() > 0.1 and np.isfinite(rgb).all()


def test_render_default_volume_and_iso(tmp_path, capsys):
    status, text, err = _run(capsys, "render", "--size", "32x32", "--gl", "osmesa",
                             "--out", str(tmp_path / "d.png"))
    assert status == 0, err
    assert "engine at iso 0.3" in text


def _raw(tmp_path):
    """A 16³ uint8 raw file whose name gives no dims."""
    path = tmp_path / "plain.raw"
    np.zeros(16 ** 3, np.uint8).tofile(path)
    return str(path)


def _file(tmp_path):
    """A file where an output's folder should be."""
    path = tmp_path / "notes.txt"
    path.write_text("notes\n")
    return path


def _black_exr(tmp_path):
    """A 2:1 map whose every pixel is 0."""
    from isolume.app.render.images import write_exr

    path = tmp_path / "black.exr"
    write_exr(path, np.zeros((8, 16, 3), np.float32))
    return str(path)


def _npy(tmp_path, name, data):
    path = tmp_path / name
    np.save(path, data)
    return str(path)


@pytest.mark.parametrize(
    ("make_args", "expected"),
    [
        (lambda t: ["render", "synthetic:sphere:16", "--iso", "5", "--out", str(t / "x.png")],
         "isovalue 5 is outside the data range"),
        (lambda t: ["render", "--out", str(t / "missing" / "x.png")], "does not exist"),
        (lambda t: ["render", "--out", str(t / "x.jpg")], "must end in .png or .exr"),
        (lambda t: ["render", "--size", "10", "--out", str(t / "x.png")], "expected WxH"),
        (lambda t: ["render", "--view", "1,2,3,4", "--out", str(t / "x.png")], "AZ,EL"),
        (lambda t: ["render", "--albedo", "2", "--out", str(t / "x.png")], "[0, 1]"),
        (lambda t: ["render", "--shading", "toon", "--out", str(t / "x.png")], "toon"),
        (lambda t: ["info", str(t / "nothing.raw")], "nothing.raw"),
        (lambda t: ["info", _npy(t, "flat.npy", np.zeros((1, 3, 3)))], "smaller than 2×2×2"),
        (lambda t: ["info", _npy(t, "nan.npy", np.full((3, 3, 3), np.nan))], "NaN"),
        (lambda t: ["render", _npy(t, "const.npy", np.ones((3, 3, 3))), "--out",
                    str(t / "x.png")], "none can be suggested"),
        (lambda t: ["info", "synthetic:cube"], "unknown synthetic volume"),
        (lambda t: ["bake", "synthetic:sphere:16", "--max-levels", "1", "--out",
                    str(t / "l.npz")], "--max-levels 1: expected 2 to 1024 levels"),
        (lambda t: ["view", "--bake-max-levels", "0"], "--bake-max-levels 0"),
        (lambda t: ["render", "--exposure", "inf", "--out", str(t / "x.png")],
         "--exposure inf: expected a positive finite number"),
        (lambda t: ["render", "--exposure", "nan", "--out", str(t / "x.png")],
         "--exposure nan: expected a positive finite number"),
        (lambda t: ["bake", "synthetic:sphere:16", "--max-samples", "0", "--out",
                    str(t / "l.npz")], "--max-samples 0: expected at least 1"),
        (lambda t: ["bake", "synthetic:sphere:16", "--samples", "16", "--target-error",
                    "0.1", "--max-samples", "8", "--out", str(t / "l.npz")],
         "--max-samples 8 is below --samples 16"),
        (lambda t: ["info", _raw(t), "--dims", "16.7,16,16"],
         "--dims '16.7,16,16': expected X,Y,Z, three whole numbers"),
        (lambda t: ["info", _raw(t), "--dims", "0,16,16"], "whole numbers of voxels ≥ 1"),
        (lambda t: ["bake", "synthetic:sphere:16", "--out", str(_file(t) / "l.npz")],
         "notes.txt is not a directory"),
        (lambda t: ["render", "--out", str(_file(t) / "x.png")], "notes.txt is not a directory"),
        (lambda t: ["render", "synthetic:sphere:16", "--env", _black_exr(t), "--out",
                    str(t / "x.png")], "nothing lights the scene: --env"),
    ],
)
def test_bad_input_gives_one_line_and_status_2(tmp_path, capsys, make_args, expected):
    status, _, err = _run(capsys, *make_args(tmp_path))
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("isolume: error:"), err
    assert expected in lines[0]


def test_unwritable_directory(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    import os

    if os.access(locked, os.W_OK):  # running as root: permissions are not enforced
        pytest.skip("directory permissions are not enforced for this user")
    status, _, err = _run(capsys, "render", "--out", str(locked / "x.png"))
    assert status == 2 and "not writable" in err


def test_a_folder_that_refuses_new_files_is_found_before_the_work(tmp_path, capsys,
                                                                   monkeypatch):
    """A folder that takes no new file — a read-only mount, or one that refuses a root
    user, whose permission bits say nothing — is found by making a file there before any
    work; a folder for a command's outputs that cannot be made says why in one line."""
    import errno
    import tempfile

    made = tempfile.TemporaryFile

    def read_only_here(*args, dir=None, **kwargs):
        if dir is not None and Path(dir) == tmp_path:
            raise OSError(errno.EROFS, "Read-only file system")
        return made(*args, dir=dir, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(tempfile, "TemporaryFile", read_only_here)
        for command in (["render", "synthetic:sphere:16", "--out", str(tmp_path / "x.png")],
                        ["bake", "synthetic:sphere:16", "--out", str(tmp_path / "x.npz")]):
            status, _, err = _run(capsys, *command)
            assert status == 2 and err.count("\n") == 1, err
            assert f"directory {tmp_path} is not writable (Read-only file system)" in err
    blocker = tmp_path / "a file"
    blocker.write_text("")
    status, _, err = _run(capsys, "chart", "synthetic:sphere:16", "--out",
                          str(blocker / "charts"))
    assert status == 2 and err.count("\n") == 1, err
    assert "cannot make the folder (Not a directory)" in err


def test_a_black_environment_is_light_enough_beside_a_light(tmp_path):
    """A map that sends no light is refused as the scene's only light, not beside one."""
    from isolume.app.options import parse_lighting

    lighting = parse_lighting(_black_exr(tmp_path), ["dir:0,0,1:1,1,1"])
    assert len(lighting.lights) == 1 and not lighting.environment.mean_radiance.any()


def test_an_unwritable_timeline_is_refused_before_the_command_runs(tmp_path, capsys):
    for timeline, expected in ((_file(tmp_path) / "t.json", "notes.txt is not a directory"),
                               (tmp_path / "gone" / "t.json", "does not exist")):
        status = main(["render", "synthetic:sphere:16", "--timeline", str(timeline), "--out",
                       str(tmp_path / "x.png")])
        err = capsys.readouterr().err
        assert status == 2 and err.startswith("isolume: error: ") and err.count("\n") == 1, err
        assert expected in err and not (tmp_path / "x.png").exists()


def test_a_picture_larger_than_the_memory_available_is_refused(tmp_path, capsys,
                                                               monkeypatch):
    """The estimate (`PIXEL_BYTES`) follows the light: 4096x4096 needs 1.85 GB even
    shaded locally; 1024x1024 fits shaded locally (0.115 GB), not traced (0.535 GB)."""
    from isolume.app import options
    from isolume.volumes.io import common

    monkeypatch.setattr(common, "available_memory", lambda: 500_000_000)
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--size", "4096x4096",
                          "--out", str(tmp_path / "x.png"))
    assert status == 2 and err == ("isolume: error: --size 4096x4096: the picture needs "
                                   "about 1.85 GB of memory (110 bytes a pixel at the "
                                   "least), more than the 0.5 GB available; expected a "
                                   "smaller size\n")
    assert options.parse_size("1024x1024") == (1024, 1024)
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--size", "1024x1024",
                          "--out", str(tmp_path / "x.png"))
    assert status == 2 and "0.535 GB of memory (510 bytes a pixel tracing the view's light)" in err
    assert not (tmp_path / "x.png").exists()


def test_a_lattice_that_records_no_bake_config_renders(tmp_path, capsys):
    """Without a config in its metadata, a lattice is shown with the default albedo, and
    the refusal of other lighting says its lighting was not recorded."""
    import json
    import zipfile

    lattice = tmp_path / "l.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "1",
                          "--bounces", "0", "--env", "constant:1,1,1", "--out", str(lattice))
    assert status == 0, err
    bare = tmp_path / "bare.npz"
    with zipfile.ZipFile(lattice) as zin, zipfile.ZipFile(bare, "w") as zout:
        for name in zin.namelist():
            if name != "meta.npy":
                zout.writestr(name, zin.read(name))
        with zin.open("meta.npy") as member:
            meta = json.loads(str(np.lib.format.read_array(member)))
        del meta["config"], meta["config_version"]
        with zout.open("meta.npy", "w") as member:
            np.lib.format.write_array(member, np.array(json.dumps(meta)))
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--lattice", str(bare),
                          "--size", "32x32", "--out", str(tmp_path / "x.png"))
    assert status == 0, err
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--lattice", str(bare),
                          "--env", "sky", "--size", "32x32", "--out", str(tmp_path / "x.png"))
    assert status == 2 and "(lighting not recorded)" in err and err.count("\n") == 1, err


def test_no_gl_names_the_alternatives(tmp_path, monkeypatch, capsys):
    import isolume.app.render.glcontext as glc

    def fail():
        raise glc.GLUnavailable("OSMesa is not installed (libOSMesa.so.8 not found); try --gl egl")

    monkeypatch.setattr(glc, "_create_osmesa", fail)
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--gl", "osmesa",
                          "--out", str(tmp_path / "x.png"))
    assert status == 2 and "--gl egl" in err


def test_console_entry_point_reports_without_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "isolume.app.cli", "info", str(tmp_path / "absent.nrrd")],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and "absent.nrrd" in result.stderr


def _subcommands(parser, prefix=()):
    """Every command path of `parser` (("render",), ("bench", "lazy"), ...)."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*prefix, name)
                yield from _subcommands(sub, (*prefix, name))


def test_every_command_has_help(capsys):
    """``isolume CMD --help`` prints usage and exits 0 for every command and subcommand
    (a stray ``%`` in a help string makes argparse fail only when help is shown)."""
    from isolume.app.cli import build_parser

    commands = list(_subcommands(build_parser()))
    assert {("render",), ("view",), ("reference",), ("bench",)} <= set(commands)
    for command in [(), *commands]:
        with pytest.raises(SystemExit) as exit_info:
            main([*command, "--help"])
        out = capsys.readouterr().out
        assert exit_info.value.code == 0, command
        assert out.startswith("usage: isolume"), (command, out[:80])


def test_a_command_parses_alone_as_among_all(capsys):
    """A command line that names its command builds that command's parser alone (the
    others' modules not imported): the same values and the same help as the parser of
    every command; a line that names none gets every command."""
    from isolume.app.cli import build_parser, command_named

    lines = [["info", "synthetic:engine:48", "--up", "x"],
             ["render", "synthetic:sphere:16", "--out", "a.png", "--size", "64x48"],
             ["bake", "v.npy", "--out", "l.npz", "--samples", "4", "--workers", "1"],
             ["bench", "cores", "--threads", "1,2"], ["movie", "v.npy", "--out", "m.mp4"],
             ["view", "v.npy"], ["reference", "v.npy", "--out", "a.exr"]]
    for words in lines:
        assert command_named(words) == words[0]
        assert build_parser(words[0]).parse_args(words) == build_parser().parse_args(words)
        helps = []
        for parser in (build_parser(words[0]), build_parser()):
            with pytest.raises(SystemExit):
                parser.parse_args([words[0], "--help"])
            helps.append(capsys.readouterr().out)
        assert helps[0] == helps[1] and helps[0].startswith(f"usage: isolume {words[0]}")
    assert command_named([]) is None and command_named(["--help"]) is None
    assert command_named(["bak"]) is None


def test_render_traces_global_illumination_by_default(tmp_path, capsys):
    """Without --lattice, render shows global illumination for its view: under a constant
    white sky a convex sphere sees the whole sky everywhere (E = π, every path escapes), so
    its radiance is albedo · 1 = 0.8 on every surface pixel, up to RGB9_E5 rounding (2⁻⁹)."""
    exr = tmp_path / "gi.exr"
    status, text, err = _run(capsys, "render", "synthetic:sphere:24", "--env", "constant:1,1,1",
                             "--size", "48x40", "--gl", "osmesa", "--samples", "8",
                             "--out", str(exr))
    assert status == 0, err
    assert "shading irradiance, lighting constant:1,1,1," in text
    assert "global illumination:" in err
    rgb = read_exr(exr)["RGB"]
    surface = rgb.max(axis=-1) > 0
    assert surface.mean() > 0.05
    np.testing.assert_allclose(rgb[surface], 0.8, rtol=2.0**-8)
    # local shading stays available
    status, text, _ = _run(capsys, "render", "synthetic:sphere:24", "--shading", "phong_hemi",
                           "--size", "48x40", "--gl", "osmesa", "--out", str(exr))
    assert status == 0 and "shading phong_hemi" in text


def test_up_turns_the_volume(capsys):
    status, out, _ = _run(capsys, "info", "synthetic:engine:48", "--up", "x")
    assert status == 0 and "25 x 30 x 48" in out  # x (48 samples) now runs up
    from isolume.app.cli import _join_negative_axes, build_parser
    from isolume.app.options import load_volume

    args = build_parser().parse_args(_join_negative_axes(["info", "synthetic:engine:48",
                                                          "--up", "-z"]))
    plain = volumes.load("synthetic:engine:48")
    np.testing.assert_array_equal(load_volume(args).data, plain.data[::-1, :, ::-1])
    status, _, err = _run(capsys, "info", "synthetic:engine:48", "--up", "w")
    assert status == 2 and "--up 'w'" in err


def test_values_that_start_with_a_minus_sign_are_an_options_values(tmp_path, capsys):
    """``--view -30,20`` (a negative azimuth) renders as ``--view=-30,20`` does, where
    argparse took ``-30,20`` for an option; plain negative numbers stay argparse's
    (``--iso-range -5 10``); ``--size -5x10`` is refused by the size's own check, in one
    line; a NaN isovalue is called not finite."""
    from isolume.app.cli import _join_negative_axes

    assert _join_negative_axes(["render", "--view", "-30,20", "--iso", "-.5", "--up", "-z",
                                "--exposure", "2"]) == ["render", "--view=-30,20",
                                                        "--iso", "-.5", "--up=-z",
                                                        "--exposure", "2"]
    for plain in (["bake", "--iso-range", "-5", "10"], ["render", "--", "-5,3"]):
        assert _join_negative_axes(plain) == plain  # numbers argparse reads, and "--"
    render = ["render", "synthetic:sphere:16", "--size", "24x24", "--gl", "osmesa"]
    for view in (["--view", "-30,20"], ["--view=-30,20"]):
        assert main([*render, *view, "--out", str(tmp_path / f"{len(view)}.png")]) == 0
    assert (tmp_path / "1.png").read_bytes() == (tmp_path / "2.png").read_bytes()
    capsys.readouterr()
    for wrong, said in ((["--size", "-5x10"], "--size"), (["--iso", "nan"], "finite")):
        assert main([*render, *wrong, "--out", str(tmp_path / "x.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], err


def test_default_render_agrees_with_the_reference(tmp_path, capsys):
    """The default picture (GI traced for the view under the default sky and sun, the sun
    added per pixel) against ``isolume reference`` with the same arguments, on a part with
    shadows and interreflections. Measured: 5.7 % RMS with 3.4 % of it the reference's own
    noise (512 spp), mean ratio 0.996; the sun counted twice gives 1.45."""
    from isolume.baking.config import DEFAULT_ENV

    common = ["synthetic:engine:48", "--size", "64x64"]
    status, _, err = _run(capsys, "render", *common, "--gl", "osmesa",
                          "--out", str(tmp_path / "gi.exr"))
    assert status == 0, err
    status, _, err = _run(capsys, "reference", *common, "--env", DEFAULT_ENV, "--spp", "512",
                          "--out", str(tmp_path / "ref.exr"))
    assert status == 0, err
    gi, ref = read_exr(tmp_path / "gi.exr"), read_exr(tmp_path / "ref.exr")
    both = (ref["mask"] > 0.5) & (gi["RGB"].max(axis=-1) > 0)
    assert both.sum() > 0.95 * (ref["mask"] > 0.5).sum()
    truth, picture, noise = ref["RGB"][both], gi["RGB"][both], ref["stderr"][both]
    # the mean over ~1500 pixels: its noise is ~0.1 %, the lattice's bias measured 0.4 %
    assert picture.mean() / truth.mean() == pytest.approx(1.0, abs=0.03)
    error = np.sqrt(np.mean((picture - truth) ** 2)) / truth.mean()
    own_noise = np.sqrt(np.mean(noise**2)) / truth.mean()
    assert np.sqrt(max(error**2 - own_noise**2, 0.0)) < 0.08


def test_lighting_options_are_refused_with_an_irradiance_lattice(tmp_path, capsys):
    """An irradiance lattice holds the light it was baked with: asking for another one is
    an error, not a picture lit otherwise than asked."""
    lattice = tmp_path / "l.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "1",
                          "--bounces", "0", "--env", "constant:1,1,1", "--out", str(lattice))
    assert status == 0, err
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--lattice", str(lattice),
                          "--env", "sky", "--out", str(tmp_path / "x.png"))
    assert status == 2 and "constant:1,1,1" in err and err.count("\n") == 1


SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "volumes"
SCANS = [("engine_zfp_256x256x128_uint8.raw.gz", []),
         ("CThead_256x256x113_uint16.raw.gz", []),
         ("CThead_256x256x113_uint16.raw.gz", ["--up", "-z"])]


@pytest.mark.slow
@pytest.mark.shared
@pytest.mark.parametrize(("name", "extra"), SCANS)
def test_default_pictures_of_real_scans_are_exposed_right(tmp_path, capsys, name, extra):
    """The default picture of the engine CT and CThead: the surface's median pixel lies in
    100–180 of 255 and its 95th percentile at most 240 (measured 158 / 142 and
    190 / 200)."""
    if not (SHARED / name).exists():
        pytest.skip(f"{SHARED / name} not present (../shared is optional)")
    out = tmp_path / "x.png"
    status, _, err = _run(capsys, "render", str(SHARED / name), *extra, "--out", str(out))
    assert status == 0, err
    rgb = np.asarray(Image.open(out).convert("RGB"))
    surface = (rgb != rgb[0, 0]).any(axis=-1)  # the corner shows the background
    values = rgb[surface].astype(float).mean(axis=-1)
    assert 0.1 < surface.mean() < 0.9
    assert 100 <= np.median(values) <= 180 and np.percentile(values, 95) <= 240


def test_default_render_is_the_same_for_any_worker_count(tmp_path, capsys):
    """The view's GI draws its random numbers per texel and path: 1 or 3 threads give the
    same picture to the bit."""
    pictures = []
    for workers in ("1", "3"):
        out = tmp_path / f"w{workers}.exr"
        status, _, err = _run(capsys, "render", "synthetic:engine:32", "--size", "48x48",
                              "--gl", "osmesa", "--samples", "8", "--workers", workers,
                              "--out", str(out))
        assert status == 0, err
        pictures.append(read_exr(out)["RGB"])
    assert pictures[0].max() > 0
    np.testing.assert_array_equal(pictures[0], pictures[1])


def test_render_view_bake_and_reference_default_to_the_same_lighting():
    """The same arguments give the same lighting, so any picture can be checked against
    the path tracer (DESIGN §6)."""
    from isolume.app.cli import build_parser
    from isolume.baking.config import DEFAULT_ENV

    parser = build_parser()
    for argv in (["render", "--out", "a.png"], ["reference", "v.npy", "--out", "a.exr"],
                 ["bake", "v.npy", "--out", "l.npz"]):
        args = parser.parse_args(argv)
        assert getattr(args, "env", None) in (None, DEFAULT_ENV), argv
    assert parser.parse_args(["reference", "v.npy", "--out", "a.exr"]).env == DEFAULT_ENV
    assert parser.parse_args(["bake", "v.npy", "--out", "l.npz"]).env == DEFAULT_ENV


def test_a_text_file_given_as_a_lattice_is_one_line(tmp_path, capsys):
    text = tmp_path / "notes.npz"
    text.write_text("not a lattice\n")
    status, _, err = _run(capsys, "render", "synthetic:sphere:16", "--lattice", str(text),
                          "--out", str(tmp_path / "x.png"))
    assert status == 2 and err.count("\n") == 1
    assert "not a lattice file" in err and "pickle" not in err


def test_a_lattice_baked_with_another_up_names_up(tmp_path, capsys):
    """The same raw file loaded with another --up has other samples: the refusal says to
    load it as the bake did."""
    raw = tmp_path / "blob_12x10x8_uint8.raw"
    z, y, x = np.mgrid[:8, :10, :12]
    ((np.hypot(np.hypot(x - 5.5, y - 4.5), z - 3.0) < 3.5) * 200).astype(np.uint8).tofile(raw)
    lattice = tmp_path / "l.npz"
    status, _, err = _run(capsys, "bake", str(raw), "--samples", "1", "--bounces", "0",
                          "--env", "constant:1,1,1", "--out", str(lattice))
    assert status == 0, err
    status, _, err = _run(capsys, "render", str(raw), "--up", "-z", "--lattice", str(lattice),
                          "--out", str(tmp_path / "x.png"))
    assert status == 2 and err.count("\n") == 1 and "--up" in err, err


def test_every_command_has_a_description_and_every_option_a_help_text():
    import argparse

    from isolume.app.cli import build_parser

    missing = []

    def walk(parser, name):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    if not sub.description:
                        missing.append(f"{name} {sub_name}: description")
                    walk(sub, f"{name} {sub_name}")
            elif action.option_strings and not action.help:
                missing.append(f"{name} {action.option_strings[-1]}")

    walk(build_parser(), "isolume")
    assert not missing, missing


def test_bake_says_what_it_will_trace_before_tracing(tmp_path, capsys, monkeypatch):
    """The outlook line counts the paths of the plan (texels × samples) and the rough
    minutes; a bake expected to run past a minute names the cheaper options: half the
    bake's own paths per texel and half its scale."""
    import importlib

    bake_module = importlib.import_module("isolume.baking.bake")
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--bounces", "0", "--out", str(tmp_path / "s.npz"))
    assert status == 0, err
    line = next(x for x in err.splitlines() if x.startswith("bake: ") and "texels" in x)
    texels = int(line.split()[1].replace(",", ""))
    assert f"{2 * texels:,} paths to trace" in line and "min on" in line
    assert "cheaper" not in err
    for stage in ("texel values", "seen sides on", "reach tests"):  # a bar each, full
        assert re.search(f"planning: {stage}[^\r\n]*: 100%", err), (stage, err)
    monkeypatch.setattr(bake_module, "PATHS_PER_THREAD_SECOND", 1e-3)
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--bounces", "0", "--scale", "0.5", "--workers", "1",
                          "--out", str(tmp_path / "t.npz"))
    cheaper = next(x for x in err.splitlines() if x.startswith("bake: cheaper"))
    assert status == 0 and "--iso-range" in cheaper, err
    assert "--samples 1," in cheaper and "--scale 0.25," in cheaper, cheaper
    assert "min on 1 thread\n" in err, err
    status, _, err = _run(capsys, "bake", "synthetic:sphere:64", "--samples", "1",
                          "--bounces", "0", "--scale", "0.08", "--out", str(tmp_path / "u.npz"))
    cheaper = next(x for x in err.splitlines() if x.startswith("bake: cheaper"))
    assert status == 0 and "--samples" not in cheaper and "--scale" not in cheaper, cheaper


def test_cheaper_options_name_only_options_the_bake_takes():
    """A texel error is named for a bake without one, never beside a noise target (the
    two are refused together), and kept beside a texel bake's halved paths (``--samples``
    alone bakes uniform texels); the named options make a config that is accepted."""
    from isolume.app.commands import cheaper_options
    from isolume.baking import BakeConfig

    def texel_error(config: BakeConfig) -> float | None:
        named = re.search(r"--texel-error ([0-9.]+)", cheaper_options(config))
        if named:  # the suggestion is a config the bake takes
            dataclasses.replace(config, texel_error=float(named.group(1)))
        return float(named.group(1)) if named else None

    assert texel_error(BakeConfig(samples=100)) == 0.02
    assert texel_error(BakeConfig(samples=16, target_error=0.1)) is None
    assert texel_error(BakeConfig(samples=64, texel_error=0.05)) == 0.05
    assert "--samples 32 --texel-error 0.05," in cheaper_options(
        BakeConfig(samples=64, texel_error=0.05))


def test_a_plan_that_fails_leaves_its_stage_unfinished_and_says_why(tmp_path, capsys,
                                                                    monkeypatch):
    """A bake whose plan fails (here its side probes) says why in one line, exit 2, with
    the bars of the stages before it full and the failed stage's bar not."""
    from isolume.baking import plan as plan_module
    from isolume.baking.errors import BakeError

    def fail(*args, **kwargs):
        raise BakeError("the side probes failed")

    monkeypatch.setattr(plan_module, "lit_sides", fail)
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--out", str(tmp_path / "s.npz"))
    assert status == 2 and "the side probes failed" in err, err
    assert re.search(r"planning: paths onto \d+ levels: 100%", err), err
    assert "planning: seen sides on" in err and not re.search(r"seen sides[^\r\n]*100%", err)


def test_a_ctrl_c_during_the_final_save_says_the_save_ends_first(tmp_path, capsys,
                                                                  ctrl_c_during_save):
    """Ctrl-C while `isolume bake` writes its finished lattice: it says the save ends
    first, writes the whole file, and exits 130 counting every active texel."""
    from isolume.baking import Lattice

    ctrl_c_during_save(1)
    path = tmp_path / "s.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--bounces", "0", "--out", str(path))
    assert status == 130, err
    assert f"the bake is done and its save to {path} is finished first" in err
    saved = Lattice.load(path)
    assert (saved.samples[saved.active] == 2).all()
    assert f"interrupted; {int(saved.active.sum()):,} finished texels saved" in err


def test_a_bake_whose_file_cannot_be_written_says_so_in_one_line(tmp_path, capsys,
                                                                   disk_full):
    """A full disk at the bake's save: exit 2 and one line naming the file and the
    reason, not a traceback."""
    disk_full()
    path = tmp_path / "s.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--bounces", "0", "--out", str(path))
    assert status == 2
    assert (f"isolume: error: {path}: cannot write the lattice: No space left on device; "
            "nothing was written") in err
    assert "Traceback" not in err and not path.exists()


def test_an_interrupted_bake_says_what_its_file_keeps(tmp_path, capsys, monkeypatch):
    """Ctrl-C during `isolume bake`: exit 130; stopped after its texels were saved, the
    count the bake tells (not read from the file again); stopped before the tracing, that
    the file keeps its last save."""
    import isolume.baking
    from isolume.baking.errors import BakeInterrupted

    path = tmp_path / "s.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--bounces", "0", "--out", str(path))
    assert status == 0, err
    for raised, says in ((BakeInterrupted(1234), f"interrupted; 1,234 finished texels "
                                                 f"saved in {path}"),
                         (KeyboardInterrupt(), f"interrupted; {path} keeps the texels of "
                                               "its last save")):
        def interrupted(*args, raised=raised, **kwargs):
            raise raised

        monkeypatch.setattr(isolume.baking, "bake", interrupted)
        status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "4",
                              "--bounces", "0", "--out", str(path))
        assert status == 130
        assert says in err, err


def test_an_interrupt_out_of_a_library_or_before_any_file_says_so(tmp_path, capsys,
                                                                  monkeypatch):
    """A Ctrl-C that comes out of numba's kernel loading as a SystemError is an
    interrupt (exit 130, one line); another SystemError stays a bug; stopped before any
    path with no file yet, the bake says nothing was written."""
    import isolume.baking

    def loading(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher returned a result with an exception set")  # noqa: B904

    monkeypatch.setattr(isolume.baking, "bake", loading)
    path = tmp_path / "new.npz"
    status, _, err = _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2",
                          "--out", str(path))
    assert status == 130 and f"interrupted before any path was traced; {path} not" in err

    def failing(*args, **kwargs):
        raise SystemError("a bug")

    monkeypatch.setattr(isolume.baking, "bake", failing)
    with pytest.raises(SystemError, match="a bug"):
        main(["bake", "synthetic:sphere:16", "--samples", "2", "--out", str(path)])


def test_render_warns_of_a_lattice_file_that_is_unfinished(tmp_path, capsys):
    """`render --lattice` of a file whose bake was cut short draws it, and says how many
    of the texels the picture reads have no paths yet; a finished file draws silently."""
    from isolume.baking import Lattice

    path = tmp_path / "l.npz"
    assert _run(capsys, "bake", "synthetic:sphere:16", "--samples", "2", "--out",
                str(path))[0] == 0
    out = ["render", "synthetic:sphere:16", "--lattice", str(path), "--size", "64x64",
           "--out", str(tmp_path / "p.png")]
    status, _, err = _run(capsys, *out)
    assert status == 0 and "unfinished" not in err
    vol = volumes.load("synthetic:sphere:16")
    lattice = Lattice.load(path, vol)
    baked = np.flatnonzero(lattice.samples.reshape(-1))
    lattice.samples.reshape(-1)[baked[::2]] = 0  # every other texel not traced yet
    lattice.values.reshape(len(lattice.samples.reshape(-1)), -1)[baked[::2]] = 0
    lattice.save(path)
    status, _, err = _run(capsys, *out)
    found = re.search(r"warning: .*l\.npz is unfinished: ([\d,]+) of the ([\d,]+) texels", err)
    assert status == 0 and found, err
    assert 0 < int(found[1].replace(",", "")) < int(found[2].replace(",", ""))


def test_origin_places_a_volume_the_file_places_far_away(tmp_path, capsys):
    """A file placed farther from the world origin than float32 coordinates serve is
    refused, naming ``--origin``; with ``--origin 0,0,0`` it loads there, as the Python
    API's ``origin=`` loads it."""
    import isolume

    path = tmp_path / "far.npz"
    np.savez(path, data=np.zeros((16, 16, 16), np.uint8), origin=np.array([5e5, 4e6, 0.0]))
    status, _, err = _run(capsys, "info", str(path))
    assert status == 2 and "--origin 0,0,0" in err and err.count("\n") == 1, err
    status, _, err = _run(capsys, "info", str(path), "--origin", "0,0,0")
    assert status == 0, err
    assert isolume.load(path, origin=(1, 2, 3)).origin == (1.0, 2.0, 3.0)
    status, _, err = _run(capsys, "info", str(path), "--origin", "0,0")
    assert status == 2 and "--origin" in err


def test_a_picture_the_surface_covers_no_pixel_of_warns(tmp_path, capsys):
    """A camera so far that the surface falls between the pixels draws an empty picture:
    the command says why; a framed view says nothing."""
    out = ["render", "synthetic:sphere:16", "--size", "32x32", "--shading", "lambert",
           "--out", str(tmp_path / "p.png")]
    status, _, err = _run(capsys, *out, "--view", "30,30,1000")
    assert status == 0 and "covers no pixel of the picture" in err, err
    status, _, err = _run(capsys, *out)
    assert status == 0 and "covers no pixel" not in err, err


def test_the_console_script_freezes_the_heap_before_the_process_exits():
    """Run as the script (no argv), `main` freezes the collector's heap as it returns, so
    that Python's finalization does not collect it again and again (~0.2 s an exit); called
    with arguments (a test, a caller that goes on) it leaves the heap alone."""
    import gc

    script = ("import gc, sys; from isolume.app.cli import main; "
              "sys.argv = ['isolume', 'info', 'synthetic:sphere:16']; main(); "
              "print(gc.get_freeze_count())")
    done = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True,
                          text=True)
    assert int(done.stdout.split()[-1]) > 0
    before = gc.get_freeze_count()
    assert main(["info", "synthetic:sphere:16"]) == 0
    assert gc.get_freeze_count() == before


def test_a_ctrl_c_inside_a_callback_from_c_is_sent_again_after_it(monkeypatch):
    """The console script's SIGINT handler (`volumes.interrupts.on_interrupt`) raises
    KeyboardInterrupt, except in a frame under llvmlite's object-cache callbacks (numba
    taking a kernel's code as it compiles: there Python would print the KeyboardInterrupt
    and go on) or a ``__del__``: it sends the signal again `RESEND_S` later instead."""
    import os
    import signal
    import threading

    from isolume.volumes import interrupts

    sent = []
    done = threading.Event()
    monkeypatch.setattr(os, "kill", lambda pid, sig: sent.append((pid, sig)) or done.set())
    here: dict = {}
    exec(compile("import sys\ndef _raw_object_cache_notify(data):\n"
                 "    return sys._getframe()\n",
                 "/site-packages/llvmlite/binding/executionengine.py", "exec"), here)

    def nested() -> object:  # a frame called from inside the callback
        return sys._getframe()

    class Finalised:
        def __del__(self):
            here["del"] = nested()

    Finalised()
    for frame in (here["_raw_object_cache_notify"](b""), here["del"]):
        done.clear()
        assert interrupts.on_interrupt(signal.SIGINT, frame) is None
        assert done.wait(2) and sent[-1] == (os.getpid(), signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        interrupts.on_interrupt(signal.SIGINT, sys._getframe())
    assert len(sent) == 2


def test_a_seed_outside_32_bits_is_refused_not_aliased(tmp_path, capsys):
    """The tracer's random numbers take a 32-bit seed: a seed outside 0 .. 2³² - 1 is
    refused in one line before any work (seed 2³² would bake seed 0's lattice)."""
    commands = [["bake", "synthetic:sphere:16", "--out", str(tmp_path / "l.npz")],
                ["render", "synthetic:sphere:16", "--out", str(tmp_path / "p.png")],
                ["reference", "synthetic:sphere:16", "--out", str(tmp_path / "r.exr")]]
    for command in commands:
        for seed in ("-1", "4294967296"):
            capsys.readouterr()
            assert main([*command, "--seed", seed]) == 2, command
            err = capsys.readouterr().err.strip().splitlines()
            assert err == [f"isolume: error: --seed {seed}: expected a whole number from 0 "
                           "to 4294967295"], err
    assert not list(tmp_path.iterdir())


def test_options_a_lattice_would_leave_unused_are_refused_in_one_line(tmp_path, capsys):
    """``--shading sh`` with an irradiance lattice and an irradiance mode with an SH one
    (each saying how the other kind is baked), ``--env-rotation`` with an irradiance
    lattice (its light cannot turn) and ``--light`` with an SH lattice: one line each,
    status 2, naming the file — not a traceback, not an option silently left out of the
    picture."""
    volume = "synthetic:sphere:16"
    irradiance, transfer = tmp_path / "e.npz", tmp_path / "sh.npz"
    for out, extra in [(irradiance, []), (transfer, ["--mode", "sh", "--sh-order", "2"])]:
        assert main(["bake", volume, "--samples", "2", "--out", str(out), *extra]) == 0
    render = ["render", volume, "--size", "16x16", "--out", str(tmp_path / "x.png")]
    for extra, expected in [
            (["--lattice", str(irradiance), "--shading", "sh"],
             f"needs an SH lattice (isolume bake --mode sh); {irradiance} holds irradiance"),
            (["--lattice", str(transfer), "--shading", "irradiance_closest"],
             f"needs an irradiance lattice (isolume bake, without --mode sh); {transfer} "
             "holds sh"),
            (["--lattice", str(transfer), "--shading", "ao"], "needs an irradiance lattice"),
            (["--lattice", str(irradiance), "--env-rotation", "90,0"], "cannot turn"),
            (["--lattice", str(transfer), "--light", "dir:0,0,1:1,1,1"], "SH lattice")]:
        capsys.readouterr()
        assert main([*render, *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], err


@pytest.mark.parametrize("sent", ["SIGINT", "SIGTERM"])
def test_the_final_save_goes_through_one_interrupt_under_the_command_line_s_handlers(sent):
    """`baking.saves.through_one_interrupt` defers one Ctrl-C under the console script's
    SIGINT handler as under Python's own (a finished bake's save is not lost to it), and
    one SIGTERM where SIGINT is ignored (a background job) and SIGTERM is the command
    line's (`interrupts.on_terminate`); a second raises, and the handlers before are
    back afterwards."""
    import os
    import signal

    from isolume.baking.saves import through_one_interrupt
    from isolume.volumes import interrupts

    handlers = {signal.SIGINT: interrupts.on_interrupt} if sent == "SIGINT" else \
        {signal.SIGINT: signal.SIG_IGN, signal.SIGTERM: interrupts.on_terminate}
    before = {signum: signal.signal(signum, handler) for signum, handler in handlers.items()}
    try:
        with through_one_interrupt(None) as pressed:
            os.kill(os.getpid(), getattr(signal, sent))
            time.sleep(0.05)
            assert pressed == [True]
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), getattr(signal, sent))
                time.sleep(0.5)
        assert all(signal.getsignal(s) is h for s, h in handlers.items())
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


def test_sigterm_stops_a_background_bake_as_a_ctrl_c_and_keeps_its_texels(tmp_path,
                                                                            stopped_after):
    """A bake run as a shell's background job (SIGINT ignored) and stopped by SIGTERM (a
    batch system's time limit, a `kill`) saves its finished texels as a Ctrl-C does."""
    import signal

    out = tmp_path / "l.npz"
    bake = [sys.executable, "-c", CLI, "bake", "synthetic:engine:64", "--samples", "2048",
            "--out", str(out)]
    proc = subprocess.Popen(bake, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    status, err = stopped_after(proc, "paths to trace", signal.SIGTERM, wait=1.0)
    assert status == 130, err
    assert "finished texels saved in" in err, err
    info = _info(out)
    assert re.search(r"finished\s+no:", info), info


def test_a_hangup_saves_the_finished_texels_though_the_terminal_is_gone(tmp_path):
    """A bake in a terminal that closes (SIGHUP; every write to it then fails with EIO)
    saves its finished texels as a Ctrl-C does: the messages after the hangup must not
    stop the save with an OSError."""
    import os
    import pty
    import signal

    out = tmp_path / "l.npz"
    master, terminal = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-c", CLI, "bake", "synthetic:engine:64",
                             "--samples", "2048", "--out", str(out)],
                            stdin=terminal, stdout=terminal, stderr=terminal,
                            start_new_session=True)
    os.close(terminal)
    try:
        seen = b""
        while b"paths to trace" not in seen:
            seen += os.read(master, 65536)
        time.sleep(1.0)
        os.close(master)  # the terminal goes away
        proc.send_signal(signal.SIGHUP)
        assert proc.wait(timeout=60) == 130
    finally:
        proc.kill()
    info = _info(out)
    assert re.search(r"finished\s+no:", info), info


def _info(lattice: Path) -> str:
    """What ``isolume info LATTICE`` prints, run as a subprocess."""
    return subprocess.run([sys.executable, "-c", CLI, "info", str(lattice)], check=True,
                          capture_output=True, text=True).stdout


def test_a_process_forked_under_the_command_line_s_handlers_ends_on_sigterm():
    """A child forked after `interrupts.install` (a pool's, the viewer's bake process)
    takes SIGTERM's default action, though its SIGINT is ignored."""
    import signal

    child = subprocess.run([sys.executable, "-c", FORKED_SIGTERM], capture_output=True,
                           text=True, timeout=30)
    assert child.stdout.split() == ["on_terminate", str(-signal.SIGTERM)], child.stderr


CLI = "import sys; from isolume.app.cli import main; sys.exit(main())"
"""``isolume ARGS`` as the console script runs it: ``python -c CLI ARGS``."""

FORKED_SIGTERM = """
import os, signal, time
from isolume.volumes import interrupts
interrupts.install()
print(signal.getsignal(signal.SIGTERM).__name__, flush=True)
pid = os.fork()
if pid == 0:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    time.sleep(30)
    os._exit(0)
time.sleep(0.2)
os.kill(pid, signal.SIGTERM)
_, status = os.waitpid(pid, 0)
print(-os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status))
"""


def test_a_second_ctrl_c_while_an_interrupted_bake_saves_says_what_was_lost(tmp_path, capsys,
                                                                           monkeypatch):
    """Ctrl-C again while the finished texels of an interrupted bake are saved: the save
    stops (`errors.SaveAbandoned`, with the count) and the command says the texels were
    not saved and what the file holds — not that no path was traced."""
    from isolume.app import commands
    from isolume.baking.errors import SaveAbandoned
    from isolume.baking.saves import save_interrupted

    class Cut:
        samples = np.array([0, 3, 5, 0])

        def save(self, path):
            raise KeyboardInterrupt

    with pytest.raises(SaveAbandoned) as stop:
        save_interrupted(Cut(), tmp_path / "l.npz", progress=False)
    assert stop.value.finished == 2

    def abandoned(args):
        raise SaveAbandoned(1234)

    monkeypatch.setattr(commands, "bake_lattice", abandoned)
    out = tmp_path / "l.npz"
    assert main(["bake", "synthetic:sphere:16", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "finished since the last save were not saved" in err and f"{out} not written" in err
    assert "before any path" not in err


def test_the_first_kernel_compiled_is_said_once(capsys):
    """A command says once, on stderr, that it compiles the kernels when numba compiles
    one it found no cached code for (a first run is 5–10 times slower); loading cached
    kernels says nothing; commands run again in one process register no second listener."""
    import numba
    from numba.core import event

    from isolume.app import cli

    cli._say_first_compile()
    cli._say_first_compile()
    assert len(cli._LISTENING) == 1
    registered = list(cli._LISTENING)
    for listener in registered:  # what earlier commands of this process registered
        event.unregister("numba:compile", listener)
    listener = cli._first_compile_listener()
    event.register("numba:compile", listener)
    try:
        for k in range(2):
            namespace: dict = {}
            exec(f"def f(x):\n    return x * {k + 2} + 1\n", namespace)
            assert numba.njit(cache=False)(namespace["f"])(3) == 3 * (k + 2) + 1
    finally:
        event.unregister("numba:compile", listener)
        for listener in registered:
            event.register("numba:compile", listener)
    assert capsys.readouterr().err.count(cli.FIRST_COMPILE) == 1
