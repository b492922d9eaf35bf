"""``isolume chart``: speed against accuracy, charted (DESIGN §7; issue 6 item 4).

Writes four PNG charts into ``--out DIR``, each with a JSON file holding every number it
plots plus the settings that made it:

1. ``chart1_bake_time``: error against bake wall time for irradiance lattices, SH lattices
   of orders 3 and 5, and per-pixel path tracing given the same time (paper Table 1,
   Fig. 7), lattices at 16, 64, 256 (and 1024 without ``--quick``) paths per texel.
2. ``chart2_resolution``: error and GL texture memory against lattice resolution 0.5×,
   1×, 2× per axis (paper Fig. 12).
3. ``chart3_lookup_normals``: error per lattice lookup (paper Fig. 6: those that
   `app.render.renderer.SHADING_MODES` offers) and per texel-normal scheme (paper Fig. 5).
4. ``chart4_shading_modes``: error and frame time of every shading mode (paper Table 2),
   local models lit to match the environment as well as they can be.
5. ``chart5_levels`` (``--charts 5``, not made by default): error against bake time per
   isovalue-level policy, the automatic one against fixed move limits
   (`app.charts.levels`).

Error: relative RMSE of linear radiance against a per-pixel path-traced reference (the
baker's own integrator, `baking.reference`), over the pixels that both images mark as
surface and over their RGB values, ``sqrt(mean((img − ref)²)) / mean(ref)``. The
reference's own noise, ``sqrt(mean(stderr²)) / mean(ref)`` over its surface pixels, must
be at most 1/4 of the smallest error charted (then it inflates that error by at most
3 %, since E|img − ref|² = err² + noise²); the reference gains samples until that holds,
or until ``--ref-max-seconds`` of tracing, which the JSON then says. The reference, the
equal-time path tracer and the bakes use different seeds, so their noise is independent.

Everything is rendered with the GL renderer (`app.render.renderer.SurfaceRenderer`) on one
headless context (EGL by default: llvmpipe where there is no GPU), same mesh, camera and
albedo for every image. Bakes cover the whole lattice (all isovalues, the paper's "full
texture"); a lattice of N paths per texel is made by resuming the one of the next lower
count (samples are deterministic per texel and index, so it equals a fresh bake), and its
time is the sum of the wall times of that chain. Lattices and the reference's state are
kept in ``DIR/cache`` (or ``--cache``) and reused by later runs with the same settings.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from isolume.app.options import CLIError, isovalue, load_volume, parse_size

HELP = "charts of error against bake time, lattice resolution, lookups and shading modes"

DEFAULT_VOLUME = "synthetic:engine:64"
DEFAULT_ENV = "sky:sun=3"
SAMPLES = (16, 64, 256, 1024)
SAMPLES_QUICK = (16, 64, 256)
CHART_SAMPLES = 256
CHART_SAMPLES_QUICK = 64
REF_MAX_SECONDS = 1800.0
REF_MAX_SECONDS_QUICK = 300.0
SCALES = (0.5, 1.0, 2.0)
NOISE_RATIO = 0.25
"""The reference's relative noise may be at most this fraction of the smallest error."""
NORMAL_SCHEMES = {
    "gradient": {"normals": "gradient", "offset": 0.0},
    "smoothed": {"normals": "smooth", "offset": 0.0},
    "smoothed + offset": {"normals": "smooth", "offset": 0.25},
}
"""Texel normal schemes of paper Fig. 5 → `BakeConfig` fields (offset in voxels)."""
SH_ORDERS = (3, 5)
AMBIENT_ORDER = 9
"""SH order of the sky's irradiance for the local models' hemisphere ambient (the clamped
cosine's coefficients fall as l^-2.5: order 9 leaves < 0.2 % of a smooth sky's E)."""
CALIBRATION_SPP = 16
"""Samples per pixel traced to measure s/spp (one pass of the tracer's job split)."""
CHARTS = ("1", "2", "3", "4", "5")


# -- options ----------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume chart``."""
    p.add_argument("volume", nargs="?", default=None,
                   help=f"volume file or synthetic:NAME[:SIZE] (default {DEFAULT_VOLUME})")
    p.add_argument("--dims", help="X,Y,Z for raw files whose name does not say")
    p.add_argument("--dtype", help="sample type for raw files, e.g. uint8, int16, float32")
    p.add_argument("--spacing", help="voxel size X,Y,Z (overrides the file)")
    p.add_argument("--crop", metavar="X0:X1,Y0:Y1,Z0:Z1",
                   help="chart a sub-volume (voxel index ranges, end exclusive)")
    p.add_argument("--downsample", type=int, default=1, metavar="F",
                   help="average F×F×F voxel blocks first (default 1: none)")
    p.add_argument("--iso", type=float, help="isovalue (default: first suggested)")
    p.add_argument("--out", required=True, help="folder for the PNG and JSON files")
    p.add_argument("--cache", help="folder for lattices and the reference state, reused by "
                   "later runs with the same settings (default OUT/cache)")
    p.add_argument("--quick", action="store_true",
                   help=f"samples {','.join(map(str, SAMPLES_QUICK))} (no 1024), "
                   f"{CHART_SAMPLES_QUICK} paths per texel for charts 2-4, "
                   f"reference capped at {REF_MAX_SECONDS_QUICK:g} s")
    p.add_argument("--size", default="128x128", help="WxH pixels of every image (default "
                   "128x128)")
    p.add_argument("--view", default="30,30", help="AZ,EL[,DIST]: degrees, diagonals")
    p.add_argument("--env", default=DEFAULT_ENV,
                   help=f"environment: constant:R,G,B | sky[:k=v,...] | FILE.exr/.hdr "
                   f"(default {DEFAULT_ENV})")
    p.add_argument("--bounces", type=int, default=2, help="diffuse bounces (default 2)")
    p.add_argument("--albedo", type=float, default=0.8, help="gray diffuse reflectance")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=None, help="threads (default: all cores)")
    p.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"],
                   help="headless GL backend (default egl)")
    p.add_argument("--samples", help="paths per texel of chart 1, comma-separated "
                   "(overrides --quick's list)")
    p.add_argument("--chart-samples", type=int, default=None,
                   help="paths per texel of the lattices of charts 2-4")
    p.add_argument("--charts", default=",".join(CHARTS[:4]),
                   help=f"which charts of {','.join(CHARTS)}, e.g. 1,4 (default 1-4)")
    p.add_argument("--ref-spp", type=int, default=64, help="first reference spp (default 64)")
    p.add_argument("--ref-max-seconds", type=float, default=None,
                   help="cap on reference tracing time (default "
                   f"{REF_MAX_SECONDS:g}, {REF_MAX_SECONDS_QUICK:g} with --quick)")
    p.add_argument("--draws", type=int, default=10, help="timed frames per mode (≥ 10)")


@dataclass(frozen=True)
class Plan:
    """What this run computes (options resolved against --quick).

    Attributes:
        samples: paths per texel of chart 1's lattices, ascending.
        chart_samples: paths per texel of the lattices of charts 2-4.
        charts: the chart numbers to make.
        ref_spp: first reference samples per pixel.
        ref_max_seconds: cap on the reference's tracing time, s.
        draws: timed frames per shading mode.
    """

    samples: tuple[int, ...]
    chart_samples: int
    charts: tuple[str, ...]
    ref_spp: int
    ref_max_seconds: float
    draws: int


