"""Drawing the frames of ``isolume movie``: one GL context and one renderer for all of them.

A movie changes one thing from frame to frame (a `Shot`): the camera's azimuth (a
turntable), the light's turn about the up axis (a light orbit) or the isovalue (a sweep).
The `Stage` keeps everything else: the mesh (extracted again only when the isovalue
changes), the lattice's textures, the environment's SH coefficients, the shader programs
and the render targets. How a light turns depends on what lights the picture
(`LightTurn`): an SH lattice's environment turns (``env_rotation``, its sun along with
it); an irradiance lattice's per-pixel sun or directional light turns (the bounces it
holds stay as baked); the global illumination traced for a view without a lattice is
traced again under the turned light; the local modes' key light turns.

Every frame is drawn with the same exposure (`meter`), so nothing flickers.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.options import CLIError
from isolume.app.render.camera import Camera
from isolume.app.render.exposure import auto_exposure_scale
from isolume.app.render.glcontext import create_headless
from isolume.app.render.lights import (
    aimed_lights,
    first_distant_light,
    key_direction,
    lattice_direct_lights,
)
from isolume.app.render.renderer import SurfaceRenderer
from isolume.app.render.settings import SHADING_MODES, Frame, RenderSettings
from isolume.app.render.traced_light import position_pass, trace_direct_light

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.view_texels import HeldLattice

KINDS = ("turntable", "light", "iso")
"""What a movie changes: the camera's azimuth, the light's azimuth, or the isovalue."""


@dataclass(frozen=True)
class Shot:
    """What one frame changes.

    Attributes:
        index: the frame's number, from 0.
        azimuth: the camera's azimuth, degrees (`app.render.camera.Camera`).
        iso: the isovalue shown.
        turn: the light's turn about the up axis (+z), degrees counter-clockwise seen from
            above (0: the light as given).
    """

    index: int
    azimuth: float
    iso: float
    turn: float = 0.0


def turn_steps(frames: int, degrees: float) -> list[float]:
    """(frames,) turns in degrees: a whole number of turns loops (frame `frames` would
    repeat frame 0, so the last frame stops one step short), any other angle ends on
    `degrees`."""
    if frames == 1:
        return [0.0]
    looped = degrees != 0 and math.isclose(degrees / 360.0, round(degrees / 360.0))
    steps = frames if looped else frames - 1
    return [degrees * i / steps for i in range(frames)]


def make_shots(kind: str, frames: int, azimuth: float, iso: float, degrees: float,
               iso_range: tuple[float, float] | None = None,
               light_follows: bool = False) -> list[Shot]:
    """The (frames,) shots of a movie of `kind` (one of `KINDS`) from the starting
    `azimuth` (degrees) at isovalue `iso`; the sweep runs over `iso_range` (lo, hi),
    both ends shown. A turntable whose `light_follows` turns the light with the camera
    (the object turns under the lights, as on a real turntable)."""
    if kind == "turntable":
        return [Shot(i, azimuth + turn, iso, turn if light_follows else 0.0)
                for i, turn in enumerate(turn_steps(frames, degrees))]
    if kind == "light":
        return [Shot(i, azimuth, iso, turn) for i, turn in enumerate(turn_steps(frames,
                                                                                degrees))]
    values = np.linspace(*iso_range, frames) if frames > 1 else [iso_range[0]]
    return [Shot(i, azimuth, float(v)) for i, v in enumerate(values)]


def turned(direction: Sequence[float] | np.ndarray, degrees: float
           ) -> tuple[float, float, float]:
    """The (3,) vector `direction` turned by `degrees` about +z (counter-clockwise seen
    from above, as ``--env-rotation``'s azimuth turns an environment)."""
    a = math.radians(degrees)
    x, y, z = (float(v) for v in direction)
    return (math.cos(a) * x - math.sin(a) * y, math.sin(a) * x + math.cos(a) * y, z)


@dataclass(frozen=True)
class LightTurn:
    """How the light of a movie turns (`light_turn`).

    Attributes:
        how: "environment" (an SH lattice: ``env_rotation``'s azimuth), "pixels" (the
            first distant light an irradiance lattice leaves to the pixels), "traced" (the
            first directional light or the sun of the light traced for each view), "key"
            (the local modes' key light).
        direction: (3,) unit vector towards the turned light at turn 0 (None for
            "environment").
    """

    how: str
    direction: tuple[float, float, float] | None = None


def light_turn(shading: str, lattice: Lattice | HeldLattice | None, traced: BakeConfig | None,
               camera: Camera, settings: RenderSettings, source: str | None,
               asked: str = "--kind light") -> LightTurn:
    """How the light turns for `shading` with `lattice` (from file `source`) or `traced`
    (the `BakeConfig` of the light traced per view); `asked`: the option that asks for
    the turn (in the messages).

    Raises:
        CLIError: nothing in the picture's light can turn.
    """
    mode = SHADING_MODES[shading]
    if mode.lattice is None:
        return LightTurn("key", tuple(key_direction(camera, settings)))
    if mode.lattice == "sh":
        return LightTurn("environment")
    if mode.lattice == "occlusion":
        raise CLIError(f"{asked}: shading {shading} shows a constant sky, which has "
                       "no direction to turn")
    if traced is not None:
        light = traced.lighting.turnable()
        if light is None:
            env, lights = traced.lighting.to_spec()
            raise CLIError(f"{asked} turns a directional light or the sky's sun; --env "
                           f"{env or 'none'} {' '.join(lights)} has neither: add --light "
                           "dir:X,Y,Z:R,G,B or a sky with a sun")
        return LightTurn("traced", tuple(light.direction))
    light = first_distant_light(settings.direct_lights or lattice_direct_lights(lattice))
    if light is None:
        raise CLIError(f"{asked}: {source} holds all of its light (no sun or directional "
                       "light left to the pixels); bake with --direct-light pixels or --mode "
                       "sh, or leave out --lattice to trace each frame's light")
    return LightTurn("pixels", tuple(light.direction))


@dataclass(frozen=True)
class Scene:
    """What every frame of a movie shares.

    Attributes:
        volume: the field.
        settings: the frames' look (its exposure and automatic exposure are replaced by
            the movie's fixed exposure).
        base: the camera every shot turns to its azimuth (a saved view's, or one that
            frames every shot: `app.movie.movie_camera`).
        normals, flip_normals: how the mesh's normals are made (`volumes.isosurface`).
        lattice: the illumination lattice every frame reads, or None.
        env_coeffs: (n², 3) SH coefficients of the environment ("sh"), or None.
        traced: the `BakeConfig` of the light traced for each frame's view when there is
            no lattice ("irradiance"), or None; spread: how its paths are spread
            (`app.render.view_gi.SPREADS`).
        light: how the light turns (`LightTurn`; None: it does not).
        shadows: the per-pixel lights' direct light: "traced" per frame, as ``isolume
            render`` (`app.render.traced_light`), or "map" (the shadow atlas).
        workers: tracing threads for `traced` and the traced direct light (None: all
            cores).
    """

    volume: volumes.Volume
    settings: RenderSettings
    base: Camera
    normals: str = "smooth"
    flip_normals: bool = False
    lattice: Lattice | HeldLattice | None = None
    env_coeffs: np.ndarray | None = None
    traced: BakeConfig | None = None
    spread: str = "noise"
    light: LightTurn | None = None
    shadows: str = "traced"
    workers: int | None = None

    def camera(self, shot: Shot) -> Camera:
        """The camera of `shot`: `base` at the shot's azimuth."""
        return replace(self.base, azimuth=shot.azimuth)

    def frame_settings(self, shot: Shot, exposure: float) -> RenderSettings:
        """The settings of `shot`: the fixed linear `exposure` (no automatic exposure) and
        the light turned by `shot.turn`."""
        s = replace(self.settings, exposure=exposure, auto_exposure=False)
        light = self.light
        if light is None or shot.turn == 0:
            return s
        if light.how == "environment":
            az, el = s.env_rotation
            return replace(s, env_rotation=(az + shot.turn, el))
        if light.how == "pixels":
            direction = turned(light.direction, shot.turn)
            return replace(s, direct_lights=aimed_lights(lattice_direct_lights(self.lattice),
                                                         direction))
        if light.how == "key":
            return replace(s, key_dir=turned(light.direction, shot.turn))
        return s

    def traced_config(self, shot: Shot) -> BakeConfig | None:
        """The `BakeConfig` of the light traced for `shot`'s view (the turned light's for a
        light orbit), or None when the frames read a lattice."""
        light = self.light
        if self.traced is None or light is None or light.how != "traced" or shot.turn == 0:
            return self.traced
        lighting = self.traced.lighting.turned(turned(light.direction, shot.turn))
        return self.traced.with_lighting(lighting)


class Stage:
    """One headless GL context and `SurfaceRenderer` that draw a movie's frames.

    Args:
        scene: what the frames share.
        backend: headless GL: "egl", "osmesa" or "auto".
    """

    scene: Scene
    empty_isos: set[float]
    renderer: SurfaceRenderer

    def __init__(self, scene: Scene, backend: str = "auto") -> None:
        self.scene = scene
        self.empty_isos: set[float] = set()
        self._gl = create_headless(backend)
        try:
            self.renderer = SurfaceRenderer(self._gl.ctx)
        except Exception:
            self._gl.release()
            raise
        self.renderer.set_bounds(*scene.volume.box)
        self.renderer.set_environment(scene.env_coeffs)
        self._texel_iso: np.ndarray | None = None
        self._iso: float | None = None
        self._triangles = 0
        self._kept: dict[int, HeldLattice] = {}  # traced light kept for a shot
        self._traced_scene: tuple[float, object] | None = None  # (iso, Embree scene)
        self._tracing: tuple[BakeConfig, object] | None = None  # (light, preview_tracing)
        if scene.lattice is not None:
            self.renderer.set_lattice(scene.lattice, self._texel_isovalues(scene.lattice))

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Free the renderer and the context."""
        self.renderer.release()
        self._gl.release()

    def _texel_isovalues(self, lattice: Lattice | HeldLattice) -> np.ndarray | None:
        """(Z, Y, X) field values at the lattice's texel centres when the shading reads
        them ("irradiance_closest"), computed once."""
        if SHADING_MODES[self.scene.settings.shading].lookup != "closest":
            return None
        if self._texel_iso is None:
            from isolume.baking.plan import texel_values

            self._texel_iso = texel_values(self.scene.volume, lattice.geometry)
        return self._texel_iso

    def _show_iso(self, iso: float) -> None:
        """Extract and upload the isosurface at `iso` unless it is the one shown."""
        if iso == self._iso:
            return
        scene = self.scene
        mesh = volumes.isosurface(scene.volume, iso, normals=scene.normals,
                                  flip_normals=scene.flip_normals)
        self.renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces, iso=mesh.iso)
        self._iso, self._triangles = iso, len(mesh.faces)
        if mesh.empty:
            self.empty_isos.add(iso)

    def _trace_view(self, shot: Shot, camera: Camera, seen: Callable[[], tuple],
                    keep: bool) -> None:
        """Trace and upload the light of `shot`'s view (`app.render.view_gi.view_lattice`,
        as ``isolume render`` does without a lattice) from the frame's position pass
        `seen()`; one traced for the same shot with `keep` is used once more instead."""
        lattice = self._kept.pop(shot.index, None)
        if lattice is None and self._triangles:
            from isolume.app.render.view_gi import view_lattice

            config = self.scene.traced_config(shot)
            scene, tracing = self._traced(shot.iso, config)
            lattice = view_lattice(self.scene.volume, config, shot.iso, seen()[0], camera.eye,
                                   workers=self.scene.workers, progress=False, scene=scene,
                                   tracing=tracing, spread=self.scene.spread)
        if keep and lattice is not None:
            self._kept[shot.index] = lattice
        self.renderer.set_lattice(lattice, None if lattice is None
                                  else self._texel_isovalues(lattice))

    def _traced(self, iso: float, config: BakeConfig):
        """The Embree scene of the surface ρ = `iso` and the preview tracing of `config`
        the frames' traced light uses, each made once (a turntable or a light orbit keeps
        one isovalue; a light that turns is a new `config` every frame)."""
        from isolume.baking.preview import preview_tracing

        if self._tracing is None or self._tracing[0] != config:
            self._tracing = (config, preview_tracing(self.scene.volume, config))
        return self._surface_scene(iso), self._tracing[1]

    def _surface_scene(self, iso: float):
        """The Embree scene of the surface ρ = `iso` (None: empty), made once per
        isovalue."""
        from isolume.baking.preview import surface_scene

        if self._traced_scene is None or self._traced_scene[0] != iso:
            self._traced_scene = None  # one scene at a time
            self._traced_scene = (iso, surface_scene(self.scene.volume, iso, 1))
        return self._traced_scene[1]

    def _trace_direct(self, shot: Shot, camera: Camera, settings: RenderSettings,
                      seen: Callable[[], tuple]) -> None:
        """Trace the per-pixel lights' direct light of `shot`'s frame
        (`app.render.traced_light`, from its position pass `seen()`) when the scene asks
        for it and the frame has such lights."""
        if self.scene.shadows != "traced" or not self.renderer.direct_lights(settings):
            self.renderer.set_traced_light((), None)
            return
        trace_direct_light(self.renderer, camera, settings, self.scene.volume, seen(),
                           self._surface_scene(shot.iso),
                           smooth=self.scene.normals == "smooth", workers=self.scene.workers)

    def draw(self, shot: Shot, exposure: float, keep: bool = False) -> Frame:
        """Draw `shot` with the linear `exposure`; `keep`: keep its traced light for one
        more draw of the same shot."""
        self._show_iso(shot.iso)
        camera = self.scene.camera(shot)
        settings = self.scene.frame_settings(shot, exposure)
        if self.scene.traced is None and self._triangles and self.scene.shadows == "traced":
            return self.renderer.render(  # the frame's own G-buffer shows its direct light
                camera, settings,  # the surface: no position pass
                seen=lambda seen: self._trace_direct(shot, camera, settings, lambda: seen))
        seen = functools.cache(lambda: position_pass(self.renderer, camera, settings))
        if self.scene.traced is not None:
            self._trace_view(shot, camera, seen, keep)
        if self._triangles:
            self._trace_direct(shot, camera, settings, seen)
        return self.renderer.render(camera, settings)


def metered_shots(shots: list[Shot], count: int) -> list[Shot]:
    """Up to `count` shots evenly spread over `shots`, the first and the last included."""
    picks = np.unique(np.linspace(0, len(shots) - 1, min(count, len(shots))).round())
    return [shots[int(i)] for i in picks]


def meter(stage: Stage, shots: list[Shot]) -> float:
    """The automatic exposure (`app.render.exposure.auto_exposure_scale`) of the surface
    pixels of every shot in `shots` pooled: one linear scale for the whole movie. The
    light traced for them is kept for their frames."""
    frames = [stage.draw(shot, 1.0, keep=True) for shot in shots]
    linear = np.stack([frame.linear for frame in frames])  # (K, H, W, 3)
    mask = np.stack([frame.mask for frame in frames])  # (K, H, W)
    return auto_exposure_scale(linear, mask)
