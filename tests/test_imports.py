"""Data flows one way: volumes → baking → app. Checked in fresh interpreters."""

import subprocess
import sys

import pytest

CHECK = "import sys, {mods}; bad = [m for m in {forbidden!r} if m in sys.modules]; print(bad)"


@pytest.mark.parametrize(
    ("modules", "forbidden"),
    [
        ("isolume.volumes", ["moderngl", "glfw", "embreex", "isolume.baking", "isolume.app"]),
        ("isolume.baking", ["moderngl", "glfw", "embreex", "isolume.app"]),
        ("isolume.app.cli, isolume.app.render.renderer, isolume.app.render.glcontext",
         ["embreex"]),
        # loaded when a chart runs
        ("isolume.app.charts.charts", ["moderngl", "matplotlib", "embreex"]),
        ("isolume.app.reference", ["embreex", "moderngl"]),
    ],
)
def test_import_direction(modules, forbidden):
    code = CHECK.format(mods=modules, forbidden=forbidden)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", f"importing {modules} loaded {out.stdout.strip()}"
