"""The light leaving each vertex of an exported isosurface (``isolume export``).

A vertex keeps one colour whatever the eye, so it shows the light on the side its normal
points to: the low-value side, outside the material (``--flip-normals`` turns it). Its
outgoing radiance is albedo·E/π of a diffuse surface, E the irradiance there, as
``isolume render`` shades its pixels:

* from a lattice (`lattice_radiance`): E of the side-aware trilinear lookup over the
  computed texels (`baking.lattice.shown_lookup`, the shader's lookup on the CPU); for
  an SH lattice the transfer dotted with the environment's coefficients, turned by
  ``--env-rotation`` (`sh_irradiance`, the shader's sum);
* without one (`traced_lattice`): global illumination traced for the surface as render
  traces it for a view (`app.render.view_gi`): the texels the vertices' lookups read get
  paths on the exported isosurface (`baking.preview.estimate`), each from the vertex
  nearest it, off the surface along its normal; then the same lookup;
* plus the lights the lattice leaves to the pixels (`app.render.lights.lattice_direct_lights`:
  ``--light`` lights and the sky's sun of a lattice baked with direct light "pixels", the
  default under a sun). The renderer shadow-maps them per pixel; here every vertex traces
  Embree shadow rays from where the renderer looks them up (the lattice's start offset
  along the normal), as ``render`` traces its pixels' (`baking.shadow_rays.light_factors`):
  one per point or directional light, 16 over the sun's disc (4 where those 4 agree),
  whose unblocked fraction is the soft penumbra the renderer filters from its map.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.baking.lattice import shown_lookup
from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.baking.lights import DirectionalLight, PointLight, SunLight
    from isolume.baking.trace import Scene
    from isolume.baking.view_texels import HeldLattice

VERTICES_PER_REPORT = 1 << 16
"""Vertices whose shadow rays are traced between progress updates."""
COVERED = 1e-6
"""A vertex whose lookup weight over computed texels is below this has no lattice light."""


def lattice_radiance(lattice: Lattice | HeldLattice, points: np.ndarray, normals: np.ndarray,
                     albedo: Sequence[float] | np.ndarray,
                     env_coeffs: np.ndarray | None = None,
                     env_rotation: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(V, 3) linear radiance albedo·E/π of the lattice's light at the vertices.

    Args:
        lattice: `baking.lattice.Lattice` or `baking.view_texels.HeldLattice` (a
            lattice file's computed texels, or `traced_lattice`'s), irradiance or SH
            transfer.
        points: (V, 3) world positions; normals: (V, 3) unit normals (the lit side).
        albedo: (3,) diffuse reflectance.
        env_coeffs: (m, 3) environment coefficients of an SH lattice
            (`app.options.environment_coefficients`); None for irradiance.
        env_rotation: (azimuth, elevation) degrees the environment turns by (SH).

    Returns:
        Radiance in the lattice's units (irradiance / sr); 0 where no computed texel is
        read (`coverage`).
    """
    values = shown_lookup(lattice, points, normals)
    if lattice.kind == "sh":
        irradiance = sh_irradiance(values, lattice, env_coeffs, env_rotation)
    else:
        irradiance = values[:, :3]
    return np.asarray(albedo, np.float64) * np.maximum(irradiance, 0.0) / np.pi


def sh_irradiance(transfer: np.ndarray, lattice: Lattice | HeldLattice, env_coeffs: np.ndarray,
                  env_rotation: tuple[float, float]) -> np.ndarray:
    """(V, 3) irradiance E_c = Σ_k τ_k,c ℓ_k,c of (V, C) SH `transfer` vectors (gray: one
    per coefficient, coloured: three) under (m, 3) `env_coeffs` turned by `env_rotation`
    (each transfer block's coefficients alike, as `SurfaceRenderer` turns them)."""
    from isolume.baking import sh

    order = int(lattice.meta["sh_order"])
    blocks = sh.transfer_blocks(lattice)
    turn = sh.rotation(sh.rotation_from_az_el(*env_rotation), order)
    coeffs = np.asarray(env_coeffs, np.float64)[: blocks * order * order]
    light = np.concatenate([turn @ block for block in np.split(coeffs, blocks)])  # (K, 3)
    tau = transfer.reshape(len(transfer), len(light), -1)  # (V, K, 1 or 3)
    if tau.shape[-1] == 1:
        return tau[..., 0] @ light
    return np.einsum("vkc,kc->vc", tau, light)


