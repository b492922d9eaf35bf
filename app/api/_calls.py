"""The Python API's functions: each a command of the same name, in this process.

Each function turns its keyword arguments into the command's parsed options
(`isolume._arguments.namespace`) and runs the code the command runs (`app.commands`,
`app.export`, `app.movie`, `app.reference`): the same checks, messages and results.
"""

from __future__ import annotations

import atexit
import functools
import os
import threading
import warnings
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Literal, ParamSpec, TypeVar

import numpy as np

from isolume._arguments import OptionError, keyword_message, namespace, shown
from isolume.baking.config import DEFAULT_ENV
from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    from isolume._picture import Picture
    from isolume.app.notebook import NotebookView
    from isolume.app.state import SavedView
    from isolume.baking.lattice import Lattice
    from isolume.volumes.core import Volume
    from isolume.volumes.stats import VolumeInfo

PathText = str | os.PathLike[str]
Numbers = Sequence[float]


P = ParamSpec("P")
R = TypeVar("R")


def _keywords_named(command: str) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Decorator: an `IsolumeError` out of the function names the options of `command`
    as the function's keywords (`_arguments.keyword_message`: ``size='0x5': …`` where
    the command says ``--size '0x5': …``)."""
    def decorate(function: Callable[P, R]) -> Callable[P, R]:
        @functools.wraps(function)
        def call(*args: P.args, **kwargs: P.kwargs) -> R:
            try:
                return function(*args, **kwargs)
            except IsolumeError as exc:
                exc.args = (keyword_message(command, str(exc)), *exc.args[1:])
                raise
        return call
    return decorate


@_keywords_named("render")
def load(source: Volume | str | os.PathLike[str] | np.ndarray, *,
         dims: Sequence[int] | str | None = None, dtype: str | None = None,
         spacing: Numbers | str | None = None, up: str | None = None,
         crop: str | None = None, downsample: int = 1, level: int | None = None,
         origin: Numbers | str | None = None, name: str = "array") -> Volume:
    """A volume: a file (raw, NRRD, NIfTI, TIFF, DICOM, Zarr, .npy…), ``synthetic:NAME
    [:SIZE]``, a (Z, Y, X) numpy array, or a `Volume` (its part, turned as asked).

    Args:
        dims: X,Y,Z samples of a raw file whose name does not say.
        dtype: sample type of a raw file (uint8, int16, float32…).
        spacing: (x, y, z) voxel size, world units (overrides the file's; an array's,
            default 1).
        up: the axis that points up (x, y, z, -x, -y, -z).
        crop: ``X0:X1,Y0:Y1,Z0:Z1`` voxel ranges to read (end exclusive).
        downsample: means of N×N×N blocks.
        level: level of an OME-Zarr multiscale image.
        origin: (x, y, z) world position of the first sample (overrides the file's; an
            array's, default 0).
        name: an array's name in messages and pictures.

    Raises:
        IsolumeError: a bad file, source or value (one line naming it).
    """
    from isolume import volumes
    from isolume.app.options import load_volume

    text = _source(source, "source")
    args = namespace("info", {"volume": text if isinstance(text, str) else None, "dims": dims,
                              "dtype": dtype, "spacing": spacing, "origin": origin, "up": up,
                              "crop": crop, "downsample": downsample, "level": level})
    if isinstance(source, np.ndarray):
        source = volumes.Volume(source, spacing=_triple(spacing, "spacing", 1.0),
                                origin=_triple(origin, "origin", 0.0), name=name, source=name)
    if not isinstance(source, volumes.Volume):
        return load_volume(args)  # the file or spec, its part, turned by args.up
    volume = volumes.crop_downsample(source, args.volume_crop, args.volume_downsample)
    return volume if up is None else volumes.turn_up(volume, up)


def _source(source: object, keyword: str) -> str | np.ndarray | Volume:
    """`source`, given as keyword `keyword`, as the volume option stores it: a path's
    text, a spec, an array or a `Volume` as it is; `OptionError` for anything else."""
    from isolume import volumes

    if isinstance(source, (str, os.PathLike)):
        return os.fspath(source)
    if isinstance(source, (np.ndarray, volumes.Volume)):
        return source
    raise OptionError(f"{keyword}={shown(source)}: expected a file path, a "
                      "'synthetic:NAME[:SIZE]' spec, a (Z, Y, X) numpy array or a Volume")


@_keywords_named("info")
def info(volume: Volume | str | os.PathLike[str]) -> VolumeInfo:
    """What ``isolume info`` says of `volume` (a `Volume`, or what `load` takes): dims,
    spacing, placement, value range, histogram (``counts``, ``edges``) and suggested
    isovalues; printed, the command's text."""
    from isolume.volumes.stats import VolumeInfo

    return VolumeInfo.of(_volume(volume))


def _triple(values: Numbers | str | None, what: str, default: float) -> tuple[float, ...]:
    from isolume.app.options import floats

    if values is None:
        return (default,) * 3
    if isinstance(values, str):
        return floats(values, 3, what)
    return floats(",".join(str(v) for v in values), 3, what)


NOT_OPTIONS = ("volume", "state", "timeline")
"""Keywords of the functions that are not their command's options as such."""


def _options(call: dict[str, object], *leave: str) -> dict[str, object]:
    """The keyword arguments of a call (its ``locals()`` on entry) that its command takes
    as options: all but `NOT_OPTIONS` and `leave`."""
    return {name: value for name, value in call.items() if name not in NOT_OPTIONS + leave}


def _volume(volume: Volume | str | os.PathLike[str] | np.ndarray) -> Volume:
    """The `Volume` of a function's `volume`: as it is, or what `load` makes of it."""
    from isolume import volumes

    if isinstance(volume, volumes.Volume):
        return volume
    return load(_source(volume, "volume"))


class _Session:
    """What this process's renders keep (`app.render.offscreen.Reuse`), behind a lock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.reuse = None

    def kept(self):
        from isolume.app.render.offscreen import Reuse

        if self.reuse is None:
            self.reuse = Reuse()
            atexit.register(self.release)
        return self.reuse

    def release(self) -> None:
        if self.reuse is not None:
            self.reuse.release()
            self.reuse = None


_SESSION = _Session()


@contextmanager
def _running(args, timeline: PathText | None, words: list[str]):
    """Use ``args.workers`` threads (`volumes.cores.use`) and record the `timeline`."""
    from isolume.volumes import cores

    cores.use(getattr(args, "workers", None))
    with cores.recording(None if timeline is None else os.fspath(timeline), command=words):
        yield


def _with_state(args, state: SavedView | PathText | None, given: dict):
    """`args` with the defaults of the saved view `state` for every keyword not given a
    value other than its default (`app.state.apply_saved`)."""
    if state is None:
        return args
    from isolume.app.state import SavedView, apply_saved, load_state

    saved = state if isinstance(state, SavedView) else load_state(state)
    out = args.out
    args = apply_saved(args, saved, state if not isinstance(state, SavedView) else "view",
                       {name for name, value in given.items() if value is not None} | {"volume"})
    args.out = out
    return args


@_keywords_named("render")
def render(volume: Volume | str | os.PathLike[str], *, iso: float | None = None,
           lattice: Lattice | PathText | None = None, env: str | None = None,
           light: str | Sequence[str] | None = None, samples: int | None = None,
           spread: Literal["noise", "even"] = "noise",
           bounces: int = 2, seed: int = 0, workers: int | None = None,
           albedo: float | Numbers | str | None = None,
           env_rotation: Numbers | str = (0, 0),
           sh_window: Literal["none", "hanning", "lanczos"] = "none",
           exposure: float = 1.0, no_auto_exposure: bool = False,
           tonemap: str = "aces", normals: Literal["smooth", "gradient"] = "smooth",
           flip_normals: bool = False, shading: str | None = None,
           size: tuple[int, int] | str = (512, 512), view: Numbers | str = (30, 30),
           gl: Literal["auto", "egl", "osmesa"] = "auto",
           shadows: Literal["traced", "map"] = "traced", out: PathText | None = None,
           state: SavedView | PathText | None = None,
           timeline: PathText | None = None) -> Picture:
    """Render the isosurface, as ``isolume render`` does (its options, the same
    defaults): without a lattice, the view's global illumination is traced for the
    texels the picture reads; `out` also writes it (PNG or EXR). The GL context and the
    surface of the last volume and isovalue are kept for the next call.

    Args:
        volume: a `Volume` (`load`), or what `load` takes.
        size: (width, height) pixels; view: (azimuth, elevation[, distance]) degrees and
            box diagonals; env_rotation, albedo: numbers or the options' text.
        state: a saved view (`View` or its file), whose values fill the keywords left at
            their defaults.

    Returns:
        The `Picture` (sRGB and linear pixels; a notebook shows it).
    """
    given = _options(locals(), "out")
    from isolume._picture import Picture
    from isolume.app.commands import render_picture

    args = namespace("render", given | {"volume": _volume(volume)})
    args = _with_state(args, state, _changed("render", given))
    with _SESSION.lock, _running(args, timeline, ["render"]):
        rendered = render_picture(args, reuse=_SESSION.kept())
    frame = rendered.frame
    picture = Picture(frame.srgb, frame.linear, frame.mask, float(frame.exposure),
                      float(rendered.iso), len(rendered.mesh.faces), rendered.summary())
    if out is not None:
        picture.save(out)
    return picture


def _changed(command: str, given: dict) -> dict:
    """The keywords of `given` whose values differ from `command`'s defaults."""
    defaults = namespace(command, {})
    reference = namespace(command, given)
    return {name: value for name, value in given.items()
            if getattr(reference, name, None) != getattr(defaults, name, None)}


@_keywords_named("bake")
def bake(volume: Volume | str | os.PathLike[str], *, out: PathText | None = None,
         mode: Literal["irradiance", "sh"] = "irradiance", sh_order: int = 5,
         samples: int | None = None, target_error: float | None = None,
         texel_error: float | None = None, max_samples: int = 1024,
         bounces: int = 2, albedo: float | Numbers | str = 0.8, scale: float = 1.0,
         iso_range: tuple[float, float] | None = None, env: str = DEFAULT_ENV,
         light: str | Sequence[str] | None = None, seed: int = 0, max_levels: int = 64,
         max_move: float | None = None,
         direct_light: Literal["pixels", "lattice"] | None = None,
         workers: int | None = None, scene_memory: float | None = None,
         scheduler: str | None = None,
         flip_normals: bool = False, sides: Literal["seen", "normals"] = "seen",
         timeline: PathText | None = None) -> Lattice:
    """Bake an illumination lattice, as ``isolume bake`` does (its options, the same
    defaults), with a progress bar (a widget in a notebook). `out` (FILE.npz) also
    writes it, and resumes a compatible lattice there. An interrupt (Ctrl-C, a notebook's
    stop) returns the finished texels (``meta["interrupted"]``; saved in `out` too) with
    a warning.

    Returns:
        The lattice (`Lattice`: `save`, `sample`; `render(…, lattice=…)` shows it).
    """
    given = _options(locals())
    from isolume.app.commands import bake_lattice

    args = namespace("bake", given | {"volume": _volume(volume)})
    with _running(args, timeline, ["bake"]):
        lattice = bake_lattice(args, dense=True, keep_interrupted=True)
    if lattice.meta.get("interrupted"):
        finished = int((lattice.samples > 0).sum())
        saved = f"; saved in {out} (the same call resumes)" if out is not None else ""
        warnings.warn(f"bake interrupted: {finished:,} finished texels returned{saved}",
                      stacklevel=2)
    return lattice


def _run_command(module: str, args) -> int:
    """Run the command of `module` (its ``run``) on the parsed options `args`."""
    import importlib

    with _running(args, None, [args.command]):
        return importlib.import_module(module).run(args)


@_keywords_named("export")
def export(volume: Volume | str | os.PathLike[str], out: PathText, *,
           iso: float | None = None, lattice: Lattice | PathText | None = None,
           env: str | None = None, light: str | Sequence[str] | None = None,
           samples: int | None = None, spread: Literal["noise", "even"] = "noise",
           bounces: int = 2, seed: int = 0,
           workers: int | None = None, albedo: float | Numbers | str | None = None,
           env_rotation: Numbers | str = (0, 0),
           sh_window: Literal["none", "hanning", "lanczos"] = "none",
           exposure: float = 1.0, no_auto_exposure: bool = False, tonemap: str = "aces",
           normals: Literal["smooth", "gradient"] = "smooth",
           flip_normals: bool = False) -> Path:
    """Write the lit isosurface as a mesh (PLY, OBJ, glTF/GLB…), as ``isolume export``
    does (its options, the same defaults): vertex colours carry the global illumination.

    Returns:
        The file written.
    """
    values = _options(locals()) | {"volume": _volume(volume)}
    _run_command("isolume.app.export", namespace("export", values))
    return Path(out)


@_keywords_named("movie")
def movie(volume: Volume | str | os.PathLike[str], out: PathText, *,
          kind: Literal["turntable", "light", "iso"] = "turntable",
          sweep: str | None = None, frames: int = 72, fps: float = 24.0,
          turntable_light: Literal["camera", "world"] | None = None,
          degrees: float = 360.0, iso_range: tuple[float, float] | None = None,
          save_lattice: PathText | None = None, meter_frames: int = 4, crf: int = 18,
          iso: float | None = None, lattice: Lattice | PathText | None = None,
          env: str | None = None, light: str | Sequence[str] | None = None,
          samples: int | None = None, spread: Literal["noise", "even"] = "noise",
          bounces: int = 2, seed: int = 0,
          workers: int | None = None, albedo: float | Numbers | str | None = None,
          env_rotation: Numbers | str = (0, 0),
          sh_window: Literal["none", "hanning", "lanczos"] = "none",
          exposure: float = 1.0, no_auto_exposure: bool = False, tonemap: str = "aces",
          normals: Literal["smooth", "gradient"] = "smooth", flip_normals: bool = False,
          shading: str | None = None, size: tuple[int, int] | str = (512, 512),
          view: Numbers | str = (30, 30), gl: Literal["auto", "egl", "osmesa"] = "auto",
          shadows: Literal["traced", "map"] = "traced",
          state: SavedView | PathText | None = None) -> Path:
    """Make a movie (MP4, or a folder of PNG frames: an existing folder, or an `out`
    without a suffix), as ``isolume movie`` does (its options, the same defaults): a
    turntable, a turning light or an isovalue sweep.

    Returns:
        The file or folder written.
    """
    from isolume.app.movie_output import is_folder

    given = _options(locals())
    if not Path(out).suffix and not is_folder(os.fspath(out)):
        given["out"] = os.path.join(os.fspath(out), "")  # a folder of frames
    args = namespace("movie", given | {"volume": _volume(volume)})
    _run_command("isolume.app.movie", _with_state(args, state, _changed("movie", given)))
    return Path(out)


@_keywords_named("reference")
def reference(volume: Volume | str | os.PathLike[str], out: PathText, *,
              iso: float | None = None, spp: int = 64,
              size: tuple[int, int] | str = (512, 512), view: Numbers | str = (30, 30),
              env: str = DEFAULT_ENV, env_rotation: Numbers | str = (0, 0),
              light: str | Sequence[str] | None = None, albedo: float | Numbers | str = 0.8,
              bounces: int = 2, seed: int = 0, workers: int | None = None,
              normals: Literal["smooth", "gradient"] = "smooth",
              flip_normals: bool = False) -> Path:
    """Path-trace a reference image (FILE.exr, with FILE.json and a resumable state), as
    ``isolume reference`` does (its options, the same defaults); a second call with more
    `spp` adds to it. An interrupt keeps the finished passes, with a warning.

    Returns:
        The EXR written.
    """
    values = _options(locals()) | {"volume": _volume(volume)}
    from isolume.app.options import EXIT_INTERRUPTED  # after locals(): not an option

    if _run_command("isolume.app.reference", namespace("reference", values)) \
            == EXIT_INTERRUPTED:
        warnings.warn(f"reference interrupted; the finished passes are saved in {out}",
                      stacklevel=2)
    return Path(out)


@_keywords_named("view")
def show(volume: Volume | str | os.PathLike[str], *, iso: float | None = None,
         lattice: Lattice | PathText | None = None, shading: str | None = None,
         size: tuple[int, int] | str = (640, 480), exposure: float = 1.0,
         no_auto_exposure: bool = False, no_bake: bool = False,
         bake_mode: Literal["irradiance", "sh"] = "irradiance", bake_env: str = DEFAULT_ENV,
         bake_samples: int = 256, bake_workers: int | None = None, bake_max_levels: int = 64,
         normals: Literal["smooth", "gradient"] = "smooth", flip_normals: bool = False,
         gl: Literal["auto", "egl", "osmesa"] = "auto") -> NotebookView:
    """An interactive view in a notebook, as ``isolume view`` is on the desktop (its
    options, the same defaults, but a notebook-sized picture): drag to orbit, wheel to
    zoom, sliders for the isovalue and the light, the shading mode; drawn off-screen
    (EGL) in the kernel and streamed to the browser (jupyter_rfb), the lazy bake
    refining the global illumination (`isolume.app.notebook`). `gl`: EGL, else OSMesa
    ("auto"); where neither exists (macOS) an `IsolumeError` says to use ``isolume
    view``."""
    given = _options(locals())
    from isolume.app.notebook import show as notebook_show
    from isolume.app.options import parse_size

    args = vars(namespace("view", given))  # each keyword converted and checked
    args["size"] = parse_size(args["size"])
    return notebook_show(_volume(volume), **{name: args[name] for name in given})