def _plan(args: argparse.Namespace) -> Plan:
    """Resolve and check the counts of ``isolume chart``."""
    samples = SAMPLES_QUICK if args.quick else SAMPLES
    if args.samples:
        try:
            samples = tuple(sorted({int(v) for v in args.samples.split(",")}))
        except ValueError:
            raise CLIError(f"--samples {args.samples!r}: expected integers, e.g. 16,64"
                           ) from None
    chart_samples = args.chart_samples or (CHART_SAMPLES_QUICK if args.quick else CHART_SAMPLES)
    charts = tuple(c.strip() for c in args.charts.split(",") if c.strip())
    if not charts or set(charts) - set(CHARTS):
        raise CLIError(f"--charts {args.charts!r}: expected numbers among {','.join(CHARTS)}")
    if min(samples) < 1 or chart_samples < 1 or args.ref_spp < 2:
        raise CLIError("sample counts must be ≥ 1 (the reference's ≥ 2)")
    if args.draws < 10:
        raise CLIError(f"--draws {args.draws}: at least 10 frames are timed per mode")
    if not 0 < args.albedo <= 1:
        raise CLIError(f"--albedo {args.albedo:g}: expected a reflectance in (0, 1]")
    cap = args.ref_max_seconds
    cap = (REF_MAX_SECONDS_QUICK if args.quick else REF_MAX_SECONDS) if cap is None else cap
    return Plan(samples, chart_samples, charts, args.ref_spp, float(cap), args.draws)


# -- the volume -------------------------------------------------------------------------
def crop_volume(volume, text: str):
    """The sub-volume of ``X0:X1,Y0:Y1,Z0:Z1`` voxel index ranges (end exclusive; an empty
    bound means the edge), same spacing, origin at its first voxel."""
    from isolume import volumes

    parts = text.split(",")
    if len(parts) != 3:
        raise CLIError(f"--crop {text!r}: expected X0:X1,Y0:Y1,Z0:Z1")
    slices = []
    for part, n in zip(parts, volume.shape_xyz, strict=True):
        lo, _, hi = part.partition(":")
        try:
            s = slice(int(lo) if lo else 0, int(hi) if hi else n)
        except ValueError:
            raise CLIError(f"--crop {text!r}: expected integer voxel indices") from None
        start, stop, _ = s.indices(n)
        if stop - start < 2:
            raise CLIError(f"--crop {text!r}: each range must hold at least 2 voxels")
        slices.append(slice(start, stop))
    sx, sy, sz = slices
    origin = np.array(volume.origin) + np.array([sx.start, sy.start, sz.start]) * volume.spacing
    return volumes.Volume(volume.data[sz, sy, sx], spacing=volume.spacing,
                          origin=tuple(origin), name=volume.name,
                          source=f"{volume.source or volume.name}[crop {text}]")


def downsample_volume(volume, factor: int):
    """Block means of `factor`³ voxels (the trailing partial blocks are dropped): (Z, Y, X)
    → (Z // f, Y // f, X // f), spacing × f, origin at the first block's centre."""
    from isolume import volumes

    f = int(factor)
    z, y, x = (n // f for n in volume.data.shape)
    if min(z, y, x) < 2:
        raise CLIError(f"--downsample {f}: leaves fewer than 2 voxels along an axis")
    data = volume.data[: z * f, : y * f, : x * f].reshape(z, f, y, f, x, f).mean(axis=(1, 3, 5))
    origin = np.array(volume.origin) + (f - 1) / 2 * np.array(volume.spacing)
    return volumes.Volume(data, spacing=tuple(f * s for s in volume.spacing),
                          origin=tuple(origin), name=volume.name,
                          source=f"{volume.source or volume.name}[downsample {f}]")


def _prepare_volume(args: argparse.Namespace):
    """(volume, notes): the volume to chart after --crop and --downsample."""
    args.volume = args.volume or DEFAULT_VOLUME
    volume, notes = load_volume(args), []
    if args.crop:
        volume = crop_volume(volume, args.crop)
        notes.append(f"sub-volume: voxels {args.crop} (x, y, z; end exclusive)")
    if args.downsample < 1:
        raise CLIError(f"--downsample {args.downsample}: expected a factor ≥ 1")
    if args.downsample > 1:
        volume = downsample_volume(volume, args.downsample)
        notes.append(f"downsampled by {args.downsample} per axis (block means)")
    return volume, notes


# -- images and the error metric --------------------------------------------------------
@dataclass
class Image:
    """A rendered picture, flat in pixels (row-major from the top-left).

    Attributes:
        linear: (N, 3) float64 linear radiance.
        mask: (N,) bool, True on surface pixels.
    """

    linear: np.ndarray
    mask: np.ndarray


def relative_rmse(image: Image, reference) -> tuple[float | None, int]:
    """(error, pixels): ``sqrt(mean((img − ref)²)) / mean(ref)`` over the RGB values of the
    pixels both mark as surface (`reference`: a `baking.reference.ReferenceImage`); None
    when they share no pixel."""
    both = image.mask & reference.mask
    if not both.any():
        return None, 0
    ref = reference.radiance[both]
    diff = image.linear[both] - ref
    return float(np.sqrt(np.mean(diff * diff)) / np.mean(ref)), int(both.sum())


def error_record(image: Image, reference) -> dict:
    """"error" and "pixels" (`relative_rmse`) plus "error_less_reference_noise":
    ``sqrt(max(error² − noise², 0))`` with the reference's noise over the same pixels,
    an estimate of the error against the exact image (E(img − ref)² = (img − exact)² +
    stderr² pixel by pixel). Informative only: the charts plot "error"."""
    error, pixels = relative_rmse(image, reference)
    if error is None:
        return {"error": None, "pixels": 0, "error_less_reference_noise": None}
    both = image.mask & reference.mask
    noise = np.sqrt(np.mean(reference.stderr[both] ** 2)) / np.mean(reference.radiance[both])
    return {"error": error, "pixels": pixels,
            "error_less_reference_noise": float(np.sqrt(max(error**2 - noise**2, 0.0)))}


def reference_noise(reference) -> float:
    """``sqrt(mean(stderr²)) / mean(ref)`` over the RGB values of the reference's surface
    pixels: the relative error its own Monte Carlo noise contributes (inf with < 2 spp)."""
    m = reference.mask
    if not m.any():
        return 0.0
    return float(np.sqrt(np.mean(reference.stderr[m] ** 2)) / np.mean(reference.radiance[m]))


# -- lighting for the local models ------------------------------------------------------
@dataclass(frozen=True)
class LocalLighting:
    """Key light and hemisphere ambient that match an environment (linear RGB irradiance
    at normal incidence).

    Attributes:
        key_dir: (3,) unit vector towards the sun (+z when there is none).
        key: the sun's irradiance (0 without a sun).
        sky, ground: irradiance of the environment without its sun on normals +z and −z.
        mean_radiance: the whole environment's mean radiance (the constant sky of
            "vicinity"/"ao" lattices).
    """

    key_dir: tuple[float, float, float]
    key: tuple[float, float, float]
    sky: tuple[float, float, float]
    ground: tuple[float, float, float]
    mean_radiance: tuple[float, float, float]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def local_lighting(env_spec: str) -> LocalLighting:
    """The fairest key light and hemisphere ambient for `env_spec`: a sky's sun becomes the
    key light (its direction and irradiance); the rest of the environment, projected on SH
    and turned into irradiance (Funk–Hecke), gives the ambient for normals ±z."""
    from isolume.baking import sh
    from isolume.baking.environment import SkyEnvironment, parse_env

    env = parse_env(env_spec)
    mean = sh.project_environment(env, 1)[0] / math.sqrt(4 * math.pi)
    key_dir, key, ambient = np.array([0.0, 0.0, 1.0]), np.zeros(3), env
    if isinstance(env, SkyEnvironment) and max(env.sun) > 0:
        key_dir, key = np.asarray(env.sun_direction), np.asarray(env.sun)
        ambient = dataclasses.replace(env, sun=(0.0, 0.0, 0.0))
    coeffs = sh.irradiance_coefficients(sh.project_environment(ambient, AMBIENT_ORDER))
    up_down = sh.basis(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), AMBIENT_ORDER) @ coeffs

    def triple(v, floor: float | None = 0.0) -> tuple[float, float, float]:
        return tuple(float(c) for c in (v if floor is None else np.maximum(v, floor)))

    return LocalLighting(triple(key_dir, None), triple(key), triple(up_down[0]),
                         triple(up_down[1]), triple(mean))


