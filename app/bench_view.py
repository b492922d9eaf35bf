"""Viewer benchmarks (figures, never timed assertions): ``isolume bench frames`` and
``isolume bench lazy``.

* frames: milliseconds per frame of every shading mode at one size, headless (EGL or
  OSMesa: llvmpipe without a GPU), on the same mesh and camera, with the ratios of the
  global-illumination modes to local shading measured in the same run (the paper found
  its lattice lookups cheaper than Phong with shadows). Lattices are filled with constant
  values: a frame's cost does not depend on them.
* lazy: the viewer's lazy bake (the same process and scheduler) on one view: seconds until
  every visible texel has a first estimate, and until the visible texels' error falls
  below a target. The error is the RMS over visible texels of the relative standard error
  of each texel's mean, estimated from its samples (per-texel second moments); with
  ``--reference N`` also against N visible texels baked to convergence separately.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

ENGINE = Path(__file__).resolve().parents[2] / "shared" / "data" / "volumes" / \
    "engine_zfp_256x256x128_uint8.raw.gz"
"""The engine CT scan, when ../shared/data is present (else synthetic:engine)."""


def _default_volume() -> str:
    return str(ENGINE) if ENGINE.exists() else "synthetic:engine"


def _add_volume_and_iso(parser) -> None:
    """The VOLUME argument and --iso option every view benchmark takes."""
    parser.add_argument("volume", nargs="?", default=None,
                        help="volume (default: the engine from ../shared/data, else "
                        "synthetic:engine)")
    parser.add_argument("--iso", type=float, help="isovalue (default: first suggested)")


# -- frames --------------------------------------------------------------------------------
def add_frames_arguments(parser) -> None:
    """Options of ``isolume bench frames``."""
    _add_volume_and_iso(parser)
    parser.add_argument("--size", default="512x512", help="WxH pixels")
    parser.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"])
    parser.add_argument("--frames", type=int, default=20, help="timed frames per mode")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def _filled_lattices(volume):
    """An irradiance lattice and a 5-band gray SH lattice with every texel computed."""
    from baking.config import BakeConfig
    from baking.lattice import Lattice, LatticeGeometry

    geometry = LatticeGeometry.for_volume(volume, 1.0)
    # a constant sky without bounces: the occlusion modes accept it too
    irr_config = BakeConfig(bounces=0, env="constant:1,1,1").to_dict()
    irr = Lattice.empty(geometry, 3, {"kind": "irradiance", "config": irr_config})
    irr.values[...] = 2.5
    irr.samples[...] = 1
    sh_config = BakeConfig(mode="sh", sh_order=5).to_dict()
    sh = Lattice.empty(geometry, 25, {"kind": "sh", "sh_order": 5, "config": sh_config})
    sh.values[..., 0] = 1.5
    sh.samples[...] = 1
    return irr, sh


def _time_mode(renderer, ctx, camera, settings, frames: int) -> list[float]:
    """Milliseconds per frame (draw, tone map, finish) after 3 warm-up frames."""
    for _ in range(3):
        renderer.resolve(renderer.draw_hdr(camera, settings), settings)
    ctx.finish()
    out = []
    for _ in range(frames):
        t0 = time.perf_counter()
        renderer.resolve(renderer.draw_hdr(camera, settings), settings)
        ctx.finish()
        out.append(1000 * (time.perf_counter() - t0))
    return out


def frame_times(volume, iso: float, size: tuple[int, int], frames: int = 20,
                backend: str = "egl") -> dict:
    """Frame times of every shading mode (and the preview mesh) in one headless context.

    Returns:
        {"renderer", "triangles", "modes": {mode: {"ms", "ms_min", "fps"}}, "ratios",
        "preview": {...}} — ratios of the GI modes to phong_hemi and phong_shadow.
    """
    import volumes
    from baking.lattice import LatticeGeometry
    from baking.plan import texel_values

    from .glcontext import create_headless
    from .render import SHADING_MODES, RenderSettings, SurfaceRenderer, default_camera

    mesh = volumes.isosurface(volume, iso)
    rho = texel_values(volume, LatticeGeometry.for_volume(volume, 1.0))
    preview = volumes.isosurface(volume, iso, step_size=2)
    irr, sh = _filled_lattices(volume)
    gl = create_headless(backend)
    result = {"renderer": gl.ctx.info["GL_RENDERER"], "size": list(size),
              "triangles": len(mesh.faces), "preview_triangles": len(preview.faces),
              "modes": {}, "preview": {}}
    try:
        renderer = SurfaceRenderer(gl.ctx)
        camera = default_camera(volume)
        renderer.set_bounds(*volume.box)
        lattices = {None: None, "sh": sh}
        for name, m in [("full", mesh), ("preview", preview)]:
            renderer.set_mesh(m.vertices, m.normals, m.faces, iso=iso)
            shown = "unset"
            for mode, spec in SHADING_MODES.items():
                if name == "preview" and mode not in ("phong_hemi", "irradiance"):
                    continue
                needs = spec.lattice if spec.lattice in lattices else spec.lattice and "irr"
                if needs != shown:
                    if needs == "irr":
                        renderer.set_lattice(irr, rho)
                    else:
                        renderer.set_lattice(lattices[needs])
                    shown = needs
                if needs == "sh":
                    env = np.zeros((25, 3))
                    env[0] = np.sqrt(4 * np.pi)  # a white sky
                    renderer.set_environment(env)
                settings = RenderSettings(size=size, shading=mode)
                ms = _time_mode(renderer, gl.ctx, camera, settings, frames)
                key = "modes" if name == "full" else "preview"
                result[key][mode] = {"ms": float(np.median(ms)), "ms_min": float(min(ms)),
                                     "fps": 1000.0 / float(np.median(ms))}
        renderer.release()
    finally:
        gl.release()
    modes = result["modes"]
    result["ratios"] = {f"{gi}/{local}": modes[gi]["ms"] / modes[local]["ms"]
                        for gi in ("irradiance", "sh") if gi in modes
                        for local in ("phong_hemi", "phong_shadow") if local in modes}
    return result


def frames(args) -> int:
    """``isolume bench frames``: print ms/frame of every mode and the GI ratios."""
    import volumes

    from .cli import _isovalue, _size

    volume = volumes.load(args.volume or _default_volume())
    iso = _isovalue(volume, args.iso)
    size = _size(args.size)
    r = frame_times(volume, iso, size, args.frames, args.gl)
    print(f"frame times: {volume.name} at iso {iso:.6g}, {r['triangles']:,} triangles "
          f"(preview {r['preview_triangles']:,}), {size[0]}x{size[1]}, {r['renderer']}")
    for mode, f in r["modes"].items():
        print(f"  {mode:20s} {f['ms']:8.1f} ms  {f['fps']:6.1f} fps")
    for mode, f in r["preview"].items():
        print(f"  {mode + ' (preview)':20s} {f['ms']:8.1f} ms  {f['fps']:6.1f} fps")
    for name, ratio in r["ratios"].items():
        print(f"  ratio {name}: {ratio:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1))
    return 0


# -- lazy ------------------------------------------------------------------------------------
def add_lazy_arguments(parser) -> None:
    """Options of ``isolume bench lazy``."""
    _add_volume_and_iso(parser)
    parser.add_argument("--size", default="512x512", help="view WxH (visible texels)")
    parser.add_argument("--target", type=float, default=0.05,
                        help="visible error to reach (relative, default 0.05)")
    parser.add_argument("--samples", type=int, default=256, help="the bake's last round")
    parser.add_argument("--max-levels", type=int, default=None,
                        help="cap on isovalue levels (fewer scenes to build, larger moves; "
                        "default: the bake's)")
    parser.add_argument("--workers", type=int, default=None, help="tracing threads")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds at most")
    parser.add_argument("--reference", type=int, default=0, metavar="N",
                        help="also measure against N visible texels baked separately to "
                        "--reference-samples (0: off)")
    parser.add_argument("--reference-samples", type=int, default=4096)
    parser.add_argument("--gl", default="egl", choices=["egl", "osmesa", "auto"])
    parser.add_argument("--json", help="also write the figures to this JSON file")


def visible_cells_headless(volume, iso: float, size: tuple[int, int], backend: str,
                           geometry):
    """Flat base ids of the lattice cells under visible pixels of the default view, and
    the camera (rendered off-screen with the position pass, as the viewer does)."""
    import volumes
    from baking.lazy import visible_cells

    from .glcontext import create_headless
    from .render import RenderSettings, SurfaceRenderer, default_camera

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
    return visible_cells(geometry, frame.linear[frame.mask]), camera


def visible_error(lattice, flat: np.ndarray) -> float:
    """RMS over texels `flat` of the relative standard error of their means (inf while
    any has fewer than 2 paths)."""
    from baking.lazy import relative_error

    values = lattice.values.reshape(-1, lattice.values.shape[-1])[flat]
    err = relative_error(values, lattice.second.reshape(-1)[flat],
                         lattice.samples.reshape(-1)[flat])
    if len(err) == 0 or not np.isfinite(err).all():
        return float("inf")
    return float(np.sqrt(np.mean(err**2)))


def _luminance(values: np.ndarray) -> np.ndarray:
    from baking.lattice import LUMINANCE

    return values[:, :3] @ LUMINANCE if values.shape[1] >= 3 else values[:, 0]


def reference_values(volume, config, flat: np.ndarray, samples: int,
                     workers: int | None) -> np.ndarray:
    """(N,) luminance of texels `flat` baked to `samples` paths with another seed and the
    bake's default number of levels (so a capped `config.max_levels` shows its bias)."""
    from dataclasses import replace

    from baking.bake import Baker
    from baking.config import BakeConfig

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


