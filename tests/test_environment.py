"""Tests of baking.environment: mappings, solid angles, sampling vs pdf, files, specs.

Statistical tests use fixed seeds (deterministic), with significance chosen as if they
were not: the χ² tests share a family-wise level of 1e-3 (Šidák correction over the
``N_CHI2`` tests below), Monte Carlo integrals must agree within 4 standard errors
(two-sided p ≈ 6e-5 each).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from isolume.baking import environment as envmod
from isolume.baking.environment import EnvSpecError
from isolume.baking.sh import rotation_from_az_el

PROBES = Path(__file__).resolve().parents[2] / "shared" / "data" / "probes"

N_CHI2 = 5  # latlong, angular, sky, constant, cone
ALPHA = 1.0 - (1.0 - 1e-3) ** (1.0 / N_CHI2)  # Šidák: family-wise 1e-3
NZ, NPHI = 8, 16  # χ² cells: uniform in z = cos θ and in φ (equal solid angles)


# ----------------------------------------------------------------------------- helpers
def _random_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cell_index(dirs: np.ndarray) -> np.ndarray:
    """Flat χ² cell of each direction: z band (from the top) × φ sector."""
    zi = np.clip(((1.0 - dirs[:, 2]) * 0.5 * NZ).astype(int), 0, NZ - 1)
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * math.pi)
    pi_ = np.clip((phi / (2 * math.pi) * NPHI).astype(int), 0, NPHI - 1)
    return zi * NPHI + pi_


def _cell_centre(zi: int, pi_: int) -> np.ndarray:
    z = 1.0 - 2.0 * (zi + 0.5) / NZ
    phi = 2 * math.pi * (pi_ + 0.5) / NPHI
    rho = math.sqrt(1 - z * z)
    return np.array([rho * math.cos(phi), rho * math.sin(phi), z])


def _chi2_pvalue(observed: np.ndarray, probs: np.ndarray) -> float:
    """Pearson χ² p-value; cells with < 5 expected samples are pooled (Mitsuba style)."""
    n = observed.sum()
    expected = probs * n
    assert not np.any((expected == 0) & (observed > 0)), "samples where the pdf is 0"
    low = expected < 5
    obs, exp = list(observed[~low].astype(float)), list(expected[~low])
    if np.any(low):
        if expected[low].sum() >= 5 or not exp:
            obs.append(observed[low].sum())
            exp.append(expected[low].sum())
        else:
            i = int(np.argmin(exp))
            obs[i] += observed[low].sum()
            exp[i] += expected[low].sum()
    obs_a, exp_a = np.array(obs), np.array(exp)
    stat = np.sum((obs_a - exp_a) ** 2 / exp_a)
    return float(stats.chi2.sf(stat, len(obs_a) - 1))


def _sun_latlong_map(h: int, w: int) -> np.ndarray:
    """A sky-ish gradient with a very bright 'sun' pixel (2000×)."""
    rows = np.linspace(1.0, 0.1, h)[:, None, None]
    px = np.broadcast_to(rows * np.array([0.4, 0.6, 1.0]), (h, w, 3)).copy()
    px[h // 4, w // 3] = 2000.0
    return px


def _sun_angular_map(n: int, sun_cell: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """A smooth map with a one-pixel sun on the direction of a χ² cell centre; returns
    (pixels (n, n, 3), sun pixel (row, col))."""
    dirs = envmod.angular_pixel_directions(n)
    px = 0.2 + 0.1 * (dirs + 1.0)  # (n, n, 3), smooth and positive
    row, col = envmod.angular_dir_to_pixel(_cell_centre(*sun_cell)[None, :], n)
    px[row[0], col[0]] = 3000.0
    return px, (int(row[0]), int(col[0]))


def _latlong_cell_probs(env: envmod.ImageEnvironment) -> np.ndarray:
    """Exact cell probabilities of a latlong map's sampler: its pdf is constant per pixel
    and pixels are rectangles in (z, φ), where dω = dz dφ, so a cell gets
    Σ pdf_pixel · |z overlap| · |φ overlap|."""
    h, w = env.shape
    pdf = env.sampler.p / env.solid_angles
    z_pix = np.cos(math.pi * np.arange(h + 1) / h)  # decreasing
    z_cell = 1.0 - 2.0 * np.arange(NZ + 1) / NZ
    oz = np.clip(
        np.minimum(z_cell[:-1, None], z_pix[None, :-1])
        - np.maximum(z_cell[1:, None], z_pix[None, 1:]),
        0,
        None,
    )
    phi_pix = 2 * math.pi * np.arange(w + 1) / w
    phi_cell = 2 * math.pi * np.arange(NPHI + 1) / NPHI
    op = np.clip(
        np.minimum(phi_cell[1:, None], phi_pix[None, 1:])
        - np.maximum(phi_cell[:-1, None], phi_pix[None, :-1]),
        0,
        None,
    )
    return (oz @ pdf @ op.T).ravel()


def _angular_cell_probs(env: envmod.ImageEnvironment, sub: int = 16) -> np.ndarray:
    """Cell probabilities of an angular map's sampler, by the same change of variables the
    sampler uses: each pixel's probability spread uniformly over sub×sub points of its
    square, pushed through the direction formula. Exact except for pixels that a cell
    boundary crosses (error ≲ p_pixel/(2·sub) each, random in sign); the test puts the
    sun (most of the probability) inside one cell, and comparing sub = 16 with sub = 64
    changes no cell by more than 0.05 standard errors of the test's counts."""
    n = env.shape[0]
    rows, cols = np.nonzero(env.sampler.p > 0)
    offs = (np.arange(sub) + 0.5) / sub
    du, dv = (g.ravel() for g in np.meshgrid(offs, offs, indexing="ij"))
    a = -1.0 + (cols[:, None] + dv[None, :]) * (2.0 / n)
    b = 1.0 - (rows[:, None] + du[None, :]) * (2.0 / n)
    dirs = envmod.angular_image_to_dir(a.ravel(), b.ravel())
    weights = np.repeat(env.sampler.p[rows, cols] / sub**2, sub * sub)
    return np.bincount(_cell_index(dirs), weights, minlength=NZ * NPHI)


