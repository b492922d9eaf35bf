"""``isolume movie``: turntables, light orbits and isovalue sweeps drawn with one fixed
exposure, each frame the picture ``isolume render`` draws for its shot at that exposure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from isolume import volumes
from isolume.app.cli import main
from isolume.app.movie_stage import make_shots, metered_shots, turn_steps
from isolume.baking import bake
from isolume.baking.config import DEFAULT_ENV, BakeConfig

GL = ("--gl", "osmesa")
SIZE = ("--size", "64x64")
SWEEP = (0.4, 0.6)
"""The iso range of the test lattices (the sphere's surface sits at 0.5)."""


def _run(capsys, *argv):
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def _movie(capsys, *argv):
    """Run ``isolume movie`` with `argv` on OSMesa; fails the test on an error."""
    status, out, err = _run(capsys, "movie", *GL, *argv)
    assert status == 0, err
    return out, err


def _frames(folder):
    """[(H, W, 3) uint8 pixels, text chunks] of the PNG frames in `folder`, in order."""
    frames = []
    for path in sorted(folder.glob("frame_*.png")):
        with Image.open(path) as image:
            frames.append((np.asarray(image.convert("RGB")), dict(image.text)))
    return frames


def _render(capsys, tmp_path, *argv):
    """(H, W, 3) uint8 pixels of ``isolume render`` with `argv`."""
    out = tmp_path / "render.png"
    status, _, err = _run(capsys, "render", *GL, *argv, "--out", out)
    assert status == 0, err
    return np.asarray(Image.open(out).convert("RGB"))


def _state_of(tmp_path, text):
    """A state file holding only the camera of a frame (its ``camera`` text)."""
    from isolume.app.render.camera import Camera
    from isolume.app.state import SavedView

    values = json.loads(text["camera"])
    camera = Camera(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    return str(SavedView(camera=camera).save(tmp_path / "frame.view.json"))


def _exposure_of(frames) -> str:
    """The one exposure every frame was drawn with (as the frames store it)."""
    exposures = {text["exposure"] for _, text in frames}
    assert len(exposures) == 1, exposures
    return exposures.pop()


@pytest.fixture(scope="module")
def lattices(tmp_path_factory):
    """{"irradiance", "sh"}: small lattices of the sphere baked for `SWEEP` under the sky
    and sun of `DEFAULT_ENV`, the irradiance one with its sun left to the pixels."""
    folder = tmp_path_factory.mktemp("lattices")
    vol = volumes.load("synthetic:sphere:24")
    paths = {}
    for mode in ("irradiance", "sh"):
        config = BakeConfig(mode=mode, sh_order=3, samples=4, bounces=1, iso_range=SWEEP,
                            env=DEFAULT_ENV, max_levels=4)
        paths[mode] = folder / f"{mode}.npz"
        bake(vol, config, out=paths[mode], workers=2)
    return paths


# -- the shots ------------------------------------------------------------------------------
def test_a_whole_turn_loops_and_a_part_ends_on_its_angle():
    assert turn_steps(4, 360) == [0, 90, 180, 270]
    assert turn_steps(3, -720) == [0, -240, -480]
    assert turn_steps(3, 90) == [0, 45, 90]
    assert turn_steps(1, 360) == [0]


def test_shots_change_one_thing_each():
    spin = make_shots("turntable", 4, 30.0, 0.5, 360.0)
    assert [s.azimuth for s in spin] == [30, 120, 210, 300]
    assert {(s.iso, s.turn) for s in spin} == {(0.5, 0.0)}
    orbit = make_shots("light", 3, 30.0, 0.5, 90.0)
    assert [s.turn for s in orbit] == [0, 45, 90] and {s.azimuth for s in orbit} == {30}
    sweep = make_shots("iso", 5, 30.0, 0.5, 360.0, (0.4, 0.6))
    assert [s.iso for s in sweep] == pytest.approx([0.4, 0.45, 0.5, 0.55, 0.6])
    assert sweep[0].iso == 0.4 and sweep[-1].iso == 0.6
    assert [s.index for s in metered_shots(sweep, 3)] == [0, 2, 4]
    assert [s.index for s in metered_shots(sweep, 1)] == [0]


# -- turntable ------------------------------------------------------------------------------
def test_turntable_frames_differ_and_repeat_to_the_byte(tmp_path, capsys):
    runs = []
    for name in ("a", "b"):
        out, _ = _movie(capsys, "synthetic:engine:32", *SIZE, "--frames", 4,
                        "--turntable-light", "world", "--out", f"{tmp_path / name}/")
        assert "4 frames 64x64" in out
        runs.append(sorted((tmp_path / name).glob("frame_*.png")))
    assert [p.name for p in runs[0]] == [f"frame_000{i}.png" for i in range(4)]
    for a, b in zip(*runs, strict=True):
        assert a.read_bytes() == b.read_bytes()
    frames = _frames(tmp_path / "a")
    for i in range(4):
        for j in range(i):
            assert np.abs(frames[i][0].astype(int) - frames[j][0]).mean() > 1, (i, j)
    _exposure_of(frames)
    assert [text["azimuth"] for _, text in frames] == ["30.0", "120.0", "210.0", "300.0"]


def test_turntable_frame_is_the_render_at_its_azimuth_and_exposure(tmp_path, capsys):
    _movie(capsys, "synthetic:sphere:24", *SIZE, "--frames", 4, "--view", "10,20",
           "--turntable-light", "world", "--out", f"{tmp_path / 'spin'}/")
    frames = _frames(tmp_path / "spin")
    exposure = _exposure_of(frames)
    for pixels, text in frames[1:3]:
        picture = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--no-auto-exposure",
                          "--exposure", exposure, "--state", _state_of(tmp_path, text))
        np.testing.assert_array_equal(pixels, picture)
    # one distance frames the surface from every azimuth: no zooming
    cameras = [json.loads(text["camera"]) for _, text in frames]
    assert len({(c["distance"], tuple(c["target"]), tuple(c["pan"])) for c in cameras}) == 1
    assert [c["azimuth"] for c in cameras] == [10.0, 100.0, 190.0, 280.0]


def test_a_turntable_turns_the_light_with_the_camera(tmp_path, capsys):
    """On a real turntable the object turns under the lamps: a sphere under the default
    sky and sun, its light traced per frame, looks the same in every frame (mean
    brightness within 1 %; measured 0.05 % at 128²), while a camera circling under a
    light that stays put sees its lit and its shadowed side (measured 16 %). The first
    frame is the plain render. (The local modes' key light is placed from the camera in
    either case.)"""
    shading = "irradiance"
    means = {}
    for light in ("camera", "world"):
        folder = tmp_path / light
        _movie(capsys, "synthetic:sphere:24", *SIZE, "--frames", 6, "--shading", shading,
               "--turntable-light", light, "--out", f"{folder}/")
        frames = _frames(folder)
        means[light] = np.array([pixels.astype(float).mean() for pixels, _ in frames])
        if light == "camera":
            first = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--shading",
                            shading, "--no-auto-exposure", "--exposure",
                            _exposure_of(frames), "--state", _state_of(tmp_path, frames[0][1]))
            np.testing.assert_array_equal(frames[0][0], first)
    spread = {k: np.ptp(v) / v.mean() for k, v in means.items()}
    assert spread["camera"] < 0.01 < 0.05 < spread["world"], spread