# -- lattices ---------------------------------------------------------------------------
@dataclass
class Baked:
    """A lattice and the wall time that made it.

    Attributes:
        lattice: the `baking.Lattice`.
        seconds: wall seconds of the bakes that made it (resumed chains summed).
        cached: True when it was read from the cache instead of baked in this run.
    """

    lattice: object
    seconds: float
    cached: bool

    def summary(self) -> dict:
        """JSON-ready figures of the bake."""
        meta = self.lattice.meta
        return {"bake_seconds": self.seconds, "cached": self.cached,
                "resumed_from": int(meta.get("chart_resumed_from", 0)),
                "rays": int(meta.get("rays_traced", 0)),
                "active_texels": int(meta["plan"]["active_texels"]),
                "texels": int(np.prod(self.lattice.geometry.shape)),
                "shape_zyx": list(self.lattice.geometry.shape)}


class LatticeStore:
    """Bakes lattices on demand and keeps them (in memory and in ``folder``).

    A lattice of N paths per texel resumes the one with the most samples below N and the
    same other settings; its `Baked.seconds` adds the wall times of the chain.
    """

    def __init__(self, volume, folder: Path, workers: int | None) -> None:
        self.volume, self.folder, self.workers = volume, folder, workers
        self._memory: dict = {}
        folder.mkdir(parents=True, exist_ok=True)

    def _stem(self, config) -> str:
        core = dataclasses.replace(config, samples=1).to_dict()
        digest = hashlib.sha1(json.dumps(core, sort_keys=True).encode()).hexdigest()[:10]
        order = config.sh_order if config.mode == "sh" else ""
        return f"{config.mode}{order}_x{config.scale:g}_{config.normals}{config.offset:g}_{digest}"

    def _path(self, config) -> Path:
        return self.folder / f"{self._stem(config)}_s{config.samples}.npz"

    def _load(self, config) -> Baked | None:
        """The cached lattice of exactly `config`, or None."""
        from isolume.baking.config import BakeConfig
        from isolume.baking.errors import BakeError
        from isolume.baking.lattice import Lattice

        if config in self._memory:
            return self._memory[config]
        path = self._path(config)
        if not path.exists():
            return None
        try:
            lattice = Lattice.load(path, self.volume)
        except BakeError:
            return None
        if BakeConfig.from_dict(lattice.meta["config"]) != config:
            return None
        baked = Baked(lattice, float(lattice.meta["chart_seconds"]), True)
        self._memory[config] = baked
        return baked

    def _start(self, config) -> Baked | None:
        """The cached lattice with the most samples below `config.samples`, or None (also
        when the levels follow the samples: resuming would keep the smaller bake's)."""
        from isolume.baking.plan import levels_follow_samples

        if levels_follow_samples(config):
            return None
        stem, best = self._stem(config), None
        for path in self.folder.glob(f"{stem}_s*.npz"):
            n = path.stem.rsplit("_s", 1)[-1]
            if n.isdigit() and int(n) < config.samples and (best is None or int(n) > best):
                if self._load(dataclasses.replace(config, samples=int(n))) is not None:
                    best = int(n)
        return None if best is None else self._load(dataclasses.replace(config, samples=best))

    def get(self, config) -> Baked:
        """The lattice of `config`: from memory, the cache, or baked now."""
        baked = self._load(config)
        if baked is None:
            baked = self._bake(config, self._start(config))
            self._memory[config] = baked
        return baked

    def _bake(self, config, start: Baked | None) -> Baked:
        from isolume.baking.bake import Baker

        lattice = None
        if start is not None:
            lattice = copy.deepcopy(start.lattice)
            lattice.meta["config"] = config.to_dict()
        began = time.perf_counter()
        baker = Baker(self.volume, config, lattice=lattice, workers=self.workers)
        try:
            baker.run()
        finally:
            baker.close()
        seconds = (start.seconds if start else 0.0) + time.perf_counter() - began
        lattice = baker.lattice
        lattice.meta["chart_seconds"] = seconds
        lattice.meta["chart_resumed_from"] = start.lattice.meta["config"]["samples"] \
            if start else 0
        lattice.save(self._path(config))
        order = f" order {config.sh_order}" if config.mode == "sh" else ""
        _say(f"baked {config.mode}{order} x{config.scale:g} {config.normals} offset "
             f"{config.offset:g} {config.env} {config.bounces} bounces, {config.samples} "
             f"paths/texel: {seconds:.1f} s")
        return Baked(lattice, seconds, False)


def texture_bytes(lattice, lookup: str = "trilinear") -> int:
    """Bytes of the GL textures that hold `lattice` (`app.render.lattice_gl`): irradiance is
    RGB9_E5 (4 B/texel) plus the R8 valid mask (1 B), plus R32F texel isovalues (4 B)
    for the closest-isovalue lookup; SH is ⌈n²/4⌉ RGBA16F textures (8 B/texel) per
    colour group plus the valid mask."""
    from isolume.app.render.lattice_gl import sh_layout
    from isolume.baking.sh import transfer_blocks

    texels = int(np.prod(lattice.geometry.shape))
    if lattice.kind == "irradiance":
        return texels * (4 + 1 + (4 if lookup == "closest" else 0))
    order = int(lattice.meta["sh_order"])
    blocks = transfer_blocks(lattice.meta)
    per_group, groups = sh_layout(order, lattice.values.shape[-1] != blocks * order * order,
                                  blocks)
    return texels * (8 * per_group * groups + 1)


