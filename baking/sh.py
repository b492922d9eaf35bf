"""Real spherical harmonics: basis, projection, clamped cosine, windowing, rotation.

Conventions (the one place they are stated; GLSL generated for the renderer must match)
---------------------------------------------------------------------------------------
* Directions are unit vectors ω = (x, y, z) in the world frame, +z up, with
  ω = (sin θ cos φ, sin θ sin φ, cos θ).
* Real SH, **without the Condon–Shortley phase**::

      Y_l^m  = √2 · N_l^|m| · P_l^|m|(cos θ) · cos(|m| φ)   m > 0
      Y_l^0  =      N_l^0   · P_l^0(cos θ)
      Y_l^m  = √2 · N_l^|m| · P_l^|m|(cos θ) · sin(|m| φ)   m < 0

  with N_l^m = sqrt((2l+1)/(4π) · (l−m)!/(l+m)!) and P_l^m the associated Legendre
  functions *without* the (−1)^m factor (paper eq. 12 read that way). So band 1 is
  (Y_1^-1, Y_1^0, Y_1^1) = sqrt(3/4π) · (y, z, x), all positive, and every Y_l^m is a
  homogeneous polynomial of degree l in (x, y, z). (scipy's complex Y_l^m includes the
  phase; real-with-phase = (−1)^m · ours for m ≠ 0.)
* Flat index i = l(l+1) + m; "order n" = bands l = 0 … n−1 = n² coefficients
  (the paper's "fifth order" = 25 coefficients).
* Projection: c_i = ∫ f(ω) Y_i(ω) dω over the sphere (steradians), so
  f ≈ Σ c_i Y_i and ∫ f g dω = Σ f_i g_i.
* Rotation contract: if c are the coefficients of f, ``rotation(R, n) @ c`` are the
  coefficients of g(ω) = f(Rᵀω) ("the function carried along by R"). Band 1 of that
  matrix is R itself in (y, z, x) order, exactly the paper's/Ivanic–Ruedenberg's
  r_{s,t} labelling (1 ↔ x, −1 ↔ y, 0 ↔ z); higher bands come from the
  Ivanic–Ruedenberg recurrence (J. Phys. Chem. 100:6342, 1996, with the 1998
  "Additions and Corrections"), paper Table 3.
* Clamped cosine: ∫ max(0, n·ω) Y_lm(ω) dω = Â_l Y_lm(n) (Funk–Hecke), so irradiance
  E(n) = Σ Â_l ℓ_lm Y_lm(n) with ℓ the radiance coefficients.
"""

# ruff: noqa: E741  (l is the SH band index, as in the literature)
from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from functools import lru_cache
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from isolume.baking.environment import (
    ConstantEnvironment,
    Environment,
    ImageEnvironment,
    RotatedEnvironment,
    SkyEnvironment,
    as_dirs,
)

if TYPE_CHECKING:
    from isolume.baking.config import BakeConfig

__all__ = [
    "band_rotation",
    "basis",
    "clamped_cosine_coefficients",
    "display_coefficients",
    "irradiance_coefficients",
    "num_coefficients",
    "project_environment",
    "project_function",
    "rotation",
    "rotation_from_az_el",
    "sh_index",
    "sphere_quadrature",
    "transfer_blocks",
    "window",
]

_SQRT2 = math.sqrt(2.0)

# Resolution of the Gauss–Legendre × uniform-φ grid used to project an environment that
# has no exact projection of its own (see project_environment): exact for functions of
# band < _GENERIC_GRID_N − order + 1.
_GENERIC_GRID_N = 256


# ----------------------------------------------------------------------------- indexing
def sh_index(l: int, m: int) -> int:
    """Flat index of (l, m): i = l(l+1) + m."""
    return l * (l + 1) + m


def num_coefficients(order: int) -> int:
    """Number of coefficients of an SH expansion of ``order`` bands: order²."""
    return order * order


def _check_order(order: int) -> int:
    if int(order) != order or order < 1:
        raise ValueError(f"SH order must be an integer ≥ 1, got {order!r}")
    return int(order)


