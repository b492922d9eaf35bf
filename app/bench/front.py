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
chosen on. Each sweep that is not uniform is set against the uniform ones
(`against_uniform`): how many times its paths the cheapest uniform sweep as accurate
(median, p90, worst, and cases with black pixels) traces, and the uniform curve's paths
at its median. Writes ``FILE.png`` and ``FILE.json`` (every number plotted, the
comparisons and the per-case figures) and prints the table and the comparisons.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import textwrap
from pathlib import Path
from typing import Any

from isolume.app.bench.accuracy_metrics import BLACK_LIMIT, RATIO_BAND, share, spread
from isolume.app.render.images import output_folder
from isolume.volumes.errors import IsolumeError

HELP = "the bake's error against paths, time and bytes over several bench accuracy sweeps"
FIGURES = (("paths", "paths traced, millions", 1e-6), ("bake_seconds", "bake wall time, s", 1.0),
           ("lattice_bytes", "lattice files, MB", 1e-6))
"""(row key, axis label, scale) of the panels."""
WITHIN = 0.005
"""Relative RMSE a sweep may add to the baseline's in a case beyond that case's reference
noise (``--baseline``): the rule a new default meets against the old."""


class FrontError(IsolumeError):
    """A sweep folder that cannot be read or holds no bake case (the message says which)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``isolume bench front``."""
    p.add_argument("sweeps", nargs="+", metavar="DIR",
                   help="bench accuracy --out folders (each holds accuracy.json)")
    p.add_argument("--baseline", metavar="DIR",
                   help="a sweep (added to the others if not among them) every other is "
                   "checked against case by case: its error within the case's reference "
                   "noise + 0.5 %%, black pixels and mean ratio within the sweep's limits")
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


def front(sweeps: list[dict[str, Any]], baseline: dict[str, Any] | None = None
          ) -> dict[str, Any]:
    """The points of `sweeps` (`read_sweep`) over the cases they share: per sweep its
    error spread and the sums of `FIGURES`, per case every sweep's error and paths, the
    sweeps that are not uniform against the uniform ones (`against_uniform`), and with a
    `baseline` (one of `sweeps`) every other against it (`against_baseline`)."""
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
                       **{key: sum(share(r, key) if r.get(key) else 0 for r in rows)
                          for key, _, _ in FIGURES}})
    per_case = [{"volume": v, "iso": iso,
                 "error": {s["label"]: s["rows"][(v, iso)]["rel_rmse_less_noise"]
                           for s in sweeps},
                 "reference_noise": sweeps[0]["rows"][(v, iso)]["reference_noise"],
                 "paths": {s["label"]: share(s["rows"][(v, iso)], "paths") for s in sweeps}}
                for v, iso in cases]
    left_out = sorted({c for s in sweeps for c in s["rows"]} - shared)
    return {"points": points, "against_uniform": against_uniform(points),
            "against_baseline": ([] if baseline is None
                                 else against_baseline(sweeps, baseline, cases)),
            "cases": per_case,
            "left_out": [{"volume": v, "iso": iso} for v, iso in left_out]}


def against_baseline(sweeps: list[dict[str, Any]], baseline: dict[str, Any],
                     cases: list[tuple[str, float]]) -> list[dict[str, Any]]:
    """Every other sweep of `sweeps` against `baseline` (one of them) over `cases`: the
    cases it fails — an error above the baseline's by more than the case's reference noise
    + `WITHIN` (or not finite), more than `BLACK_LIMIT` black pixels, a mean ratio outside
    `RATIO_BAND` — its smallest margin to the first rule and that case, and its paths over
    the baseline's."""
    out = []
    for sweep in sweeps:
        if sweep is baseline:
            continue
        margins, failed = [], []
        for case in cases:
            mine, theirs = sweep["rows"][case], baseline["rows"][case]
            margin = (theirs["rel_rmse_less_noise"] + theirs["reference_noise"] + WITHIN
                      - mine["rel_rmse_less_noise"])
            if math.isfinite(margin):
                margins.append((margin, case))
            if (not margin >= 0 or mine["black_fraction"] > BLACK_LIMIT
                    or not RATIO_BAND[0] <= mine["mean_ratio"] <= RATIO_BAND[1]):
                failed.append({"volume": case[0], "iso": case[1]})
        smallest, (volume, iso) = min(margins, default=(math.nan, ("", math.nan)))
        out.append({"label": sweep["label"], "baseline": baseline["label"],
                    "cases": len(cases), "failed": failed, "smallest_margin": smallest,
                    "smallest_at": {"volume": volume, "iso": iso},
                    "paths_ratio": (sum(share(sweep["rows"][c], "paths") for c in cases)
                                    / max(sum(share(baseline["rows"][c], "paths")
                                              for c in cases), 1))})
    return out


def is_uniform(point: dict[str, Any]) -> bool:
    """Whether a point is a uniform sweep (exactly N paths a texel, any scale)."""
    return point["kind"].split(",")[0] == "uniform"


