"""The Python API (`import isolume`): in-process, one code path with the commands, the
same options and defaults, light to import, one identity per module."""

from __future__ import annotations

import ast
import inspect
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import isolume
from isolume._arguments import option_actions, option_value
from isolume.app.cli import main
from isolume.app.render.images import read_exr
from isolume.volumes.errors import IsolumeError

ROOT = Path(__file__).resolve().parents[1]

VOLUME_OPTIONS = {"volume", "dims", "dtype", "spacing", "origin", "up", "crop", "downsample",
                  "level"}
"""Options of the volume: keywords of `isolume.load`; the other functions take a Volume."""

EXCEPTIONS = {
    "view": {"size": "640x480 in a notebook cell (1024x768 on the desktop)",
             "frames": "desktop scripting", "screenshot": "desktop scripting",
             "script": "desktop scripting", "stats": "desktop scripting",
             "timeline": "desktop scripting", "no_ui": "the notebook's controls are widgets",
             "state": "desktop: the viewer's saved views"},
}
"""Reviewed differences between a command's options and its API counterpart's keywords:
{command: {option keyword: why}}."""

FUNCTIONS = {"render": "render", "bake": "bake", "export": "export", "movie": "movie",
             "reference": "reference", "view": "show", "info": "load"}


def _png(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path))


@pytest.mark.parametrize("command", sorted(FUNCTIONS))
def test_every_option_has_a_keyword_of_the_same_name_and_default(command):
    function = getattr(isolume, FUNCTIONS[command])
    parameters = inspect.signature(function).parameters
    assert not any(p.kind is p.VAR_KEYWORD for p in parameters.values()), "no **kwargs"
    exceptions = EXCEPTIONS.get(command, {})
    for name, action in option_actions(command).items():
        if name in exceptions or (name in VOLUME_OPTIONS and command != "info"):
            continue
        if command == "info" and name == "volume":
            name = "source"
        assert name in parameters, f"isolume {command} --{name}: no keyword {name}"
        default = parameters[name].default
        if default is inspect.Parameter.empty:  # required: out
            assert action.required or name in ("out", "source"), name
            continue
        assert option_value(name, default) == action.default, (
            f"isolume.{FUNCTIONS[command]}({name}={default!r}) is not --{name}'s default "
            f"{action.default!r}")
    load_keywords = inspect.signature(isolume.load).parameters
    assert VOLUME_OPTIONS - {"volume"} <= set(load_keywords)


def test_the_reviewed_exceptions_are_still_options():
    for command, names in EXCEPTIONS.items():
        assert set(names) <= set(option_actions(command)), command


def test_keywords_are_stored_as_their_options_would_be():
    assert option_value("size", (256, 128)) == "256x128"
    assert option_value("view", (30, 12.5, 1.5)) == "30,12.5,1.5"
    assert option_value("albedo", 0.5) == "0.5"
    assert option_value("albedo", (0.1, 0.2, 0.3)) == "0.1,0.2,0.3"
    assert option_value("light", "dir:0,0,1:1,1,1") == ["dir:0,0,1:1,1,1"]
    assert option_value("lattice", Path("a/b.npz")) == "a/b.npz"


def test_render_equals_the_command_png_and_exr(tmp_path):
    volume = isolume.load("synthetic:engine:48")
    picture = isolume.render(volume, size=(96, 64), gl="osmesa", samples=16)
    picture.save(tmp_path / "a.png")
    picture.save(tmp_path / "a.exr")
    for suffix in ("png", "exr"):
        assert main(["render", "synthetic:engine:48", "--size", "96x64", "--gl", "osmesa",
                     "--samples", "16", "--out", str(tmp_path / f"b.{suffix}")]) == 0
    assert np.array_equal(_png(tmp_path / "a.png"), _png(tmp_path / "b.png"))
    assert np.array_equal(read_exr(tmp_path / "a.exr")["RGB"], read_exr(tmp_path / "b.exr")["RGB"])
    assert picture.srgb.shape == (64, 96, 3) and picture.srgb.std() > 5
    assert picture.size == (96, 64)


