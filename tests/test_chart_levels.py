"""Chart 5 (``isolume chart --charts 5``): error against bake time per level policy."""

import json

import pytest

from isolume.app.charts.levels import POLICIES
from isolume.app.cli import main


def test_level_policy_chart(tmp_path):
    from isolume.app.render.glcontext import GLUnavailable, create_headless

    try:
        create_headless("osmesa").release()
    except GLUnavailable as exc:
        pytest.skip(f"no OSMesa: {exc}")
    status = main(["chart", "synthetic:shells:20", "--charts", "5", "--samples", "4,64",
                   "--size", "48x48", "--bounces", "1", "--ref-max-seconds", "5",
                   "--gl", "osmesa", "--out", str(tmp_path)])
    assert status == 0
    record = json.loads((tmp_path / "chart5_levels.json").read_text())
    assert (tmp_path / "chart5_levels.png").stat().st_size > 10_000
    series = record["series"]
    assert list(series) == [label for label, _ in POLICIES]
    for points in series.values():
        assert [p["samples"] for p in points] == [4, 64]
        assert all(p["error"] > 0 and p["seconds"] > 0 for p in points)
    auto, fine, coarse = series["auto"], series["0.25 voxel"], series["2 voxels"]
    # the automatic policy loosens the spacing at 4 paths and tightens it at 64
    assert auto[0]["move_limit_voxels"] == 2.0 and auto[1]["move_limit_voxels"] == 1.0
    assert auto[0]["levels"] <= auto[1]["levels"] <= fine[1]["levels"]
    assert coarse[0]["levels"] == coarse[1]["levels"] <= fine[0]["levels"]
    assert auto[1]["error"] < auto[0]["error"]  # noise falls with the samples
