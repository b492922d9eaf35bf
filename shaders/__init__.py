"""GLSL sources and the small preprocessor that assembles them.

Shaders are real files in this folder. `source(name, defines)` returns the text with

* ``#include "file.glsl"`` lines replaced by that file (recursively, each file once),
* the given ``defines`` inserted as ``#define NAME VALUE`` lines right after ``#version``.

Unknown include files, include cycles, a missing ``#version`` line and define names that
are not identifiers raise `ShaderError` — nothing is silently dropped. This module needs
no GL and is tested as plain strings.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$')
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\([A-Za-z_][A-Za-z0-9_, ]*\))?$")


class ShaderError(ValueError):
    """A shader file could not be assembled."""


def shader_dir() -> Path:
    """Folder holding the GLSL files (works from a source tree and an installed wheel)."""
    return Path(str(resources.files(__name__)))


def _read(name: str) -> str:
    path = shader_dir() / name
    if not path.is_file():
        available = sorted(p.name for p in shader_dir().glob("*") if p.suffix != ".py")
        raise ShaderError(f"shader file {name!r} not found; available: {', '.join(available)}")
    return path.read_text()


def _expand(name: str, stack: tuple[str, ...], seen: set[str]) -> list[str]:
    """Lines of `name` with includes expanded; `stack` detects cycles."""
    if name in stack:
        raise ShaderError(f"include cycle: {' -> '.join((*stack, name))}")
    out: list[str] = []
    for number, line in enumerate(_read(name).splitlines(), start=1):
        match = _INCLUDE.match(line)
        if match is None:
            out.append(line)
            continue
        child = match.group(1)
        if child in seen:
            continue
        seen.add(child)
        out.append(f"// begin {child} (included from {name}:{number})")
        out.extend(_expand(child, (*stack, name), seen))
        out.append(f"// end {child}")
    return out


def _define_lines(defines: dict[str, object]) -> list[str]:
    lines = []
    for key, value in defines.items():
        if not _IDENT.match(key):
            raise ShaderError(f"define name {key!r} is not a GLSL identifier or NAME(args)")
        if isinstance(value, bool):
            value = int(value)
        if isinstance(value, float):
            value = repr(value) if "." in repr(value) or "e" in repr(value) else f"{value}.0"
        lines.append(f"#define {key} {value}".rstrip())
    return lines


def source(name: str, defines: dict[str, object] | None = None) -> str:
    """Assembled GLSL text of shader file `name` with `defines` applied."""
    lines = _expand(name, (), {name})
    version = next((i for i, line in enumerate(lines) if line.startswith("#version")), None)
    if version is None:
        raise ShaderError(f"shader {name!r} has no #version line")
    extra = _define_lines(defines or {})
    return "\n".join([*lines[: version + 1], *extra, *lines[version + 1 :]]) + "\n"
