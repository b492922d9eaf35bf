"""The quick-start notebook (docs/quickstart.ipynb) runs clean in a kernel, and its
outputs are what it says: a picture, a bake with a progress widget, three pictures of a
sweep, a mesh."""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np
import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "docs" / "quickstart.ipynb"


def _pictures(cell) -> list[np.ndarray]:
    from PIL import Image

    return [np.asarray(Image.open(io.BytesIO(base64.b64decode(out["data"]["image/png"]))))
            for out in cell.outputs if "image/png" in out.get("data", {})]


@pytest.mark.slow
def test_the_quick_start_notebook_runs_and_shows_what_it_says(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    monkeypatch.delenv("QT_API", raising=False)  # set by Qt's test plugins; tqdm would
    notebook = nbformat.read(NOTEBOOK, as_version=4)  # take the kernel for a Qt console
    nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    cells = [c for c in notebook.cells if c.cell_type == "code"]
    assert not [o for c in cells for o in c.outputs if o.output_type == "error"]
    assert "suggested isovalues" in "".join(o.get("text", "") for o in cells[0].outputs)
    (first,) = _pictures(cells[1])
    assert first.shape == (288, 384, 3) and first.std() > 10
    widgets = [o for o in cells[2].outputs
               if "application/vnd.jupyter.widget-view+json" in o.get("data", {})]
    assert widgets, "the bake's progress is a widget in a notebook"
    assert (tmp_path / "engine.npz").exists()
    sweep = _pictures(cells[3])
    assert len(sweep) == 3 and all(p.shape == (192, 256, 3) for p in sweep)
    assert not np.array_equal(sweep[0], sweep[2])
    assert (tmp_path / "engine.glb").stat().st_size > 10_000
