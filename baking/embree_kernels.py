"""Embree called per ray from compiled code: closest hits and occlusion of (3, M) rays,
through the addresses of `rtcIntersect1` and `rtcOccluded1` in `trace.EmbreeCalls`, with
no Python (and so no wait for the GIL) between the rays (`baking.kernels.trace_chunk`).
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from isolume.volumes.field import JIT, PART

_INVALID_ID = np.uint32(0xFFFFFFFF)  # RTC_INVALID_GEOMETRY_ID
_ALL_GEOMETRY = np.uint32(0xFFFFFFFF)  # a ray mask that every geometry passes


@intrinsic
def _call_embree(typingctx, function, scene, ray):
    """Call ``void function(RTCScene scene, RTCRay(Hit)* ray, NULL)``: `rtcIntersect1` or
    `rtcOccluded1` at address `function` (all three arguments are 64-bit integers)."""
    if not all(isinstance(t, types.Integer) and t.bitwidth == 64
               for t in (function, scene, ray)):
        return None

    def codegen(context, builder, signature, args):
        pointer = ir.IntType(8).as_pointer()
        callee = ir.FunctionType(ir.VoidType(), [pointer, pointer, pointer])
        target = builder.inttoptr(args[0], callee.as_pointer())
        builder.call(target, [builder.inttoptr(args[1], pointer),
                              builder.inttoptr(args[2], pointer), pointer(None)])
        return context.get_dummy_value()

    return types.void(function, scene, ray), codegen


@numba.njit(**PART)
def _set_ray(ray, bits, ox, oy, oz, dx, dy, dz) -> None:
    """Fill an RTCRayHit (`ray` float32, `bits` its uint32 view) for a query from (ox, oy,
    oz) towards (dx, dy, dz), distances 0 … ∞, no hit yet."""
    ray[0], ray[1], ray[2], ray[3] = ox, oy, oz, np.float32(0.0)
    ray[4], ray[5], ray[6], ray[7] = dx, dy, dz, np.float32(0.0)
    ray[8] = np.float32(np.inf)
    bits[9], bits[10], bits[11] = _ALL_GEOMETRY, np.uint32(0), np.uint32(0)  # mask, id, flags
    bits[18], bits[19] = _INVALID_ID, _INVALID_ID  # geomID, instID[0]


@numba.njit(**JIT)
def ray_buffer():
    """An RTCRayHit (at most 96 bytes) on a 16-byte boundary: its float32 words, the same
    words as uint32, and its address (for `occluded_one`, reused from ray to ray)."""
    storage = np.empty(40, np.float32)
    first = (16 - storage.ctypes.data % 16) % 16 // 4
    ray = storage[first:first + 24]
    return ray, ray.view(np.uint32), ray.ctypes.data


@numba.njit(**PART)
def intersect_one(calls: tuple[int, ...], ray: np.ndarray, bits: np.ndarray, address: int,
                  ox: float, oy: float, oz: float, dx: float, dy: float, dz: float
                  ) -> tuple[np.float32, np.int32]:
    """The closest hit of the float32 ray from (ox, oy, oz) along (dx, dy, dz), distances
    0 … ∞: its distance and triangle id in its piece (-1: no hit); its unnormalised facet
    normal is left in ``ray[12:15]``. `ray`, `bits`, `address`: a `ray_buffer`."""
    scene, intersect, _ = calls
    _set_ray(ray, bits, ox, oy, oz, dx, dy, dz)
    _call_embree(intersect, scene, address)
    return ray[8], np.int32(-1) if bits[18] == _INVALID_ID else np.int32(bits[17])


@numba.njit(**PART)
def occluded_before(calls: tuple[int, ...], ray: np.ndarray, bits: np.ndarray, address: int,
                    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
                    far: float) -> bool:
    """Does anything block the float32 ray from (ox, oy, oz) along (dx, dy, dz) at a
    distance 0 … `far`? `ray`, `bits`, `address`: a `ray_buffer`."""
    scene, _, occluded = calls
    _set_ray(ray, bits, ox, oy, oz, dx, dy, dz)
    ray[8] = far
    _call_embree(occluded, scene, address)
    return ray[8] < 0  # tfar becomes -inf when something is hit


@numba.njit(**PART)
def occluded_one(calls: tuple[int, ...], ray: np.ndarray, bits: np.ndarray, address: int,
                 ox: float, oy: float, oz: float, dx: float, dy: float, dz: float) -> bool:
    """Does anything block the float32 ray from (ox, oy, oz) along (dx, dy, dz), distances
    0 … ∞? `ray`, `bits`, `address`: a `ray_buffer`."""
    return occluded_before(calls, ray, bits, address, ox, oy, oz, dx, dy, dz,
                           np.float32(np.inf))


@numba.njit(**JIT)
def intersect_rays(calls: tuple[int, ...], pos: np.ndarray, dirs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest hits of (3, M) float32 rays (distances 0 … ∞), Embree called per ray
    (`trace.EmbreeCalls`).

    Returns:
        t (M,) float32 distances, prim (M,) int32 triangle ids in their pieces (-1: no
        hit), ng (M, 3) float32 unnormalised facet normals — as embreex's
        ``run(..., output=1)``.
    """
    ray, bits, address = ray_buffer()
    m = pos.shape[1]
    t = np.empty(m, np.float32)
    prim = np.empty(m, np.int32)
    ng = np.empty((m, 3), np.float32)
    for i in range(m):
        t[i], prim[i] = intersect_one(calls, ray, bits, address, pos[0, i], pos[1, i],
                                      pos[2, i], dirs[0, i], dirs[1, i], dirs[2, i])
        ng[i, 0], ng[i, 1], ng[i, 2] = ray[12], ray[13], ray[14]
    return t, prim, ng


@numba.njit(**JIT)
def occluded_rays(calls: tuple[int, ...], pos: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(M,) bool: does anything block the (3, M) float32 rays (distances 0 … ∞)?"""
    ray, bits, address = ray_buffer()
    m = pos.shape[1]
    blocked = np.empty(m, np.bool_)
    for i in range(m):
        blocked[i] = occluded_one(calls, ray, bits, address, pos[0, i], pos[1, i], pos[2, i],
                                  dirs[0, i], dirs[1, i], dirs[2, i])
    return blocked
