"""Regenerate docs/images/first_pictures.png: the first pictures with default settings.

``python docs/images/first_pictures.py`` renders, with ``isolume render`` and nothing but
the defaults, the built-in volume (what ``./run`` writes with no display) and — when
../shared/data is present — the engine CT and CThead (CThead with ``--up -z``: its raw
slices run top to bottom and a raw file cannot say so), pastes them side by side and
prints each one's wall time and the spread of its surface pixels (0–255, mean of R, G, B;
the surface is every pixel that differs from the background's colour).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data" / "volumes"
PICTURES = (
    ("./run (synthetic:engine)", []),
    ("engine CT", [str(SHARED / "engine_zfp_256x256x128_uint8.raw.gz")]),
    ("CThead, --up -z", [str(SHARED / "CThead_256x256x113_uint16.raw.gz"), "--up", "-z"]),
)


def render(args: list[str], out: Path) -> float:
    """Run ``isolume render ARGS --out OUT``; returns the wall time in seconds."""
    from isolume.app.cli import main

    t0 = time.perf_counter()
    if main(["render", *args, "--out", str(out)]) != 0:
        raise SystemExit(f"isolume render {' '.join(args)} failed")
    return time.perf_counter() - t0


def surface_spread(rgb: np.ndarray) -> tuple[float, float, float]:
    """(median, 5th, 95th percentile) of the surface pixels of an (H, W, 3) sRGB image."""
    surface = (rgb != rgb[0, 0]).any(axis=-1)
    values = rgb[surface].astype(np.float64).mean(axis=-1)
    return tuple(float(np.percentile(values, q)) for q in (50, 5, 95))


def main() -> None:
    tiles = []
    with tempfile.TemporaryDirectory() as tmp:
        for n, (label, args) in enumerate(PICTURES):
            if args and not Path(args[0]).exists():
                print(f"{label}: {args[0]} not present, left out")
                continue
            out = Path(tmp) / f"{n}.png"
            seconds = render(args, out)
            rgb = np.asarray(Image.open(out).convert("RGB"))
            median, low, high = surface_spread(rgb)
            print(f"{label}: {seconds:.1f} s; surface median {median:.0f}, 5-95 % "
                  f"{low:.0f}-{high:.0f}")
            tile = Image.fromarray(rgb)
            ImageDraw.Draw(tile).text((8, 6), label, fill=(235, 235, 235))
            tiles.append(tile)
    sheet = Image.new("RGB", (sum(t.width for t in tiles), max(t.height for t in tiles)))
    x = 0
    for tile in tiles:
        sheet.paste(tile, (x, 0))
        x += tile.width
    sheet.save(ROOT / "docs" / "images" / "first_pictures.png", optimize=True)


if __name__ == "__main__":
    main()
