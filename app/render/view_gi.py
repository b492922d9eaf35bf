"""Global illumination for one view without a lattice file (``isolume render`` by default).

A lattice baked for every isovalue takes minutes; one picture needs only the texels that
its pixels read. So, as the lazy viewer's previews do (`baking.preview`), the corner texels
of the lattice cells under the visible pixels get paths traced on the *displayed*
isosurface (one Embree scene), each from the visible surface point nearest it, on the side
the eye sees (`baking.preview.seen_starts`), in one pass of `paths` paths each; the
picture is then drawn by the ordinary lattice shading ("irradiance": side-aware trilinear
lookups, and whatever the renderer adds per pixel for the lattice's configuration). The
lattice is used for this picture only, never saved: its texels hold values for the
displayed isovalue, not their own.

Its error against per-pixel path tracing (`isolume reference` with the same arguments) is
the previews': a few per cent at 64 paths (README, "The first picture").
"""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.passes import Tracing
    from isolume.baking.trace import Scene
    from isolume.baking.view_texels import HeldLattice

DEFAULT_PATHS = 64
"""Paths per texel of a render's view lattice (``isolume render --samples``)."""
REPORT_S = 0.2
"""Seconds between rewrites of the progress line."""


def view_lattice(volume: volumes.Volume, config: BakeConfig, iso: float, points: np.ndarray,
                 eye: np.ndarray, *, workers: int | None = None, progress: bool = True,
                 scene: Scene | None = None, tracing: Tracing | None = None) -> HeldLattice:
    """A lattice lit for the view whose visible surface points are `points`.

    Args:
        config: `baking.config.BakeConfig` of the lighting (env, lights, bounces, albedo,
            seed); its `samples` are the paths per texel.
        iso: the displayed isovalue.
        points: (N, 3) world positions of the surface under the visible pixels (the
            renderer's position pass).
        eye: (3,) world position of the camera: each texel's paths start at the visible
            point nearest it, on the side the eye sees (`baking.preview.seen_starts`).
        workers: tracing threads (None: all cores).
        progress: report on stderr.
        scene, tracing: the Embree scene of the surface ρ = `iso` at marching-cubes
            step 1 (`baking.preview.surface_scene`, or one of the displayed mesh) and the
            `preview_tracing` of (volume, config), when the caller has them (the
            displayed mesh, a movie's several views); None: made here.

    Returns:
        A `baking.view_texels.HeldLattice` holding the estimates of the texels the
        picture reads, and nothing else (its memory follows them, not the volume's box).
    """

    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.preview import (
        estimate,
        picture_texels,
        preview_tracing,
        seen_surface,
        surface_scene,
    )
    from isolume.baking.view_texels import HeldLattice

    geometry = LatticeGeometry.for_volume(volume, config.scale)
    texels = picture_texels(geometry, points)
    lattice = HeldLattice.for_texels(volume, config, texels)
    report = _Progress(progress, int(config.samples), len(texels))
    if scene is None and len(texels):
        scene = surface_scene(volume, iso, 1)
    if scene is None or not len(texels):
        return lattice
    tracing = tracing or preview_tracing(volume, config)
    cores.stage("nearest points")
    seen = seen_surface(scene, volume, config, geometry, eye, points)
    cores.stage("tracing")
    estimate(volume, config, lattice, iso, texels, scene, 1, paths=int(config.samples),
             tracing=tracing, workers=workers or cores.threads(), seen=seen,
             told=report.update)
    report.done(int((lattice.paths > 0).sum()))
    return lattice


class _Progress:
    """One updating line on stderr: texels done, paths per texel, seconds (rewritten at
    most every `REPORT_S`)."""

    def __init__(self, enabled: bool, paths: int, total: int) -> None:
        self.enabled = enabled and sys.stderr is not None
        self.paths, self.total, self.t0 = paths, total, time.perf_counter()
        self.shown = -REPORT_S

    def update(self, done: int) -> None:
        now = time.perf_counter() - self.t0
        if now - self.shown < REPORT_S:
            return
        self.shown = now
        self._line(f"global illumination: {done:,} of {self.total:,} texels, {self.paths} "
                   f"paths each, {now:.1f} s", end="")

    def done(self, texels: int) -> None:
        self._line(f"global illumination: {texels:,} texels × {self.paths} paths in "
                   f"{time.perf_counter() - self.t0:.1f} s")

    def _line(self, text: str, end: str = "\n") -> None:
        if self.enabled:
            print(f"\r{text}\033[K", end=end, file=sys.stderr, flush=True)
