"""The procedural sky (`baking.environment.SkyEnvironment`), compiled: its light samples,
radiance and sampling density per ray, for the path kernels (`baking.kernels`).

A sky reaches the kernels packed into one float64 array (`sky_params`, `SKY_PARAMS`
words), its fields at the indices and slices named below (`ZENITH` … `SUN_DENSITY`),
which both the packing and the kernels read. Per ray the kernels hold it as a tuple
(`_sky_tuple`) and read its fields by the same names: constant indices and slices of a
tuple, resolved when numba compiles.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np

from isolume.baking.sampling_kernels import (
    dimension_key,
    sincos_turns,
    tangent_frame,
    uniform31,
    uniform_f32,
)
from isolume.volumes.field import JIT, PART

if TYPE_CHECKING:
    from isolume.baking.environment.models import SkyEnvironment

ZENITH = slice(0, 3)
"""Radiance (linear RGB) of the gradient straight up."""
HORIZON = slice(3, 6)
"""Radiance of the gradient at the horizon."""
GROUND = slice(6, 9)
"""Radiance below the horizon."""
HORIZON_BLUR = 9
"""sin(horizon blur angle): the gradient meets the ground over −h ≤ z ≤ h."""
SUN_DIRECTION = slice(10, 13)
"""Unit vector towards the sun."""
SUN_COS_RADIUS = 13
"""Cosine of the sun's angular radius."""
SUN_RADIANCE = slice(14, 17)
"""Radiance inside the sun's cone."""
SUN_PROBABILITY = 17
"""Probability that the sampler picks the sun's cone (0: no sun)."""
SUN_DENSITY = 18
"""1 / (solid angle of the sun's cone), sr⁻¹: the density of the sampler's sun cone."""
SKY_PARAMS = 19
"""Length of `sky_params`."""


def sky_params(env: SkyEnvironment) -> np.ndarray:
    """(SKY_PARAMS,) float64 description of a `SkyEnvironment` for the sky kernels."""
    cone = 2.0 * math.pi * (1.0 - env.sun_cos_radius)
    out = np.empty(SKY_PARAMS)
    out[ZENITH], out[HORIZON], out[GROUND] = env.zenith, env.horizon, env.ground
    out[HORIZON_BLUR] = math.sin(math.radians(env.horizon_blur))
    out[SUN_DIRECTION] = env.sun_direction
    out[SUN_COS_RADIUS] = env.sun_cos_radius
    out[SUN_RADIANCE] = env.sun_radiance
    out[SUN_PROBABILITY] = env.sun_probability
    out[SUN_DENSITY] = 1.0 / cone if cone > 0 else 0.0
    return out


def sky_without_sun(p: np.ndarray) -> np.ndarray:
    """`sky_params` of the same sky without its sun (no sun radiance, no sun sampling)."""
    out = np.array(p, np.float64)
    out[SUN_RADIANCE] = 0.0
    out[SUN_PROBABILITY] = 0.0
    return out


@numba.njit(**JIT)
def _sky_tuple(p: np.ndarray) -> tuple:
    """The (SKY_PARAMS,) array as a tuple of its words in order, read by the same field
    names: helpers called per ray take it by value (an array argument costs reference
    counting on every call, ten times the helper's arithmetic). The helpers are inlined
    by numba itself (`volumes.field.PART`): left to LLVM they stay calls, and the loops
    calling them do not vectorise (65 vs 22 ns per light sample)."""
    return (p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11], p[12],
            p[13], p[14], p[15], p[16], p[17], p[18])


@numba.njit(**PART)
def _sky_sun(p: tuple, x: float, y: float, z: float) -> bool:
    """Is unit direction (x, y, z) inside the sun's cone? (No branch: it is random.)"""
    sx, sy, sz = p[SUN_DIRECTION]
    return (p[SUN_PROBABILITY] > 0) & (x * sx + y * sy + z * sz >= p[SUN_COS_RADIUS])


