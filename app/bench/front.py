"""``isolume bench front``: the bake's error against its cost, over several accuracy sweeps.

Each ``bench accuracy`` sweep (its ``--out`` folder's ``accuracy.json``) with other bake
settings — ``--paths N`` (exactly N paths a texel) or ``--target-error E`` (paths where
the noise is, `baking.adaptive`), at a lattice ``--scale``, with or without
``--texel-error E`` (texels where the light varies, `baking.density`) — is one point: over the bake
cases every sweep measured (the same volumes and isovalues; cases missing from any sweep
are left out, and said), the median, 90th percentile and worst relative RMSE less the
reference's noise against the summed paths traced, bake wall time and lattice file bytes.
Sweeps of one kind (uniform or target, at one scale, with or without a texel error) are
joined by a line, cheapest first: the front of speed against accuracy the defaults are
chosen on. Writes ``FILE.png`` and
``FILE.json`` (every number plotted and the per-case figures) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from isolume.app.bench.accuracy_metrics import BLACK_LIMIT, spread
from isolume.volumes.errors import IsolumeError

HELP = "the bake's error against paths, time and bytes over several bench accuracy sweeps"
FIGURES = (("paths", "paths traced, millions", 1e-6), ("bake_seconds", "bake wall time, s", 1.0),
           ("lattice_bytes", "lattice files, MB", 1e-6))
"""(row key, axis label, scale) of the panels."""


class FrontError(IsolumeError):
    """A sweep folder that cannot be read or holds no bake case (the message says which)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume bench front``."""
    p.add_argument("sweeps", nargs="+", metavar="DIR",
                   help="bench accuracy --out folders (each holds accuracy.json)")
    p.add_argument("--out", required=True, metavar="FILE.png",
                   help="the chart (FILE.json beside it holds its numbers)")


def read_sweep(folder: Path) -> dict[str, Any]:
    """One sweep: its label, kind ("uniform" or "target") and bake rows by case.

    Raises:
        FrontError: no readable accuracy.json, or no bake case in it.
    """
    path = folder / "accuracy.json"
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FrontError(f"{path}: not a readable bench accuracy result ({exc})") from None
    rows = {(r["volume"], round(float(r["iso"]), 6)): r for r in document.get("rows", [])
            if r.get("mode") == "bake" and r.get("paths") is not None}
    if not rows:
        raise FrontError(f"{path}: holds no bake case with its paths (a sweep of --skip-bake, "
                         "or one made before paths were recorded)")
    first = next(iter(rows.values()))
    target, scale = first.get("target_error"), float(first.get("scale", 1.0))
    texel = first.get("texel_error")
    kind = "uniform" if target is None else "target"
    label = (f"{first['samples']} paths" if target is None
             else f"target {target:g} (from {first['samples']})")
    if texel is not None:
        kind, label = f"texels, {kind}", f"{label}, texel error {texel:g}"
    if scale != 1.0:
        kind, label = f"{kind}, scale {scale:g}", f"{label} x{scale:g}"
    return {"folder": str(folder), "label": label, "kind": kind, "target_error": target,
            "texel_error": texel, "samples": first["samples"], "scale": scale, "rows": rows}


def front(sweeps: list[dict[str, Any]]) -> dict[str, Any]:
    """The points of `sweeps` (`read_sweep`) over the cases they share: per sweep its
    error spread and the sums of `FIGURES`, and per case every sweep's error and paths."""
    shared = set.intersection(*(set(s["rows"]) for s in sweeps))
    if not shared:
        raise FrontError("the sweeps share no bake case (volume and isovalue): run them on "
                         "the same volumes")
    cases = sorted(shared)
    points = []
    for sweep in sweeps:
        rows = [sweep["rows"][c] for c in cases]
        errors = [r["rel_rmse_less_noise"] for r in rows
                  if math.isfinite(r["rel_rmse_less_noise"])]
        points.append({"label": sweep["label"], "kind": sweep["kind"],
                       "folder": sweep["folder"], "samples": sweep["samples"],
                       "target_error": sweep["target_error"],
                       "texel_error": sweep["texel_error"], "scale": sweep["scale"],
                       **spread(errors),
                       "black_cases": sum(r["black_fraction"] > BLACK_LIMIT for r in rows),
                       **{key: sum(r.get(key) or 0 for r in rows) for key, _, _ in FIGURES}})
    per_case = [{"volume": v, "iso": iso,
                 "error": {s["label"]: s["rows"][(v, iso)]["rel_rmse_less_noise"]
                           for s in sweeps},
                 "reference_noise": sweeps[0]["rows"][(v, iso)]["reference_noise"],
                 "paths": {s["label"]: s["rows"][(v, iso)]["paths"] for s in sweeps}}
                for v, iso in cases]
    left_out = sorted({c for s in sweeps for c in s["rows"]} - shared)
    return {"points": points, "cases": per_case,
            "left_out": [{"volume": v, "iso": iso} for v, iso in left_out]}


