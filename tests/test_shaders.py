"""The GLSL preprocessor, tested as strings (no GL)."""

import pytest

from isolume import shaders


def test_defines_follow_version_line():
    text = shaders.source("surface.frag", {"SHADING": 3, "FLAG": True, "SCALE": 2.0})
    lines = text.splitlines()
    assert lines[0].startswith("#version 330")
    assert lines[1:4] == ["#define SHADING 3", "#define FLAG 1", "#define SCALE 2.0"]


def test_include_is_expanded_once():
    text = shaders.source("surface.frag", {"SHADING": 1})
    assert "#include" not in text
    assert text.count("vec3 lambert_irradiance(") == 1
    assert "// begin lighting.glsl" in text


def test_unknown_include_fails_loudly(tmp_path, monkeypatch):
    (tmp_path / "a.frag").write_text('#version 330 core\n#include "missing.glsl"\n')
    monkeypatch.setattr(shaders, "shader_dir", lambda: tmp_path)
    with pytest.raises(shaders.ShaderError, match=r"missing\.glsl"):
        shaders.source("a.frag")


def test_include_cycle_detected(tmp_path, monkeypatch):
    (tmp_path / "a.glsl").write_text('#include "b.glsl"\n')
    (tmp_path / "b.glsl").write_text('#include "a.glsl"\n')
    (tmp_path / "main.frag").write_text('#version 330 core\n#include "a.glsl"\n')
    monkeypatch.setattr(shaders, "shader_dir", lambda: tmp_path)
    # a -> b -> a: the second visit of a.glsl is skipped as already included, not looped
    text = shaders.source("main.frag")
    assert text.count("begin a.glsl") == 1 and text.count("begin b.glsl") == 1


def test_self_include_is_a_cycle(tmp_path, monkeypatch):
    (tmp_path / "main.frag").write_text('#version 330 core\n#include "main.frag"\n')
    monkeypatch.setattr(shaders, "shader_dir", lambda: tmp_path)
    text = shaders.source("main.frag")  # the root counts as included: nothing duplicated
    assert text.count("#version") == 1


def test_bad_define_name_and_missing_version(tmp_path, monkeypatch):
    with pytest.raises(shaders.ShaderError, match="not a GLSL identifier"):
        shaders.source("surface.frag", {"1BAD": 1})
    (tmp_path / "nov.frag").write_text("void main() {}\n")
    monkeypatch.setattr(shaders, "shader_dir", lambda: tmp_path)
    with pytest.raises(shaders.ShaderError, match="no #version"):
        shaders.source("nov.frag")
