"""``isolume bench accuracy``: its figures on hand-made images, the reference's noise taken
out in quadrature, the files it writes, and its one-line errors."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from isolume.app.bench import accuracy
from isolume.app.bench.accuracy_metrics import (
    black_fraction,
    case_figures,
    less_noise,
    mean_ratio,
    next_spp,
    p99_error,
    reference_noise,
    relative_rmse,
    summarize,
)
from isolume.app.cli import main

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "volumes"
FAST = ["--size", "24x24", "--paths", "4", "--ref-spp", "64", "--gl", "osmesa"]
"""Options that keep a case to about a second."""


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    """References are kept under this test's folder, not the user's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))


def _hand_made():
    """Five pixels: four on the reference's surface at radiance 2 (grey), one off it.
    The picture shows 2.2, 2.2, 1.8 and black on them, and something off the surface."""
    reference = np.zeros((5, 3))
    reference[:4] = 2.0
    mask = np.array([True, True, True, True, False])
    image = np.array([[2.2] * 3, [2.2] * 3, [1.8] * 3, [0.0] * 3, [5.0] * 3])
    return image, reference, mask


def test_figures_of_a_hand_made_picture():
    """Differences 0.2, 0.2, −0.2, −2 on a mean of 2: RMSE √1.03 / 2, mean ratio 6.2 / 8,
    one black pixel in four, p99 between the two largest pixel errors; the pixel off the
    reference's surface counts nowhere but in the mask mismatch."""
    image, reference, mask = _hand_made()
    assert relative_rmse(image, reference, mask) == pytest.approx(math.sqrt(1.03) / 2)
    assert mean_ratio(image, reference, mask) == pytest.approx(0.775)
    assert black_fraction(image, reference, mask) == 0.25
    assert p99_error(image, reference, mask) == pytest.approx((0.2 + 0.97 * 1.8) / 2)
    figures = case_figures(image, image[:, 0] > 0, reference, mask, noise=0.0)
    assert figures["surface_pixels"] == 4 and figures["mask_mismatch"] == 2
    assert figures["rel_rmse_less_noise"] == pytest.approx(figures["rel_rmse"])


def test_a_scaled_picture_and_black_where_the_reference_is_dark():
    """10 % too bright everywhere: RMSE 10 %, ratio 1.1; a black pixel where the reference
    is black too is no black pixel."""
    rng = np.random.default_rng(1)
    reference = rng.uniform(0.5, 2.0, (100, 3))
    reference[7] = 0.0
    mask = np.ones(100, bool)
    image = 1.1 * reference
    assert relative_rmse(image, reference, mask) == pytest.approx(
        0.1 * np.sqrt(np.mean(reference**2)) / np.mean(reference))
    assert mean_ratio(image, reference, mask) == pytest.approx(1.1)
    assert black_fraction(image, reference, mask) == 0.0


def test_the_reference_noise_comes_out_in_quadrature():
    """A picture 5 % off pixel by pixel against a reference with 4 % noise of known
    standard error: the plain error is about √(5² + 4²) %, less the noise about 5 %."""
    rng = np.random.default_rng(0)
    n = 40000
    truth = np.ones((n, 3))
    image = truth * (1 + 0.05 * rng.standard_normal((n, 1)))
    stderr = np.full((n, 3), 0.04)
    reference = truth + stderr * rng.standard_normal((n, 3))
    mask = np.ones(n, bool)
    noise = reference_noise(reference, stderr, mask)
    assert noise == pytest.approx(0.04, rel=0.01)
    error = relative_rmse(image, reference, mask)
    assert error == pytest.approx(math.hypot(0.05, 0.04), rel=0.02)
    assert less_noise(error, noise) == pytest.approx(0.05, rel=0.03)
    assert less_noise(0.05, 0.03) == pytest.approx(0.04)
    assert less_noise(0.02, 0.03) == 0.0
    assert math.isnan(less_noise(0.02, math.inf))


def test_the_reference_gains_samples_towards_a_quarter_of_the_error():
    """Noise ∝ 1/√spp: noise equal to the error needs 16× the samples (+10 %), within
    2×–16× a step and the cap."""
    assert next_spp(256, 0.04, 0.04, 100000) == 16 * 256
    assert next_spp(256, 0.011, 0.04, 100000) == 2 * 256
    assert next_spp(256, 0.02, 0.04, 100000) == math.ceil(256 * 4 * 1.1)
    assert next_spp(256, 0.04, 0.04, 1000) == 1000
    assert next_spp(256, 0.04, 0.0, 100000) == 16 * 256