def lattice_coverage(lattice, mesh) -> dict:
    """How much of the displayed surface `lattice` covers, from the trilinear weight w of
    its computed texels at the (V, 3) mesh vertices (what the shader divides by):
    "surface_uncovered" is the fraction with w < 0.25, where the shader shows mostly its
    local fallback (``lattice_blend`` in ``lattice.glsl``), "surface_partly_covered" the
    fraction with some uncomputed neighbour (w < 1)."""
    from isolume.baking.lattice import trilinear

    if mesh.empty:
        return {"surface_uncovered": None, "surface_partly_covered": None}
    valid = lattice.computed[..., None].astype(np.float32)
    w = trilinear(valid, lattice.geometry.to_texel_coords(mesh.vertices))[:, 0]
    return {"surface_uncovered": float(np.mean(w < 0.25)),
            "surface_partly_covered": float(np.mean(w < 0.999))}


# -- GL ---------------------------------------------------------------------------------
class GLScene:
    """One headless context, renderer, mesh and camera for every image of a run."""

    def __init__(self, volume, iso: float, camera, size: tuple[int, int], backend: str,
                 lighting: LocalLighting, albedo: float, env_spec: str) -> None:
        from isolume import volumes
        from isolume.app.render.glcontext import create_headless
        from isolume.app.render.renderer import SurfaceRenderer

        self.volume, self.camera, self.size = volume, camera, size
        self.lighting, self.albedo, self.env_spec = lighting, albedo, env_spec
        self.mesh = volumes.isosurface(volume, iso)
        self.gl = create_headless(backend)
        self.ctx = self.gl.ctx
        self.renderer = SurfaceRenderer(self.ctx)
        self.renderer.set_mesh(self.mesh.vertices, self.mesh.normals, self.mesh.faces,
                               iso=self.mesh.iso)
        self.renderer.set_bounds(*volume.box)
        self._lattice = None
        self._texel_iso: dict = {}
        self._env: dict = {}

    @property
    def gl_renderer(self) -> str:
        info = self.ctx.info
        return f"{info.get('GL_RENDERER')} ({info.get('GL_VERSION')}, {self.gl.backend})"

    def settings(self, shading: str):
        """`RenderSettings` of `shading`: the run's size and albedo, the local lighting."""
        from isolume.app.render.renderer import RenderSettings

        light = self.lighting
        return RenderSettings(size=self.size, shading=shading, albedo=(self.albedo,) * 3,
                              key_dir=light.key_dir, key_irradiance=light.key,
                              head_irradiance=(0.0, 0.0, 0.0), sky_irradiance=light.sky,
                              ground_irradiance=light.ground)

    def use(self, shading: str, lattice=None) -> None:
        """Upload what `shading` reads: the lattice (with texel isovalues for the
        closest-isovalue lookup) and, for SH, the environment's coefficients."""
        from isolume.app.render.renderer import SHADING_MODES

        mode = SHADING_MODES[shading]
        closest = mode.lookup == "closest" and lattice is not None
        key = (id(lattice), closest)
        if self._lattice != key:
            self.renderer.set_lattice(lattice, self._texel_isovalues(lattice) if closest
                                      else None)
            self._lattice = key
        if shading == "sh":
            from isolume.baking.sh import transfer_blocks

            self.renderer.set_environment(self._env_coeffs(int(lattice.meta["sh_order"]),
                                                           transfer_blocks(lattice.meta)))

    def _texel_isovalues(self, lattice) -> np.ndarray:
        from isolume.baking.plan import texel_values

        shape = lattice.geometry.shape
        if shape not in self._texel_iso:
            self._texel_iso[shape] = texel_values(self.volume, lattice.geometry)
        return self._texel_iso[shape]

    def _env_coeffs(self, order: int, blocks: int = 1) -> np.ndarray:
        """`baking.sh.display_coefficients` of the chart's environment (cached)."""
        from isolume.baking import sh
        from isolume.baking.environment import parse_env

        if (order, blocks) not in self._env:
            self._env[order, blocks] = sh.display_coefficients(parse_env(self.env_spec),
                                                               order, blocks)
        return self._env[order, blocks]

    def render(self, shading: str, lattice=None) -> Image:
        """Draw `shading` (with `lattice` where it reads one) and read it back."""
        self.use(shading, lattice)
        frame = self.renderer.render(self.camera, self.settings(shading))
        return Image(frame.linear.reshape(-1, 3).astype(np.float64), frame.mask.reshape(-1))

    def frame_seconds(self, shading: str, lattice, draws: int, warmup: int = 3) -> np.ndarray:
        """(draws,) wall seconds of single frames (linear pass + tone-mapping pass, ended by
        ``ctx.finish()``, no read-back) after `warmup` untimed ones."""
        self.use(shading, lattice)
        settings = self.settings(shading)
        times = []
        for i in range(warmup + draws):
            began = time.perf_counter()
            targets = self.renderer.draw_hdr(self.camera, settings)
            self.renderer.resolve(targets, settings)
            self.ctx.finish()
            if i >= warmup:
                times.append(time.perf_counter() - began)
        return np.array(times)

    def release(self) -> None:
        self.renderer.release()
        self.gl.release()


# -- per-pixel path tracing -------------------------------------------------------------
class Reference:
    """The reference image: per-pixel path tracing that gains samples on request, with
    its state kept in ``path`` (resumed when the settings match)."""

    def __init__(self, run: Run, path: Path) -> None:
        from isolume.baking.reference import PixelStats, ReferenceTracer, load_state

        config = dataclasses.replace(run.config, seed=run.config.seed + 1)
        self.path, self.seconds = path, 0.0
        self.tracer = ReferenceTracer(run.volume, run.iso, run.origins, run.dirs, config,
                                      workers=run.workers)
        self.stats = PixelStats.empty(self.tracer.pixels)
        if path.exists():
            stats, meta = load_state(path)
            if meta.get("identity") == self.tracer.identity:
                self.stats, self.seconds = stats, float(meta.get("seconds", 0.0))

    @property
    def spp(self) -> int:
        """Samples of every surface pixel."""
        counts = self.stats.count[self.tracer.hits.pixels]
        return int(counts.min()) if len(counts) else 0

    @property
    def seconds_per_spp(self) -> float:
        return self.seconds / max(self.spp, 1)

    def extend(self, spp: int) -> None:
        """Bring every surface pixel to `spp` samples (and save the state)."""
        from isolume.baking.reference import save_state

        if spp <= self.spp:
            return
        began = time.perf_counter()
        self.tracer.run(self.stats, spp)
        self.seconds += time.perf_counter() - began
        save_state(self.path, self.stats, {"identity": self.tracer.identity,
                                           "seconds": self.seconds})

    def image(self):
        return self.tracer.image(self.stats)

    def close(self) -> None:
        self.tracer.close()


