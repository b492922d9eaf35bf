"""Synthetic and analytic volumes, generated on demand: ``synthetic:NAME[:SIZE]``.

Every volume is a smooth density in [0, 1] (no hard steps, so marching cubes and gradients
behave as on real scans) built from signed distance functions (SDF, negative inside):
``density = 0.5 - 0.5 * tanh(sdf / width)``, so the isovalue 0.5 lies exactly on the SDF's
zero set. ``SIZE`` is the number of samples along the longest axis (default per volume).
World units: the longest axis spans 1.0 (spacing = 1 / (SIZE - 1)), centred at the origin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from isolume.volumes.core import Volume, VolumeError


@dataclass(frozen=True)
class _Spec:
    builder: Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]
    default_size: int
    aspect: tuple[float, float, float]  # extent x, y, z relative to the longest axis
    iso: tuple[float, ...]
    about: str


def _density(sdf: np.ndarray, width: float) -> np.ndarray:
    """Smooth occupancy from a signed distance (world units); 0.5 on the zero set."""
    return 0.5 - 0.5 * np.tanh(sdf / width)


def _sphere(x, y, z, w):
    return _density(np.sqrt(x * x + y * y + z * z) - SPHERE_RADIUS, w)


def _torus(x, y, z, w):
    ring = np.sqrt(x * x + y * y) - 0.28
    return _density(np.sqrt(ring * ring + z * z) - 0.12, w)


def _marschner_lobb(x, y, z, w):
    """Marschner & Lobb (1994) test signal on [-1, 1]^3 (f_M = 6, alpha = 0.25)."""
    del w
    x, y, z = 2 * x, 2 * y, 2 * z
    fm, alpha = 6.0, 0.25
    rho_r = np.cos(2 * np.pi * fm * np.cos(np.pi * np.sqrt(x * x + y * y) / 2))
    return (1 - np.sin(np.pi * z / 2) + alpha * (1 + rho_r)) / (2 * (1 + alpha))


def _box_sdf(x, y, z, half):
    q = np.stack([np.abs(x) - half[0], np.abs(y) - half[1], np.abs(z) - half[2]])
    outside = np.linalg.norm(np.maximum(q, 0), axis=0)
    return outside + np.minimum(q.max(axis=0), 0)


def _engine(x, y, z, w):
    """Two-cylinder engine-like block: a casing (density 0.55) with blind bores, cooling
    fins, a side pocket and a closed internal channel; dense sleeves (1.0) cast into the bore
    walls and a crank shaft.

    Isovalue 0.3 shows the casing; 0.8 shows the sleeves and the crank shaft alone.
    """
    block = _box_sdf(x, y, z + 0.04, (0.46, 0.26, 0.2))
    bores = np.minimum(
        np.hypot(x - 0.2, y) - 0.13, np.hypot(x + 0.2, y) - 0.13
    )  # vertical cylinders along z
    bore_depth = np.maximum(bores, -(z + 0.08))  # blind bores, floors at z = -0.08
    casing = np.maximum(block, -bore_depth)
    pocket = _box_sdf(x, y + 0.26, z + 0.04, (0.3, 0.06, 0.1))  # side pocket (open)
    casing = np.maximum(casing, -pocket)
    cavity = _box_sdf(x, y, z + 0.16, (0.3, 0.12, 0.03))  # closed internal channel
    casing = np.maximum(casing, -cavity)
    fins = _box_sdf(np.mod(x + 0.05, 0.1) - 0.05, np.abs(y) - 0.26, z + 0.02, (0.012, 0.05, 0.14))
    fins = np.maximum(fins, np.abs(x) - 0.4)  # cooling fins on the back face
    fins = np.maximum(fins, y)
    casing = np.minimum(casing, fins)
    liner_shell = np.abs(bores - 0.03) - 0.015  # dense sleeves cast into the bore walls
    liners = np.maximum(liner_shell, np.abs(z - 0.03) - 0.11)
    crank = np.maximum(np.hypot(y, z + 0.24) - 0.05, np.abs(x) - 0.5)
    dense = np.minimum(liners, crank)
    return np.maximum(0.55 * _density(casing, w), _density(dense, w))


def _mixing_layer(x, y, z, w):
    """Richtmyer–Meshkov-like mixing layer: a multi-scale perturbed interface with bubbles."""
    rng = np.random.default_rng(1603)
    height = np.zeros_like(x)
    for scale, amp, count in ((2, 0.08, 3), (5, 0.035, 6), (11, 0.015, 10)):
        for _ in range(count):
            kx, ky = rng.normal(size=2) * scale * np.pi
            phase = rng.uniform(0, 2 * np.pi)
            height += amp / np.sqrt(count) * np.sin(kx * x + ky * y + phase)
    sdf = z - height
    for _ in range(14):  # detached bubbles and spikes near the interface
        c = rng.uniform(-0.4, 0.4, size=3) * (1, 1, 0.5)
        r = rng.uniform(0.03, 0.07)
        blob = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
        sdf = np.where(c[2] > 0, np.minimum(sdf, blob), np.maximum(sdf, -blob))
    return _density(sdf, 2.5 * w)


def _shells(x, y, z, w):
    """Three nested spherical shells, each with openings cut by cones along different axes."""
    r = np.sqrt(x * x + y * y + z * z) + 1e-12
    sdf = np.full_like(x, np.inf)
    axes = ((0, 0, 1), (1, 0, 0), (0, 1, 0))
    for radius, axis in zip((0.18, 0.31, 0.44), axes, strict=True):
        shell = np.abs(r - radius) - 0.025
        cos_to_axis = (x * axis[0] + y * axis[1] + z * axis[2]) / r
        cone = (np.abs(cos_to_axis) - 0.9) * r  # openings at both poles of the axis
        sdf = np.minimum(sdf, np.maximum(shell, cone))
    return _density(sdf, w)


def _contact(x, y, z, w):
    """A sphere of radius 0.2 hanging about a voxel (at 56 samples) above a plane, the
    solid below z = −0.25, their shells 1.5 voxels wide: a contact gap, where the light
    changes within a texel."""
    sdf = np.minimum(z + 0.25, np.sqrt(x * x + y * y + (z + 0.02) ** 2) - 0.2)
    return _density(sdf, 1.25 * w)


SPHERE_RADIUS = 0.35
"""Radius of ``synthetic:sphere`` in world units (the analytic answer for tests)."""

_SPECS: dict[str, _Spec] = {
    "sphere": _Spec(_sphere, 64, (1, 1, 1), (0.5,), "sphere of radius 0.35"),
    "torus": _Spec(_torus, 64, (1, 1, 0.5), (0.5,), "torus R = 0.28, r = 0.12"),
    "marschner_lobb": _Spec(
        _marschner_lobb, 41, (1, 1, 1), (0.5,), "Marschner–Lobb test signal"
    ),
    "engine": _Spec(_engine, 128, (1, 0.625, 0.5), (0.3, 0.8), "engine-like machined part"),
    "mixing_layer": _Spec(
        _mixing_layer, 96, (1, 1, 0.75), (0.5,), "Richtmyer–Meshkov-like mixing layer"
    ),
    "shells": _Spec(_shells, 96, (1, 1, 1), (0.5,), "nested shells with openings"),
    "contact": _Spec(_contact, 56, (1, 1, 1), (0.5,), "sphere just above a plane"),
}

NAMES: tuple[str, ...] = tuple(_SPECS)
DEFAULT = "synthetic:engine"
"""The built-in default volume (view and render when no volume is given)."""


def describe() -> dict[str, str]:
    """Name -> one-line description of every synthetic volume."""
    return {name: spec.about for name, spec in _SPECS.items()}


def make(name: str, size: int | None = None) -> Volume:
    """Build ``synthetic:NAME[:SIZE]``.

    Args:
        name: one of `NAMES`.
        size: samples along the longest axis (>= 8); the volume's default when None.

    Returns:
        Volume with spacing 1/(size-1) (isotropic), centred at the world origin.
    """
    spec, size = _checked(name, size)
    h, axes = _axes(spec, size)
    data = layers(name, size, 0, len(axes[2]))
    origin = tuple(float(a[0]) for a in axes)
    label = f"synthetic:{name}:{size}"
    return Volume(
        data,
        spacing=(h, h, h),
        origin=origin,
        name=name,
        source=label,
        suggested_iso=spec.iso,
    )


def shape(name: str, size: int | None = None) -> tuple[int, int, int]:
    """(Z, Y, X) samples of ``synthetic:NAME:SIZE``."""
    spec, size = _checked(name, size)
    _, axes = _axes(spec, size)
    return len(axes[2]), len(axes[1]), len(axes[0])


def layers(name: str, size: int | None, k0: int, k1: int) -> np.ndarray:
    """(k1 - k0, Y, X) float32 z layers k0..k1-1 of ``synthetic:NAME:SIZE``: the same
    samples as `make`'s, a part at a time (a volume larger than memory, written layer by
    layer)."""
    spec, size = _checked(name, size)
    h, axes = _axes(spec, size)
    z, y, x = np.meshgrid(axes[2][k0:k1], axes[1], axes[0], indexing="ij")
    return spec.builder(x, y, z, 1.2 * h).astype(np.float32)


def _checked(name: str, size: int | None) -> tuple[_Spec, int]:
    """The spec of `name` and its size (the default for None), or VolumeError."""
    spec = _SPECS.get(name)
    if spec is None:
        raise VolumeError(
            f"synthetic:{name}: unknown synthetic volume; expected one of {', '.join(NAMES)}"
        )
    size = spec.default_size if size is None else int(size)
    if not 8 <= size <= 1024:
        raise VolumeError(f"synthetic:{name}:{size}: size must be between 8 and 1024 samples")
    return spec, size


def _axes(spec: _Spec, size: int) -> tuple[float, list[np.ndarray]]:
    """(spacing, [x, y, z] sample coordinates, world units)."""
    h = 1.0 / (size - 1)
    counts = [max(2, round(a * (size - 1)) + 1) for a in spec.aspect]  # x, y, z
    return h, [(np.arange(n) - (n - 1) / 2) * h for n in counts]


def parse(spec: str) -> Volume:
    """Build a volume from ``synthetic:NAME[:SIZE]``."""
    parts = spec.split(":")
    if len(parts) not in (2, 3) or parts[0] != "synthetic":
        raise VolumeError(f"{spec}: expected synthetic:NAME[:SIZE]")
    size = None
    if len(parts) == 3:
        try:
            size = int(parts[2])
        except ValueError:
            raise VolumeError(f"{spec}: SIZE must be an integer, got {parts[2]!r}") from None
    return make(parts[1], size)
