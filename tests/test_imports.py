"""Data flows one way: volumes → baking → app. Checked in fresh interpreters."""

import subprocess
import sys

import pytest

CHECK = "import sys, {mods}; bad = [m for m in {forbidden!r} if m in sys.modules]; print(bad)"


@pytest.mark.parametrize(
    ("modules", "forbidden"),
    [
        ("volumes", ["moderngl", "glfw", "embreex", "baking", "app"]),
        ("baking", ["moderngl", "glfw", "embreex", "app"]),
        ("app, app.cli, app.render, app.glcontext", ["embreex"]),
        ("app.charts", ["moderngl", "matplotlib", "embreex"]),  # loaded when a chart runs
        ("app.reference", ["embreex", "moderngl"]),
    ],
)
def test_import_direction(modules, forbidden):
    code = CHECK.format(mods=modules, forbidden=forbidden)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", f"importing {modules} loaded {out.stdout.strip()}"
