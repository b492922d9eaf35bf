"""The environment spec grammar (``--env``) and the constructors it builds on:
``constant:R,G,B``, ``sky[:key=value,...]``, ``PATH[@latlong|@angular][*SCALE]``."""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from isolume.baking.environment.files import EnvSpecError, read_image
from isolume.baking.environment.models import (
    MAPPINGS,
    SKY_COLOUR_KEYS,
    SKY_DEFAULTS,
    ConstantEnvironment,
    Environment,
    ImageEnvironment,
    SkyEnvironment,
)


# ----------------------------------------------------------------------------- constructors
def constant(rgb: npt.ArrayLike) -> ConstantEnvironment:
    """Uniform environment of radiance rgb (scalar or (3,))."""
    return ConstantEnvironment(np.asarray(rgb, dtype=np.float64))


def sky(**params: Any) -> SkyEnvironment:
    """Procedural sky; keyword parameters as in :class:`SkyEnvironment` / the module docs."""
    return SkyEnvironment(**params)


def _guess_mapping(h: int, w: int, hint: str | None, name: str) -> str:
    if hint == "cube" or (h == 6 * w) or (w == 6 * h) or (3 * w == 4 * h) or (4 * w == 3 * h):
        raise EnvSpecError(
            f"{name}: a {w}x{h} cube map; cube maps are not supported, "
            "expected a latitude-longitude (2:1) or angular (1:1) map"
        )
    if w == 2 * h:
        return "latlong"
    if w == h:
        return "angular"
    raise EnvSpecError(
        f"{name}: {w}x{h} image, expected 2:1 (latlong) or 1:1 (angular); "
        "add @latlong to force a latitude-longitude mapping"
    )


def _validated_pixels(px: np.ndarray, name: str) -> np.ndarray:
    """(H, W, 3) `px` of the map `name` with negative values clamped to 0, said in one
    ``isolume: warning:`` line on stderr.

    Raises:
        EnvSpecError: NaN or infinite pixels.
    """
    bad = ~np.isfinite(px)
    if np.any(bad):
        row, col, _ = np.argwhere(bad)[0]
        raise EnvSpecError(
            f"{name}: {int(bad.any(axis=2).sum())} pixels are NaN or infinite "
            f"(first at row {row}, col {col}); expected finite radiance"
        )
    if np.any(px < 0):
        count = int((px < 0).any(axis=2).sum())
        print(f"isolume: warning: {name}: {count} pixels had negative values, clamped to 0",
              file=sys.stderr)
        px = np.maximum(px, 0)
    return px


def image(path: str | Path, mapping: str | None = None, scale: float = 1.0) -> ImageEnvironment:
    """Environment from an .exr / .hdr probe file.

    mapping: "latlong", "angular" or None (2:1 → latlong, 1:1 → angular, cube-map
    layouts and other shapes → EnvSpecError). scale multiplies the radiance.
    """
    name = str(path)
    if mapping is not None and mapping not in MAPPINGS:
        raise EnvSpecError(f"{name}@{mapping}: unknown mapping, expected @latlong or @angular")
    if not (math.isfinite(scale) and scale >= 0):
        raise EnvSpecError(f"{name}*{scale}: scale must be finite and ≥ 0")
    px, hint = read_image(path)
    h, w = px.shape[:2]
    if mapping is None:
        mapping = _guess_mapping(h, w, hint, name)
    elif mapping == "angular" and h != w:
        raise EnvSpecError(f"{name}@angular: {w}x{h} image, expected a square angular map")
    px = _validated_pixels(px, name)
    return ImageEnvironment(px, mapping, name=name, scale=float(scale))


def image_from_array(pixels: np.ndarray, mapping: str, name: str = "<array>") -> ImageEnvironment:
    """Environment from an in-memory (H, W, 3) map (e.g. synthetic tests)."""
    return ImageEnvironment(np.asarray(pixels), mapping, name=name)


