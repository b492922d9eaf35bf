"""``isolume bench front``: sweeps read, cases shared, sums and spreads, chart written."""

import json

import pytest

from isolume.app.bench.front import FrontError, front, read_sweep
from isolume.app.cli import main


def _sweep(folder, samples, target, cases, scale=1.0, texel=None):
    """A bench accuracy folder whose bake rows are `cases`: (volume, iso, error, paths)."""
    folder.mkdir(parents=True)
    rows = [{"volume": v, "iso": iso, "mode": "render", "rel_rmse_less_noise": 0.5,
             "paths_per_texel": 64} for v, iso, _, _ in cases]
    rows += [{"volume": v, "iso": iso, "mode": "bake", "rel_rmse_less_noise": error,
              "reference_noise": 0.004, "black_fraction": 0.0, "paths": paths,
              "samples": samples, "target_error": target, "scale": scale,
              "texel_error": texel, "bake_seconds": paths / 1e6,
              "lattice_bytes": 1000} for v, iso, error, paths in cases]
    (folder / "accuracy.json").write_text(json.dumps({"rows": rows}))
    return folder


def test_the_front_sums_and_spreads_the_shared_cases(tmp_path):
    uniform = _sweep(tmp_path / "u", 100, None,
                     [("a", 1.0, 0.02, 3_000_000), ("b", 2.0, 0.06, 10_000_000),
                      ("c", 3.0, 0.03, 1_000_000)])
    target = _sweep(tmp_path / "t", 16, 0.1,
                    [("a", 1.0, 0.03, 1_000_000), ("b", 2.0, 0.07, 6_000_000)])
    record = front([read_sweep(uniform), read_sweep(target)])
    by_label = {p["label"]: p for p in record["points"]}
    assert set(by_label) == {"100 paths", "target 0.1 (from 16)"}
    u, t = by_label["100 paths"], by_label["target 0.1 (from 16)"]
    assert u["paths"] == 13_000_000 and t["paths"] == 7_000_000  # "c" is in one sweep only
    assert u["median"] == pytest.approx(0.04) and u["worst"] == 0.06
    assert t["kind"] == "target" and u["kind"] == "uniform"
    assert record["left_out"] == [{"volume": "c", "iso": 3.0}]
    assert record["cases"][1]["error"]["target 0.1 (from 16)"] == 0.07
    coarse = read_sweep(_sweep(tmp_path / "c", 100, None, [("a", 1.0, 0.03, 400_000)], 0.5))
    assert (coarse["kind"], coarse["label"]) == ("uniform, scale 0.5", "100 paths x0.5")
    texels = read_sweep(_sweep(tmp_path / "x", 100, None, [("a", 1.0, 0.02, 900_000)],
                               texel=0.05))
    assert (texels["kind"], texels["label"]) == ("texels, uniform",
                                                 "100 paths, texel error 0.05")
    assert texels["texel_error"] == 0.05


def test_the_command_writes_the_chart_and_refuses_what_it_cannot_read(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    a = _sweep(tmp_path / "a", 32, None, [("a", 1.0, 0.04, 1_000_000)])
    b = _sweep(tmp_path / "b", 100, None, [("a", 1.0, 0.03, 3_000_000)])
    c = _sweep(tmp_path / "c", 16, 0.1, [("a", 1.0, 0.032, 1_500_000)])
    out = tmp_path / "front.png"
    assert main(["bench", "front", str(a), str(b), str(c), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "target 0.1" in printed and out.stat().st_size > 10_000
    assert len(json.loads(out.with_suffix(".json").read_text())["points"]) == 3
    assert main(["bench", "front", str(a), str(tmp_path / "none"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none/accuracy.json" in err
    with pytest.raises(FrontError, match="share no bake case"):
        front([read_sweep(a), read_sweep(_sweep(tmp_path / "d", 8, None,
                                                [("z", 1.0, 0.1, 10)]))])
