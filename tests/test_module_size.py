"""Every module of isolume is at most `MAX_LINES` lines long, or says why it is longer.

Convention: a module longer than `MAX_LINES` lines keeps a line in its module docstring
that starts with ``Length:`` and explains why it stays in one piece, e.g.::

    Length: one table of the GLSL uniforms and the code that fills them; split, each half
    would have to repeat the other's names.

The explanation must be non-empty, and it counts only in the module docstring (the first
statement of the file), not in comments or other strings.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("app", "baking", "volumes", "shaders")
"""Top-level folders that install as isolume's packages (pyproject's ``package-dir``)."""
MAX_LINES = 700
"""The longest a module may be without a ``Length:`` line in its docstring."""


def _modules() -> list[Path]:
    """Every Python source file of isolume, sorted."""
    return sorted(path for folder in FOLDERS for path in (ROOT / folder).rglob("*.py"))


def _line_count(text: str) -> int:
    return len(text.splitlines())


def explains_length(text: str) -> bool:
    """True when the module docstring of the source `text` has a line that starts with
    ``Length:`` followed by an explanation."""
    docstring = ast.get_docstring(ast.parse(text)) or ""
    return any(line.strip().startswith("Length:") and line.strip()[len("Length:"):].strip()
               for line in docstring.splitlines())


def test_isolume_has_modules_to_measure():
    names = {path.relative_to(ROOT).as_posix() for path in _modules()}
    assert {"app/cli.py", "baking/bake.py", "volumes/core.py", "shaders/__init__.py"} <= names


def test_every_module_is_short_or_says_why():
    too_long = []
    for path in _modules():
        text = path.read_text()
        lines = _line_count(text)
        if lines > MAX_LINES and not explains_length(text):
            too_long.append(f"{path.relative_to(ROOT)}: {lines} lines")
    assert not too_long, (f"modules over {MAX_LINES} lines without a 'Length:' line in "
                          "their docstring: " + "; ".join(too_long))


def test_the_length_line_counts_only_in_the_module_docstring():
    assert explains_length('"""A module.\n\nLength: one state machine, read as one."""\n')
    assert explains_length('"""Length: the table and its reader stay together."""\nx = 1\n')
    assert not explains_length('"""A module.\n\nLength:\n"""\n')  # no explanation
    assert not explains_length('"""A module; its Length: is not explained."""\n')
    assert not explains_length('# Length: a comment is not the docstring\nx = 1\n')
    assert not explains_length('x = 1\n"""Length: a later string is not the docstring."""\n')
    assert not explains_length('def f():\n    """Length: a function\'s docstring."""\n')
