"""What ``isolume bench accuracy`` writes: the table (printed row by row and saved as
``table.txt``), ``accuracy.json`` and the contact sheet ``accuracy.png`` (one row per case:
picture | reference | signed error map); `Report` gathers them as the cases come."""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from isolume.app.bench.accuracy_metrics import LUMINANCE, NOISE_RATIO, TOTALS, summarize
from isolume.volumes.errors import IsolumeError

ERROR_LIMIT = 0.25
"""The error map's colour scale: ± this fraction of the reference's mean luminance."""
BACKGROUND = (46, 50, 56)
"""sRGB of the pixels off the surface in the contact sheet."""
LABEL_WIDTH = 260
"""Pixels of the label column of the contact sheet."""

_COLUMNS = (("volume", 24, "s"), ("iso", 9, "iso"), ("mode", 6, "s"), ("rel RMSE", 9, "%"),
            ("less noise", 10, "%"), ("ref noise", 9, "%"), ("ratio", 6, ".3f"),
            ("black", 7, "%"), ("p99", 7, "%"), ("render s", 8, ".1f"), ("bake s", 7, ".1f"),
            ("ref s", 6, ".1f"), ("ref spp", 7, "d"), ("paths/tx", 8, ".1f"))
_KEYS = ("volume", "iso", "mode", "rel_rmse", "rel_rmse_less_noise", "reference_noise",
         "mean_ratio", "black_fraction", "p99_error", "render_seconds", "bake_seconds",
         "reference_seconds", "reference_spp", "paths_per_texel")


def _cell(value, width: int, form: str) -> str:
    """One table cell, right-aligned except text; '-' for a missing number."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return f"{'-':>{width}}"
    if form == "s":
        return f"{str(value)[:width]:<{width}}"
    if form == "%":
        return f"{value:>{width}.2%}"
    if form == "iso":
        return f"{value:>{width}.5g}"
    return f"{value:>{width}{form}}"


def table_header() -> str:
    """The table's column titles."""
    return " ".join(f"{name:<{w}}" if form == "s" else f"{name:>{w}}"
                    for name, w, form in _COLUMNS)


def table_row(row: dict[str, Any]) -> str:
    """One case as a table line; a '*' ends the line where the reference's noise exceeds
    `NOISE_RATIO` × the error less the noise (the sample cap was reached)."""
    line = " ".join(_cell(row.get(key), w, form)
                    for key, (_, w, form) in zip(_KEYS, _COLUMNS, strict=True))
    return line + ("" if row.get("noise_rule_holds", True) else " *")


def _pct(value) -> str:
    return "-" if value is None else f"{value:.2%}"


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The summary printed after the table."""
    lines = []
    for mode, figures in summary["modes"].items():
        c, raw = figures["rel_rmse_less_noise"], figures["rel_rmse"]
        worst = figures["worst_case"]
        lines.append(f"{mode:6s} {figures['cases']:3d} cases: relative RMSE less the "
                     f"reference's noise median {_pct(c['median'])}, p90 {_pct(c['p90'])}, "
                     f"worst {_pct(c['worst'])} ({worst['volume']} at iso "
                     f"{worst['iso']:.5g}); plain median {_pct(raw['median'])}, "
                     f"p90 {_pct(raw['p90'])}, worst {_pct(raw['worst'])}")
        if all(f"total_{key}" in figures for key in TOTALS):
            lines.append(f"{mode:6s} totals: {figures['total_paths']:,.0f} paths, "
                         f"{figures['total_bake_seconds']:.1f} s of bakes, "
                         f"{figures['total_lattice_bytes'] / 1e6:.2f} MB of lattice files")
    lo, hi = summary["ratio_band"]
    lines.append(f"black fraction > {summary['black_limit']:.1%}: {summary['black_cases']} "
                 f"of {summary['cases']} cases; mean ratio outside {lo:g}-{hi:g}: "
                 f"{summary['ratio_cases']}; reference noise above {NOISE_RATIO:g} x the "
                 f"error (*): {summary['noise_rule_unmet']}; failed: {summary['failures']}")
    return lines


def write_json(path: Path, document: dict[str, Any]) -> None:
    """Write `document` (settings, rows, failures, summary) as indented JSON."""
    path.write_text(json.dumps(document, indent=1, default=_plain) + "\n")


def _plain(value):
    """JSON form of numpy scalars and arrays."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON-ready: {type(value).__name__}")