def coverage(lattice: Lattice | HeldLattice, points: np.ndarray) -> np.ndarray:
    """(V,) weight of the computed texels in the trilinear lookups at (V, 3) world points
    (1 where all 8 are computed, 0 where none is)."""
    from isolume.baking.lattice import trilinear_corners

    idx, weights = trilinear_corners(lattice.geometry.shape,
                                     lattice.geometry.to_texel_coords(points))
    return (weights * lattice.shown((idx[..., 0], idx[..., 1], idx[..., 2]))).sum(axis=1)


def traced_lattice(volume: volumes.Volume, config: BakeConfig, iso: float, points: np.ndarray,
                   normals: np.ndarray, scene: Scene, *, workers: int | None = None,
                   progress: bool = False, spread: str = "noise") -> HeldLattice:
    """A lattice lit for the whole surface ρ = `iso`: `config.samples` paths a texel on
    average for the texels the vertices' lookups read, placed where the vertices' noise is
    (`baking.view_paths`, each texel's share of the vertices as of a picture's pixels;
    `spread` "even": that many at every texel), traced on `scene` (`baking.trace.Scene` of
    that surface), from the vertex nearest the texel, `config.offset` voxels off it along
    its normal.

    Args:
        config: `baking.config.BakeConfig` of the lighting (`app.options.view_light`).
        points: (V, 3) world vertex positions; normals: (V, 3) their unit normals.
        workers: tracing threads (None: all cores).
        progress: a tqdm bar on stderr.

    Returns:
        A `baking.view_texels.HeldLattice` holding the estimates of the texels the
        vertices' lookups read, and nothing else.
    """
    from tqdm import tqdm

    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.preview import (
        SeenSurface,
        estimate,
        nearest_points,
        preview_tracing,
    )
    from isolume.baking.view_paths import picture_share
    from isolume.baking.view_texels import HeldLattice

    geometry = LatticeGeometry.for_volume(volume, config.scale)
    texels, nearest = nearest_points(geometry, points)
    lattice = HeldLattice.for_texels(volume, config, texels)
    h = float(np.mean(volume.spacing))
    seen = SeenSurface(points, points + config.offset * h * normals, normals, texels, nearest)
    tracing = preview_tracing(volume, config)
    threads = workers or cores.threads()
    with tqdm(total=len(texels), unit="texel", desc="global illumination",
              disable=not progress, dynamic_ncols=True) as bar:
        estimate(volume, config, lattice, iso, texels, scene, 1, paths=int(config.samples),
                 tracing=tracing, workers=threads, seen=seen,
                 told=lambda done: bar.update(done - bar.n),
                 share=picture_share(geometry, texels, points) if spread == "noise" else None)
    return lattice


def pixel_lights(lattice: Lattice | HeldLattice,
                 rotation: tuple[float, float] = (0.0, 0.0)) -> tuple:
    """The lights `lattice` leaves to the pixels (`app.render.lights.lattice_direct_lights`),
    an SH lattice's sun turned by `rotation` (azimuth, elevation degrees) with its
    environment, as `SurfaceRenderer.direct_lights` does."""
    from isolume.app.render.lights import lattice_direct_lights, rotated_lights

    lights = lattice_direct_lights(lattice)
    return rotated_lights(lights, rotation) if lattice.kind == "sh" and lights else lights


