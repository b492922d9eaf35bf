"""Per-pixel path tracing of ``isolume chart`` (the baker's own integrator,
`baking.reference`): the reference image and the path tracer given each bake's time.

The reference's own noise, ``sqrt(mean(stderr²)) / mean(ref)`` over its surface pixels,
must be at most `NOISE_RATIO` of the smallest error charted (then it inflates that error
by at most 3 %, since E|img − ref|² = err² + noise²); the reference gains samples until
that holds, or until the time cap, which the JSON then says (`settle_reference`). The
reference, the equal-time path tracer and the bakes use different seeds, so their noise
is independent.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from isolume.app.charts.metrics import Image, error_record, image_entries, reference_noise
from isolume.app.charts.model import Chart, Plan, Run
from isolume.app.charts.progress import say

if TYPE_CHECKING:
    from isolume.baking.reference import PixelStats, ReferenceImage, ReferenceTracer

NOISE_RATIO = 0.25
"""The reference's relative noise may be at most this fraction of the smallest error."""
CALIBRATION_SPP = 16
"""Samples per pixel traced to measure s/spp (one pass of the tracer's job split)."""


class Reference:
    """The reference image: per-pixel path tracing that gains samples on request, with
    its state kept in ``path`` (resumed when the settings match)."""

    path: Path
    seconds: float
    tracer: ReferenceTracer
    stats: PixelStats

    def __init__(self, run: Run, path: Path) -> None:
        from isolume.baking.reference import PixelStats, ReferenceTracer, load_state

        config = dataclasses.replace(run.config, seed=run.config.seed + 1)
        self.path, self.seconds = path, 0.0
        self.tracer = ReferenceTracer(run.volume, run.iso, run.origins, run.dirs, config,
                                      workers=run.workers)
        self.stats = PixelStats.empty(self.tracer.pixels)
        if path.exists():
            stats, meta = load_state(path)
            if meta.get("identity") == self.tracer.identity:
                self.stats, self.seconds = stats, float(meta.get("seconds", 0.0))

    @property
    def spp(self) -> int:
        """Samples of every surface pixel."""
        counts = self.stats.count[self.tracer.hits.pixels]
        return int(counts.min()) if len(counts) else 0

    @property
    def seconds_per_spp(self) -> float:
        return self.seconds / max(self.spp, 1)

    def extend(self, spp: int) -> None:
        """Bring every surface pixel to `spp` samples (and save the state)."""
        from isolume.baking.reference import save_state

        if spp <= self.spp:
            return
        began = time.perf_counter()
        self.tracer.run(self.stats, spp)
        self.seconds += time.perf_counter() - began
        save_state(self.path, self.stats, {"identity": self.tracer.identity,
                                           "seconds": self.seconds})

    def image(self) -> ReferenceImage:
        return self.tracer.image(self.stats)

    def close(self) -> None:
        self.tracer.close()


