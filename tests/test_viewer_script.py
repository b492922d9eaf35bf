"""The viewer's script language, parsed as plain strings (no GL, no window)."""

from pathlib import Path

import pytest

from isolume.app.viewer.script import (
    COMMANDS,
    Command,
    ScriptError,
    load_script,
    parse_line,
    parse_script,
    screenshot_paths,
)

MODES = ("lambert", "phong", "phong_hemi", "irradiance")

EVERY_COMMAND = """
# a comment, then every command
iso 0.42
orbit 30 -10
zoom 1.2
pan 0.1 -0.05
reset
mode irradiance
light 45 30
light camera
exposure 0.8
wait-mesh
wait-mesh 5
wait-gi
wait-gi 20
wait-bake 0.5
wait-bake 1 30
wait-light 1 30
frames 5
sleep 0.25
screenshot "out dir/shot.png"   # quoted paths may hold spaces
window-shot ui.png
save-view
save-view "saved views/v.view.json"
save-lattice
save-lattice lazy.npz
check-lattice
QUIT
"""


def test_every_command_parses_with_converted_arguments():
    commands = parse_script(EVERY_COMMAND, modes=MODES)
    got = [(c.name, c.args) for c in commands]
    assert got == [
        ("iso", (0.42,)),
        ("orbit", (30.0, -10.0)),
        ("zoom", (1.2,)),
        ("pan", (0.1, -0.05)),
        ("reset", ()),
        ("mode", ("irradiance",)),
        ("light", (45.0, 30.0)),
        ("light", ("camera",)),
        ("exposure", (0.8,)),
        ("wait-mesh", ()),
        ("wait-mesh", (5.0,)),
        ("wait-gi", ()),
        ("wait-gi", (20.0,)),
        ("wait-bake", (0.5,)),
        ("wait-bake", (1.0, 30.0)),
        ("wait-light", (1.0, 30.0)),
        ("frames", (5,)),
        ("sleep", (0.25,)),
        ("screenshot", ("out dir/shot.png",)),
        ("window-shot", ("ui.png",)),
        ("save-view", ()),
        ("save-view", ("saved views/v.view.json",)),
        ("save-lattice", ()),
        ("save-lattice", ("lazy.npz",)),
        ("check-lattice", ()),
        ("quit", ()),
    ]
    assert {c.name for c in commands} == set(COMMANDS)
    assert commands[0] == Command("iso", (0.42,), 3)  # line numbers count blanks/comments


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("spin 3", "unknown command 'spin'; expected one of iso, orbit"),
        ("iso", "iso takes 1 argument(s), got 0; usage: iso VALUE"),
        ("iso abc", "iso: 'abc' is not a number"),
        ("iso nan", "iso: 'nan' is not a number"),
        ("orbit 30", "orbit takes 2 argument(s), got 1"),
        ("zoom 0", "zoom: 0 is not positive"),
        ("zoom -2", "zoom: -2 is not positive"),
        ("mode toon", "unknown shading mode 'toon'; expected one of lambert, phong"),
        ("light 45", "expected `light AZIMUTH ELEVATION` or `light camera`"),
        ("light east 10", "light azimuth: 'east' is not a number"),
        ("light 10 95", "elevation 95 is outside [-90, 90]"),
        ("exposure 0", "exposure: 0 is not positive"),
        ("wait-bake 1.5", "wait-bake: 1.5 is not within [0, 1]"),
        ("wait-bake 0.5 0", "wait-bake: 0 is not positive"),
        ("wait-mesh 1 2", "wait-mesh takes 0 to 1 argument(s), got 2"),
        ("frames 0", "frames: 0 is not a positive whole number"),
        ("frames 2.5", "frames: '2.5' is not a whole number"),
        ("screenshot shot.jpg", "screenshot 'shot.jpg' must end in .png or .exr"),
        ("window-shot ui.exr", "window-shot 'ui.exr' must end in .png"),
        ("screenshot 'unterminated", "No closing quotation"),
        ("quit now", "quit takes 0 argument(s), got 1"),
    ],
)
def test_errors_name_the_line_and_say_what_is_wrong(line, message):
    text = f"iso 0.5\n\n{line}\nquit\n"
    with pytest.raises(ScriptError) as info:
        parse_script(text, source="s.txt", modes=MODES)
    assert str(info.value).startswith("s.txt:3: ")
    assert message in str(info.value)


def test_modes_are_free_words_without_a_mode_list():
    assert parse_line("mode anything", 1).args == ("anything",)
    assert parse_line("   # only a comment", 1) is None


