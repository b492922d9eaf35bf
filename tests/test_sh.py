"""Tests of baking.sh: basis, projection, clamped cosine, windows, rotation.

Tolerance ladder (each assertion says which rung it is on and why):
* closed forms and exact quadratures: 1e-10 absolute on O(1) numbers (rounding of a
  few hundred float64 operations is ~1e-14; 1e-10 leaves room, still catches any
  sign or index error, which is O(1));
* fast vs slow evaluation of the same formula: 1e-10 as well (both are deterministic);
* non-exact quadratures: from the measured convergence rate of that quadrature, with
  a 10× margin, stated where used.
"""

# ruff: noqa: E741  (l is the SH band index, as in the literature)
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import integrate, special
from scipy.spatial.transform import Rotation

from isolume.baking import environment as envmod
from isolume.baking import sh

EXACT = 1e-10  # closed forms / exact quadrature, see module docstring


# ----------------------------------------------------------------------------- helpers
def _random_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _random_rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


def _complex_sh(l: int, m: int, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """scipy's complex Y_l^m (with Condon–Shortley phase), θ polar, φ azimuth."""
    if hasattr(special, "sph_harm_y"):  # scipy ≥ 1.15
        return special.sph_harm_y(l, m, theta, phi)
    return special.sph_harm(m, l, phi, theta)  # older: (m, l, azimuth, polar)


def _real_sh_reference(dirs: np.ndarray, order: int) -> np.ndarray:
    """Real SH without the Condon–Shortley phase, from scipy's complex ones.

    Ours = √2 (−1)^m Re Y_l^m (m > 0), √2 (−1)^m Im Y_l^|m| (m < 0), Y_l^0 (m = 0):
    the (−1)^m undoes scipy's Condon–Shortley phase.
    """
    theta = np.arctan2(np.hypot(dirs[:, 0], dirs[:, 1]), dirs[:, 2])
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    out = np.empty((dirs.shape[0], order * order))
    for l in range(order):
        for m in range(-l, l + 1):
            y = _complex_sh(l, abs(m), theta, phi)
            if m > 0:
                v = math.sqrt(2.0) * (-1) ** m * y.real
            elif m < 0:
                v = math.sqrt(2.0) * (-1) ** m * y.imag
            else:
                v = y.real
            out[:, l * (l + 1) + m] = v
    return out


def _gl_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Independent product quadrature: n Gauss–Legendre z × 2n uniform φ (exact to degree
    2n − 1 in (x, y, z))."""
    z, wz = np.polynomial.legendre.leggauss(n)
    phi = 2.0 * math.pi * (np.arange(2 * n) + 0.5) / (2 * n)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    rho = np.sqrt(1.0 - zz**2)
    dirs = np.stack([rho * np.cos(pp), rho * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    w = (wz[:, None] * np.full(2 * n, math.pi / n)[None, :]).ravel()
    return dirs, w


def _rz(alpha: float) -> np.ndarray:
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- basis
def test_basis_matches_scipy_up_to_band_10():
    rng = np.random.default_rng(1)
    dirs = np.vstack(
        [_random_dirs(rng, 300), [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [-1, 0, 0]]]
    )
    order = 11  # bands 0 … 10
    ours = sh.basis(dirs, order)
    ref = _real_sh_reference(dirs, order)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=EXACT)
    for k in range(1, order):  # a lower order is a prefix of the higher one
        np.testing.assert_array_equal(sh.basis(dirs, k), ours[:, : k * k])


def test_band_0_and_1_are_the_documented_polynomials():
    rng = np.random.default_rng(2)
    d = _random_dirs(rng, 50)
    y = sh.basis(d, 2)
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    np.testing.assert_allclose(y[:, 0], 0.5 / math.sqrt(math.pi), atol=EXACT)
    np.testing.assert_allclose(y[:, 1:4], c1 * d[:, [1, 2, 0]], atol=EXACT)  # (y, z, x)


def test_orthonormal_by_quadrature_up_to_band_10():
    order = 11
    dirs, w = _gl_grid(12)  # exact for Y_i Y_j of degree ≤ 20 ≤ 23
    y = sh.basis(dirs, order)
    np.testing.assert_allclose(y.T @ (w[:, None] * y), np.eye(order * order), atol=EXACT)


def test_sphere_quadrature_and_project_function_are_exact_for_band_limited_f():
    _, w = sh.sphere_quadrature(9)
    assert math.isclose(w.sum(), 4.0 * math.pi, rel_tol=1e-13)
    rng = np.random.default_rng(3)
    c = rng.normal(size=(36, 2))

    def f(d):
        return sh.basis(d, 6) @ c

    np.testing.assert_allclose(sh.project_function(f, 6), c, atol=EXACT)


# ----------------------------------------------------------------------------- rotation
def _reference_band_rotation(r: np.ndarray, order: int) -> list[np.ndarray]:
    """Slow scalar transcription of paper Table 3 / eq. 17 (errata applied), per element."""
    bands = [np.ones((1, 1)), r[np.ix_([1, 2, 0], [1, 2, 0])]]

    def el(l, s, t):
        return bands[l][s + l, t + l]

    def p(a, b, t, l):
        if t == l:
            return el(1, a, 1) * el(l - 1, b, l - 1) - el(1, a, -1) * el(l - 1, b, -l + 1)
        if t == -l:
            return el(1, a, 1) * el(l - 1, b, -l + 1) + el(1, a, -1) * el(l - 1, b, l - 1)
        return el(1, a, 0) * el(l - 1, b, t)

    for l in range(2, order):
        m = np.zeros((2 * l + 1, 2 * l + 1))
        for s in range(-l, l + 1):
            for t in range(-l, l + 1):
                den = 2 * l * (2 * l - 1) if abs(t) == l else (l + t) * (l - t)
                d0 = 1.0 if s == 0 else 0.0
                u = math.sqrt((l + s) * (l - s) / den)
                v = 0.5 * math.sqrt((1 + d0) * (l + abs(s) - 1) * (l + abs(s)) / den) * (1 - 2 * d0)
                w = -0.5 * math.sqrt(max(0, (l - abs(s) - 1) * (l - abs(s))) / den) * (1 - d0)
                total = 0.0
                if u:
                    total += u * p(0, s, t, l)
                if v:
                    if s == 0:
                        vv = p(1, 1, t, l) + p(-1, -1, t, l)
                    elif s > 0:
                        d1 = 1.0 if s == 1 else 0.0
                        vv = p(1, s - 1, t, l) * math.sqrt(1 + d1)
                        if not d1:
                            vv -= p(-1, -s + 1, t, l)
                    else:
                        d1 = 1.0 if s == -1 else 0.0
                        vv = p(-1, -s - 1, t, l) * math.sqrt(1 + d1)
                        if not d1:
                            vv += p(1, s + 1, t, l)
                    total += v * vv
                if w:
                    if s > 0:
                        ww = p(1, s + 1, t, l) + p(-1, -s - 1, t, l)
                    else:
                        ww = p(1, s - 1, t, l) - p(-1, -s + 1, t, l)
                    total += w * ww
                m[s + l, t + l] = total
        bands.append(m)
    return bands


def test_vectorised_recurrence_matches_scalar_transcription():
    r = _random_rotation(4)
    ref = _reference_band_rotation(r, 9)
    for l in range(9):
        np.testing.assert_allclose(sh.band_rotation(r, l), ref[l], atol=EXACT)


@pytest.mark.parametrize("order", range(1, 10))
def test_rotation_is_orthogonal_block_diagonal_and_identity_at_i(order):
    r = _random_rotation(10 + order)
    m = sh.rotation(r, order)
    np.testing.assert_allclose(m @ m.T, np.eye(order * order), atol=EXACT)
    band = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
    assert np.all(m[band[:, None] != band[None, :]] == 0)
    for l in range(order):
        block = m[l * l : (l + 1) ** 2, l * l : (l + 1) ** 2]
        np.testing.assert_allclose(block, sh.band_rotation(r, l), atol=EXACT)
    np.testing.assert_allclose(sh.rotation(np.eye(3), order), np.eye(order * order), atol=EXACT)


def test_rotation_composes():
    a, b = _random_rotation(20), _random_rotation(21)
    for order in (2, 5, 9):
        np.testing.assert_allclose(
            sh.rotation(a, order) @ sh.rotation(b, order), sh.rotation(a @ b, order), atol=EXACT
        )


def test_z_rotation_closed_form_per_band():
    """g(ω) = f(Rz(α)ᵀω) = f(φ − α): (c_m, s_m) → (c cos mα − s sin mα, c sin mα + s cos mα)."""
    for alpha in (0.3, 1.0, -2.2, math.pi):
        for l in range(9):
            expected = np.zeros((2 * l + 1, 2 * l + 1))
            expected[l, l] = 1.0
            for m in range(1, l + 1):
                c, s = math.cos(m * alpha), math.sin(m * alpha)
                expected[l + m, l + m] = c
                expected[l + m, l - m] = -s
                expected[l - m, l + m] = s
                expected[l - m, l - m] = c
            np.testing.assert_allclose(sh.band_rotation(_rz(alpha), l), expected, atol=EXACT)


@pytest.mark.parametrize("order", range(1, 9))
def test_rotating_coefficients_equals_reprojecting_rotated_function(order):
    rng = np.random.default_rng(30 + order)
    r = _random_rotation(40 + order)
    c = rng.normal(size=order * order)
    dirs, w = _gl_grid(order + 1)  # f(Rᵀω) Y(ω) has degree ≤ 2(order − 1): exact
    g = sh.basis(dirs @ r, order) @ c  # rows: (Rᵀω)ᵀ = ωᵀ R
    reprojected = sh.basis(dirs, order).T @ (w * g)
    np.testing.assert_allclose(sh.rotation(r, order) @ c, reprojected, atol=EXACT)


def test_rotated_environment_reprojects_to_rotated_coefficients():
    """SH rotation of a sky's coefficients vs projecting the rotated sky's radiance.

    zenith = horizon makes the sky C¹ (only the smoothstep blend, whose second
    derivative jumps on two circles that the rotation tilts against the grid). The
    quadrature error of project_function then falls ~16× per doubling of n
    (measured 2e-5, 1.3e-6, 1.0e-7 at n = 64, 128, 256); at n = 256 a bound of 1e-6
    keeps a 10× margin.
    """
    sky = envmod.sky(zenith=1.0, horizon=1.0, ground=0.2, horizon_blur=10)
    r = _random_rotation(50)
    rotated = envmod.rotated(sky, r)
    via_matrix = sh.project_environment(rotated, 5)
    np.testing.assert_allclose(via_matrix, sh.rotation(r, 5) @ sh.project_environment(sky, 5))
    reprojected = sh.project_function(rotated.radiance, 5, n=256)
    np.testing.assert_allclose(via_matrix, reprojected, rtol=0, atol=1e-6)


def test_rotation_from_az_el():
    for az, el in ((0, 0), (30, 20), (-120, 75), (200, -10)):
        r = sh.rotation_from_az_el(az, el)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=EXACT)
        assert math.isclose(np.linalg.det(r), 1.0, rel_tol=1e-12)
        a, e = math.radians(az), math.radians(el)
        target = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
        np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], target, atol=EXACT)
    np.testing.assert_allclose(sh.rotation_from_az_el(0, 0), np.eye(3), atol=EXACT)
    # Pure azimuth is a turn about +z (the horizon stays put).
    np.testing.assert_allclose(sh.rotation_from_az_el(35, 0), _rz(math.radians(35)), atol=EXACT)


# ----------------------------------------------------------------------------- clamped cosine
def test_clamped_cosine_closed_form():
    a = sh.clamped_cosine_coefficients(11)
    listed = [math.pi, 2 * math.pi / 3, math.pi / 4, 0, -math.pi / 24, 0, math.pi / 64]
    np.testing.assert_allclose(a[:7], listed, atol=EXACT)
    x, wx = np.polynomial.legendre.leggauss(16)  # t·P_l(t) on [0, 1]: degree ≤ 11, exact
    t, wt = 0.5 * (x + 1.0), 0.5 * wx
    numeric = [2 * math.pi * np.sum(wt * t * special.eval_legendre(l, t)) for l in range(11)]
    np.testing.assert_allclose(a, numeric, atol=EXACT)


def test_projecting_clamped_cosine_gives_a_l_y_lm():
    """∫ max(0, n·ω) Y(ω) dω = Â_l Y(n), for n = +z and random n.

    Quadrature in a frame whose z axis is n, with Gauss–Legendre split at the kink
    (n·ω = 0): the integrand is a polynomial on each half, so it is exact.
    """
    order = 11
    rng = np.random.default_rng(5)
    x, wx = np.polynomial.legendre.leggauss(order + 2)
    nphi = 2 * order + 2
    phi = 2 * math.pi * (np.arange(nphi) + 0.5) / nphi
    z = 0.5 * (x + 1.0)  # upper half only: the lower half contributes 0
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    rho = np.sqrt(1 - zz**2)
    local = np.stack([rho * np.cos(pp), rho * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    w = np.outer(0.5 * wx, np.full(nphi, 2 * math.pi / nphi)).ravel()
    a = sh.clamped_cosine_coefficients(order)[np.repeat(np.arange(order), 2 * np.arange(order) + 1)]
    for n in [np.array([0.0, 0.0, 1.0]), *_random_dirs(rng, 4)]:
        # frame: columns t, b, n
        t = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t /= np.linalg.norm(t)
        frame = np.stack([t, np.cross(n, t), n], axis=1)
        dirs = local @ frame.T
        proj = sh.basis(dirs, order).T @ (w * (dirs @ n))
        np.testing.assert_allclose(proj, a * sh.basis(n, order)[0], atol=EXACT)


def test_irradiance_of_constant_sky_is_pi_l():
    rng = np.random.default_rng(6)
    env = envmod.constant([0.5, 1.0, 2.0])
    e = sh.irradiance_coefficients(sh.project_environment(env, 5))
    irr = sh.basis(_random_dirs(rng, 20), 5) @ e
    np.testing.assert_allclose(
        irr, np.tile(math.pi * np.array([0.5, 1.0, 2.0]), (20, 1)), atol=EXACT
    )


# ----------------------------------------------------------------------------- windowing
def test_window_values():
    h = sh.window(5, "hanning")
    np.testing.assert_allclose(h, 0.5 * (1 + np.cos(np.pi * np.arange(5) / 5)), atol=EXACT)
    lz = sh.window(5, "lanczos")
    assert lz[0] == 1.0 and np.all(np.diff(lz) < 0) and np.all(lz > 0)
    with pytest.raises(ValueError, match="unknown SH window"):
        sh.window(5, "gauss")


def _disk_irradiance_theory(order: int, radius: float, window: np.ndarray) -> np.ndarray:
    """Order-n SH irradiance of a unit-irradiance disk at +z, along θ ∈ [0, π] (4001 pts),
    from scipy Legendre integrals (Funk–Hecke), independent of baking.sh:
    E(θ) = Σ_l w_l Â_l λ_l (2l+1)/(4π) P_l(cos θ) L,  λ_l = 2π ∫_{cos r}^1 P_l,
    Â_l = 2π ∫_0^1 t P_l, L = 1/(π sin² r)."""
    theta = np.linspace(0.0, math.pi, 4001)
    radiance = 1.0 / (math.pi * math.sin(radius) ** 2)
    e = np.zeros_like(theta)
    for l in range(order):

        def p_l(t, l=l):
            return special.eval_legendre(l, t)

        lam = 2 * math.pi * integrate.quad(p_l, math.cos(radius), 1.0, epsabs=1e-14)[0]
        a_l = 2 * math.pi * integrate.quad(lambda t, f=p_l: t * f(t), 0, 1, epsabs=1e-14)[0]
        e += (
            window[l]
            * a_l
            * lam
            * (2 * l + 1)
            / (4 * math.pi)
            * special.eval_legendre(l, np.cos(theta))
            * radiance
        )
    return e


def test_window_reduces_negative_lobe_of_small_source():
    """A 5°-radius disk at +z: the order-5 SH irradiance rings negative on the far side.

    The unwindowed minimum/peak ratio from baking.sh must equal the Funk–Hecke theory
    computed with scipy (1e-8: quad's absolute error 1e-14 on O(1) integrals, summed
    over 5 bands, divided by a peak of O(1)), it is ≈ −3.1 %, and Hanning and Lanczos
    windows make it smaller in magnitude (measured −1.7 % and −1.4 %).
    """
    order, radius = 5, math.radians(5.0)
    env = envmod.sky(zenith=0, horizon=0, ground=0, sun=1.0, sun_el=90, sun_radius=5.0)
    theta = np.linspace(0.0, math.pi, 4001)
    dirs = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)

    def ratio(window):
        e = (
            sh.basis(dirs, order)
            @ sh.irradiance_coefficients(sh.project_environment(env, order, window=window))[:, 0]
        )
        return e.min() / e.max()

    theory = _disk_irradiance_theory(order, radius, np.ones(order))
    plain = ratio(None)
    assert plain == pytest.approx(theory.min() / theory.max(), abs=1e-8)
    assert -0.035 < plain < -0.025
    for kind in ("hanning", "lanczos"):
        windowed = ratio(kind)
        w_theory = _disk_irradiance_theory(order, radius, sh.window(order, kind))
        assert windowed == pytest.approx(w_theory.min() / w_theory.max(), abs=1e-8)
        assert abs(windowed) < 0.6 * abs(plain)


# ----------------------------------------------------------------------------- projection
def test_project_constant_and_window_factors():
    env = envmod.constant([1.0, 2.0, 3.0])
    c = sh.project_environment(env, 4)
    assert c.shape == (16, 3)
    np.testing.assert_allclose(c[0], math.sqrt(4 * math.pi) * np.array([1.0, 2.0, 3.0]))
    assert np.all(c[1:] == 0)
    sky = envmod.sky(sun=3.0)
    band = np.repeat(np.arange(4), 2 * np.arange(4) + 1)
    np.testing.assert_allclose(
        sh.project_environment(sky, 4, window="hanning"),
        sh.project_environment(sky, 4) * sh.window(4, "hanning")[band][:, None],
    )


def test_latlong_projection_is_exact_integral_of_nearest_pixel_map():
    """Fast separable projection vs slow 12×12 Gauss–Legendre per pixel (both exact to
    rounding for these smooth per-pixel integrands): fast-vs-slow rung, 1e-10."""
    rng = np.random.default_rng(7)
    h, w, order = 6, 12, 6
    env = envmod.image_from_array(rng.random((h, w, 3)), "latlong")
    px = env.pixels.astype(np.float64)
    x, wx = np.polynomial.legendre.leggauss(12)
    slow = np.zeros((order * order, 3))
    for row in range(h):
        th = (row + 0.5 + 0.5 * x) * math.pi / h
        wt = wx * 0.5 * math.pi / h * np.sin(th)
        for col in range(w):
            ph = (col + 0.5 + 0.5 * x) * 2 * math.pi / w
            tt, pp = np.meshgrid(th, ph, indexing="ij")
            d = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
            weights = np.outer(wt, wx * math.pi / w).ravel()
            slow += np.outer(sh.basis(d.reshape(-1, 3), order).T @ weights, px[row, col])
    np.testing.assert_allclose(sh.project_environment(env, order), slow, atol=EXACT)


def test_angular_projection_converges_to_function_coefficients():
    """An angular map sampling a band-2 function at pixel centres: the midpoint rule with
    exact pixel solid angles has error O(pixel²) (plus O(pixel) from rim pixels, whose
    centre lies outside their in-disk part). Measured max error 1.2e-3 at N = 64 and
    3e-4 at N = 128 on coefficients of size ~1; bound 3e-3 at N = 64."""
    rng = np.random.default_rng(8)
    c = np.zeros((9, 3))
    c[0] = 3.0
    c[1:] = 0.3 * rng.normal(size=(8, 3))
    n = 64
    dirs = envmod.angular_pixel_directions(n).reshape(-1, 3)
    px = (sh.basis(dirs, 3) @ c).reshape(n, n, 3)
    env = envmod.image_from_array(np.maximum(px, 0), "angular")
    assert np.all(px > 0)
    np.testing.assert_allclose(sh.project_environment(env, 3), c, atol=3e-3)


def test_sky_projection_zenith_sun_matches_zonal_quadrature():
    """Sun at the zenith: everything is zonal; 2π ∫ L(z) Y_l0(z) dz by Gauss–Legendre on
    the polynomial pieces (breakpoints including cos r) is exact → 1e-10."""
    order = 6
    env = envmod.sky(sun=(3.0, 2.0, 1.0), sun_el=90, sun_radius=5, horizon_blur=3)
    breaks = sorted([*env.gradient_breakpoints(), env.sun_cos_radius])
    x, wx = np.polynomial.legendre.leggauss(40)
    zonal = np.array([l * (l + 1) for l in range(order)])
    ref = np.zeros((order * order, 3))
    for z0, z1 in itertools.pairwise(breaks):
        z = 0.5 * (z1 - z0) * x + 0.5 * (z1 + z0)
        d = np.stack([np.sqrt(1 - z * z), np.zeros_like(z), z], axis=1)
        wz = 0.5 * (z1 - z0) * wx * 2 * math.pi
        ref[zonal] += sh.basis(d, order)[:, zonal].T @ (wz[:, None] * env.radiance(d))
    np.testing.assert_allclose(sh.project_environment(env, order), ref, atol=EXACT)


def test_sky_sun_direction_agrees_with_rotation():
    order = 6
    kw = dict(zenith=0, horizon=0, ground=0, sun=1.0, sun_radius=4.0)
    up = sh.project_environment(envmod.sky(sun_el=90, **kw), order)
    env = envmod.sky(sun_az=130, sun_el=25, **kw)
    s = env.sun_direction
    axis = np.cross([0.0, 0.0, 1.0], s)
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.acos(s[2])).as_matrix()
    np.testing.assert_allclose(turn @ [0, 0, 1.0], s, atol=EXACT)
    np.testing.assert_allclose(
        sh.rotation(turn, order) @ up, sh.project_environment(env, order), atol=EXACT
    )


class _PolynomialEnvironment(envmod.Environment):
    """A band-limited environment with no special projection: exercises the fallback."""

    spec = "test:polynomial"
    mean_radiance = np.array([1.0, 1.0, 1.0])

    def radiance(self, dirs):
        d = np.asarray(dirs)
        return np.stack([1 + d[:, 0] * d[:, 1], 1 + d[:, 2] ** 3, np.ones(len(d))], axis=1)

    def sample(self, u):
        raise NotImplementedError

    def pdf(self, dirs):
        raise NotImplementedError


def test_generic_projection_fallback_is_exact_for_band_limited_environment():
    env = _PolynomialEnvironment()
    exact = sh.project_function(env.radiance, 5, n=8)  # degree ≤ 3 + 4 ≤ 15: exact
    np.testing.assert_allclose(sh.project_environment(env, 5), exact, atol=EXACT)
