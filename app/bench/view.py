"""Viewer benchmarks (figures, never timed assertions): ``isolume bench frames`` and
``isolume bench lazy``.

* frames: milliseconds per frame of every shading mode at one size, headless (EGL or
  OSMesa: llvmpipe without a GPU), on the same mesh and camera, with the ratios of the
  global-illumination modes to local shading measured in the same run (the paper found
  its lattice lookups cheaper than Phong with shadows). Lattices are filled with constant
  values: a frame's cost does not depend on them.
* lazy: the viewer's lazy bake (the same process and scheduler) on one view: seconds until
  every visible texel shows an estimate, and until the visible error falls below a target.
  The visible error is that of the picture: the RMS over visible pixels (a random subset)
  of the relative difference between the radiance the lattice shows there (previews
  included, looked up as the shader does) and per-pixel path tracing of the displayed
  surface (`baking.reference`, traced before the bake starts). Also reported: when the
  visible texels' *own* samples reach the target (the RMS of each texel's relative
  standard error, from its second moment), and with ``--reference N`` the own values of N
  visible texels against the same texels baked to convergence separately, when the
  bake's rounds over the visible texels are done (the rays traced by then, and the
  picture from the texels' own samples then, also as the charts' RMSE), and the picture
  from the texels' own samples at the end of the run (what a saved lattice shows:
  previews are never saved) against the least error any picture of the run reached. The
  run ends when both the own samples' target is met and the visible rounds are done.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume.volumes import cores

if TYPE_CHECKING:
    from isolume.app.render.camera import Camera
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.volumes import Volume

DATA_ENV = "ISOLUME_DATA"
"""Environment variable naming the data folder (real volumes) when ``--data`` does not."""
DEFAULT_DATA = Path("..") / "shared" / "data"
"""The data folder when neither ``--data`` nor `DATA_ENV` names one, relative to the
current directory (the ``shared/data`` beside a clone, run from the clone)."""
ENGINE = Path("volumes") / "engine_zfp_256x256x128_uint8.raw.gz"
"""The engine CT scan, inside the data folder."""


def data_folder(option: str | None) -> tuple[Path, str | None]:
    """(folder, what named it): `option` (``--data``), else ``$ISOLUME_DATA``, else
    `DEFAULT_DATA` (named by nothing: None)."""
    if option:
        return Path(option).expanduser(), "--data"
    if os.environ.get(DATA_ENV):
        return Path(os.environ[DATA_ENV]).expanduser(), f"${DATA_ENV}"
    return DEFAULT_DATA, None


def default_volume(data: str | None) -> str:
    """The volume of a view benchmark given none: the engine CT scan (`ENGINE`) in the data
    folder (`data_folder`), else synthetic:engine when the folder is the unnamed default.

    Raises:
        CLIError: the folder that ``--data`` or ``$ISOLUME_DATA`` names lacks the scan.
    """
    from isolume.app.options import CLIError

    folder, named_by = data_folder(data)
    engine = folder / ENGINE
    if engine.is_file():
        return str(engine)
    if named_by is not None:
        raise CLIError(f"{named_by} {folder}: no {ENGINE} in it (the engine CT scan, the "
                       "default volume); name a folder that holds it, or give a VOLUME")
    return "synthetic:engine"


def _add_volume_and_iso(parser) -> None:
    """The VOLUME argument and the --data and --iso options every view benchmark takes."""
    parser.add_argument("volume", nargs="?", default=None,
                        help=f"volume (default: DATA/{ENGINE}, else synthetic:engine)")
    parser.add_argument("--data", metavar="DIR",
                        help=f"data folder holding {ENGINE} (default ${DATA_ENV}, else "
                        f"{DEFAULT_DATA} from the current folder)")
    parser.add_argument("--iso", type=float, help="isovalue (default: first suggested)")


# -- frames --------------------------------------------------------------------------------
def add_frames_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``isolume bench frames``."""
    _add_volume_and_iso(parser)
    parser.add_argument("--size", default="512x512", help="WxH pixels")
    parser.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"],
                        help="headless GL (default egl)")
    parser.add_argument("--frames", type=int, default=20, help="timed frames per mode")
    parser.add_argument("--rounds", type=int, default=4,
                        help="rounds the frames are split into, every mode once per round "
                        "(interleaved: a change in the machine's load touches all modes alike)")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def _filled_lattices(volume):
    """An irradiance lattice and a 5-band gray SH lattice with every texel computed, each
    with a known facing (+z): the side-aware lookup the shader runs on baked lattices."""
    from isolume.baking import octahedral
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice, LatticeGeometry

    geometry = LatticeGeometry.for_volume(volume, 1.0)
    # a constant sky without bounces: the occlusion modes accept it too
    irr_config = BakeConfig(bounces=0, env="constant:1,1,1")
    irr = Lattice.empty(geometry, 3, {"kind": "irradiance"}, config=irr_config)
    irr.values[...] = 2.5
    irr.samples[...] = 1
    sh_config = BakeConfig(mode="sh", sh_order=5)
    sh = Lattice.empty(geometry, 25, {"kind": "sh", "sh_order": 5}, config=sh_config)
    sh.values[..., 0] = 1.5
    sh.samples[...] = 1
    for lattice in (irr, sh):
        lattice.facing[...] = octahedral.encode(np.array([0.0, 0.0, 1.0]))
    return irr, sh