# -- the contact sheet -------------------------------------------------------------------
@dataclass
class Tile:
    """One row of the contact sheet.

    Attributes:
        label: lines of text (volume, isovalue, mode, errors).
        image, reference, error: (H, W, 3) uint8 sRGB pictures.
    """

    label: list[str]
    image: np.ndarray
    reference: np.ndarray
    error: np.ndarray


def display(linear: np.ndarray, mask: np.ndarray, size: tuple[int, int],
            scale: float) -> np.ndarray:
    """(H, W, 3) uint8 of (N, 3) linear radiance as the renderer shows it: times `scale`
    (the exposure), the ACES curve (Narkowicz fit, as ``tonemap.frag``), sRGB; off the
    (N,) `mask` the sheet's background."""
    x = np.maximum(np.asarray(linear, np.float64) * scale, 0.0)
    tone = np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    srgb = np.where(tone <= 0.0031308, 12.92 * tone, 1.055 * tone ** (1 / 2.4) - 0.055)
    out = np.round(srgb * 255).astype(np.uint8)
    out[~mask] = BACKGROUND
    w, h = size
    return out.reshape(h, w, 3)


def error_map(image: np.ndarray, reference: np.ndarray, mask: np.ndarray,
              size: tuple[int, int], limit: float = ERROR_LIMIT) -> np.ndarray:
    """(H, W, 3) uint8 of the signed luminance error (img − ref) / mean(ref) on the (N,)
    reference surface `mask`, in diverging colours (blue: too dark, red: too bright,
    saturated at ± `limit`); off the surface the sheet's background."""
    from matplotlib import colormaps

    lum_img, lum_ref = image @ LUMINANCE, reference @ LUMINANCE
    mean = float(np.mean(lum_ref[mask])) if mask.any() else 1.0
    signed = (lum_img - lum_ref) / max(mean, 1e-30)
    colours = colormaps["RdBu_r"](np.clip(0.5 + 0.5 * signed / limit, 0.0, 1.0))[:, :3]
    out = np.round(colours * 255).astype(np.uint8)
    out[~mask] = BACKGROUND
    w, h = size
    return out.reshape(h, w, 3)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # no FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _fit(picture: np.ndarray, side: int):
    """`picture` as a PIL image `side` pixels high (nearest neighbour: pixels stay
    pixels)."""
    from PIL import Image

    h, w = picture.shape[:2]
    width = max(1, round(w * side / h))
    return Image.fromarray(picture).resize((width, side), Image.Resampling.NEAREST)


def _header(width: int, side: int, columns: list[int], draw_font, limit: float):
    """The sheet's title strip: column names and the error map's colour bar."""
    from matplotlib import colormaps
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (width, 44), (255, 255, 255))
    draw = ImageDraw.Draw(strip)
    draw.text((6, 4), "volume, isovalue, mode", fill=(0, 0, 0), font=draw_font)
    draw.text((6, 22), "rel RMSE (less ref noise)", fill=(90, 90, 90), font=draw_font)
    for x, title in zip(columns, ("picture", "reference", "error / mean"), strict=True):
        draw.text((x + 2, 4), title, fill=(0, 0, 0), font=draw_font)
    bar_x, bar_w = columns[2], max(side - 4, 16)
    ramp = colormaps["RdBu_r"](np.linspace(0, 1, bar_w))[:, :3]
    bar = np.repeat(np.round(ramp * 255).astype(np.uint8)[None], 6, axis=0)
    strip.paste(Image.fromarray(bar), (bar_x + 2, 20))
    draw.text((bar_x + 2, 28), f"-{limit:.0%}", fill=(0, 0, 0), font=draw_font)
    draw.text((bar_x + bar_w - 30, 28), f"+{limit:.0%}", fill=(0, 0, 0), font=draw_font)
    return strip