def against_uniform(points: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each sweep of `points` (`front`) that is not uniform, against the uniform ones: the
    cheapest in paths whose median, p90, worst and cases with black pixels are each at
    most its own (None: none is), and the paths the uniform sweeps at scale 1 trace at its
    median, read off their curve (log-linear in paths between the two around it; None
    outside it)."""
    uniform = [p for p in points if is_uniform(p)]
    curve = sorted((p for p in uniform if p["kind"] == "uniform"), key=lambda p: p["paths"])
    out = []
    for point in points:
        if is_uniform(point):
            continue
        as_good = [u for u in uniform if all(u[stat] <= point[stat] for stat in
                                             ("median", "p90", "worst", "black_cases"))]
        cheapest = min(as_good, key=lambda u: u["paths"], default=None)
        out.append({"label": point["label"], "paths": point["paths"],
                    "cheapest_as_good": None if cheapest is None else cheapest["label"],
                    "its_paths": None if cheapest is None else cheapest["paths"],
                    "at_median_paths": _paths_at(curve, point["median"])})
    return out


def _paths_at(curve: list[dict[str, Any]], median: float) -> float | None:
    """Paths at which the (paths-sorted) `curve` of uniform sweeps has the error `median`:
    log-linear between two neighbours whose medians bracket it, or None."""
    for a, b in itertools.pairwise(curve):
        low, high = sorted((a["median"], b["median"]))
        if low <= median <= high and low < high:
            t = (a["median"] - median) / (a["median"] - b["median"])
            return float(math.exp(math.log(a["paths"]) + t * (math.log(b["paths"])
                                                               - math.log(a["paths"]))))
    return None


def comparison_lines(record: dict[str, Any]) -> list[str]:
    """`against_uniform`'s and `against_baseline`'s figures as text lines."""
    lines = []
    for c in record["against_baseline"]:
        at = c["smallest_at"]
        lines.append(f"{c['label']} against {c['baseline']}: {len(c['failed'])} of "
                     f"{c['cases']} cases beyond its error + the reference's noise + "
                     f"{WITHIN:.1%}, its black pixels or mean ratio limits; smallest margin "
                     f"{100 * c['smallest_margin']:.2f} points ({at['volume']} at "
                     f"{at['iso']:g}); "
                     f"{c['paths_ratio']:.3f}x its paths")
    for c in record["against_uniform"]:
        if c["cheapest_as_good"] is None:
            best = "no uniform sweep is as accurate (median, p90, worst, black cases)"
        else:
            best = (f"the cheapest uniform sweep as accurate (median, p90, worst, black "
                    f"cases): {c['cheapest_as_good']}, {c['its_paths'] / c['paths']:.2f}x "
                    "its paths")
        at = ("" if c["at_median_paths"] is None else
              f"; uniform paths at its median: {c['at_median_paths'] / c['paths']:.2f}x")
        lines.append(f"{c['label']}: {best}{at}")
    return lines


def plot(record: dict[str, Any], path: Path) -> None:
    """Three log-log panels (paths, seconds, bytes) of the error's median, p90 and worst,
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
            for i, (p, xv) in enumerate(zip(pts, x, strict=True)):
                ax.annotate(p["label"].split(" (")[0], (xv, p["median"]), fontsize=6,
                            xytext=(2, -9 if i % 2 == 0 else 4), textcoords="offset points")
        plain_log_ticks(ax, "x")
        ax.set_yscale("log")
        plain_log_ticks(ax, "y", (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0), "{:.0%}")
        ax.set_xlabel(f"{label}, summed over the {len(record['cases'])} cases")
        ax.set_ylabel("relative RMSE less the reference's noise")
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=7)
    names = ", ".join(sorted({c["volume"] for c in record["cases"]}))
    fig.suptitle("bake error against cost: uniform paths, paths where the noise is, "
                 "texels where the light varies, lattice scales\n"
                 + textwrap.fill(names, 230), fontsize=9)
    fig.tight_layout(rect=(0, 0.04 * (1 + (len(labels) - 1) // 6), 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(record: dict[str, Any]) -> list[str]:
    """The points as text lines."""
    lines = [f"{'sweep':28s} {'median':>7s} {'p90':>7s} {'worst':>7s} {'paths':>14s} "
             f"{'bake s':>8s} {'MB':>8s} {'black':>5s}"]
    for p in sorted(record["points"], key=lambda p: (p["kind"], p["paths"])):
        lines.append(f"{p['label'][:28]:28s} {p['median']:7.2%} {p['p90']:7.2%} "
                     f"{p['worst']:7.2%} {p['paths']:14,.0f} {p['bake_seconds']:8.1f} "
                     f"{p['lattice_bytes'] / 1e6:8.2f} {p['black_cases']:5d}")
    return lines


def run(args: argparse.Namespace) -> int:
    """Read the sweeps, print the table, write the chart and its JSON.

    Raises:
        CLIError: a sweep that cannot be read, or sweeps without a shared case.
    """
    from isolume.app.options import CLIError

    folders = [Path(d).expanduser() for d in args.sweeps]
    base = None if args.baseline is None else Path(args.baseline).expanduser()
    if base is not None and base not in folders:
        folders.append(base)
    try:
        sweeps = [read_sweep(folder) for folder in folders]
        record = front(sweeps, None if base is None else sweeps[folders.index(base)])
    except FrontError as exc:
        raise CLIError(str(exc)) from None
    out = Path(args.out).expanduser()
    output_folder(out.parent)
    for line in table(record) + comparison_lines(record):
        print(line)
    if record["left_out"]:
        print(f"left out: {len(record['left_out'])} cases not in every sweep")
    plot(record, out)
    out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    print(f"wrote {out} and {out.with_suffix('.json')}")
    return 0
