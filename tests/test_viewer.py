"""The interactive viewer: scripted sessions in a real window under Xvfb, surfaces off the
render thread, lazy-bake uploads equal to the lattice, controls."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from isolume import volumes
from isolume.app.render.images import read_exr

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "volumes"
"""``<clone>/../shared/data/volumes``: real volumes, present on developer machines."""
RGB9E5_RELATIVE = 2.0**-9
"""RGB9_E5 keeps 9 mantissa bits of the largest channel: rounding error ≤ 2⁻⁹ of it."""


# -- a display for the window -------------------------------------------------------------
def _free_display() -> int:
    for n in range(90, 200):
        if not Path(f"/tmp/.X{n}-lock").exists() and not Path(f"/tmp/.X11-unix/X{n}").exists():
            return n
    raise RuntimeError("no free X display number in :90-:199")


@pytest.fixture(scope="module")
def display():
    """DISPLAY of an Xvfb server started for these tests (skipped when Xvfb cannot run)."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb)")
    n = _free_display()
    proc = subprocess.Popen([xvfb, f":{n}", "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    socket = Path(f"/tmp/.X11-unix/X{n}")
    for _ in range(100):
        if socket.exists() or proc.poll() is not None:
            break
        time.sleep(0.05)
    if not socket.exists():
        proc.kill()
        err = proc.stderr.read().decode(errors="replace")[-300:] if proc.stderr else ""
        pytest.skip(f"Xvfb :{n} did not start: {err.strip()}")
    yield f":{n}"
    proc.terminate()
    proc.wait(5)


def _view_command(args, env_display) -> tuple[list[str], dict[str, str]]:
    """(command line, environment) of ``isolume view ARGS`` run as the console script."""
    env = dict(os.environ)
    env.pop("WAYLAND_DISPLAY", None)
    if env_display is None:
        env.pop("DISPLAY", None)
    else:
        env["DISPLAY"] = env_display
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, "-c", "import sys; from isolume.app.cli import main; sys.exit(main())",
           "view", *args]
    return cmd, env


def _view(args, env_display, cwd, timeout=120):
    """Run ``isolume view ARGS`` in a subprocess (as the console script does)."""
    cmd, env = _view_command(args, env_display)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path), float)


def _surface(path):
    """(linear RGB (H, W, 3), mask (H, W)) of a screenshot's EXR (0 off the surface)."""
    rgb = read_exr(path)["RGB"]
    return rgb, rgb.max(axis=-1) > 0


# -- scripted sessions in a real window ---------------------------------------------------
SESSION = """
wait-mesh
screenshot base.png
exposure 2.5
screenshot bright.png
exposure 1
light 200 -30
screenshot light.png
light camera
iso 0.7
wait-mesh
screenshot iso.png
iso 0.3
wait-mesh
mode irradiance
wait-bake 1.0 60
check-lattice
screenshot irradiance.png
window-shot window.png
quit
"""


def test_sigterm_closes_the_viewer_as_quit_does(display, tmp_path, stopped_after):
    """SIGTERM (a `kill`, a closed session) while the lazy bake runs: the viewer saves its
    lattice, stops its bake process and frees their shared memory (no resource-tracker
    warning of leaked objects), with the exit status of a Ctrl-C."""
    (tmp_path / "s.txt").write_text("wait-bake 0.1\nsleep 600\n")
    cmd, env = _view_command(["synthetic:engine:48", "--size", "320x240", "--script",
                              "s.txt", "--lattice", "lazy.npz"], display)
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    status, err = stopped_after(proc, "wait-bake done", signal.SIGTERM)
    assert status == 130, err
    assert "leaked" not in err and (tmp_path / "lazy.npz").exists(), err