def equal_time_path_tracing(run: Run, targets: list[tuple[str, float]]
                            ) -> list[dict[str, Any]]:
    """Per-pixel path tracing given the time of each bake.

    The seconds per sample per pixel are measured first (`CALIBRATION_SPP` samples on a
    separate state); then one image gains samples in order of the target times and is
    kept at each ``spp = max(1, round((T − setup) / (s/spp)))``, s/spp being updated to
    the mean measured so far after each step. Every point records the time it really took
    (tracer setup plus tracing up to its spp), which is what the chart plots.

    Args:
        targets: (label, seconds) of the bakes to match.

    Returns:
        One dict per target: matches (label), target_seconds, spp, seconds, image (key
        into ``run.images``).
    """
    from isolume.baking.reference import PixelStats, ReferenceTracer

    config = dataclasses.replace(run.config, seed=run.config.seed + 2)
    with ReferenceTracer(run.volume, run.iso, run.origins, run.dirs, config,
                         workers=run.workers) as tracer:
        setup = tracer.counters.setup_seconds
        began = time.perf_counter()
        tracer.run(PixelStats.empty(tracer.pixels), CALIBRATION_SPP)
        per_spp = calibrated = (time.perf_counter() - began) / CALIBRATION_SPP
        stats, traced, points = PixelStats.empty(tracer.pixels), 0.0, []
        for label, seconds in sorted(targets, key=lambda t: t[1]):
            spp = max(1, round((seconds - setup) / per_spp))
            began = time.perf_counter()
            tracer.run(stats, spp)
            traced += time.perf_counter() - began
            done = int(stats.count[tracer.hits.pixels].min()) if len(tracer.hits.pixels) else 0
            per_spp = traced / max(done, 1)
            key = f"path_traced/{done}"
            picture = tracer.image(stats)
            run.images[key] = Image(picture.radiance, picture.mask)
            points.append({"matches": label, "target_seconds": seconds, "spp": done,
                           "seconds": setup + traced, "image": key})
    say(f"path traced at equal time: {calibrated:.3g} s/spp calibrated, {per_spp:.3g} "
        f"measured, setup {setup:.2f} s, up to {points[-1]['spp'] if points else 0} spp")
    run.facts["path_traced_seconds_per_spp"] = per_spp
    run.facts["path_traced_seconds_per_spp_calibration"] = calibrated
    run.facts["path_traced_setup_seconds"] = setup
    return points



def fill_errors(charts: list[Chart], images: dict[str, Image], reference: ReferenceImage
                ) -> list[float]:
    """Set "error" and "pixels" of every image entry against `reference` (a
    `baking.reference.ReferenceImage`); returns the errors (not None)."""
    errors = []
    for chart in charts:
        for entry in image_entries(chart.data):
            entry.update(error_record(images[entry["image"]], reference))
            if entry["error"] is not None:
                errors.append(entry["error"])
    return errors


def settle_reference(ref: Reference, charts: list[Chart], images: dict[str, Image],
                     plan: Plan) -> dict[str, Any]:
    """Add reference samples until its noise is ≤ `NOISE_RATIO` × the smallest error (or
    the time cap); fill in the errors against the final reference.

    Returns:
        The rule's record: spp, seconds, noise, smallest error, ratio, holds, capped, and
        the spp the rule needs (estimated from noise ∝ 1/√spp where capped).
    """
    ref.extend(plan.ref_spp)
    while True:
        picture = ref.image()
        noise = reference_noise(picture)
        errors = fill_errors(charts, images, picture)
        smallest = min(errors) if errors else 0.0
        holds = noise <= NOISE_RATIO * smallest
        needed = ref.spp if holds else (
            math.inf if smallest <= 0 else
            math.ceil(ref.spp * (noise / (NOISE_RATIO * smallest)) ** 2 * 1.1))
        affordable = ref.spp + int(max(plan.ref_max_seconds - ref.seconds, 0.0)
                                   / max(ref.seconds_per_spp, 1e-9))
        say(f"reference: {ref.spp} spp ({ref.seconds:.1f} s), noise {noise:.3%}, "
            f"smallest error {smallest:.3%}: {'holds' if holds else 'more samples'}")
        if holds or affordable < 1.1 * ref.spp:  # the cap leaves < 10 % more: stop
            break
        ref.extend(int(min(needed, affordable, 64 * ref.spp)))
    return {"rule": f"reference noise <= {NOISE_RATIO:g} x smallest error charted",
            "spp": ref.spp, "seconds": ref.seconds, "seconds_per_spp": ref.seconds_per_spp,
            "noise": noise, "smallest_error": smallest,
            "noise_over_smallest_error": noise / smallest if smallest > 0 else None,
            "holds": bool(holds), "capped": not holds, "cap_seconds": plan.ref_max_seconds,
            "spp_needed": None if math.isinf(needed) else int(needed),
            "seed": ref.tracer.config.seed, "normals": "smooth",
            "offset_voxels": ref.tracer.config.offset,
            "surface_pixels": int(picture.mask.sum())}