# ----------------------------------------------------------------------------- mappings
@pytest.mark.parametrize("shape", [(4, 8), (32, 64), (33, 70), (500, 1000)])
def test_latlong_solid_angles_sum_to_4pi(shape):
    omega = envmod.latlong_solid_angles(*shape)
    assert omega.shape == shape
    # exact formula: only summation rounding (~1e-16 per term) remains; spec asks 1e-6
    assert omega.sum() == pytest.approx(4 * math.pi, rel=1e-12)


@pytest.mark.parametrize("n", [8, 16, 33, 64, 256])
def test_angular_solid_angles_sum_to_4pi(n):
    omega = envmod.angular_solid_angles(n)
    # Spec: 1e-3. Clipped, kink-split Gauss–Legendre gives 2.4e-8 at n = 8, 3.5e-10 at
    # 16, 8e-14 at 64 (measured), so 1e-6 still leaves a 40× margin.
    assert omega.sum() == pytest.approx(4 * math.pi, rel=1e-6)
    np.testing.assert_allclose(omega, omega[::-1], atol=1e-15)  # mirror symmetric
    np.testing.assert_allclose(omega, omega.T, atol=1e-15)
    assert np.all(omega[~envmod.angular_pixels_in_disk(n)] == 0)
    assert np.all(omega[envmod.angular_pixels_inside_disk(n)] > 0)


def test_latlong_pixel_centres_round_trip():
    h, w = 24, 48
    dirs = envmod.latlong_pixel_directions(h, w).reshape(-1, 3)
    rows, cols = envmod.latlong_dir_to_pixel(dirs, h, w)
    np.testing.assert_array_equal(rows, np.repeat(np.arange(h), w))
    np.testing.assert_array_equal(cols, np.tile(np.arange(w), h))


def test_angular_pixel_centres_round_trip():
    n = 40
    dirs = envmod.angular_pixel_directions(n)
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = 2 * (cc + 0.5) / n - 1
    b = 1 - 2 * (rr + 0.5) / n
    inside = a**2 + b**2 < 1  # centres beyond the rim map to the far side of +x
    rows, cols = envmod.angular_dir_to_pixel(dirs[inside], n)
    np.testing.assert_array_equal(rows, rr[inside])
    np.testing.assert_array_equal(cols, cc[inside])


