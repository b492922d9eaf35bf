"""Path tracing from texel points: next-event estimation, diffuse bounces, MIS.

For irradiance, a path from texel point x with normal n estimates
E(x) = ∫ L_in(ω) cos θ dω. Each vertex v of the path adds its *direct* irradiance
estimate weighted by c_v = albedo^v (the radiance leaving a diffuse vertex is albedo·E/π,
and a cosine-sampled direction turns radiance into irradiance with the factor π):

* point and directional lights: deterministic shadow rays (hard shadows);
* a non-constant environment: one light sample (importance sampled) and the escaping
  cosine-sampled continuation ray, combined with the power heuristic (compiled for the
  procedural sky, `baking.sky_kernels`; numpy for the others);
* a constant environment: the cosine-sampled ray alone (it is already the ideal sampler).

`trace_paths` goes a vertex at a time over all the paths, with one embreex batch per
step. Irradiance under a constant environment or the procedural sky, without point or
directional lights — the common bake — is traced by `trace_whole_paths` instead: the
same kernels in the same order, in one compiled call per chunk of paths that calls
Embree itself for every ray (`kernels.trace_chunk`), so the same estimates to the bit
with no Python between the chunk's rays.

Paths end after `bounces` bounces; nothing is cut early, so the estimate of the B-bounce
solution is unbiased (no Russian roulette is needed with a fixed, small B). The last
vertex's continuation ray only has to tell whether it escapes: an occlusion query, about
half the cost of a closest hit (and none at all when nothing lights escaping rays).

In SH mode each path that escapes in direction ω adds c_v·π·Y(ω): the projection of the
transfer function, including shadowing and every bounce, onto the SH basis.

Split SH transfer (``PathSettings.sh_split``, an SH bake with ``direct_light="pixels"``):
escapes of the first vertex (the texel's own point: its direct, shadowed transfer T₀) and
of the bounce vertices (the indirect transfer T₁) go to two blocks of n² coefficients.
The renderer forms ℓ_sf·T₀ + ℓ·T₁ with the rotated sky without its sun ℓ_sf and the whole
rotated sky ℓ, and adds the rotated sun's direct light per pixel: the first vertex does
not see the sun, the bounces do (the sun's bounced light turns with the sky too).

Split direct light (``TracingLights.pixel_direct``, a bake with ``direct_light="pixels"``): at
the first vertex — the texel's own point — the point and directional lights add nothing
and the procedural sky is seen without its sun, by the cosine-sampled ray alone: what is
left of the sky is smooth, and cosine sampling alone is the better estimator for it (5 %
less noise per path than with the MIS light sample on the synthetic engine, and one
shadow ray less per path). Bounce vertices see every light, sampled as before. The
estimate is then the irradiance minus the lights' and the sun's direct irradiance, which
the renderer adds back per pixel with exact shadows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from isolume.baking import kernels, sampling_kernels, sky_kernels
from isolume.baking.lights import Light
from isolume.baking.rays import RayStats
from isolume.baking.sampling import power_heuristic

if TYPE_CHECKING:  # embreex is imported only when a bake runs
    from isolume.baking.trace import Scene

DIMS_PER_VERTEX = kernels.DIMS_PER_VERTEX


@dataclass(frozen=True)
class TracingLights:
    """What the integrator sees of a scene's lights (`baking.lighting.Lighting`, prepared
    by `baking.bake.tracing_lights`).

    Attributes:
        env: the distant environment (`baking.environment.Environment`) or None.
        sample_env: True to importance-sample the environment (next-event estimation).
        lights: point and directional lights.
        sky: `sky_kernels.sky_params` of a procedural sky (sampled by compiled kernels), or
            None for the numpy path of any other environment.
        pixel_direct: leave the lights' and the sun's direct light at the first vertex out
            (the renderer shades it per pixel; see the module docs).
        first_env, first_sky: what the first vertex sees of `env` and `sky` (without the
            sun when `pixel_direct`), derived.
        first_sample_env: whether the first vertex takes a light sample of the
            environment (not of a sun-free sky: its cosine-sampled ray alone), derived.
    """

    env: object | None
    sample_env: bool
    lights: tuple[Light, ...]
    sky: np.ndarray | None = None
    pixel_direct: bool = False
    first_env: object | None = field(init=False, repr=False)
    first_sky: np.ndarray | None = field(init=False, repr=False)
    first_sample_env: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        first_env, first_sky, first_sample = self.env, self.sky, self.sample_env
        if self.pixel_direct and hasattr(self.env, "without_sun"):  # a procedural sky
            first_env, first_sample = self.env.without_sun(), False
            first_sky = None if self.sky is None else sky_kernels.sky_without_sun(self.sky)
        object.__setattr__(self, "first_env", first_env)
        object.__setattr__(self, "first_sky", first_sky)
        object.__setattr__(self, "first_sample_env", first_sample)

    def lights_at(self, vertex: int) -> tuple[Light, ...]:
        """The point and directional lights whose light samples vertex `vertex` takes."""
        return () if self.pixel_direct and vertex == 0 else self.lights


@dataclass(frozen=True)
class PathSettings:
    """Per-bake path-tracing parameters.

    Attributes:
        bounces: diffuse bounces after the first vertex.
        albedo: (3,) diffuse reflectance.
        hit_offset: world distance by which new ray origins leave a hit surface.
        sh_order: None for irradiance, else the SH order whose basis escapes project on.
        rgb_transfer: SH mode with coloured albedo: keep a transfer vector per channel.
        sh_split: SH mode with the sun's direct light per pixel: the first vertex's escapes
            (direct transfer) and the bounces' (indirect transfer) in two blocks, first
            vertex first (see the module docs).
    """

    bounces: int
    albedo: tuple[float, float, float]
    hit_offset: float
    sh_order: int | None = None
    rgb_transfer: bool = False
    sh_split: bool = False

    @property
    def block(self) -> int:
        """Values of one SH transfer block: n² (×3 for coloured transfer)."""
        return self.sh_order**2 * (3 if self.rgb_transfer else 1)

    @property
    def channels(self) -> int:
        """Values per texel: 3 (RGB irradiance) or n² (×3 for coloured SH transfer, ×2
        for split transfer)."""
        if self.sh_order is None:
            return 3
        return self.block * (2 if self.sh_split else 1)


def _direct_lights(scene: Scene, pos, n, beta, lights, stats) -> np.ndarray:
    """(M, 3) irradiance from point/directional lights with shadow rays, times beta.

    pos, n, beta: (M, 3) arrays (views of the tracer's (3, M) rows)."""
    out = np.zeros(beta.shape)
    for light in lights:
        d, dist, e = light.towards(pos)
        cos = (n * d).sum(axis=1)
        lit = cos > 0
        if not lit.any():
            continue
        blocked = scene.occluded(pos[lit], d[lit], dist[lit] * (1 - 1e-5), stats)
        visible = np.flatnonzero(lit)[~blocked]
        out[visible] += beta[visible] * e[visible] * cos[visible, None]
    return out


def _direct_env(scene: Scene, pos, n, beta, keys, dim, env, stats) -> np.ndarray:
    """(M, 3) MIS-weighted environment light sample, times beta (arguments as
    `_direct_lights`)."""
    out = np.zeros(beta.shape)
    d, pdf = env.sample(sampling_kernels.uniform2(keys, dim))
    cos = (n * d).sum(axis=1)
    ok = (cos > 0) & (pdf > 0)
    if not ok.any():
        return out
    idx = np.flatnonzero(ok)
    blocked = scene.occluded(pos[idx], d[idx], None, stats)
    idx = idx[~blocked]
    weight = power_heuristic(pdf[idx], cos[idx] / np.pi)
    radiance = env.radiance(d[idx])
    out[idx] = beta[idx] * radiance * (cos[idx] * weight / pdf[idx])[:, None]
    return out


def _direct_sky(scene: Scene, result, alive, pos, n, beta, keys, dim, sky, stats) -> None:
    """`_direct_env` for the procedural sky with the compiled sampler: adds the
    MIS-weighted light sample of each vertex to ``result[alive]`` (pos, n, beta: (3, M))."""
    dirs, contrib, useful = sky_kernels.sky_light_samples(sky, keys, dim, n)
    idx, origins, shadow_dirs = sky_kernels.shadow_rays(useful, pos, dirs)
    blocked = scene.occluded(origins.T, shadow_dirs.T, None, stats)
    sky_kernels.add_unblocked(result, alive, idx, blocked, beta, contrib)


def _escape_sh(beta: np.ndarray, dirs: np.ndarray, settings: PathSettings) -> np.ndarray:
    """(M, C) SH projection π·beta·Y(ω) of escaping paths."""
    from isolume.baking.sh import basis

    y = np.pi * basis(dirs, settings.sh_order)
    if settings.rgb_transfer:
        return (y[:, :, None] * beta[:, None, :]).reshape(len(dirs), -1)
    return y * beta[:, :1]


def trace_paths(scene: Scene, origins: np.ndarray, normals: np.ndarray, keys: np.ndarray,
                lighting: TracingLights, settings: PathSettings, stats: RayStats | None = None,
                dirs: np.ndarray | None = None) -> np.ndarray:
    """Estimate irradiance (or SH transfer) for P paths starting at texel points.

    Args:
        scene: the level surface the paths live on.
        origins: (P, 3) start points, already offset off the surface.
        normals: (P, 3) unit normals at the start points. Both are used as (3, P) float32
            rows: the transposes of such arrays (`kernels.path_starts`) are not copied.
        keys: (P,) uint32 path keys (`rng.path_keys`).
        dirs: (P, 3) first directions if already drawn (`kernels.path_starts` draws
            them), else `kernels.cosine_directions` (keys, 0, normals) is drawn here.

    Returns:
        (P, C) float64 per-path estimates (C = `settings.channels`).
    """
    count = len(origins)
    result = np.zeros((count, settings.channels))
    alive = np.arange(count)
    pos, n = _rows(origins), _rows(normals)
    keys = np.ascontiguousarray(keys, np.uint32)
    beta = np.ones((3, count), np.float32)
    albedo = np.asarray(settings.albedo, np.float32)
    irradiance = settings.sh_order is None
    constant_radiance = _constant_radiance(lighting, settings)
    constant = constant_radiance is not None  # cosine sampling is ideal here
    escaped_radiance = constant_radiance if constant else np.zeros(3)
    sees_env = lighting.env is not None or not irradiance  # escaping rays bring something
    dirs = kernels.cosine_directions(keys, 0, n) if dirs is None else _rows(dirs)
    for vertex in range(settings.bounces + 1):
        dim = vertex * DIMS_PER_VERTEX
        env, sky, sample_env = (
            (lighting.first_env, lighting.first_sky, lighting.first_sample_env) if vertex == 0
            else (lighting.env, lighting.sky, lighting.sample_env))
        lights = lighting.lights_at(vertex)
        if irradiance and lights:
            result[alive, :3] += _direct_lights(scene, pos.T, n.T, beta.T, lights, stats)
        if irradiance and sky is not None:
            if sample_env:
                _direct_sky(scene, result, alive, pos, n, beta, keys, dim + 2, sky, stats)
        elif irradiance and sample_env:
            result[alive, :3] += _direct_env(scene, pos.T, n.T, beta.T, keys, dim + 2,
                                             env, stats)
        last = vertex == settings.bounces
        if last and not sees_env:  # nothing comes back along the last ray
            break
        if last:  # only whether the ray escapes matters: an occlusion query (half the cost)
            prim = scene.occluded(pos.T, dirs.T, None, stats).astype(np.int32) - 1
        else:
            hits = scene.intersect(pos.T, dirs.T, stats)
            prim = hits["prim"]
        if irradiance and sky is not None:
            sky_kernels.sky_add_escaped(sky, result, alive, prim, beta, dirs, n, sample_env)
        elif not constant and sees_env:
            _add_escaped(result, alive, prim < 0, beta.T, dirs.T, n.T, env, sample_env,
                         settings, vertex)
        if last:
            kernels.add_escaped(result, alive, prim, beta, escaped_radiance)
            break
        pos, n, beta, dirs, keys, alive = kernels.next_vertices(
            pos, dirs, hits["t"], hits["ng"], prim, beta, keys, alive, albedo,
            settings.hit_offset, result, escaped_radiance, dim + DIMS_PER_VERTEX)
        if len(alive) == 0:
            break
    return result


@dataclass(frozen=True)
class WholePaths:
    """The parameters of `kernels.trace_chunk` for one bake (`whole_paths`)."""

    bounces: int
    albedo: np.ndarray
    offset: float
    escaped_radiance: np.ndarray
    sky: np.ndarray
    first_sky: np.ndarray
    first_sampled: bool
    use_sky: bool


def whole_paths(lighting: TracingLights, settings: PathSettings) -> WholePaths | None:
    """`WholePaths` where `trace_whole_paths` covers the lighting (irradiance,
    a constant environment or the procedural sky, no point or directional lights), else
    None."""
    constant_radiance = _constant_radiance(lighting, settings)
    use_sky = lighting.sky is not None
    covered = settings.sh_order is None and not lighting.lights and (
        constant_radiance is not None or use_sky)
    if not covered:
        return None
    no_sky = np.zeros(sky_kernels.SKY_PARAMS)
    return WholePaths(
        settings.bounces, np.asarray(settings.albedo, np.float32), settings.hit_offset,
        np.zeros(3) if use_sky else constant_radiance,
        lighting.sky if use_sky else no_sky, lighting.first_sky if use_sky else no_sky,
        lighting.first_sample_env, use_sky)


def _constant_radiance(lighting: TracingLights, settings: PathSettings) -> np.ndarray | None:
    """(3,) π·L that a cosine-sampled ray escaping to a constant environment brings, in
    an irradiance bake (where cosine sampling alone is the ideal sampler); else None."""
    rgb = getattr(lighting.env, "rgb", None) if not lighting.sample_env else None
    if settings.sh_order is not None or rgb is None:
        return None
    return np.pi * np.asarray(rgb, np.float64)


NO_STRATA = np.zeros(0, np.int64)
"""The strata of paths whose first directions come from their keys (`trace_whole_paths`,
`kernels.trace_chunk`)."""


class _PassSums(Protocol):
    """The pass sums `trace_whole_paths` adds to (`passes.PassSums`)."""

    sum: np.ndarray
    second: np.ndarray
    n: np.ndarray


def trace_whole_paths(scene: Scene, params: WholePaths,
                      starts: tuple[np.uint32, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                    np.ndarray, np.ndarray],
                      weights: np.ndarray, acc: _PassSums,
                      stats: RayStats | None = None, strata: np.ndarray = NO_STRATA
                      ) -> None:
    """`kernels.path_starts`, `trace_paths` and `kernels.accumulate` in one compiled call
    that calls Embree per ray (needs ``scene.calls``).

    Args:
        starts: the arguments of `kernels.path_starts`: (seed_key, ids, pos, samples,
            texels, origins, normals).
        weights: (C,) brightness weights; acc: the pass sums (``sum`` (A, 3),
            ``second`` (A,), ``n`` (A,)) the paths add to.
        stats: the seconds added are the call's: Embree's and the arithmetic between
            its calls.
        strata: (P,) the paths' strata: first directions by
            `kernels.stratify_first_directions`; or (0,): by the paths' keys.
    """
    recorder = scene.recorder
    if recorder is None:
        record = _NO_RECORD
    else:
        record = recorder.reserve(2 * (params.bounces + 1) * len(starts[2]))
    start = time.perf_counter()
    rays = kernels.trace_chunk(tuple(scene.calls), *starts, strata, params.bounces,
                               params.albedo,
                               params.offset, params.escaped_radiance, params.sky,
                               params.first_sky, params.first_sampled, params.use_sky,
                               weights, acc.sum,
                               acc.second, acc.n, record)
    if stats is not None:
        stats.add(rays, time.perf_counter() - start)
    if recorder is not None:
        recorder.commit(rays)


_NO_RECORD = np.empty((0, kernels.RAY_RECORD_ROWS), np.float32)


def _rows(vectors: np.ndarray) -> np.ndarray:
    """(3, N) float32 C-contiguous rows of (N, 3) vectors; no copy when `vectors` is the
    transpose of such rows."""
    return np.ascontiguousarray(np.transpose(vectors), np.float32)


def _add_escaped(result: np.ndarray, alive: np.ndarray, escaped: np.ndarray,
                 beta: np.ndarray, dirs: np.ndarray, n: np.ndarray, env,
                 sample_env: bool, settings: PathSettings, vertex: int = 0) -> None:
    """Add what the cosine-sampled rays of path vertex `vertex` that `escaped` (M,) bring
    back from a non-constant environment `env` (MIS-weighted against its light sample
    when `sample_env`), or their SH projection (into the bounces' block of a split
    transfer after the first vertex)."""
    if not escaped.any():
        return
    esc_dirs = dirs[escaped].astype(np.float64)
    if settings.sh_order is not None:
        first = settings.block if settings.sh_split and vertex > 0 else 0
        columns = np.s_[first:first + settings.block]
        result[alive[escaped], columns] += _escape_sh(beta[escaped], esc_dirs, settings)
        return
    weight = np.full(len(esc_dirs), np.pi)
    if sample_env:
        cos = (n[escaped] * dirs[escaped]).sum(axis=1)
        weight *= power_heuristic(cos / np.pi, env.pdf(esc_dirs))
    result[alive[escaped], :3] += beta[escaped] * env.radiance(esc_dirs) * weight[:, None]
