"""The files of ``isolume chart``: per chart, ``NAME.json`` with every number it plots
plus the settings that made it and the reference rule, and ``NAME.png`` drawn from that
record."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from isolume.app.charts.levels import plot_levels
from isolume.app.charts.metrics import image_entries
from isolume.app.charts.model import Chart
from isolume.app.charts.plotting import (
    plot_bake_time,
    plot_lookup_normals,
    plot_resolution,
    plot_shading_modes,
)

PLOTTERS: dict[str, Callable[[dict[str, Any], Path], None]] = {
    "chart1_bake_time": plot_bake_time, "chart2_resolution": plot_resolution,
    "chart3_lookup_normals": plot_lookup_normals,
    "chart4_shading_modes": plot_shading_modes, "chart5_levels": plot_levels}
"""Chart name → plot(record, png path)."""


def jsonable(node: object) -> Any:
    """`node` with numpy scalars and tuples made JSON-ready and non-finite floats None."""
    if isinstance(node, dict):
        return {str(k): jsonable(v) for k, v in node.items()}
    if isinstance(node, list | tuple):
        return [jsonable(v) for v in node]
    if isinstance(node, np.generic):
        node = node.item()
    if isinstance(node, float) and not math.isfinite(node):
        return None
    return node


def write_chart(chart: Chart, out: Path, settings: dict[str, Any],
                reference: dict[str, Any]) -> Path:
    """Write ``NAME.json`` (numbers, settings, reference rule) and ``NAME.png``."""
    chart_errors = [e["error"] for e in image_entries(chart.data) if e.get("error") is not None]
    record = {"chart": chart.name, "title": chart.title, "png": f"{chart.name}.png",
              "settings": settings,
              "reference": {**reference, "smallest_error_in_this_chart":
                            min(chart_errors) if chart_errors else None},
              **chart.data}
    record = jsonable(record)
    (out / f"{chart.name}.json").write_text(json.dumps(record, indent=2) + "\n")
    png = out / f"{chart.name}.png"
    PLOTTERS[chart.name](record, png)
    return png

