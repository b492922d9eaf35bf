"""Plotting for ``isolume chart``: the figure helpers every chart uses (`figure`, `finish`,
`noise_line`, `plain_log_ticks`, `percent`) and the plots of charts 1-4, each drawn from
the chart's JSON record into a PNG (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def figure(ncols: int = 1) -> tuple[ModuleType, Figure, list[Axes]]:
    """(pyplot, figure, axes): one row of `ncols` 6.4 × 4.8 inch panels (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(6.4 * ncols, 4.8), squeeze=False)
    return plt, fig, list(axes[0])


def _subtitle(record: dict) -> str:
    """Two lines on the scene and the reference of a chart's JSON `record`."""
    s, r = record["settings"], record["reference"]
    return (f"{Path(s['volume']).name} iso {s['iso']:.4g}, {s['env']}, {s['bounces']} bounces, "
            f"albedo {s['albedo']:g}\n{s['size'][0]}x{s['size'][1]} px; reference {r['spp']} "
            f"spp, noise {r['noise']:.2%} ({'meets' if r['holds'] else 'misses'} the 1/4 rule)")


def finish(plt: ModuleType, fig: Figure, record: dict[str, Any], path: Path) -> None:
    """Title `fig` from `record` (title, scene, reference), save it to `path` (PNG, 110
    dpi) and close it."""
    fig.suptitle(f"{record['title']}\n{_subtitle(record)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def noise_line(ax: Axes, record: dict[str, Any]) -> None:
    """A dotted horizontal line at the reference's relative noise."""
    ax.axhline(record["reference"]["noise"], color="0.6", ls=":", lw=1,
               label="reference noise")


def plain_log_ticks(ax: Axes, axes: str = "xy", subs: tuple[float, ...] = (1.0, 2.0, 5.0),
                    text: str = "{:g}") -> None:
    """Log axes ticked at `subs` × 10ⁿ (1, 2, 5) and labelled as `text` formats the value
    (0.1, 0.2, 0.5, not 10⁻¹ ...)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for name in axes:
        axis = ax.xaxis if name == "x" else ax.yaxis
        axis.set_major_locator(LogLocator(base=10, subs=subs, numticks=30))
        axis.set_major_formatter(FuncFormatter(lambda v, _: text.format(v)))
        axis.set_minor_formatter(NullFormatter())


def plot_bake_time(record: dict[str, Any], path: Path) -> None:
    """Log–log error against seconds, one line per method, points labelled by samples."""
    plt, fig, (ax,) = figure()
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
    noise_line(ax, record)
    plain_log_ticks(ax)
    ax.set_xlabel("wall time, s (bake, or path tracing); labels: paths per texel, spp")
    ax.set_ylabel("relative RMSE of radiance")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    finish(plt, fig, record, path)


def plot_resolution(record: dict[str, Any], path: Path) -> None:
    """Error and texture memory against lattice scale."""
    plt, fig, (ax, mem) = figure(2)
    pts = record["points"]
    scales = [p["scale"] for p in pts]
    ax.plot(scales, [p["error"] for p in pts], "o-", label="irradiance lattice")
    noise_line(ax, record)
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
        ax.annotate(percent(p["error"]) + note, (p["scale"], p["error"]), **where)
        mem.annotate(f"{p['memory_bytes'] / 2**20:.3g} MiB, bake {p['bake_seconds']:.3g} s",
                     (p["scale"], p["memory_bytes"] / 2**20), **where)
    for a in (ax, mem):
        a.set_xscale("log", base=2)
        a.set_xticks(scales, [f"{s:g}x" for s in scales])
        a.set_xlabel(f"lattice texels per voxel along the finest axis "
                     f"({record['samples']} paths/texel)")
        a.grid(True, which="both", alpha=0.3)
        a.margins(x=0.2)
    ax.legend(fontsize=8)
    finish(plt, fig, record, path)


def percent(value: float) -> str:
    """A relative error as a percentage with two significant digits at least."""
    return f"{value:.2%}" if value >= 1e-3 or value == 0 else f"{100 * value:.2g}%"


def _bars(ax, labels: list[str], errors: list[float], colour: str) -> None:
    """One labelled bar per error (None drawn as 0)."""
    values = [e if e is not None else 0.0 for e in errors]
    ax.bar(range(len(values)), values, color=colour)
    ax.set_xticks(range(len(values)), labels, fontsize=8)
    for i, v in enumerate(values):
        ax.annotate(percent(v), (i, v), ha="center", fontsize=8, xytext=(0, 2),
                    textcoords="offset points")
    ax.set_ylabel("relative RMSE of radiance")
    ax.grid(True, axis="y", alpha=0.3)


def plot_lookup_normals(record: dict[str, Any], path: Path) -> None:
    """Bars: error per lookup scheme, error per normal scheme."""
    plt, fig, (ax, nx) = figure(2)
    _bars(ax, [e["lookup"] for e in record["lookups"]],
          [e["error"] for e in record["lookups"]], "C0")
    ax.set_title(f"lattice lookup ({record['samples']} paths/texel)", fontsize=9)
    _bars(nx, [e["scheme"] for e in record["normals"]],
          [e["error"] for e in record["normals"]], "C2")
    nx.set_title("texel normals (trilinear lookup)", fontsize=9)
    for a in (ax, nx):
        noise_line(a, record)
        a.legend(fontsize=8)
    finish(plt, fig, record, path)


KIND_COLOURS = {"local": "C3", "irradiance": "C0", "sh": "C2", "occlusion": "C1"}
KIND_LABELS = {"local": "local model", "irradiance": "irradiance lattice",
               "sh": "SH lattice", "occlusion": "occlusion lattice (constant sky, no bounce)"}


def plot_shading_modes(record: dict[str, Any], path: Path) -> None:
    """One row per shading mode, best first: error (log) and frame time side by side, so
    local models and lattices share both axes."""
    plt, fig, (ax, ft) = figure(2)
    modes = sorted((m for m in record["modes"] if m.get("error") is not None),
                   key=lambda m: m["error"])
    rows = np.arange(len(modes))[::-1]
    colours = [KIND_COLOURS.get(m["kind"], "k") for m in modes]
    floor = 1e-6  # exact images (error 0) still get a visible bar on the log axis
    ax.barh(rows, [max(m["error"], floor) for m in modes], color=colours)
    ax.set_xscale("log")
    plain_log_ticks(ax, "x")
    ax.set_yticks(rows, [m["mode"] for m in modes], fontsize=8)
    for r, m in zip(rows, modes, strict=True):
        ax.annotate(percent(m["error"]), (max(m["error"], floor), r), fontsize=7,
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
    finish(plt, fig, record, path)
