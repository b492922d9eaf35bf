"""`BakeConfig`: everything that determines a lattice's values (frozen, explicit)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from isolume.baking.errors import BakeError
from isolume.baking.lighting import Lighting, lighting_of, remember

MODES = ("irradiance", "sh")
DEFAULT_ENV = "sky:sun=6,sun_az=-150,sun_el=40"
"""The lighting of the command line when none is given (``render``, ``view``, ``bake`` and
``reference`` alike): a blue sky over a grey ground with a sun of irradiance 6 from the
left of the default view (azimuth −150°, the camera's −60° turned 90°; elevation 40°), so
that the first picture shows shape by cast shadows as well as by the sky's soft light.
`BakeConfig`'s own default `env` stays the constant white sky (E = π on open surfaces,
what the analytic tests use)."""
DIRECT_LIGHT = ("pixels", "lattice")
"""Where the direct light of point/directional lights and the sky's sun is computed."""
SIDES = ("seen", "normals")
"""Which side of its surface a texel is lit on (`BakeConfig.sides`)."""


DEFAULT_SAMPLES = 100
"""Paths per texel of a bake that traces every texel and names no count (`BakeConfig`'s
default; an SH bake's that names no count, target nor texel error)."""
DEFAULT_TEXEL_ERROR = 0.02
"""The texel error (`BakeConfig.texel_error`) of an irradiance bake that names no count,
noise target nor texel error (``isolume bake``'s default), at `TEXEL_SAMPLES`
([accuracy.md](../docs/accuracy.md#texels-where-the-light-varies-against-uniform-texels))."""
TEXEL_SAMPLES = 32
"""Paths per traced texel of a bake to a texel error that names no count (the nodes that
fill get `NODE_PATHS` times as many, and the level plan is sized for at least
`TEXEL_PLAN_SAMPLES`; below `baking.lattice.TRAPPED_PATHS`, texels dark on all of theirs
go on to that many; their first directions stratified, `baking.passes.stratifies`).
Over the 58 bake cases of ``../shared/data`` the default is within each case's reference
noise + 0.5 % of the uniform `DEFAULT_SAMPLES` bake at 0.297× its paths (the smallest
margin 0.19 points), and the cheapest uniform bake as accurate (median, p90 and worst
error, no black pixels) of those measured is that one; at 28 paths a texel the worst case
is above that of 36 unstratified paths (15.39 against 15.20 %) and the smallest margin
0.03 points ([accuracy.md](../docs/accuracy.md#the-default-against-the-front))."""
DEFAULT_BOUNCES = 2
"""Diffuse bounces of every command's light when none is given."""
DEFAULT_ALBEDO = 0.8
"""Diffuse reflectance (grey) of every command's surface when none is given."""
TEXEL_PLAN_SAMPLES = 80
"""Least paths per texel the level plan of a bake to a texel error is sized for
(`BakeConfig.plan_samples`). A plan sized for fewer spaces its levels wider
(`baking.plan.move_limit`: a move's error need not be smaller than the noise), where the
light of a filled texel is a mix of several nodes, less noisy than any one of them: at
36 paths a texel, a plan for its nodes' 72 paths put the hydrogen atom at iso 9.46 at
6.02 % against 3.74 % with one for 80 (3.66 % at 40 paths a texel)."""
NODE_PATHS = 2
"""Paths of a node that fills texels per path of a traced texel (`BakeConfig.samples`) in a
bake to a texel error (`baking.density`): its light is mixed into up to 26 filled texels
around it, so its noise shows over a larger part of the picture (docs/accuracy.md
measures the choice)."""
MIN_TARGET_SAMPLES = 4
"""The fewest first-round paths of a bake to a noise target."""
SCALES = (0.05, 8.0)
"""Smallest and largest lattice scale, texels per voxel."""

MAX_SEED = (1 << 32) - 1
"""Largest seed: the tracer's random numbers (`baking.rng`) take a 32-bit seed."""