def test_render_with_a_baked_lattice_equals_the_command(tmp_path):
    volume = isolume.load("synthetic:engine:32")
    lattice = isolume.bake(volume, samples=8, out=tmp_path / "l.npz", workers=2)
    assert isinstance(lattice, isolume.Lattice) and (lattice.samples == 8).any()
    in_memory = isolume.render(volume, lattice=lattice, size=(64, 64), gl="osmesa")
    from_file = isolume.render(volume, lattice=tmp_path / "l.npz", size=(64, 64), gl="osmesa")
    assert main(["render", "synthetic:engine:32", "--lattice", str(tmp_path / "l.npz"),
                 "--size", "64x64", "--gl", "osmesa", "--out", str(tmp_path / "c.png")]) == 0
    command = _png(tmp_path / "c.png")
    assert np.array_equal(from_file.srgb, command)
    assert np.array_equal(in_memory.srgb, command)
    with pytest.raises(IsolumeError, match=r"^env/light: the irradiance lattice of "
                       r"'engine' \(\d+×\d+×\d+ texels\) holds irradiance baked"):
        isolume.render(volume, lattice=lattice, env="constant:1,1,1")


@pytest.mark.parametrize(("function", "keywords", "message"), [
    ("bake", {"seed": 1 << 32}, "seed=4294967296: expected a whole number from 0 to"),
    ("bake", {"iso_range": (0.7, 0.2)}, "iso_range=(0.7, 0.2): expected LO < HI"),
    ("bake", {"texel_error": 0.02, "target_error": 0.05},
     "texel_error with target_error: a bake takes one of them"),
    ("render", {"view": "1,2,3,4"}, "view='1,2,3,4': expected AZ,EL[,DIST]"),
    ("load", {"downsample": 0}, "downsample=0: expected an integer factor"),
])
def test_errors_of_the_command_s_own_checks_name_the_keywords(function, keywords, message):
    """A value the command's code refuses after parsing (``isolume bake --seed …`` says
    ``--seed 4294967296: …``) is named as the function's keyword, as the values its
    parser refuses are."""
    source = "synthetic:sphere:16"
    with pytest.raises(IsolumeError) as raised:
        getattr(isolume, function)(source if function == "load" else isolume.load(source),
                                   **keywords)
    text = str(raised.value)
    assert text.startswith(message) and "--" not in text, text


def test_keyword_message_rewrites_only_the_command_s_options():
    from isolume._arguments import keyword_message

    assert keyword_message("bake", "--samples 5 with --target-error: expected at least 8") \
        == "samples 5 with target_error: expected at least 8"
    assert keyword_message("bake", "--max-samples 10 is below --samples 20") \
        == "max_samples 10 is below samples 20"
    assert keyword_message("render", "x.raw: pass --spacing X,Y,Z or --no-such") \
        == "x.raw: pass spacing X,Y,Z or --no-such"
    assert keyword_message("render", "--size '1x2x3': expected WxH") \
        == "size='1x2x3': expected WxH"


def test_a_second_render_keeps_the_context_and_the_surface():
    from isolume._calls import _SESSION

    volume = isolume.load("synthetic:sphere:24")
    first = isolume.render(volume, size=(32, 32), gl="osmesa", samples=4)
    kept = _SESSION.reuse
    context, mesh = kept.context("osmesa"), kept._mesh[1]
    second = isolume.render(volume, size=(32, 32), gl="osmesa", samples=4, view=(60, 10))
    assert kept.context("osmesa") is context and kept._mesh[1] is mesh
    assert not np.array_equal(first.srgb, second.srgb)
    isolume.render(volume, size=(32, 32), gl="osmesa", samples=4, iso=0.3)
    assert kept._mesh[1] is not mesh


def test_errors_are_the_commands_one_line_messages(tmp_path):
    volume = isolume.load("synthetic:sphere:16")
    with pytest.raises(IsolumeError, match=r"^size='0x5': width and height"):
        isolume.render(volume, size=(0, 5))
    with pytest.raises(IsolumeError, match=r"tonemap='sepia': expected one of"):
        isolume.render(volume, tonemap="sepia")
    with pytest.raises(IsolumeError, match=r"output must end in"):
        isolume.bake(volume, out=tmp_path / "x.txt")
    with pytest.raises(IsolumeError, match=r"nope\.raw"):
        isolume.load(tmp_path / "nope.raw")


