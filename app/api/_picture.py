"""`Picture`: what `isolume.render` returns."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True, eq=False)
class Picture:
    """A rendered picture of an isosurface.

    Attributes:
        srgb: (H, W, 3) uint8 display pixels (exposure, tone curve, sRGB), what a PNG holds.
        linear: (H, W, 3) float32 linear radiance before exposure (0 off the surface),
            what an EXR holds.
        mask: (H, W) bool, True on surface pixels.
        exposure: the linear scale applied before the tone curve.
        iso: the isovalue drawn, field units.
        triangles: the surface's triangle count.
        summary: one line saying what was drawn (the command's ``wrote …`` line).
    """

    srgb: np.ndarray
    linear: np.ndarray
    mask: np.ndarray
    exposure: float
    iso: float
    triangles: int
    summary: str

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) pixels."""
        return int(self.srgb.shape[1]), int(self.srgb.shape[0])

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the picture: FILE.png (sRGB) or FILE.exr (linear), as ``isolume render
        --out`` writes them; returns the path.

        Raises:
            IsolumeError: another suffix, or a folder that is missing or not writable.
        """
        from isolume.app.render.images import check_output_path, write_image

        path = check_output_path(path)
        write_image(path, self.linear, self.srgb)
        return path

    def _repr_png_(self) -> bytes:
        """The PNG of `srgb` (what a notebook shows)."""
        from isolume.app.render.png import encode_png

        return encode_png(self.srgb)

    def __repr__(self) -> str:
        return f"Picture({self.summary})"