def lazy(args) -> int:
    """``isolume bench lazy``: time to first estimates and to the error target."""
    from dataclasses import replace

    import volumes
    from baking.config import BakeConfig
    from baking.lattice import LatticeGeometry
    from baking.lazy import View
    from baking.preview import cell_corners

    from .cli import _isovalue, _size
    from .viewer import BakeLink, SharedLattice, lattice_meta

    volume = volumes.load(args.volume or _default_volume())
    iso = _isovalue(volume, args.iso)
    config = BakeConfig(samples=args.samples)
    if args.max_levels is not None:
        config = replace(config, max_levels=args.max_levels)
    geometry = LatticeGeometry.for_volume(volume, config.scale)
    cells, camera = visible_cells_headless(volume, iso, _size(args.size), args.gl, geometry)
    meta = lattice_meta(volume, config)
    shared = SharedLattice.create(geometry, meta["channels"], meta)
    workers = args.workers or os.cpu_count() or 1
    print(f"lazy GI: {volume.name} at iso {iso:.6g}, {args.size} view, {workers} workers, "
          f"target {args.target:.0%}")
    t0 = time.perf_counter()
    link = BakeLink(volume, config, shared, workers, iso)
    link.send_view(View(iso, tuple(float(v) for v in camera.eye), cells))
    figures = {"volume": volume.name, "iso": iso, "workers": workers, "size": args.size}
    visible_flat = subset = None
    trace, subset_lum = [], []
    corners = cell_corners(geometry.shape, cells)  # every texel the picture reads
    figures["visible_corner_texels"] = len(corners)
    try:
        while time.perf_counter() - t0 < args.timeout:
            link.poll()
            if link.error:
                raise RuntimeError(link.error)
            if "first_estimate_s" not in figures:
                lat = shared.lattice
                shown = ((lat.samples.reshape(-1)[corners] > 0)
                         | (lat.first.reshape(-1)[corners] > 0))
                if shown.all():
                    figures["first_estimate_s"] = time.perf_counter() - t0
                    print(f"  every visible texel ({len(corners):,}) shows an estimate after "
                          f"{figures['first_estimate_s']:.1f} s (first estimates on the "
                          "displayed surface)")
            if link.ready is not None and "ready_s" not in figures:
                figures["ready_s"] = time.perf_counter() - t0
                figures["active_texels"] = link.ready["active"]
                figures["levels"] = link.ready["levels"]
                print(f"  plan ready after {figures['ready_s']:.1f} s "
                      f"({link.ready['active']:,} active texels, {link.ready['levels']} levels)")
            p = link.progress
            if p is not None and p.visible and visible_flat is None:
                visible_flat = _visible_flat(shared.lattice, geometry, cells)
                figures["visible_texels"] = len(visible_flat)
                rng = np.random.default_rng(0)
                subset = np.sort(rng.choice(visible_flat, min(args.reference,
                                                              len(visible_flat)),
                                            replace=False))
            if visible_flat is not None:
                now = time.perf_counter() - t0
                started = int((shared.lattice.samples.reshape(-1)[visible_flat] > 0).sum())
                err = visible_error(shared.lattice, visible_flat)
                trace.append((now, started, err))
                values = shared.lattice.values.reshape(-1, shared.lattice.values.shape[-1])
                subset_lum.append(_luminance(values[subset]))
                if started == len(visible_flat) and "bake_estimate_s" not in figures:
                    figures["bake_estimate_s"] = now
                    print(f"  every visible active texel ({started:,}) has samples of its "
                          f"own after {now:.1f} s")
                if err <= args.target:
                    figures["target_s"] = now
                    print(f"  visible error {err:.3f} <= {args.target} after {now:.1f} s")
                    break
            time.sleep(0.25)
        else:
            print(f"  stopped after {args.timeout:.0f} s")
        figures["stats"] = link.stats
    finally:
        link.stop()
    figures["first_passes"] = [{"at_s": at, **f} for at, f in link.first]
    if link.first:
        at, f = link.first[0]
        warm = link.warm["seconds"] if link.warm else float("nan")
        figures["process_start_s"] = warm
        print(f"  first-estimate pass: {f['texels']:,} texels in {f['seconds']:.2f} s, done "
              f"{at:.1f} s after the bake process was started ({warm:.1f} s of which "
              "starting it: imports, kernels, gradient grid — the viewer starts it with "
              "its window)")
    if args.reference and subset is not None and len(subset):
        _reference_figures(args, volume, config, subset, trace, subset_lum, figures)
    figures["trace"] = trace[:: max(1, len(trace) // 200)]
    shared.close()
    print(f"  bake: {figures['stats'].get('rays', 0):,} rays, "
          f"{figures['stats'].get('scene_seconds', 0):.1f} s building level scenes, "
          f"{figures['stats'].get('trace_seconds', 0):.1f} s tracing (thread-seconds)")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1, default=float))
    return 0