# ----------------------------------------------------------------------------- parse_env
def _parse_numbers(text: str, spec: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise EnvSpecError(f"{spec!r}: expected numbers, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise EnvSpecError(f"{spec!r}: expected finite numbers, got {text!r}")
    return values


def _parse_constant(spec: str, body: str) -> Environment:
    values = _parse_numbers(body, spec)
    if len(values) not in (1, 3) or any(v < 0 for v in values):
        raise EnvSpecError(f"{spec!r}: expected constant:R,G,B or constant:V with values ≥ 0")
    return constant(values if len(values) == 3 else values[0])


def _parse_sky(spec: str, body: str) -> Environment:
    params: dict[str, list[str]] = {}
    key = None
    for token in filter(None, (t.strip() for t in body.split(","))):
        if "=" in token:
            key, value = (s.strip() for s in token.split("=", 1))
            if key not in SKY_DEFAULTS:
                raise EnvSpecError(
                    f"{spec!r}: unknown sky key {key!r}, expected one of {', '.join(SKY_DEFAULTS)}"
                )
            params[key] = [value]
        elif key is None:
            raise EnvSpecError(f"{spec!r}: expected sky:key=value,... got {token!r}")
        else:
            params[key].append(token)
    kwargs = {}
    for key, values in params.items():
        numbers = _parse_numbers(",".join(values), spec)
        if key in SKY_COLOUR_KEYS:
            if len(numbers) not in (1, 3):
                raise EnvSpecError(f"{spec!r}: sky {key} takes 1 or 3 numbers, got {len(numbers)}")
            kwargs[key] = tuple(numbers) if len(numbers) == 3 else (numbers[0],) * 3
        elif len(numbers) != 1:
            raise EnvSpecError(f"{spec!r}: sky {key} takes one number, got {len(numbers)}")
        else:
            kwargs[key] = numbers[0]
    try:
        return SkyEnvironment(**kwargs)
    except ValueError as exc:
        raise EnvSpecError(f"{spec!r}: {exc}") from None


def parse_env(spec: str) -> Environment:
    """Environment from a spec: ``constant:R,G,B``, ``constant:V``, ``sky[:k=v,...]`` or
    ``PATH[@latlong|@angular][*SCALE]``. Raises EnvSpecError (one line, names the spec)."""
    text = spec.strip() if isinstance(spec, str) else ""
    if not text:
        raise EnvSpecError(
            f"{spec!r}: empty environment spec, expected constant:..., "
            "sky[:...] or an .exr/.hdr path"
        )
    head, colon, body = text.partition(":")
    if head == "constant":
        return _parse_constant(spec, body if colon else "1")
    if head == "sky":
        return _parse_sky(spec, body)
    path, mapping, scale = text, None, 1.0
    for _ in range(2):  # suffixes in either order: @mapping, *scale
        m = re.search(r"\*([^*@/\\]+)$", path)
        if m:
            try:
                scale = float(m.group(1))
            except ValueError:
                raise EnvSpecError(f"{spec!r}: expected *SCALE with a number") from None
            path = path[: m.start()]
        m = re.search(r"@([A-Za-z]+)$", path)
        if m:
            mapping, path = m.group(1).lower(), path[: m.start()]
    if mapping is not None and mapping not in MAPPINGS:
        raise EnvSpecError(f"{spec!r}: unknown mapping @{mapping}, expected @latlong or @angular")
    if not (math.isfinite(scale) and scale >= 0):
        raise EnvSpecError(f"{spec!r}: scale must be finite and ≥ 0")
    if not Path(path).is_file():
        raise EnvSpecError(
            f"{spec!r}: no such file; expected constant:R,G,B, "
            "sky[:key=value,...] or an .exr/.hdr path"
        )
    try:
        return image(path, mapping=mapping, scale=scale)
    except EnvSpecError as exc:  # named by the spec, the file's name said once
        said = str(exc)
        said = said[len(path) + 2:] if said.startswith(f"{path}: ") else said
        raise EnvSpecError(f"{spec!r}: {said}") from None