BAD_VALUES = [
    ("render", {"iso": "abc"}, "iso='abc': invalid float value"),
    ("render", {"samples": 2.5}, "samples=2.5: invalid int value"),
    ("render", {"exposure": [1]}, "exposure=[1]: invalid float value"),
    ("render", {"no_auto_exposure": "yes"}, "no_auto_exposure='yes': expected True or False"),
    ("render", {"env": 5}, "env=5: expected a str"),
    ("render", {"light": 5}, "light=5: expected a spec or a list of specs"),
    ("render", {"light": ["dir:0,0,1:1,1,1", 5]}, "light=['dir:0,0,1:1,1,1', 5]: expected "
     "a spec or a list of specs"),
    ("render", {"lattice": 5}, "lattice=5: expected a Lattice or a path"),
    ("render", {"size": 512}, "size=512: expected a str or a sequence of numbers"),
    ("render", {"volume": None}, "volume=None: expected a file path, a "
     "'synthetic:NAME[:SIZE]' spec, a (Z, Y, X) numpy array or a Volume"),
    ("bake", {"samples": "many"}, "samples='many': invalid int value"),
    ("bake", {"iso_range": (70, "x")}, "iso_range=(70, 'x'): invalid float value"),
    ("bake", {"iso_range": "70,110"}, "iso_range='70,110': expected 2 values"),
    ("bake", {"max_samples": True}, "max_samples=True: invalid int value"),
    ("export", {"out": "x.ply", "bounces": "two"}, "bounces='two': invalid int value"),
    ("export", {"out": 5}, "out=5: expected a str"),
    ("movie", {"out": "m.mp4", "frames": "x"}, "frames='x': invalid int value"),
    ("movie", {"out": "m.mp4", "fps": "fast"}, "fps='fast': invalid float value"),
    ("reference", {"out": "r.exr", "spp": "x"}, "spp='x': invalid int value"),
    ("reference", {"out": "r.exr", "seed": 1.5}, "seed=1.5: invalid int value"),
    ("show", {"bake_samples": "x"}, "bake_samples='x': invalid int value"),
    ("load", {"source": [[[1, 2], [3, 4]], [[5, 6], [7, 8]]]},
     "source=[[[1, 2], [3, 4]], [[5, 6], [7, 8]]]: expected a file path, a "
     "'synthetic:NAME[:SIZE]' spec, a (Z, Y, X) numpy array or a Volume"),
    ("load", {"source": None}, "source=None: expected a file path"),
    ("load", {"source": "synthetic:sphere:16", "downsample": "x"},
     "downsample='x': invalid int value"),
    ("load", {"source": np.zeros((4, 4, 4), np.float32), "downsample": "x"},
     "downsample='x': invalid int value"),
    ("load", {"source": "synthetic:sphere:16", "level": 1.5}, "level=1.5: invalid int value"),
]
"""(function, keywords, the start of its message): values the command's parser refuses,
given to the functions (the volume, where the function takes one: a sphere)."""


@pytest.mark.parametrize(("function", "keywords", "message"), BAD_VALUES,
                         ids=[f"{f}-{m.split('=')[0]}" for f, _, m in BAD_VALUES])
def test_a_bad_value_is_an_isolume_error_naming_the_keyword(function, keywords, message,
                                                            tmp_path):
    """As ``isolume render --iso abc`` refuses its value in one line, so does
    ``isolume.render(v, iso="abc")``: an IsolumeError naming the keyword and the value,
    before any work (no ValueError, TypeError or silent default)."""
    arguments = dict(keywords)
    if function != "load":
        arguments.setdefault("volume", isolume.load("synthetic:sphere:16"))
    if isinstance(arguments.get("out"), str):
        arguments["out"] = tmp_path / arguments["out"]
    with pytest.raises(IsolumeError) as raised:
        getattr(isolume, function)(**arguments)
    text = str(raised.value)
    assert text.startswith(message) and "\n" not in text, text
    assert not list(tmp_path.iterdir())


def test_a_value_is_shown_on_one_short_line():
    volume = isolume.load("synthetic:sphere:16")
    with pytest.raises(IsolumeError, match=r"^iso=array\(\[\[1\., .*\.\.\.: invalid float "
                       r"value$") as raised:
        isolume.render(volume, iso=np.ones((30, 30)))
    assert len(str(raised.value)) < 120