DIRECT_MODE = "irradiance+sun"
"""Lattice irradiance with the sun of ``sky:sun=3`` shaded per pixel (a lattice baked with
direct light "pixels"): soft shadow from a 0.5° disc."""


def _variants(mode: str) -> list[tuple[str, tuple | None]]:
    """(label, per-pixel lights) to time for `mode`: "irradiance" also with the sun shaded
    per pixel (`DIRECT_MODE`)."""
    if mode != "irradiance":
        return [(mode, None)]
    from isolume.baking.lighting import lighting_of

    return [(mode, None), (DIRECT_MODE, lighting_of("sky:sun=3").pixel_lights())]


def _time_mode(renderer, ctx, camera, settings, frames: int) -> tuple[list, list]:
    """Wall and CPU milliseconds of `frames` frames (draw, tone map, finish) after one
    warm-up frame. CPU time is the process's (llvmpipe's threads included): on a machine
    shared with other jobs it moves less than wall time."""
    renderer.resolve(renderer.draw_hdr(camera, settings), settings)
    ctx.finish()
    wall, cpu = [], []
    for _ in range(frames):
        t0, c0 = time.perf_counter(), time.process_time()
        renderer.resolve(renderer.draw_hdr(camera, settings), settings)
        ctx.finish()
        wall.append(1000 * (time.perf_counter() - t0))
        cpu.append(1000 * (time.process_time() - c0))
    return wall, cpu


def _jobs(preview: bool) -> list[tuple[str, str, str | None, tuple | None]]:
    """(label, mode, kind of lattice needed: None, "irradiance" or "sh", per-pixel
    lights) to time, grouped by the lattice they need (one upload per group and
    round)."""
    from isolume.app.render.settings import SHADING_MODES

    jobs = []
    for mode, spec in SHADING_MODES.items():
        if preview and mode not in ("phong_hemi", "irradiance"):
            continue
        jobs += [(label, mode, spec.lattice_kind, direct) for label, direct in _variants(mode)]
    order = {None: 0, "irradiance": 1, "sh": 2}
    return sorted(jobs, key=lambda job: order[job[2]])


