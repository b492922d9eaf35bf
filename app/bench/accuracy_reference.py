"""The settled reference of a ``bench accuracy`` case: ``isolume reference``'s per-pixel
path tracing of the case's view, from `START_SPP` samples per pixel until its noise is a
quarter of the error it measures, started from and kept in the sweep's reference cache
(keyed by the tracer's identity: volume, isovalue, camera rays, lighting)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume.volumes.errors import IsolumeError

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig
    from isolume.volumes import Volume

START_SPP = 256
"""The reference's first samples per pixel, before its noise is compared with the error."""


class AccuracyError(IsolumeError):
    """A volume or case the sweep cannot measure (the message says why)."""


@dataclass
class Truth:
    """The settled reference.

    Attributes:
        radiance, stderr: (N, 3) linear radiance and its standard error; mask: (N,)
        surface pixels; noise: relative (`accuracy_metrics.reference_noise`); spp: the
        median samples per surface pixel; seconds: wall time (tracer set-up included);
        kept: it started from a kept reference (``--cache``).
    """

    radiance: np.ndarray
    stderr: np.ndarray
    mask: np.ndarray
    noise: float
    spp: int
    seconds: float
    kept: bool = False


def settle_reference(volume: Volume, iso: float, shots: list[Any], config: BakeConfig,
                     sweep: Any) -> Truth:
    """Path-trace the reference of `shots`' view (the case's `accuracy.Shot` pictures, of
    the `accuracy.Sweep` `sweep`'s camera, size, cache and cap) under `config`'s light
    (seed + 1) from `START_SPP` samples per pixel until its noise is at most
    `NOISE_RATIO` × the smallest error less that noise, or ``--ref-spp``.

    Raises:
        AccuracyError: no pixel sees the surface.
    """
    from isolume.app.bench.accuracy_metrics import (
        NOISE_RATIO,
        less_noise,
        next_spp,
        reference_noise,
        relative_rmse,
    )
    from isolume.app.render.renderer import framed_camera
    from isolume.baking.reference import PixelStats, ReferenceTracer, save_state

    camera = framed_camera(volume, iso, sweep.view, sweep.size)
    origins, dirs = camera.primary_rays(*sweep.size)
    config = replace(config, seed=config.seed + 1)
    began = time.perf_counter()
    with ReferenceTracer(volume, iso, origins, dirs, config, smooth=config.normals == "smooth",
                         workers=sweep.workers) as tracer:
        if len(tracer.hits.pixels) == 0:
            raise AccuracyError(f"iso {iso:.6g}: no pixel of the {sweep.view_text} view sees "
                                "the surface")
        kept = _kept_reference(sweep.cache, tracer)
        stats = kept if kept is not None else PixelStats.empty(tracer.pixels)
        had = int(stats.count.sum())
        spp = min(START_SPP, sweep.ref_spp)
        while True:
            _trace(tracer, stats, spp, sweep.progress)
            image = tracer.image(stats)
            noise = reference_noise(image.radiance, image.stderr, image.mask)
            error = min(less_noise(relative_rmse(s.linear, image.radiance, image.mask), noise)
                        for s in shots)
            if noise <= NOISE_RATIO * error or spp >= sweep.ref_spp:
                break
            spp = next_spp(spp, noise, error, sweep.ref_spp)
        if sweep.cache is not None and int(stats.count.sum()) > had:
            save_state(_cache_file(sweep.cache, tracer), stats, {"identity": tracer.identity})
    return Truth(image.radiance, image.stderr, image.mask, noise,
                 int(np.median(stats.count[stats.count > 0])), time.perf_counter() - began,
                 kept is not None)


def _cache_file(folder: Path, tracer) -> Path:
    """The kept reference of `tracer`'s identity in `folder`."""
    import hashlib
    import json

    key = json.dumps(tracer.identity, sort_keys=True)
    return folder / f"{hashlib.sha1(key.encode()).hexdigest()}.state.npz"


def _kept_reference(folder: Path | None, tracer):
    """The `PixelStats` kept in `folder` for `tracer`'s identity, or None (none kept, no
    cache, or a file of another identity or format: it is replaced later)."""
    from isolume.baking.errors import BakeError
    from isolume.baking.reference import load_state

    if folder is None:
        return None
    path = _cache_file(folder, tracer)
    if not path.exists():
        return None
    try:
        stats, meta = load_state(path)
    except BakeError:
        return None
    return stats if tracer.holds(stats, meta) else None


def _trace(tracer, stats, spp: int, progress: bool) -> None:
    """Bring every surface pixel of `tracer` to `spp` samples (a progress bar when
    `progress`)."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=tracer.pending_paths(stats, spp), unit="path", unit_scale=True,
                   dynamic_ncols=True, smoothing=0.1, desc="reference", leave=False)
    tracer.run(stats, spp, bar=bar)
    if bar is not None:
        bar.close()
