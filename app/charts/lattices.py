"""Lattices of ``isolume chart``: baked on demand and cached (`LatticeStore`), and what
their GL textures cost and how much of the displayed surface they cover.

A lattice whose levels do not follow its samples is made by resuming the one of the next
lower count (samples are deterministic per texel and index, so it equals a fresh bake), and
its time is the sum of the wall times of that chain. One whose levels follow its samples
(the automatic level policy under noisy light, `baking.plan.levels_follow_samples`) is
baked afresh: a resumed bake would keep the lower count's levels. Before its first bake a
store pays the process's one-off costs in an untimed warm-up (`LatticeStore.warm_up`).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume.app.charts.progress import say
from isolume.app.render.images import output_folder

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.volumes import Volume
    from isolume.volumes.mesh import Mesh

BAKE_TIME = ("wall time of the bake, after an untimed warm-up bake that keeps the process's "
             "one-off costs (loading the kernels, the first scenes, the volume's caches) off "
             "every point; a lattice whose levels follow its samples (the automatic level "
             "policy under noisy light: resumed_from 0) is a fresh bake timed end to end, any "
             "other resumes the one of the next lower count (resumed_from: its samples) and "
             "its time is the sum over that chain")
"""What `Baked.seconds` measures, as the JSON of every chart says."""
WARM_TEXELS = 4096
"""Most texels the warm-up bake traces (one path each)."""
WARM_MARK = "chart_after_warm_up"
"""Lattice metadata key of a chart lattice timed after the warm-up; a cached lattice
without it was timed with the one-off costs and is baked again."""


@dataclass
class Baked:
    """A lattice and the wall time that made it.

    Attributes:
        lattice: the `baking.Lattice`.
        seconds: wall seconds of the bakes that made it (resumed chains summed).
        cached: True when it was read from the cache instead of baked in this run.
    """

    lattice: Lattice
    seconds: float
    cached: bool

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures of the bake."""
        meta = self.lattice.meta
        return {"bake_seconds": self.seconds, "cached": self.cached,
                "resumed_from": int(meta.get("chart_resumed_from", 0)),
                "rays": int(meta.get("rays_traced", 0)),
                "active_texels": int(meta["plan"]["active_texels"]),
                "texels": int(np.prod(self.lattice.geometry.shape)),
                "shape_zyx": list(self.lattice.geometry.shape)}