def frame_times(volume: Volume, iso: float, size: tuple[int, int], frames: int = 20,
                backend: str = "egl", rounds: int = 4) -> dict[str, Any]:
    """Frame times of every shading mode (and the preview mesh) in one headless context,
    the frames of each mode split over `rounds` interleaved rounds.

    Returns:
        {"renderer", "triangles", "modes": {mode: {"ms", "ms_min", "fps", "cpu_ms"}},
        "ratios", "cpu_ratios", "preview": {...}} — medians, and their ratios of the GI
        modes to phong_hemi and phong_shadow (wall and CPU time).
    """
    from isolume import volumes
    from isolume.app.render.glcontext import create_headless
    from isolume.app.render.renderer import SurfaceRenderer, default_camera
    from isolume.app.render.settings import RenderSettings
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.plan import texel_values

    mesh = volumes.isosurface(volume, iso)
    rho = texel_values(volume, LatticeGeometry.for_volume(volume, 1.0))
    preview = volumes.isosurface(volume, iso, step_size=2)
    irr, sh = _filled_lattices(volume)
    gl = create_headless(backend)
    result = {"renderer": gl.ctx.info["GL_RENDERER"], "size": list(size),
              "triangles": len(mesh.faces), "preview_triangles": len(preview.faces),
              "rounds": rounds, "modes": {}, "preview": {}}
    per_round = max(1, -(-frames // rounds))
    try:
        renderer = SurfaceRenderer(gl.ctx)
        camera = default_camera(volume)
        renderer.set_bounds(*volume.box)
        for name, m in [("full", mesh), ("preview", preview)]:
            renderer.set_mesh(m.vertices, m.normals, m.faces, iso=iso)
            key = "modes" if name == "full" else "preview"
            times = {}
            for _ in range(rounds):
                shown = "unset"
                for label, mode, needs, direct in _jobs(name == "preview"):
                    if needs != shown:
                        if needs == "sh":
                            renderer.set_lattice(sh)
                            env = np.zeros((25, 3))
                            env[0] = np.sqrt(4 * np.pi)  # a white sky
                            renderer.set_environment(env)
                        else:
                            renderer.set_lattice(irr if needs == "irradiance" else None, rho)
                        shown = needs
                    settings = RenderSettings(size=size, shading=mode, direct_lights=direct)
                    wall, cpu = _time_mode(renderer, gl.ctx, camera, settings, per_round)
                    times.setdefault(label, ([], []))
                    times[label][0].extend(wall)
                    times[label][1].extend(cpu)
            for label, (wall, cpu) in times.items():
                result[key][label] = {"ms": float(np.median(wall)), "ms_min": float(min(wall)),
                                      "fps": 1000.0 / float(np.median(wall)),
                                      "cpu_ms": float(np.median(cpu))}
        renderer.release()
    finally:
        gl.release()
    modes = result["modes"]
    for name, field in (("ratios", "ms"), ("cpu_ratios", "cpu_ms")):
        result[name] = {f"{gi}/{local}": modes[gi][field] / modes[local][field]
                        for gi in ("irradiance", DIRECT_MODE, "sh") if gi in modes
                        for local in ("phong_hemi", "phong_shadow") if local in modes}
    return result


def frames(args: argparse.Namespace) -> int:
    """``isolume bench frames``: print ms/frame of every mode and the GI ratios."""
    from isolume import volumes
    from isolume.app.options import isovalue, parse_size

    volume = volumes.load(args.volume or default_volume(args.data))
    iso = isovalue(volume, args.iso)
    size = parse_size(args.size)
    r = frame_times(volume, iso, size, args.frames, args.gl, args.rounds)
    print(f"frame times: {volume.name} at iso {iso:.6g}, {r['triangles']:,} triangles "
          f"(preview {r['preview_triangles']:,}), {size[0]}x{size[1]}, {r['renderer']}; "
          f"medians of {args.frames} frames in {args.rounds} interleaved rounds")
    for mode, f in r["modes"].items():
        print(f"  {mode:20s} {f['ms']:8.1f} ms  {f['fps']:6.1f} fps  (CPU {f['cpu_ms']:.1f} ms)")
    for mode, f in r["preview"].items():
        print(f"  {mode + ' (preview)':20s} {f['ms']:8.1f} ms  {f['fps']:6.1f} fps  "
              f"(CPU {f['cpu_ms']:.1f} ms)")
    for name, ratio in r["ratios"].items():
        print(f"  ratio {name}: {ratio:.2f} (CPU time {r['cpu_ratios'][name]:.2f})")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1))
    return 0


