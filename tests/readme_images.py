"""Regenerate the docs' pictures (synthetic volumes only): ``python tests/readme_images.py``.

Writes docs/images/engine_gi_vs_local.png (lattice irradiance | Phong with hemisphere
ambient, same mesh and camera) and docs/images/sh_rotation.png (an SH-transfer lattice
under a sky whose sun turns around the part).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from isolume import volumes
from isolume.app.render.offscreen import render_volume
from isolume.app.render.settings import RenderSettings
from isolume.baking import BakeConfig, bake, sh
from isolume.baking.environment import parse_env

OUT = Path(__file__).resolve().parents[1] / "docs" / "images"
SKY = "sky:zenith=0.12,0.2,0.45,horizon=0.35,ground=0.15,sun=10,sun_az=60,sun_el=35,sun_radius=1"


def _label(image: np.ndarray, text: str) -> Image.Image:
    picture = Image.fromarray(image)
    ImageDraw.Draw(picture).text((8, 6), text, fill=(235, 235, 235))
    return picture


def _row(pictures: list[Image.Image]) -> Image.Image:
    w, h = pictures[0].size
    row = Image.new("RGB", (w * len(pictures), h))
    for i, p in enumerate(pictures):
        row.paste(p, (i * w, 0))
    return row


def engine_comparison() -> None:
    vol = volumes.load("synthetic:engine:128")
    lattice = bake(vol, BakeConfig(samples=256, bounces=2, env=SKY), workers=None,
                   progress=True)
    view = (35.0, 35.0, 1.7)
    gi, _ = render_volume(vol, 0.3, RenderSettings(size=(448, 448), shading="irradiance",
                                                    exposure=0.6), view=view, lattice=lattice)
    local, _ = render_volume(vol, 0.3, RenderSettings(size=(448, 448), shading="phong_hemi"),
                             view=view)
    _row([_label(gi.srgb, "lattice irradiance (sky + sun, 2 bounces)"),
          _label(local.srgb, "Phong + hemisphere ambient")]).save(OUT / "engine_gi_vs_local.png")


def sh_rotation() -> None:
    vol = volumes.load("synthetic:engine:96")
    lattice = bake(vol, BakeConfig(mode="sh", sh_order=5, samples=512, bounces=1), progress=True)
    # a broad sun over a brighter sky suits five SH bands (a small bright sun rings and
    # amplifies the transfer's Monte Carlo noise); the Hanning window tames both
    sky = "sky:sun=3,sun_az=60,sun_el=35,sun_radius=8"
    coeffs = sh.project_environment(parse_env(sky), 5, window="hanning")
    pictures = []
    for az in (0, 90, 180, 270):
        settings = RenderSettings(size=(256, 256), shading="sh", exposure=0.5,
                                  env_rotation=(az, 0.0))
        frame, _ = render_volume(vol, 0.3, settings, view=(35.0, 35.0, 1.7), lattice=lattice,
                                 env_coeffs=coeffs)
        pictures.append(_label(frame.srgb, f"sky turned {az} deg"))
    _row(pictures).save(OUT / "sh_rotation.png")


if __name__ == "__main__":
    import sys

    OUT.mkdir(parents=True, exist_ok=True)
    wanted = sys.argv[1:] or ["engine", "sh"]
    if "engine" in wanted:
        engine_comparison()
    if "sh" in wanted:
        sh_rotation()