def test_a_light_that_cannot_turn_stays_put_unless_asked(tmp_path, capsys):
    """A lattice that holds all its light cannot turn it: the turntable says so and keeps
    the light in place; asked for with --turntable-light camera, it is a one-line error."""
    lattice = tmp_path / "all.npz"
    bake(volumes.load("synthetic:sphere:24"), BakeConfig(samples=2, bounces=0, env="sky:sun=3",
                                        direct_light="lattice", iso_range=(0.4, 0.6)),
         workers=2).save(lattice)
    _, err = _movie(capsys, "synthetic:sphere:24", *SIZE, "--frames", 2, "--lattice",
                    lattice, "--out", f"{tmp_path / 'put'}/")
    assert "the light stays put" in err
    status, _, err = _run(capsys, "movie", *GL, "synthetic:sphere:24", *SIZE, "--frames", 2,
                          "--lattice", lattice, "--turntable-light", "camera", "--out",
                          f"{tmp_path / 'no'}/")
    assert status == 2 and err.count("\n") == 1 and "--turntable-light camera" in err, err


def test_exposure_is_metered_once_for_the_movie(tmp_path, capsys):
    """The metered exposure is not any one frame's own: a frame rendered with automatic
    exposure at its azimuth differs from the movie's frame."""
    _movie(capsys, "synthetic:engine:32", *SIZE, "--frames", 4, "--out",
           f"{tmp_path / 'spin'}/")
    frames = _frames(tmp_path / "spin")
    exposure = float(_exposure_of(frames))
    status, out, err = _run(capsys, "render", *GL, "synthetic:engine:32", *SIZE, "--view",
                            f"{frames[1][1]['azimuth']},30", "--out", tmp_path / "auto.png")
    assert status == 0, err
    own = float(out.rsplit("exposure ", 1)[1].rstrip(")\n"))
    assert abs(own / exposure - 1) > 0.01


