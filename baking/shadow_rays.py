"""Ray-traced direct light of the per-pixel lights: the reference's own estimate, per pixel.

A lattice baked with direct light "pixels" leaves its point and directional lights and
its sky's sun to the renderer, which shadows them per pixel. A shadow map compares depths
with a bias of a fraction of a voxel, so an occluder closer than that to the receiver
(the next grain of a granular surface, the lip of a sub-voxel pit) casts no shadow; and
near a light's terminator a vertex normal interpolated across a triangle can face the
light where the exact smoothed gradient (the reference's normal) does not, or the other
way. On the noisy surfaces of CT and MRI scans a few per cent of the sunlit pixels so
disagree with the path-traced reference about being lit, and they carry most of the
picture's error. An off-screen picture can afford the reference's own estimate instead:
from each pixel's start point and normal (the surface point under it, lifted along its
smoothed-gradient normal as the reference lifts it, `reference.primary_hits`), rays
towards every light on the displayed surface's Embree scene (`light_factors`); the
renderer multiplies each light's irradiance at normal incidence by that factor, the
cosine-weighted fraction of the light seen (``direct.glsl`` with TRACED).

A sun is a disc: `SUN_RAYS` rays over its cone, a stratified spiral turned per pixel, so
the penumbra's fraction is resolved to 1/`SUN_RAYS` and its banding becomes fine noise.
Most pixels see all of the disc or none of it, so `SUN_PROBES` of those rays, the ones
spread widest over the disc, go first, and a pixel traces the rest only where they
disagree: in a penumbra, or where an occluder covers part of the disc between them
(`SUN_PROBES` says what that saves and how many pixels it changes). With Embree's per-ray
calls (`trace.EmbreeCalls`) a block of pixels is one compiled call
(`baking.pixel_kernels`), else numpy over embreex's batches, with the same rule.
A directional light takes one ray, a point light one ray that stops at the light.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from isolume import volumes
from isolume.baking.config import BakeConfig
from isolume.baking.lights import DirectionalLight, PointLight, SunLight
from isolume.baking.pixel_kernels import GOLDEN_ANGLE, sun_factors
from isolume.baking.sampling import orthonormal_basis
from isolume.volumes import cores

if TYPE_CHECKING:  # embreex is imported only when shadow rays are traced
    from isolume.baking.trace import Scene

SUN_RAYS = 16
"""Rays per pixel over a sun's disc."""
SUN_PROBES = 4
"""Of a pixel's `SUN_RAYS`, those traced first (`disc_order`): where they all reach the
sun, or are all blocked, so are the others taken to be. The 512² default views, against
all 16 traced: the engine CT 4.0 rays a pixel, 0.02 % of its pixels differ, by at most
0.05 of the factor (1: the whole disc seen head-on); the foot CT, whose grains cut the
disc in many places, 4.3 rays, 0.23 % of pixels, by at most 0.30, the RMS over all its
pixels 1 % of their mean factor; 8 probes would leave 0.03 %."""
CHUNK_RAYS = 1 << 17
"""Shadow rays one work item traces at most (~0.05 s, ~12 MiB of arrays): a 512²
picture's sun is dozens of items for the cores to share."""


def disc_offsets(count: int) -> np.ndarray:
    """(count, 2) points on the unit disc, uniform by area (Vogel's spiral: radius
    sqrt((k + 0.5) / count), angle k times the golden angle)."""
    k = np.arange(count, dtype=np.float64)
    radius = np.sqrt((k + 0.5) / count)
    angle = k * GOLDEN_ANGLE
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def disc_order(count: int = SUN_RAYS, probes: int = SUN_PROBES) -> np.ndarray:
    """(count,) int64 indices of the `disc_offsets` points: first `probes` spread widest
    (the outermost, then each time the point farthest from those chosen), then the rest in
    the spiral's order."""
    points = disc_offsets(count)
    chosen = [int(np.argmax(np.hypot(points[:, 0], points[:, 1])))]
    while len(chosen) < probes:
        gaps = np.min([np.hypot(*(points - points[c]).T) for c in chosen], axis=0)
        chosen.append(int(np.argmax(gaps)))
    rest = [k for k in range(count) if k not in chosen]
    return np.array(chosen + rest, np.int64)


