"""``isolume export``: the lit isosurface as .glb and .ply, read back with trimesh and
pygltflib, its colours checked against ``isolume render``'s pixels, and its one-line
errors."""

import argparse

import numpy as np
import pygltflib
import pytest
import trimesh

from isolume import volumes
from isolume.app.cli import build_parser, main
from isolume.app.export_files import Z_UP_TO_Y_UP, srgb_bytes, tone
from isolume.app.options import environment_coefficients, view_light
from isolume.app.render.offscreen import render_volume
from isolume.app.render.renderer import framed_camera
from isolume.app.render.settings import RenderSettings
from isolume.baking import BakeConfig, bake

SUN_SKY = "sky:sun=6,sun_az=-150,sun_el=40"
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
SIZE = (256, 256)


def _run(capsys, *argv: str) -> tuple[int, str]:
    status = main(list(argv))
    return status, capsys.readouterr().err


def _glb(path) -> dict[str, np.ndarray]:
    """The arrays of a .glb's one primitive (indices, POSITION, NORMAL, COLOR_0,
    _RADIANCE), read with pygltflib, and its document under "document"."""
    document = pygltflib.GLTF2.load(str(path))
    blob = document.binary_blob()
    primitive = document.meshes[0].primitives[0]

    def accessor(index: int) -> np.ndarray:
        a = document.accessors[index]
        view = document.bufferViews[a.bufferView]
        dtype = np.uint32 if a.componentType == pygltflib.UNSIGNED_INT else np.float32
        width = 1 if a.type == "SCALAR" else 3
        data = np.frombuffer(blob, dtype, a.count * width, view.byteOffset)
        return data if width == 1 else data.reshape(a.count, width)

    names = ("POSITION", "NORMAL", "COLOR_0", "_RADIANCE")
    arrays = {name: accessor(getattr(primitive.attributes, name)) for name in names}
    return {**arrays, "indices": accessor(primitive.indices), "document": document}


def _ply_radiance(mesh: trimesh.Trimesh) -> np.ndarray:
    """(V, 3) the radiance_r/g/b properties of a PLY that trimesh loaded."""
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    return np.stack([raw[f"radiance_{c}"] for c in "rgb"], axis=1).astype(np.float64)


@pytest.fixture(scope="module")
def sphere_lattice(tmp_path_factory):
    """An irradiance lattice of synthetic:sphere:32 around iso 0.5 under the default sky
    and sun (the sun left to the pixels), 16 paths per texel."""
    path = tmp_path_factory.mktemp("lattice") / "sphere.npz"
    volume = volumes.load("synthetic:sphere:32")
    bake(volume, BakeConfig(samples=16, bounces=1, env=SUN_SKY, iso_range=(0.45, 0.55)),
         out=path, workers=2)
    return path


def test_glb_and_ply_hold_the_mesh_its_colours_and_its_radiance(tmp_path, capsys,
                                                               sphere_lattice):
    """Both files hold every vertex of the isosurface render draws, unit normals pointing
    out of the sphere, the radiance (the same in both) and the display colours: glTF's
    linear COLOR_0 and PLY's 8-bit sRGB are one colour (to rounding), and each is the tone
    curve of the radiance times the exposure the file records."""
    volume = volumes.load("synthetic:sphere:32")
    mesh = volumes.isosurface(volume, 0.5)
    for name in ("s.glb", "s.ply"):
        status, err = _run(capsys, "export", "synthetic:sphere:32", "--lattice",
                           str(sphere_lattice), "--out", str(tmp_path / name))
        assert status == 0, err
    glb = _glb(tmp_path / "s.glb")
    ply = trimesh.load(tmp_path / "s.ply", process=False)
    back = Z_UP_TO_Y_UP.T  # glTF +Y up → world +Z up
    positions, normals = glb["POSITION"] @ back.T, glb["NORMAL"] @ back.T
    assert len(positions) == len(ply.vertices) == len(mesh.vertices)
    assert np.allclose(positions, mesh.vertices, atol=1e-6)
    assert np.allclose(ply.vertices, mesh.vertices, atol=1e-6)
    assert np.array_equal(glb["indices"].reshape(-1, 3), mesh.faces)
    assert len(ply.faces) == len(mesh.faces)
    for n in (normals, ply.vertex_normals):
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
        outward = np.einsum("vc,vc->v", n, positions / np.linalg.norm(positions, axis=1,
                                                                        keepdims=True))
        assert outward.min() > 0.95
    radiance = glb["_RADIANCE"].astype(np.float64)
    assert np.allclose(_ply_radiance(ply), radiance)
    assert radiance.min() > 0 and radiance.max() < 10
    exposure = glb["document"].asset.extras["exposure"]
    assert np.allclose(glb["COLOR_0"], tone(radiance * exposure, "aces"), atol=1e-6)
    colours = ply.visual.vertex_colors[:, :3].astype(int)
    assert np.abs(colours - srgb_bytes(glb["COLOR_0"])).max() <= 1
    assert glb["document"].extensionsUsed == ["KHR_materials_unlit"]
    reloaded = next(iter(trimesh.load(tmp_path / "s.glb").geometry.values()))
    assert reloaded.vertex_attributes["_RADIANCE"].shape == (len(mesh.vertices), 3)


