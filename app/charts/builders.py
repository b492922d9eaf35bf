"""The charts of ``isolume chart``, each built from a `Run` into a `Chart` whose image
entries get their errors once the reference is final (`tracing.settle_reference`):

1. ``chart1_bake_time``: error against bake wall time for irradiance lattices, SH lattices
   of orders `SH_ORDERS`, and per-pixel path tracing given the same time (paper Table 1,
   Fig. 7).
2. ``chart2_resolution``: error and GL texture memory against lattice resolution
   (`SCALES` per axis; paper Fig. 12).
3. ``chart3_lookup_normals``: error per lattice lookup (paper Fig. 6: those that
   `app.render.settings.SHADING_MODES` offers) and per texel-normal scheme (paper Fig. 5).
4. ``chart4_shading_modes``: error and frame time of every shading mode (paper Table 2),
   local models lit to match the environment as well as they can be.
5. ``chart5_levels``: error against bake time per isovalue-level policy
   (`app.charts.levels`).

Bakes cover the whole lattice (all isovalues, the paper's "full texture").
"""

from __future__ import annotations

from isolume.app.charts.lattices import Baked, texture_bytes
from isolume.app.charts.levels import chart_levels
from isolume.app.charts.model import Chart, Run
from isolume.app.charts.tracing import equal_time_path_tracing

SCALES: tuple[float, ...] = (0.5, 1.0, 2.0)
"""Lattice texels per voxel along the finest axis (`--scale`) of chart 2."""
NORMAL_SCHEMES: dict[str, dict[str, str | float]] = {
    "gradient": {"normals": "gradient", "offset": 0.0},
    "smoothed": {"normals": "smooth", "offset": 0.0},
    "smoothed + offset": {"normals": "smooth", "offset": 0.25},
}
"""Texel normal schemes of paper Fig. 5 → `BakeConfig` fields (offset in voxels)."""
SH_ORDERS = (3, 5)
"""SH orders of chart 1's SH lattices; chart 4's SH mode reads the highest."""


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
    from isolume.app.render.settings import SHADING_MODES

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
    from isolume.app.render.settings import SHADING_MODES

    for name, mode in SHADING_MODES.items():
        baked = _mode_lattice(run, mode)
        yield name, name, mode, baked
        pixels = baked is not None and baked.lattice.config.direct_light
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
                "config": lattice.config.to_dict(), **run.summary(baked)},
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


CHART_BUILDERS = {"1": chart_bake_time, "2": chart_resolution, "3": chart_lookup_normals,
                  "4": chart_shading_modes, "5": chart_levels}
"""Chart number → the function that builds it from a `Run`."""