def test_no_auto_exposure_keeps_the_given_exposure(tmp_path, capsys):
    _movie(capsys, "synthetic:sphere:24", *SIZE, "--frames", 2, "--no-auto-exposure",
           "--exposure", "0.3", "--out", f"{tmp_path / 'fixed'}/")
    assert _exposure_of(_frames(tmp_path / "fixed")) == "0.3"


# -- isovalue sweep -------------------------------------------------------------------------
def test_sweep_frames_are_the_lattice_renders_at_their_isovalues(tmp_path, capsys, lattices):
    lattice = lattices["irradiance"]
    out, _ = _movie(capsys, "synthetic:sphere:24", *SIZE, "--kind", "iso", "--frames", 3,
                    "--lattice", lattice, "--out", f"{tmp_path / 'sweep'}/")
    assert "isovalues 0.4 to 0.6" in out  # the range the lattice serves
    frames = _frames(tmp_path / "sweep")
    assert [float(text["isovalue"]) for _, text in frames] == [0.4, 0.5, 0.6]
    exposure = _exposure_of(frames)
    for pixels, text in frames:
        picture = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--lattice", lattice,
                          "--iso", text["isovalue"], "--no-auto-exposure", "--exposure",
                          exposure, "--state", _state_of(tmp_path, text))
        assert np.abs(pixels.astype(int) - picture).max() <= 1
    # one camera frames every frame's sphere
    assert len({text["camera"] for _, text in frames}) == 1
    sizes = [(pixels != pixels[0, 0]).any(axis=2).sum() for pixels, _ in frames]
    assert sizes[0] > sizes[1] > sizes[2]  # a lower isovalue: a larger sphere


def test_sweep_without_lattice_bakes_one_for_its_range(tmp_path, capsys):
    kept = tmp_path / "kept.npz"
    _, err = _movie(capsys, "synthetic:sphere:24", *SIZE, "--kind", "iso", "--frames", 2,
                    "--iso-range", 0.45, 0.55, "--samples", 4, "--save-lattice", kept,
                    "--out", f"{tmp_path / 'sweep'}/")
    assert "baking one for isovalues 0.45 to 0.55" in err and kept.exists()
    frames = _frames(tmp_path / "sweep")
    pixels, text = frames[1]
    assert text["isovalue"] == "0.55"
    picture = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--lattice", kept,
                      "--iso", "0.55", "--no-auto-exposure", "--exposure", text["exposure"],
                      "--state", _state_of(tmp_path, text))
    assert np.abs(pixels.astype(int) - picture).max() <= 1


# -- light orbit ----------------------------------------------------------------------------
def test_light_orbit_without_lattice_traces_each_frame_under_the_turned_sun(tmp_path,
                                                                            capsys):
    _movie(capsys, "synthetic:engine:32", *SIZE, "--kind", "light", "--frames", 4,
           "--out", f"{tmp_path / 'orbit'}/")
    frames = _frames(tmp_path / "orbit")
    exposure = _exposure_of(frames)
    # DEFAULT_ENV's sun at azimuth -150 turned by 90 and 180 degrees
    for (pixels, text), sun_az in zip(frames[1:3], (-60, 30), strict=True):
        assert text["light turn"] == repr(90.0 * int(text["frame"]))
        picture = _render(capsys, tmp_path, "synthetic:engine:32", *SIZE, "--env",
                          f"sky:sun=6,sun_az={sun_az},sun_el=40", "--no-auto-exposure",
                          "--exposure", exposure)
        np.testing.assert_array_equal(pixels, picture)


