"""The per-pixel lights of off-screen pictures lit by traced rays (render, movie, chart).

The renderer shadows the lights a lattice leaves to the pixels with its shadow atlas, as
the viewer must at interactive rates; an off-screen picture instead gives each pixel the
reference's own estimate of their direct light (`baking.shadow_rays`), from a position
pass and an Embree scene of the surface drawn (`SurfaceRenderer.set_traced_light`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.app.render.camera import Camera
from isolume.app.render.renderer import SurfaceRenderer
from isolume.app.render.settings import RenderSettings
from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.baking.trace import Scene


def position_pass(renderer: SurfaceRenderer, camera: Camera,
                  settings: RenderSettings) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points of the surface under the visible pixels and the (H, W) mask of
    those pixels, rows top to bottom (a position pass: a timeline item "gl", parallel
    inside on Mesa's llvmpipe threads)."""
    with cores.timed_item("gl"):
        position = renderer.render(camera, replace(settings, shading="position",
                                                   auto_exposure=False))
    return position.linear[position.mask], position.mask


def trace_direct_light(renderer: SurfaceRenderer, camera: Camera, settings: RenderSettings,
                       volume: volumes.Volume, seen: tuple[np.ndarray, np.ndarray],
                       scene: Scene | None, *,
                       smooth: bool = True, workers: int | None = None) -> None:
    """Give `renderer` the traced light of the per-pixel lights of a frame of `settings`
    seen by `camera` (none: nothing to do): `seen` = (points, mask) of that frame's
    position pass, `scene` the Embree scene of the surface drawn, `smooth` its normals'
    kind. The start offset is the lattice's (`renderer.lattice`'s bake config)."""
    from isolume.baking.shadow_rays import light_factors, pixel_starts

    lights = renderer.direct_lights(settings)
    points, mask = seen
    config = renderer.lattice.lattice.config if renderer.lattice is not None else None
    if not lights or config is None or scene is None:
        renderer.set_traced_light((), None)
        return
    origins, dirs = camera.primary_rays(*settings.size, np.flatnonzero(mask))
    starts, normals = pixel_starts(scene, volume, origins, dirs, points, config,
                                   smooth=smooth)
    light = np.zeros((*mask.shape, len(lights)), np.float32)
    light[mask] = light_factors(scene, starts, normals, lights, workers=workers)
    renderer.set_traced_light(lights, light)