def equal_time_path_tracing(run: Run, targets: list[tuple[str, float]]) -> list[dict]:
    """Per-pixel path tracing given the time of each bake.

    The seconds per sample per pixel are measured first (`CALIBRATION_SPP` samples on a
    separate state); then one image gains samples in order of the target times and is
    kept at each ``spp = max(1, round((T − setup) / (s/spp)))``, s/spp being updated to
    the mean measured so far after each step. Every point records the time it really took
    (tracer setup plus tracing up to its spp), which is what the chart plots.

    Args:
        targets: (label, seconds) of the bakes to match.

    Returns:
        One dict per target: matches (label), target_seconds, spp, seconds, image (key
        into ``run.images``).
    """
    from isolume.baking.reference import PixelStats, ReferenceTracer

    config = dataclasses.replace(run.config, seed=run.config.seed + 2)
    with ReferenceTracer(run.volume, run.iso, run.origins, run.dirs, config,
                         workers=run.workers) as tracer:
        setup = tracer.counters.setup_seconds
        began = time.perf_counter()
        tracer.run(PixelStats.empty(tracer.pixels), CALIBRATION_SPP)
        per_spp = calibrated = (time.perf_counter() - began) / CALIBRATION_SPP
        stats, traced, points = PixelStats.empty(tracer.pixels), 0.0, []
        for label, seconds in sorted(targets, key=lambda t: t[1]):
            spp = max(1, round((seconds - setup) / per_spp))
            began = time.perf_counter()
            tracer.run(stats, spp)
            traced += time.perf_counter() - began
            done = int(stats.count[tracer.hits.pixels].min()) if len(tracer.hits.pixels) else 0
            per_spp = traced / max(done, 1)
            key = f"path_traced/{done}"
            picture = tracer.image(stats)
            run.images[key] = Image(picture.radiance, picture.mask)
            points.append({"matches": label, "target_seconds": seconds, "spp": done,
                           "seconds": setup + traced, "image": key})
    _say(f"path traced at equal time: {calibrated:.3g} s/spp calibrated, {per_spp:.3g} "
         f"measured, setup {setup:.2f} s, up to {points[-1]['spp'] if points else 0} spp")
    run.facts["path_traced_seconds_per_spp"] = per_spp
    run.facts["path_traced_seconds_per_spp_calibration"] = calibrated
    run.facts["path_traced_setup_seconds"] = setup
    return points


# -- a run ------------------------------------------------------------------------------
@dataclass
class Run:
    """Everything shared by the charts of one ``isolume chart`` call.

    Attributes:
        volume, iso: the scalar field and the displayed isovalue.
        origins, dirs: (N, 3) primary rays of the camera, one per pixel.
        config: base `BakeConfig` (irradiance, env, bounces, albedo, seed).
        images: key → `Image`, every picture that is charted.
        facts: measured figures recorded in every JSON (GL renderer, s/spp, ...).
    """

    volume: object
    iso: float
    origins: np.ndarray
    dirs: np.ndarray
    config: object
    plan: Plan
    store: LatticeStore
    gl: GLScene
    workers: int | None
    images: dict = field(default_factory=dict)
    facts: dict = field(default_factory=dict)

    def lattice(self, **changes) -> Baked:
        """The lattice of the base config with `changes` (e.g. samples, mode, scale); where
        the direct light goes is chosen anew for it (`BakeConfig.direct_light`: per pixel
        for irradiance with a sun or lights) unless `changes` say."""
        changes.setdefault("direct_light", None)
        return self.store.get(dataclasses.replace(self.config, **changes))

    def summary(self, baked: Baked) -> dict:
        """`Baked.summary` plus how much of the displayed surface the lattice covers."""
        coverage = lattice_coverage(baked.lattice, self.gl.mesh)
        if (coverage["surface_uncovered"] or 0) > 0.01:
            config = baked.lattice.meta["config"]
            _say(f"warning: the {config['mode']} lattice x{config['scale']:g} leaves "
                 f"{coverage['surface_uncovered']:.1%} of the surface's vertices without "
                 "computed texels (the renderer shows its local fallback there)")
        return {**baked.summary(), **coverage}

    def render(self, key: str, shading: str, lattice=None) -> str:
        """Render `shading` into ``images[key]``; returns `key`."""
        self.images[key] = self.gl.render(shading, lattice)
        return key


@dataclass
class Chart:
    """One chart's numbers before the errors are filled in.

    Attributes:
        name: file stem (``chart1_bake_time``).
        title: what it shows.
        data: JSON-ready dict; every dict in it with an "image" key gets "error" and
            "pixels" from that image once the reference is final.
    """

    name: str
    title: str
    data: dict


def _lattice_kinds() -> list[tuple[str, dict]]:
    """(label, BakeConfig changes) of chart 1's lattices."""
    return [("irradiance", {"mode": "irradiance"})] + [
        (f"sh{n}", {"mode": "sh", "sh_order": n}) for n in SH_ORDERS]


def chart_bake_time(run: Run) -> Chart:
    """Chart 1: error against bake time (lattices) and equal-time path tracing."""
    series: dict[str, list[dict]] = {}
    for label, changes in _lattice_kinds():
        points = []
        for n in run.plan.samples:
            baked = run.lattice(samples=n, **changes)
            shading = "sh" if changes["mode"] == "sh" else "irradiance"
            key = run.render(f"bake_time/{label}/{n}", shading, baked.lattice)
            points.append({"samples": n, "seconds": baked.seconds, "image": key,
                           **run.summary(baked)})
        series[label] = points
    targets = [(f"{label}@{p['samples']}", p["seconds"])
               for label, points in series.items() for p in points]
    series["path_traced"] = equal_time_path_tracing(run, targets)
    return Chart("chart1_bake_time", "error against bake time (paper Table 1, Fig. 7)",
                 {"series": series, "x": "seconds (wall)", "y": "relative RMSE"})


def chart_resolution(run: Run) -> Chart:
    """Chart 2: error and texture memory against lattice resolution."""
    points = []
    for scale in SCALES:
        baked = run.lattice(samples=run.plan.chart_samples, scale=scale)
        key = run.render(f"resolution/{scale:g}", "irradiance", baked.lattice)
        points.append({"scale": scale, "memory_bytes": texture_bytes(baked.lattice),
                       "image": key, **run.summary(baked)})
    return Chart("chart2_resolution", "error and memory against lattice resolution "
                 "(paper Fig. 12)", {"points": points, "samples": run.plan.chart_samples})


def chart_lookup_normals(run: Run) -> Chart:
    """Chart 3: error per lattice lookup (Fig. 6) and per texel-normal scheme (Fig. 5)."""
    from isolume.app.render.renderer import SHADING_MODES

    base = run.lattice(samples=run.plan.chart_samples)
    lookups = []
    for name, mode in SHADING_MODES.items():
        if mode.lattice == "irradiance":
            key = run.render(f"lookup/{name}", name, base.lattice)
            lookups.append({"mode": name, "lookup": mode.lookup, "image": key,
                            "memory_bytes": texture_bytes(base.lattice, mode.lookup)})
    normals = []
    for label, changes in NORMAL_SCHEMES.items():
        baked = run.lattice(samples=run.plan.chart_samples, **changes)
        key = run.render(f"normals/{label}", "irradiance", baked.lattice)
        normals.append({"scheme": label, **changes, "image": key, **run.summary(baked)})
    return Chart("chart3_lookup_normals", "error per lattice lookup (paper Fig. 6) and per "
                 "normal scheme (paper Fig. 5)",
                 {"lookups": lookups, "normals": normals, "samples": run.plan.chart_samples,
                  "bake": run.summary(base)})


