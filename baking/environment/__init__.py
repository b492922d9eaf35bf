"""Distant environment light: constant, procedural sky, HDR image probes; sampling and pdfs.

The package: `models` (the environments), `maps` (latitude–longitude and angular map
geometry), `sphere` (directions and uniform sampling), `files` (EXR and RGBE files) and
`spec` (the ``--env`` grammar); the names below are re-exported here.

Conventions
-----------
* World up is +z. A direction ω = (x, y, z) is a unit vector pointing *from* the scene
  *towards* the environment; ``radiance(ω)`` is the radiance arriving from there.
  Spherical angles: ω = (sin θ cos φ, sin θ sin φ, cos θ), θ from +z, φ from +x
  towards +y.
* Radiance is linear RGB, float64 on output. Probability densities are per steradian.
* **Latitude–longitude maps** (W×H, normally W = 2H): row 0 is the top. Pixel
  (row, col) covers θ ∈ π·[row, row+1]/H and φ ∈ 2π·[col, col+1]/W; its centre is
  θ = π(row+0.5)/H, φ = 2π(col+0.5)/W. So the image's centre column looks at −x, the
  left/right edges at +x, and moving right in the image turns from −x towards −y.
  Pixel solid angle (exact): Δφ·(cos θ0 − cos θ1).
* **Angular maps** (Debevec's "light probe" angular map, square N×N): image-plane
  coordinates a = 2(col+0.5)/N − 1 (right +), b = 1 − 2(row+0.5)/N (up +),
  r = sqrt(a² + b²) ≤ 1. The probe's centre looks at **−x** (the same direction as the
  centre of a latlong map), image up is +z and image right is −y (the latlong's layout
  around its centre), so a probe converted between the two layouts by the usual tools
  describes the same environment here. A point at radius r lies at angle ψ = π r from
  −x; the rim r = 1 is the opposite direction +x:
  ω = (−cos πr, −sin(πr)·a/r, sin(πr)·b/r), and r = acos(−x)/π.
  dω = J(r) da db with J(r) = π sin(πr)/r. Pixels that do not meet the unit disk are
  never used; pixel solid angles (the part inside the disk) come from Gauss–Legendre
  quadrature clipped exactly to the disk.
* **OpenEXR's own envmap orientation** (y up) is *not* applied: a latlong EXR is read
  with the layout above, like every other latlong file; turn it with ``rotated``.
* Radiance lookup in an image is the nearest pixel (piecewise constant), so the
  sampling pdf and the radiance agree pixel by pixel.

Sampling (pure functions of the random numbers u ∈ [0,1)²; ``pdf`` is the exact density)
------------------------------------------------------------------------------------
* constant: uniform sphere, pdf 1/4π.
* sky: mixture of a uniform cone over the sun disk (probability p_sun ∝ the sun's share
  of the power, clipped to [0.1, 0.9]) and the uniform sphere.
* image: a pixel with probability p ∝ luminance × solid angle, mixed with 2 %
  (``FLOOR_FRACTION``) of a uniform distribution (by solid angle for latlong, by image
  area over the pixels meeting the disk for angular maps) so that every pixel with
  light is reachable and the estimator stays unbiased. Row then column (pbrt's
  Distribution2D), the remainders of u place the point inside the pixel: uniform in
  (φ, cos θ) for latlong, so pdf = p / Ω_pixel exactly; uniform in image area for
  angular maps, so pdf = Σ_preimages p / (A_pixel · J(r)) (a rim pixel's corner beyond
  r = 1 maps through the same formula onto the directions next to +x, which ``pdf``
  counts as a second preimage).

Specs (``parse_env``)
---------------------
``constant:R,G,B`` | ``constant:V`` | ``sky[:key=value,...]`` |
``PATH[@latlong|@angular][*SCALE]``. Sky keys (colours take 1 or 3 numbers)::

    zenith=0.3,0.5,1.0    radiance straight up
    horizon=1.0           radiance at the horizon (linear in z = cos θ in between)
    ground=0.3            radiance below the horizon
    horizon_blur=3        degrees over which horizon and ground blend (smoothstep in z)
    sun=0                 sun irradiance at normal incidence (0: no sun)
    sun_az=45, sun_el=40  sun direction in degrees (azimuth from +x towards +y, elevation)
    sun_radius=0.5        angular radius of the sun disk in degrees

e.g. ``sky:sun=5,sun_el=30``. Bad specs raise :class:`EnvSpecError`. Negative pixel
values (small filter undershoots are common in real EXRs) are clamped to 0 with a
warning; NaN or infinite pixels are an error.
"""

from isolume.baking.environment.files import EnvSpecError, read_exr, read_hdr, read_image, write_hdr
from isolume.baking.environment.maps import (
    angular_dir_to_pixel,
    angular_image_to_dir,
    angular_pixel_directions,
    angular_pixels_in_disk,
    angular_pixels_inside_disk,
    angular_solid_angles,
    latlong_dir_to_pixel,
    latlong_pixel_directions,
    latlong_solid_angles,
)
from isolume.baking.environment.models import (
    ConstantEnvironment,
    Environment,
    ImageEnvironment,
    RotatedEnvironment,
    SkyEnvironment,
    rotated,
)
from isolume.baking.environment.spec import constant, image, image_from_array, parse_env, sky
from isolume.baking.environment.sphere import (
    FLOOR_FRACTION,
    LUMINANCE_WEIGHTS,
    as_dirs,
    luminance,
    sample_uniform_cone,
    sample_uniform_sphere,
)

__all__ = [
    "FLOOR_FRACTION",
    "LUMINANCE_WEIGHTS",
    "ConstantEnvironment",
    "EnvSpecError",
    "Environment",
    "ImageEnvironment",
    "RotatedEnvironment",
    "SkyEnvironment",
    "angular_dir_to_pixel",
    "angular_image_to_dir",
    "angular_pixel_directions",
    "angular_pixels_in_disk",
    "angular_pixels_inside_disk",
    "angular_solid_angles",
    "as_dirs",
    "constant",
    "image",
    "image_from_array",
    "latlong_dir_to_pixel",
    "latlong_pixel_directions",
    "latlong_solid_angles",
    "luminance",
    "parse_env",
    "read_exr",
    "read_hdr",
    "read_image",
    "rotated",
    "sample_uniform_cone",
    "sample_uniform_sphere",
    "sky",
    "write_hdr",
]