def surface_radiance(volume: volumes.Volume, iso: float, mesh: volumes.Mesh, scene: Scene,
                     lattice: Lattice | HeldLattice | None, traced: BakeConfig | None,
                     albedo: Sequence[float] | np.ndarray, *,
                     env_coeffs: np.ndarray | None = None,
                     env_rotation: tuple[float, float] = (0.0, 0.0),
                     workers: int | None = None, progress: bool = False,
                     direct: dict | None = None, spread: str = "noise"
                     ) -> tuple[np.ndarray, Lattice | HeldLattice, tuple]:
    """The light ``isolume export`` gives `mesh`'s vertices: the lattice's (without one,
    `traced_lattice` under `traced`: the light traced for the surface ρ = `iso`) through
    the side-aware lookup (`lattice_radiance`; its paths spread as `spread` says), plus
    the lights it leaves to the pixels through shadow rays on `scene` (`direct_radiance`).
    `direct`, where given, keeps that direct light by its lights and offset for a later
    call on the same mesh (passes of more paths under the same lights trace no shadow ray
    again).

    Returns:
        ((V, 3) linear outgoing radiance (irradiance units / sr), the lattice read, the
        per-pixel lights added).
    """
    from isolume.app.render.lights import lattice_start_offset

    points = np.asarray(mesh.vertices, np.float64)
    normals = np.asarray(mesh.normals, np.float64)
    if lattice is None:
        lattice = traced_lattice(volume, traced, iso, points, normals, scene,
                                 workers=workers, progress=progress, spread=spread)
    radiance = lattice_radiance(lattice, points, normals, albedo, env_coeffs, env_rotation)
    lights = pixel_lights(lattice, env_rotation)
    if lights:
        offset = lattice_start_offset(lattice)
        key = (tuple(lights), offset, tuple(np.asarray(albedo, np.float64).ravel()))
        shone = direct.get(key) if direct is not None else None
        if shone is None:
            shone = direct_radiance(scene, lights, points, normals, offset, albedo,
                                    progress=progress)
            if direct is not None:  # the last lights' only
                direct.clear()
                direct[key] = shone
        radiance += shone
    return radiance, lattice, lights


def direct_radiance(scene: Scene, lights: Sequence[PointLight | DirectionalLight | SunLight],
                    points: np.ndarray, normals: np.ndarray, offset: float,
                    albedo: Sequence[float] | np.ndarray, *, progress: bool = False
                    ) -> np.ndarray:
    """(V, 3) linear radiance albedo·E/π of the direct light of `lights` at the vertices,
    shadowed by `scene`.

    Args:
        scene: `baking.trace.Scene` of the exported surface.
        lights: `baking.lights.PointLight`, `DirectionalLight` and `SunLight` values.
        points: (V, 3) world positions; normals: (V, 3) unit normals (the lit side).
        offset: world distance the shadow rays start off the surface along the normal.
        albedo: (3,) diffuse reflectance.
        progress: a tqdm bar on stderr.
    """
    from tqdm import tqdm

    from isolume.baking.lights import SunLight
    from isolume.baking.shadow_rays import light_factors

    origins = np.asarray(points, np.float64) + offset * np.asarray(normals, np.float64)
    normals = np.asarray(normals, np.float64)
    irradiance = np.zeros((len(points), 3))
    with tqdm(total=len(points) * len(lights), unit="vertex", desc="direct light",
              disable=not progress, dynamic_ncols=True) as bar:
        for light in lights:
            for lo in range(0, len(points), VERTICES_PER_REPORT):
                part = slice(lo, lo + VERTICES_PER_REPORT)
                seen = light_factors(scene, origins[part], normals[part], (light,))[:, 0]
                normal = (np.asarray(light.irradiance, np.float64)[None, :]
                          if isinstance(light, SunLight) else light.towards(origins[part])[2])
                irradiance[part] += normal * seen[:, None]
                bar.update(len(origins[part]))
    return np.asarray(albedo, np.float64) * irradiance / np.pi