def test_load_script_reads_files_and_reports_missing_ones(tmp_path: Path):
    path = tmp_path / "s.txt"
    path.write_text("frames 2\nquit\n")
    assert [c.name for c in load_script(path)] == ["frames", "quit"]
    with pytest.raises(ScriptError, match="cannot read it"):
        load_script(tmp_path / "missing.txt")
    path.write_text("frames 2\nfly 3\n")
    with pytest.raises(ScriptError, match=r"s\.txt:2: unknown command 'fly'"):
        load_script(path)


def test_screenshot_paths_pair_png_and_exr():
    assert screenshot_paths("a/b.png") == (Path("a/b.png"), Path("a/b.exr"))
    assert screenshot_paths("a/b.EXR") == (Path("a/b.png"), Path("a/b.exr"))
    assert screenshot_paths("shot") == (Path("shot.png"), Path("shot.exr"))


# -- running scripts against the viewer's public interface ---------------------------------
class FakeViewer:
    """A `ScriptTarget` that records the calls it gets; its surface is ready after two
    frames and its bake reaches 60 % of the texels after three polls."""

    def __init__(self, bake: bool = True) -> None:
        self.calls: list[tuple] = []
        self.quit = False
        self.frames = 0
        self.polls = 0
        self.bake = bake
        self.held = False

    def __getattr__(self, name):
        if name in ("request_iso", "set_mode", "set_exposure", "move_camera", "reset_camera",
                    "screenshot", "save_view", "save_lattice"):
            return lambda *args, **kw: self.calls.append((name, *args))
        raise AttributeError(name)

    def redraw(self) -> None:
        pass

    def set_light(self, angles, moving=False) -> None:
        self.calls.append(("set_light", angles, moving))

    def request_quit(self) -> None:
        self.quit = True

    def window_pixels(self):
        import numpy as np

        return np.zeros((2, 3, 3), np.uint8)

    def surface_ready(self) -> bool:
        return self.frames >= 2

    def gi_shown(self) -> bool:
        return self.frames >= 3

    def bake_progress(self):
        if not self.bake:
            raise ValueError("no lazy bake is running")
        self.polls += 1
        return (None if self.polls < 2 else 0.3 * (self.polls - 1)), None

    def hold_bake(self, held: bool) -> None:
        self.held = held
        self.calls.append(("hold_bake", held))

    def bake_held(self) -> bool:
        return self.held

    def check_lattice(self) -> dict:
        self.calls.append(("check_lattice",))
        return {}


def _run_script(text: str, viewer: FakeViewer, limit: int = 50) -> None:
    from isolume.app.viewer.script import ScriptRunner

    runner = ScriptRunner(parse_script(text, modes=MODES))
    for _ in range(limit):
        runner.step(viewer)
        if viewer.quit:
            return
        runner.before_swap(viewer)
        viewer.frames += 1
        runner.frame_done()
    raise AssertionError("the script did not end")


def test_script_drives_the_public_interface_in_order(tmp_path):
    viewer = FakeViewer()
    shot = tmp_path / "w.png"
    _run_script(f"iso 0.4\norbit 30 -10\nzoom 1.5\npan 0.1 0.2\nreset\nlight 45 30\n"
                f"light camera\nmode phong\nexposure 2\nwait-mesh\nwait-gi\nwait-bake 0.6\n"
                f"check-lattice\nwindow-shot {shot}\nsave-lattice\nscreenshot s.png\n"
                f"save-view v.view.json\nquit\n",
                viewer)
    assert viewer.calls == [
        ("request_iso", 0.4), ("move_camera", "orbit", 30.0, -10.0),
        ("move_camera", "zoom", 1.5), ("move_camera", "pan", 0.1, 0.2), ("reset_camera",),
        ("set_light", (45.0, 30.0), True), ("set_light", None, True), ("set_mode", "phong"),
        ("set_exposure", 2.0), ("hold_bake", True), ("check_lattice",), ("hold_bake", False),
        ("save_lattice", None), ("screenshot", "s.png"), ("save_view", "v.view.json")]
    assert viewer.frames >= 3 and viewer.polls == 3  # waited: mesh, light on screen, bake
    assert shot.exists()


def test_script_errors_name_the_line():
    with pytest.raises(ScriptError, match="script line 2: wait-bake: no lazy bake"):
        _run_script("iso 0.4\nwait-bake 0.5\n", FakeViewer(bake=False))
    with pytest.raises(ScriptError, match="script line 1: wait-mesh waited"):
        _run_script("wait-mesh 0.001\n", _NeverReady(), limit=10_000_000)
    with pytest.raises(ScriptError, match=r"script line 1: wait-gi waited .* for global"):
        _run_script("wait-gi 0.001\n", _NeverReady(), limit=10_000_000)


class _NeverReady(FakeViewer):
    def surface_ready(self) -> bool:
        return False

    def gi_shown(self) -> bool:
        return False
