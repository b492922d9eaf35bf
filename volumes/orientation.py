"""Placing a volume upright in the world: header orientations and ``--up``.

Volume files say where their index axes point: NRRD ``space directions`` (in its
``space``), NIfTI's affine (sform or qform, RAS), MetaImage ``TransformMatrix`` (LPS, as
ITK writes it), DICOM ``ImageOrientationPatient`` with the slices' positions (LPS). The
world of isolume is the patient's LPS frame wherever a file names one (RAS is turned into
it): +z is superior, so the default camera (world up +z, looking from −y, the anterior
side) sees a head upright and from the front.

A `Volume` stays an axis-aligned grid (DESIGN §2: texel coordinates are ``(p − lo) / (hi −
lo)`` everywhere), so an orientation is applied by reordering the samples — transposing
and flipping the array, and moving the origin to the sample that becomes the first — which
is exact for the axis permutations and flips that scanners write. An oblique acquisition
is placed along the nearest axes (as nibabel's ``as_closest_canonical`` does); `Placement`
reports the angle left out.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from isolume.volumes.core import Volume, VolumeError

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
"""What ``--up`` accepts."""


@dataclass(frozen=True)
class Placement:
    """Samples reordered so that their axes run along world +x, +y, +z.

    Attributes:
        data: (Z, Y, X) the samples in world axis order: a view of the samples given
            (transposed and flipped, nothing read or copied).
        spacing: (3,) voxel size along world x, y, z.
        origin: (3,) world position of the first sample.
        residual_deg: the largest angle between an index axis and the world axis it was
            placed along (0 for permutations and flips).
    """

    data: np.ndarray
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float]
    residual_deg: float
    axes: str = "x, y, z"

    def describe(self, frame: str) -> str:
        """One line for `isolume info`: where the index axes went."""
        text = f"{frame}: index axes x, y, z along world {self.axes}"
        if self.residual_deg > 0.5:
            text += f" (oblique by {self.residual_deg:.1f}°, placed along the nearest axes)"
        return text


def nearest_axes(directions: np.ndarray) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The signed axis permutation nearest to `directions`.

    Args:
        directions: (3, 3) column a = world direction of index axis a (x, y, z order).

    Returns:
        (world axis of each index axis, its sign ±1): the permutation maximising the sum
        of |cosines| between index axes and the world axes they are placed along.
    """
    d = np.asarray(directions, np.float64)
    best = max(itertools.permutations(range(3)),
               key=lambda perm: sum(abs(d[perm[a], a]) for a in range(3)))
    signs = tuple(1 if d[best[a], a] >= 0 else -1 for a in range(3))
    return tuple(best), signs


def place(data: np.ndarray, spacing: npt.ArrayLike, origin: npt.ArrayLike,
          directions: np.ndarray | None,
          where: str = "volume") -> Placement:
    """Reorder (Z, Y, X) `data` whose voxel (k, j, i) lies at ``origin + directions @
    (spacing * (i, j, k))`` so that its axes run along world +x, +y, +z.

    Args:
        spacing, origin: (3,) as the file gives them (index axes x, y, z; world).
        directions: (3, 3) unit columns, the world direction of each index axis; None
            for the identity.

    Raises:
        VolumeError: directions that are not three independent finite vectors.
    """
    spacing = np.asarray(spacing, np.float64)
    origin = np.asarray(origin, np.float64)
    if directions is None:
        return Placement(data, tuple(spacing), tuple(origin), 0.0)
    d = np.asarray(directions, np.float64)
    norms = np.linalg.norm(d, axis=0) if d.shape == (3, 3) else np.zeros(3)
    if d.shape != (3, 3) or not np.isfinite(d).all() or not (norms > 0).all() or abs(
            np.linalg.det(d / norms)) < 1e-3:
        raise VolumeError(f"{where}: orientation {d.tolist()} is not three independent "
                          "axis directions")
    d = d / norms
    world, signs = nearest_axes(d)
    arr = np.asarray(data).transpose(2, 1, 0)  # index axes x, y, z
    n = np.array(arr.shape)
    first = np.where(np.array(signs) < 0, n - 1, 0)  # the sample that becomes the first
    snapped = np.zeros((3, 3))
    for a in range(3):
        snapped[world[a], a] = signs[a]
        if signs[a] < 0:
            arr = np.flip(arr, axis=a)
    order = [world.index(w) for w in range(3)]  # index axis placed along world axis w
    arr = arr.transpose(order).transpose(2, 1, 0)
    cosines = np.clip(np.abs(d[list(world), [0, 1, 2]]), -1.0, 1.0)
    axes = ", ".join(f"{'+' if signs[a] > 0 else '-'}{'xyz'[world[a]]}" for a in range(3))
    return Placement(arr, tuple(float(v) for v in spacing[order]),
                     tuple(float(v) for v in origin + snapped @ (spacing * first)),
                     float(np.degrees(np.arccos(cosines.min()))), axes)


def up_rotation(axis: str) -> np.ndarray:
    """(3, 3) rotation that turns the volume's `axis` (one of `UP_AXES`) to world +z: about
    x for ±y, about y for ±x and −z (so a −z turn keeps the side facing the default camera,
    −y, where it was).

    Raises:
        VolumeError: an unknown axis.
    """
    rotations = {
        "z": np.eye(3),
        "-z": np.diag([-1.0, 1.0, -1.0]),
        "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
        "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
        "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
        "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
    }
    key = axis.strip().lower().replace("+", "")
    if key not in rotations:
        raise VolumeError(f"--up {axis!r}: expected one of {', '.join(UP_AXES)}")
    return rotations[key]


def turn_up(volume: Volume, axis: str) -> Volume:
    """`volume` turned (about the world origin) so that its `axis` points up (+z)."""
    r = up_rotation(axis)
    if np.array_equal(r, np.eye(3)):
        return volume
    placed = place(volume.data, volume.spacing, r @ np.asarray(volume.origin), r,
                   volume.source or volume.name)
    turned = f"turned so that its {axis.strip().lower()} axis points up"
    return Volume(placed.data, placed.spacing, placed.origin, name=volume.name,
                  source=volume.source, suggested_iso=volume.suggested_iso,
                  placement=f"{volume.placement}; {turned}" if volume.placement else turned)
