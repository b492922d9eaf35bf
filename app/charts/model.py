"""What the charts of one ``isolume chart`` call share: the resolved counts (`Plan`), the
scene, lattices and images (`Run`), and one chart's numbers (`Chart`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from isolume.app.charts.lattices import Baked, LatticeStore, lattice_coverage
from isolume.app.charts.progress import say
from isolume.app.charts.scene import GLScene

if TYPE_CHECKING:
    from isolume.app.charts.metrics import Image
    from isolume.baking.config import BakeConfig
    from isolume.baking.lattice import Lattice
    from isolume.volumes import Volume


@dataclass(frozen=True)
class Plan:
    """What this run computes (options resolved against --quick).

    Attributes:
        samples: paths per texel of chart 1's lattices, ascending.
        chart_samples: paths per texel of the lattices of charts 2-4.
        charts: the chart numbers to make.
        ref_spp: first reference samples per pixel.
        ref_max_seconds: cap on the reference's tracing time, s.
        draws: timed frames per shading mode.
    """

    samples: tuple[int, ...]
    chart_samples: int
    charts: tuple[str, ...]
    ref_spp: int
    ref_max_seconds: float
    draws: int


@dataclass
class Run:
    """Everything shared by the charts of one ``isolume chart`` call.

    Attributes:
        volume, iso: the scalar field and the displayed isovalue.
        origins, dirs: (N, 3) primary rays of the camera, one per pixel.
        config: base `BakeConfig` (irradiance, env, bounces, albedo, seed).
        images: key → `Image`, every picture that is charted.
        facts: measured figures recorded in every JSON (GL renderer, s/spp, ...).
    """

    volume: Volume
    iso: float
    origins: np.ndarray
    dirs: np.ndarray
    config: BakeConfig
    plan: Plan
    store: LatticeStore
    gl: GLScene
    workers: int | None
    images: dict[str, Image] = field(default_factory=dict)
    facts: dict[str, Any] = field(default_factory=dict)

    def lattice(self, **changes: Any) -> Baked:
        """The lattice of the base config with `changes` (e.g. samples, mode, scale); where
        the direct light goes is chosen anew for it (`BakeConfig.direct_light`: per pixel
        for irradiance with a sun or lights) unless `changes` say."""
        changes.setdefault("direct_light", None)
        return self.store.get(dataclasses.replace(self.config, **changes))

    def summary(self, baked: Baked) -> dict[str, Any]:
        """`Baked.summary` plus how much of the displayed surface the lattice covers."""
        coverage = lattice_coverage(baked.lattice, self.gl.mesh)
        if (coverage["surface_uncovered"] or 0) > 0.01:
            config = baked.lattice.config
            say(f"warning: the {config.mode} lattice x{config.scale:g} leaves "
                f"{coverage['surface_uncovered']:.1%} of the surface's vertices without "
                "computed texels (the renderer shows its local fallback there)")
        return {**baked.summary(), **coverage}

    def render(self, key: str, shading: str, lattice: Lattice | None = None) -> str:
        """Render `shading` into ``images[key]``; returns `key`."""
        self.images[key] = self.gl.render(shading, lattice)
        return key


@dataclass
class Chart:
    """One chart's numbers before the errors are filled in.

    Attributes:
        name: file stem (``chart1_bake_time``).
        title: what it shows.
        data: JSON-ready dict; every dict in it with an "image" key gets "error" and
            "pixels" from that image once the reference is final.
    """

    name: str
    title: str
    data: dict[str, Any]