def _visible_flat(lattice, geometry, cells: np.ndarray) -> np.ndarray:
    """Flat ids of the active texels at the corners of the visible cells."""
    from baking.lazy import corner_offsets

    flat = np.unique((cells[:, None] + corner_offsets(geometry.shape)[None, :]).reshape(-1))
    return flat[lattice.active.reshape(-1)[flat]]


def _reference_figures(args, volume, config, subset, trace, subset_lum, figures) -> None:
    """Error of the lazy lattice's visible texels (a subset) against a converged bake, at
    every trace point; the time it first falls below the target."""
    t = time.perf_counter()
    ref = reference_values(volume, config, subset, args.reference_samples, args.workers)
    seconds = time.perf_counter() - t
    rms = []
    floor = 0.01 * float(np.median(np.abs(ref)))  # as `Lattice.relative_error`: deep
    for lum in subset_lum:  # shadow is judged against the scene's light level, not ~0
        rel = (lum - ref) / np.maximum(np.abs(ref), floor)
        rms.append(float(np.sqrt(np.mean(rel**2))))
    for (now, _, _), e in zip(trace, rms, strict=True):
        trace_err = e
        if trace_err <= args.target:
            figures["reference_target_s"] = now
            break
    figures["reference"] = {"texels": len(subset), "samples": args.reference_samples,
                            "seconds": seconds, "rms_rel_error": rms[:: max(1, len(rms) // 200)],
                            "rms_rel_error_at_end": rms[-1] if rms else None}
    at = figures.get("reference_target_s")
    print(f"  against {len(subset)} visible texels baked to {args.reference_samples} paths: "
          f"RMS relative error {rms[-1]:.3f} at the end"
          + (f", below {args.target:.0%} after {at:.1f} s" if at is not None else ""))
