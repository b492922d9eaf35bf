"""Chart 5 of ``isolume chart``: error against bake time for several level policies.

A lattice's texels are lit on a few isovalue *levels* (`baking.plan`): more levels move
texels less far onto them (less bias) but cost a marching-cubes mesh and an Embree scene
each. The automatic policy (the default, ``max_move`` None) loosens the level spacing as
the Monte Carlo noise grows (few paths per texel) and caps the level count at a fraction
of the tracing cost; the fixed policies keep one move limit whatever the samples. A point
of the automatic policy is a fresh bake timed end to end (a resumed one would keep its
file's levels); a fixed policy's resumes its next lower count, and its time is the sum
over that chain (`app.charts.lattices`). No point's time holds the process's one-off costs
(`LatticeStore.warm_up`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from isolume.app.charts.model import Chart, Run
from isolume.app.charts.plotting import figure, finish, noise_line, plain_log_ticks

POLICIES = (("auto", None), ("0.25 voxel", 0.25), ("0.5 voxel", 0.5), ("1 voxel", 1.0),
            ("2 voxels", 2.0))
"""(label, max_move): the automatic policy and fixed move limits."""


def chart_levels(run: Run) -> Chart:
    """Chart 5: error against bake time of irradiance lattices at chart 1's sample
    counts, one series per level policy (`POLICIES`)."""
    series = {}
    for label, max_move in POLICIES:
        points = []
        for n in run.plan.samples:
            baked = run.lattice(samples=n, max_move=max_move)
            key = run.render(f"levels/{label}/{n}", "irradiance", baked.lattice)
            plan = baked.lattice.meta["plan"]
            points.append({"samples": n, "seconds": baked.seconds, "image": key,
                           "levels": len(plan["levels"]),
                           "move_limit_voxels": plan["move_limit_voxels"],
                           **run.summary(baked)})
        series[label] = points
    return Chart("chart5_levels", "error against bake time per level policy",
                 {"series": series, "x": "seconds (wall)", "y": "relative RMSE"})


def plot_levels(record: dict[str, Any], path: Path) -> None:
    """Log–log error against seconds, one line per policy, points labelled by samples
    and level count."""
    plt, fig, (ax,) = figure()
    styles = {"auto": ("o-", "automatic (from samples and cost)"),
              "0.25 voxel": ("v--", "fixed: move <= 0.25 voxel"),
              "0.5 voxel": ("s--", "fixed: move <= 0.5 voxel"),
              "1 voxel": ("D--", "fixed: move <= 1 voxel"),
              "2 voxels": ("^--", "fixed: move <= 2 voxels")}
    for label, points in record["series"].items():
        points = [p for p in points if p.get("error") is not None]
        if not points:
            continue
        style, name = styles.get(label, ("x:", label))
        ax.plot([p["seconds"] for p in points], [p["error"] for p in points], style,
                label=name, lw=2.5 if label == "auto" else 1.2)
        for p in points:
            ax.annotate(f"{p['samples']}·{p['levels']}L", (p["seconds"], p["error"]),
                        fontsize=6, xytext=(3, 3), textcoords="offset points")
    noise_line(ax, record)
    ax.set_xscale("log")
    ax.set_yscale("log")
    plain_log_ticks(ax)
    ax.set_xlabel("bake wall time, s (plan, level scenes, tracing; fixed limits: the resumed "
                  "chain's sum)")
    ax.set_ylabel("relative RMSE against path tracing")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.text(0.01, 0.01, "labels: paths per texel · levels", transform=ax.transAxes,
            fontsize=6, color="0.4")
    finish(plt, fig, record, path)
