"""The typed lighting (`baking.lighting.Lighting`) and the bake config a lattice carries:
parsed once, written back to the same specs, turned without touching anything else."""

import json
import math
import zipfile

import numpy as np
import pytest

from isolume.baking.config import BakeConfig
from isolume.baking.environment import SkyEnvironment
from isolume.baking.errors import BakeError
from isolume.baking.lattice import Lattice, LatticeGeometry
from isolume.baking.lighting import Lighting, lighting_of
from isolume.baking.lights import DirectionalLight, SunLight

SPECS = [
    ("constant:1,1,1", ()),
    ("constant:0.5", ()),
    ("sky", ()),
    ("sky:sun=6,sun_az=-150,sun_el=40", ()),
    ("sky:zenith=0.2,0.4,1,horizon=0.9,ground=0.1,sun=3,sun_radius=2", ()),
    ("", ("point:0,0,2:1,1,1",)),
    ("sky:sun=3", ("dir:1,2,3:2,1,1", "point:0.1,0.2,40:2000,2000,2000")),
]


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize(("env", "lights"), SPECS)
def test_the_specs_of_a_lighting_read_back_as_the_same_lighting(env, lights):
    lighting = Lighting.parse(env, lights)
    again = Lighting.parse(*lighting.to_spec())
    assert again == lighting
    assert again.to_spec() == lighting.to_spec()
    if env.startswith("sky"):  # the environment's own spec reads back the same sky
        sky = Lighting.parse(lighting.environment.spec).environment
        np.testing.assert_array_equal(sky.sun_direction, lighting.environment.sun_direction)
        np.testing.assert_array_equal(sky.gradient_radiance(np.linspace(-1, 1, 9)),
                                      lighting.environment.gradient_radiance(
                                          np.linspace(-1, 1, 9)))
    for a, b in zip(again.lights, lighting.lights, strict=True):
        assert a == b  # the light specs keep every digit


def test_a_configs_lighting_reads_as_one_line_of_its_specs():
    """What a command's summary line and its refusals say a lighting is: the environment
    and every light, in their order."""
    assert BakeConfig(env="sky:sun=6", lights=("dir:0,0,1:1,1,1", "point:1,2,3:4,4,4")
                      ).lighting_text == "sky:sun=6 + dir:0,0,1:1,1,1 + point:1,2,3:4,4,4"
    assert BakeConfig(env="", lights=("dir:0,0,1:1,1,1",)).lighting_text == \
        "no environment + dir:0,0,1:1,1,1"
    assert BakeConfig(env="constant:1,1,1").lighting_text == "constant:1,1,1"


def test_a_lighting_is_parsed_once_per_process():
    assert lighting_of("sky:sun=4") is lighting_of("sky:sun=4")
    config = BakeConfig(env="sky:sun=4", samples=3)
    assert config.lighting is BakeConfig(env="sky:sun=4", samples=9).lighting


def test_pixel_lights_are_the_lights_then_the_sun_and_none_for_an_open_sky():
    lighting = Lighting.parse("sky:sun=2,sun_az=90,sun_el=30", ("point:1,2,3:4,4,4",
                                                               "dir:0,0,1:1,1,1"))
    kinds = [type(light).__name__ for light in lighting.pixel_lights()]
    assert kinds == ["PointLight", "DirectionalLight", "SunLight"]
    assert isinstance(lighting.turnable(), DirectionalLight)
    assert Lighting.parse("sky").pixel_lights() == () and Lighting.parse("sky").sun is None
    assert Lighting.parse("constant:1").turnable() is None


def test_turning_the_sun_changes_its_direction_and_nothing_else():
    lighting = Lighting.parse("sky:zenith=0.2,0.4,1,ground=0.1,sun=6,sun_az=-150,sun_el=40,"
                              "sun_radius=2")
    d = _unit((0.6, 0.3, 0.5))
    turned = lighting.turned(d)
    assert isinstance(turned.turnable(), SunLight)
    np.testing.assert_allclose(turned.sun.direction, d, atol=1e-8)
    before, after = lighting.environment, turned.environment
    assert isinstance(after, SkyEnvironment)
    for key in ("zenith", "horizon", "ground", "sun", "sun_radius", "horizon_blur"):
        assert getattr(after, key) == getattr(before, key), key
    assert Lighting.parse(*turned.to_spec()) == turned  # what a relit lattice file holds
    el = math.degrees(math.asin(d[2]))
    assert after.sun_el == pytest.approx(el, abs=1e-6)


