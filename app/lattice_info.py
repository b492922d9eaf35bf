"""`isolume info` of an illumination lattice file: what it holds, for which volume, under
which light, and how far its bake has come — read from its metadata and its samples
member, no texel values."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from isolume.baking.lattice import open_lattice, xyz_text
from isolume.volumes.io.arrays import LATTICE_MEMBERS


def is_lattice_file(path: str | os.PathLike[str]) -> bool:
    """Whether `path` is a zip archive holding the members every lattice file holds
    (`volumes.io.arrays.LATTICE_MEMBERS`, what the volume reader refuses as a lattice)."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = set(archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False
    return {f"{name}.npy" for name in LATTICE_MEMBERS} <= names


def describe_lattice(path: str | os.PathLike[str]) -> str:
    """Lines about the lattice file `path`: kind, texels and box, the volume it was baked
    for, the bake's settings and lighting, its paths, rays and seconds, and the active
    texels that have no paths yet (an unfinished bake).

    Raises:
        BakeError: a file that is not a readable lattice.
    """
    file, geometry, config = open_lattice(path)
    meta = file.meta
    texels, read = file.read_texels(None, ("samples", "active"))
    active = int(np.count_nonzero(read["active"]))
    waiting = int(np.count_nonzero(read["active"] & (read["samples"] == 0)))
    volume = meta.get("volume", {})
    stats = meta.get("stats", {})
    z, y, x = geometry.shape
    lines = [f"{Path(path).name}: {meta.get('kind', 'irradiance')} lattice"
             + (f" of SH order {meta['sh_order']}" if meta.get("kind") == "sh" else ""),
             f"texels     {x} × {y} × {z} (x × y × z), {len(texels):,} held, {active:,} "
             "active",
             f"box        {xyz_text(geometry.lo)} to {xyz_text(geometry.hi)}",
             f"volume     {volume.get('name')!r} of shape {volume.get('shape')} (z, y, x), "
             f"spacing {xyz_text(volume.get('spacing', ()))}, origin "
             f"{xyz_text(volume.get('origin', ()))}"]
    if volume.get("source"):
        lines.append(f"baked from {volume['source']}")
    if config is not None:
        lines += [f"lighting   {config.lighting_text}",
                  f"bake       {_settings(config)}"]
    if stats:
        lines.append(f"traced     {stats.get('paths', 0):,} paths, "
                     f"{stats.get('rays_traced', 0):,} rays in "
                     f"{stats.get('bake_seconds', stats.get('trace_seconds', 0.0)):.1f} s")
    lines.append(f"finished   {'yes' if not waiting else 'no'}"
                 + (f": {waiting:,} of {active:,} active texels have no paths yet "
                    "(run its bake again to finish it)" if waiting else ""))
    return "\n".join(lines)


def _settings(config) -> str:
    """The bake settings that shape a lattice, one line."""
    parts = [f"--samples {config.samples}", f"--bounces {config.bounces}",
             f"--scale {config.scale:g}"]
    if config.iso_range is not None:
        parts.append(f"--iso-range {config.iso_range[0]:g} {config.iso_range[1]:g}")
    if config.texel_error is not None:
        parts.append(f"--texel-error {config.texel_error:g}")
    if config.target_error is not None:
        parts.append(f"--target-error {config.target_error:g}")
    if config.direct_light is not None:
        parts.append(f"--direct-light {config.direct_light}")
    return " ".join(parts)

