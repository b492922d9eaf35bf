"""The illumination lattice and its file (DESIGN §4).

Geometry: a lattice of scale s has ``max(2, round(n * s * r))`` texels along each axis of
``n`` voxels, spanning the volume's world box (the union of voxel cells); r
(`refinement`) is 1 on the volume's finest axis and on the others their voxel size over
the finest, at most `MAX_REFINEMENT`: texels are cubes where the voxels are not (a CT of
slices twice as thick as its pixels gets texels as thin as a pixel in every direction).
Texel centres carry the values: texel t along an axis sits at
``lo + (t + 1/2) * (hi - lo) / m``, so at s = 1 texel centres coincide with the samples of
the finest axes, and a GL texture coordinate is simply ``(p - lo) / (hi - lo)`` (the
half-texel term is built into GL's texel centres).

File: one ``.npz`` holding the arrays of the texels that are active or computed, and
``meta`` (JSON); `baking.lattice_file` reads and writes it a slab at a time. `Lattice.load`
reads it dense over the box; a display reads only the texels it shows
(`baking.view_texels.LatticeOnFile`); a bake holds it over its plan's texels only
(`baking.plan_lattice.PlanLattice`).

Side-aware lookup (`Lattice.sample` with normals; ``shaders/lattice.glsl`` the same): each
texel's light weighed by how its facing meets the point's normal (`baking.sided`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from isolume.baking import octahedral
from isolume.baking.config import BakeConfig
from isolume.baking.environment import latlong_pixel_directions
from isolume.baking.errors import BakeError
from isolume.baking.lattice_file import LatticeFile, lattice_kind, write_lattice
from isolume.baking.sided import side_weights, sided_mix
from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.volumes.core import Volume

CONFIG_VERSION = 1
"""Version of the bake config a file's metadata holds (``meta["config"]``, written with
``meta["config_version"]``); a file without one holds version 1's fields."""
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
MAX_REFINEMENT = 2.0
"""A coarse axis of an anisotropic volume gets at most this many times the texels per voxel
of its finest axis (`refinement`). Walls thinner than a texel leak light between their
faces (`tests/test_failure_modes.py`), and a texel as tall as a thick slice is thicker
than the bone a CT shows in it: on CThead's 2× block means (voxels 2 × 2 × 4) the 64-path
irradiance lattice is 11.7 % off with texels as tall as the voxels, 9.3 % with cubic ones
(twice the texels). The cap keeps a thick-sliced scan (slices five times as thick as its
pixels) at twice the texels of one texel per voxel."""


def refinement(spacing: npt.ArrayLike) -> np.ndarray:
    """(3,) xyz texels per voxel along each axis per texel per voxel along the finest: the
    voxel size over the finest voxel size (1 where the voxels are cubes), at most
    `MAX_REFINEMENT`; `spacing` (3,) the voxel size, xyz, world units."""
    spacing = np.asarray(spacing, np.float64)
    return np.minimum(spacing / spacing.min(), MAX_REFINEMENT)