def test_turning_a_directional_light_keeps_its_irradiance_and_the_other_lights():
    lighting = Lighting.parse("sky:sun=3", ("point:0,0,2:1,1,1", "dir:0,0,1:2,1,1",
                                            "dir:1,0,0:1,1,1"))
    d = _unit((-0.2, 0.9, 0.4))
    turned = lighting.turned(d)
    assert turned.environment is lighting.environment
    assert turned.lights[0] == lighting.lights[0] and turned.lights[2] == lighting.lights[2]
    np.testing.assert_allclose(turned.lights[1].direction, d, atol=1e-8)
    assert turned.lights[1].irradiance == (2, 1, 1)
    with pytest.raises(ValueError, match="no per-pixel"):
        Lighting.parse("constant:1").turned(d)


def _lattice(config):
    geometry = LatticeGeometry((2, 2, 2), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    lattice = Lattice.empty(geometry, 3, {"kind": "irradiance"})
    lattice.config = config
    return lattice


def test_a_lattice_file_holds_its_config_typed_in_and_typed_out(tmp_path):
    config = BakeConfig(env="sky:sun=3", lights=("dir:0,0,1:1,1,1",), samples=7,
                        iso_range=(0.2, 0.4))
    _lattice(config).save(tmp_path / "a.npz")
    loaded = Lattice.load(tmp_path / "a.npz")
    assert loaded.config == config and "config" not in loaded.meta
    with np.load(tmp_path / "a.npz") as f:
        meta = json.loads(str(f["meta"]))
    assert meta["config_version"] == 1 and meta["config"]["samples"] == 7


def _rewrite_meta(path, change):
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    meta = json.loads(str(arrays["meta"]))
    change(meta)
    arrays["meta"] = np.array(json.dumps(meta))
    with zipfile.ZipFile(path, "w") as z:
        for name, a in arrays.items():
            with z.open(name + ".npy", "w") as out:
                np.lib.format.write_array(out, a)


def test_a_file_without_a_config_version_loads_and_a_newer_one_is_refused(tmp_path):
    path = tmp_path / "old.npz"
    _lattice(BakeConfig(env="sky:sun=3")).save(path)

    def older(meta):  # a file of the first format: no version, no direct_light
        del meta["config_version"], meta["config"]["direct_light"]

    _rewrite_meta(path, older)
    assert Lattice.load(path).config.direct_light == "lattice"  # what such a file holds
    _rewrite_meta(path, lambda meta: meta.update(config_version=99))
    with pytest.raises(BakeError, match="config version 99"):
        Lattice.load(path)


def _turned_by_text(env, lights, d):
    """The turned specs as text edits make them: the first ``dir:`` light's vector
    replaced, else the sky's ``sun_az``/``sun_el`` (9 significant digits)."""
    xyz = ",".join(f"{v:.9g}" for v in d)
    for i, spec in enumerate(lights):
        kind, _, rest = spec.partition(":")
        if kind == "dir":
            edited = list(lights)
            edited[i] = f"dir:{xyz}:{rest.split(':', 1)[1]}"
            return env, tuple(edited)
    az = math.degrees(math.atan2(d[1], d[0]))
    el = math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0))))
    return f"{env},sun_az={az:.9g},sun_el={el:.9g}", lights


@pytest.mark.parametrize(("env", "lights"), [
    ("sky:zenith=0.2,0.4,1,sun=6,sun_az=-150,sun_el=40", ()),
    ("sky:sun=3", ("point:0,0,2:1,1,1", "dir:1,2,3:2,1,1")),
])
@pytest.mark.parametrize("direction", [(0.6, 0.3, 0.5), (-0.2, -0.9, 0.1), (0.0, 0.0, 1.0)])
def test_a_turned_lighting_is_the_one_its_edited_specs_describe_to_the_bit(env, lights,
                                                                          direction):
    d = _unit(direction)
    turned = Lighting.parse(env, lights).turned(d)
    want = Lighting.parse(*_turned_by_text(env, lights, d))
    assert turned.lights == want.lights  # the same floats
    if turned.sun is not None:
        assert turned.sun == want.sun
        np.testing.assert_array_equal(turned.environment.sun_direction,
                                      want.environment.sun_direction)
    assert Lighting.parse(*turned.to_spec()).lights == turned.lights


def test_a_bake_config_made_from_a_lighting_keeps_its_specs_and_the_value():
    lighting = Lighting.parse("sky:sun=3", ("dir:1,2,3:2,1,1",))
    config = BakeConfig.lit_by(lighting, samples=5)
    assert (config.env, config.lights) == ("sky:sun=3", ("dir:1,2,3:2,1,1",))
    assert config.lighting is lighting
    relit = config.with_lighting(lighting.turned((0.0, 0.0, 1.0)))
    assert relit.lighting.lights[0].direction == (0.0, 0.0, 1.0)
    assert BakeConfig.from_dict(relit.to_dict()) == relit
