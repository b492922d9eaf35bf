"""Golden outputs: hashes of small lattices and pictures, to prove that a change which
moves code changes no result.

``python tests/golden/record.py [--check]`` bakes (irradiance, SH, ambient occlusion, a
Dask cluster bake, a relit lazy bake) and renders (every shading mode, the view's traced
GI) a 32³ synthetic engine through the command line and the public API, then writes the
SHA-256 of every array to ``hashes.json`` beside this file (``--check``: compares instead,
exit 1 on a difference). `tests/test_golden.py` runs the check. Pictures depend on the
GL implementation (Mesa llvmpipe through OSMesa), recorded with the hashes: a picture is
compared only under the same renderer string.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
HASHES = HERE / "hashes.json"
VOLUME = "synthetic:engine:32"
ISO = "0.3"
SMALL = ["--samples", "8", "--bounces", "1", "--seed", "7", "--workers", "2"]
BAKES = {
    "irradiance": ["--env", "sky:sun=3"],
    "irradiance_lattice_sun": ["--env", "sky:sun=3", "--direct-light", "lattice"],
    "sh": ["--mode", "sh", "--sh-order", "3", "--env", "sky"],
    "sh_split": ["--mode", "sh", "--sh-order", "3", "--env", "sky:sun=3",
                 "--direct-light", "pixels"],
    "ao": ["--env", "constant:1,1,1", "--bounces", "0"],
    "point": ["--env", "", "--light", "point:0,0,40:2000,2000,2000"],
}
RENDERS = {  # name: (lattice or None, extra render arguments)
    "gi_traced": (None, ["--samples", "8", "--workers", "2", "--seed", "7"]),
    "irradiance": ("irradiance", []),
    "irradiance_shadow_map": ("irradiance", ["--shadows", "map"]),
    "point_shadow_map": ("point", ["--shadows", "map"]),
    "irradiance_lattice_sun": ("irradiance_lattice_sun", []),
    "irradiance_closest": ("irradiance", ["--shading", "irradiance_closest"]),
    "irradiance_nearest": ("irradiance", ["--shading", "irradiance_nearest"]),
    "irradiance_bspline": ("irradiance", ["--shading", "irradiance_bspline"]),
    "sh": ("sh", ["--env", "sky", "--env-rotation", "40,10"]),
    "sh_split": ("sh_split", ["--env", "sky:sun=3", "--env-rotation", "40,10"]),
    "vicinity": ("ao", ["--shading", "vicinity"]),
    "ao": ("ao", ["--shading", "ao"]),
    "point": ("point", []),
    **{m: (None, ["--shading", m]) for m in (
        "lambert", "phong", "lambert_hemi", "phong_hemi", "lambert_shadow", "phong_shadow",
        "lambert_fog")},
}


def _cli_main():
    try:
        from isolume.app.cli import main
    except ImportError:
        from isolume.app.cli import main
    return main


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _lattice_digest(path: Path) -> str:
    """The lattice's arrays dense over its box, in name order (whatever the file's layout)."""
    from isolume.baking.lattice import Lattice

    lattice = Lattice.load(path)
    return _digest(*(getattr(lattice, k) for k in ("active", "facing", "samples", "second",
                                                    "values")))


def _picture_digest(path: Path) -> str:
    from PIL import Image

    return _digest(np.asarray(Image.open(path)))


def _run(argv: list[str]) -> None:
    status = _cli_main()(argv)
    if status:
        raise SystemExit(f"isolume {' '.join(argv)} exited {status}")


def _cluster_digest(folder: Path) -> str:
    out = folder / "cluster.npz"
    _run(["bake", VOLUME, "--out", str(out), "--iso-range", "0.25", "0.35", *SMALL,
          "--env", "sky:sun=3", "--scheduler", "local:2"])
    return _lattice_digest(out)


def _relight_digest() -> str:
    """A lazy bake of the surface seen from one eye under the default sun, the sun turned,
    and the same surface re-baked: the relit lattice's arrays."""
    try:
        from isolume import volumes
        from isolume.baking.bake import Baker
        from isolume.baking.config import BakeConfig
        from isolume.baking.lazy import LazyScheduler, Relight, View, relit_config, serve
    except ImportError:
        from isolume import volumes
        from isolume.baking.bake import Baker
        from isolume.baking.config import BakeConfig
        from isolume.baking.lazy import LazyScheduler, Relight, View, relit_config, serve

    volume = volumes.load(VOLUME)
    config = BakeConfig(samples=16, bounces=1, env="sky:sun=6,sun_az=-150,sun_el=40",
                        iso_range=(0.25, 0.35), seed=5)
    baker = Baker(volume, config, workers=1, scene_cache=64)

    def bake_view(samples):
        scheduler = LazyScheduler(baker.plan, baker.geometry, samples, max_samples=16,
                                  batch_paths=20_000)
        inbox = [View(0.3, (0.0, -3.0, 1.0), None)]

        def receive(block):
            if inbox:
                return inbox.pop(0)
            return "stop" if block else None

        serve(baker, scheduler, receive, lambda m: None, stop_when_done=True)

    try:
        bake_view(baker.lattice.samples.reshape(-1))
        before = _digest(baker.lattice.values, baker.lattice.samples)
        direction = np.array([0.6, 0.3, 0.5]) / np.linalg.norm([0.6, 0.3, 0.5])
        relight = Relight(baker.lattice, relit_config(baker.config, direction))
        baker.relight(relight.config, relight.fresh)
        bake_view(relight.fresh.samples.reshape(-1))
    finally:
        baker.close()
    fresh = relight.fresh
    return before + ":" + _digest(fresh.values, fresh.samples, fresh.second)


