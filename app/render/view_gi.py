"""Global illumination for one view without a lattice file (``isolume render`` by default).

A lattice baked for every isovalue takes minutes; one picture needs only the texels that
its pixels read. So, as the lazy viewer's previews do (`baking.preview`), the corner texels
of the lattice cells under the visible pixels get paths traced on the *displayed*
isosurface (one Embree scene), each from the visible surface point nearest it, on the side
the eye sees (`baking.preview.seen_starts`), `paths` paths a texel on average placed where
the picture's noise is (`baking.view_paths`: a few each, then the rest by the spread of
their light and their share of the pixels); the picture is then drawn by the ordinary
lattice shading ("irradiance": side-aware trilinear lookups, and whatever the renderer adds
per pixel for the lattice's configuration). The lattice is used for this picture only,
never saved: its texels hold values for the displayed isovalue, not their own.

Its error against per-pixel path tracing (`isolume reference` with the same arguments) is
a few per cent (README, "The first picture"). The paths' first directions are stratified
over each texel's samples (`baking.passes.Tracing.stratified`): at `DEFAULT_PATHS` paths a
texel on average the picture is more accurate in every case of the sweep than at 32
independent ones, and as accurate as 64 of those at every texel (docs/accuracy.md, "The
traced light of one picture").
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

DEFAULT_PATHS = 28
"""Paths per texel, on average, of a render's view lattice (``isolume render --samples``):
the fewest of those measured whose sweep's median, p90 and worst error are each below
those of 32 independent paths (docs/accuracy.md)."""
SPREADS = ("noise", "even")
"""How a view lattice's paths are spread over its texels: where the picture's noise is
(`baking.view_paths`), or the same number at every texel."""
REPORT_S = 0.2
"""Seconds between rewrites of the progress line."""


def view_lattice(volume: volumes.Volume, config: BakeConfig, iso: float, points: np.ndarray,
                 eye: np.ndarray, *, workers: int | None = None, progress: bool = True,
                 scene: Scene | None = None, tracing: Tracing | None = None,
                 spread: str = "noise") -> HeldLattice:
    """A lattice lit for the view whose visible surface points are `points`.

    Args:
        config: `baking.config.BakeConfig` of the lighting (env, lights, bounces, albedo,
            seed); its `samples` are the paths per texel (on average: `spread`).
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
        spread: one of `SPREADS`.

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
    from isolume.baking.view_paths import picture_share
    from isolume.baking.view_texels import HeldLattice

    if spread not in SPREADS:
        raise ValueError(f"spread {spread!r}: expected one of {', '.join(SPREADS)}")
    geometry = LatticeGeometry.for_volume(volume, config.scale)
    texels = picture_texels(geometry, points)
    lattice = HeldLattice.for_texels(volume, config, texels)
    report = _Progress(progress, int(config.samples), len(texels), spread)
    if scene is None and len(texels):
        scene = surface_scene(volume, iso, 1)
    if scene is None or not len(texels):
        return lattice
    tracing = tracing or preview_tracing(volume, config)
    cores.stage("nearest points")
    seen = seen_surface(scene, volume, config, geometry, eye, points)
    cores.stage("tracing")
    share = picture_share(geometry, texels, points) if spread == "noise" else None
    estimate(volume, config, lattice, iso, texels, scene, 1, paths=int(config.samples),
             tracing=tracing, workers=workers or cores.threads(), seen=seen,
             told=report.update, share=share)
    report.done(int((lattice.paths > 0).sum()))
    return lattice


class _Progress:
    """One updating line on stderr: texels done (their worth of the paths, where the paths
    are placed by noise), paths per texel, seconds (rewritten at most every
    `REPORT_S`)."""

    def __init__(self, enabled: bool, paths: int, total: int, spread: str) -> None:
        self.enabled = enabled and sys.stderr is not None
        self.paths, self.total, self.t0 = paths, total, time.perf_counter()
        self.each = "each" if spread == "even" else "on average"
        self.shown = -REPORT_S

    def update(self, done: int) -> None:
        now = time.perf_counter() - self.t0
        if now - self.shown < REPORT_S:
            return
        self.shown = now
        self._line(f"global illumination: {done:,} of {self.total:,} texels, {self.paths} "
                   f"paths {self.each}, {now:.1f} s", end="")

    def done(self, texels: int) -> None:
        self._line(f"global illumination: {texels:,} texels × {self.paths} paths "
                   f"{self.each} in {time.perf_counter() - self.t0:.1f} s")

    def _line(self, text: str, end: str = "\n") -> None:
        if self.enabled:
            print(f"\r{text}\033[K", end=end, file=sys.stderr, flush=True)
