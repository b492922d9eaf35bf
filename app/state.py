"""Saved views (``--state FILE``): a small JSON file that holds what the viewer shows, from
which ``isolume view``, ``render`` and ``movie`` start.

The file (`SavedView`, written by the viewer's "save view", read by `load_state`) names
the volume and its load options as the command line takes them, the isovalue, the camera,
the lighting, the shading, the exposure, the tone curve and the lattice; docs/state.md
describes its fields. `apply_state` makes them the defaults of a command: an option the
command line spells out (`given_options`) wins over the file. Paths are written absolute;
relative ones (a hand-written file) are read against the file's folder.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from isolume.app.options import CLIError, parse_albedo, parse_size
from isolume.app.render.camera import Camera, parse_view
from isolume.app.render.settings import SHADING_MODES, TONEMAPS
from isolume.volumes.errors import IsolumeError
from isolume.volumes.writing import atomic_write

if TYPE_CHECKING:
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice, LatticeOnFile

FORMAT = "isolume view"
"""The ``format`` field of every state file."""
VERSION = 1
"""The ``version`` written, and the newest one read."""
SUFFIX = ".view.json"
"""The ending of the state files the viewer names itself."""
SYNTHETIC = "synthetic:"
"""Volumes named by this prefix are built, not read from a file."""
STATE_ONLY = ("camera", "light_angles")
"""What `apply_state` gives a command beyond its options: the saved camera (an
`app.render.camera.Camera`) and the world-fixed light's angles (`SavedView.light_angles`);
None without ``--state``."""
PART_OPTIONS = {"crop": "volume_crop", "downsample": "volume_downsample",
                "level": "volume_level"}
"""The fields of the part of the volume read (``--crop``, ``--downsample``, ``--level``) →
their names in a command's namespace (`app.options.add_volume_options`)."""


class StateError(IsolumeError):
    """A state file that cannot be used; the message names the file and says why."""


class _StateOption(argparse.Action):
    """``--state FILE``: keeps the file and, for `given_options`, the command's parser
    (as ``state_parser``)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        namespace.state_parser = parser


def add_state_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--state FILE`` to a command's `parser` (`apply_state` reads it), and the
    `STATE_ONLY` names to its namespace."""
    parser.add_argument("--state", metavar="FILE", action=_StateOption,
                        help="start from a view saved by the viewer (V, or the panel's "
                        "'save view'); options given here win over the file's")
    parser.set_defaults(**dict.fromkeys(STATE_ONLY))


# -- the file -------------------------------------------------------------------------------
@dataclass(frozen=True)
class VolumeSource:
    """The volume as the command line names it (the viewer's, kept for its saved views).

    Attributes:
        volume: a file path or ``synthetic:NAME[:SIZE]`` (None: a state file that names
            none).
        dims, dtype, spacing, origin, up, crop: the load options' text (``--dims X,Y,Z``
            ...), or None.
        downsample, level: ``--downsample N`` and ``--level K``, or None.
    """

    volume: str | None = None
    dims: str | None = None
    dtype: str | None = None
    spacing: str | None = None
    origin: str | None = None
    up: str | None = None
    crop: str | None = None
    downsample: int | None = None
    level: int | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> VolumeSource:
        """The volume options of `args`, a file's path made absolute (None: the default
        volume, `volumes.DEFAULT`)."""
        from isolume import volumes

        spec = args.volume or volumes.DEFAULT
        if not spec.startswith(SYNTHETIC):
            spec = os.path.abspath(spec)
        parts = {name: getattr(args, dest, None) for name, dest in PART_OPTIONS.items()}
        return cls(spec, args.dims, args.dtype, args.spacing, getattr(args, "origin", None),
                   args.up, **parts)