def _renderer() -> str:
    try:
        from isolume.app.glcontext import create_headless
    except ImportError:
        try:
            from isolume.app.render.glcontext import create_headless
        except ImportError:
            from isolume.app.render.glcontext import create_headless
    gl = create_headless("osmesa")
    try:
        return f"{gl.ctx.info['GL_RENDERER']} | {gl.ctx.info['GL_VERSION']}"
    finally:
        gl.release()


def record() -> dict:
    """{"lattices": {name: sha}, "pictures": {name: sha}, "renderer": str}."""
    out: dict = {"renderer": _renderer(), "lattices": {}, "pictures": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name, extra in BAKES.items():
            path = folder / f"{name}.npz"
            _run(["bake", VOLUME, "--out", str(path), "--iso-range", "0.25", "0.35",
                  *SMALL, *extra])
            out["lattices"][name] = _lattice_digest(path)
        out["lattices"]["cluster"] = _cluster_digest(folder)
        out["lattices"]["relight"] = _relight_digest()
        for name, (lattice, extra) in RENDERS.items():
            path = folder / f"{name}.png"
            argv = ["render", VOLUME, "--iso", ISO, "--size", "96x96", "--gl", "osmesa",
                    "--out", str(path), *extra]
            if lattice:
                argv += ["--lattice", str(folder / f"{lattice}.npz")]
            _run(argv)
            out["pictures"][name] = _picture_digest(path)
    return out


def differences(want: dict, got: dict) -> list[str]:
    """Names whose hashes differ (pictures only under the recorded renderer)."""
    bad = [f"lattice {k}" for k, v in want["lattices"].items() if got["lattices"].get(k) != v]
    if want["renderer"] == got["renderer"]:
        bad += [f"picture {k}" for k, v in want["pictures"].items()
                if got["pictures"].get(k) != v]
    return bad


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="compare with hashes.json")
    args = parser.parse_args(argv)
    got = record()
    if not args.check:
        HASHES.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
        print(f"wrote {HASHES}")
        return 0
    bad = differences(json.loads(HASHES.read_text()), got)
    print("golden: " + ("identical" if not bad else "DIFFERENT: " + ", ".join(bad)))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