@numba.njit(**PART)
def _sky_pdf(p: tuple, x: float, y: float, z: float) -> float:
    """Density (1/sr) of the sky's sampler at unit direction (x, y, z)."""
    p_sun = p[SUN_PROBABILITY]
    return (1.0 - p_sun) / (4.0 * math.pi) + (
        p_sun * p[SUN_DENSITY] if _sky_sun(p, x, y, z) else 0.0)


@numba.njit(**PART)
def _sky_radiance(p: tuple, x: float, y: float, z: float):
    """(r, g, b) sky radiance arriving from unit direction (x, y, z)."""
    h = p[HORIZON_BLUR]
    t = min(max((z + h) / (2 * h), 0.0), 1.0) if h > 0 else 0.0
    g = t * t * (3.0 - 2.0 * t) if h > 0 else (1.0 if z >= 0 else 0.0)
    sun = 1.0 if _sky_sun(p, x, y, z) else 0.0
    up = max(z, 0.0)
    zenith, horizon, ground, sun_rgb = p[ZENITH], p[HORIZON], p[GROUND], p[SUN_RADIANCE]
    return (g * (horizon[0] + (zenith[0] - horizon[0]) * up) + (1.0 - g) * ground[0]
            + sun * sun_rgb[0],
            g * (horizon[1] + (zenith[1] - horizon[1]) * up) + (1.0 - g) * ground[1]
            + sun * sun_rgb[1],
            g * (horizon[2] + (zenith[2] - horizon[2]) * up) + (1.0 - g) * ground[2]
            + sun * sun_rgb[2])


@numba.njit(**PART)
def _sky_sample(p: tuple, sun_frame: tuple, u0: float, u1: np.float32):
    """The sky sampler's unit direction (x, y, z) for uniforms (u0, u1): the sun cone
    with probability p_sun, else the whole sphere (`SkyEnvironment.sample`); `sun_frame`
    is `tangent_frame` of the sun direction, the angle's sine and cosine come from
    `sincos_turns` (u1 in single precision, below 1). Both candidates are computed and
    one is selected: a branch on the random u0 mispredicts every other time."""
    p_sun = p[SUN_PROBABILITY]
    sx, sy, sz = p[SUN_DIRECTION]
    c32, s32 = sincos_turns(u1)
    cos_phi, sin_phi = float(c32), float(s32)
    cos_t = 1.0 - (u0 / max(p_sun, 1e-300)) * (1.0 - p[SUN_COS_RADIUS])
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    tx, ty, tz, bx, by, bz = sun_frame
    cx, cy = sin_t * cos_phi, sin_t * sin_phi
    v = min((u0 - p_sun) / (1.0 - p_sun), 1.0 - 2.0**-53)
    z = 1.0 - 2.0 * v
    rho = math.sqrt(max(0.0, 1.0 - z * z))
    in_sun = u0 < p_sun
    return (cx * tx + cy * bx + cos_t * sx if in_sun else rho * cos_phi,
            cx * ty + cy * by + cos_t * sy if in_sun else rho * sin_phi,
            cx * tz + cy * bz + cos_t * sz if in_sun else z)


