"""Saved views (``--state FILE``): the file round-trips, ``render``, ``movie`` and ``view``
start from it, options given on the command line win, the viewer's "save view" writes a
state that reproduces its picture, and bad files end in one line."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_viewer import _view, display  # noqa: F401 (display: the Xvfb fixture)

from isolume import volumes
from isolume.app.cli import main
from isolume.app.render.camera import Camera
from isolume.app.render.renderer import framed_camera
from isolume.app.state import (
    FORMAT,
    VERSION,
    SavedView,
    given_options,
    layout,
    load_state,
    picture_beside,
)

VOLUME = "synthetic:sphere:24"
LOOK = ["--shading", "lambert", "--size", "64x64", "--gl", "osmesa"]
"""Fast pictures: local shading (no bake, no traced light), 64 × 64, OSMesa."""


def _saved(**changes) -> SavedView:
    """A state of `VOLUME` with the camera ``render --view 40,20,2`` uses."""
    camera = framed_camera(volumes.load(VOLUME), 0.45, (40.0, 20.0, 2.0))
    saved = SavedView(volume=VOLUME, iso=0.45, camera=camera, size="64x64", shading="lambert",
                      exposure=1.3, auto_exposure=True, tonemap="reinhard",
                      albedo="0.6,0.7,0.8")
    return replace(saved, **changes)


EXPLICIT = [VOLUME, "--iso", "0.45", "--view", "40.0,20.0,2.0", "--size", "64x64",
            "--shading", "lambert", "--exposure", "1.3", "--tonemap", "reinhard",
            "--albedo", "0.6,0.7,0.8", "--gl", "osmesa"]
"""The options that say what `_saved()` says."""


def _render(capsys, *argv) -> bytes:
    """The PNG bytes ``isolume render ARGV`` writes (to its ``--out``)."""
    assert main(["render", *argv]) == 0, capsys.readouterr().err
    out = Path(argv[argv.index("--out") + 1])
    return out.read_bytes()


def _pixels(path) -> np.ndarray:
    return np.asarray(Image.open(path), np.int16)


# -- the file -------------------------------------------------------------------------------
def test_a_state_round_trips_through_its_file(tmp_path):
    saved = _saved(volume=str(tmp_path / "ct.raw"), dims="64,64,32", dtype="uint16",
                   spacing="1,1,2.5", up="-z", crop=":,:,0:9", downsample=2, level=0,
                   camera=Camera(12.5, -30.0, 0.7, (1.0, 2.0, 3.0), 4.5, 25.0, (0.1, -0.2)),
                   env="sky:sun=6,sun_az=10,sun_el=40", lights=("dir:1,0,1:2,2,2",),
                   light_angles=(200.0, -35.5), lattice=str(tmp_path / "ct.npz"),
                   normals="gradient", flip_normals=True, auto_exposure=False)
    path = saved.save(tmp_path / "v.view.json")
    assert load_state(path) == saved
    data = json.loads(path.read_text())
    assert list(data)[:2] == ["format", "version"] and data["format"] == FORMAT
    assert data["version"] == VERSION and data["camera"]["pan"] == [0.1, -0.2]
    assert '"target": [1.0, 2.0, 3.0]' in path.read_text()  # short lists on one line
    # a hand-written state: relative paths are the file's folder's, absent fields None
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "h.json").write_text(layout(
        {"format": FORMAT, "version": 1, "volume": "data/ct.raw", "lattice": "ct.npz"}))
    hand = load_state(tmp_path / "sub" / "h.json")
    assert hand == SavedView(volume=str(tmp_path / "sub" / "data" / "ct.raw"),
                             lattice=str(tmp_path / "sub" / "ct.npz"))
    assert picture_beside(tmp_path / "v.view.json", "30x20") == tmp_path / "v-30x20.png"


@pytest.mark.parametrize(
    ("words", "given"),
    [
        (["--tonemap", "aces", "--view=1,2", "--no-auto"],
         {"tonemap", "view", "no_auto_exposure"}),  # defaults, = and prefixes count
        (["x.raw", "--light", "dir:1,0,0:1,1,1", "--crop", ":,:,0:9"],
         {"volume", "light", "volume_crop"}),  # positional, append, own dest
        ([], set()),
    ],
)
def test_options_on_the_command_line_are_told_from_defaults(words, given):
    from isolume.app.cli import build_parser

    words = ["--state", "v.view.json", "--out", "x.png", *words]
    args = build_parser().parse_args(["render", *words])
    assert given_options(args, words) == given | {"state", "out"}


def test_the_viewer_keeps_the_volume_as_named_and_starts_from_a_state(tmp_path,
                                                                       monkeypatch):
    from dataclasses import asdict

    from isolume.app.cli import build_parser
    from isolume.app.state import VolumeSource, apply_state

    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["view", "ct.raw", "--dims", "4,5,6", "--dtype", "uint8",
                                      "--origin", "1,2,3", "--up=-z", "--crop", ":,:,0:3",
                                      "--downsample", "2"])
    source = VolumeSource.from_args(args)
    assert source == VolumeSource(str(tmp_path / "ct.raw"), "4,5,6", "uint8", None, "1,2,3",
                                  "-z", ":,:,0:3", 2, None)
    (tmp_path / "ct.raw").write_bytes(bytes(120))
    path = _saved(**asdict(source), env="sky:sun=6,sun_az=10,sun_el=40",
                  light_angles=(10.0, 40.0), auto_exposure=False).save("v.view.json")
    words = ["--state", str(path), "--size", "200x100"]
    args = apply_state(build_parser().parse_args(["view", *words]), words)
    assert (args.volume, args.volume_crop, args.volume_downsample, args.up, args.origin) == (
        str(tmp_path / "ct.raw"), ":,:,0:3", 2, "-z", "1,2,3")
    assert args.bake_env == "sky:sun=6,sun_az=10,sun_el=40" and args.no_auto_exposure
    assert args.camera == _saved().camera and args.light_angles == (10.0, 40.0)
    assert args.size == "200x100" and args.iso == 0.45 and args.shading == "lambert"


# -- render and movie from a state ----------------------------------------------------------
def test_render_from_a_state_equals_render_with_the_same_options(tmp_path, capsys):
    state = _saved().save(tmp_path / "v.view.json")
    explicit = _render(capsys, *EXPLICIT, "--out", str(tmp_path / "explicit.png"))
    assert main(["render", "--state", str(state)]) == 0  # written beside the state
    assert (tmp_path / "v-64x64.png").read_bytes() == explicit
    # the state's camera is used whole: another target moves the picture
    moved = _saved(camera=replace(_saved().camera, target=(0.2, 0.0, 0.0)))
    moved.save(tmp_path / "m.view.json")
    assert _render(capsys, "--state", str(tmp_path / "m.view.json"),
                   "--out", str(tmp_path / "m.png")) != explicit


def test_options_given_win_over_the_state(tmp_path, capsys):
    state = str(_saved().save(tmp_path / "v.view.json"))
    # --tonemap aces is the option's default: given, it still wins over reinhard
    changed = ["--tonemap", "aces", "--size", "48x40", "--exposure", "0.9"]
    got = _render(capsys, "--state", state, *changed, "--view", "10,5",
                  "--out", str(tmp_path / "s.png"))
    # --view turns the saved camera; without a distance it keeps the saved one
    want = _render(capsys, *EXPLICIT, *changed, "--view", "10,5,2",
                   "--out", str(tmp_path / "e.png"))
    assert got == want
    assert _pixels(tmp_path / "s.png").shape == (40, 48, 3)
    assert got != _render(capsys, *EXPLICIT, "--out", str(tmp_path / "plain.png"))


def test_a_turned_light_turns_the_key_light(tmp_path, capsys):
    from isolume.app.render.offscreen import render_volume
    from isolume.app.render.settings import RenderSettings
    from isolume.app.viewer.panel import direction_from_angles

    state = _saved(light_angles=(250.0, 10.0), auto_exposure=False).save(tmp_path / "l.json")
    _render(capsys, "--state", str(state), "--out", str(tmp_path / "l.png"))
    vol = volumes.load(VOLUME)
    settings = RenderSettings(size=(64, 64), shading="lambert", exposure=1.3,
                              tonemap="reinhard", albedo=(0.6, 0.7, 0.8),
                              key_dir=tuple(direction_from_angles(250.0, 10.0)))
    frame, _ = render_volume(vol, 0.45, settings, view=(40.0, 20.0, 2.0), backend="osmesa")
    np.testing.assert_array_equal(_pixels(tmp_path / "l.png"), frame.srgb)
    plain = _render(capsys, *EXPLICIT, "--no-auto-exposure", "--out", str(tmp_path / "p.png"))
    assert plain != (tmp_path / "l.png").read_bytes()


def test_a_movie_from_a_state_starts_at_its_picture(tmp_path, capsys):
    camera = replace(_saved().camera, target=(0.1, -0.05, 0.0), pan=(0.15, 0.05))
    state = str(_saved(camera=camera, auto_exposure=False).save(tmp_path / "v.view.json"))
    assert main(["movie", "--state", state, "--frames", "3", "--gl", "osmesa",
                 "--out", str(tmp_path / "frames") + "/"]) == 0, capsys.readouterr().err
    picture = _render(capsys, "--state", state, "--out", str(tmp_path / "r.png"))
    first = _pixels(tmp_path / "frames" / "frame_0000.png")
    np.testing.assert_array_equal(first, _pixels(tmp_path / "r.png"))
    assert first.shape == (64, 64, 3) and len(picture) > 0
    assert not np.array_equal(first, _pixels(tmp_path / "frames" / "frame_0001.png"))


# -- errors ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, "no such file"),
        ('{"format": "isolume view", "version": 1,', "not JSON"),
        ('{"format": "isolume view", "version": 2}', "state version 2 is newer than this"),
        ('{"format": "isolume view", "version": 0}', "version 0: expected a whole number"),
        ('{"version": 1}', "not an isolume view state"),
        ('{"format": "isolume view", "version": 1, "zoom": 2}', "unknown field(s) zoom"),
        ('{"format": "isolume view", "version": 1, "iso": "high"}', "iso \"high\": expected"),
        ('{"format": "isolume view", "version": 1, "shading": "toon"}',
         "shading \"toon\": expected one of lambert"),
        ('{"format": "isolume view", "version": 1, "camera": {"azimuth": 1}}',
         "missing elevation, distance, target, scale"),
        ('{"format": "isolume view", "version": 1, "volume": "gone/ct.raw"}',
         "ct.raw no longer exists"),
    ],
)
@pytest.mark.parametrize("command", ["render", "movie", "view"])
def test_bad_states_end_in_one_line_naming_the_file(tmp_path, capsys, monkeypatch, command,
                                                    text, message):
    monkeypatch.delenv("DISPLAY", raising=False)  # never a window
    path = tmp_path / "bad.view.json"
    if text is not None:
        path.write_text(text)
    extra = {"render": ["--out", str(tmp_path / "x.png")],
             "movie": ["--out", str(tmp_path / "x.mp4")], "view": []}[command]
    assert main([command, "--state", str(path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"isolume: error: --state {path}: ") and err.count("\n") == 1
    assert message in err and "Traceback" not in err


# -- the viewer -----------------------------------------------------------------------------
SCRIPT = """
wait-mesh
orbit 40 10
zoom 1.3
pan 0.05 0.02
light 60 40
exposure 1.5
screenshot shot.png
save-view saved.view.json
quit
"""


def test_the_viewers_saved_view_renders_as_it_showed(display, tmp_path, capsys):  # noqa: F811
    """The viewer's "save view" (its script command) writes what is on screen; ``render
    --state`` draws the same picture (the exposure the window showed), and ``view
    --state`` shows it again."""
    (tmp_path / "s.txt").write_text(SCRIPT)
    run = _view([VOLUME, "--shading", "lambert", "--no-bake", "--size", "320x240",
                 "--script", "s.txt"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    assert "saved the view in saved.view.json" in run.stdout
    saved = load_state(tmp_path / "saved.view.json")
    assert saved.volume == VOLUME and saved.shading == "lambert" and saved.exposure == 1.5
    assert saved.light_angles == (60.0, 40.0) and saved.auto_exposure is True
    assert saved.shown_exposure is not None and saved.shown_exposure != 1.5
    assert saved.camera.pan != (0.0, 0.0)  # framed beside the panel, then panned
    shot = _pixels(tmp_path / "shot.png")
    _render(capsys, "--state", str(tmp_path / "saved.view.json"), "--gl", "osmesa",
            "--out", str(tmp_path / "r.png"))
    rendered = _pixels(tmp_path / "r.png")
    assert rendered.shape == shot.shape == (240, 320, 3)
    assert np.abs(rendered - shot).max() <= 1
    # the default view of the same options is another picture
    _render(capsys, VOLUME, "--shading", "lambert", "--no-auto-exposure", "--exposure", "1.5",
            "--size", "320x240", "--gl", "osmesa", "--out", str(tmp_path / "d.png"))
    assert np.abs(_pixels(tmp_path / "d.png") - shot).mean() > 5
    # reopened (the viewer meters its exposure again: given the one shown, to compare)
    again = _view(["--state", "saved.view.json", "--frames", "1", "--screenshot", "again.png",
                   "--no-auto-exposure", "--exposure", repr(saved.shown_exposure)],
                  display, tmp_path)
    assert again.returncode == 0, again.stderr
    assert np.abs(_pixels(tmp_path / "again.png") - shot).max() <= 1