def test_values_are_converted_as_their_options_parsers_convert_text():
    from isolume._arguments import namespace

    args = namespace("bake", {"samples": np.int64(8), "iso_range": (70, "110.5"),
                              "scale": "2", "flip_normals": True})
    assert args.samples == 8 and type(args.samples) is int
    assert args.iso_range == [70.0, 110.5] and args.scale == 2.0 and args.flip_normals
    args = namespace("render", {"iso": 90, "size": (256.0, 128), "light": "dir:0,0,1:1,1,1"})
    assert args.iso == 90.0 and args.size == "256x128" and args.light == ["dir:0,0,1:1,1,1"]
    assert namespace("render", {"iso": np.float32(0.3)}).iso == float(np.float32(0.3))


def test_load_takes_arrays_files_and_parts(tmp_path):
    z, y, x = np.mgrid[-1:1:20j, -1:1:24j, -1:1:28j]
    field = (x * x + y * y + z * z).astype(np.float32)
    volume = isolume.load(field, spacing=(0.5, 1, 2), origin=(1, 2, 3), name="ball")
    assert volume.spacing == (0.5, 1.0, 2.0) and volume.origin == (1.0, 2.0, 3.0)
    info = isolume.info(volume)
    assert info.dims == (28, 24, 20) and info.counts.sum() == field.size
    assert len(info.suggested) >= 1 and "suggested isovalues" in str(info)
    np.save(tmp_path / "f.npy", field)
    part = isolume.load(tmp_path / "f.npy", crop="0:20,:,:", downsample=2, up="-z")
    assert part.data.shape == (10, 12, 10)


def test_info_is_the_command_text(capsys):
    assert main(["info", "synthetic:torus:24"]) == 0
    assert capsys.readouterr().out.strip() == str(isolume.info("synthetic:torus:24"))


def test_picture_shows_in_a_notebook():
    from io import BytesIO

    from PIL import Image

    picture = isolume.render("synthetic:sphere:16", size=(40, 30), gl="osmesa", samples=4)
    shown = np.asarray(Image.open(BytesIO(picture._repr_png_())))
    assert np.array_equal(shown, picture.srgb)


def test_a_saved_view_renders_as_the_command_renders_it(tmp_path):
    from isolume.app.render.camera import Camera

    view = isolume.View(volume="synthetic:engine:32", iso=0.3, size="48x40",
                        camera=Camera(azimuth=80.0, elevation=20.0, distance=2.5),
                        tonemap="reinhard")
    path = view.save(tmp_path / "v.isolume.json")
    assert isolume.View.load(path) == view
    picture = isolume.render("synthetic:engine:32", state=path, gl="osmesa", samples=4,
                             size=(48, 40))
    assert main(["render", "--state", str(path), "--gl", "osmesa", "--samples", "4",
                 "--out", str(tmp_path / "s.png")]) == 0
    assert np.array_equal(picture.srgb, _png(tmp_path / "s.png"))


def test_an_interrupted_bake_returns_and_saves_its_finished_texels(tmp_path, monkeypatch):
    import importlib

    bake_module = importlib.import_module("isolume.baking.bake")

    calls = []

    def interrupt(self, committed):
        calls.append(len(committed))
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(bake_module.Checkpoints, "__call__", interrupt)
    volume = isolume.load("synthetic:engine:32")
    with pytest.warns(UserWarning, match="bake interrupted: .* finished texels returned; "
                      "saved in"):
        lattice = isolume.bake(volume, samples=4, out=tmp_path / "i.npz", workers=1)
    finished = int((lattice.samples > 0).sum())
    assert lattice.meta["interrupted"] and 0 < finished < lattice.meta["plan"]["active_texels"]
    saved = isolume.Lattice.load(tmp_path / "i.npz")
    assert int((saved.samples > 0).sum()) == finished
    monkeypatch.undo()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        whole = isolume.bake(volume, samples=4, out=tmp_path / "i.npz", workers=1)
    assert int((whole.samples > 0).sum()) == whole.meta["plan"]["active_texels"]