def _mode_lattice(run: Run, mode) -> Baked | None:
    """The lattice a shading mode reads at the chart's samples (None for local ones)."""
    n = run.plan.chart_samples
    if mode.lattice is None:
        return None
    if mode.lattice == "sh":
        return run.lattice(samples=n, mode="sh", sh_order=max(SH_ORDERS))
    if mode.lattice == "occlusion":
        rgb = ",".join(f"{v:.9g}" for v in run.gl.lighting.mean_radiance)
        return run.lattice(samples=n, env=f"constant:{rgb}", bounces=0, lights=())
    return run.lattice(samples=n)


DIRECT_IN_LATTICE = "irradiance, direct in lattice"
"""Chart 4's row for an irradiance lattice that holds the lights' and the sun's direct light
too (``--direct-light lattice``), beside "irradiance" with it shaded per pixel."""


def _chart4_rows(run: Run):
    """(row name, shading mode name, mode, baked lattice or None) of chart 4: every shading
    mode, and the irradiance lattice with the direct light in it as well, when the
    lighting has a sun or lights to shade per pixel."""
    from isolume.app.render.renderer import SHADING_MODES

    for name, mode in SHADING_MODES.items():
        baked = _mode_lattice(run, mode)
        yield name, name, mode, baked
        pixels = baked is not None and baked.lattice.meta["config"].get("direct_light")
        if name == "irradiance" and pixels == "pixels":
            yield DIRECT_IN_LATTICE, name, mode, run.lattice(
                samples=run.plan.chart_samples, direct_light="lattice")


def chart_shading_modes(run: Run) -> Chart:
    """Chart 4: error and frame time of every shading mode."""
    modes = []
    for row, name, mode, baked in _chart4_rows(run):
        lattice = None if baked is None else baked.lattice
        key = run.render(f"mode/{row}", name, lattice)
        seconds = run.gl.frame_seconds(name, lattice, run.plan.draws)
        modes.append({
            "mode": row, "kind": mode.lattice or "local", "lookup": mode.lookup,
            "shadow": mode.shadow, "fog": mode.fog, "image": key,
            "frame_ms_mean": 1e3 * float(seconds.mean()),
            "frame_ms_min": 1e3 * float(seconds.min()),
            "frame_ms_std": 1e3 * float(seconds.std()), "draws": len(seconds),
            "memory_bytes": 0 if lattice is None else texture_bytes(lattice, mode.lookup),
            "lattice": None if baked is None else {
                "config": lattice.meta["config"], **run.summary(baked)},
        })
    return Chart("chart4_shading_modes", "error and frame time of every shading mode "
                 "(paper Table 2)", {
                     "modes": modes, "samples": run.plan.chart_samples,
                     "local_lighting": run.gl.lighting.to_dict(),
                     "frame_time": "wall time of the linear pass and the tone-mapping pass "
                                   "ended by ctx.finish() (no read-back), after 3 untimed "
                                   "frames; shadow maps are drawn once per mesh and light "
                                   "and reused (a static light), as the renderer does",
                     "memory": "bytes of the GL textures the mode reads (app.render.lattice_gl)"})


def chart_levels(run: Run) -> Chart:
    """Chart 5: error against bake time per level policy (`app.charts.levels`)."""
    from isolume.app.charts.levels import chart_levels as levels

    return levels(run)


CHART_BUILDERS = {"1": chart_bake_time, "2": chart_resolution, "3": chart_lookup_normals,
                  "4": chart_shading_modes, "5": chart_levels}


# -- errors and the reference rule ------------------------------------------------------
def _image_entries(node) -> list[dict]:
    """Every dict under `node` (nested dicts and lists) that names an image."""
    if isinstance(node, dict):
        found = [node] if "image" in node else []
        return found + [e for v in node.values() for e in _image_entries(v)]
    if isinstance(node, list):
        return [e for v in node for e in _image_entries(v)]
    return []


def fill_errors(charts: list[Chart], images: dict, reference) -> list[float]:
    """Set "error" and "pixels" of every image entry; returns the errors (not None)."""
    errors = []
    for chart in charts:
        for entry in _image_entries(chart.data):
            entry.update(error_record(images[entry["image"]], reference))
            if entry["error"] is not None:
                errors.append(entry["error"])
    return errors


def settle_reference(ref: Reference, charts: list[Chart], images: dict, plan: Plan) -> dict:
    """Add reference samples until its noise is ≤ `NOISE_RATIO` × the smallest error (or
    the time cap); fill in the errors against the final reference.

    Returns:
        The rule's record: spp, seconds, noise, smallest error, ratio, holds, capped, and
        the spp the rule needs (estimated from noise ∝ 1/√spp where capped).
    """
    ref.extend(plan.ref_spp)
    while True:
        picture = ref.image()
        noise = reference_noise(picture)
        errors = fill_errors(charts, images, picture)
        smallest = min(errors) if errors else 0.0
        holds = noise <= NOISE_RATIO * smallest
        needed = ref.spp if holds else (
            math.inf if smallest <= 0 else
            math.ceil(ref.spp * (noise / (NOISE_RATIO * smallest)) ** 2 * 1.1))
        affordable = ref.spp + int(max(plan.ref_max_seconds - ref.seconds, 0.0)
                                   / max(ref.seconds_per_spp, 1e-9))
        _say(f"reference: {ref.spp} spp ({ref.seconds:.1f} s), noise {noise:.3%}, "
             f"smallest error {smallest:.3%}: {'holds' if holds else 'more samples'}")
        if holds or affordable < 1.1 * ref.spp:  # the cap leaves < 10 % more: stop
            break
        ref.extend(int(min(needed, affordable, 64 * ref.spp)))
    return {"rule": f"reference noise <= {NOISE_RATIO:g} x smallest error charted",
            "spp": ref.spp, "seconds": ref.seconds, "seconds_per_spp": ref.seconds_per_spp,
            "noise": noise, "smallest_error": smallest,
            "noise_over_smallest_error": noise / smallest if smallest > 0 else None,
            "holds": bool(holds), "capped": not holds, "cap_seconds": plan.ref_max_seconds,
            "spp_needed": None if math.isinf(needed) else int(needed),
            "seed": ref.tracer.config.seed, "normals": "smooth",
            "offset_voxels": ref.tracer.config.offset,
            "surface_pixels": int(picture.mask.sum())}


# -- output -----------------------------------------------------------------------------
def _jsonable(node):
    """`node` with numpy scalars and tuples made JSON-ready and non-finite floats None."""
    if isinstance(node, dict):
        return {str(k): _jsonable(v) for k, v in node.items()}
    if isinstance(node, list | tuple):
        return [_jsonable(v) for v in node]
    if isinstance(node, np.generic):
        node = node.item()
    if isinstance(node, float) and not math.isfinite(node):
        return None
    return node


