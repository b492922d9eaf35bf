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
              "texel_error": texel, "bake_seconds": paths / 1e6, "mean_ratio": 1.0,
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


def test_every_sweep_is_checked_against_the_baseline_case_by_case(tmp_path, capsys):
    """A case fails when its error exceeds the baseline's by more than the case's
    reference noise + 0.5 % (the sweeps' rows: noise 0.4 %), or it has black pixels or a
    mean ratio beyond the sweep's limits; the smallest margin and its case are named."""
    base = _sweep(tmp_path / "u100", 100, None, [("a", 1.0, 0.02, 4_000_000),
                                                 ("b", 2.0, 0.03, 4_000_000),
                                                 ("c", 3.0, 0.05, 4_000_000)])
    close = _sweep(tmp_path / "tx", 36, None, [("a", 1.0, 0.028, 1_000_000),
                                               ("b", 2.0, 0.03, 1_000_000),
                                               ("c", 3.0, 0.06, 2_000_000)], texel=0.02)
    dark = _sweep(tmp_path / "u32", 32, None, [("a", 1.0, 0.02, 1_000_000),
                                               ("b", 2.0, 0.03, 1_000_000),
                                               ("c", 3.0, 0.05, 1_000_000)])
    document = json.loads((dark / "accuracy.json").read_text())
    bakes = [r for r in document["rows"] if r["mode"] == "bake"]
    bakes[0]["black_fraction"], bakes[1]["mean_ratio"] = 0.002, 0.96
    (dark / "accuracy.json").write_text(json.dumps(document))
    sweeps = [read_sweep(base), read_sweep(close), read_sweep(dark)]
    record = front(sweeps, sweeps[0])
    near, black = record["against_baseline"]
    assert near["failed"] == [{"volume": "c", "iso": 3.0}]
    assert near["smallest_margin"] == pytest.approx(-0.001)
    assert near["smallest_at"] == {"volume": "c", "iso": 3.0}
    assert near["paths_ratio"] == pytest.approx(4 / 12)
    assert [f["volume"] for f in black["failed"]] == ["a", "b"]
    assert black["smallest_margin"] == pytest.approx(0.009)
    assert front(sweeps)["against_baseline"] == []
    pytest.importorskip("matplotlib")
    out = tmp_path / "front.png"
    assert main(["bench", "front", str(close), "--baseline", str(base), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert ("36 paths, texel error 0.02 against 100 paths: 1 of 3 cases beyond" in printed
            and "smallest margin -0.10 points (c at 3)" in printed)


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


def test_a_sweep_is_set_against_the_cheapest_uniform_one_as_accurate(tmp_path):
    """The cheapest uniform sweep whose median, p90, worst and black cases are each at
    most the texel sweep's, and the uniform curve's paths at its median, log-linear between the two
    sweeps around it; a uniform sweep at another scale counts for the first only."""
    cases = [("a", 1.0), ("b", 2.0), ("c", 3.0)]

    def sweep(name, samples, errors, paths, **kw):
        return read_sweep(_sweep(tmp_path / name, samples, None,
                                 [(v, iso, e, paths) for (v, iso), e in zip(cases, errors,
                                                                          strict=True)],
                                 **kw))

    record = front([
        sweep("u32", 32, (0.02, 0.04, 0.10), 1_000_000),      # median 4 %
        sweep("u64", 64, (0.015, 0.03, 0.09), 2_000_000),     # median 3 %, as good
        sweep("u128", 128, (0.01, 0.025, 0.08), 4_000_000),   # better, dearer
        sweep("half", 100, (0.01, 0.02, 0.095), 500_000, scale=0.5),  # worst too high
        sweep("tx", 36, (0.02, 0.032, 0.091), 800_000, texel=0.02)])
    (compared,) = record["against_uniform"]
    assert compared["label"] == "36 paths, texel error 0.02"
    assert compared["cheapest_as_good"] == "64 paths"
    assert compared["its_paths"] == 6_000_000 and compared["paths"] == 2_400_000
    # median 3.2 %: 0.8 of the way from 32 paths (4 %) to 64 (3 %) in log paths
    assert compared["at_median_paths"] == pytest.approx(3_000_000 * 2 ** 0.8)
    worse = front([sweep("u16", 16, (0.05, 0.06, 0.2), 500_000),
                   sweep("tx2", 36, (0.02, 0.032, 0.091), 800_000, texel=0.02)])
    (none,) = worse["against_uniform"]
    assert none["cheapest_as_good"] is None and none["at_median_paths"] is None
    black = tmp_path / "u64b"
    sweep("u64b", 64, (0.015, 0.03, 0.09), 2_000_000)
    document = json.loads((black / "accuracy.json").read_text())
    document["rows"][-1]["black_fraction"] = 0.01  # a case with black pixels
    (black / "accuracy.json").write_text(json.dumps(document))
    dark = front([read_sweep(black), sweep("tx3", 36, (0.02, 0.032, 0.091), 800_000,
                                            texel=0.02)])
    assert dark["against_uniform"][0]["cheapest_as_good"] is None


def test_a_bake_shared_by_several_cases_is_counted_once(tmp_path):
    """Rows of one bake drawn at several isovalues (``--bake-range default``) carry its
    paths, seconds and bytes with ``shared_by``: the sums count the bake once."""
    folder = _sweep(tmp_path / "d", 36, None, [("a", 1.0, 0.03, 6_000_000),
                                               ("a", 2.0, 0.05, 6_000_000)], texel=0.02)
    document = json.loads((folder / "accuracy.json").read_text())
    for row in document["rows"]:
        row["shared_by"] = 2
    (folder / "accuracy.json").write_text(json.dumps(document))
    (point,) = front([read_sweep(folder)])["points"]
    assert point["paths"] == 6_000_000 and point["lattice_bytes"] == 1000
    assert point["bake_seconds"] == pytest.approx(6.0)