# -- lazy ------------------------------------------------------------------------------------
def add_lazy_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``isolume bench lazy``."""
    _add_volume_and_iso(parser)
    parser.add_argument("--size", default="512x512", help="view WxH (visible texels)")
    parser.add_argument("--target", type=float, default=0.05,
                        help="visible error to reach (relative, default 0.05)")
    parser.add_argument("--pixels", type=int, default=3000,
                        help="visible pixels the picture's error is measured at")
    parser.add_argument("--pixel-paths", type=int, default=2048,
                        help="paths per pixel of their path-traced reference")
    parser.add_argument("--samples", type=int, default=256, help="the bake's last round")
    parser.add_argument("--max-levels", type=int, default=None,
                        help="cap on isovalue levels (fewer scenes to build, larger moves; "
                        "default: the bake's)")
    parser.add_argument("--workers", type=int, default=None, help="tracing threads")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds at most")
    parser.add_argument("--wide-range", action="store_true",
                        help="bake for the default iso range, not the one around the view "
                        "(as the viewer does with a lattice file of such a bake)")
    parser.add_argument("--relative", type=float, default=1.2, metavar="F",
                        help="also time the picture to within F x the RMSE (the charts' "
                        "error) of the same view's texels fully baked (default 1.2; 0: off)")
    parser.add_argument("--reference", type=int, default=0, metavar="N",
                        help="also measure against N visible texels baked separately to "
                        "--reference-samples (0: off)")
    parser.add_argument("--reference-samples", type=int, default=4096,
                        help="paths per pixel of the path-traced truth (default 4096)")
    parser.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"],
                        help="headless GL (default egl)")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def visible_pixels_headless(volume: Volume, iso: float, size: tuple[int, int], backend: str
                            ) -> tuple[np.ndarray, np.ndarray, Camera]:
    """World positions (M, 3) of the visible pixels of the default view, their flat pixel
    indices (M,) (row 0 at the top), and the camera (rendered off-screen with the
    position pass, as the viewer does)."""
    from isolume import volumes
    from isolume.app.render.glcontext import create_headless
    from isolume.app.render.renderer import SurfaceRenderer, default_camera
    from isolume.app.render.settings import RenderSettings

    mesh = volumes.isosurface(volume, iso)
    camera = default_camera(volume)
    gl = create_headless(backend)
    try:
        renderer = SurfaceRenderer(gl.ctx)
        renderer.set_mesh(mesh.vertices, mesh.normals, mesh.faces)
        frame = renderer.render(camera, RenderSettings(size=size, shading="position"))
        renderer.release()
    finally:
        gl.release()
    return frame.linear[frame.mask][:, :3], np.flatnonzero(frame.mask.reshape(-1)), camera


@dataclass(frozen=True)
class PixelTruth:
    """Path-traced radiance at visible pixels: what the picture should show there.

    Attributes:
        points: (P, 3) world points where the pixels' rays meet the displayed mesh.
        luminance: (P,) mean radiance luminance; noise: (P,) its standard error.
        albedo: (3,) the surface albedo (radiance = albedo·E/π).
        normals: (P, 3) unit normals there, turned to the eye (the side-aware lookup's).
    """

    points: np.ndarray
    luminance: np.ndarray
    noise: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray

    def error(self, lattice: Lattice) -> float:
        """RMS over the pixels of the relative difference between the luminance `lattice`
        shows there (`Lattice.sample`, normalized like the shader) and the truth; the
        truth is floored at 1 % of its median (deep shadow judged against the scene's light
        level, not against ~0)."""
        shown = lattice.sample(self.points, normalized=True, normals=self.normals)[:, :3] \
            * self.albedo / np.pi
        rel = (_luminance(shown) - self.luminance) / self._floored()
        return float(np.sqrt(np.mean(rel**2)))

    def rmse(self, lattice: Lattice) -> float:
        """The charts' error (`app.charts.metrics.relative_rmse`) of the luminance `lattice` shows:
        RMS difference over the mean truth. Unlike `error`, a dark pixel weighs no more
        than a bright one (on CThead one crack of luminance 0.003, shown at 0.6, makes
        `error` 146 % alone)."""
        shown = lattice.sample(self.points, normalized=True, normals=self.normals)[:, :3] \
            * self.albedo / np.pi
        diff = _luminance(shown) - self.luminance
        return float(np.sqrt(np.mean(diff**2)) / np.mean(self.luminance))

    def own_noise(self) -> float:
        """RMS relative standard error of the truth itself (the error's floor)."""
        return float(np.sqrt(np.mean((self.noise / self._floored()) ** 2)))

    def _floored(self) -> np.ndarray:
        return np.maximum(self.luminance, 0.01 * float(np.median(self.luminance)))


def pixel_truth(volume: Volume, config: BakeConfig, iso: float, camera: Camera,
                size: tuple[int, int], pixels: np.ndarray, paths: int, workers: int | None
                ) -> PixelTruth:
    """Trace `paths` paths at each of the (P,) flat `pixels` of `camera`'s view (of `size`)
    on the displayed isosurface, with the bake's lighting (`baking.reference`)."""
    from dataclasses import replace

    from isolume.baking.lattice import LUMINANCE
    from isolume.baking.reference import PixelStats, ReferenceTracer

    origins, dirs = camera.primary_rays(*size)
    with ReferenceTracer(volume, iso, origins[pixels], dirs[pixels],
                         replace(config, samples=paths), workers=workers) as tracer:
        stats = PixelStats.empty(tracer.pixels)
        tracer.run(stats)
        image, hit = tracer.image(stats), tracer.hits.pixels
        # the channels share their paths: the luminance's standard error is at most the
        # weighted sum of theirs
        return PixelTruth(tracer.hits.points, image.radiance[hit] @ LUMINANCE,
                          image.stderr[hit] @ LUMINANCE, np.array(config.albedo),
                          tracer.hits.normals)


def visible_error(lattice: Lattice, flat: np.ndarray) -> float:
    """RMS over texels `flat` of the relative standard error of their means (inf while
    any has fewer than 2 paths)."""
    from isolume.baking.adaptive import relative_error

    values = lattice.values.reshape(-1, lattice.values.shape[-1])[flat]
    err = relative_error(values, lattice.second.reshape(-1)[flat],
                         lattice.samples.reshape(-1)[flat])
    if len(err) == 0 or not np.isfinite(err).all():
        return float("inf")
    return float(np.sqrt(np.mean(err**2)))


def _luminance(values: np.ndarray) -> np.ndarray:
    from isolume.baking.lattice import LUMINANCE

    return values[:, :3] @ LUMINANCE if values.shape[1] >= 3 else values[:, 0]


def reference_values(volume: Volume, config: BakeConfig, flat: np.ndarray, samples: int,
                     workers: int | None) -> np.ndarray:
    """(N,) luminance of texels `flat` baked to `samples` paths with another seed and the
    bake's default number of levels (so a capped `config.max_levels` shows its bias)."""
    from dataclasses import replace

    from isolume.baking.bake import Baker
    from isolume.baking.config import BakeConfig

    reference = replace(config, seed=config.seed + 7919, samples=samples,
                        max_levels=BakeConfig().max_levels)
    baker = Baker(volume, reference, workers=workers, scene_cache=2)
    try:
        pos = np.searchsorted(baker.plan.ids, flat)
        baker.run(pos, samples)
        values = baker.lattice.values.reshape(-1, baker.lattice.values.shape[-1])[flat]
    finally:
        baker.close()
    return _luminance(values)


def full_bake_error(volume: Volume, config: BakeConfig, corners: np.ndarray,
                    truth: PixelTruth, workers: int | None) -> tuple[float, float]:
    """The picture's error (`PixelTruth.rmse`) when the texels it reads, (N,) flat ids
    `corners`, are baked to `config.samples` paths (the lazy bake's end for this view),
    and the seconds that bake took."""
    from isolume.baking.bake import Baker

    began = time.perf_counter()
    baker = Baker(volume, config, workers=workers, scene_cache=2)
    try:
        active = corners[baker.plan.active.reshape(-1)[corners]]
        baker.run(np.searchsorted(baker.plan.ids, active))
        return truth.rmse(baker.lattice), time.perf_counter() - began
    finally:
        baker.close()


def lazy(args: argparse.Namespace) -> int:
    """``isolume bench lazy``: time to first estimates and to the error target."""
    from dataclasses import replace

    from isolume import volumes
    from isolume.app.options import isovalue, parse_size
    from isolume.app.viewer.bake_client import BakeLink, SharedLattice, lattice_meta
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import LatticeGeometry
    from isolume.baking.lazy import View, view_iso_range, visible_cells
    from isolume.baking.preview import cell_corners

    volume = volumes.load(args.volume or default_volume(args.data))
    iso = isovalue(volume, args.iso)
    config = BakeConfig(samples=args.samples)
    if args.max_levels is not None:
        config = replace(config, max_levels=args.max_levels)
    geometry = LatticeGeometry.for_volume(volume, config.scale)
    size = parse_size(args.size)
    points, pixels, camera = visible_pixels_headless(volume, iso, size, args.gl)
    cells = visible_cells(geometry, points)
    workers = args.workers or cores.threads()
    print(f"lazy GI: {volume.name} at iso {iso:.6g}, {args.size} view, {workers} workers, "
          f"target {args.target:.0%}")
    t = time.perf_counter()
    probe = np.sort(np.random.default_rng(0).choice(pixels, min(args.pixels, len(pixels)),
                                                    replace=False))
    truth = pixel_truth(volume, config, iso, camera, size, probe, args.pixel_paths, workers)
    figures = {"volume": volume.name, "iso": iso, "workers": workers, "size": args.size,
               "pixels": len(truth.points), "pixel_paths": args.pixel_paths,
               "pixel_truth_noise": truth.own_noise()}
    print(f"  reference: {len(truth.points):,} visible pixels path-traced to "
          f"{args.pixel_paths} paths in {time.perf_counter() - t:.1f} s (its own noise: "
          f"{truth.own_noise():.2%} RMS)")
    relative_target = float("nan")
    if args.relative > 0:
        full_config = config if args.wide_range else replace(
            config, iso_range=view_iso_range(volume, iso))  # what the lazy bake ends with
        full, seconds = full_bake_error(volume, full_config,
                                        cell_corners(geometry.shape, cells), truth, workers)
        relative_target = args.relative * full
        figures.update(full_bake_error=full, full_bake_seconds=seconds,
                       relative_target=relative_target)
        print(f"  the same view's texels fully baked ({config.samples} paths, "
              f"{seconds:.0f} s): picture RMSE {full:.2%} (the charts' error); target "
              f"{args.relative:g}x = {relative_target:.2%}")
    meta = lattice_meta(volume, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    t0 = time.perf_counter()
    link = BakeLink(volume, config, shared, workers, iso, follow_iso=not args.wide_range)
    link.send_view(View(iso, tuple(float(v) for v in camera.eye), cells, None,
                        points.astype(np.float32)))
    visible_flat = subset = None
    trace, subset_lum = [], []
    corners = cell_corners(geometry.shape, cells)  # every texel the picture reads
    figures["visible_corner_texels"] = len(corners)
    try:
        while time.perf_counter() - t0 < args.timeout:
            link.poll()
            if link.error:
                raise RuntimeError(link.error)
            now = time.perf_counter() - t0
            lat = shared.lattice
            _first_shown(figures, lat, corners, now)
            image_err = truth.error(lat)
            shown = bool(link.previews)  # a picture: the first preview pass is done
            if shown and "relative_target_s" not in figures and args.relative > 0:
                rmse = truth.rmse(lat)
                if rmse <= relative_target:
                    figures["relative_target_s"] = now
                    print(f"  the picture is within {args.relative:g}x the fully baked "
                          f"error ({rmse:.1%} RMSE) after {now:.1f} s")
            if image_err <= args.target and "target_s" not in figures:
                figures["target_s"] = now
                print(f"  the picture is within {image_err:.1%} RMS of the path-traced one "
                      f"after {now:.1f} s")
            if link.ready is not None and "ready_s" not in figures:
                figures["ready_s"] = now
                figures["active_texels"] = link.ready["active"]
                figures["levels"] = link.ready["levels"]
                print(f"  plan ready after {now:.1f} s ({link.ready['active']:,} active "
                      f"texels, {link.ready['levels']} levels)")
            p = link.progress
            if p is not None and p.visible and visible_flat is None:
                visible_flat = corners[lat.active.reshape(-1)[corners]]  # active ones
                figures["visible_texels"] = len(visible_flat)
                rng = np.random.default_rng(0)
                subset = np.sort(rng.choice(visible_flat, min(args.reference,
                                                              len(visible_flat)),
                                            replace=False))
            own_err = float("inf")
            if visible_flat is not None:
                own_err = _own_progress(figures, lat, visible_flat, now)
                values = lat.values.reshape(-1, lat.values.shape[-1])
                subset_lum.append((now, _luminance(values[subset])))
            trace.append((now, image_err, own_err))
            if own_err <= args.target and "own_target_s" not in figures:
                figures["own_target_s"] = now
                print(f"  the visible texels' own samples: error {own_err:.3f} <= "
                      f"{args.target} after {now:.1f} s")
            _visible_rounds(figures, p, link.stats, now, lat, truth)
            if "own_target_s" in figures and "visible_rounds_s" in figures:
                break
            time.sleep(0.25)
        else:
            print(f"  stopped after {args.timeout:.0f} s")
        figures["stats"] = link.stats
    finally:
        link.stop()
    _preview_figures(figures, link)
    _hand_over_figures(figures, shared.lattice, truth, trace)
    if args.reference and subset is not None and len(subset):
        _reference_figures(args, volume, config, subset, subset_lum, figures)
    figures["trace"] = [{"s": now, "picture_error": image, "own_error": own}
                        for now, image, own in trace[:: max(1, len(trace) // 200)]]
    shared.close()
    print(f"  bake: {figures['stats'].get('rays', 0):,} rays, "
          f"{figures['stats'].get('scene_seconds', 0):.1f} s building level scenes, "
          f"{figures['stats'].get('trace_seconds', 0):.1f} s tracing (thread-seconds)")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1, default=float))
    return 0


def _first_shown(figures: dict, lattice, corners: np.ndarray, now: float) -> None:
    """Note when every texel the picture reads first shows an estimate."""
    region = np.unravel_index(corners, lattice.geometry.shape)
    if "first_estimate_s" not in figures and lattice.shown(region).all():
        figures["first_estimate_s"] = now
        print(f"  every visible texel ({len(corners):,}) shows an estimate after {now:.1f} s "
              "(previews traced on the displayed surface)")


def _own_progress(figures: dict, lattice, visible_flat: np.ndarray, now: float) -> float:
    """The visible texels' own-sample error (`visible_error`); notes when all have some."""
    started = int((lattice.samples.reshape(-1)[visible_flat] > 0).sum())
    if started == len(visible_flat) and "bake_estimate_s" not in figures:
        figures["bake_estimate_s"] = now
        print(f"  every visible active texel ({started:,}) has samples of its own after "
              f"{now:.1f} s")
    return visible_error(lattice, visible_flat)


def _visible_rounds(figures: dict, progress, stats: dict, now: float, lattice,
                    truth: PixelTruth) -> None:
    """Notes when the lazy bake's rounds over the visible texels are done (its `progress`
    has gone on to the rest of the surface): the rays traced by then, and the picture
    from the texels' own samples then (`own_picture`)."""
    if (progress is None or not progress.visible or "visible_rounds_s" in figures
            or (progress.stage is not None and progress.stage[0] == "visible")):
        return
    error, rmse = own_picture(lattice, truth)
    figures.update(visible_rounds_s=now, visible_rounds_rays=stats.get("rays", 0),
                   visible_rounds_error=error, visible_rounds_rmse=rmse)
    print(f"  the visible texels' rounds are done after {now:.1f} s "
          f"({figures['visible_rounds_rays']:,} rays): the picture from their own samples "
          f"{error:.1%} RMS, RMSE {rmse:.2%}")


def own_picture(lattice, truth: PixelTruth) -> tuple[float, float]:
    """`truth.error` and `truth.rmse` of the picture from `lattice`'s own samples alone,
    without its previews: what a saved lattice shows."""
    saved = dataclasses.replace(lattice, preview=None, preview_paths=None,
                                preview_facing=None)
    return truth.error(saved), truth.rmse(saved)


def _preview_figures(figures: dict, link) -> None:
    """The preview passes the bake process reported, and its start-up time."""
    figures["preview_passes"] = [{"at_s": at, **f} for at, f in link.previews]
    warm = link.warm["seconds"] if link.warm else float("nan")
    figures["process_start_s"] = warm
    for at, f in link.previews:
        print(f"  preview pass: {f['paths']} paths on {f['texels']:,} texels in "
              f"{f['seconds']:.2f} s, done {at:.1f} s after the bake process was started")
    print(f"  ({warm:.1f} s of that is starting the process: imports, kernels, gradient "
          "grid — the viewer starts it with its window)")


def _hand_over_figures(figures: dict, lattice, truth: PixelTruth, trace: list) -> None:
    """The picture's error at the end of the run from the texels' own samples alone (what
    a saved lattice shows), against the least error the run's pictures reached (the
    previews', traced on the displayed surface, while they rested on more paths): a
    display hands a texel over to its own value once that rests on as many paths."""
    own, own_rmse = own_picture(lattice, truth)
    best = min((image for _, image, _ in trace), default=float("nan"))
    figures.update(own_picture_error=own, own_picture_rmse=own_rmse,
                   least_picture_error=best)
    print(f"  the picture from the texels' own samples at the end: {own:.1%} RMS of the "
          f"path-traced one (the least any picture of the run reached: {best:.1%}); "
          f"RMSE {own_rmse:.2%} (the charts' error)")


def _reference_figures(args, volume, config, subset, subset_lum, figures) -> None:
    """Error of the lazy lattice's visible texels (a subset; `subset_lum` holds (seconds,
    (N,) luminance) along the run) against a converged bake; the time it first falls
    below the target."""
    t = time.perf_counter()
    ref = reference_values(volume, config, subset, args.reference_samples, args.workers)
    seconds = time.perf_counter() - t
    rms = []
    floor = 0.01 * float(np.median(np.abs(ref)))  # as `PixelTruth.error`: deep shadow is
    for now, lum in subset_lum:  # judged against the scene's light level, not against ~0
        rel = (lum - ref) / np.maximum(np.abs(ref), floor)
        rms.append(float(np.sqrt(np.mean(rel**2))))
        if rms[-1] <= args.target and "reference_target_s" not in figures:
            figures["reference_target_s"] = now
    figures["reference"] = {"texels": len(subset), "samples": args.reference_samples,
                            "seconds": seconds, "rms_rel_error": rms[:: max(1, len(rms) // 200)],
                            "rms_rel_error_at_end": rms[-1] if rms else None}
    at = figures.get("reference_target_s")
    print(f"  against {len(subset)} visible texels baked to {args.reference_samples} paths: "
          f"RMS relative error {rms[-1]:.3f} at the end"
          + (f", below {args.target:.0%} after {at:.1f} s" if at is not None else ""))
