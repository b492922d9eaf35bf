"""First estimates for the lazy viewer: every visible texel lit within about a second.

A lattice texel's proper value needs paths on its *own* isosurface, and the texels around
one displayed surface span dozens of isovalue levels — one marching-cubes mesh and one
Embree scene each (`baking.plan`), seconds apiece on a CT scan, before the first texel
can be shown. The displayed surface itself, however, is one scene, and for the picture
on screen it is the right one: the renderer interpolates these texels on exactly that
surface. So before (and besides) the level-by-level bake, the visible texels get a few
paths traced on a coarse mesh of the displayed isosurface, from their centres projected
onto it. These *first estimates* are written into the lattice's values with no sample
counted and flagged in ``Lattice.first``; the display shows them until the texel's own
samples replace them (the bake's first commit overwrites the value), and they are never
saved. Their error is that of the "closest isovalue" choice for texels off the surface
plus the noise of `PATHS` paths — the point is to show soft light at once, not to be
final.

Cost on the engine CT (256×256×128, 2 cores): a step-2 mesh (~150 k triangles) and its
scene (`COARSE_VOXELS`), plain-gradient normals (the smoothed gradient grid would cost
seconds to build), and ~2.5 rays per path.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

import volumes

from . import kernels, rng
from .bake import make_lighting, path_settings
from .config import BakeConfig
from .integrator import trace_paths
from .lattice import Lattice
from .lazy import corner_offsets
from .plan import project_to_level

PATHS = 4
"""Paths per texel of a first estimate."""
COARSE_VOXELS = 1 << 22
"""Volumes with more voxels than this (e.g. 256×256×64) get a step-2 preview surface (4×
fewer triangles, 4× faster to extract and to hand to Embree); smaller ones the full one.
On a 32³ shells volume the step-2 mesh loses parts of the thin shells and the first
estimates come out 11 % too bright; at full detail they agree with the bake to 0.3 %."""
COARSE_OFFSET_VOXELS = 0.5
"""Start-point offset on a step-2 surface: that mesh sits up to (2 voxels)²/(8 R) off the
true surface in concave regions of radius R, so the bake's 0.25 voxels would let concave
texels start behind a facet for R < 2 voxels."""
SEED_SALT = 0x5EED_F1A5
"""Mixed into the bake seed: first estimates use paths of their own."""
CHUNK = 16384


def cell_corners(shape: tuple[int, int, int], cells: np.ndarray) -> np.ndarray:
    """(K,) sorted unique flat ids of the 8 corner texels of (N,) cells given by the flat
    id of their (0, 0, 0) corner."""
    flat = (np.asarray(cells, np.int64)[:, None] + corner_offsets(shape)[None, :]).reshape(-1)
    return np.unique(flat[flat < int(np.prod(shape))])


def first_estimates(volume: volumes.Volume, config: BakeConfig, lattice: Lattice,
                    iso: float, cells: np.ndarray, *, workers: int = 1,
                    paths: int = PATHS, only_active: bool = False) -> np.ndarray:
    """Give the corner texels of the visible `cells` that have no sample a first
    estimate traced on the displayed isosurface ρ = `iso`.

    Writes ``lattice.values`` and ``lattice.first`` (which must be set) of those texels
    only; samples stay 0. Texels that already have samples are left alone.

    Args:
        only_active: skip texels outside ``lattice.active`` (once the plan is known:
            the bake will never replace their first estimates, and a lattice saved and
            shown again would not have them).

    Args:
        cells: (N,) flat ids of the (0, 0, 0) corners of the lattice cells under visible
            pixels (`baking.lazy.visible_cells`).
        workers: threads tracing concurrently.

    Returns:
        (K,) flat ids of the texels written (empty when none needed it, or when the
        isovalue has no surface).
    """
    flat = cell_corners(lattice.geometry.shape, cells)
    flat = flat[lattice.samples.reshape(-1)[flat] == 0]
    if only_active:
        flat = flat[lattice.active.reshape(-1)[flat]]
    step = 2 if volume.data.size > COARSE_VOXELS else 1
    mesh = volumes.isosurface(volume, iso, step_size=step, normals="none")
    if len(flat) == 0 or mesh.empty:
        return flat[:0]
    from .trace import Scene

    scene = Scene(mesh.vertices, mesh.faces)
    h = float(np.mean(volume.spacing))
    on_surface = project_to_level(volume, lattice.geometry.centres(flat), iso,
                                  max_move=4 * config.max_move * h, smooth=False)
    normals = volumes.normals_at(volume, on_surface, smooth=False, flip=config.flip_normals)
    offset = COARSE_OFFSET_VOXELS if step == 2 else config.offset
    origins = (on_surface + offset * h * normals).astype(np.float32)
    sums = _trace(scene, volume, config, flat, origins, normals, workers, paths)
    values = lattice.values.reshape(-1, lattice.values.shape[-1])
    still_empty = lattice.samples.reshape(-1)[flat] == 0  # the bake may have come first
    values[flat[still_empty]] = (sums[still_empty] / paths).astype(np.float32)
    lattice.first.reshape(-1)[flat[still_empty]] = 1
    return flat[still_empty]


def _trace(scene, volume, config, flat, origins, normals, workers, paths) -> np.ndarray:
    """(K, C) sums of `paths` path estimates per texel, traced on `workers` threads."""
    lighting, settings = make_lighting(config), path_settings(volume, config)
    seed_key = np.uint64(rng.seed_key(config.seed ^ SEED_SALT))
    texels = np.arange(len(flat), dtype=np.int64)
    per_chunk = max(1, CHUNK // paths)

    def run(lo: int) -> np.ndarray:
        hi = min(lo + per_chunk, len(flat))
        pos = np.repeat(texels[lo:hi], paths)
        samples = np.tile(np.arange(paths, dtype=np.int64), hi - lo)
        keys, o, n = kernels.path_starts(seed_key, flat, pos, samples, texels[lo:hi],
                                         origins[lo:hi], normals[lo:hi])
        estimates = trace_paths(scene, o, n, keys, lighting, settings)
        return estimates.reshape(hi - lo, paths, -1).sum(axis=1)

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        parts = list(pool.map(run, range(0, len(flat), per_chunk)))
    return np.concatenate(parts)


def drop_inactive(lattice: Lattice) -> np.ndarray:
    """Withdraw the first estimates of texels outside ``lattice.active`` (made before the
    plan was known); returns their (K,) flat ids, to be re-uploaded."""
    stale = np.flatnonzero((lattice.first.reshape(-1) > 0) & ~lattice.active.reshape(-1))
    lattice.first.reshape(-1)[stale] = 0
    return stale


def warm_up(volume: volumes.Volume) -> None:
    """Do ahead of the first view what `first_estimates` would otherwise do on it: load
    the compiled kernels and build the plain gradient grid (together ~1 s on a CT scan)."""
    kernels.warm_up()
    centre = np.mean(volume.sample_box, axis=0)[None, :]
    project_to_level(volume, centre, float(volume.data.mean()), 0.0, smooth=False)