@numba.njit(**JIT)
def sky_light_samples(p: np.ndarray, keys: np.ndarray, dim: int, normals: np.ndarray):
    """One importance-sampled sky direction per path vertex, MIS-weighted against cosine
    sampling (power heuristic), as `integrator._direct_env` does with numpy.

    Args:
        p: (SKY_PARAMS,) `sky_params`.
        keys: (M,) path keys; normals: (3, M) unit normals of the vertices.

    Returns:
        dirs (3, M) float32, contributions (3, M) float64 = L·cos·w/pdf (to be multiplied
        by the throughput where the shadow ray is not blocked; zero where not useful), and
        useful (M,) bool (cos > 0 and pdf > 0).
    """
    k0, k1 = dimension_key(dim), dimension_key(dim + 1)
    m = len(keys)
    dirs = np.empty((3, m), np.float32)
    contrib = np.empty((3, m))
    useful = np.empty(m, np.bool_)
    sun_frame = tangent_frame(*_sky_tuple(p)[SUN_DIRECTION])
    p = _sky_tuple(p)
    for i in range(m):  # no branches: the loop runs at 26 ns per vertex instead of 65
        x, y, z = _sky_sample(p, sun_frame, uniform31(keys[i], k0), uniform_f32(keys[i], k1))
        dirs[0, i], dirs[1, i], dirs[2, i] = x, y, z
        cos = normals[0, i] * x + normals[1, i] * y + normals[2, i] * z
        pdf = _sky_pdf(p, x, y, z)
        ok = (cos > 0) & (pdf > 0)
        useful[i] = ok
        other = cos / math.pi
        scale = cos * pdf / (pdf * pdf + other * other) if ok else 0.0  # L·cos·w/pdf
        r, g, b = _sky_radiance(p, x, y, z)
        contrib[0, i], contrib[1, i], contrib[2, i] = r * scale, g * scale, b * scale
    return dirs, contrib, useful


@numba.njit(**JIT)
def shadow_rays(useful: np.ndarray, pos: np.ndarray, dirs: np.ndarray):
    """The shadow rays of the (M,) `useful` light samples of vertices at (3, M) `pos`
    towards (3, M) `dirs`: their indices (K,) int64, origins (3, K) and directions
    (3, K), float32."""
    idx = np.flatnonzero(useful)
    origins = np.empty((3, len(idx)), np.float32)
    out = np.empty((3, len(idx)), np.float32)
    for j in range(len(idx)):
        for c in range(3):
            origins[c, j] = pos[c, idx[j]]
            out[c, j] = dirs[c, idx[j]]
    return idx, origins, out


@numba.njit(**JIT)
def add_unblocked(result: np.ndarray, alive: np.ndarray, idx: np.ndarray,
                  blocked: np.ndarray, beta: np.ndarray, contrib: np.ndarray) -> None:
    """result[alive[idx[j]], :3] += beta[:, idx[j]]·contrib[:, idx[j]] for every shadow
    ray j that is not `blocked` (beta, contrib: (3, M))."""
    for j in range(len(idx)):  # without branches: blocked rays add exactly 0
        i = idx[j]
        seen = np.float64(not blocked[j])
        for c in range(3):
            result[alive[i], c] += beta[c, i] * contrib[c, i] * seen


@numba.njit(**JIT)
def sky_add_escaped(p: np.ndarray, result: np.ndarray, alive: np.ndarray, prim: np.ndarray,
                    beta: np.ndarray, dirs: np.ndarray, normals: np.ndarray,
                    mis: bool) -> None:
    """result[alive[i], :3] += beta[:, i]·L(dir)·π·w for every cosine-sampled ray i that
    escaped (prim < 0), w the power-heuristic weight against the sky's light sample when
    `mis` (the vertex took one), else 1 (beta, dirs, normals: (3, M))."""
    p = _sky_tuple(p)
    m = len(prim)
    added = np.empty((3, m))
    for i in range(m):  # without branches, in SIMD lanes; hits get zero
        x, y, z = float(dirs[0, i]), float(dirs[1, i]), float(dirs[2, i])
        cos = normals[0, i] * x + normals[1, i] * y + normals[2, i] * z
        own, pdf = cos / math.pi, _sky_pdf(p, x, y, z) if mis else 0.0
        total = own * own + pdf * pdf
        weight = math.pi * own * own / total if (total > 0) & (prim[i] < 0) else 0.0
        r, g, b = _sky_radiance(p, x, y, z)
        added[0, i], added[1, i], added[2, i] = r * weight, g * weight, b * weight
    for i in range(m):  # without branches: `added` is 0 for rays that hit
        row = alive[i]
        for c in range(3):
            result[row, c] += beta[c, i] * added[c, i]