class LatticeStore:
    """Bakes lattices on demand and keeps them (in memory and in ``folder``).

    A lattice of N paths per texel resumes the one with the most samples below N and the
    same other settings unless its levels follow its samples; its `Baked.seconds` adds the
    wall times of the chain. The first bake is preceded by `warm_up`.
    """

    volume: Volume
    folder: Path
    workers: int | None

    def __init__(self, volume: Volume, folder: Path, workers: int | None) -> None:
        self.volume, self.folder, self.workers = volume, folder, workers
        self._memory: dict = {}
        self._warm = False
        output_folder(folder, "--cache")

    def _stem(self, config) -> str:
        core = dataclasses.replace(config, samples=1).to_dict()
        digest = hashlib.sha1(json.dumps(core, sort_keys=True).encode()).hexdigest()[:10]
        order = config.sh_order if config.mode == "sh" else ""
        return f"{config.mode}{order}_x{config.scale:g}_{config.normals}{config.offset:g}_{digest}"

    def _path(self, config) -> Path:
        return self.folder / f"{self._stem(config)}_s{config.samples}.npz"

    def _load(self, config) -> Baked | None:
        """The cached lattice of exactly `config`, of the texels a bake places now
        (`baking.lattice.other_texels`) and timed after a warm-up (`WARM_MARK`), or None."""
        from isolume.baking.errors import BakeError
        from isolume.baking.lattice import Lattice, other_texels

        if config in self._memory:
            return self._memory[config]
        path = self._path(config)
        if not path.exists():
            return None
        try:
            lattice = Lattice.load(path, self.volume)
        except BakeError:
            return None
        if (not lattice.meta.get(WARM_MARK) or lattice.config != config
                or other_texels(lattice.geometry, self.volume, config.scale)):
            return None
        baked = Baked(lattice, float(lattice.meta["chart_seconds"]), True)
        self._memory[config] = baked
        return baked

    def _start(self, config) -> Baked | None:
        """The cached lattice with the most samples below `config.samples`, or None (also
        when the levels follow the samples: resuming would keep the smaller bake's)."""
        from isolume.baking.plan import levels_follow_samples

        if levels_follow_samples(config):
            return None
        stem, best = self._stem(config), None
        for path in self.folder.glob(f"{stem}_s*.npz"):
            n = path.stem.rsplit("_s", 1)[-1]
            if n.isdigit() and int(n) < config.samples and (best is None or int(n) > best):
                if self._load(dataclasses.replace(config, samples=int(n))) is not None:
                    best = int(n)
        return None if best is None else self._load(dataclasses.replace(config, samples=best))

    def get(self, config: BakeConfig) -> Baked:
        """The lattice of `config`: from memory, the cache, or baked now."""
        baked = self._load(config)
        if baked is None:
            baked = self._bake(config, self._start(config))
            self._memory[config] = baked
        return baked

    def warm_up(self, config: BakeConfig) -> None:
        """Pay the process's one-off costs of baking, once per store and untimed, so that
        no bake's time holds them: load the kernels (`baking.kernels.warm_up`) and trace
        one path for up to `WARM_TEXELS` texels of `config`'s settings (the first Embree
        scenes, the volume's caches)."""
        from isolume.baking import kernels
        from isolume.baking.bake import Baker

        if self._warm:
            return
        kernels.warm_up()
        baker = Baker(self.volume, dataclasses.replace(config, samples=1), workers=self.workers)
        try:
            baker.run(np.arange(min(len(baker.plan.ids), WARM_TEXELS)))
        finally:
            baker.close()
        self._warm = True

    def _bake(self, config, start: Baked | None) -> Baked:
        from isolume.baking.bake import Baker

        self.warm_up(config)
        lattice = None
        if start is not None:
            lattice = copy.deepcopy(start.lattice)
            lattice.config = config
        began = time.perf_counter()
        baker = Baker(self.volume, config, lattice=lattice, workers=self.workers)
        try:
            baker.run()
        finally:
            baker.close()
        seconds = (start.seconds if start else 0.0) + time.perf_counter() - began
        lattice = baker.lattice
        lattice.meta["chart_seconds"] = seconds
        lattice.meta["chart_resumed_from"] = start.lattice.config.samples if start else 0
        lattice.meta[WARM_MARK] = True
        lattice.save(self._path(config))
        order = f" order {config.sh_order}" if config.mode == "sh" else ""
        say(f"baked {config.mode}{order} x{config.scale:g} {config.normals} offset "
            f"{config.offset:g} {config.env} {config.bounces} bounces, {config.samples} "
            f"paths/texel: {seconds:.1f} s")
        return Baked(lattice, seconds, False)


def texture_bytes(lattice: Lattice, lookup: str = "trilinear") -> int:
    """Bytes of the GL textures that hold `lattice` (`app.render.lattice_gl`): irradiance is
    RGB9_E5 (4 B/texel) plus the R8 valid mask (1 B), plus R32F texel isovalues (4 B)
    for the closest-isovalue lookup; SH is ⌈n²/4⌉ RGBA16F textures (8 B/texel) per
    colour group plus the valid mask."""
    from isolume.app.render.lattice_gl import sh_layout
    from isolume.baking.sh import transfer_blocks

    texels = int(np.prod(lattice.geometry.shape))
    if lattice.kind == "irradiance":
        return texels * (4 + 1 + (4 if lookup == "closest" else 0))
    order = int(lattice.meta["sh_order"])
    blocks = transfer_blocks(lattice)
    per_group, groups = sh_layout(order, lattice.values.shape[-1] != blocks * order * order,
                                  blocks)
    return texels * (8 * per_group * groups + 1)


def lattice_coverage(lattice: Lattice, mesh: Mesh) -> dict[str, float | None]:
    """How much of the displayed surface `lattice` covers, from the trilinear weight w of
    its computed texels at the (V, 3) mesh vertices (what the shader divides by):
    "surface_uncovered" is the fraction with w < 0.25, where the shader shows mostly its
    local fallback (``lattice_blend`` in ``lattice.glsl``), "surface_partly_covered" the
    fraction with some uncomputed neighbour (w < 1)."""
    from isolume.baking.lattice import trilinear

    if mesh.empty:
        return {"surface_uncovered": None, "surface_partly_covered": None}
    valid = lattice.computed[..., None].astype(np.float32)
    w = trilinear(valid, lattice.geometry.to_texel_coords(mesh.vertices))[:, 0]
    return {"surface_uncovered": float(np.mean(w < 0.25)),
            "surface_partly_covered": float(np.mean(w < 0.999))}