def write_chart(chart: Chart, out: Path, settings: dict, reference: dict) -> Path:
    """Write ``NAME.json`` (numbers, settings, reference rule) and ``NAME.png``."""
    chart_errors = [e["error"] for e in _image_entries(chart.data) if e.get("error") is not None]
    record = {"chart": chart.name, "title": chart.title, "png": f"{chart.name}.png",
              "settings": settings,
              "reference": {**reference, "smallest_error_in_this_chart":
                            min(chart_errors) if chart_errors else None},
              **chart.data}
    record = _jsonable(record)
    (out / f"{chart.name}.json").write_text(json.dumps(record, indent=2) + "\n")
    png = out / f"{chart.name}.png"
    PLOTTERS[chart.name](record, png)
    return png


def _figure(ncols: int = 1):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(6.4 * ncols, 4.8), squeeze=False)
    return plt, fig, list(axes[0])


def _subtitle(record: dict) -> str:
    s, r = record["settings"], record["reference"]
    return (f"{Path(s['volume']).name} iso {s['iso']:.4g}, {s['env']}, {s['bounces']} bounces, "
            f"albedo {s['albedo']:g}\n{s['size'][0]}x{s['size'][1]} px; reference {r['spp']} "
            f"spp, noise {r['noise']:.2%} ({'meets' if r['holds'] else 'misses'} the 1/4 rule)")