def test_the_summary_counts_cases():
    rows = [{"volume": f"v{i}", "iso": float(i), "mode": mode, "rel_rmse": e,
             "rel_rmse_less_noise": e - 0.01, "black_fraction": black, "mean_ratio": ratio,
             "noise_rule_holds": holds}
            for i, (mode, e, black, ratio, holds) in enumerate([
                ("render", 0.05, 0.0, 1.0, True), ("render", 0.10, 0.002, 0.96, False),
                ("render", 0.03, 0.0005, 1.02, True), ("bake", 0.08, 0.0, 1.05, True)])]
    summary = summarize(rows, [{"volume": "bad", "iso": None, "error": "unreadable"}])
    render = summary["modes"]["render"]
    assert render["cases"] == 3 and render["rel_rmse_less_noise"]["median"] == pytest.approx(
        0.04)
    assert render["rel_rmse"]["worst"] == 0.10 and render["worst_case"]["volume"] == "v1"
    assert summary["modes"]["bake"]["rel_rmse"]["p90"] == 0.08
    assert (summary["black_cases"], summary["ratio_cases"], summary["noise_rule_unmet"],
            summary["failures"]) == (1, 2, 1, 1)


def test_volumes_folders_names_and_blocks(tmp_path):
    """A folder stands for its volume files (sorted, other files left out); --only
    matches file names; block means keep 2 samples an axis; --up rules by name."""
    for name in ("b_4x4x4_uint8.raw.gz", "A.npy", "notes.json", "c.zfp"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub").mkdir()
    specs = accuracy.volume_specs([str(tmp_path), "synthetic:torus:24", "missing.raw"], None)
    assert [Path(s).name for s in specs[:2]] == ["A.npy", "b_4x4x4_uint8.raw.gz"]
    assert specs[2:] == ["synthetic:torus:24", "missing.raw"]
    assert [s for s in specs if accuracy.selected(s, "torus,B_4")] == [specs[1], specs[2]]
    assert accuracy.block_factor((256, 256, 128), 128) == 2
    assert accuracy.block_factor((341, 341, 93), 128) == 3
    assert accuracy.block_factor((64, 64, 512), 128) == 4
    assert accuracy.block_factor((300, 4, 4), 128) == 2
    assert accuracy.block_factor((256, 256, 128), 0) == 1
    rules = accuracy.parse_up_rules(["-y", "CThead=-z"])
    assert accuracy.up_axis("CThead_256x256x113_uint16.raw.gz", rules) == "-z"
    assert accuracy.up_axis("engine.raw", rules) == "-y"


def test_the_command_writes_its_table_json_and_contact_sheet(tmp_path, capsys):
    """A synthetic torus in both modes and a missing file: two rows, one failure (one line
    on stderr), exit status 1; the JSON's rows hold the figures, the table the rows."""
    pytest.importorskip("moderngl")
    from PIL import Image

    out = tmp_path / "acc"
    missing = tmp_path / "missing_8x8x8_uint8.raw"
    status = main(["bench", "accuracy", "synthetic:torus:24", str(missing), *FAST,
                   "--out", str(out)])
    stdout, stderr = capsys.readouterr()
    assert status == 1
    failed = [line for line in stderr.splitlines() if "missing_8x8x8" in line]
    assert len(failed) == 1 and "no such file" in failed[0]
    document = json.loads((out / "accuracy.json").read_text())
    rows = document["rows"]
    assert [r["mode"] for r in rows] == ["render", "bake"]
    for row in rows:
        assert row["volume"] == "torus" and row["iso"] == 0.5
        assert 0 < row["rel_rmse"] < 0.5 and 0.8 < row["mean_ratio"] < 1.2
        assert row["rel_rmse_less_noise"] <= row["rel_rmse"]
        assert row["reference_spp"] == 64 and row["surface_pixels"] > 50
        assert row["black_fraction"] == 0.0
    assert rows[1]["bake_seconds"] > 0 and rows[1]["iso_range"][0] < 0.5
    assert rows[1]["paths"] == 4 * rows[1]["active_texels"] and rows[1]["lattice_bytes"] > 0
    assert rows[1]["target_error"] is None and rows[1]["scale"] == 1.0  # --paths: exactly
    assert len(list((tmp_path / "xdg" / "isolume" / "references").iterdir())) == 1
    assert document["failures"][0]["volume"] == str(missing)
    assert document["summary"]["cases"] == 2 and document["complete"]
    table = (out / "table.txt").read_text().splitlines()
    assert table[0].startswith("volume") and table[1].split()[:3] == ["torus", "0.5", "render"]
    assert any(line.startswith("render ") and "median" in line for line in table)
    assert table[1] in stdout
    sheet = Image.open(out / "accuracy.png")
    assert sheet.height > 2 * 96 and sheet.width > 3 * 96


def test_one_bake_over_the_default_range_draws_isovalues_across_it(tmp_path, capsys):
    """``--bake-range default --isovalues across:3``: three isovalues spread evenly over
    the range ``isolume bake`` bakes by default, all drawn from one bake of the volume,
    whose paths, seconds and bytes the sums count once; a bad rule is one line."""
    pytest.importorskip("moderngl")
    from isolume import volumes
    from isolume.baking.plan import default_iso_range

    out = tmp_path / "across"
    assert main(["bench", "accuracy", "synthetic:torus:24", *FAST, "--bake-range",
                 "default", "--isovalues", "across:3", "--out", str(out)]) == 0
    capsys.readouterr()
    document = json.loads((out / "accuracy.json").read_text())
    bakes = [r for r in document["rows"] if r["mode"] == "bake"]
    lo, hi = default_iso_range(volumes.load("synthetic:torus:24"))
    assert [r["iso"] for r in bakes] == pytest.approx([lo + (k + 0.5) * (hi - lo) / 3
                                                       for k in range(3)])
    assert all(r["iso_range"] == pytest.approx([lo, hi]) and r["shared_by"] == 3
               for r in bakes)
    assert len({(r["paths"], r["bake_seconds"], r["lattice_bytes"]) for r in bakes}) == 1
    totals = document["summary"]["modes"]["bake"]
    assert totals["total_paths"] == pytest.approx(bakes[0]["paths"])
    assert totals["total_lattice_bytes"] == pytest.approx(bakes[0]["lattice_bytes"])
    assert "3 across the default bake range" in document["settings"]["isovalues"]
    for bad in ("across:0", "some"):
        with pytest.raises(SystemExit) as exit_:
            main(["bench", "accuracy", "--isovalues", bad, "--out", str(tmp_path / "x")])
        assert exit_.value.code == 2
        assert "expected first, all or across:N" in capsys.readouterr().err


def test_a_kept_reference_is_where_a_later_sweep_starts(tmp_path, capsys):
    """The second sweep of the same case starts from the first's reference (the same
    figures; its row says so); another lighting is another reference; ``--cache none``
    keeps none."""
    pytest.importorskip("moderngl")
    cache = tmp_path / "refs"
    args = ["bench", "accuracy", "synthetic:torus:24", *FAST, "--skip-bake",
            "--cache", str(cache)]
    rows = []
    for out in ("a", "b"):
        assert main([*args, "--out", str(tmp_path / out)]) == 0
        rows.append(json.loads((tmp_path / out / "accuracy.json").read_text())["rows"][0])
    capsys.readouterr()
    assert [r["reference_kept"] for r in rows] == [False, True]
    assert rows[0]["rel_rmse"] == rows[1]["rel_rmse"]
    assert rows[1]["reference_seconds"] < rows[0]["reference_seconds"]
    assert main([*args[:-2], "--cache", "none", "--out", str(tmp_path / "c")]) == 0
    capsys.readouterr()
    assert len(list(cache.iterdir())) == 1


def test_a_missing_data_folder_is_one_line(tmp_path, capsys, monkeypatch):
    """--data or $ISOLUME_DATA naming a folder without volumes/: exit 2, one line naming
    it; nothing measured."""
    from isolume.app.bench.view import DATA_ENV

    missing = tmp_path / "nowhere"
    status = main(["bench", "accuracy", "--data", str(missing), "--out", str(tmp_path / "o")])
    _, err = capsys.readouterr()
    assert status == 2 and err.count("\n") == 1 and f"--data {missing}" in err
    monkeypatch.setenv(DATA_ENV, str(missing))
    status = main(["bench", "accuracy", "--out", str(tmp_path / "o")])
    _, err = capsys.readouterr()
    assert status == 2 and err.count("\n") == 1 and f"${DATA_ENV}" in err
    status = main(["bench", "accuracy", "synthetic:torus", "--only", "engine",
                   "--out", str(tmp_path / "o")])
    _, err = capsys.readouterr()
    assert status == 2 and err.count("\n") == 1 and "--only engine" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.shared
def test_one_real_scan(tmp_path, capsys):
    """The nucleon scan from ../shared/data (skipped without it), block-meaned to 20³."""
    pytest.importorskip("moderngl")
    path = SHARED / "nucleon_41x41x41_uint8.raw.gz"
    if not path.exists():
        pytest.skip(f"{path} not present (../shared/data is optional)")
    out = tmp_path / "acc"
    status = main(["bench", "accuracy", str(SHARED), "--only", "nucleon", *FAST,
                   "--max-size", "24", "--isovalues", "first", "--out", str(out)])
    capsys.readouterr()
    assert status == 0
    rows = json.loads((out / "accuracy.json").read_text())["rows"]
    assert [r["mode"] for r in rows] == ["render", "bake"]
    assert rows[0]["volume_notes"]["dims"] == [20, 20, 20]
    assert all(0 < r["rel_rmse"] < 1 and r["surface_pixels"] > 0 for r in rows)