@dataclass(frozen=True)
class SavedView(VolumeSource):
    """What a state file holds; None (``null`` in the file): not saved, the command's
    default applies.

    Attributes:
        volume, dims, dtype, spacing, origin, up, crop, downsample, level: the volume (the
            fields of `VolumeSource`, first in the file).
        iso: the isovalue, field units.
        camera: the whole camera (degrees; distance and pan in units of its scale, a world
            length; target in world units).
        size: ``WxH`` pixels of the picture.
        shading, tonemap, normals: as the options of the same names.
        exposure: the linear exposure multiplier; auto_exposure: whether it multiplies the
            automatic exposure.
        shown_exposure: the linear exposure of the picture as the viewer showed it (the
            multiplier times the automatic exposure as it stood); ``render`` and ``movie``
            draw with it, fixed, unless ``--exposure`` or ``--no-auto-exposure`` is given
            (``view`` meters again).
        albedo: ``A`` or ``R,G,B``.
        env, lights: the lighting specs (``--env``, ``--light``); None and (): the
            lattice's own, or the command's default.
        light_angles: (azimuth, elevation) degrees of the world-fixed light the viewer
            turned (the key light, the environment in "sh", a lattice's per-pixel sun);
            None: the light follows the camera.
        lattice: the lattice file shown.
        flip_normals: material less dense than air.
    """

    iso: float | None = None
    camera: Camera | None = None
    size: str | None = None
    shading: str | None = None
    exposure: float | None = None
    auto_exposure: bool | None = None
    shown_exposure: float | None = None
    tonemap: str | None = None
    albedo: str | None = None
    env: str | None = None
    lights: tuple[str, ...] = ()
    light_angles: tuple[float, float] | None = None
    lattice: str | None = None
    normals: str | None = None
    flip_normals: bool | None = None

    def to_json(self) -> dict[str, object]:
        """The file's JSON object: ``format`` and ``version`` first, then every field."""
        data = {"format": FORMAT, "version": VERSION} | asdict(self)
        camera = self.camera
        if camera is not None:
            data["camera"] = {"azimuth": float(camera.azimuth),
                              "elevation": float(camera.elevation),
                              "distance": float(camera.distance),
                              "target": [float(v) for v in camera.target],
                              "scale": float(camera.scale), "fov_y": float(camera.fov_y),
                              "pan": [float(v) for v in camera.pan]}
        data["lights"] = list(self.lights)
        angles = self.light_angles
        data["light_angles"] = None if angles is None else [float(v) for v in angles]
        return data

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> SavedView:
        """The state file at `path` (`load_state`)."""
        return load_state(path)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the state to `path` (`layout`), whole or not at all
        (`volumes.writing.atomic_write`); returns the path."""
        path = Path(path)
        text = layout(self.to_json()) + "\n"
        atomic_write(path, lambda tmp: Path(tmp).write_text(text), "view")
        return path

    @classmethod
    def from_json(cls, data: object, source: Path) -> SavedView:
        """The state of the JSON value `data` read from the file `source` (relative paths
        in it are taken from the file's folder).

        Raises:
            StateError: not a state, a newer version, an unknown field or a bad value.
        """
        where = f"--state {source}"
        _check_header(data, where)
        values = {}
        for key, read in _READERS.items():
            if data.get(key) is None:
                continue
            try:
                values[key] = read(data[key])
            except (ValueError, TypeError) as exc:
                raise StateError(f"{where}: {key} {json.dumps(data[key])}: {exc}") from None
        for key in ("volume", "lattice"):
            if key in values:
                values[key] = _from_folder(values[key], source.parent)
        return cls(**values)

    def option_values(self) -> dict[str, object]:
        """{namespace name: value} of the options the state gives (None: it gives none);
        a command takes those it has (``env`` is ``bake_env`` in the viewer)."""
        values: dict[str, object] = {
            name: getattr(self, name) for name in
            ("volume", "dims", "dtype", "spacing", "origin", "up", "iso", "size", "shading",
             "exposure", "tonemap", "albedo", "env", "lattice", "normals", "flip_normals")}
        values |= {dest: getattr(self, name) for name, dest in PART_OPTIONS.items()}
        values["bake_env"] = self.env
        values["light"] = list(self.lights) or None
        if self.auto_exposure is not None:
            values["no_auto_exposure"] = not self.auto_exposure
        if self.camera is not None:
            c = self.camera
            values["view"] = f"{c.azimuth!r},{c.elevation!r},{c.distance!r}"
        if self.light_angles is not None:
            azimuth, elevation = self.light_angles
            values["env_rotation"] = f"{azimuth!r},{elevation!r}"
        return values


def layout(value: object, indent: str = "") -> str:
    """JSON text of `value`: an object one member a line (indented by two spaces a level),
    anything else on one line."""
    if not isinstance(value, dict):
        return json.dumps(value)
    inner = indent + "  "
    members = [f"{inner}{json.dumps(key)}: {layout(v, inner)}" for key, v in value.items()]
    return "{\n" + ",\n".join(members) + f"\n{indent}}}"


# -- reading the fields ---------------------------------------------------------------------
def _text(value) -> str:
    if not isinstance(value, str):
        raise ValueError("expected a string")
    return value


def _number(value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError("expected a finite number")
    return float(value)


def _positive(value) -> float:
    if _number(value) <= 0:
        raise ValueError("expected a positive number")
    return float(value)


def _whole(value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError("expected a whole number from 0")
    return value


def _flag(value) -> bool:
    if not isinstance(value, bool):
        raise ValueError("expected true or false")
    return value


def _numbers(value, count: int) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != count:
        raise ValueError(f"expected a list of {count} numbers")
    return tuple(_number(v) for v in value)


def _texts(value) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise ValueError("expected a list of strings")
    return tuple(_text(v) for v in value)


def _elevation(value) -> float:
    elevation = _number(value)
    if abs(elevation) > 90:
        raise ValueError(f"elevation {elevation:g} is outside [-90, 90]")
    return elevation


def _angles(value) -> tuple[float, float]:
    azimuth, elevation = _numbers(value, 2)
    return azimuth, _elevation(elevation)


def _camera(value) -> Camera:
    """A `Camera` of the JSON object `value`: azimuth, elevation, distance, target and
    scale required, fov_y and pan optional."""
    if not isinstance(value, dict):
        raise ValueError("expected an object with azimuth, elevation, distance, target, scale")
    readers = {"azimuth": _number, "elevation": _elevation,
               "distance": _positive, "target": lambda v: _numbers(v, 3), "scale": _positive,
               "fov_y": _positive, "pan": lambda v: _numbers(v, 2)}
    unknown = sorted(set(value) - set(readers))
    missing = [key for key in ("azimuth", "elevation", "distance", "target", "scale")
               if key not in value]
    if unknown or missing:
        raise ValueError(f"unknown {', '.join(unknown)}" if unknown
                         else f"missing {', '.join(missing)}")
    return Camera(**{key: readers[key](v) for key, v in value.items()})


def _choice(choices: Sequence[str]) -> Callable[[object], str]:
    """A reader of one of `choices`."""
    def read(value) -> str:
        if _text(value) not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}")
        return value
    return read


def _size(value) -> str:
    parse_size(_text(value))
    return value


def _albedo(value) -> str:
    parse_albedo(_text(value))
    return value


_READERS: dict[str, Callable[[object], object]] = {
    "volume": _text, "dims": _text, "dtype": _text, "spacing": _text, "origin": _text,
    "up": _text,
    "crop": _text, "downsample": _whole, "level": _whole,
    "iso": _number, "camera": _camera, "size": _size, "shading": _choice(tuple(SHADING_MODES)),
    "exposure": _positive, "auto_exposure": _flag, "shown_exposure": _positive,
    "tonemap": _choice(tuple(TONEMAPS)),
    "albedo": _albedo, "env": _text, "lights": _texts, "light_angles": _angles,
    "lattice": _text, "normals": _choice(("smooth", "gradient")),
    "flip_normals": _flag,
}
"""How each field of the file is read, in the order the file lists them (`SavedView`'s)."""


def _check_header(data: object, where: str) -> None:
    """Raise `StateError` (naming `where`) unless `data` is a JSON object with the
    state's ``format``, a ``version`` this isolume reads and no field it does not know."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise StateError(f"{where}: not an isolume view state (expected \"format\": "
                         f"\"{FORMAT}\")")
    version = data.get("version")
    if type(version) is not int or version < 1:
        raise StateError(f"{where}: version {json.dumps(version)}: expected a whole number "
                         "from 1")
    if version > VERSION:
        raise StateError(f"{where}: state version {version} is newer than this isolume reads "
                         f"(up to {VERSION}); update isolume")
    unknown = sorted(set(data) - set(_READERS) - {"format", "version"})
    if unknown:
        raise StateError(f"{where}: unknown field(s) {', '.join(unknown)}; expected "
                         f"{', '.join(_READERS)}")


def _from_folder(path: str, folder: Path) -> str:
    """`path` (a synthetic spec: as it is) as read from a file in `folder`."""
    if path.startswith(SYNTHETIC):
        return path
    path = Path(path).expanduser()
    return str(path if path.is_absolute() else folder / path)


def load_state(path: str | os.PathLike[str]) -> SavedView:
    """Read the state file at `path`.

    Raises:
        StateError: a missing or unreadable file, not JSON, or not a state this isolume
            reads (`SavedView.from_json`); one line naming the file.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise StateError(f"--state {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise StateError(f"--state {path}: cannot read it ({exc.__class__.__name__}: "
                         f"{exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise StateError(f"--state {path}: not JSON ({exc.msg} at line {exc.lineno}, "
                         f"column {exc.colno})") from None
    return SavedView.from_json(data, path)


# -- the command line -----------------------------------------------------------------------
class _Unset(list):
    """The value `given_options` puts in every name before parsing the words again: an
    empty one is left where no option wrote (a list, for ``append`` options to add to)."""


def given_options(args: argparse.Namespace, words: Sequence[str]) -> set[str]:
    """The namespace names of the options that `words` (the command's, after its name)
    give, parsed again by the command's parser (``args.state_parser``) into a namespace
    where nothing has a default: ``--name VALUE``, ``--name=VALUE`` and the prefixes
    argparse accepts all count, also at the option's default value; ``volume`` counts
    when one is named."""
    probe = argparse.Namespace(**{name: _Unset() for name in vars(args)})
    args.state_parser.parse_args(words, probe)
    given = {name for name, value in vars(probe).items()
             if not (isinstance(value, _Unset) and not value)}
    given -= {"volume", "state_parser"}  # volume: argparse writes its default
    return given | ({"volume"} if args.volume is not None else set())


def apply_state(args: argparse.Namespace, words: Sequence[str]) -> argparse.Namespace:
    """`args` with the defaults of ``--state FILE`` (when given): every option the state
    gives and the command has, unless the command's `words` (after its name) give it
    (`given_options`); ``args.camera``, the saved `Camera` (its azimuth, elevation and
    distance those of an explicit ``--view``); ``args.light_angles``
    (`SavedView.light_angles`); the exposure shown, fixed (`SavedView.shown_exposure`),
    for a picture or movie; and ``args.out``, where the command has one and none is
    given, `picture_beside` the file.

    Raises:
        StateError: a bad file (`load_state`), or a volume file it names that is gone.
    """
    path = getattr(args, "state", None)
    if path is None:
        return args
    given = given_options(args, words)
    del args.state_parser
    return apply_saved(args, load_state(path), path, given)


def apply_saved(args: argparse.Namespace, saved: SavedView, path: str | os.PathLike[str],
                given: set[str]) -> argparse.Namespace:
    """`args` with the defaults of the state `saved` (read from `path`, named in errors
    and beside which a picture goes) for every option not in `given` (namespace names);
    what `apply_state` does once it knows which options the command line gave."""
    for name, value in saved.option_values().items():
        if value is not None and hasattr(args, name) and name not in given:
            setattr(args, name, value)
    volume = saved.volume
    if "volume" not in given and volume and not volume.startswith(SYNTHETIC):
        if not Path(volume).exists():
            raise StateError(f"--state {path}: volume {volume} no longer exists (name "
                             "the volume on the command line to use another)")
    if (saved.shown_exposure is not None and args.command != "view"
            and not given & {"exposure", "no_auto_exposure"}):
        args.exposure, args.no_auto_exposure = saved.shown_exposure, True
    args.camera = _camera_with_view(saved.camera, args.view if "view" in given else None)
    args.light_angles = saved.light_angles
    if getattr(args, "out", "") is None:  # render without --out
        args.out = str(picture_beside(Path(path), args.size))
    return args


def picture_beside(path: Path, size: str) -> Path:
    """The picture ``render --state`` writes without ``--out``: beside the state file
    `path`, its name without `SUFFIX` (or ``.json``) and with the picture's `size`
    (``WxH``): ``v.view.json`` → ``v-3000x2000.png``."""
    name = path.name
    for suffix in (SUFFIX, ".json"):
        if name.endswith(suffix):
            name = name[:-len(suffix)]
            break
    return path.with_name(f"{name}-{size}.png")


def _camera_with_view(camera: Camera | None, view: str | None) -> Camera | None:
    """`camera` with the azimuth, elevation and (when given) distance of ``--view``
    `view` (None: as saved)."""
    if camera is None or view is None:
        return camera
    try:
        azimuth, elevation, distance = parse_view(view)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    return replace(camera, azimuth=azimuth, elevation=elevation,
                   distance=camera.distance if distance is None else distance)


def light_settings(angles: tuple[float, float] | None,
                   lattice: Lattice | HeldLattice | LatticeOnFile | None) -> dict[str, Any]:
    """`app.render.settings.RenderSettings` keywords of a world-fixed light at `angles`
    ((azimuth, elevation) degrees; None: the light follows the camera, no keywords) as
    the viewer draws it: the key light, and the first sun or directional light that
    `lattice` (None: none) leaves to the pixels, turned towards it."""
    if angles is None:
        return {}
    from isolume.app.render.lights import aimed_lights, first_distant_light, lattice_direct_lights
    from isolume.app.viewer.panel import direction_from_angles

    direction = tuple(float(v) for v in direction_from_angles(*angles))
    keywords: dict[str, object] = {"key_dir": direction}
    lights = lattice_direct_lights(lattice)
    if first_distant_light(lights) is not None:
        keywords["direct_lights"] = aimed_lights(lights, direction)
    return keywords