def _band_of_index(order: int) -> np.ndarray:
    """(order²,) int: the band l of every flat index."""
    return np.repeat(np.arange(order), 2 * np.arange(order) + 1)


def _m_of_index(order: int) -> np.ndarray:
    """(order²,) int: the signed m of every flat index."""
    l = _band_of_index(order)
    return np.arange(order * order) - l * (l + 1)


# ----------------------------------------------------------------------------- basis
def _legendre_bar(z: np.ndarray, order: int) -> np.ndarray:
    """Normalised associated Legendre factors, without the sin^m θ factor.

    Returns Pbar of shape (N, order²) with Pbar[:, i(l, ±m)] = N_l^m · P_l^m(z) / (1−z²)^{m/2}
    (a polynomial in z), so that Y_l^m = √2 · Pbar · Re/Im((x + i y)^m) for m ≠ 0 and
    Y_l^0 = Pbar. Stable normalised recurrences (no factorials):
    P̄_m^m = sqrt((2m+1)/(2m)) P̄_{m−1}^{m−1} (no Condon–Shortley sign),
    P̄_{m+1}^m = sqrt(2m+3) z P̄_m^m,
    P̄_l^m = a (z P̄_{l−1}^m − b P̄_{l−2}^m), a = sqrt((4l²−1)/(l²−m²)),
    b = sqrt(((l−1)²−m²)/(4(l−1)²−1)).
    """
    z = np.asarray(z, dtype=np.float64)
    out = np.empty((z.shape[0], order * order), dtype=np.float64)
    pmm = np.full_like(z, 1.0 / math.sqrt(4.0 * math.pi))
    for m in range(order):
        if m > 0:
            pmm = pmm * math.sqrt((2 * m + 1) / (2 * m))
        out[:, sh_index(m, m)] = pmm
        out[:, sh_index(m, -m)] = pmm
        if m + 1 >= order:
            break
        p_prev2 = pmm
        p_prev1 = math.sqrt(2 * m + 3) * z * pmm
        out[:, sh_index(m + 1, m)] = p_prev1
        out[:, sh_index(m + 1, -m)] = p_prev1
        for l in range(m + 2, order):
            a = math.sqrt((4 * l * l - 1) / (l * l - m * m))
            b = math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
            p = a * (z * p_prev1 - b * p_prev2)
            out[:, sh_index(l, m)] = p
            out[:, sh_index(l, -m)] = p
            p_prev2, p_prev1 = p_prev1, p
    return out