def test_mapping_orientations():
    h, w = 8, 16
    rows, cols = envmod.latlong_dir_to_pixel(np.array([[-1.0, 0, 0], [0, 0, 1.0]]), h, w)
    assert (rows[0], cols[0]) == (h // 2, w // 2)  # latlong centre looks at −x
    assert rows[1] == 0  # top row is +z
    n = 16
    probe = np.array([[-1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    rows, cols = envmod.angular_dir_to_pixel(probe, n)
    assert (rows[0], cols[0]) == (n // 2, n // 2)  # centre: −x
    assert (rows[1], cols[1]) == (n // 4, n // 2)  # up: +z, at r = 1/2
    assert (rows[2], cols[2]) == (n // 2, 3 * n // 4)  # right: −y


def test_latlong_and_angular_maps_of_one_function_agree():
    """f = 1 + 0.5x + 0.3y + 0.2z sampled at pixel centres of both layouts: lookups may
    differ by |∇f| (≤ 0.62 per radian) × (max centre-to-corner angle of a latlong pixel,
    √2·π/(2·64) = 0.035, plus of an angular pixel, ≤ π·√2/96 = 0.046, the map stretching
    image distances by at most π) ≤ 0.05. Any mirror or turn of a layout breaks this."""
    coef = np.array([0.5, 0.3, 0.2])

    def f(d):
        return np.repeat((1 + d @ coef)[..., None], 3, axis=-1)

    ll = envmod.image_from_array(f(envmod.latlong_pixel_directions(64, 128)), "latlong")
    an = envmod.image_from_array(f(envmod.angular_pixel_directions(96)), "angular")
    d = _random_dirs(np.random.default_rng(1), 4000)
    assert np.abs(ll.radiance(d) - an.radiance(d)).max() < 0.05
    assert np.abs(ll.radiance(d) - f(d)).max() < 0.62 * 0.035 + 1e-6


# ----------------------------------------------------------------------------- sampling
ANGULAR_N, ANGULAR_SUN_CELL = 48, (2, 5)


def _environments() -> dict[str, envmod.Environment]:
    # A coarse latlong map (6×12 pixels vs 8×16 cells, not aligned) so that the χ² test
    # sees the distribution inside pixels (uniform in θ instead of cos θ fails it).
    ll = envmod.image_from_array(_sun_latlong_map(6, 12), "latlong")
    angular = _sun_angular_map(ANGULAR_N, ANGULAR_SUN_CELL)[0]
    return {
        "constant": envmod.constant([1.0, 0.5, 0.25]),
        "sky": envmod.sky(sun=4.0, sun_radius=2.0),
        "latlong": ll,
        "angular": envmod.image_from_array(angular, "angular"),
        "rotated": envmod.rotated(ll, _rotation()),
    }


def _rotation() -> np.ndarray:
    return rotation_from_az_el(70.0, -25.0)


@pytest.mark.parametrize("name", ["constant", "sky", "latlong", "angular", "rotated"])
def test_sample_returns_unit_directions_and_its_own_pdf(name):
    env = _environments()[name]
    u = np.random.default_rng(2).random((20000, 2))
    dirs, pdf = env.sample(u)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    assert np.all(pdf > 0)
    # same formula evaluated twice (latlong: p/Ω of the chosen pixel vs of the looked-up
    # pixel): agreement to rounding.
    np.testing.assert_allclose(env.pdf(dirs), pdf, rtol=1e-12)
    assert np.all(np.isfinite(env.radiance(dirs)))


def _chi2_of(env: envmod.Environment, probs: np.ndarray, n: int, seed: int) -> float:
    assert probs.sum() == pytest.approx(1.0, abs=1e-9)
    dirs, _ = env.sample(np.random.default_rng(seed).random((n, 2)))
    observed = np.bincount(_cell_index(dirs), minlength=NZ * NPHI)
    return _chi2_pvalue(observed, probs)


def test_chi2_latlong_sampler_with_sun():
    env = _environments()["latlong"]
    assert _chi2_of(env, _latlong_cell_probs(env), 200_000, 3) > ALPHA


def test_chi2_angular_sampler_with_sun():
    env = _environments()["angular"]
    # premise of _angular_cell_probs' accuracy: the sun pixel maps into one cell
    _, (row, col) = _sun_angular_map(ANGULAR_N, ANGULAR_SUN_CELL)
    t = (np.arange(64) + 0.5) / 64
    a = -1 + (col + t[None, :]) * (2 / ANGULAR_N)
    b = 1 - (row + t[:, None]) * (2 / ANGULAR_N)
    sun_cells = _cell_index(envmod.angular_image_to_dir(*np.broadcast_arrays(a, b)).reshape(-1, 3))
    assert np.all(sun_cells == ANGULAR_SUN_CELL[0] * NPHI + ANGULAR_SUN_CELL[1])
    assert _chi2_of(env, _angular_cell_probs(env), 200_000, 4) > ALPHA


def test_chi2_sky_sampler_with_sun():
    """Sun (radius 2°) centred in one cell: the cone lies wholly inside it, so cell
    probabilities are exact: (1 − p_sun)/cells + p_sun for the sun's cell."""
    centre = _cell_centre(2, 5)
    az = math.degrees(math.atan2(centre[1], centre[0]))
    el = math.degrees(math.asin(centre[2]))
    env = envmod.sky(sun=6.0, sun_az=az, sun_el=el, sun_radius=2.0)
    probs = np.full(NZ * NPHI, (1 - env.sun_probability) / (NZ * NPHI))
    probs[2 * NPHI + 5] += env.sun_probability
    assert env.sun_probability > 0.3  # the sun gets a large share of the samples
    assert _chi2_of(env, probs, 200_000, 5) > ALPHA


def test_chi2_uniform_cone():
    """Cone about +z of half-angle 60°: cos θ uniform on [1/2, 1] and φ uniform, so cells
    in (z, φ) have exact probabilities (z-overlap / (1/2)) / NPHI. The sky's sun uses
    this sampler with a rotated frame (checked: all directions within the cone)."""
    u = np.random.default_rng(13).random((100_000, 2))
    dirs = envmod.sample_uniform_cone(u, np.array([0.0, 0.0, 1.0]), 0.5)
    z_cell = 1.0 - 2.0 * np.arange(NZ + 1) / NZ
    overlap = np.clip(np.minimum(z_cell[:-1], 1.0) - np.maximum(z_cell[1:], 0.5), 0, None)
    probs = np.repeat(overlap / 0.5 / NPHI, NPHI)
    observed = np.bincount(_cell_index(dirs), minlength=NZ * NPHI)
    assert _chi2_pvalue(observed, probs) > ALPHA
    axis = _random_dirs(np.random.default_rng(14), 1)[0]
    tilted = envmod.sample_uniform_cone(u, axis, 0.9)
    np.testing.assert_allclose(tilted @ axis, 1.0 - u[:, 0] * 0.1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tilted, axis=1), 1.0, atol=1e-12)


def test_chi2_constant_is_uniform():
    env = _environments()["constant"]
    assert _chi2_of(env, np.full(NZ * NPHI, 1.0 / (NZ * NPHI)), 100_000, 6) > ALPHA


@pytest.mark.parametrize("name", ["sky", "latlong", "angular", "rotated"])
def test_monte_carlo_integral_matches_quadrature(name):
    """mean(L/pdf) estimates ∫ L dω = 4π·mean_radiance (quadrature / closed form);
    per channel within 4 standard errors of the estimator."""
    env = _environments()[name]
    n = 100_000
    dirs, pdf = env.sample(np.random.default_rng(7).random((n, 2)))
    terms = env.radiance(dirs) / pdf[:, None]
    estimate = terms.mean(axis=0)
    stderr = terms.std(axis=0, ddof=1) / math.sqrt(n)
    exact = 4 * math.pi * env.mean_radiance
    assert np.all(np.abs(estimate - exact) < 4 * stderr + 1e-12 * exact), (estimate, exact)


def test_image_pdf_floor_keeps_dark_pixels_reachable():
    px = np.zeros((16, 32, 3))
    px[3, 7] = 100.0  # everything else black
    env = envmod.image_from_array(px, "latlong")
    assert np.all(env.sampler.p > 0)
    share = env.sampler.p.sum() - env.sampler.p[3, 7]
    expected_share = envmod.FLOOR_FRACTION * (1 - env.solid_angles[3, 7] / (4 * math.pi))
    assert share == pytest.approx(expected_share, rel=1e-9)


def test_constant_sampler_pdf_and_mean():
    env = envmod.constant(2.0)
    np.testing.assert_array_equal(env.mean_radiance, [2.0, 2.0, 2.0])
    d = _random_dirs(np.random.default_rng(8), 10)
    np.testing.assert_allclose(env.pdf(d), 1 / (4 * math.pi))
    np.testing.assert_allclose(env.radiance(d), 2.0)


def test_sky_closed_forms():
    env = envmod.sky(zenith=(0.2, 0.4, 0.8), horizon=1.0, ground=0.1, sun=3.0, sun_radius=1.0)
    # radiance inside the sun disk = sun irradiance / (π sin² r), on top of the gradient
    inside = env.radiance(env.sun_direction[None, :]) - env.gradient_radiance(
        np.array([env.sun_direction[2]])
    )
    np.testing.assert_allclose(inside[0], 3.0 / (math.pi * math.sin(math.radians(1.0)) ** 2))
    # straight up and straight down
    np.testing.assert_allclose(env.radiance(np.array([[0, 0, 1.0]]))[0], [0.2, 0.4, 0.8])
    np.testing.assert_allclose(env.radiance(np.array([[0, 0, -1.0]]))[0], 0.1)
    # mean radiance vs a fine quadrature of the gradient in z + the sun's power
    z = np.linspace(-1, 1, 400_001)
    grad = np.trapezoid(env.gradient_radiance(z), z, axis=0) * 2 * math.pi
    sun = (
        3.0
        / (math.pi * math.sin(math.radians(1.0)) ** 2)
        * 2
        * math.pi
        * (1 - math.cos(math.radians(1.0)))
    )
    # trapezoid on a C¹ piecewise polynomial with step 5e-6: error ~1e-11
    np.testing.assert_allclose(4 * math.pi * env.mean_radiance, grad + sun, rtol=1e-9)


# ----------------------------------------------------------------------------- rotation
def test_rotated_environment_looks_up_r_transpose_omega():
    inner = _environments()["latlong"]
    r = _rotation()
    env = envmod.rotated(inner, r)
    d = _random_dirs(np.random.default_rng(9), 100)
    np.testing.assert_array_equal(env.radiance(d), inner.radiance(d @ r))
    np.testing.assert_array_equal(env.pdf(d), inner.pdf(d @ r))
    twice = envmod.rotated(env, r)
    assert twice.inner is inner
    np.testing.assert_allclose(twice.radiance(d), inner.radiance(d @ r @ r), atol=0)
    with pytest.raises(ValueError, match="orthonormal"):
        envmod.rotated(inner, np.diag([1.0, 1.0, -1.0]))


def test_environments_are_immutable():
    env = _environments()["latlong"]
    with pytest.raises(AttributeError):
        env.mapping = "angular"
    with pytest.raises(ValueError):
        env.pixels[0, 0, 0] = 1.0
    with pytest.raises(ValueError):
        envmod.constant(1.0).rgb[0] = 2.0


# ----------------------------------------------------------------------------- files
def _write_exr(path: Path, channels: dict[str, np.ndarray], header: dict | None = None):
    import OpenEXR

    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    with OpenEXR.File(hdr, channels) as f:
        f.write(str(path))


def test_exr_round_trip_float_rgb_and_half_channels(tmp_path):
    rng = np.random.default_rng(10)
    rgb = (rng.random((8, 16, 3)) * 10).astype(np.float32)
    _write_exr(tmp_path / "f.exr", {"RGB": rgb})
    pixels, hint = envmod.read_exr(tmp_path / "f.exr")
    np.testing.assert_array_equal(pixels, rgb)
    assert hint is None
    half = rgb.astype(np.float16)
    # (the bindings ignore strides: pass contiguous planes)
    planes = {c: np.ascontiguousarray(half[..., i]) for i, c in enumerate("RGBA"[:3])}
    planes["A"] = np.ones_like(planes["R"])
    _write_exr(tmp_path / "h.exr", planes)
    env = envmod.image(tmp_path / "h.exr")
    assert env.mapping == "latlong"
    np.testing.assert_array_equal(env.pixels, half.astype(np.float32))
    _write_exr(tmp_path / "y.exr", {"Y": np.ascontiguousarray(rgb[..., 1])})
    np.testing.assert_array_equal(envmod.read_exr(tmp_path / "y.exr")[0][..., 2], rgb[..., 1])


@pytest.mark.parametrize("rle", [True, False])
def test_hdr_round_trip(tmp_path, rle):
    """RGBE keeps 8 mantissa bits per channel relative to the pixel's largest channel, and
    the reader returns bin centres: |error| ≤ max channel / 256."""
    rng = np.random.default_rng(11)
    rgb = rng.random((12, 40, 3)) * np.logspace(-3, 3, 40)[None, :, None]
    rgb[3] = 0.0  # a black row: long runs
    rgb[5, 10:30] = [1.5, 0.25, 4.0]  # constant span: runs in every channel
    envmod.write_hdr(tmp_path / "m.hdr", rgb, rle=rle)
    back = envmod.read_hdr(tmp_path / "m.hdr")
    assert back.shape == rgb.shape and back.dtype == np.float32
    bound = rgb.max(axis=2, keepdims=True) / 256 * (1 + 1e-6)
    assert np.all(np.abs(back - rgb) <= bound)
    assert np.all(back[3] == 0)


def test_hdr_orientation_exposure_and_truncation(tmp_path):
    rgb = np.arange(2 * 16 * 3, dtype=np.float64).reshape(2, 16, 3) + 1.0
    envmod.write_hdr(tmp_path / "a.hdr", rgb)
    data = (tmp_path / "a.hdr").read_bytes()
    flipped = data.replace(b"-Y 2 +X 16", b"+Y 2 +X 16").replace(b"FORMAT", b"EXPOSURE=2\nFORMAT")
    (tmp_path / "b.hdr").write_bytes(flipped)
    np.testing.assert_allclose(
        envmod.read_hdr(tmp_path / "b.hdr"), envmod.read_hdr(tmp_path / "a.hdr")[::-1] / 2
    )
    (tmp_path / "c.hdr").write_bytes(data[:-5])
    with pytest.raises(EnvSpecError, match="truncated"):
        envmod.read_hdr(tmp_path / "c.hdr")


@pytest.mark.parametrize(
    ("old", "new", "fragment"),
    [
        (b"FORMAT", b"EXPOSURE=abc\nFORMAT", "EXPOSURE=abc, expected a positive finite"),
        (b"FORMAT", b"EXPOSURE=0\nFORMAT", "EXPOSURE=0, expected a positive finite"),
        (b"FORMAT", b"EXPOSURE=-1\nFORMAT", "EXPOSURE=-1, expected a positive finite"),
        (b"FORMAT", b"EXPOSURE=inf\nFORMAT", "EXPOSURE=inf, expected a positive finite"),
        (b"FORMAT", b"EXPOSURE=1e300\nEXPOSURE=1e300\nFORMAT", "product of the EXPOSURE"),
        (b"-Y 2 +X 16", b"-Y 0 +X 0", "resolution '-Y 0 +X 0', expected a height and a width"),
        (b"-Y 2 +X 16", b"-Y 2 +X 0", "of at least 1 pixel"),
    ],
)
def test_a_bad_hdr_header_is_one_line_naming_the_file_and_value(tmp_path, old, new, fragment):
    """An exposure that is not a positive finite number (which would divide the pixels
    into NaN, infinite or negative radiance) and an empty resolution are refused."""
    envmod.write_hdr(tmp_path / "a.hdr", np.ones((2, 16, 3)))
    (tmp_path / "b.hdr").write_bytes((tmp_path / "a.hdr").read_bytes().replace(old, new))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy warning on the way
        with pytest.raises(EnvSpecError) as info:
            envmod.parse_env(str(tmp_path / "b.hdr"))
    message = str(info.value)
    assert "\n" not in message and "b.hdr" in message and fragment in message, message


# ----------------------------------------------------------------------------- specs
def test_parse_env_specs(tmp_path):
    assert np.allclose(envmod.parse_env("constant:0.5").mean_radiance, 0.5)
    assert np.allclose(envmod.parse_env("constant:1,2,3").mean_radiance, [1, 2, 3])
    sky = envmod.parse_env("sky:zenith=0.1,0.2,0.3,sun=5,sun_el=30")
    assert sky.zenith == (0.1, 0.2, 0.3) and sky.sun == (5.0, 5.0, 5.0) and sky.sun_el == 30
    assert envmod.parse_env("sky").sun_probability == 0  # no sun by default
    for env in (sky, envmod.parse_env("constant:0.5")):
        assert envmod.parse_env(env.spec).spec == env.spec
    px = np.ones((16, 16, 3), np.float32)
    envmod.write_hdr(tmp_path / "p.hdr", px)
    env = envmod.parse_env(f"{tmp_path / 'p.hdr'}*2")
    assert env.mapping == "angular" and env.pixels.max() == pytest.approx(2.0, rel=1e-2)
    env2 = envmod.parse_env(f"{tmp_path / 'p.hdr'}@latlong*0.5")
    assert env2.mapping == "latlong" and env2.scale == 0.5
    assert envmod.parse_env(env2.spec).spec == env2.spec


@pytest.fixture
def bad_files(tmp_path) -> dict[str, Path]:
    wide = np.ones((10, 30, 3), np.float32)  # 3:1
    cube = np.ones((60, 10, 3), np.float32)  # 1:6 vertical strip
    nan = np.ones((8, 16, 3), np.float32)
    nan[2, 3, 1] = np.nan
    files = {}
    for name, arr in (("wide", wide), ("cube", cube), ("nan", nan)):
        files[name] = tmp_path / f"{name}.exr"
        _write_exr(files[name], {"RGB": arr})
    files["png"] = tmp_path / "x.png"
    files["png"].write_bytes(b"\x89PNG\r\n")
    files["junk"] = tmp_path / "junk.hdr"
    files["junk"].write_bytes(b"not an hdr file")
    files["ok"] = tmp_path / "ok.exr"
    _write_exr(files["ok"], {"RGB": np.ones((8, 16, 3), np.float32)})
    return files


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        ("", "empty"),
        ("constant:", "expected numbers"),
        ("constant:1,2", "constant:R,G,B"),
        ("constant:a", "expected numbers"),
        ("constant:-1", "≥ 0"),
        ("sky:foo=1", "unknown sky key"),
        ("sky:sun_el=abc", "expected numbers"),
        ("sky:zenith=1,2", "1 or 3 numbers"),
        ("sky:sun_radius=0", "sun_radius"),
        ("sky:1", "key=value"),
        ("{tmp}/missing.exr", "no such file"),
        ("{png}", "unsupported image format"),
        ("{junk}", "not a Radiance HDR"),
        ("{wide}", "expected 2:1"),
        ("{cube}", "cube map"),
        ("{nan}", "NaN or infinite"),
        ("{ok}@cube", "unknown mapping"),
        ("{ok}@angular", "square"),
        ("{ok}*x", "SCALE"),
    ],
)
def test_bad_specs_raise_one_line_errors(bad_files, tmp_path, spec, fragment):
    spec = spec.format(tmp=tmp_path, **bad_files)
    with pytest.raises(EnvSpecError) as info:
        envmod.parse_env(spec)
    message = str(info.value)
    assert "\n" not in message
    assert repr(spec) in message
    assert fragment in message
    assert isinstance(info.value, ValueError)


def test_negative_pixels_are_clamped_with_a_warning(tmp_path, capsys):
    arr = np.ones((8, 16, 3), np.float32)
    arr[1, 2] = -0.01
    _write_exr(tmp_path / "neg.exr", {"RGB": arr})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the project's warning line, not a Python warning
        env = envmod.parse_env(str(tmp_path / "neg.exr"))
    assert env.pixels.min() == 0.0
    assert capsys.readouterr().err == (f"isolume: warning: {tmp_path / 'neg.exr'}: 1 pixels "
                                       "had negative values, clamped to 0\n")


# ----------------------------------------------------------------------------- real probes
def _probe(name: str) -> Path:
    path = PROBES / name
    if not path.exists():
        pytest.skip(f"{path} not present (../shared/data is optional)")
    return path


@pytest.mark.shared
@pytest.mark.parametrize("name", ["openexr_KernerEnvLatLong.exr", "polyhaven_venice_sunset_1k.hdr"])
def test_real_probes_load(name, capsys):
    env = envmod.parse_env(str(_probe(name)))
    assert "negative" not in capsys.readouterr().err  # these probes have no negative pixels
    assert env.mapping == "latlong"
    assert np.all(np.isfinite(env.pixels)) and env.pixels.min() >= 0
    assert env.solid_angles.sum() == pytest.approx(4 * math.pi, rel=1e-12)
    assert np.all(env.mean_radiance > 0)
    dirs, pdf = env.sample(np.random.default_rng(12).random((1000, 2)))
    np.testing.assert_allclose(env.pdf(dirs), pdf, rtol=1e-12)


@pytest.mark.shared
def test_real_cube_probe_is_refused():
    with pytest.raises(EnvSpecError, match="cube"):
        envmod.parse_env(str(_probe("openexr_KernerEnvCube.exr")))