def _sun_frame(sun: SunLight) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit direction (3,) to `sun`'s centre and two unit axes (3,) across its disc."""
    centre = np.asarray(sun.direction, np.float64)
    centre = centre / np.linalg.norm(centre)
    u, v = (axis[0] for axis in orthonormal_basis(centre[None]))
    return centre, u, v


def sun_directions(sun: SunLight, pixels: np.ndarray, count: int = SUN_RAYS) -> np.ndarray:
    """(P, count, 3) unit directions towards `sun`'s disc for the (P,) pixel indices
    `pixels`: `disc_offsets` on the plane tangent to the disc's centre, scaled by
    tan(radius), turned by the golden angle times each pixel's index (deterministic).
    Uniform in that plane is uniform in solid angle to within tan²(radius) (7.6e-5 at
    the sky's 0.5°)."""
    centre, u, v = _sun_frame(sun)
    offsets = disc_offsets(count) * math.tan(math.radians(sun.radius))
    turn = (np.asarray(pixels, np.float64) * GOLDEN_ANGLE)[:, None]
    c, s = np.cos(turn), np.sin(turn)
    a = offsets[None, :, 0] * c - offsets[None, :, 1] * s
    b = offsets[None, :, 0] * s + offsets[None, :, 1] * c
    d = centre + a[..., None] * u + b[..., None] * v
    return d / np.linalg.norm(d, axis=2, keepdims=True)