def _azimuthal_factors(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """(N, order²): √2·Re((x+iy)^m) for m > 0, √2·Im((x+iy)^|m|) for m < 0, 1 for m = 0.

    Built by the recurrence C_m = x C_{m−1} − y S_{m−1}, S_m = x S_{m−1} + y C_{m−1}
    (so sin^m θ cos mφ without any trigonometric call).
    """
    out = np.empty((x.shape[0], order * order), dtype=np.float64)
    c = np.ones_like(x)
    s = np.zeros_like(x)
    for m in range(order):
        if m > 0:
            c, s = x * c - y * s, x * s + y * c
        for l in range(m, order):
            if m == 0:
                out[:, sh_index(l, 0)] = 1.0
            else:
                out[:, sh_index(l, m)] = _SQRT2 * c
                out[:, sh_index(l, -m)] = _SQRT2 * s
    return out


def basis(dirs: np.ndarray, order: int) -> np.ndarray:
    """Real SH basis values.

    dirs: (N, 3) unit vectors (not renormalised; the values are the degree-l
    polynomials evaluated at the given points). Returns (N, order²) float64,
    column i = l(l+1)+m. Any order ≥ 1 (stable recurrences, tested to order 10).
    """
    order = _check_order(order)
    d = as_dirs(dirs)
    return _legendre_bar(d[:, 2], order) * _azimuthal_factors(d[:, 0], d[:, 1], order)


# ----------------------------------------------------------------------------- projection
def sphere_quadrature(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Product quadrature on the sphere: n Gauss–Legendre nodes in z × 2n uniform φ.

    Returns (dirs (n·2n, 3), weights (n·2n,) in steradians, sum 4π). Exact for
    polynomials in (x, y, z) of degree ≤ 2n − 1, i.e. ∫ f g dω is exact when
    band(f) + band(g) ≤ 2n − 1.
    """
    z, wz = np.polynomial.legendre.leggauss(n)
    nphi = 2 * n
    phi = (np.arange(nphi) + 0.5) * (2.0 * math.pi / nphi)
    rho = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    dirs = np.stack(
        [
            np.outer(rho, np.cos(phi)).ravel(),
            np.outer(rho, np.sin(phi)).ravel(),
            np.repeat(z, nphi),
        ],
        axis=1,
    )
    weights = np.repeat(wz, nphi) * (2.0 * math.pi / nphi)
    return dirs, weights


def project_function(
    f: Callable[[np.ndarray], np.ndarray], order: int, n: int | None = None
) -> np.ndarray:
    """Project f: (N, 3) → (N,) or (N, C) onto SH by ``sphere_quadrature(n)``.

    n defaults to 2·order + 8 (exact for f of band ≤ order + 16). Returns (order²,) or
    (order², C).
    """
    order = _check_order(order)
    n = 2 * order + 8 if n is None else int(n)
    dirs, w = sphere_quadrature(n)
    values = np.asarray(f(dirs), dtype=np.float64)
    y = basis(dirs, order)
    if values.ndim == 1:
        return y.T @ (w * values)
    return y.T @ (w[:, None] * values)


def _window_factors(order: int, window_spec) -> np.ndarray:
    if window_spec is None:
        return np.ones(order)
    if isinstance(window_spec, str):
        return window(order, window_spec)
    factors = np.asarray(window_spec, dtype=np.float64)
    if factors.shape != (order,):
        raise ValueError(f"window factors must have shape ({order},), got {factors.shape}")
    return factors


def project_environment(env: Environment, order: int,
                        window: str | npt.ArrayLike | None = None) -> np.ndarray:
    """Radiance coefficients ℓ_i = ∫ L(ω) Y_i(ω) dω of an environment.

    env: a ``baking.environment.Environment``. order: number of bands. window: None,
    a kind for :func:`window` ("hanning", "lanczos"), or (order,) per-band factors,
    multiplied into the result. Returns (order², 3) float64 (linear RGB).

    Deterministic quadrature, never Monte Carlo:

    * constant: closed form (only ℓ_0 = L·sqrt(4π)).
    * sky: the gradient depends on z only, so only m = 0 terms; 2π ∫ L(z) Y_l0(z) dz by
      Gauss–Legendre on its polynomial pieces (exact). The sun disk (a spherical cap of
      constant radiance) by Funk–Hecke: L_sun · 2π ∫_{cos r}^1 P_l(t) dt · Y_lm(s).
    * latitude–longitude image: the exact integral of the nearest-pixel (piecewise
      constant) radiance: every pixel contributes L_pix ∫_pixel Y dω, with the φ
      integral in closed form and the θ integral by (order + 8)-point Gauss–Legendre
      per row (exact to rounding: < 1e-13 measured up to order 21, H ≥ 2).
    * angular image: Σ_pixels L_pix · Y(ω_pixel centre) · Ω_pixel, with the exact pixel
      solid angles (midpoint rule, error O(pixel²)).
    * rotated: rotation(R, order) @ (projection of the inner environment).
    * anything else: ``project_function`` on a ``sphere_quadrature(256)`` grid.
    """
    order = _check_order(order)
    coeffs = _project_unwindowed(env, order)
    return coeffs * _window_factors(order, window)[_band_of_index(order)][:, None]


def _project_unwindowed(env, order: int) -> np.ndarray:
    if isinstance(env, ConstantEnvironment):
        out = np.zeros((order * order, 3))
        out[0] = np.asarray(env.rgb) * math.sqrt(4.0 * math.pi)
        return out
    if isinstance(env, SkyEnvironment):
        return _project_sky(env, order)
    if isinstance(env, ImageEnvironment):
        if env.mapping == "latlong":
            return _project_latlong(env.pixels, order)
        return _project_by_pixel_centres(env, order)
    if isinstance(env, RotatedEnvironment):
        return rotation(env.rotation, order) @ _project_unwindowed(env.inner, order)
    return project_function(env.radiance, order, n=_GENERIC_GRID_N)


def _project_sky(env, order: int) -> np.ndarray:
    """Sky gradient (zonal, exact piecewise Gauss–Legendre) + sun cap (Funk–Hecke)."""
    out = np.zeros((order * order, 3))
    # Gradient: L(z) is a polynomial of degree ≤ 4 on each piece between breakpoints.
    nodes, weights = np.polynomial.legendre.leggauss(order + 4)
    zonal = np.array([sh_index(l, 0) for l in range(order)])
    breaks = env.gradient_breakpoints()
    for z0, z1 in itertools.pairwise(breaks):
        z = 0.5 * (z1 - z0) * nodes + 0.5 * (z1 + z0)
        w = 0.5 * (z1 - z0) * weights * 2.0 * math.pi
        y0 = _legendre_bar(z, order)[:, zonal]  # (G, order) = Y_l0(z)
        out[zonal] += y0.T @ (w[:, None] * env.gradient_radiance(z))
    # Sun cap about direction s with cos(radius) = c, constant radiance L_sun.
    if np.any(env.sun_radiance > 0):
        c = env.sun_cos_radius
        # Plain Legendre P_l(c) for l = 0..order: P_l = P̄_l^0 · sqrt(4π/(2l+1)).
        pbar = _legendre_bar(np.array([c]), order + 1)[0]
        p = np.array(
            [pbar[sh_index(l, 0)] * math.sqrt(4 * math.pi / (2 * l + 1)) for l in range(order + 1)]
        )
        cap = np.empty(order)  # ∫_c^1 P_l(t) dt
        cap[0] = 1.0 - c
        for l in range(1, order):
            cap[l] = (p[l - 1] - p[l + 1]) / (2 * l + 1)
        y_sun = basis(env.sun_direction[None, :], order)[0]
        out += np.outer(2.0 * math.pi * cap[_band_of_index(order)] * y_sun, env.sun_radiance)
    return out


def _project_latlong(pixels: np.ndarray, order: int) -> np.ndarray:
    """Exact ∫ L Y dω of a nearest-pixel latlong map. pixels: (H, W, 3) → (order², 3)."""
    h, w = pixels.shape[:2]
    # θ part per row: A[row, i] = ∫_row Pbar_i(cos θ) sin^|m| θ · sin θ dθ, a trigonometric
    # polynomial of degree ≤ order in θ: Gauss–Legendre with order + 8 nodes per row.
    g = order + 8
    g_nodes, g_weights = np.polynomial.legendre.leggauss(g)
    dtheta = math.pi / h
    theta = (np.arange(h)[:, None] + 0.5 + 0.5 * g_nodes[None, :]) * dtheta  # (H, g)
    z = np.cos(theta).ravel()
    rho = np.sin(theta).ravel()
    signed_m = _m_of_index(order)
    row_part = _legendre_bar(z, order) * rho[:, None] ** np.abs(signed_m) * rho[:, None]
    row_part = (row_part * np.tile(0.5 * dtheta * g_weights, h)[:, None]).reshape(h, g, -1)
    row_part = row_part.sum(axis=1)  # (H, order²)
    # φ part per column, closed form: ∫ √2 cos mφ dφ, ∫ √2 sin mφ dφ, ∫ 1 dφ.
    phi_edges = np.arange(w + 1) * (2.0 * math.pi / w)
    col_part = np.empty((w, 2 * order - 1))  # index m + order − 1
    col_part[:, order - 1] = np.diff(phi_edges)
    for m in range(1, order):
        col_part[:, order - 1 + m] = _SQRT2 * np.diff(np.sin(m * phi_edges)) / m
        col_part[:, order - 1 - m] = -_SQRT2 * np.diff(np.cos(m * phi_edges)) / m
    per_m = np.einsum("hwc,wm->mhc", np.asarray(pixels, dtype=np.float64), col_part)
    return np.einsum("hi,ihc->ic", row_part, per_m[signed_m + order - 1])


def _project_by_pixel_centres(env, order: int, rows_per_chunk: int = 256) -> np.ndarray:
    """Σ L_pix Y(ω_centre) Ω_pix over all pixels with Ω_pix > 0. Returns (order², 3)."""
    out = np.zeros((order * order, 3))
    h = env.pixels.shape[0]
    for r0 in range(0, h, rows_per_chunk):
        rows = slice(r0, min(h, r0 + rows_per_chunk))
        omega = env.solid_angles[rows].ravel()
        used = omega > 0
        if not np.any(used):
            continue
        dirs = env.pixel_directions(rows).reshape(-1, 3)[used]
        values = np.asarray(env.pixels[rows], dtype=np.float64).reshape(-1, 3)[used]
        out += basis(dirs, order).T @ (omega[used][:, None] * values)
    return out


# ----------------------------------------------------------------------------- clamped cosine
def clamped_cosine_coefficients(order: int) -> np.ndarray:
    """Â_l = 2π ∫_0^1 t P_l(t) dt for l = 0 … order−1, shape (order,).

    π, 2π/3, π/4, 0, −π/24, 0, π/64, …; closed form: Â_1 = 2π/3, Â_l = 0 for odd l > 1,
    and for even l: Â_l = 2π (−1)^{l/2−1} / ((l+2)(l−1)) · C(l, l/2) / 2^l.
    """
    order = _check_order(order)
    out = np.zeros(order)
    for l in range(order):
        if l == 1:
            out[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            sign = -1.0 if (l // 2) % 2 == 0 else 1.0  # (−1)^{l/2 − 1}
            out[l] = 2.0 * math.pi * sign / ((l + 2) * (l - 1)) * math.comb(l, l // 2) / 2.0**l
    return out


def irradiance_coefficients(l_coeffs: np.ndarray, order: int | None = None) -> np.ndarray:
    """Â_l · ℓ_lm: coefficients of irradiance E(n) = Σ_i out_i Y_i(n).

    l_coeffs: (≥order², ...) radiance coefficients; order defaults to all of them.
    Returns (order², ...) (e.g. (order², 3) for RGB).
    """
    c = np.asarray(l_coeffs, dtype=np.float64)
    if order is None:
        order = math.isqrt(c.shape[0])
    order = _check_order(order)
    if c.shape[0] < order * order:
        raise ValueError(f"need {order * order} coefficients for order {order}, got {c.shape[0]}")
    a = clamped_cosine_coefficients(order)[_band_of_index(order)]
    return c[: order * order] * a.reshape((-1,) + (1,) * (c.ndim - 1))


def hemisphere_irradiance(env: Environment, order: int) -> np.ndarray:
    """(2, 3) RGB irradiance E(n) ≥ 0 that `env` gives normals facing +z and −z, from its
    `order`-band projection (`irradiance_coefficients`): the hemisphere ambient that
    stands for an environment in local shading."""
    coeffs = irradiance_coefficients(project_environment(env, order))
    return np.maximum(basis(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), order) @ coeffs,
                      0.0)


class _BakedLattice(Protocol):
    """What `transfer_blocks` reads of a lattice (`baking.lattice.Lattice`, a
    `baking.view_texels.HeldLattice`)."""

    @property
    def config(self) -> BakeConfig | None: ...

    @property
    def kind(self) -> str: ...


def transfer_blocks(lattice: _BakedLattice) -> int:
    """Transfer blocks per texel of `lattice` (a `baking.lattice.Lattice`): 2 for an SH bake
    with ``direct_light="pixels"`` (direct transfer T₀, then indirect T₁:
    `baking.integrator`), else 1."""
    config = lattice.config
    split = lattice.kind == "sh" and config is not None and config.direct_light == "pixels"
    return 2 if split else 1


def display_coefficients(env: Environment, order: int, blocks: int = 1,
                         window: str | npt.ArrayLike | None = None) -> np.ndarray:
    """(blocks·order², 3) environment coefficients an SH lattice's transfer blocks are
    dotted with (`project_environment` with `window`): for one block the environment's;
    for a split transfer (2 blocks) the environment without its sun (seen by the direct
    transfer: the renderer adds the sun per pixel), then the whole environment (seen by
    the indirect transfer: the sun's bounced light).

    Raises:
        ValueError: a split transfer under an environment without a sun to take out.
    """
    whole = project_environment(env, order, window)
    if blocks == 1:
        return whole
    if not hasattr(env, "without_sun"):
        raise ValueError("a split SH lattice (direct light per pixel) is shown under a "
                         "procedural sky with a sun (sky:...), not under this environment")
    return np.concatenate([project_environment(env.without_sun(), order, window), whole])


# ----------------------------------------------------------------------------- windowing
def window(order: int, kind: str = "hanning", width: float | None = None) -> np.ndarray:
    """Per-band factors (order,) that taper high bands to reduce ringing.

    kind "hanning": w_l = (1 + cos(π l / width)) / 2 for l < width, else 0;
    kind "lanczos": w_l = sinc(l / width) = sin(π l/width) / (π l/width).
    width defaults to ``order`` (so band order−1 keeps a small positive weight). Multiply
    coefficients of band l by w_l (see project_environment's ``window``; Sloan, "Stupid
    Spherical Harmonics Tricks", 2008).
    """
    order = _check_order(order)
    width = float(order if width is None else width)
    if width <= 0:
        raise ValueError(f"window width must be > 0, got {width}")
    l = np.arange(order, dtype=np.float64)
    if kind == "hanning":
        return np.where(l < width, 0.5 * (1.0 + np.cos(np.pi * l / width)), 0.0)
    if kind == "lanczos":
        return np.sinc(l / width)
    raise ValueError(f"unknown SH window {kind!r}; expected 'hanning' or 'lanczos'")


# ----------------------------------------------------------------------------- rotation
# Ivanic & Ruedenberg recurrence (paper Table 3, corrected per the 1998 errata), with
# centred indices: matrix element (s, t) of band l lives at [s + l, t + l].
def _c(m: int, l: int) -> int:
    """Centred index: array position of m ∈ [−l, l]."""
    return m + l


_YZX_ROWS = np.array([[1], [2], [0]])
_YZX_COLS = np.array([1, 2, 0])


def _band1(r: np.ndarray) -> np.ndarray:
    """Band-1 rotation: R in (y, z, x) order, i.e. r_{s,t} with 1↔x, −1↔y, 0↔z."""
    return r[_YZX_ROWS, _YZX_COLS]


def P(l: int, r1: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Table 3(c): _aP^l_{b,t} for a ∈ {−1, 0, 1}, b ∈ [−(l−1), l−1], t ∈ [−l, l].

    r1: band-1 matrix (3, 3), centred (r1[_c(a,1), _c(b,1)] = r_{a,b}); prev: band l−1
    (2l−1, 2l−1). Returns (3, 2l−1, 2l+1) indexed [_c(a,1), _c(b,l−1), _c(t,l)]:
    |t| < l: r_{a,0} R^{l−1}_{b,t};
    t = l:   r_{a,1} R^{l−1}_{b,l−1} − r_{a,−1} R^{l−1}_{b,−l+1};
    t = −l:  r_{a,1} R^{l−1}_{b,−l+1} + r_{a,−1} R^{l−1}_{b,l−1}.
    """
    sel = _p_selectors(l)
    return prev @ (r1 @ sel.reshape(3, -1)).reshape(sel.shape)


@lru_cache(maxsize=64)
def _p_selectors(l: int) -> np.ndarray:
    """(3, 2l−1, 2l+1) 0/±1 matrices S_k with _aP^l = R^{l−1} @ Σ_k r_{a,k} S_k (k = −1, 0, 1).

    Table 3(c) is linear in r_{a,·} and in R^{l−1}; writing it this way turns P into
    one matrix product for all three a.
    """
    sel = np.zeros((3, 2 * l - 1, 2 * l + 1))
    for t in range(-l + 1, l):  # |t| < l: r_{a,0} R_{b,t}
        sel[_c(0, 1), _c(t, l - 1), _c(t, l)] = 1.0
    # t = l: r_{a,1} R_{b,l−1} − r_{a,−1} R_{b,−l+1}
    sel[_c(1, 1), _c(l - 1, l - 1), _c(l, l)] = 1.0
    sel[_c(-1, 1), _c(-l + 1, l - 1), _c(l, l)] = -1.0
    # t = −l: r_{a,1} R_{b,−l+1} + r_{a,−1} R_{b,l−1}
    sel[_c(1, 1), _c(-l + 1, l - 1), _c(-l, l)] = 1.0
    sel[_c(-1, 1), _c(l - 1, l - 1), _c(-l, l)] += 1.0
    sel.setflags(write=False)
    return sel


@lru_cache(maxsize=64)
def _uvw(l: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Table 3(a): coefficients u, v, w as (2l+1, 2l+1) arrays over centred (s, t)."""
    s = np.arange(-l, l + 1, dtype=np.float64)[:, None]
    t = np.arange(-l, l + 1, dtype=np.float64)[None, :]
    d0 = (s == 0).astype(np.float64)
    denom = np.where(np.abs(t) == l, 2.0 * l * (2.0 * l - 1.0), (l + t) * (l - t))
    a = np.abs(s)
    u = np.sqrt((l + s) * (l - s) / denom)
    v = 0.5 * np.sqrt((1.0 + d0) * (l + a - 1.0) * (l + a) / denom) * (1.0 - 2.0 * d0)
    w = -0.5 * np.sqrt(np.maximum(0.0, (l - a - 1.0) * (l - a)) / denom) * (1.0 - d0)
    for arr in (u, v, w):
        arr.setflags(write=False)
    return u, v, w


# U, V, W (Table 3(b)) are sums of rows of _aP: each is a list of terms (a, rows, factors)
# meaning X_{s,t} = Σ_terms factors[s] · _aP[rows[s], t], with rows centred in band l−1.
# Rows whose coefficient u, v or w is zero get row 0 and factor 0.
Terms = list[tuple[int, list[int], list[float]]]


def _row(b: int, l: int) -> int:
    return _c(b, l - 1) if abs(b) <= l - 1 else 0


def U(l: int) -> Terms:
    """U_{s,t} = 0P_{s,t} (rows |s| = l are never used: u = 0 there)."""
    s_all = range(-l, l + 1)
    return [(0, [_row(s, l) for s in s_all], [1.0 if abs(s) < l else 0.0 for s in s_all])]


def V(l: int) -> Terms:
    """V_{s,t}. s = 0: 1P_{1,t} + −1P_{−1,t};
    s > 0: 1P_{s−1,t}·sqrt(1+δ_{s,1}) − −1P_{−s+1,t}·(1−δ_{s,1});
    s < 0: 1P_{s+1,t}·(1−δ_{s,−1}) + −1P_{−s−1,t}·sqrt(1+δ_{s,−1})."""
    p1_rows, p1_f, pm_rows, pm_f = [], [], [], []
    for s in range(-l, l + 1):
        d1 = 1.0 if abs(s) == 1 else 0.0
        if s == 0:
            b1, f1, bm, fm = 1, 1.0, -1, 1.0
        elif s > 0:
            b1, f1, bm, fm = s - 1, math.sqrt(1.0 + d1), -s + 1, -(1.0 - d1)
        else:
            b1, f1, bm, fm = s + 1, 1.0 - d1, -s - 1, math.sqrt(1.0 + d1)
        p1_rows.append(_row(b1, l))
        p1_f.append(f1)
        pm_rows.append(_row(bm, l))
        pm_f.append(fm)
    return [(1, p1_rows, p1_f), (-1, pm_rows, pm_f)]


def W(l: int) -> Terms:
    """W_{s,t}. s > 0: 1P_{s+1,t} + −1P_{−s−1,t}; s < 0: 1P_{s−1,t} − −1P_{−s+1,t};
    unused where w = 0 (s = 0 and |s| ≥ l − 1)."""
    p1_rows, p1_f, pm_rows, pm_f = [], [], [], []
    for s in range(-l, l + 1):
        if s == 0 or abs(s) >= l - 1:
            b1, f1, bm, fm = 0, 0.0, 0, 0.0
        elif s > 0:
            b1, f1, bm, fm = s + 1, 1.0, -s - 1, 1.0
        else:
            b1, f1, bm, fm = s - 1, 1.0, -s + 1, -1.0
        p1_rows.append(_row(b1, l))
        p1_f.append(f1)
        pm_rows.append(_row(bm, l))
        pm_f.append(fm)
    return [(1, p1_rows, p1_f), (-1, pm_rows, pm_f)]


@lru_cache(maxsize=64)
def _recurrence_tables(l: int) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 17 flattened to 5 terms (uU, vV ×2, wW ×2): R^l = Σ_k coef[k] ∘ P_flat[rows[k]].

    rows (5, 2l+1) index the (3·(2l−1), 2l+1) reshaped output of :func:`P`;
    coef (5, 2l+1, 2l+1) = (u, v or w)[s, t] · factor[s]. Cached per band.
    """
    u, v, w = _uvw(l)
    rows, coefs = [], []
    for weight, terms in ((u, U(l)), (v, V(l)), (w, W(l))):
        for a, term_rows, factors in terms:
            rows.append(_c(a, 1) * (2 * l - 1) + np.asarray(term_rows))
            coefs.append(weight * np.asarray(factors)[:, None])
    rows_arr, coef_arr = np.stack(rows), np.stack(coefs)
    rows_arr.setflags(write=False)
    coef_arr.setflags(write=False)
    return rows_arr, coef_arr


def _next_band(r1: np.ndarray, prev: np.ndarray, l: int) -> np.ndarray:
    """Eq. 17: R^l_{s,t} = u U + v V + w W from band 1 and band l−1: (2l+1, 2l+1)."""
    rows, coef = _recurrence_tables(l)
    p_flat = P(l, r1, prev).reshape(3 * (2 * l - 1), 2 * l + 1)
    return np.einsum("kst,kst->st", coef, p_flat[rows])


def _check_rotation_matrix(r: np.ndarray) -> np.ndarray:
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be a (3, 3) matrix, got shape {r.shape}")
    return r


def band_rotation(r: np.ndarray, l: int) -> np.ndarray:
    """(2l+1, 2l+1) rotation of band l's coefficients (centred m order −l … l).

    Same contract as :func:`rotation`. Builds bands 1 … l by the recurrence.
    """
    r = _check_rotation_matrix(r)
    if l == 0:
        return np.ones((1, 1))
    r1 = _band1(r)
    band = r1
    for k in range(2, l + 1):
        band = _next_band(r1, band, k)
    return band


def rotation(r: np.ndarray, order: int) -> np.ndarray:
    """Block-diagonal SH rotation (order², order²) for a 3×3 rotation matrix r.

    Contract: if c are the coefficients of f, ``rotation(r, order) @ c`` are those of
    g(ω) = f(rᵀω). Orthogonal; rotation(a) @ rotation(b) = rotation(a @ b).
    r must be a proper rotation (orthonormal, det +1); it is not re-orthonormalised.
    """
    r = _check_rotation_matrix(r)
    order = _check_order(order)
    out = np.zeros((order * order, order * order))
    out[0, 0] = 1.0
    if order == 1:
        return out
    r1 = _band1(r)
    out[1:4, 1:4] = r1
    band = r1
    for l in range(2, order):
        band = _next_band(r1, band, l)
        out[l * l : (l + 1) ** 2, l * l : (l + 1) ** 2] = band
    return out


def rotation_from_az_el(az_deg: float, el_deg: float) -> np.ndarray:
    """3×3 rotation for ``--env-rotation AZ,EL`` (degrees).

    R = Rz(az) · Ry(−el): tilt by the elevation towards +z in the x–z plane, then turn
    by the azimuth about +z (counter-clockwise seen from +z). R maps +x to
    (cos el cos az, cos el sin az, sin el); with the rotation contract
    (L'(ω) = L(Rᵀω)) the environment's content that was at +x moves there, and
    (az, el) = (0, 0) is the identity.
    """
    az = math.radians(az_deg)
    el = math.radians(el_deg)
    ca, sa, ce, se = math.cos(az), math.sin(az), math.cos(el), math.sin(el)
    rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[ce, 0.0, -se], [0.0, 1.0, 0.0], [se, 0.0, ce]])  # Ry(−el)
    return rz @ ry
