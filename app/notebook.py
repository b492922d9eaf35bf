"""`show`: the interactive view of a volume in Jupyter (``isolume.show``).

The view is the desktop viewer's picture drawn off-screen in the kernel and streamed to the
browser by `jupyter_rfb` (the remote frame buffer pygfx and fastplotlib use): JPEG while
the view moves, a lossless PNG once it rests. Drag to orbit (shift-drag or middle-drag:
pan; ctrl-drag or right-drag: turn the light), wheel to zoom; beside the picture, sliders
for the isovalue and the light's azimuth and elevation, the shading mode, and the lazy
bake's progress. The parts:

* `app.notebook_scene`: the drawing, surfaces and lazy bake on a headless GL context;
* `app.notebook_view`: the widget (`NotebookView`, a ``jupyter_rfb.RemoteFrameBuffer``):
  events, frames, the API tests and notebooks use;
* `app.notebook_controls`: the ipywidgets beside it.

Where EGL is missing the context falls back to OSMesa; where neither exists (macOS,
Windows) `show` raises `volumes.errors.IsolumeError` naming the desktop viewer.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from isolume import volumes
from isolume.app.viewer.command import DEFAULT_BAKE_SAMPLES, Options
from isolume.baking.config import DEFAULT_ENV

if TYPE_CHECKING:  # imported by `show` (jupyter_rfb and ipywidgets are optional)
    from isolume.app.notebook_view import NotebookView
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import LatticeOnFile


def show(volume: volumes.Volume, *, iso: float | None = None,
         lattice: str | os.PathLike[str] | Lattice | None = None,
         shading: str | None = None, size: tuple[int, int] = (640, 480),
         exposure: float = 1.0, no_auto_exposure: bool = False, no_bake: bool = False,
         bake_mode: str = "irradiance", bake_env: str = DEFAULT_ENV,
         bake_samples: int = DEFAULT_BAKE_SAMPLES, bake_workers: int | None = None,
         bake_max_levels: int = 64, normals: str = "smooth", flip_normals: bool = False,
         gl: str = "auto") -> NotebookView:
    """An interactive view of `volume`'s isosurface in a Jupyter notebook.

    The keywords are those of ``isolume view`` (``--bake-env`` is `bake_env`; the same
    defaults and checks, and errors name the option). Displaying the returned
    `app.notebook_view.NotebookView` (the last expression of a cell, or
    ``IPython.display.display``) shows the picture with its controls beside it
    (``view.panel``, an ``ipywidgets.HBox`` of the view and ``view.controls.box``); its
    methods (``orbit``, ``zoom``, ``pan``, ``set_iso``, ``set_light``, ``set_shading``,
    ``snapshot``, ``close``) drive it from code. Outside a running kernel's event loop
    (a script, a test) nothing refreshes by itself: ``snapshot`` and ``update`` do.

    Args:
        volume: the scalar field (`volumes.Volume`).
        iso: the isovalue (None: the first suggested, `volumes.suggest_isovalues`).
        lattice: an illumination lattice: a ``.npz`` path (shown and, when incomplete,
            baked further lazily; a new file is created; saved on `close`), a
            `baking.Lattice` (shown, and baked further, from a temporary copy: pass a path
            to keep the result), or None (a new one baked lazily unless `no_bake`).
        shading: the shading mode (`app.render.settings.SHADING_MODES`; None: irradiance
            when a lattice is shown or baked, else phong_hemi).
        size: (W, H) of the picture in CSS pixels (frames are drawn at this size).
        exposure, no_auto_exposure: linear exposure multiplier, on the automatic exposure
            unless `no_auto_exposure`.
        no_bake: no lazy bake (local shading, or `lattice` as it is).
        bake_mode, bake_env, bake_samples, bake_workers, bake_max_levels: the lazy bake of
            a new lattice (``isolume view --bake-*``).
        normals, flip_normals: shading normals ("smooth" or "gradient"), and their flip
            for material less dense than air.
        gl: the headless OpenGL: "auto" (EGL, then Mesa's OSMesa), "egl" or "osmesa".

    Returns:
        The widget, an `app.notebook_view.NotebookView`.

    Raises:
        volumes.errors.IsolumeError: a bad option, a lattice file that does not fit,
            jupyter_rfb or ipywidgets missing, or no headless OpenGL (macOS has no EGL).
    """
    from isolume.app.options import isovalue

    view_class = notebook_view_class()
    iso = isovalue(volume, iso)
    options = view_options(volume, size, lattice, shading=shading, exposure=exposure,
                           no_auto_exposure=no_auto_exposure, no_bake=no_bake,
                           bake_mode=bake_mode, bake_env=bake_env, bake_samples=bake_samples,
                           bake_workers=bake_workers, bake_max_levels=bake_max_levels,
                           normals=normals, flip_normals=flip_normals)
    opened, temporary = open_lattice(lattice, volume, options)
    try:
        return view_class(volume, iso, opened, options, gl=gl, temporary=temporary)
    except BaseException:
        if temporary is not None:
            temporary.unlink(missing_ok=True)
        raise


def notebook_view_class() -> type[NotebookView]:
    """`app.notebook_view.NotebookView`, or a one-line `IsolumeError` when the notebook
    extras are missing."""
    from isolume.volumes.errors import IsolumeError

    try:
        from isolume.app.notebook_view import NotebookView
    except ImportError as exc:
        raise IsolumeError(f"isolume.show needs jupyter_rfb and ipywidgets ({exc}): "
                           "pip install 'isolume[notebook]'") from None
    return NotebookView


def view_options(volume: volumes.Volume, size: tuple[int, int],
                 lattice: str | os.PathLike[str] | Lattice | None, **chosen: Any) -> Options:
    """The checked `app.viewer.command.Options` of ``isolume view`` with `chosen` (its
    options by their argparse names) and the picture `size` (W, H); `lattice` a path
    becomes ``--lattice``.

    Raises:
        volumes.errors.IsolumeError: as ``isolume view`` would (`read_options`).
    """
    from isolume.app.render.settings import LATTICE_MODES
    from isolume.app.viewer.command import add_arguments, read_options
    from isolume.app.viewer.state import ViewerError

    parser = argparse.ArgumentParser(prog="isolume.show")
    add_arguments(parser)
    args = parser.parse_args([])
    _check_choices(parser, chosen)
    vars(args).update(chosen)
    args.volume = volume.source if isinstance(volume.source, str) else None
    args.size = "x".join(str(int(v)) for v in size)
    args.lattice = os.fspath(lattice) if isinstance(lattice, (str, os.PathLike)) else None
    options = read_options(args)
    if options.shading in LATTICE_MODES and lattice is None and not options.bake:
        raise ViewerError(f"shading {options.shading} needs a lattice: pass lattice=, or "
                          "leave out no_bake=True to bake one lazily")
    return options


def _check_choices(parser: argparse.ArgumentParser, chosen: dict[str, Any]) -> None:
    """Raise `ViewerError` where a value of `chosen` (None: the option's default) is not
    one of its option's choices in `parser`, as argparse would for the command line
    (`app.options.choice_error`)."""
    from isolume.app.options import choice_error
    from isolume.app.viewer.state import ViewerError

    for action in parser._actions:  # argparse keeps no public list of them
        message = choice_error(action, action.dest, chosen.get(action.dest))
        if message is not None:
            raise ViewerError(f"isolume.show: {message}")


def open_lattice(lattice: str | os.PathLike[str] | Lattice | None, volume: volumes.Volume,
                 options: Options) -> tuple[LatticeOnFile | None, Path | None]:
    """(`lattice` opened for the viewer, a `baking.view_texels.LatticeOnFile` or None;
    the temporary file it was written to, or None).

    A path is opened when it exists (a new one: None, baked into and saved on close); a
    `baking.Lattice` is written to a temporary file and opened from it (the view
    deletes it when it closes: a turned sun's bake reads it again).

    Raises:
        baking.BakeError: the file does not hold a lattice of `volume`.
    """
    from isolume.baking import Lattice
    from isolume.baking.view_texels import LatticeOnFile

    if isinstance(lattice, Lattice):
        handle, name = tempfile.mkstemp(suffix=".npz", prefix="isolume-show-")
        os.close(handle)
        path = Path(name)
        lattice.save(path)
        return LatticeOnFile.open(path, volume), path
    path = options.lattice_path
    if path is None or not path.exists():
        return None, None
    return LatticeOnFile.open(path, volume), None
