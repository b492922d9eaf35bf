"""The module graph of isolume: every module imports, no import cycle, and no module takes
another's private names.

The graph is read from the sources (every import statement, also those inside functions
and under ``TYPE_CHECKING``), so a cycle that only a late import closes counts too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from graphs import strongly_connected

ROOT = Path(__file__).resolve().parents[1]
def _modules() -> dict[str, Path]:
    """{dotted module name: source file} of every module of isolume, as pyproject's
    packages and ``package-dir`` install them (`layout.package_folders`: app/api is
    `isolume`)."""
    from layout import package_folders

    modules = {}
    for package, folder in package_folders().items():
        for path in sorted(folder.glob("*.py")):
            name = package if path.stem == "__init__" else f"{package}.{path.stem}"
            modules[name] = path
    return modules


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[str, str | None, int]]:
    """(imported module, imported name or None, line) of every isolume import in `path`;
    ``from PACKAGE import MODULE`` counts as an import of the module."""
    found = []
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, None, node.lineno) for alias in node.names
                      if alias.name.startswith("isolume")]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the importing package
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            if not base.startswith("isolume"):
                continue
            for alias in node.names:
                full = f"{base}.{alias.name}"
                if full in MODULES:
                    found.append((full, None, node.lineno))
                else:
                    found.append((base, alias.name, node.lineno))
    return found


def _graph() -> dict[str, set[str]]:
    """{module: the isolume modules it imports}."""
    return {name: {target for target, _, _ in _imports(name, path)
                   if target in MODULES and target != name}
            for name, path in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, each sorted."""
    return [c for c in strongly_connected(graph) if len(c) > 1]


def test_the_source_tree_has_the_installed_modules():
    assert {"isolume.baking.bake", "isolume.volumes.core", "isolume.app.cli"} <= set(MODULES)


def test_the_cycle_finder_finds_cycles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    cycles = _cycles(_graph())
    assert not cycles, "modules that import each other (directly or around a loop): " + \
        "; ".join(" <-> ".join(cycle) for cycle in cycles)


def test_no_module_imports_another_modules_private_names():
    private = [f"{MODULES[name].relative_to(ROOT)}:{line} imports {target}.{imported}"
               for name, path in MODULES.items()
               for target, imported, line in _imports(name, path)
               if imported is not None and imported.startswith("_") and target != name]
    assert not private, "\n".join(private)


def test_every_tracing_backend_offers_the_whole_protocol():
    """The baker hands its passes to local threads or a Dask cluster through
    `TracingBackend` alone: both implement each of its methods, with its parameters."""
    import inspect

    from isolume.baking.backend import ThreadBackend, TracingBackend
    from isolume.baking.cluster import ClusterBackend

    methods = [name for name, member in vars(TracingBackend).items()
               if inspect.isfunction(member) and not name.startswith("_")]
    assert "trace_pass" in methods and "close" in methods
    for backend in (ThreadBackend, ClusterBackend):
        for name in methods:
            want = inspect.signature(getattr(TracingBackend, name)).parameters
            got = inspect.signature(getattr(backend, name)).parameters
            assert list(got) == list(want), f"{backend.__name__}.{name}"


def _part(name: str) -> str:
    """The part of isolume module `name` belongs to: a folder's package, or the API."""
    parts = name.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 and parts[1] in PARTS else "isolume"


PARTS = ("app", "baking", "volumes", "shaders")
"""The subpackages that are the repository's top-level folders."""


@pytest.mark.parametrize("package", ["isolume", *(f"isolume.{p}" for p in PARTS)])
def test_every_module_imports_in_a_fresh_interpreter(package):
    """Each module of `package` imports on its own, in a fresh interpreter (an import
    cycle that Python cannot resolve fails here)."""
    names = sorted(name for name in MODULES if _part(name) == package)
    code = ("import importlib, sys\n"
            "bad = []\n"
            f"for name in {names!r}:\n"
            "    for loaded in [m for m in sys.modules if m.startswith('isolume')]:\n"
            "        del sys.modules[loaded]\n"
            "    try:\n"
            "        importlib.import_module(name)\n"
            "    except Exception as exc:\n"
            "        bad.append(f'{name}: {type(exc).__name__}: {exc}')\n"
            "print('\\n'.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT.parent)
    assert out.stdout.strip() == "", out.stdout