@dataclass(frozen=True)
class LatticeGeometry:
    """Where the texels are.

    Attributes:
        shape: (Z, Y, X) texel counts.
        lo, hi: (3,) world box corners, xyz.
    """

    shape: tuple[int, int, int]
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @classmethod
    def for_volume(cls, volume: Volume, scale: float) -> LatticeGeometry:
        """Lattice of `scale` texels per voxel along `volume`'s finest axis over its world
        box, about as many per world unit along the others (`refinement`)."""
        per_voxel = [scale * float(r) for r in refinement(volume.spacing)[::-1]]  # z, y, x
        shape = tuple(max(2, round(n * f)) for n, f in zip(volume.data.shape, per_voxel,
                                                             strict=True))
        lo, hi = volume.box
        return cls(shape, tuple(float(v) for v in lo), tuple(float(v) for v in hi))

    @property
    def texel_size(self) -> np.ndarray:
        """(3,) xyz world size of one texel."""
        return (np.array(self.hi) - np.array(self.lo)) / np.array(self.shape[::-1])

    def centres(self, flat_ids: np.ndarray) -> np.ndarray:
        """(N, 3) world xyz centres of texels given by (N,) flat [z,y,x] indices."""
        k, j, i = np.unravel_index(flat_ids, self.shape)
        idx = np.stack([i, j, k], axis=1) + 0.5
        return np.array(self.lo) + idx * self.texel_size

    def all_centres(self) -> np.ndarray:
        """(Z, Y, X, 3) world xyz of every texel centre."""
        axes = [np.array(self.lo[a]) + (np.arange(self.shape[2 - a]) + 0.5)
                * self.texel_size[a] for a in range(3)]
        z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return np.stack([x, y, z], axis=-1)

    def to_texel_coords(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world xyz → (N, 3) continuous texel coordinates (z, y, x); centres are
        at integers. Many points (a picture's: millions) in blocks on every core."""
        points = np.asarray(points)
        if len(points) <= COORD_BLOCK:
            return self._texel_coords(points)
        out = np.empty((len(points), 3))

        def block(part: slice) -> None:
            out[part] = self._texel_coords(points[part])

        cores.for_blocks(block, len(points), COORD_BLOCK, "texel coordinates")
        return out

    def _texel_coords(self, points: np.ndarray) -> np.ndarray:
        """`to_texel_coords` on the calling thread (a view, z, y, x reversed)."""
        f = (np.asarray(points, np.float64) - np.array(self.lo)) / self.texel_size - 0.5
        return f[:, ::-1]


COORD_BLOCK = 1 << 16
"""Points `LatticeGeometry.to_texel_coords` converts in one work item."""
BRICK = 8
"""Texels per side of a brick: the renderer's atlas keeps a lattice in bricks
(`app.render.bricks`), and a bake to a texel error judges it by them (`baking.density`)."""


def brick_grid(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """(BZ, BY, BX) bricks over a (Z, Y, X) lattice."""
    return tuple(-(-int(n) // BRICK) for n in shape)


def trilinear_corners(shape: tuple[int, int, int], coords_zyx: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The texels a trilinear lookup at (N, 3) texel coordinates reads in a (Z, Y, X)
    grid, clamped to the edge texels like GL's CLAMP_TO_EDGE.

    Returns:
        (N, 8, 3) int64 z, y, x indices of the corners and (N, 8) float64 weights.
    """
    shape = np.array(shape)
    c = np.clip(coords_zyx, 0, shape - 1)
    base = np.minimum(np.floor(c).astype(np.int64), shape - 2).clip(0)
    frac = c - base
    offs = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)])
    idx = np.minimum(base[:, None, :] + offs[None], shape - 1)
    weights = np.prod(np.where(offs[None] == 1, frac[:, None, :], 1 - frac[:, None, :]),
                      axis=2)
    return idx, weights


def trilinear(grid: np.ndarray, coords_zyx: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a (Z, Y, X, C) grid at (N, 3) texel coordinates, clamped
    to the edge texels like GL's CLAMP_TO_EDGE. Returns (N, C) float64."""
    idx, w = trilinear_corners(grid.shape[:3], coords_zyx)
    corners = grid[idx[..., 0], idx[..., 1], idx[..., 2]].astype(np.float64)  # (N, 8, C)
    return np.einsum("nk,nkc->nc", w, corners)


class _ShownLattice(Protocol):
    """What `shown_lookup` reads of a lattice (`Lattice`, `view_texels.HeldLattice`)."""

    geometry: LatticeGeometry

    def shown(self, region: tuple[Any, ...]) -> np.ndarray: ...

    def displayed(self, region: tuple[Any, ...]) -> np.ndarray: ...

    def displayed_facing(self, region: tuple[Any, ...]) -> np.ndarray: ...


def shown_lookup(lattice: _ShownLattice, points_xyz: np.ndarray, normals: np.ndarray | None = None
                 ) -> np.ndarray:
    """(N, C) the shader's lookup at (N, 3) world points of what a display shows of
    `lattice` (a `Lattice`, or anything with its ``geometry``, ``shown``, ``displayed``
    and ``displayed_facing``: `baking.view_texels.HeldLattice`): trilinear over the
    shown texels, renormalised (0 where none is), side-aware (`sided_mix`) with the
    points' (N, 3) unit `normals` turned to the eye."""
    coords = lattice.geometry.to_texel_coords(points_xyz)
    idx, w = trilinear_corners(lattice.geometry.shape, coords)
    region = (idx[..., 0], idx[..., 1], idx[..., 2])
    w = w * lattice.shown(region)
    sides = (np.ones_like(w) if normals is None
             else side_weights(lattice.displayed_facing(region), normals))
    return sided_mix(w, sides, lattice.displayed(region).astype(np.float64))


TRAPPED_PATHS = 64
"""Under an environment that sends light from every direction, a texel whose displayed
light rests on at least this many paths and is exactly zero is *trapped*: every path
stayed in a pocket of the level it was lit on that is sealed from the sky (with 64 paths, a
texel that sees the sky through even 5 % of its hemisphere escapes with 96 % probability).
The surface a display draws through it is not that pocket — it is seen — so
`Lattice.shown` leaves the texel out and the lookups take its neighbours, or the local
shading where no neighbour shows light. Other lights leave texels honestly dark in
shadow: there nothing is trapped."""

_SKY_EVERYWHERE: dict[str, bool] = {}


def sky_everywhere(config: BakeConfig | None) -> bool:
    """Whether `config`'s environment sends light from every direction (every centre of a
    64 × 128 latitude-longitude grid of directions); False without an environment."""
    if config is None or config.lighting.environment is None:
        return False
    if config.env not in _SKY_EVERYWHERE:
        dirs = latlong_pixel_directions(64, 128).reshape(-1, 3)
        radiance = config.lighting.environment.radiance(dirs)
        _SKY_EVERYWHERE[config.env] = bool((radiance.max(axis=1) > 0).all())
    return _SKY_EVERYWHERE[config.env]


def drop_trapped(mask: np.ndarray, many: np.ndarray,
                 light_of: Callable[[tuple[np.ndarray, ...]], np.ndarray]) -> np.ndarray:
    """`mask` (bool, any shape) with its trapped texels cleared, for a light that is
    `sky_everywhere` (the caller checks): of the texels where `many` (their displayed light
    rests on `TRAPPED_PATHS` or more paths), those whose light is all zero. Only their
    light is read: `light_of(at)`, (N, C) at the index tuple `at`."""
    if many.any():
        at = np.nonzero(many)
        mask[at] &= light_of(at).any(axis=-1)
    return mask


def _luminance(values: np.ndarray, kind: str) -> np.ndarray:
    """(…) luminance of (…, C) texel values (SH: the DC term)."""
    return values[..., :3] @ LUMINANCE if kind == "irradiance" else values[..., 0]


def path_variance(mean: np.ndarray, second: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(…) float64 unbiased per-path variance of a brightness from its (…) `mean`, mean
    square `second` and sample counts `samples` (0 with fewer than 2 samples)."""
    n = samples.astype(np.float64)
    var = np.maximum(second.astype(np.float64) - mean.astype(np.float64) ** 2, 0.0)
    return np.where(n > 1, var * n / np.maximum(n - 1, 1), 0.0)


def standard_error(values: np.ndarray, samples: np.ndarray, second: np.ndarray,
                   kind: str) -> np.ndarray:
    """(…) float32 standard error of the luminance mean of texels with (…, C) `values`,
    (…) `samples` and `second` moments (`Lattice`'s, of `kind`); inf where < 2 samples."""
    var = path_variance(_luminance(values, kind), second, samples)
    se = np.where(samples > 1, np.sqrt(var / np.maximum(samples, 1)), np.inf)
    return se.astype(np.float32)


@dataclass
class Lattice:
    """An illumination lattice.

    Attributes:
        geometry: texel placement.
        values: (Z, Y, X, C) float32 per-texel mean estimate: irradiance E (RGB, linear,
            C = 3) or SH transfer coefficients.
        samples: (Z, Y, X) uint32 paths averaged into each texel (0 = not computed).
        second: (Z, Y, X) float32 mean of the squared per-path luminance estimate.
        active: (Z, Y, X) bool, texels the bake must fill.
        meta: format version, kind, volume identity, statistics (JSON-ready).
        config: the `BakeConfig` the lattice is baked with, or None. The file holds it as
            a dict in its metadata (`file_meta` writes it, `open_lattice` reads it, with
            its version `CONFIG_VERSION`).
        preview: None, or (Z, Y, X, C) float32 estimates traced on the *displayed*
            isosurface (the lazy viewer's preview passes, `baking.preview`); never saved.
        preview_paths: None, or (Z, Y, X) uint16 paths behind each preview (0 = none).
            A display shows the preview while the texel has fewer samples of its own
            than that, and the texel's own mean from then on (`displayed`).
        facing: (Z, Y, X, 2) uint8 octahedral code (`baking.octahedral`) of the mean
            direction the texel's paths started along (its start normals weighted like
            its samples over its levels); `octahedral.UNKNOWN` where not computed, and
            everywhere in files written before it was kept. Zeros when not given.
        preview_facing: None, or (Z, Y, X, 2) uint8 the same of the previews' paths
            (`ensure_preview_facing` makes it); shown where the preview is (`displayed_facing`).
    """

    geometry: LatticeGeometry
    values: np.ndarray
    samples: np.ndarray
    second: np.ndarray
    active: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    preview: np.ndarray | None = None
    preview_paths: np.ndarray | None = None
    config: BakeConfig | None = None
    facing: np.ndarray | None = None
    preview_facing: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.facing is None:
            self.facing = np.zeros((*self.geometry.shape, 2), np.uint8)

    @classmethod
    def empty(cls, geometry: LatticeGeometry, channels: int, meta: dict[str, Any],
              config: BakeConfig | None = None) -> Lattice:
        """A lattice with nothing computed, baked with `config`."""
        shape = geometry.shape
        return cls(geometry, np.zeros((*shape, channels), np.float32),
                   np.zeros(shape, np.uint32), np.zeros(shape, np.float32),
                   np.zeros(shape, bool), meta, config=config)

    @property
    def kind(self) -> str:
        return lattice_kind(self.meta)

    def __str__(self) -> str:
        """How messages name it: its kind, volume and size (its arrays are not printed)."""
        name = self.meta.get("volume", {}).get("name", "a volume")
        return (f"the {self.kind} lattice of {name!r} ({'×'.join(map(str, self.geometry.shape))} "
                "texels)")

    @property
    def computed(self) -> np.ndarray:
        """(Z, Y, X) bool: texels with at least one sample."""
        return self.samples > 0

    def shown(self, region: tuple[Any, ...] = (...,)) -> np.ndarray:
        """Bool mask of the texels a display uses in `region` (slices of (Z, Y, X)): those
        computed or holding a preview, except the trapped (`TRAPPED_PATHS`)."""
        return self._shown(region, *self._counts(region))

    def previewed(self, region: tuple[Any, ...] = (...,)) -> np.ndarray:
        """Bool mask of the texels in `region` whose preview is shown: it rests on more
        paths than the texel's own samples."""
        samples, previews = self._counts(region)
        return np.zeros(samples.shape, bool) if previews is None else previews > samples

    def displayed(self, region: tuple[Any, ...] = (...,)) -> np.ndarray:
        """(…, C) float32 values a display shows in `region`: the preview where
        `previewed`, else the texel's own mean (0 where neither exists)."""
        return self._picked(region, self.values, self.preview, np.float32,
                            *self._counts(region))

    def displayed_facing(self, region: tuple[Any, ...] = (...,)) -> np.ndarray:
        """(…, 2) uint8 facing codes a display uses in `region`, as `displayed` picks the
        values: the preview's where `previewed`, else the texel's own where computed,
        else unknown."""
        return self._picked(region, self.facing, self.preview_facing, np.uint8,
                            *self._counts(region))

    def display(self, region: tuple[Any, ...] = (...,)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`shown`, `displayed_facing` and `displayed` of `region` (what an upload reads),
        whole while another process writes them (the bake's, which then sends the texels
        it wrote): every choice is made from one copy of the counts, and a texel whose
        counts moved meanwhile is left out (values 0) rather than shown with a mean its
        count does not vouch for (black), or hidden with light (too bright)."""
        counts = self._counts(region, copy=True)
        shown = self._shown(region, *counts)
        facing = self._picked(region, self.facing, self.preview_facing, np.uint8, *counts)
        values = self._picked(region, self.values, self.preview, np.float32, *counts)
        again = self._counts(region)
        moved = (counts[0] != again[0]) | (False if counts[1] is None else counts[1] != again[1])
        shown &= ~moved
        values[~shown], facing[moved] = 0, 0
        return shown, facing, values

    def _counts(self, region: tuple[Any, ...], copy: bool = False
                ) -> tuple[np.ndarray, np.ndarray | None]:
        """(samples, preview_paths or None) in `region`: copies (one reading of the counts)
        with `copy`, else views where slices make them."""
        take = np.array if copy else np.asarray
        previews = None if self.preview_paths is None else take(self.preview_paths[region])
        return take(self.samples[region]), previews

    def _shown(self, region: tuple[Any, ...], samples: np.ndarray,
               previews: np.ndarray | None) -> np.ndarray:
        """`shown` of `region` by the counts `samples` and `previews` (`_counts`)."""
        mask = samples > 0
        if previews is not None:
            mask |= previews > 0
        if not sky_everywhere(self.config):
            return mask
        many = samples >= TRAPPED_PATHS
        if previews is not None:
            many |= previews >= TRAPPED_PATHS

        def light_of(at: tuple) -> np.ndarray:  # what `displayed` shows there
            light = self.values[region][at]
            if previews is None:
                return light
            return np.where((previews[at] > samples[at])[:, None], self.preview[region][at],
                            light)

        return drop_trapped(mask, many, light_of)

    def _picked(self, region: tuple[Any, ...], own: np.ndarray, preview: np.ndarray | None,
                dtype: type, samples: np.ndarray, previews: np.ndarray | None) -> np.ndarray:
        """(…, C) `dtype` in `region`: `preview` (or None) where the counts `samples` and
        `previews` (`_counts`) show it, else `own` where computed, else 0."""
        picked = np.where((samples > 0)[..., None], own[region], 0)
        if preview is not None and previews is not None:
            picked = np.where((previews > samples)[..., None], preview[region], picked)
        return picked.astype(dtype)

    def ensure_preview_facing(self) -> np.ndarray:
        """`preview_facing`, made (all unknown) if it is None."""
        if self.preview_facing is None:
            self.preview_facing = np.zeros((*self.geometry.shape, 2), np.uint8)
        return self.preview_facing

    def store_preview(self, flat: np.ndarray, paths: np.ndarray, values: np.ndarray,
                      codes: np.ndarray) -> None:
        """Store the previews of (N,) texels `flat` (``preview`` and ``preview_paths``
        must be set): (N,) `paths` behind each (0: none could start), and for those with
        paths, in order, (M, C) means and (M, 2) facing codes. The values go first: another
        process may be displaying them as soon as their paths are set."""
        traced = np.asarray(flat)[np.asarray(paths) > 0]
        self.preview.reshape(-1, self.preview.shape[-1])[traced] = values
        self.ensure_preview_facing().reshape(-1, 2)[traced] = codes
        self.preview_paths.reshape(-1)[flat] = paths

    def facing_known(self) -> bool:
        """Whether any texel a display shows has a known facing (else the side-aware
        lookup is the plain one)."""
        return bool(octahedral.known(self.displayed_facing()).any())

    def standard_error(self) -> np.ndarray:
        """(Z, Y, X) float32 standard error of the luminance mean (`standard_error`)."""
        return standard_error(self.values, self.samples, self.second, self.kind)

    def sample(self, points_xyz: np.ndarray, normalized: bool = False,
               normals: np.ndarray | None = None) -> np.ndarray:
        """(N, C) trilinear lookup at (N, 3) world points, as the GPU does it.

        Args:
            normalized: what the shader does while a bake is incomplete: weight only the
                texels shown (`shown`, with the values `displayed`) and renormalise;
                points with no such neighbour get 0.
            normals: (N, 3) unit normals at the points, turned to the eye: the side-aware
                lookup (`sided_mix`, with the facings `displayed_facing`), as the shader
                does it for a lattice with known facings.

        Raises:
            BakeError: points or normals that are not (N, 3) arrays of numbers.
        """
        points_xyz = _points(points_xyz, "points")
        normals = None if normals is None else _points(normals, "normals", len(points_xyz))
        if normalized:
            return shown_lookup(self, points_xyz, normals)
        coords = self.geometry.to_texel_coords(points_xyz)
        if normals is None:
            return trilinear(self.values, coords)
        idx, w = trilinear_corners(self.geometry.shape, coords)
        region = (idx[..., 0], idx[..., 1], idx[..., 2])
        return sided_mix(w, side_weights(self.facing[region], normals),
                         self.values[region].astype(np.float64))

    # -- files -------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write atomically to `path` (.npz, `baking.lattice_file`)."""
        write_lattice(path, {"values": self.values, "samples": self.samples,
                             "second": self.second, "active": self.active,
                             "facing": self.facing},
                      file_meta(self.meta, self.geometry, self.config))

    @classmethod
    def load(cls, path: str | os.PathLike[str], volume: Volume | None = None) -> Lattice:
        """Read a lattice file, dense over its box; with `volume`, check that it was baked
        for that volume (before its arrays are read).

        Raises:
            BakeError: missing/corrupt file, unknown format version, other volume.
        """
        file, geometry, config = open_lattice(path, volume)
        arrays = file.read_dense()  # each array's shape checked against the box's
        return cls(geometry, arrays["values"], arrays["samples"], arrays["second"],
                   arrays["active"], file.meta, config=config, facing=arrays["facing"])

    def check_volume(self, volume: Volume, path: str | os.PathLike[str] = "lattice") -> None:
        """Raise BakeError unless this lattice was baked for `volume`."""
        check_identity(self.meta, volume, path)


def _points(values: npt.ArrayLike, what: str, count: int | None = None) -> np.ndarray:
    """`values` as an (N, 3) float64 array (N = `count` where given).

    Raises:
        BakeError: naming `what`, the shape given and the shape expected.
    """
    try:
        array = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        raise BakeError(f"Lattice.sample: {what} {type(values).__name__}: expected an "
                        "(N, 3) array of x, y, z") from None
    if array.ndim != 2 or array.shape[1] != 3 or count not in (None, len(array)):
        rows = "N" if count is None else str(count)
        raise BakeError(f"Lattice.sample: {what} of shape {array.shape}: expected "
                        f"({rows}, 3), x, y, z")
    return array


def file_meta(meta: dict[str, Any], geometry: LatticeGeometry, config: BakeConfig | None
              ) -> dict[str, Any]:
    """`meta` as a lattice file holds it: with the box's shape and corners, and the bake
    config as a dict (the only writer of that dict, with its version `CONFIG_VERSION`)."""
    meta = dict(meta, shape=list(geometry.shape), box_lo=list(geometry.lo),
                box_hi=list(geometry.hi))
    if config is not None:
        meta.update(config=config.to_dict(), config_version=CONFIG_VERSION)
    return meta


def open_lattice(path: str | os.PathLike[str], volume: Volume | None = None
                 ) -> tuple[LatticeFile, LatticeGeometry, BakeConfig | None]:
    """A lattice file opened (`baking.lattice_file.LatticeFile`; its meta without the
    bake config's dict), its geometry and bake config; with `volume`, checked to be baked
    for it. No texel is read.

    Raises:
        BakeError: missing/corrupt file, unknown format version, other volume.
    """
    file = LatticeFile.open(path)
    meta = file.meta
    config = _config_from(meta.pop("config", None), meta.pop("config_version", CONFIG_VERSION),
                          file.path)
    lo, hi = (_corner(meta, key, file.path) for key in ("box_lo", "box_hi"))
    if not all(a < b for a, b in zip(lo, hi, strict=True)):
        raise BakeError(f"{path}: lattice box from {lo} to {hi}: expected each coordinate of "
                        "box_hi above box_lo's")
    _check_channels(file, config)
    if volume is not None:
        check_identity(meta, volume, path)
    return file, LatticeGeometry(file.shape, lo, hi), config


def _corner(meta: dict[str, Any], key: str, path: Path) -> tuple[float, float, float]:
    """The box corner `key` of a file's `meta`: x, y, z world coordinates.

    Raises:
        BakeError: missing, or not three finite numbers.
    """
    corner = meta.get(key)
    if not (isinstance(corner, list) and len(corner) == 3
            and all(type(c) in (int, float) and np.isfinite(c) for c in corner)):
        raise BakeError(f"{path}: lattice {key} {corner!r}: expected three finite numbers")
    return tuple(float(c) for c in corner)


def _check_channels(file: LatticeFile, config: BakeConfig | None) -> None:
    """Refuse a file whose values per texel do not fit its kind: 3 (RGB irradiance), or
    n² transfer coefficients (×3 coloured) per block of an SH lattice of order n (two
    blocks where the bake left the sun to the pixels: `baking.sh.transfer_blocks`).

    Raises:
        BakeError: naming the file, the kind, the values it holds and those expected.
    """
    kind = lattice_kind(file.meta)
    if kind == "irradiance":
        expected: tuple[int, ...] = (3,)
    else:
        order = file.meta.get("sh_order")
        if type(order) is not int or order < 1:
            raise BakeError(f"{file.path}: SH order {order!r}: expected a whole number ≥ 1")
        blocks = 2 if config is not None and config.direct_light == "pixels" else 1
        expected = (blocks * order**2, 3 * blocks * order**2)
    channels = file.channels
    if channels not in expected:
        raise BakeError(f"{file.path}: a lattice of kind {kind} with {channels} values a "
                        f"texel: expected {' or '.join(map(str, expected))}")


def other_texels(geometry: LatticeGeometry, volume: Volume, scale: float,
                 path: str | os.PathLike[str] = "lattice") -> str:
    """"" when a lattice of `geometry` (the file `path`'s) has the texels that a bake of
    `volume` at `scale` makes (`LatticeGeometry.for_volume`), so a bake can add paths to
    them; else a one-line message saying how they differ."""
    want = LatticeGeometry.for_volume(volume, scale)
    if tuple(geometry.shape) == tuple(want.shape):
        return ""
    return (f"{path}: a lattice of {'×'.join(map(str, geometry.shape))} texels (z×y×x), where "
            f"a bake of {volume.name!r} at --scale {scale:g} places "
            f"{'×'.join(map(str, want.shape))} (cubic texels where the voxels are not): it "
            "can be shown, not baked further; bake to a new file")


def check_identity(meta: dict[str, Any], volume: Volume,
                   path: str | os.PathLike[str] = "lattice") -> None:
    """Raise BakeError unless the lattice of metadata `meta` was baked for `volume`: its
    samples, shape and spacing (`Volume.data_hash`) and its place (the origin)."""
    want = meta.get("volume", {})
    if want.get("hash") != volume.data_hash():
        shape = list(volume.data.shape)
        raise BakeError(
            f"{path}: baked for volume {want.get('name')!r} of shape {want.get('shape')} "
            f"(hash {str(want.get('hash'))[:12]}), not for {volume.name!r} of shape "
            f"{shape} (hash {volume.data_hash()[:12]}); {_identity_hint(want, volume)}"
        )
    origin = want.get("origin")
    if origin is not None and not np.allclose(origin, volume.origin, rtol=0.0,
                                              atol=1e-9 * max(1.0, *np.abs(origin))):
        raise BakeError(f"{path}: baked for {want.get('name')!r} with its first sample at "
                        f"{xyz_text(origin)}, here at {xyz_text(volume.origin)}: the light would "
                        "be looked up a shift away; load it with the --origin (and --up) "
                        "the bake was given")


def _identity_hint(want: dict[str, Any], volume: Volume) -> str:
    """What to do about a volume whose hash differs from the bake's volume `want`
    (`volume_identity`): the loading option that differs where the metadata shows it."""
    spacing = want.get("spacing")
    if want.get("shape") == list(volume.data.shape) and spacing is not None \
            and not np.allclose(spacing, volume.spacing, rtol=1e-12, atol=0.0):
        return (f"its voxels are {xyz_text(spacing)} apart, here {xyz_text(volume.spacing)}: load "
                "it with the --spacing the bake was given")
    if want.get("source") and want.get("source") == volume.source:
        return ("the same file, placed otherwise: load it with the --up (and --dims, "
                "--dtype, --crop, --downsample, --level) the bake was given")
    return "bake it for this volume"


def xyz_text(values: npt.ArrayLike) -> str:
    """x, y, z as the options write them ("?" where none are recorded)."""
    flat = np.asarray(values, np.float64).reshape(-1)
    return ",".join(f"{v:g}" for v in flat) if len(flat) else "?"


def _config_from(d: dict | None, version: int, path: Path) -> BakeConfig | None:
    """The `BakeConfig` of the config dict of version `version` in the file `path` (None
    for None).

    Raises:
        BakeError: a newer version than `CONFIG_VERSION`, or a bad config.
    """
    if d is None:
        return None
    if type(version) is not int:
        raise BakeError(f"{path}: bake config version {version!r}: expected a whole number")
    if version > CONFIG_VERSION:
        raise BakeError(f"{path}: bake config version {version}, this isolume reads up to "
                        f"{CONFIG_VERSION}")
    if not isinstance(d, dict):
        raise BakeError(f"{path}: bake config {d!r:.60}: expected a mapping of settings")
    try:
        return BakeConfig.from_dict(d)
    except (TypeError, ValueError, KeyError) as exc:
        raise BakeError(f"{path}: a bake config this isolume cannot read ({exc}); the file "
                        "is damaged, or written by another version of isolume") from None


def volume_identity(volume: Volume, hashed: bool = True) -> dict[str, Any]:
    """The metadata that ties a lattice to its volume; without `hashed`, its ``hash`` is
    None: for a lattice that is neither saved nor checked against a volume, which need not
    wait for the SHA-256 of the samples (`Volume.data_hash`: 0.05 s of one core for the
    engine CT, 0.5 s at 512³)."""
    return {"name": volume.name, "source": volume.source, "shape": list(volume.data.shape),
            "spacing": list(volume.spacing), "origin": list(volume.origin),
            "hash": volume.data_hash() if hashed else None}