def plot(record: dict[str, Any], path: Path) -> None:
    """Three log-x panels (paths, seconds, bytes) of the error's median, p90 and worst,
    one line per kind of sweep."""
    from isolume.app.charts.plotting import figure, plain_log_ticks

    plt, fig, axes = figure(len(FIGURES))
    kinds = list(dict.fromkeys(p["kind"] for p in record["points"]))
    colours = dict(zip(kinds, plt.rcParams["axes.prop_cycle"].by_key()["color"],
                       strict=False))
    for ax, (key, label, scale) in zip(axes, FIGURES, strict=True):
        for kind, colour in colours.items():
            pts = sorted((p for p in record["points"] if p["kind"] == kind),
                         key=lambda p: p[key])
            if not pts:
                continue
            x = [p[key] * scale for p in pts]
            for stat, style in (("median", "o-"), ("p90", "s--"), ("worst", "^:")):
                ax.semilogx(x, [p[stat] for p in pts], style, color=colour, ms=4,
                            label=f"{kind}: {stat}")
            for p, xv in zip(pts, x, strict=True):
                ax.annotate(p["label"].split(" (")[0], (xv, p["median"]), fontsize=6,
                            xytext=(2, -9), textcoords="offset points")
        plain_log_ticks(ax, "x")
        ax.set_xlabel(f"{label}, summed over the {len(record['cases'])} cases")
        ax.set_ylabel("relative RMSE less the reference's noise")
        ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:.1%}"))
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    names = sorted({c["volume"] for c in record["cases"]})
    fig.suptitle("bake error against cost: uniform paths, paths where the noise is, "
                 "texels where the light varies, lattice scales\n"
                 f"{', '.join(names)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(record: dict[str, Any]) -> list[str]:
    """The points as text lines."""
    lines = [f"{'sweep':28s} {'median':>7s} {'p90':>7s} {'worst':>7s} {'paths':>14s} "
             f"{'bake s':>8s} {'MB':>8s} {'black':>5s}"]
    for p in sorted(record["points"], key=lambda p: (p["kind"], p["paths"])):
        lines.append(f"{p['label'][:28]:28s} {p['median']:7.2%} {p['p90']:7.2%} "
                     f"{p['worst']:7.2%} {p['paths']:14,d} {p['bake_seconds']:8.1f} "
                     f"{p['lattice_bytes'] / 1e6:8.2f} {p['black_cases']:5d}")
    return lines


def run(args: argparse.Namespace) -> int:
    """Read the sweeps, print the table, write the chart and its JSON.

    Raises:
        CLIError: a sweep that cannot be read, or sweeps without a shared case.
    """
    from isolume.app.options import CLIError

    try:
        record = front([read_sweep(Path(d).expanduser()) for d in args.sweeps])
    except FrontError as exc:
        raise CLIError(str(exc)) from None
    out = Path(args.out).expanduser()
    out.parent.mkdir(parents=True, exist_ok=True)
    for line in table(record):
        print(line)
    if record["left_out"]:
        print(f"left out: {len(record['left_out'])} cases not in every sweep")
    plot(record, out)
    out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    print(f"wrote {out} and {out.with_suffix('.json')}")
    return 0
