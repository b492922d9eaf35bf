"""The installed layout of the package, as links: what a wheel of pyproject.toml holds.

``python tests/layout.py DIR`` makes ``DIR/isolume/...`` (each package of
``[tool.setuptools] packages`` a folder of links to the modules of its folder under
``package-dir``) and prints DIR; ``./run --tests`` points lint-imports at it, since the
import graph needs one folder per package (the editable install maps `isolume` to
app/api and `isolume.app` to app).
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_folders(root: Path = ROOT) -> dict[str, Path]:
    """{package: its source folder} of pyproject.toml's packages."""
    config = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = config["package-dir"]
    found = {}
    for package in config["packages"]:
        parent = max((p for p in folders if package == p or package.startswith(p + ".")),
                     key=len)
        rest = package[len(parent):].lstrip(".").replace(".", "/")
        found[package] = root / folders[parent] / rest
    return found


def make_layout(target: Path, root: Path = ROOT) -> Path:
    """Link the files of every package (its modules, py.typed, shaders…) into `target` as
    a wheel would place them."""
    for package, folder in package_folders(root).items():
        place = target.joinpath(*package.split("."))
        place.mkdir(parents=True, exist_ok=True)
        for module in (f for f in folder.iterdir() if f.is_file()):
            link = place / module.name
            if not link.exists():
                link.symlink_to(module)
    return target


if __name__ == "__main__":
    print(make_layout(Path(sys.argv[1])))