def test_light_orbit_turns_an_sh_lattice_environment(tmp_path, capsys, lattices):
    lattice = lattices["sh"]
    _movie(capsys, "synthetic:sphere:24", *SIZE, "--kind", "light", "--frames", 3,
           "--degrees", 90, "--env-rotation", "10,0", "--lattice", lattice,
           "--out", f"{tmp_path / 'orbit'}/")
    frames = _frames(tmp_path / "orbit")
    exposure = _exposure_of(frames)
    assert [text["light turn"] for _, text in frames] == ["0.0", "45.0", "90.0"]
    for pixels, text in frames:
        rotation = 10 + float(text["light turn"])
        picture = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--lattice",
                          lattice, "--env-rotation", f"{rotation},0", "--no-auto-exposure",
                          "--exposure", exposure)
        assert np.abs(pixels.astype(int) - picture).max() <= 1
    assert np.abs(frames[0][0].astype(int) - frames[2][0]).mean() > 0.5


def test_light_orbit_turns_an_irradiance_lattice_sun_per_pixel(tmp_path, capsys, lattices):
    lattice = lattices["irradiance"]
    _, err = _movie(capsys, "synthetic:sphere:24", *SIZE, "--kind", "light", "--frames", 2,
                    "--degrees", 180, "--lattice", lattice, "--iso", 0.5,
                    "--out", f"{tmp_path / 'orbit'}/")
    assert "bounces" in err
    frames = _frames(tmp_path / "orbit")
    first = _render(capsys, tmp_path, "synthetic:sphere:24", *SIZE, "--lattice", lattice,
                    "--iso", 0.5, "--no-auto-exposure", "--exposure", _exposure_of(frames))
    np.testing.assert_array_equal(frames[0][0], first)
    assert np.abs(frames[0][0].astype(int) - frames[1][0]).mean() > 1  # the sun moved


def test_light_orbit_turns_the_key_light_of_a_local_mode(tmp_path, capsys):
    _movie(capsys, "synthetic:engine:32", *SIZE, "--kind", "light", "--frames", 3,
           "--shading", "lambert_shadow", "--out", f"{tmp_path / 'orbit'}/")
    frames = _frames(tmp_path / "orbit")
    first = _render(capsys, tmp_path, "synthetic:engine:32", *SIZE, "--shading",
                    "lambert_shadow", "--no-auto-exposure", "--exposure", _exposure_of(frames))
    assert np.abs(frames[0][0].astype(int) - first).max() <= 1
    assert np.abs(frames[0][0].astype(int) - frames[1][0]).mean() > 1


# -- MP4 ------------------------------------------------------------------------------------
def test_mp4_holds_every_frame(tmp_path, capsys):
    import imageio_ffmpeg

    movie = tmp_path / "spin.mp4"
    _movie(capsys, "synthetic:engine:32", "--size", "64x48", "--frames", 5, "--fps", 10,
           "--crf", 0, "--out", movie)
    _movie(capsys, "synthetic:engine:32", "--size", "64x48", "--frames", 5,
           "--out", f"{tmp_path / 'png'}/")
    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(movie))
    assert frames == 5 and seconds == pytest.approx(0.5, abs=0.05)
    reader = imageio_ffmpeg.read_frames(str(movie))
    meta = next(reader)
    assert tuple(meta["size"]) == (64, 48)
    decoded = np.frombuffer(next(reader), np.uint8).reshape(48, 64, 3)
    reader.close()
    png = _frames(tmp_path / "png")[0][0]
    assert np.abs(decoded.astype(int) - png).mean() < 4  # yuv420p: colour per 2×2 block


@pytest.mark.parametrize("stop_at", [3, 0])
def test_a_stopped_movie_keeps_its_frames_and_says_so(tmp_path, capsys, monkeypatch, stop_at):
    """A Ctrl-C while the frames are drawn closes the MP4 with the frames written (a
    playable file of those) and says how many; an MP4 of none is not kept."""
    import imageio_ffmpeg

    from isolume.app.movie_output import Mp4Frames

    written = Mp4Frames.write

    def write(frames, index, srgb, text):
        if index == stop_at:
            raise KeyboardInterrupt
        written(frames, index, srgb, text)

    monkeypatch.setattr(Mp4Frames, "write", write)
    out = tmp_path / "stopped.mp4"
    assert main(["movie", "synthetic:engine:32", "--size", "64x48", "--frames", "8",
                 "--out", str(out)]) == 130
    err = capsys.readouterr().err
    if stop_at:
        assert "stopped after 3 of 8 frames; " in err and f"{out} holds them" in err
        assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 3
    else:
        assert "stopped before the first frame" in err and not out.exists()