def _finish(plt, fig, record: dict, path: Path) -> None:
    fig.suptitle(f"{record['title']}\n{_subtitle(record)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _noise_line(ax, record: dict) -> None:
    ax.axhline(record["reference"]["noise"], color="0.6", ls=":", lw=1,
               label="reference noise")


def _plain_log_ticks(ax, axes: str = "xy") -> None:
    """Log axes ticked at 1, 2, 5 × 10ⁿ and labelled 0.1, 0.2, 0.5 (not 10⁻¹ ...)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for name in axes:
        axis = ax.xaxis if name == "x" else ax.yaxis
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=30))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def plot_bake_time(record: dict, path: Path) -> None:
    """Log–log error against seconds, one line per method, points labelled by samples."""
    plt, fig, (ax,) = _figure()
    styles = {"irradiance": ("o-", "irradiance lattice"), "sh3": ("s-", "SH lattice, order 3"),
              "sh5": ("D-", "SH lattice, order 5"),
              "path_traced": ("^--", "per-pixel path tracing, equal time")}
    for name, points in record["series"].items():
        pts = [p for p in points if p.get("error")]
        style, label = styles.get(name, ("o-", name))
        ax.loglog([p["seconds"] for p in pts], [p["error"] for p in pts], style, label=label,
                  ms=5)
        if name == "path_traced":
            pts = pts[:1] + pts[-1:] if len(pts) > 1 else pts  # close together: ends only
        for p in pts:
            text = f"{p['samples']}" if "samples" in p else f"{p['spp']} spp"
            ax.annotate(text, (p["seconds"], p["error"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    _noise_line(ax, record)
    _plain_log_ticks(ax)
    ax.set_xlabel("wall time, s (bake, or path tracing); labels: paths per texel, spp")
    ax.set_ylabel("relative RMSE of radiance")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _finish(plt, fig, record, path)


def plot_resolution(record: dict, path: Path) -> None:
    """Error and texture memory against lattice scale."""
    plt, fig, (ax, mem) = _figure(2)
    pts = record["points"]
    scales = [p["scale"] for p in pts]
    ax.plot(scales, [p["error"] for p in pts], "o-", label="irradiance lattice")
    _noise_line(ax, record)
    ax.set_ylabel("relative RMSE of radiance")
    ax.set_ylim(bottom=0)
    mem.plot(scales, [p["memory_bytes"] / 2**20 for p in pts], "s-", color="C1")
    mem.set_yscale("log")
    mem.set_ylabel("GL texture memory, MiB (RGB9_E5 + valid mask)")
    for i, p in enumerate(pts):
        last = i == len(pts) - 1  # label the rightmost point on its left: stays inside
        where = {"xytext": (-4 if last else 4, 4), "textcoords": "offset points",
                 "ha": "right" if last else "left", "fontsize": 8}
        uncovered = p.get("surface_uncovered") or 0.0
        note = f"\n({uncovered:.0%} of the surface uncovered)" if uncovered > 0.01 else ""
        ax.annotate(_percent(p["error"]) + note, (p["scale"], p["error"]), **where)
        mem.annotate(f"{p['memory_bytes'] / 2**20:.3g} MiB, bake {p['bake_seconds']:.3g} s",
                     (p["scale"], p["memory_bytes"] / 2**20), **where)
    for a in (ax, mem):
        a.set_xscale("log", base=2)
        a.set_xticks(scales, [f"{s:g}x" for s in scales])
        a.set_xlabel(f"lattice texels per voxel per axis ({record['samples']} paths/texel)")
        a.grid(True, which="both", alpha=0.3)
        a.margins(x=0.2)
    ax.legend(fontsize=8)
    _finish(plt, fig, record, path)


def _percent(value: float) -> str:
    """A relative error as a percentage with two significant digits at least."""
    return f"{value:.2%}" if value >= 1e-3 or value == 0 else f"{100 * value:.2g}%"


def _bars(ax, labels: list[str], errors: list[float], colour: str) -> None:
    values = [e if e is not None else 0.0 for e in errors]
    ax.bar(range(len(values)), values, color=colour)
    ax.set_xticks(range(len(values)), labels, fontsize=8)
    for i, v in enumerate(values):
        ax.annotate(_percent(v), (i, v), ha="center", fontsize=8, xytext=(0, 2),
                    textcoords="offset points")
    ax.set_ylabel("relative RMSE of radiance")
    ax.grid(True, axis="y", alpha=0.3)


def plot_lookup_normals(record: dict, path: Path) -> None:
    """Bars: error per lookup scheme, error per normal scheme."""
    plt, fig, (ax, nx) = _figure(2)
    _bars(ax, [e["lookup"] for e in record["lookups"]],
          [e["error"] for e in record["lookups"]], "C0")
    ax.set_title(f"lattice lookup ({record['samples']} paths/texel)", fontsize=9)
    _bars(nx, [e["scheme"] for e in record["normals"]],
          [e["error"] for e in record["normals"]], "C2")
    nx.set_title("texel normals (trilinear lookup)", fontsize=9)
    for a in (ax, nx):
        _noise_line(a, record)
        a.legend(fontsize=8)
    _finish(plt, fig, record, path)


KIND_COLOURS = {"local": "C3", "irradiance": "C0", "sh": "C2", "occlusion": "C1"}
KIND_LABELS = {"local": "local model", "irradiance": "irradiance lattice",
               "sh": "SH lattice", "occlusion": "occlusion lattice (constant sky, no bounce)"}


def plot_shading_modes(record: dict, path: Path) -> None:
    """One row per shading mode, best first: error (log) and frame time side by side, so
    local models and lattices share both axes."""
    plt, fig, (ax, ft) = _figure(2)
    modes = sorted((m for m in record["modes"] if m.get("error") is not None),
                   key=lambda m: m["error"])
    rows = np.arange(len(modes))[::-1]
    colours = [KIND_COLOURS.get(m["kind"], "k") for m in modes]
    floor = 1e-6  # exact images (error 0) still get a visible bar on the log axis
    ax.barh(rows, [max(m["error"], floor) for m in modes], color=colours)
    ax.set_xscale("log")
    _plain_log_ticks(ax, "x")
    ax.set_yticks(rows, [m["mode"] for m in modes], fontsize=8)
    for r, m in zip(rows, modes, strict=True):
        ax.annotate(_percent(m["error"]), (max(m["error"], floor), r), fontsize=7,
                    va="center", xytext=(2, 0), textcoords="offset points")
    ax.set_xlabel("relative RMSE of radiance")
    ax.set_xlim(right=3 * max([m["error"] for m in modes] + [floor]))
    if record["reference"]["noise"]:
        ax.axvline(record["reference"]["noise"], color="0.6", ls=":", lw=1,
                   label="reference noise")
    ft.barh(rows, [m["frame_ms_mean"] for m in modes],
            xerr=[m["frame_ms_std"] for m in modes], color=colours)
    ft.set_yticks(rows, [m["mode"] for m in modes], fontsize=8)
    for r, m in zip(rows, modes, strict=True):
        ft.annotate(f"{m['frame_ms_mean']:.1f} ms", (m["frame_ms_mean"] + m["frame_ms_std"], r),
                    fontsize=7,
                    va="center", xytext=(4, 0), textcoords="offset points")
    ft.set_xlabel(f"frame time, ms (mean ± sd of {modes[0]['draws'] if modes else 0} draws, "
                  f"{record['settings']['gl_renderer'].split(' (')[0]})")
    from matplotlib.patches import Patch

    handles = [Patch(color=colour, label=KIND_LABELS[kind])
               for kind, colour in KIND_COLOURS.items() if any(m["kind"] == kind for m in modes)]
    ax.legend(handles=handles, fontsize=7, loc="upper right")  # best (shortest) bars on top
    for a in (ax, ft):
        a.grid(True, axis="x", which="both", alpha=0.3)
    _finish(plt, fig, record, path)


PLOTTERS = {"chart1_bake_time": plot_bake_time, "chart2_resolution": plot_resolution,
            "chart3_lookup_normals": plot_lookup_normals,
            "chart4_shading_modes": plot_shading_modes,
            "chart5_levels": lambda record, path: _levels_plot()(record, path)}


def _levels_plot():
    from isolume.app.charts.levels import plot_levels

    return plot_levels


# -- the command ------------------------------------------------------------------------
def _say(text: str) -> None:
    print(f"chart: {text}", file=sys.stderr, flush=True)


def _settings(args, volume, iso: float, plan: Plan, notes: list[str], run: Run) -> dict:
    """The settings block of every JSON."""
    lo, hi = volume.value_range
    return {
        "volume": volume.source or volume.name, "dims_xyz": list(volume.shape_xyz),
        "spacing": list(volume.spacing), "value_range": [lo, hi], "preprocessing": notes,
        "iso": iso, "size": list(run.gl.size), "view": args.view, "env": args.env,
        "bounces": args.bounces, "albedo": args.albedo, "seed": args.seed,
        "quick": args.quick, "samples": list(plan.samples),
        "chart_samples": plan.chart_samples, "triangles": len(run.gl.mesh.faces),
        "gl_renderer": run.gl.gl_renderer, "workers": args.workers or os.cpu_count(),
        "cpu_count": os.cpu_count(), "load_average_1min_at_end": os.getloadavg()[0],
        "error_metric": "sqrt(mean((img - ref)^2)) / mean(ref) over the RGB values of the "
                        "pixels both images mark as surface (linear radiance)",
        "bake_time": "wall time of the bake; a lattice of N paths/texel resumes the one of "
                     "the next lower count, and its time is the sum over that chain",
        **run.facts,
    }


def _cache_folder(args: argparse.Namespace, out: Path) -> Path:
    return Path(args.cache) if args.cache else out / "cache"


def _make_run(args, volume, iso: float, plan: Plan, out: Path) -> Run:
    from isolume.app.render.camera import parse_view
    from isolume.app.render.renderer import default_camera
    from isolume.baking.config import BakeConfig

    try:
        camera = default_camera(volume, parse_view(args.view))
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    size = parse_size(args.size)
    origins, dirs = camera.primary_rays(*size)
    config = BakeConfig(mode="irradiance", samples=plan.chart_samples, bounces=args.bounces,
                        albedo=(args.albedo,) * 3, env=args.env, seed=args.seed)
    lighting = local_lighting(args.env)
    gl = GLScene(volume, iso, camera, size, args.gl, lighting, args.albedo, args.env)
    store = LatticeStore(volume, _cache_folder(args, out), args.workers)
    return Run(volume, iso, origins, dirs, config, plan, store, gl, args.workers)


def run(args: argparse.Namespace) -> int:
    """Make the charts; returns the exit status."""
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    plan = _plan(args)
    volume, notes = _prepare_volume(args)
    iso = isovalue(volume, args.iso)
    began, load = time.perf_counter(), os.getloadavg()[0]
    chart_run = _make_run(args, volume, iso, plan, out)
    try:
        if chart_run.gl.mesh.empty:
            raise CLIError(f"no surface at isovalue {iso:g}: {chart_run.gl.mesh.message}")
        charts = []
        for number in plan.charts:
            charts.append(CHART_BUILDERS[number](chart_run))
            _say(f"chart {number} rendered ({time.perf_counter() - began:.0f} s)")
        ref = Reference(chart_run, _cache_folder(args, out) / "reference.state.npz")
        try:
            reference = settle_reference(ref, charts, chart_run.images, plan)
        finally:
            ref.close()
        settings = _settings(args, volume, iso, plan, notes, chart_run)
        settings["total_seconds"] = time.perf_counter() - began
        settings["load_average_1min_at_start"] = load
        for chart in charts:
            png = write_chart(chart, out, settings, reference)
            print(f"wrote {png} and {png.with_suffix('.json').name}")
    finally:
        chart_run.gl.release()
    _report(reference, charts)
    return 0


def _report(reference: dict, charts: list[Chart]) -> None:
    """One line on the reference rule, one per chart with its key figures."""
    rule = "holds" if reference["holds"] else (
        f"NOT met within the {reference['cap_seconds']:g} s cap (needs ~"
        f"{reference['spp_needed']} spp)")
    print(f"reference {reference['spp']} spp in {reference['seconds']:.0f} s: noise "
          f"{reference['noise']:.2%}, smallest error {reference['smallest_error']:.2%}; "
          f"rule (noise <= {NOISE_RATIO:g} x smallest) {rule}")
    for chart in charts:
        entries = _image_entries(chart.data)
        figures = ", ".join(f"{_entry_label(e)} {e['error']:.2%}" for e in entries
                            if e.get("error") is not None)
        print(f"{chart.name}: {figures}")


def _entry_label(entry: dict) -> str:
    """A short name of a charted image for the summary line."""
    image = entry["image"]
    if image.startswith("path_traced/"):
        return f"pt {entry['spp']}spp"
    return image.split("/", 1)[1]