@pytest.mark.parametrize("module", ["isolume", "isolume.baking"])
def test_importing_the_api_loads_only_the_standard_library(module):
    """No moderngl, glfw, numba, numpy…: the names load when first used."""
    code = (f"import sys; before = set(sys.modules); import {module}; "
            "print(' '.join(sorted({m.split('.')[0] for m in set(sys.modules) - before})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert "isolume" in out
    assert [m for m in out if m not in sys.stdlib_module_names
            and m != "isolume" and not m.startswith("__editable__")] == [], out


def test_one_identity_per_module_in_the_editable_install():
    code = ("import importlib, sys, isolume, isolume.app.cli, isolume.app.commands\n"
            "try:\n    importlib.import_module('isolume.app.api')\n"
            "except ImportError as e:\n    print('refused', e)\n"
            "files = [m.__file__ for n, m in sys.modules.items() "
            "if n.startswith('isolume') and getattr(m, '__file__', None)]\n"
            "print(len(files) == len(set(files)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert "refused isolume.app.api: import isolume instead" in out and "True" in out


def test_every_public_name_resolves():
    """Each name of ``isolume.__all__`` (docs/python.md's table) is there when asked for,
    the widget class included."""
    code = ("import isolume\n"
            "print(all(getattr(isolume, n) is not None for n in isolume.__all__))\n"
            "print(isolume.NotebookView.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["True", "NotebookView"]


def test_nothing_under_app_baking_or_volumes_imports_the_api():
    subpackages = {"app", "baking", "volumes", "shaders"}
    for folder in ("app", "baking", "volumes", "shaders"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.is_relative_to(ROOT / "app" / "api"):
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    assert all(a.name != "isolume" and not a.name.startswith("isolume._")
                               for a in node.names), path
                if isinstance(node, ast.ImportFrom) and node.module == "isolume":
                    assert {a.name for a in node.names} <= subpackages, path


PACKAGE_SHARE = 0.95
"""The least share of the package's symbols whose types pyright knows."""
UNTYPED_BASES = {
    "isolume.NotebookView": "a jupyter_rfb widget: ipywidgets ships no types, so pyright "
                            "knows no ipywidgets widget's base class",
    "isolume.show": "returns a NotebookView",
}
"""Reviewed symbols of the public API whose types pyright cannot know, and why."""


@pytest.mark.slow
def test_the_package_and_its_public_api_are_typed(tmp_path):
    import json
    import os
    import shutil

    from layout import make_layout

    if shutil.which("pyright") is None:
        pytest.skip("pyright is not installed")
    env = dict(os.environ, PYTHONPATH=str(make_layout(tmp_path)))  # pyright follows no
    run = subprocess.run(["pyright", "--verifytypes", "isolume", "--ignoreexternal",  # finder
                          "--outputjson"], capture_output=True, text=True, timeout=600,
                         env=env, cwd=tmp_path)
    if not run.stdout.strip().startswith("{"):
        pytest.skip(f"pyright could not run here: {run.stderr.strip()[:200]}")
    report = json.loads(run.stdout)["typeCompleteness"]
    public = [s for s in report["symbols"] if s["name"].count(".") == 1
              or s["name"].split(".")[1] in ("_calls", "_picture")]
    unknown = sorted(s["name"] for s in public if not s["isTypeKnown"])
    print(f"pyright --verifytypes isolume: {report['completenessScore']:.1%} of the package; "
          f"public API: {len(public) - len(unknown)} of {len(public)} symbols known")
    assert report["completenessScore"] >= PACKAGE_SHARE
    assert len(public) >= 30 and set(unknown) <= set(UNTYPED_BASES), unknown


@pytest.mark.slow
def test_export_movie_and_reference_write_what_the_commands_write(tmp_path):
    volume = isolume.load("synthetic:torus:24")
    common = ["synthetic:torus:24", "--samples", "4"]
    assert isolume.export(volume, tmp_path / "a.ply", samples=4) == tmp_path / "a.ply"
    assert main(["export", *common, "--out", str(tmp_path / "b.ply")]) == 0
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    isolume.movie(volume, tmp_path / "a", frames=2, size=(32, 32), samples=4, gl="osmesa")
    assert main(["movie", *common, "--frames", "2", "--size", "32x32", "--gl", "osmesa",
                 "--out", str(tmp_path / "b") + "/"]) == 0
    frames = sorted(p.name for p in (tmp_path / "a").glob("*.png"))
    assert len(frames) == 2 and frames == sorted(p.name for p in (tmp_path / "b").glob("*.png"))
    for name in frames:
        assert np.array_equal(_png(tmp_path / "a" / name), _png(tmp_path / "b" / name))
    isolume.reference(volume, tmp_path / "a.exr", spp=2, size=(24, 24), workers=1)
    assert main(["reference", "synthetic:torus:24", "--spp", "2", "--size", "24x24",
                 "--workers", "1", "--out", str(tmp_path / "b.exr")]) == 0
    assert np.array_equal(read_exr(tmp_path / "a.exr")["RGB"], read_exr(tmp_path / "b.exr")["RGB"])