# -- one-line errors ------------------------------------------------------------------------
def _a_file(folder: Path) -> Path:
    """A file `folder`/taken, written."""
    (folder / "taken").write_text("")
    return folder / "taken"


@pytest.mark.parametrize(
    ("make_args", "expected"),
    [
        (lambda t: ["--size", "63x64", "--out", t / "x.mp4"], "even width and height"),
        (lambda t: ["--out", t / "x.gif"], "expected FILE.mp4 or a folder"),
        (lambda t: ["--out", t / "missing" / "x.mp4"], "does not exist"),
        (lambda t: ["--out", f"{t / 'missing' / 'frames'}/"], "does not exist"),
        (lambda t: ["--out", f"{_a_file(t)}/"], "is a file, not a folder"),
        (lambda t: ["--frames", "0", "--out", f"{t}/"], "--frames 0"),
        (lambda t: ["--fps", "0", "--out", f"{t}/"], "--fps 0"),
        (lambda t: ["--crf", "60", "--out", t / "x.mp4"], "--crf 60"),
        (lambda t: ["--degrees", "inf", "--out", f"{t}/"], "--degrees"),
        (lambda t: ["--iso-range", "0.4", "0.6", "--out", f"{t}/"], "only for --kind iso"),
        (lambda t: ["--kind", "iso", "--iso-range", "0.6", "0.4", "--out", f"{t}/"],
         "LO < HI"),
        (lambda t: ["--kind", "iso", "--iso-range", "0.4", "7", "--out", f"{t}/"],
         "outside the data range"),
        (lambda t: ["--save-lattice", t / "l.npz", "--out", f"{t}/"], "--save-lattice"),
        (lambda t: ["--kind", "iso", "--save-lattice", t / "l.txt", "--out", f"{t}/"],
         "must end in .npz"),
        (lambda t: ["--kind", "light", "--env", "constant:1,1,1", "--out", f"{t}/"],
         "has neither"),
        (lambda t: ["--view", "1,2,3,4", "--out", f"{t}/"], "AZ,EL"),
    ],
)
def test_bad_input_gives_one_line_and_status_2(tmp_path, capsys, make_args, expected):
    status, _, err = _run(capsys, "movie", "synthetic:sphere:16", *GL, "--frames", 2,
                          *make_args(tmp_path))
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("isolume: error:"), err
    assert expected in lines[0]


def test_a_lattice_refuses_a_sweep_beyond_its_range(tmp_path, capsys, lattices):
    status, _, err = _run(capsys, "movie", "synthetic:sphere:24", *GL, "--kind", "iso",
                          "--lattice", lattices["irradiance"], "--iso-range", 0.3, 0.6,
                          "--out", f"{tmp_path}/")
    assert status == 2 and "baked for isovalues 0.4 to 0.6" in err
    assert len(err.strip().splitlines()) == 1


def test_sweep_and_turntable_shorthands(tmp_path, capsys):
    """``--sweep LO:HI`` draws the frames of ``--kind iso --iso-range LO HI`` and
    ``--turntable`` those of ``--kind turntable``; a malformed sweep is one line."""
    pairs = [(["--sweep", "0.35:0.65"], ["--kind", "iso", "--iso-range", "0.35", "0.65"]),
             (["--turntable"], ["--kind", "turntable"])]
    for short, long in pairs:
        folders = []
        for name, options in (("short", short), ("long", long)):
            folder = tmp_path / f"{long[1]}-{name}"
            _movie(capsys, "synthetic:sphere:24", *SIZE, "--frames", 3, *options,
                   "--out", f"{folder}/")
            folders.append(sorted(folder.glob("frame_*.png")))
        assert len(folders[0]) == 3
        for a, b in zip(*folders, strict=True):
            assert a.read_bytes() == b.read_bytes()
    status, _, err = _run(capsys, "movie", *GL, "synthetic:sphere:24", "--sweep", "0.3",
                          "--out", f"{tmp_path / 'bad'}/")
    assert status == 2 and err.count("\n") == 1 and "LO:HI" in err, err