def _rays(light, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(P, 1, 3) unit directions of the shadow rays of a directional or point `light` from
    (P, 3) `starts` and their (P, 1) far ends (None: unbounded)."""
    if isinstance(light, DirectionalLight):
        d = np.asarray(light.direction, np.float64)
        return np.broadcast_to(d / np.linalg.norm(d), starts.shape)[:, None, :], None
    if isinstance(light, PointLight):
        dirs, dist, _ = light.towards(starts)
        return dirs[:, None, :], (dist * (1.0 - 1e-5))[:, None]
    raise TypeError(f"no shadow rays for a {type(light).__name__}")


def _blocked(scene: Scene, starts: np.ndarray, dirs: np.ndarray,
             far: np.ndarray | None = None) -> np.ndarray:
    """(P, K) bool: is each of the (P, K, 3) rays `dirs` from the (P, 3) `starts`
    (as far as (P, K) `far`, None: unbounded) blocked on `scene`?"""
    origins = np.ascontiguousarray(
        np.broadcast_to(starts[:, None, :], dirs.shape).reshape(-1, 3), np.float32)
    flat = np.ascontiguousarray(dirs.reshape(-1, 3), np.float32)
    tfar = None if far is None else np.asarray(far, np.float32).reshape(-1)
    return scene.occluded(origins, flat, tfar=tfar).reshape(dirs.shape[:2])


def _seen_cosine(scene: Scene, light, starts: np.ndarray, normals: np.ndarray,
                 pixels: np.ndarray, probes: int) -> np.ndarray:
    """(P,) float32 mean over `light`'s shadow rays from (P, 3) `starts` of max(0, n·d)
    for those that reach it (n: the (P, 3) unit `normals`; a sun's rays turned for the
    (P,) `pixels`, `probes` of them first: `SUN_PROBES`)."""
    if isinstance(light, SunLight):
        return _sun_seen(scene, light, starts, normals, pixels, probes)
    dirs, far = _rays(light, starts)
    cosine = np.maximum(np.einsum("pkc,pc->pk", dirs, normals), 0.0)
    return np.where(_blocked(scene, starts, dirs, far), 0.0, cosine).mean(
        axis=1).astype(np.float32)


def _sun_seen(scene: Scene, sun: SunLight, starts: np.ndarray, normals: np.ndarray,
              pixels: np.ndarray, probes: int) -> np.ndarray:
    """`_seen_cosine` of a sun: the rays of `disc_order`'s first `probes` points, then the
    others only where those disagree (`baking.pixel_kernels.sun_factors` where the scene
    has Embree's per-ray calls, else the same rule in numpy)."""
    order = disc_order(SUN_RAYS, probes)
    if scene.calls is not None:
        out = np.empty(len(starts), np.float32)
        offsets = disc_offsets(SUN_RAYS)[order] * math.tan(math.radians(sun.radius))
        sun_factors(tuple(scene.calls), starts, normals, pixels.astype(np.int64),
                    np.stack(_sun_frame(sun)), offsets, probes, out)
        return out
    dirs = sun_directions(sun, pixels)[:, order]
    cosine = np.maximum(np.einsum("pkc,pc->pk", dirs, normals), 0.0)
    reached = ~_blocked(scene, starts, dirs[:, :probes])
    seen = np.where(reached, cosine[:, :probes], 0.0).sum(axis=1)
    whole = reached.all(axis=1)
    seen[whole] += cosine[whole, probes:].sum(axis=1)
    part = reached.any(axis=1) & ~whole
    if part.any():
        rest = ~_blocked(scene, starts[part], dirs[part, probes:])
        seen[part] += np.where(rest, cosine[part, probes:], 0.0).sum(axis=1)
    return (seen / SUN_RAYS).astype(np.float32)


def light_factors(scene: Scene, starts: np.ndarray, normals: np.ndarray,
                  lights: tuple[SunLight | DirectionalLight | PointLight, ...], *,
                  workers: int | None = None, probes: int = SUN_PROBES) -> np.ndarray:
    """(P, L) float32 factor of each of `lights` (`SunLight`, `DirectionalLight`,
    `PointLight`) at the (P, 3) world `starts` with unit `normals` (P, 3) on the
    `baking.trace.Scene` `scene`: the mean over its shadow rays of max(0, n·d) for the
    rays that reach it — the cosine where nothing is in the way, 0 in full shadow, the
    cosine-weighted share of a sun's disc in its penumbra (its rays traced where its
    first `probes` disagree: `SUN_PROBES`; `SUN_RAYS` traces them all). A light's
    irradiance at the point is its irradiance at normal incidence (a point light's
    intensity / r²) times this."""
    if not 1 <= probes <= SUN_RAYS:
        raise ValueError(f"probes {probes}: expected 1 to {SUN_RAYS}")
    starts = np.asarray(starts, np.float64)
    normals = np.asarray(normals, np.float64)
    out = np.zeros((len(starts), len(lights)), np.float32)
    if not len(starts) or not len(lights):
        return out
    per_pixel = SUN_RAYS if any(isinstance(x, SunLight) for x in lights) else 1
    step = max(1, CHUNK_RAYS // per_pixel)
    jobs = [(j, lo) for j in range(len(lights)) for lo in range(0, len(starts), step)]

    def run(job: tuple[int, int]) -> None:
        j, lo = job
        pixels = np.arange(lo, min(lo + step, len(starts)))
        out[pixels, j] = _seen_cosine(scene, lights[j], starts[pixels], normals[pixels],
                                      pixels, probes)

    cores.for_items(lambda i: run(jobs[i]), len(jobs), "shadow rays", workers=workers)
    return out


def pixel_starts(scene: Scene, volume: volumes.Volume, origins: np.ndarray, dirs: np.ndarray,
                 points: np.ndarray, config: BakeConfig, *, smooth: bool = True
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) start points and (P, 3) unit normals of the shadow rays of P pixels: where
    the pixel's eye ray
    (`origins`, `dirs`, (P, 3)) meets `scene`, lifted and checked as the reference starts
    its paths (`reference.primary_hits`: `config.offset` voxels along the smoothed normal
    turned to the eye, moved back along the ray where that step crosses a facet); where
    the ray misses the scene (a silhouette pixel the rasteriser covers and Embree does
    not), the renderer's own surface point `points` (P, 3), lifted along its normal turned
    to the eye (where the field has no gradient, the eye's direction is the normal)."""
    from isolume.baking.reference import primary_hits

    hits = primary_hits(scene, volume, origins, dirs, config, smooth)
    starts = np.asarray(points, np.float64).copy()
    normals = np.empty_like(starts)
    missed = np.ones(len(starts), bool)
    missed[hits.pixels] = False
    starts[hits.pixels], normals[hits.pixels] = hits.origins, hits.normals
    if missed.any():
        d = np.asarray(dirs, np.float64)[missed]
        n = volumes.normals_at(volume, starts[missed], smooth=smooth,
                               flip=config.flip_normals).astype(np.float64)
        n *= np.where((n * d).sum(axis=1, keepdims=True) > 0, -1.0, 1.0)
        flat = ~(np.abs(np.linalg.norm(n, axis=1) - 1.0) < 1e-3)
        n[flat] = -d[flat]
        normals[missed] = n
        starts[missed] += config.offset * float(np.mean(volume.spacing)) * n
    return starts, normals
