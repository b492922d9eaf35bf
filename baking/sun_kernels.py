"""A sun's shadow rays for a block of pixels in one compiled call (`baking.shadow_rays`).

Per pixel: the directions towards the points of the sun's disc (`shadow_rays.sun_directions`'s
spiral, turned by the pixel's index), the cosine of each with the pixel's normal, and
Embree's occlusion test of the first `probes` of them — the points spread widest over the
disc (`shadow_rays.disc_order`). Where those all reach the sun the pixel sees the whole
disc, where all are blocked none of it; only where they disagree, in a penumbra, are the
other rays traced. No Python, no temporaries and no GIL between the rays.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from isolume.baking.embree_kernels import occluded_one, ray_buffer
from isolume.volumes.field import JIT

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
"""Turn (radians) of the disc's spiral from one point to the next, and from one pixel's
spiral to the next pixel's."""


@numba.njit(**JIT)
def sun_factors(calls: tuple[int, ...], starts: np.ndarray, normals: np.ndarray,
                pixels: np.ndarray, frame: np.ndarray, offsets: np.ndarray, probes: int,
                out: np.ndarray) -> None:
    """Into (P,) float32 `out`: each pixel's mean over the K disc points of max(0, n·d)
    for those whose ray reaches the sun, tracing the others only where the `probes` first
    disagree.

    Args:
        calls: `trace.EmbreeCalls` of the scene.
        starts, normals: (P, 3) float64 start points and unit normals n.
        pixels: (P,) int64 pixel indices: pixel i's points are turned by i ×
            `GOLDEN_ANGLE`.
        frame: (3, 3) float64 rows: the disc's centre direction and two unit axes u, v
            across it.
        offsets: (K, 2) float64 the points in the (u, v) plane (the unit disc's × the tangent
            of the sun's radius), the probes first.
        probes: how many of `offsets` are traced first (1 … K).
    """
    ray, bits, address = ray_buffer()
    count = len(offsets)
    cosine = np.empty(count)
    dirs = np.empty((count, 3), np.float32)
    for p in range(len(starts)):
        turn = pixels[p] * GOLDEN_ANGLE
        c, s = math.cos(turn), math.sin(turn)
        for j in range(count):
            a = offsets[j, 0] * c - offsets[j, 1] * s
            b = offsets[j, 0] * s + offsets[j, 1] * c
            dx = frame[0, 0] + a * frame[1, 0] + b * frame[2, 0]
            dy = frame[0, 1] + a * frame[1, 1] + b * frame[2, 1]
            dz = frame[0, 2] + a * frame[1, 2] + b * frame[2, 2]
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            dx, dy, dz = dx / length, dy / length, dz / length
            cosine[j] = max(dx * normals[p, 0] + dy * normals[p, 1] + dz * normals[p, 2], 0.0)
            dirs[j, 0], dirs[j, 1], dirs[j, 2] = dx, dy, dz
        ox, oy, oz = np.float32(starts[p, 0]), np.float32(starts[p, 1]), np.float32(starts[p, 2])
        seen = 0.0
        reached = 0
        for j in range(probes):
            if not occluded_one(calls, ray, bits, address, ox, oy, oz, dirs[j, 0], dirs[j, 1],
                                dirs[j, 2]):
                seen += cosine[j]
                reached += 1
        if reached == probes:
            for j in range(probes, count):
                seen += cosine[j]
        elif reached > 0:
            for j in range(probes, count):
                if not occluded_one(calls, ray, bits, address, ox, oy, oz, dirs[j, 0],
                                    dirs[j, 1], dirs[j, 2]):
                    seen += cosine[j]
        out[p] = seen / count
