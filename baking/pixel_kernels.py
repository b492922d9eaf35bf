"""Compiled per-pixel work of off-screen pictures, a block of pixels in one call: no
Python, no temporaries and no GIL between the rays.

`primary_starts`: `baking.reference.primary_hits`'s rays — each pixel's eye ray, the
smoothed normal where it meets the surface, turned to the side it arrives from, and the
start point lifted off the surface along it, checked for a facet in the way.

`sun_factors`: a sun's shadow rays (`baking.shadow_rays`). Per pixel: the directions
towards the points of the sun's disc (`shadow_rays.sun_directions`'s spiral, turned by the
pixel's index), the cosine of each with the pixel's normal, and Embree's occlusion test
of the first `probes` of them — the points spread widest over the disc
(`shadow_rays.disc_order`). Where those all reach the sun the pixel sees the whole disc,
where all are blocked none of it; only where they disagree, in a penumbra, are the other
rays traced.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from isolume.baking.embree_kernels import (
    intersect_one,
    occluded_before,
    occluded_one,
    ray_buffer,
)
from isolume.volumes.field import JIT, normal_in, normal_scratch

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


@numba.njit(**JIT)
def primary_starts(calls: tuple[int, ...], origins: np.ndarray, dirs: np.ndarray,
                   stencil: tuple[np.ndarray, ...], flip: bool, lift: float, back: float,
                   hit: np.ndarray, points: np.ndarray, starts: np.ndarray,
                   normals: np.ndarray) -> None:
    """`baking.reference.primary_hits` of a block of N rays, to the bit: where each meets
    the surface, its smoothed normal there turned to the side of the hit facet the ray
    arrives from (the eye's direction where the field has no gradient), and its start
    point `lift` along that normal — moved back along the ray instead where that step
    crosses a facet.

    Args:
        calls: `trace.EmbreeCalls` of the scene.
        origins, dirs: (N, 3) float64 rays (unit directions).
        stencil: `volumes.field.normal_stencil` of the volume; flip: normals towards
            higher values.
        lift: world distance a start leaves the surface by; back: how far before the hit
            the check of that step starts (free space: the ray has just crossed it).
        hit: (N,) bool out: whether each ray meets the surface; points, starts, normals:
            (N, 3) float64 out, where it does.
    """
    ray, bits, address = ray_buffer()
    scratch = normal_scratch()
    data, w, inverse, origin, spacing = stencil
    for i in range(len(dirs)):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        t, prim = intersect_one(calls, ray, bits, address, np.float32(origins[i, 0]),
                                np.float32(origins[i, 1]), np.float32(origins[i, 2]),
                                np.float32(dx), np.float32(dy), np.float32(dz))
        hit[i] = prim >= 0
        if prim < 0:
            continue
        fx, fy, fz = np.float64(ray[12]), np.float64(ray[13]), np.float64(ray[14])
        dist = np.float64(t)
        px, py, pz = origins[i, 0] + dist * dx, origins[i, 1] + dist * dy, \
            origins[i, 2] + dist * dz
        nx, ny, nz = normal_in(data, w, inverse, origin, spacing, px, py, pz, flip, scratch)
        nx, ny, nz = np.float64(nx), np.float64(ny), np.float64(nz)
        turn = -np.sign(fx * dx + fy * dy + fz * dz)  # the facet towards the eye
        fx, fy, fz = fx * turn, fy * turn, fz * turn
        if nx * fx + ny * fy + nz * fz < 0:
            nx, ny, nz = -nx, -ny, -nz
        if not abs(math.sqrt(nx * nx + ny * ny + nz * nz) - 1.0) < 1e-3:  # no gradient
            nx, ny, nz = -dx, -dy, -dz
        sx, sy, sz = px + lift * nx, py + lift * ny, pz + lift * nz
        bx, by, bz = px - back * dx, py - back * dy, pz - back * dz
        ux, uy, uz = sx - bx, sy - by, sz - bz
        length = math.sqrt(ux * ux + uy * uy + uz * uz)
        if length > 0 and occluded_before(
                calls, ray, bits, address, np.float32(bx), np.float32(by), np.float32(bz),
                np.float32(ux / length), np.float32(uy / length), np.float32(uz / length),
                np.float32(min(length, 1e30))):
            sx, sy, sz = px - length * dx, py - length * dy, pz - length * dz
        points[i, 0], points[i, 1], points[i, 2] = px, py, pz
        starts[i, 0], starts[i, 1], starts[i, 2] = sx, sy, sz
        normals[i, 0], normals[i, 1], normals[i, 2] = nx, ny, nz
