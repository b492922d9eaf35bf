"""Regenerate docs/images/seams.png: where bricks traced whole meet filled ones.

``python docs/images/seams.py`` bakes ``synthetic:contact`` (a sphere hanging a voxel
above a plane) under a sky and a sun over the isovalues 0.16–0.89, with the sun's direct
light in the pixels (top row) and in the lattice (bottom row): a reference of 1024 paths
a texel, a uniform bake of 64 and a bake to a texel error of 0.02 at 64 (same seed and
levels: the texel bake's plan). It renders each at 512² (iso 0.2, where the two shells
nearly meet in the gap) and pastes the 256² around the contact: the three pictures, then
each bake's relative error against the reference, white at 25 %. It prints the RMS and
the 99.9th percentile of the relative error over the surface, and the bakes' paths.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from isolume.baking.lattice import LUMINANCE  # noqa: E402

ENV = "sky:sun=4,sun_az=30,sun_el=35"
ISO = 0.2
CROP = (slice(150, 406), slice(128, 384))
"""Rows and columns of the 512² pictures around the contact."""


def pictures(direct_light: str) -> tuple[list[np.ndarray], list[str]]:
    """(H, W, 3) linear pictures of the reference, the uniform bake and the texel-error
    bake with `direct_light`, and their labels."""
    import isolume
    from isolume.baking import BakeConfig, bake
    from isolume.baking.plan import move_limit
    from isolume.volumes.synthetic import make

    volume = make("contact")
    config = BakeConfig(samples=64, env=ENV, direct_light=direct_light, seed=5,
                        iso_range=(0.16, 0.89))
    texels = dataclasses.replace(config, texel_error=0.02)
    config = dataclasses.replace(config, max_move=move_limit(texels))  # the same levels
    bakes = [("reference, 1024 paths", dataclasses.replace(config, samples=1024)),
             ("uniform, 64 paths", config),
             ("texel error 0.02, 64", texels)]
    out, labels = [], []
    for label, settings in bakes:
        lattice = bake(volume, settings, workers=None)
        print(f"{direct_light}: {label}: {lattice.meta['stats']['paths']:,} paths")
        picture = isolume.render(volume, iso=ISO, lattice=lattice, size=(512, 512),
                                 view=(30, 20))
        out.append(np.asarray(picture.linear, np.float64)[..., :3])
        labels.append(f"{direct_light}: {label}")
    return out, labels


def srgb(linear: np.ndarray, scale: float) -> np.ndarray:
    """(H, W, 3) uint8 sRGB of the linear pixels times `scale`, clipped."""
    x = np.clip(linear * scale, 0, 1)
    return np.round(255 * np.where(x <= 0.0031308, 12.92 * x,
                                   1.055 * x ** (1 / 2.4) - 0.055)).astype(np.uint8)


def error_tile(picture: np.ndarray, reference: np.ndarray, label: str) -> Image.Image:
    """The relative luminance error of `picture` against `reference`, white at 25 %,
    printed as RMS and 99.9th percentile over the surface."""
    lum, ref = picture @ LUMINANCE, reference @ LUMINANCE
    surface = ref > 1e-4
    rel = np.where(surface, np.abs(lum - ref) / np.maximum(ref, 1e-4), 0.0)
    print(f"{label}: relative error RMS {np.sqrt(np.mean(rel[surface] ** 2)):.3f}, "
          f"99.9 % {np.percentile(rel[surface], 99.9):.3f}")
    grey = np.round(255 * np.clip(rel / 0.25, 0, 1)).astype(np.uint8)[CROP]
    return labelled(Image.fromarray(grey).convert("RGB"), f"error: {label}")


def labelled(tile: Image.Image, text: str) -> Image.Image:
    """`tile` with `text` in its top left corner."""
    ImageDraw.Draw(tile).text((6, 4), text, fill=(235, 120, 60))
    return tile


def main() -> None:
    rows = []
    for direct_light in ("pixels", "lattice"):
        (reference, *bakes), labels = pictures(direct_light)
        lum = reference @ LUMINANCE
        scale = 0.9 / np.percentile(lum[lum > 1e-4], 99)  # one exposure for the row
        tiles = [labelled(Image.fromarray(srgb(p, scale)[CROP]), text)
                 for p, text in zip((reference, *bakes), labels, strict=True)]
        tiles += [error_tile(p, reference, text.split(": ")[1])
                  for p, text in zip(bakes, labels[1:], strict=True)]
        rows.append(tiles)
    width, height = rows[0][0].size
    sheet = Image.new("RGB", (width * len(rows[0]), height * len(rows)))
    for r, tiles in enumerate(rows):
        for c, tile in enumerate(tiles):
            sheet.paste(tile, (c * width, r * height))
    sheet.save(ROOT / "docs" / "images" / "seams.png", optimize=True)


if __name__ == "__main__":
    main()
