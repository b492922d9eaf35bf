"""`isolume.show` (`app.notebook`): the notebook widget's frames through its API and
jupyter_rfb's events, the lazy bake refining them, closing, and the missing-EGL path.

Frames are drawn off-screen (EGL, else OSMesa) with no browser: `NotebookView.snapshot`
draws one now; `NotebookView.update` does what the kernel's timer does.
"""

from __future__ import annotations

import inspect
import time

import numpy as np
import pytest

pytest.importorskip("jupyter_rfb")

from isolume import volumes
from isolume.app.notebook import show
from isolume.volumes.errors import IsolumeError

SIZE = (160, 120)
"""Frames of the tests (W, H): small, for speed."""


@pytest.fixture(scope="module")
def engine():
    return volumes.load("synthetic:engine:64")


@pytest.fixture
def view(engine):
    """A view without the lazy bake (local shading)."""
    v = show(engine, size=SIZE, no_bake=True)
    yield v
    v.close()


def differs(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two uint8 frames (0–255)."""
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


def assert_picture(frame: np.ndarray) -> None:
    """`frame` is an (H, W, 3) uint8 picture of the surface, not a blank background."""
    assert frame.shape == (SIZE[1], SIZE[0], 3) and frame.dtype == np.uint8
    background = frame[0, 0]
    surface = np.any(frame != background, axis=-1).mean()
    assert 0.1 < surface < 0.95, surface
    assert frame.std() > 10


def pointer(kind: str, x: float, y: float, button: int = 1, modifiers=()) -> dict:
    """A jupyter_rfb pointer event (buttons from 1: left, 2: right, 3: middle)."""
    return {"type": kind, "x": x, "y": y, "button": button,
            "buttons": (button,) if kind != "pointer_up" else (), "modifiers": modifiers,
            "ntouches": 0, "touches": {}, "timestamp": 0.0}


def drag(view, start: tuple[float, float], end: tuple[float, float], **how) -> None:
    view.handle_event(pointer("pointer_down", *start, **how))
    view.handle_event(pointer("pointer_move", *end, **how))
    view.handle_event(pointer("pointer_up", *end, **how))


def test_messages_from_another_thread_are_handled_on_the_views_own(engine):
    """A kernel may deliver widget messages on another thread (ipykernel's subshells,
    JupyterLab's default): the drag, the slider and the frames they ask for run on the
    thread of the loop the view was made on, where its GL context is current."""
    import asyncio
    import threading

    async def session() -> tuple[set[int], float, int]:
        v = show(engine, size=SIZE, no_bake=True)
        try:
            first = v.snapshot()
            drawn_on: set[int] = set()
            get_frame = v.get_frame

            def recorded() -> np.ndarray | None:
                drawn_on.add(threading.get_ident())
                return get_frame()

            v.get_frame = recorded  # what jupyter_rfb calls to draw
            v._has_visible_views = True  # as a browser showing it says
            v._rfb_handle_msg(v, {"type": "resize", "width": SIZE[0], "height": SIZE[1]}, [])

            async def subshell() -> None:  # a thread with its own running loop
                message = {k: list(x) if isinstance(x, tuple) else x
                           for k, x in pointer("pointer_down", 50, 50).items()}
                v._rfb_handle_msg(v, message, [])
                v._rfb_handle_msg(v, {**message, "type": "pointer_move", "x": 90}, [])
                v._rfb_handle_msg(v, {**message, "type": "pointer_up", "x": 90}, [])
                v.controls.iso.value = v.controls.iso.value * 1.02
                await asyncio.sleep(0.3)  # what it schedules on its own loop runs

            other = threading.Thread(target=asyncio.run, args=(subshell(),))
            other.start()
            while other.is_alive():
                await asyncio.sleep(0.01)
            for _ in range(50):  # the calls sent to this loop run, and the frames they ask
                await asyncio.sleep(0.02)
            return drawn_on, differs(first, v.snapshot()), threading.get_ident()
        finally:
            v.close()

    drawn_on, change, home = asyncio.run(session())
    assert drawn_on == {home}
    assert change > 1


def test_show_takes_the_view_commands_options_and_defaults():
    """Every keyword but `volume`, `size` and `gl` is an ``isolume view`` option, with its
    default."""
    import argparse

    from isolume.app.viewer.command import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    defaults = vars(parser.parse_args([]))
    params = inspect.signature(show).parameters
    own = [name for name in params if name not in ("volume", "size", "gl")]
    assert own and all(name in defaults for name in own)
    assert {name: params[name].default for name in own} == {name: defaults[name]
                                                            for name in own}


def test_a_snapshot_changes_after_an_orbit_and_after_an_isovalue_change(view, engine):
    first = view.snapshot()
    assert_picture(first)
    view.orbit(60, 15)
    turned = view.snapshot()
    assert_picture(turned)
    assert differs(first, turned) > 5
    lo, hi = engine.value_range
    view.set_iso(lo + 0.7 * (hi - lo))
    other = view.snapshot()
    assert_picture(other)
    assert differs(turned, other) > 5
    assert view.controls.iso.value == pytest.approx(lo + 0.7 * (hi - lo))


def test_a_left_drag_orbits_and_the_wheel_zooms(view):
    before = view.snapshot()
    camera = view.scene.state.camera
    drag(view, (80, 60), (105, 50))
    assert view.scene.state.drag is None  # released
    moved = view.scene.state.camera
    assert moved.azimuth == pytest.approx((camera.azimuth - 25 * 0.4) % 360)
    assert moved.elevation == pytest.approx(camera.elevation - 10 * 0.4)
    dragged = view.snapshot()
    assert differs(before, dragged) > 2
    view.handle_event({"type": "wheel", "x": 80, "y": 60, "dx": 0.0, "dy": -100.0,
                       "buttons": (), "modifiers": (), "timestamp": 0.0})
    assert view.scene.state.camera.distance < moved.distance  # wheel up: closer
    assert differs(dragged, view.snapshot()) > 2


def test_shift_drag_pans_and_right_drag_turns_the_light(view):
    view.snapshot()
    camera = view.scene.state.camera
    drag(view, (80, 60), (100, 60), modifiers=("Shift",))
    assert view.scene.state.camera.pan[0] < camera.pan[0]  # the surface follows the pointer
    assert view.scene.state.camera.azimuth == camera.azimuth
    assert view.scene.state.view.light is None  # follows the camera until turned
    lit = view.snapshot()
    drag(view, (10, 60), (160, 60), button=2)  # 60° of azimuth
    assert view.scene.state.view.light is not None
    assert view.controls.azimuth.value == pytest.approx(view.scene.state.view.light[0])
    assert differs(lit, view.snapshot()) > 2


def test_the_light_and_shading_controls_drive_the_view(view):
    first = view.snapshot()
    view.controls.azimuth.value = (view.controls.azimuth.value + 120) % 360
    assert view.scene.state.view.light is not None
    lit = view.snapshot()
    assert differs(first, lit) > 5
    view.controls.shading.value = "lambert"
    assert view.scene.state.view.shading == "lambert"
    assert differs(lit, view.snapshot()) > 5
    assert "irradiance" not in view.controls.shading.options  # no lattice: not offered
    with pytest.raises(IsolumeError, match="needs a lattice"):
        view.set_shading("irradiance")


def test_a_resize_event_sets_the_frame_size(view):
    view.snapshot()
    view.handle_event({"type": "resize", "width": 200, "height": 100, "pwidth": 400,
                       "pheight": 200, "ratio": 2.0, "timestamp": 0.0})
    assert view.size == (200, 100)
    assert view.get_frame().shape == (100, 200, 3)  # CSS pixels: the browser scales


def test_bad_options_are_one_line_errors(engine):
    with pytest.raises(IsolumeError, match="shading 'glossy'"):
        show(engine, shading="glossy", no_bake=True)
    with pytest.raises(IsolumeError, match="bake-samples 0"):
        show(engine, bake_samples=0)
    with pytest.raises(IsolumeError, match="needs a lattice"):
        show(engine, shading="irradiance", no_bake=True)
    with pytest.raises(IsolumeError, match=r"bake_mode='bogus': expected one of irradiance, sh"):
        show(engine, bake_mode="bogus")
    with pytest.raises(IsolumeError, match=r"normals='sharp': expected one of smooth, gradient"):
        show(engine, normals="sharp", no_bake=True)


def test_without_egl_auto_falls_back_to_osmesa_and_egl_alone_says_what_to_do(
        engine, monkeypatch):
    """As on macOS, where EGL is missing: "auto" takes OSMesa where Mesa has it, and a
    forced EGL (or no OSMesa either) is a one-line error naming the desktop viewer."""
    import moderngl

    def no_egl(*_args, **_kwargs):
        raise Exception("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(moderngl, "create_standalone_context", no_egl)
    with pytest.raises(IsolumeError, match=r"EGL or OSMesa.*isolume view") as error:
        show(engine, size=SIZE, no_bake=True, gl="egl")
    assert "\n" not in str(error.value)
    view = show(engine, size=SIZE, no_bake=True, gl="auto")
    try:
        assert view.scene.gl.backend == "osmesa"
        assert_picture(view.snapshot())
    finally:
        view.close()


def wait_for_light(view, share: float = 0.5, timeout: float = 45.0) -> None:
    """Drive the view as the kernel's timer does until `share` of the texels near the
    displayed surface have the lazy bake's estimates (previews alone are not saved)."""
    bake = view.scene.illumination.bake
    deadline = time.perf_counter() + timeout
    while (bake.near_fraction(view.scene.state.view.iso) or 0.0) < share:
        assert time.perf_counter() < deadline, f"no light after {timeout} s: {bake.error}"
        assert bake.error is None, bake.error
        view.update()
        time.sleep(0.05)


@pytest.fixture(scope="module")
def lazy(engine, tmp_path_factory):
    """A view baking lazily into a new lattice file: its frames before and after the
    light arrived, its status text, what it held, and the file, once closed."""
    path = tmp_path_factory.mktemp("lazy") / "lazy.npz"
    view = show(engine, size=SIZE, lattice=path)
    try:
        scene = view.scene
        seen = {"shading": scene.state.view.shading, "first": view.snapshot()}
        wait_for_light(view)
        seen.update(lit=view.snapshot(), status=view.controls.status.value,
                    process=scene.illumination.bake.process, ctx=scene.gl.ctx)
    finally:
        view.close()
    return {**seen, "view": view, "path": path}


def test_the_lazy_bake_refines_the_frames(lazy):
    assert lazy["shading"] == "irradiance"
    assert_picture(lazy["first"])  # before any light arrived: the fallback shading
    assert_picture(lazy["lit"])
    assert differs(lazy["first"], lazy["lit"]) > 2
    assert "paths" in lazy["status"]  # the bake's progress is shown


def test_close_ends_the_bake_process_and_the_gl_context(lazy):
    view = lazy["view"]
    assert view.closed and not lazy["process"].is_alive()
    assert type(lazy["ctx"].mglo).__name__ == "InvalidObject"  # released
    assert lazy["path"].exists()  # the lattice file named was saved
    with pytest.raises(IsolumeError, match="closed"):
        view.snapshot()
    view.close()  # again: nothing left to do


def test_a_lattice_object_is_shown_from_a_temporary_file(engine, lazy):
    from isolume.baking import Lattice

    view = show(engine, size=SIZE, lattice=Lattice.load(lazy["path"]), no_bake=True)
    temporary = view.scene.temporary
    try:
        assert temporary.exists() and view.scene.state.view.shading == "irradiance"
        shown = view.snapshot()
        assert_picture(shown)
        assert differs(lazy["first"], shown) > 2  # lit by the lattice's texels,
        assert differs(lazy["lit"], shown) < differs(lazy["first"], shown)  # as baked
    finally:
        view.close()
    assert not temporary.exists()


NOTEBOOK = [
    # the view, displayed as a cell's last expression
    "import asyncio\n"
    "from isolume import volumes\n"
    "from isolume.app.notebook import show\n"
    "view = show(volumes.load('synthetic:engine:64'), size=(160, 120))\n"
    "view",
    # the kernel's event loop alone (no update() here) brings the lazy bake's light
    "iso = view.scene.state.view.iso\n"
    "bake = view.scene.illumination.bake\n"
    "for _ in range(450):\n"
    "    if (bake.near_fraction(iso) or 0.0) >= 0.5:\n"
    "        break\n"
    "    await asyncio.sleep(0.1)\n"
    "print(view.panel.model_id, bake.near_fraction(iso), bake.error)",
    "view.close()\n"
    "print(bake.process.is_alive(), view.closed)",
]
"""Cells run in a real kernel by `test_in_a_kernel_the_event_loop_refines_the_view`."""


def test_in_a_kernel_the_event_loop_refines_the_view(tmp_path):
    """In a Jupyter kernel the view shows as the picture beside its controls, and the
    kernel's event loop alone drives the lazy bake (the widget's timer)."""
    import nbclient
    import nbformat

    notebook = nbformat.v4.new_notebook(
        cells=[nbformat.v4.new_code_cell(source) for source in NOTEBOOK])
    nbclient.NotebookClient(notebook, timeout=90, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    shown, waited, closed = (cell.outputs for cell in notebook.cells)
    widget = shown[-1]["data"]["application/vnd.jupyter.widget-view+json"]
    model_id, fraction, error = waited[-1]["text"].split()
    assert widget["model_id"] == model_id  # the panel: picture and controls
    assert error == "None" and float(fraction) >= 0.5
    assert closed[-1]["text"].split() == ["False", "True"]


def test_a_view_made_outside_a_kernel_prints_nothing(engine, capsys):
    """A script's view (no IPython kernel) prints nothing on standard output: jupyter_rfb's
    output widget, displayed as the view is made, would print its repr there."""
    capsys.readouterr()
    v = show(engine, size=SIZE, no_bake=True)
    try:
        assert capsys.readouterr().out == ""
    finally:
        v.close()