def contact_sheet(path: Path, tiles: list[Tile], limit: float = ERROR_LIMIT) -> None:
    """Write the contact sheet: a title strip, then per tile its label, picture,
    reference and error map side by side, each scaled to 96–160 pixels high."""
    from PIL import Image, ImageDraw

    if not tiles:
        return
    font = _font(13)
    h = tiles[0].image.shape[0]
    side = int(min(max(h, 96), 160))
    width0 = _fit(tiles[0].image, side).width
    gap = 4
    columns = [LABEL_WIDTH + i * (width0 + gap) for i in range(3)]
    width = columns[-1] + width0 + gap
    header = _header(width, width0, columns, font, limit)
    sheet = Image.new("RGB", (width, header.height + len(tiles) * (side + gap)),
                      (255, 255, 255))
    sheet.paste(header, (0, 0))
    draw = ImageDraw.Draw(sheet)
    for i, tile in enumerate(tiles):
        top = header.height + i * (side + gap)
        for line_no, line in enumerate(tile.label):
            draw.text((6, top + 4 + 17 * line_no), line, fill=(0, 0, 0), font=font)
        for x, picture in zip(columns, (tile.image, tile.reference, tile.error), strict=True):
            sheet.paste(_fit(picture, side), (x, top))
    sheet.save(path, optimize=True)


# -- the report -------------------------------------------------------------------------
class Report:
    """Rows, failures and tiles as they come; the table on stdout; the files in `out`."""

    out: Path
    settings: dict[str, Any]
    began: float

    def __init__(self, out: Path, settings: dict[str, Any]) -> None:
        self.out, self.settings = out, settings
        self.rows: list[dict[str, Any]] = []
        self.failures: list[dict[str, Any]] = []
        self.tiles: list[Tile] = []
        self.lines: list[str] = []
        self.began = time.perf_counter()

    def say(self, line: str) -> None:
        """A line of the table: printed now, kept for table.txt."""
        print(line, flush=True)
        self.lines.append(line)

    def add(self, rows: list[dict[str, Any]], tiles: list[Tile]) -> None:
        for row in rows:
            self.say(table_row(row))
        self.rows += rows
        self.tiles += tiles

    def fail(self, volume: str, iso: float | None, exc: BaseException) -> None:
        """One line on stderr and a failure record."""
        message = " ".join(str(exc).split())
        if not isinstance(exc, IsolumeError):
            message = f"{type(exc).__name__}: {message}"
        where = volume if iso is None else f"{volume} at iso {iso:.6g}"
        print(f"isolume: bench accuracy: {where}: skipped: {message}", file=sys.stderr,
              flush=True)
        self.failures.append({"volume": volume, "iso": iso, "error": message})

    def save(self, final: bool = False) -> dict[str, Any]:
        """Write accuracy.json and table.txt (and, when `final`, accuracy.png); returns
        the summary."""
        summary = summarize(self.rows, self.failures)
        wall = time.perf_counter() - self.began
        lines = [*self.lines, "", *summary_lines(summary), f"wall time {wall:.0f} s"]
        lines += [f"failed: {f['volume']}" + ("" if f["iso"] is None else f" at iso "
                  f"{f['iso']:.6g}") + f": {f['error']}" for f in self.failures]
        (self.out / "table.txt").write_text("\n".join(lines) + "\n")
        write_json(self.out / "accuracy.json",
                   {"settings": self.settings, "rows": self.rows, "failures": self.failures,
                    "summary": summary, "wall_seconds": wall, "complete": final})
        if final:
            contact_sheet(self.out / "accuracy.png", self.tiles)
        return summary
