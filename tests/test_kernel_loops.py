"""The compiled per-point loops keep no reference counting.

numba increments and decrements an array's reference count (atomic operations) where a
function binds it, and its pruning pass removes the pairs only where nothing in between
calls a function that takes arrays: a per-point call of such a helper, or a view such as
``out[i]`` taken per point, leaves the pairs in the loop (30 atomic operations per normal
made `volumes.normals_at` twice as slow on one thread). These tests compile each kernel
afresh for the argument types a bake gave it and count the operations left in the
blocks of its loops, in the LLVM IR of the kernel and of every helper compiled with it.
"""

from __future__ import annotations

import re

import numba
import numpy as np
import pytest
from graphs import strongly_connected

from isolume import volumes
from isolume.baking import BakeConfig, bake, pixel_kernels, plan_kernels, side_kernels
from isolume.baking.lights import SunLight
from isolume.baking.reference import primary_hits
from isolume.baking.shadow_rays import light_factors
from isolume.baking.trace import Scene
from isolume.volumes import field

PER_POINT = [
    (field, "_normals"), (field, "_gradients"), (field, "_trilinear"),
    (field, "_grid_trilinear"), (plan_kernels, "gradient_norms"),
    (plan_kernels, "landed_starts"), (plan_kernels, "reach_tests"),
    (side_kernels, "probe_sides"), (pixel_kernels, "sun_factors"),
    (pixel_kernels, "primary_starts"),
]
"""The kernels whose loops run per point, texel or pixel, with the helpers compiled with
them (`reach_tests`: `volumes.field.newton_steps`, `volumes.field.along_normals`)."""

ONCE_PER_ITEM = {
    "calls of _nearest_crossing": "a stalled Newton point's search along 26 lines",
    "_lit_side_checks": "its loop over the two sides",
    "calls of along_normals": "one for each side, from `_lit_side_checks`",
}
"""Helpers whose counting runs once per item of a loop that does far more per item."""

_NRT = re.compile(r"call void @NRT_(?:incref|decref)")


@pytest.fixture(scope="module")
def baked() -> None:
    """Gives every kernel of `PER_POINT` its argument types: a small bake."""
    volume = volumes.load("synthetic:engine:32")
    bake(volume, BakeConfig(samples=2, bounces=1, env="sky:sun=3"), workers=1)
    volumes.normals_at(volume, np.zeros((2, 3)))
    volumes.gradient_at(volume, np.zeros((2, 3)))
    volumes.value_at(volume, np.zeros((2, 3)))
    volumes.values_on_grid(volume, np.zeros(2), np.zeros(2), np.zeros(2))
    volumes.values_along_normals(volume, np.zeros((2, 3)), 0.1)
    plate = Scene(np.array([[-1, -1, 1], [1, -1, 1], [0, 1, 1]], np.float32),
                  np.array([[0, 1, 2]], np.int32))
    light_factors(plate, np.zeros((2, 3)), np.tile([[0.0, 0.0, 1.0]], (2, 1)),
                  (SunLight((0.0, 0.0, 1.0), (1.0, 1.0, 1.0), 0.5),), workers=1)
    mesh = volumes.isosurface(volume, 0.3)
    centre = np.mean(volume.box, axis=0)
    primary_hits(Scene(mesh.vertices, mesh.faces), volume, np.tile(centre + 2.0, (2, 1)),
                 np.tile(-np.ones(3) / np.sqrt(3.0), (2, 1)), BakeConfig())


def _functions(ir: str) -> dict[str, str]:
    """The bodies of the module's functions by mangled name, numba's wrappers left out."""
    out = {}
    for text in re.split(r"\ndefine ", ir)[1:]:
        name = re.search(r"@([^\s(]+)\(", text.splitlines()[0])
        if name and name.group(1).startswith("_ZN") and not name.group(1).startswith(
                ("_ZN5numba", "_ZN7cpython")):
            out[name.group(1)] = text.split("\n}\n")[0]
    return out


def _short(mangled: str) -> str:
    """The function's own name in numba's mangled name (its last length-prefixed part)."""
    parts, i = [], 3  # after "_ZN"
    while i < len(mangled) and mangled[i].isdigit():
        j = i
        while mangled[j].isdigit():
            j += 1
        parts.append(mangled[j:j + int(mangled[i:j])])
        i = j + int(mangled[i:j])
    return parts[-1]


def _blocks(body: str) -> tuple[dict[str, list[str]], dict[str, set[str]]]:
    """A function's basic blocks (their lines) and the blocks each branches to."""
    blocks, name = {"entry": []}, "entry"
    for line in body.splitlines()[1:]:
        label = re.match(r"^([\w.\-]+):", line)
        if label:
            name = label.group(1)
            blocks[name] = []
        else:
            blocks[name].append(line)
    succ = {b: set(re.findall(r"label %([\w.\-]+)", "\n".join(lines)))
            for b, lines in blocks.items()}
    return blocks, succ


def _in_loops(succ: dict[str, set[str]]) -> set[str]:
    """The blocks on a cycle of the control-flow graph: in a strongly connected
    component of several blocks, or branching to themselves."""
    return {block for component in strongly_connected(succ) for block in component
            if len(component) > 1 or block in succ.get(block, ())}


def loop_counting(ir: str) -> dict[str, int]:
    """Per function of the module (short name): the reference-count operations in its
    loops; and per helper with such operations that a loop calls ("calls of NAME"),
    their number times the loops that call it."""
    functions = _functions(ir)
    counting = {name: len(_NRT.findall(body)) for name, body in functions.items()}
    found = {_short(name): 0 for name in functions}
    for name, body in functions.items():
        blocks, succ = _blocks(body)
        for block in _in_loops(succ):
            for line in blocks[block]:
                found[_short(name)] += bool(_NRT.search(line))
                for callee in re.findall(r"call [^@]*@(_ZN[^\s(]+)\(", line):
                    if counting.get(callee):
                        key = f"calls of {_short(callee)}"
                        found[key] = found.get(key, 0) + counting[callee]
    return found


@numba.njit(nogil=True)
def _ratio(row, out):
    out[0] = row[0] / row[1]  # may raise: Python's error model


@numba.njit(nogil=True)
def _ratios(rows, out):
    for i in range(rows.shape[0]):
        _ratio(rows[i], out[i])


def test_the_scan_finds_counting_in_a_loop():
    """The scan itself: views passed per row to a helper that may raise keep their
    counting in the loop."""
    _ratios(np.ones((4, 2)), np.empty((4, 1)))
    assert loop_counting(_ratios.inspect_llvm(_ratios.signatures[0]))["_ratios"] > 0


@pytest.mark.parametrize("module, name", PER_POINT, ids=[n for _, n in PER_POINT])
def test_per_point_loops_keep_no_reference_counting(baked, module, name):
    kernel = getattr(module, name)
    assert kernel.signatures, f"{name} was not run by the bake"
    options = {k: v for k, v in kernel.targetoptions.items() if k != "cache"}
    fresh = numba.njit(**options)(kernel.py_func)
    fresh.compile(kernel.signatures[0])
    counting = loop_counting(fresh.inspect_llvm(fresh.signatures[0]))
    assert name in counting
    left = {f: n for f, n in counting.items() if n and f not in ONCE_PER_ITEM}
    assert not left, f"reference counting in the loops of {left}"