def _sh_case(tmp_path):
    """(volume spec, export options, render keyword arguments) of a torus lit by a split SH
    lattice (transfer under the sun-free sky, the sun per pixel), its sky turned."""
    volume = volumes.load("synthetic:torus:32")
    lattice = bake(volume, BakeConfig(mode="sh", sh_order=3, samples=16, bounces=1,
                                      env=SUN_SKY, iso_range=(0.45, 0.55),
                                      direct_light="pixels"), workers=2)
    lattice.save(tmp_path / "sh.npz")
    coeffs = environment_coefficients(None, lattice, "none")
    return ("synthetic:torus:32", ["--lattice", str(tmp_path / "sh.npz"),
                                   "--env-rotation", "40,10"],
            {"lattice": lattice, "env_coeffs": coeffs, "shading": "sh",
             "env_rotation": (40.0, 10.0)})


def _irradiance_case(tmp_path, lattice_path):
    """The sphere under its irradiance lattice (the sun per pixel)."""
    from isolume.baking import Lattice

    return ("synthetic:sphere:32", ["--lattice", str(lattice_path)],
            {"lattice": Lattice.load(lattice_path), "shading": "irradiance"})


def _traced_case(tmp_path):
    """The engine at iso 0.3 without a lattice: global illumination traced by both (64
    paths per texel), the sun's cast shadows in the bores and under the fins."""
    spec, options = "synthetic:engine:48", ["--iso", "0.3"]
    args = build_parser().parse_args(["export", spec, *options, "--out", "x.glb"])
    return spec, options, {"view_light": view_light(args, volumes.load(spec)),
                           "shading": "irradiance"}