def test_scripted_session_changes_what_it_should(display, tmp_path):
    (tmp_path / "s.txt").write_text(SESSION)
    run = _view(["synthetic:engine:48", "--shading", "phong_hemi", "--size", "320x240",
                 "--bake-samples", "4", "--script", "s.txt", "--stats", "stats.json",
                 "--lattice", "lazy.npz"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    stats = json.loads((tmp_path / "stats.json").read_text())
    base, mask = _surface(tmp_path / "base.exr")
    assert (tmp_path / "base.png").exists() and mask.mean() > 0.05
    # the window frames the surface beside the panel; its screenshots in the whole window
    rows, cols = np.nonzero(mask)
    assert 0.4 < cols.mean() / mask.shape[1] < 0.6
    assert max(np.ptp(cols) / mask.shape[1], np.ptp(rows) / mask.shape[0]) > 0.65
    # exposure scales the displayed image, not the linear radiance
    srgb = {n: _png(tmp_path / f"{n}.png") for n in ("base", "bright")}
    assert srgb["bright"][mask].mean() > srgb["base"][mask].mean() + 20
    np.testing.assert_allclose(_surface(tmp_path / "bright.exr")[0], base, atol=1e-6)
    # a light from below-behind darkens what the camera light lit
    lit, lit_mask = _surface(tmp_path / "light.exr")
    assert (lit_mask == mask).all()
    assert lit[mask].mean() < 0.8 * base[mask].mean()
    # another isovalue, another silhouette
    _, iso_mask = _surface(tmp_path / "iso.exr")
    union, inter = (mask | iso_mask).sum(), (mask & iso_mask).sum()
    assert inter / union < 0.97
    # global illumination from the lazily baked lattice differs from local shading and
    # the uploaded textures hold the lattice's values
    gi, gi_mask = _surface(tmp_path / "irradiance.exr")
    assert (gi_mask == mask).all()
    assert np.abs(gi[mask] - base[mask]).mean() > 0.05
    (check,) = stats["checks"]
    assert check["texels"] > 0 and check["valid_mismatch"] == 0
    assert check["max_rel_error"] <= RGB9E5_RELATIVE and check["uncomputed_nonzero"] == 0
    assert check["facing_mismatch"] == 0
    progress = stats["bake"]["progress"]
    assert progress["surface_started"] == progress["surface"] > 0
    # the panel is drawn over the picture in the window, not in the screenshots
    window, shot = _png(tmp_path / "window.png"), _png(tmp_path / "irradiance.png")
    assert window.shape == shot.shape
    assert np.abs(window[:60, :120] - shot[:60, :120]).mean() > 10
    # the lattice was saved on exit; shown again from the file, it gives the same picture
    from isolume.baking.lattice import Lattice

    saved = Lattice.load(tmp_path / "lazy.npz", volumes.load("synthetic:engine:48"))
    assert (saved.samples > 0).sum() == check["computed"] > 0
    traced = saved.meta["stats"]  # its own bake's: the paths it holds, their rays
    assert traced["paths"] == saved.samples.sum() and traced["rays_traced"] >= traced["paths"]
    assert saved.meta["rays_traced"] == traced["rays_traced"] and traced["bake_seconds"] > 0
    assert saved.active.sum() > check["texels"]  # the plan's active texels, for resuming
    again = _view(["synthetic:engine:48", "--lattice", "lazy.npz", "--no-bake",
                   "--size", "320x240", "--frames", "1", "--screenshot", "again.png"],
                  display, tmp_path)
    assert again.returncode == 0, again.stderr
    np.testing.assert_array_equal(_surface(tmp_path / "again.exr")[0], gi)


def test_wait_gi_ends_when_the_first_preview_is_on_screen(display, tmp_path):
    """``wait-gi`` waits for the lazy bake's first preview pass (the plan's texels come
    later) to be on screen, and the screenshot after it shows its light: it differs from
    the one taken as the surface arrived, and no face is left unlit against the one taken
    once the bake is done (a wait that ended on the first texels received left 40 % of
    the surface below half its light). ``--timeline`` records the session's stages, the
    bake process's CPU time among them."""
    (tmp_path / "s.txt").write_text("wait-mesh\nscreenshot local.png\nwait-gi 120\nframes 1\n"
                                    "screenshot gi.png\nwait-bake 1 120\nframes 3\n"
                                    "screenshot done.png\nquit\n")
    run = _view(["synthetic:engine", "--size", "320x240", "--script", "s.txt",
                 "--stats", "stats.json", "--timeline", "t.json"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    stages = json.loads((tmp_path / "t.json").read_text())["stages"]
    assert [s["name"] for s in stages] == ["load", "surface", "draw"]
    assert sum(s["children_cpu_s"] for s in stages) > 0.1  # the lazy bake's process
    previews = json.loads((tmp_path / "stats.json").read_text())["bake"]["previews"]
    assert previews and previews[0]["paths"] > 0
    from isolume.app.bench.scale import first_gi

    said = [line for line in run.stderr.splitlines() if line.startswith("script line")]
    assert [line.split(" done")[0] for line in said] == ["script line 1: wait-mesh",
                                                         "script line 3: wait-gi",
                                                         "script line 6: wait-bake"]
    assert 0 < first_gi(run.stderr) < 120  # seconds after the start, as bench scale reads
    local, mask = _surface(tmp_path / "local.exr")
    gi, gi_mask = _surface(tmp_path / "gi.exr")
    both = mask & gi_mask
    assert both.mean() > 0.05 and np.abs(gi[both] - local[both]).mean() > 0.01
    done, done_mask = _surface(tmp_path / "done.exr")  # the view's texels all traced
    lit = both & done_mask & (done.sum(axis=-1) > 0)
    ratio = gi[lit].sum(axis=-1) / done[lit].sum(axis=-1)  # the light on screen at wait-gi
    assert np.mean(ratio < 0.5) < 0.05, np.mean(ratio < 0.5)  # no face left unlit


def test_wait_gi_lights_what_the_screenshot_sees_beside_the_panel(display, tmp_path):
    """With the panel shown open (a window wide enough for it) the window's camera stands
    aside to frame the surface beside it, and a screenshot's (framed in the whole window,
    `ViewerState.whole_window`) sees faces the window's does not: on the torus, part of
    the hole's inner wall. ``wait-gi`` returns once they have their first light too: no
    pixel of the screenshot after it is below a quarter of its light once the bake is done
    (the window's visible texels alone leave the inner wall's pixels so)."""
    (tmp_path / "s.txt").write_text("wait-gi 120\nscreenshot gi.png\nwait-bake 1 120\n"
                                    "frames 3\nscreenshot done.png\nquit\n")
    run = _view(["synthetic:torus", "--size", "900x400", "--script", "s.txt"],
                display, tmp_path)
    assert run.returncode == 0, run.stderr
    gi, gi_mask = _surface(tmp_path / "gi.exr")
    done, done_mask = _surface(tmp_path / "done.exr")
    lit = gi_mask & done_mask & (done.sum(axis=-1) > 0)
    assert lit.mean() > 0.3
    ratio = gi[lit].sum(axis=-1) / done[lit].sum(axis=-1)
    assert np.sum(ratio < 0.25) <= 5, np.sum(ratio < 0.25)  # none left unlit


def test_frames_keep_coming_while_the_full_surface_is_extracted(display, tmp_path):
    """A 256³ volume (its full surface takes a few tenths of a second): the isovalue change
    shows a preview first, and frames are drawn until the full-resolution surface replaces
    it."""
    (tmp_path / "s.txt").write_text("wait-mesh\niso 0.42\nwait-mesh\nquit\n")
    run = _view(["synthetic:sphere:256", "--no-bake", "--size", "256x192", "--script", "s.txt",
                 "--stats", "stats.json"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    change = json.loads((tmp_path / "stats.json").read_text())["extractions"][-1]
    assert change["iso"] == pytest.approx(0.42)
    assert change["coarse_s"] < change["full_s"]
    assert change["frames"] >= 3, change
    assert change["max_gap_ms"] < 1000 * change["full_s"], change


def test_a_small_window_folds_the_panel_and_shows_the_surface_whole(display, tmp_path):
    """At 640×480 the open panel would cover 54 % of the window: it starts folded to its
    title bar, and the window frames the surface in the whole window, as its screenshots
    do — the two pictures differ only under the bar, under 3 % of the window."""
    (tmp_path / "s.txt").write_text("wait-mesh\nframes 2\nscreenshot shot.png\n"
                                    "window-shot window.png\nquit\n")
    run = _view(["synthetic:engine:48", "--no-bake", "--size", "640x480", "--script",
                 "s.txt"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    window, shot = _png(tmp_path / "window.png"), _png(tmp_path / "shot.png")
    assert _surface(tmp_path / "shot.exr")[1].mean() > 0.1
    rows, cols = np.nonzero(np.abs(window - shot).max(axis=-1) > 8)
    hidden = (np.ptp(rows) + 1) * (np.ptp(cols) + 1) / (640 * 480)  # the panel's box
    assert rows.max() < 40 and hidden < 0.03, (rows.max(), cols.max(), hidden)


def test_no_display_names_the_off_screen_alternative(monkeypatch, capsys):
    from isolume.app.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", "synthetic:sphere:16", "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert "isolume render" in err and err.count("\n") == 1


def test_bad_script_fails_before_a_window_opens(tmp_path, monkeypatch, capsys):
    from isolume.app.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    (tmp_path / "s.txt").write_text("iso 0.5\nmode toon\n")
    assert main(["view", "synthetic:sphere:16", "--script", str(tmp_path / "s.txt")]) == 2
    assert "s.txt:2: unknown shading mode 'toon'" in capsys.readouterr().err


# -- a complete lattice file: its saves, its modes, its panel --------------------------------
SUN = "sky:sun=6,sun_az=-150,sun_el=40"
BAKED_RANGE = (0.25, 0.35)


@pytest.fixture(scope="module")
def lattice_file(tmp_path_factory):
    """A complete lattice of synthetic:engine:48 (8 paths a texel, iso range `BAKED_RANGE`,
    the sun shaded per pixel) and its stats."""
    from isolume.baking.bake import bake
    from isolume.baking.config import BakeConfig

    path = tmp_path_factory.mktemp("lattice") / "light.npz"
    config = BakeConfig(samples=8, bounces=1, env=SUN, iso_range=BAKED_RANGE)
    lattice = bake(volumes.load("synthetic:engine:48"), config, out=path, workers=2)
    return path, dict(lattice.meta["stats"])


def _copy_in(lattice_file, tmp_path) -> Path:
    """The lattice file copied into the test's folder (the viewer writes beside it)."""
    path = tmp_path / lattice_file[0].name
    shutil.copyfile(lattice_file[0], path)
    return path


def _said(stdout: str, start: str) -> list[str]:
    """The lines of `stdout` from the first that starts with `start` on."""
    lines = stdout.splitlines()
    firsts = [i for i, line in enumerate(lines) if line.startswith(start)]
    assert firsts, stdout
    return lines[firsts[0]:]


TURNED_SESSION = """
wait-mesh
light 60 40
sleep 0.5
save-lattice pending.npz
wait-light 1 120
save-lattice early.npz
wait-bake 1 120
save-lattice
quit
"""


def _turned_session(volume: str, iso: float, tmp_path, display) -> list[list[str]]:
    """Run `TURNED_SESSION` on light.npz (in `tmp_path`) shown at `iso`; the stdout lines
    from the save of early.npz on, and from that of light-relit.npz on. The save as the
    turn's bake starts writes nothing (the lattice baked is still the file's) and says
    so."""
    (tmp_path / "s.txt").write_text(TURNED_SESSION)
    run = _view([volume, "--iso", str(iso), "--lattice", "light.npz", "--size", "320x240",
                 "--script", "s.txt"], display, tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("isolume: nothing saved") and not (
        tmp_path / "pending.npz").exists(), run.stdout
    return [_said(run.stdout, f"isolume: saved {name}")
            for name in ("early.npz", "light-relit.npz")]


def test_a_turned_files_saves_count_their_own_bake(display, tmp_path, lattice_file):
    """A complete file whose sun is turned: the saves say they hold the re-bake for the
    turned light, the file keeping its own; after ``wait-bake 1`` the one beside the file
    comes without a warning. Each saved lattice's stats count its own bake (the paths it
    holds, the rays since the turn), not the file's."""
    from isolume.baking.lattice import Lattice

    _copy_in(lattice_file, tmp_path)
    early, late = _turned_session("synthetic:engine:48", 0.3, tmp_path, display)
    assert "re-baked for the turned light" in early[0] and "light.npz keeps" in early[0]
    assert len(late) == 1  # no warning once the texels near the surface have samples
    vol = volumes.load("synthetic:engine:48")
    file_stats = lattice_file[1]
    for name in ("early.npz", "light-relit.npz"):
        saved = Lattice.load(tmp_path / name, vol)
        traced = saved.meta["stats"]
        assert traced["paths"] == saved.samples.sum() < file_stats["paths"], name
        assert traced["rays_traced"] != file_stats["rays_traced"], name
    assert traced["paths"] > 0 and traced["rays_traced"] >= traced["paths"]


def test_a_save_right_after_wait_light_warns_that_previews_are_not_saved(display, tmp_path):
    """The tooth CT's complete file, its sun turned: ``wait-light`` ends once the previews
    show the turned light (the re-bake's own rounds come after them), so the save right
    after it holds few of the re-bake's texels or none: it says so, and names
    ``wait-bake``, one line (it said "0 texels computed" and nothing more)."""
    from isolume.baking.bake import bake
    from isolume.baking.config import BakeConfig
    tooth = SHARED / "tooth_zfp_103x94x161_uint8.raw.gz"
    if not tooth.exists():
        pytest.skip(f"{tooth} not present (../shared/data is optional)")
    tooth = str(tooth)
    bake(volumes.load(tooth), BakeConfig(samples=16, env=SUN, iso_range=(100, 130)),
         out=tmp_path / "light.npz", workers=2)
    early, late = _turned_session(tooth, 115, tmp_path, display)
    assert early[1].startswith("isolume: warning: ") and "wait-bake" in early[1], early
    assert "previews" in early[1] and early[2] == late[0]


FILE_SESSION = """
wait-mesh
frames 3
window-shot panel.png
save-lattice
save-lattice copy.npz
mode vicinity
quit
"""


def test_a_file_shown_as_it_is_wraps_its_warning_and_says_why_nothing_is_saved(
        display, tmp_path, lattice_file):
    """A complete file shown outside its baked range: the panel's range warning wraps to
    the panel's width (unwrapped, it widened the panel past the middle of the window,
    where the surface is framed beside it); a save
    without a name writes nothing and says why on stdout, one line; ``save-lattice
    FILE`` writes a copy; ``mode vicinity`` is refused for the reason `render` gives (a
    constant sky, no bounces), not the lattice's kind, which is right."""
    path = _copy_in(lattice_file, tmp_path)
    (tmp_path / "s.txt").write_text(FILE_SESSION)
    width = 900  # the panel shows open: wide enough for the surface beside it
    run = _view(["synthetic:engine:48", "--iso", "0.6", "--lattice", "light.npz",
                 "--size", f"{width}x420", "--script", "s.txt"], display, tmp_path)
    assert run.returncode == 2, run.stderr
    window = _png(tmp_path / "panel.png")
    title = window[19]  # the panel's title bar, blue, as wide as the panel
    blue = np.flatnonzero(title[:, 2] - title[:, 0] > 50)
    assert len(blue) > 100 and blue.max() < width / 2, blue.max()
    (nothing, copied) = _said(run.stdout, "isolume: nothing saved")
    assert "light.npz" in nothing and "save-lattice OTHER.npz" in nothing
    assert copied.startswith("isolume: saved copy.npz")
    assert (tmp_path / "copy.npz").read_bytes() == path.read_bytes()
    assert "--env constant:1,1,1 --bounces 0" in run.stderr
    assert "irradiance modes need" not in run.stderr


def test_the_light_note_says_whether_a_turned_light_is_re_baked(gl):
    """The panel's note under the light controls: a file's bounced light "is re-baked once
    the light rests" when the viewer bakes it for a turned light (baking on), else it
    "stays as baked"."""
    from types import SimpleNamespace

    from isolume.app.viewer.draw import Drawing, ViewState
    from isolume.app.viewer.illumination import Illumination
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.lazy import new_lattice

    vol = volumes.load("synthetic:sphere:16")
    config = BakeConfig(env=SUN)
    drawing = Drawing(gl, vol)
    try:
        assert drawing.show_lattice(new_lattice(vol, config)) is None
        notes = {}
        for bake in (True, False):
            state = SimpleNamespace(view=ViewState(0.5, "irradiance", 1.0))
            illumination = Illumination(vol, drawing, state, SimpleNamespace(bake=bake))
            illumination.static_lattice = SimpleNamespace(config=config)
            illumination.static_file = SimpleNamespace(
                geometry=LatticeGeometry.for_volume(vol, config.scale))
            notes[bake] = illumination.light_note()
    finally:
        drawing.release()
    assert notes[True].endswith("their bounced light is re-baked once the light rests.")
    assert notes[False].endswith("their bounced light stays as baked.")


def test_a_mode_of_another_lattice_kind_names_the_bake_that_makes_it():
    """A mode that reads another kind of lattice than the one shown: the renderer's reason,
    and the lazy bake's option that makes that kind."""
    from types import SimpleNamespace

    from isolume.app.render.settings import RenderError
    from isolume.app.viewer.actions import check_mode
    from isolume.app.viewer.state import ViewerError

    def refuse(mode):
        raise RenderError(f"shading {mode!r} needs an sh lattice, this one holds irradiance")

    drawing = SimpleNamespace(modes=("lambert", "sh"), usable_modes=lambda: ("lambert",),
                              renderer=SimpleNamespace(lattice=SimpleNamespace(
                                  kind="irradiance"), check_mode=refuse))
    with pytest.raises(ViewerError, match=r"needs an sh lattice, .*--bake-mode sh\)$"):
        check_mode(drawing, "sh")


# -- surfaces off the render thread -------------------------------------------------------
def test_viewer_surfaces_are_the_isosurface_and_can_be_cancelled():
    from isolume.app.viewer.surfaces import extract_surface

    vol = volumes.load("synthetic:engine:64")
    for step in (1, 2):
        whole = volumes.isosurface(vol, 0.3, step_size=step)
        slabs = extract_surface(vol, 0.3, step=step)

        def triangles(mesh):
            t = np.sort(np.round(mesh.vertices[mesh.faces].reshape(-1, 9), 5), axis=0)
            return t[np.lexsort(t.T[::-1])]

        assert len(slabs.faces) == len(whole.faces)
        np.testing.assert_allclose(triangles(slabs), triangles(whole), atol=1e-5)
    # smooth normals as volumes computes them
    n = volumes.normals_at(vol, slabs.vertices)
    np.testing.assert_allclose(slabs.normals, n, atol=1e-6)
    assert extract_surface(vol, 0.3, cancelled=lambda: True) is None
    assert extract_surface(vol, 0.0).empty


def test_preview_step_grows_with_the_surface():
    from isolume.app.viewer.surfaces import PREVIEW_TARGET_TRIANGLES, preview_step

    assert preview_step(None) == 2 and preview_step(1000) == 2
    assert preview_step(9 * PREVIEW_TARGET_TRIANGLES) == 3
    assert preview_step(100 * PREVIEW_TARGET_TRIANGLES) == 4


def test_mesh_worker_drops_stale_isovalues():
    from isolume.app.viewer.surfaces import MeshWorker

    worker = MeshWorker(volumes.load("synthetic:shells:96"))
    try:
        worker.request(0.3)
        worker.request(0.6)
        results = _until_full(worker, 30)
    finally:
        worker.close()
    assert results and all(r.iso == 0.6 for r in results)
    assert [r.stage for r in results][-1] == "full"


def _until_full(worker, seconds: float) -> list:
    """The surfaces a `MeshWorker` gives until a full one arrives (or `seconds` pass)."""
    results = []
    deadline = time.time() + seconds
    while time.time() < deadline and not any(r.stage == "full" for r in results):
        results += worker.poll()
        time.sleep(0.01)
    return results


@pytest.mark.parametrize(("size", "step"), [(96, 2), (192, 4)])
def test_the_first_preview_step_is_the_one_the_full_surface_wants(size, step):
    """Before any full surface is known, the coarse surface is made at the step that the
    full one wants (`preview_step`), its size estimated from the coarsest surface (within
    5 % on smooth shells): no finer preview than needed, no second one once the full
    surface is known."""
    from isolume.app.viewer.surfaces import (
        LARGEST_STEP,
        MeshWorker,
        estimated_triangles,
        extract_surface,
        preview_step,
    )

    vol = volumes.load(f"synthetic:shells:{size}")
    full = len(extract_surface(vol, 0.3).faces)
    coarsest = extract_surface(vol, 0.3, step=LARGEST_STEP)
    assert abs(estimated_triangles(coarsest) / full - 1) < 0.05
    assert preview_step(full) == step
    worker = MeshWorker(vol)
    try:
        worker.request(0.3)
        results = _until_full(worker, 60)
        time.sleep(0.2)
        results += worker.poll()
    finally:
        worker.close()
    assert [r.stage for r in results] == ["coarse", "full"]  # no "lod" after the full
    expected = coarsest if step == LARGEST_STEP else extract_surface(vol, 0.3, step=step)
    np.testing.assert_array_equal(results[0].mesh.faces, expected.faces)
    assert len(results[1].mesh.faces) == full


# -- uploads of lazily baked texels -------------------------------------------------------
def test_uploaded_regions_equal_the_lattice(gl):
    """Texels changed after the upload reach the GL textures block by block, within the
    RGB9_E5 precision; untouched and uncomputed texels stay as they were."""
    from isolume.app.render.lattice_gl import LatticeTextures
    from isolume.app.viewer.draw import TexelUploader, check_textures
    from isolume.baking.lattice import Lattice, LatticeGeometry

    geometry = LatticeGeometry((13, 17, 21), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    lattice = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    rng = np.random.default_rng(3)
    textures = LatticeTextures(gl, lattice)
    uploader = TexelUploader(textures)
    flat = rng.choice(lattice.samples.size, 900, replace=False)
    values = lattice.values.reshape(-1, 3)
    values[flat] = rng.uniform(0.01, 4.0, (900, 3)) * rng.uniform(0.1, 10.0, (900, 1))
    lattice.samples.reshape(-1)[flat] = rng.integers(1, 64, 900)
    lattice.facing.reshape(-1, 2)[flat] = rng.integers(1, 256, (900, 2))
    assert not textures.facing_known
    uploader.mark(flat)
    assert uploader.pending > 0
    while uploader.pending:
        uploader.upload(budget_s=0.0)  # one batch of bricks per call
    result = check_textures(textures)
    assert result["texels"] == 900 and result["valid_mismatch"] == 0
    assert result["missing_bricks"] == 0
    assert result["max_rel_error"] <= RGB9E5_RELATIVE
    assert result["uncomputed_nonzero"] == 0
    assert result["facing_mismatch"] == 0 and textures.facing_known
    # a texel changed but not marked is not re-uploaded
    values[flat[0]] *= 2
    assert check_textures(textures)["max_rel_error"] > 0.4
    textures.release()
    assert gl.error == "GL_NO_ERROR"


def test_bricks_written_as_neighbours_show_their_light_and_keep_their_aprons(gl):
    """A texel on a brick's low face is also in the apron of the brick below, which
    `write_bricks` writes whole beside it. A brick written so has shown its first light
    (it is not first in line again), but stays marked when it was: its own low face is
    in the apron of the brick below it, which only its own upload rewrites — a frame whose
    budget ends after the first light leaves no stale apron behind."""
    from isolume.app.render.lattice_gl import LatticeTextures
    from isolume.app.viewer.draw import TexelUploader, check_textures
    from isolume.baking.lattice import Lattice, LatticeGeometry

    geometry = LatticeGeometry((28, 12, 12), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))  # 4 bricks in z
    lattice = Lattice.empty(geometry, 3, {"kind": "irradiance"})

    def light(z: int, value: float) -> np.ndarray:
        flat = np.ravel_multi_index((z, 3, 3), geometry.shape)
        lattice.values.reshape(-1, 3)[flat] = value
        lattice.samples.reshape(-1)[flat] = 16
        return np.array([flat])

    textures = LatticeTextures(gl, lattice)
    uploader = TexelUploader(textures)
    uploader.mark(np.concatenate([light(3, 1.0), light(10, 1.0)]))  # bricks 0 and 1
    uploader.upload(None)
    uploader.mark(np.concatenate([light(8, 3.0), light(12, 2.0)]))  # brick 1, refined
    uploader.mark(light(16, 2.0))  # brick 2: its first light, and brick 1's apron
    assert not uploader.shown[2, 0, 0]
    uploader.upload(budget_s=0.0, first_budget_s=10.0)  # no time left for the refinement
    assert uploader.shown[2, 0, 0] and uploader.dirty[1, 0, 0] and uploader.pending == 1
    while uploader.pending:
        uploader.upload(budget_s=None)
    result = check_textures(textures)
    assert result["texels"] == 5 and result["max_rel_error"] <= RGB9E5_RELATIVE
    assert result["missing_bricks"] == 0 and result["valid_mismatch"] == 0
    textures.release()


# -- controls ------------------------------------------------------------------------------
def test_camera_and_light_controls():
    from isolume.app.render.camera import Camera
    from isolume.app.viewer.panel import (
        angles_from_direction,
        direction_from_angles,
        drag_target,
        orbit,
        pan,
        zoom,
    )

    cam = Camera(azimuth=10, elevation=80)
    assert orbit(cam, 20, 30).elevation == 89.5 and orbit(cam, 355, 0).azimuth == 5
    assert zoom(cam, 2).distance == pytest.approx(cam.distance / 2)
    assert zoom(cam, 1e-6).distance == 20.0
    assert pan(cam, 0.1, -0.2).pan == (0.1, -0.2)
    for az, el in [(0, 0), (45, 30), (200, -60)]:
        assert angles_from_direction(direction_from_angles(az, el)) == pytest.approx(
            (az if az <= 180 else az - 360, el))
    # the light at the camera's angles points to the eye
    cam = Camera(azimuth=45, elevation=30)
    eye_dir = (cam.eye - cam.center) / np.linalg.norm(cam.eye - cam.center)
    np.testing.assert_allclose(direction_from_angles(45, 30), eye_dir, atol=1e-12)
    assert drag_target(0, False, False) == "rotate"
    assert drag_target(0, True, False) == "pan" and drag_target(2, False, False) == "pan"
    assert drag_target(0, False, True) == "light" and drag_target(1, False, False) == "light"
    assert drag_target(5, False, False) is None


def _panel_rects(size, frames, presses=()):
    """The panel's (x, y, width, height) in each of `frames` Dear ImGui frames of a window
    of `size` (W, H) window units, laid out without a window or GL; the C key goes down in
    the frames numbered in `presses` and up in the next."""
    imgui = pytest.importorskip("imgui_bundle").imgui
    from isolume.app.viewer.panel import PanelModel, draw_panel

    model = PanelModel(
        title="engine  128x80x65", iso=0.3, iso_range=(0.0, 1.0),
        mesh_status="full resolution: 110,818 triangles, 55,560 vertices",
        modes=("phong_hemi", "irradiance"), enabled=("phong_hemi", "irradiance"),
        mode="irradiance", exposure=1.0, light=None, auto_exposure=0.23,
        light_note="The sun and lights are shaded per pixel (exact shadows); turning the "
                   "light moves them, their bounced light is re-baked once the light rests.",
        bake_lines=("planning the bake (gradients)... 4 s",
                    "preview: 4 paths/texel on this surface"),
        can_bake=True, can_save=True, frame_ms=30.0, size=size)
    context = imgui.create_context()
    io = imgui.get_io()
    io.set_ini_filename(None)
    io.backend_flags |= imgui.BackendFlags_.renderer_has_textures  # no font texture needed
    rects = []
    try:
        for frame in range(frames):
            io.display_size, io.delta_time = imgui.ImVec2(*size), 1 / 60
            if frame in presses or frame - 1 in presses:
                io.add_key_event(imgui.Key.c, frame in presses)
            imgui.new_frame()
            actions = draw_panel(imgui, model)
            imgui.render()
            rects += [a.value for a in actions if a.name == "panel_rect"]
    finally:
        imgui.destroy_context(context)
    return rects


def test_the_panel_takes_a_small_share_of_a_small_window():
    """Open, the panel is 419×394 window units: 54 % of a 640×480 window, past its middle.
    There it shows folded to a one-line title bar from its first visible frame (Dear ImGui
    lays it out hidden in the first), under 2 % of the window; C opens it and folds it
    again. In the default 1024×768 window it shows open (21 %), beside the surface."""
    def share(rect, size):
        return rect[2] * rect[3] / (size[0] * size[1])

    small = (640, 480)
    rects = _panel_rects(small, 12, presses=(4, 8))
    assert max(share(r, small) for r in rects[1:4]) < 0.02, rects
    assert rects[1][3] < 25 and rects[1][2] > 150  # a title bar wide enough for its hint
    assert 0.4 < share(rects[7], small) < 0.6  # opened by C
    assert share(rects[-1], small) < 0.02  # folded again
    large = (1024, 768)
    rects = _panel_rects(large, 4)
    assert all(0.15 < share(r, large) < 0.3 for r in rects[2:]), rects
    x, _, width, _ = rects[-1]
    assert x + width + 10 <= 0.5 * large[0]


def test_keys_map_to_actions():
    import glfw

    from isolume.app.viewer.panel import Action, key_action

    modes = ("lambert", "phong", "irradiance")
    assert key_action(glfw, glfw.KEY_RIGHT, 0, modes) == Action("iso_step", 1)
    assert key_action(glfw, glfw.KEY_LEFT, glfw.MOD_SHIFT, modes) == Action("iso_step", -10)
    assert key_action(glfw, glfw.KEY_3, 0, modes) == Action("mode", "irradiance")
    assert key_action(glfw, glfw.KEY_4, 0, modes) is None
    assert key_action(glfw, glfw.KEY_F12, 0, modes) == Action("screenshot")
    assert key_action(glfw, glfw.KEY_P, 0, modes) == Action("screenshot")
    assert key_action(glfw, glfw.KEY_R, 0, modes) == Action("reset_camera")
    assert key_action(glfw, glfw.KEY_EQUAL, 0, modes) == Action("exposure_by", 1.25)
    assert key_action(glfw, glfw.KEY_ESCAPE, 0, modes) == Action("quit")
    assert key_action(glfw, glfw.KEY_Z, 0, modes) is None


def test_actions_change_the_state_and_report_problems():
    """Keys and the panel end in `Actions.apply`: it changes the viewer's state; a request
    it cannot honour becomes the status message (no window needed)."""
    from types import SimpleNamespace

    from isolume.app.render.camera import Camera
    from isolume.app.viewer.actions import ISO_STEPS, Actions
    from isolume.app.viewer.draw import ViewState
    from isolume.app.viewer.panel import Action
    from isolume.app.viewer.state import ViewerState

    requested = []
    drawing = SimpleNamespace(modes=("lambert", "irradiance"), usable_modes=lambda: ("lambert",),
                              renderer=SimpleNamespace(lattice=None),
                              light_angles=lambda view, cam: (cam.azimuth, cam.elevation))
    home = Camera(azimuth=10, elevation=20)
    state = ViewerState(ViewState(1.0, "lambert", 1.0), home, home)
    actions = Actions(SimpleNamespace(value_range=(0.0, 2.0)), state, drawing,
                      SimpleNamespace(request=requested.append), illumination=None, saver=None)
    actions.apply(Action("iso", 5.0))  # clamped inside the data range
    assert state.view.iso == pytest.approx(2.0 - 2e-6) and requested == [state.view.iso]
    actions.apply(Action("iso_step", -10))
    assert state.view.iso == pytest.approx(2.0 - 2e-6 - 10 * 2.0 / ISO_STEPS)
    actions.apply(Action("exposure_by", 1.25))
    assert state.view.exposure == 1.25
    actions.apply(Action("toggle_light"))
    assert state.view.light == (10.0, 20.0)  # world-fixed where the camera light was
    actions.apply(Action("toggle_light"))
    assert state.view.light is None
    state.dirty = False
    actions.apply(Action("mode", "irradiance"))
    assert state.view.shading == "lambert" and "needs a lattice" in state.message and state.dirty
    actions.apply(Action("panel_rect", (10, 10, 200, 300)))
    assert state.panel_rect == (10, 10, 200, 300) and state.panel_frames == 1
    actions.move_camera("orbit", 30, 0)
    assert state.camera.azimuth == 40 and state.interacting(time.perf_counter())
    actions.apply(Action("reset_camera"))
    assert state.camera == home
    actions.apply(Action("quit"))
    assert state.quit


def test_a_file_the_viewer_cannot_write_is_said_in_the_window():
    """A save that fails (a full disk: `WriteError`) sets the window's message; the viewer
    goes on."""
    from types import SimpleNamespace

    from isolume.app.render.camera import Camera
    from isolume.app.viewer.actions import Actions
    from isolume.app.viewer.draw import ViewState
    from isolume.app.viewer.panel import Action
    from isolume.app.viewer.state import ViewerState
    from isolume.volumes.errors import WriteError

    def full(path=None):
        raise WriteError("x.npz: cannot write the lattice: No space left on device; "
                         "nothing was written")

    home = Camera(azimuth=10, elevation=20)
    state = ViewerState(ViewState(1.0, "lambert", 1.0), home, home)
    actions = Actions(SimpleNamespace(value_range=(0.0, 2.0)), state, None, None,
                      illumination=None, saver=SimpleNamespace(save_lattice=full))
    actions.apply(Action("save_lattice"))
    assert "No space left on device" in state.message and not state.quit


def test_interactive_quality_backs_off_then_recovers():
    from isolume.app.viewer.draw import INTERACTIVE_MS, RENDER_SCALES, Quality

    q = Quality()
    q.adapt(5 * INTERACTIVE_MS, full_triangles=500_000)
    assert q.coarse and q.scale == 1.0  # the preview mesh first
    for _ in range(10):
        q.adapt(5 * INTERACTIVE_MS, full_triangles=500_000)
    assert q.scale == RENDER_SCALES[-1]
    q.adapt(0.1 * INTERACTIVE_MS, full_triangles=500_000)
    assert q.scale == RENDER_SCALES[-2]
    small = Quality()
    small.adapt(5 * INTERACTIVE_MS, full_triangles=1000)
    assert not small.coarse and small.scale < 1.0  # a small mesh gains nothing from it


def test_bricks_show_their_first_light_before_their_refinements():
    """`TexelUploader.upload` writes the bricks never uploaded (their first light) within
    `first_budget_s` before those uploaded already (the light refined) within `budget_s`;
    a `watch` clears as its bricks are written, though they are marked again meanwhile."""
    from types import SimpleNamespace

    from isolume.app.viewer.draw import TexelUploader

    class Textures:
        def __init__(self):
            self.lattice = SimpleNamespace(geometry=SimpleNamespace(shape=(32, 32, 32)))
            self.written = []

        def write_bricks(self, batch):
            self.written.extend(map(tuple, batch))
            return np.zeros((0, 3), np.int64)

    def flat(z, y, x):  # a texel of brick (z, y, x)
        return np.array([np.ravel_multi_index((8 * z + 1, 8 * y + 2, 8 * x + 3), (32, 32, 32))])

    textures = Textures()
    uploader = TexelUploader(textures)
    uploader.mark(flat(0, 0, 0))
    assert uploader.upload(None) == 1 and uploader.pending == 0
    uploader.mark(flat(0, 0, 0))  # refined
    uploader.mark(flat(3, 2, 1))  # first light
    watched = uploader.watch()
    textures.written.clear()
    assert uploader.upload(budget_s=0.0, first_budget_s=10.0) == 1  # no time for the rest
    assert textures.written == [(3, 2, 1)] and uploader.dirty[0, 0, 0]
    assert watched[0, 0, 0] and not watched[3, 2, 1]
    uploader.mark(flat(0, 0, 0))
    uploader.upload(None)
    assert not watched.any() and uploader.pending == 0