@dataclass(frozen=True)
class BakeConfig:
    """Bake settings. Two bakes with equal configs (except `samples`) can share a file.

    Attributes:
        mode: "irradiance" (RGB E, static lights) or "sh" (transfer coefficients).
        sh_order: SH bands n (n² coefficients) in "sh" mode.
        samples: target Monte Carlo paths per texel.
        bounces: diffuse interreflection bounces (0 = direct light only).
        albedo: diffuse reflectance, linear RGB in [0, 1].
        scale: lattice texels per voxel along the volume's finest axis (cubic texels
            where the voxels are not: `baking.lattice.refinement`).
        iso_range: (lo, hi) isovalues of interest; None = the data range.
        env: environment spec (see `baking.environment.parse_env`); "" = none.
        lights: point/directional light specs (see `baking.lights`).
        seed: random seed.
        max_move: largest Newton move onto a level surface (for 90 % of the texels),
            voxels; sets the number of isovalue levels from the data's gradients. None
            (the default): chosen from the samples, and the level count capped by the
            scenes' cost (`baking.plan.move_limit`, `level_budget`).
        max_levels: cap on the number of levels (memory and build time).
        offset: ray-origin offset along the normal, voxels (paper Fig. 5, "offset").
        normals: "smooth" (cubic-B-spline-smoothed gradient, the paper's) or "gradient"
            (plain central differences, paper Fig. 5 left) for the texel normals.
        flip_normals: normals from low to high values.
        sides: "seen" (each texel lit on the side of its surface that a camera outside
            the volume can see, both sides in a checkerboard where both can be seen:
            `baking.sides`) or "normals" (the side the normals point to, everywhere).
        target_error: None for exactly `samples` paths per texel; else paths where the
            noise is (`baking.adaptive`): texels get paths in doubling rounds from
            `samples` up to `max_samples`, in proportion to the spread of their paths'
            brightness (luminance, or the SH DC term), until each isosurface's
            root-mean-square standard error is this fraction of its light level ("model
            no more than a scene needs": easy texels stop early).
        max_samples: cap on paths per texel with `target_error`.
        texel_error: None for every active texel traced; else texels where the light
            varies (`baking.density`): a brick of the lattice is traced at half
            resolution, and its other texels filled from it, where the interpolation's
            error, estimated from the light's surpluses at twice that spacing, is within
            this fraction of the scene's light level (traced texels get `samples` paths,
            the nodes that fill texels twice that).
        direct_light: "pixels": the lights' and the sun's direct light (at a texel's own
            point) is left out of the lattice, which the renderer adds per pixel with
            shadow maps; their bounces and the rest of the sky stay in the lattice.
            In SH mode (a sky with a sun) the transfer keeps its direct and indirect
            parts apart, shown under the sun-free and the whole rotated sky, and the
            rotated sun is shaded per pixel (`baking.integrator`).
            "lattice": everything in the lattice. None chooses "pixels" for an
            irradiance bake with a light or a sun, else "lattice" (SH bakes ask for the
            split: it doubles the transfer's values; a file written before the field
            existed reads as "lattice", what it holds).
    """

    mode: str = "irradiance"
    sh_order: int = 5
    samples: int = DEFAULT_SAMPLES
    bounces: int = DEFAULT_BOUNCES
    albedo: tuple[float, float, float] = (DEFAULT_ALBEDO,) * 3
    scale: float = 1.0
    iso_range: tuple[float, float] | None = None
    env: str = "constant:1,1,1"
    lights: tuple[str, ...] = ()
    seed: int = 0
    max_move: float | None = None
    max_levels: int = 64
    offset: float = 0.25
    normals: str = "smooth"
    flip_normals: bool = False
    sides: str = "seen"
    target_error: float | None = None
    max_samples: int = 4096
    texel_error: float | None = None
    direct_light: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise BakeError(f"--mode {self.mode!r}: expected one of {', '.join(MODES)}")
        if not 1 <= self.sh_order <= 10:
            raise BakeError(f"--sh-order {self.sh_order}: expected 1 to 10 bands")
        if self.samples < 1:
            raise BakeError(f"--samples {self.samples}: expected at least 1")
        if not 0 <= self.seed <= MAX_SEED:
            raise BakeError(f"--seed {self.seed}: expected a whole number from 0 to {MAX_SEED}")
        if not 0 <= self.bounces <= 16:
            raise BakeError(f"--bounces {self.bounces}: expected 0 to 16")
        albedo = tuple(float(a) for a in np.broadcast_to(self.albedo, 3))
        if min(albedo) < 0 or max(albedo) > 1:
            raise BakeError(f"--albedo {self.albedo}: reflectance must lie in [0, 1]")
        object.__setattr__(self, "albedo", albedo)
        if not SCALES[0] <= self.scale <= SCALES[1]:
            raise BakeError(f"--scale {self.scale:g}: expected {SCALES[0]:g} to {SCALES[1]:g} "
                            "texels per voxel")
        if self.iso_range is not None:
            lo, hi = (float(v) for v in self.iso_range)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise BakeError(f"--iso-range {self.iso_range}: expected LO < HI")
            object.__setattr__(self, "iso_range", (lo, hi))
        object.__setattr__(self, "lights", tuple(self.lights))
        if self.mode == "sh" and self.lights:
            raise BakeError(
                "--mode sh takes only a distant environment (--env): point and directional "
                f"lights ({', '.join(self.lights)}) are not low-frequency; bake them in "
                "--mode irradiance"
            )
        if not self.env and not self.lights:
            raise BakeError("nothing lights the scene: give --env and/or --light")
        object.__setattr__(self, "_lighting", lighting_of(self.env, self.lights))
        if self.max_move is not None and not 0 < self.max_move <= 4:
            raise BakeError(f"--max-move {self.max_move:g}: expected (0, 4] voxels")
        if not 2 <= self.max_levels <= 1024:
            raise BakeError(f"--max-levels {self.max_levels}: expected 2 to 1024 levels")
        if self.target_error is not None and not 0 < self.target_error < 1:
            raise BakeError(f"--target-error {self.target_error:g}: expected a relative "
                            "standard error between 0 and 1, e.g. 0.1")
        if self.target_error is not None and self.samples < MIN_TARGET_SAMPLES:
            raise BakeError(f"--samples {self.samples} with --target-error: expected at "
                            f"least {MIN_TARGET_SAMPLES} (a texel's noise is estimated from "
                            "its first paths)")
        if self.texel_error is not None and not 0 < self.texel_error < 1:
            raise BakeError(f"--texel-error {self.texel_error:g}: expected a fraction of the "
                            "light level between 0 and 1, e.g. 0.02")
        if self.texel_error is not None and self.target_error is not None:
            raise BakeError("--texel-error with --target-error: a bake takes one of them "
                            "(texels where the light varies at --samples paths each, or "
                            "paths where the noise is over every texel)")
        if self.max_samples < self.samples:
            raise BakeError(f"--max-samples {self.max_samples} is below --samples "
                            f"{self.samples}")
        if self.normals not in ("smooth", "gradient"):
            raise BakeError(f"normals {self.normals!r}: expected 'smooth' or 'gradient'")
        if self.sides not in SIDES:
            raise BakeError(f"--sides {self.sides!r}: expected one of {', '.join(SIDES)}")
        if not 0 <= self.offset <= 2:
            raise BakeError(f"offset {self.offset:g}: expected 0 to 2 voxels")
        self._choose_direct_light()

    def _choose_direct_light(self) -> None:
        """Resolve and check `direct_light` (see the class docs)."""
        if self.direct_light is None:
            pixels = self.mode == "irradiance" and bool(self.lighting.pixel_lights())
            object.__setattr__(self, "direct_light", "pixels" if pixels else "lattice")
        if self.direct_light not in DIRECT_LIGHT:
            raise BakeError(f"--direct-light {self.direct_light!r}: expected one of "
                            f"{', '.join(DIRECT_LIGHT)}")
        if (self.direct_light == "pixels" and self.mode == "sh"
                and self.lighting.sun is None):
            raise BakeError(f"--direct-light pixels with --mode sh needs a sky with a sun "
                            f"(--env {self.env!r} has none to shade per pixel); use "
                            "--direct-light lattice")

    @property
    def lighting(self) -> Lighting:
        """The typed lighting of `env` and `lights` (`baking.lighting.Lighting`), parsed
        when the config is made (once per process for the same specs: `lighting_of`)."""
        return self._lighting

    @property
    def lighting_text(self) -> str:
        """The environment and the lights as given, one line ("sky:… + dir:…"; "no
        environment" where `env` is empty)."""
        return " + ".join([self.env or "no environment", *self.lights])

    def __getstate__(self) -> dict[str, Any]:
        """The fields alone: a config crosses to another process as its specs, and its
        lighting is parsed there (`__setstate__`)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for name, value in state.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_lighting", lighting_of(self.env, self.lights))

    @classmethod
    def lit_by(cls, lighting: Lighting, **settings: Any) -> BakeConfig:
        """A config lit by `lighting` (whose `lighting` property is that very value);
        `settings`: the other fields."""
        env, lights = remember(lighting).to_spec()
        return cls(env=env, lights=lights, **settings)

    def with_lighting(self, lighting: Lighting) -> BakeConfig:
        """This config lit by `lighting` (whose `lighting` property is that very value)."""
        env, lights = remember(lighting).to_spec()
        return dataclasses.replace(self, env=env, lights=lights)

    @property
    def plan_samples(self) -> int:
        """The paths per texel the level plan is sized for (`baking.plan.move_limit`,
        `level_budget`): `samples`; with a `texel_error`, the paths of the nodes that fill
        (`NODE_PATHS` × `samples`: what most of the picture's light rests on), at least
        `TEXEL_PLAN_SAMPLES`; with a `target_error` E, the uniform count whose noise meets
        E where a path's brightness spreads as much as its mean, 1 / E², within
        `samples` … `max_samples`."""
        if self.texel_error is not None:
            return max(NODE_PATHS * self.samples, TEXEL_PLAN_SAMPLES)
        if self.target_error is None:
            return self.samples
        return int(np.clip(round(1 / self.target_error ** 2), self.samples, self.max_samples))

    @property
    def gray(self) -> bool:
        """True when the albedo is the same in every channel."""
        return self.albedo[0] == self.albedo[1] == self.albedo[2]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field."""
        d = dataclasses.asdict(self)
        d["lights"] = list(self.lights)
        d["albedo"] = list(self.albedo)
        d["iso_range"] = None if self.iso_range is None else list(self.iso_range)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BakeConfig:
        """Inverse of `to_dict` (unknown keys are an error)."""
        d = dict(d)
        d.setdefault("direct_light", "lattice")  # files from before the field: all in it
        d.setdefault("sides", "normals")  # files from before the field: the normals' side
        d.pop("noise_sigmas", None)  # files from when noisy cells were left out
        d["lights"] = tuple(d.get("lights", ()))
        d["albedo"] = tuple(d.get("albedo", (0.8, 0.8, 0.8)))
        if d.get("iso_range") is not None:
            d["iso_range"] = tuple(d["iso_range"])
        return cls(**d)

    def same_result_as(self, other: BakeConfig) -> bool:
        """True when both configs give the same per-sample estimates (samples may differ:
        a resumed bake keeps its file's levels and move limit, `baking.bake._planned`)."""
        return not self.differences(other)

    def differences(self, other: BakeConfig) -> list[str]:
        """What differs between this config (a file's) and `other` (a command's) beyond the
        paths asked for: one "--option: X in the file, Y here" per setting, in field
        order."""
        def core(c: BakeConfig) -> dict[str, Any]:  # an irradiance bake has no SH order
            return dataclasses.asdict(dataclasses.replace(
                c, samples=1, target_error=None, max_samples=BakeConfig.max_samples,
                texel_error=None, sh_order=c.sh_order if c.mode == "sh" else
                BakeConfig.sh_order))

        mine, theirs = core(self), core(other)
        options = {"lights": "light"}  # fields whose option has another name
        return [f"--{options.get(name, name).replace('_', '-')}: {mine[name]!r} in the file, "
                f"{theirs[name]!r} here" for name in mine if mine[name] != theirs[name]]