def _seen_vertices(volume, mesh, mask: np.ndarray) -> tuple[np.ndarray, ...]:
    """(rows, columns, seen) of the mesh's vertices in render's default view at `SIZE`:
    the pixel each projects into, and whether the eye sees the vertex from its normal's
    side there: an Embree ray from the eye to the vertex meets nothing half a voxel or more
    before it, the facet it meets there faces the eye on the side the vertex normal points
    to (the side render lights; at a surface cut open by the volume's box the eye looks at
    the other), the 3 × 3 pixels around it all show the surface (`mask`: not at a
    silhouette), and it lies 2 voxels or more inside the volume's box (where the surface is
    cut off by the box, the one-sided gradient turns the normals of a vertex and of the
    pixels beside it up to 70° apart)."""
    from isolume.baking.trace import Scene

    w, h = SIZE
    camera = framed_camera(volume, mesh.iso, None, SIZE)
    points = np.asarray(mesh.vertices, np.float64)
    clip = np.c_[points, np.ones(len(points))] @ camera.view_proj(w / h).T
    ndc = clip[:, :2] / clip[:, 3:]
    col = np.floor((ndc[:, 0] + 1) / 2 * w).astype(int)
    row = np.floor((1 - ndc[:, 1]) / 2 * h).astype(int)
    inside = (col >= 1) & (col < w - 1) & (row >= 1) & (row < h - 1)
    col, row = col.clip(1, w - 2), row.clip(1, h - 2)
    covered = np.ones(len(points), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            covered &= mask[row + dy, col + dx]
    rays = points - camera.eye
    distance = np.linalg.norm(rays, axis=1)
    rays /= distance[:, None]
    hits = Scene(mesh.vertices, mesh.faces).intersect(
        np.broadcast_to(camera.eye, rays.shape), rays)
    facet = hits["ng"].astype(np.float64)
    towards_eye = -np.sign(np.einsum("vc,vc->v", facet, rays))
    normal_side = np.sign(np.einsum("vc,vc->v", facet, np.asarray(mesh.normals, np.float64)))
    reached = hits["t"] > distance - 0.5 * min(volume.spacing)
    voxel = (points - np.asarray(volume.origin)) / np.asarray(volume.spacing)
    last = np.array(volume.data.shape[::-1]) - 1
    interior = ((voxel >= 2) & (voxel <= last - 2)).all(axis=1)
    return row, col, inside & covered & reached & (towards_eye == normal_side) & interior


@pytest.mark.parametrize("case", ["irradiance lattice", "traced", "sh lattice"])
def test_vertex_colours_agree_with_the_rendered_pixels(tmp_path, capsys, sphere_lattice,
                                                       case):
    """At the vertices the default view shows, the exported linear radiance is what
    `render` draws at the pixel each vertex projects into, and the 8-bit sRGB colours
    (exported with the frame's exposure) are the picture's bytes.

    Both read the same lattice (or trace the same light: the same texels, paths and seeds,
    from the vertex or the visible point nearest each texel) with the same side-aware lookup
    and add the sun's direct light, so what separates them is where they look: the pixel's
    surface point lies up to 0.7 pixel (a fifth of a voxel here) from the vertex, across
    which the light changes by a few per cent where it changes fastest (the sun's
    terminator, creases, shadow edges), and render stores irradiance as RGB9E5 (2⁻⁹) and
    SH transfer as float16. Measured (llvmpipe): median relative difference 0.6 %
    (irradiance lattice), 1.1 % (traced, engine), 0.7 % (SH); 90th percentile 2.3 %,
    8.8 %, 3.9 %; means within 0.4 %. The bounds leave room for other GL rounding and
    noise; a light missing, a factor π, or another side's light breaks them. The sRGB
    bytes: one level apart at the median (rounding of the same curve), 2, 7 and 3 levels
    at the 90th percentile.
    """
    make = {"irradiance lattice": lambda: _irradiance_case(tmp_path, sphere_lattice),
            "traced": lambda: _traced_case(tmp_path), "sh lattice": lambda: _sh_case(tmp_path)}
    spec, options, render_kwargs = make[case]()
    volume = volumes.load(spec)
    iso = 0.3 if "engine" in spec else 0.5
    shading = render_kwargs.pop("shading")
    settings = RenderSettings(size=SIZE, shading=shading, auto_exposure=True,
                              albedo=(0.8, 0.8, 0.8),
                              env_rotation=render_kwargs.pop("env_rotation", (0.0, 0.0)))
    frame, mesh = render_volume(volume, iso, settings, workers=2, **render_kwargs)
    status, err = _run(capsys, "export", spec, *options, "--no-auto-exposure", "--exposure",
                       repr(frame.exposure), "--workers", "2", "--out", str(tmp_path / "m.ply"))
    assert status == 0, err
    exported = trimesh.load(tmp_path / "m.ply", process=False)
    row, col, visible = _seen_vertices(volume, mesh, frame.mask)
    assert visible.sum() > 500
    ours = _ply_radiance(exported)[visible] @ LUMINANCE
    theirs = frame.linear[row, col][visible].astype(np.float64) @ LUMINANCE
    relative = np.abs(ours - theirs) / np.maximum(theirs, 1e-3 * theirs.max())
    assert np.median(relative) < 0.03, np.median(relative)
    assert np.percentile(relative, 90) < 0.15, np.percentile(relative, 90)
    assert abs(ours.mean() / theirs.mean() - 1) < 0.02
    levels = np.abs(exported.visual.vertex_colors[visible, :3].astype(int)
                    - frame.srgb[row, col][visible].astype(int)).max(axis=1)
    assert np.median(levels) <= 2 and np.percentile(levels, 90) <= 10


@pytest.mark.parametrize("curve", ["clamp", "reinhard", "aces"])
def test_the_tone_curves_are_the_shaders(curve):
    """`tone` and `srgb_bytes` turn a frame's linear pixels into its bytes, to one level
    (the GPU rounds, or truncates, its 8-bit output)."""
    volume = volumes.load("synthetic:torus:24")
    settings = RenderSettings(size=(64, 64), shading="phong_hemi", exposure=1.7,
                              tonemap=curve)
    frame, _ = render_volume(volume, 0.5, settings)
    ours = srgb_bytes(tone(frame.linear[frame.mask] * frame.exposure, curve)).astype(int)
    assert np.abs(ours - frame.srgb[frame.mask].astype(int)).max() <= 1


def test_automatic_exposure_meters_the_whole_surface(tmp_path, capsys, sphere_lattice):
    """The exposure a file records brings the area-weighted log-average luminance of its
    vertices (all lit here) to middle grey, and --exposure multiplies it."""
    from isolume.app.export_files import vertex_areas
    from isolume.app.render.exposure import EXPOSURE_KEY

    exposures = []
    for factor in ("1", "2"):
        status, err = _run(capsys, "export", "synthetic:sphere:32", "--lattice",
                           str(sphere_lattice), "--exposure", factor,
                           "--out", str(tmp_path / "s.glb"))
        assert status == 0, err
        glb = _glb(tmp_path / "s.glb")
        exposures.append(glb["document"].asset.extras["exposure"])
    lum = glb["_RADIANCE"].astype(np.float64) @ LUMINANCE
    weights = vertex_areas(glb["POSITION"], glb["indices"].reshape(-1, 3))
    log_average = np.exp(np.average(np.log(lum), weights=weights))
    assert exposures[0] * log_average == pytest.approx(EXPOSURE_KEY, rel=1e-3)
    assert exposures[1] == pytest.approx(2 * exposures[0], rel=1e-9)


@pytest.fixture(scope="module")
def torus_lattice(tmp_path_factory):
    """A one-path lattice of synthetic:torus:16 for isovalues 0.4 to 0.6."""
    path = tmp_path_factory.mktemp("torus") / "torus.npz"
    bake(volumes.load("synthetic:torus:16"),
         BakeConfig(samples=1, bounces=0, iso_range=(0.4, 0.6)), out=path, workers=1)
    return path


def _top(spec: str) -> str:
    """The largest value of a volume, as a command line writes it (the same float)."""
    return repr(float(volumes.load(spec).value_range[1]))


@pytest.mark.parametrize(
    ("make_args", "expected"),
    [
        (lambda t, lat: ["synthetic:torus:16", "--out", str(t / "x.obj")],
         "must end in .glb or .ply"),
        (lambda t, lat: ["synthetic:torus:16", "--iso", "5", "--out", str(t / "x.glb")],
         "outside the data range"),
        (lambda t, lat: ["synthetic:sphere:16", "--lattice", str(lat), "--out",
                         str(t / "x.glb")], "baked for volume"),
        (lambda t, lat: ["synthetic:torus:16", "--lattice", str(lat), "--iso", "0.2",
                         "--out", str(t / "x.glb")], "baked for isovalues 0.4 to 0.6"),
        (lambda t, lat: ["synthetic:torus:16", "--lattice", str(lat), "--env", "sky",
                         "--out", str(t / "x.glb")], "--env/--light"),
        (lambda t, lat: ["synthetic:torus:16", "--exposure", "0", "--out", str(t / "x.glb")],
         "--exposure 0"),
        (lambda t, lat: ["synthetic:torus:16", "--albedo", "3", "--out", str(t / "x.ply")],
         "--albedo"),
        (lambda t, lat: ["synthetic:torus:16", "--iso", _top("synthetic:torus:16"), "--out",
                         str(t / "x.ply")], "nothing to export"),
    ],
)
def test_bad_input_gives_one_line_and_status_2(tmp_path, capsys, torus_lattice, make_args,
                                               expected):
    status, err = _run(capsys, "export", *make_args(tmp_path, torus_lattice))
    assert status == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("isolume: error:"), err
    assert expected in lines[0], lines[0]
    assert not list(tmp_path.glob("x.*"))


def test_export_is_a_command_with_examples():
    """``isolume export --help`` describes the formats and gives an example."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    text = sub.choices["export"].format_help()
    assert "COLOR_0" in text and "examples:" in text and "isolume export" in text
