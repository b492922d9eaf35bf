"""``isolume bench scale``: the volumes it writes, what it measures, how it extrapolates."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from isolume import volumes
from isolume.app.bench.scale import (
    Run,
    exponent,
    measure,
    predicted,
    texels_of,
    write_synthetic,
    write_upsampled,
)
from isolume.app.cli import main


def test_the_synthetic_volume_is_the_engine_in_bytes(tmp_path):
    path = write_synthetic(40, tmp_path)
    engine = volumes.load("synthetic:engine:40")
    written = volumes.load(str(path))
    assert written.data.shape == engine.data.shape
    np.testing.assert_array_equal(written.data, np.rint(engine.data * 255))


def test_upsampling_keeps_the_scan_at_its_own_size_and_interpolates_between(tmp_path):
    z, y, x = np.mgrid[:9, :12, :16]
    source = tmp_path / "ramp.npy"
    np.save(source, (10 * x + 3 * y + z).astype(np.float32))
    same = volumes.load(str(write_upsampled(str(source), 16, tmp_path)))
    np.testing.assert_array_equal(same.data, volumes.load(str(source)).data)
    double = volumes.load(str(write_upsampled(str(source), 31, tmp_path)))
    assert double.data.shape == (17, 23, 31)
    # a linear ramp stays linear: every other sample is a source sample, those between
    # their mean (rounded to the byte)
    np.testing.assert_array_equal(double.data[::2, ::2, ::2], same.data)
    source_samples = same.data.astype(np.float32)  # bytes: their sum would wrap
    between = (source_samples[:, :, :-1] + source_samples[:, :, 1:]) / 2
    assert np.abs(double.data[::2, ::2, 1::2] - between).max() <= 0.5


def test_measure_sees_the_peak_memory_and_the_failure():
    grab = "import numpy, time; a = numpy.ones(300 * 2**20 // 8); time.sleep(0.5)"
    status, seconds, peak, _ = measure([sys.executable, "-c", grab], timeout=60)
    assert status == "ok" and seconds >= 0.5 and peak >= 300
    status, _, _, text = measure([sys.executable, "-c", "raise SystemExit('no')"], 60)
    assert status == "failed" and "no" in text
    status, seconds, _, _ = measure([sys.executable, "-c", "import time; time.sleep(30)"], 1)
    assert status == "timeout" and seconds < 10


def test_extrapolation_follows_the_last_two_sizes():
    runs = [Run("s", 64, "bake", 1000, seconds=2.0, peak_mb=100.0),
            Run("s", 128, "bake", 8000, seconds=16.0, peak_mb=200.0),
            Run("s", 128, "info", 8000, seconds=1.0, peak_mb=50.0)]
    memory, seconds = predicted(runs, "s", "bake", 64000)
    assert memory == pytest.approx(400.0) and seconds == pytest.approx(128.0)
    memory, seconds = predicted(runs, "s", "info", 64000)  # one run: proportional
    assert memory == pytest.approx(400.0) and seconds == pytest.approx(8.0)
    assert predicted(runs, "s", "view", 64000) == (None, None)
    assert exponent([1e3, 8e3, 64e3], [1.0, 2.0, 4.0]) == pytest.approx(1 / 3)
    assert exponent([5.0, 5.0], [1.0, 2.0]) is None


def test_texels_are_read_from_what_the_commands_print():
    render = ("global illumination: 8,192 of 114,580 texels, 64 paths each, 1.1 s\n"
              "global illumination: 114,580 texels × 64 paths in 2.5 s\n")
    assert texels_of("render", render) == 114580
    bake = "wrote l.npz: 6,676 of 10,880 texels active (61.4%), 2 levels"
    assert texels_of("bake", bake) == 6676
    assert texels_of("info", bake) is None


def test_a_small_sweep_writes_its_table_json_and_chart(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["bench", "scale", "--sizes", "16", "24", "--sources", "synthetic",
                 "--commands", "info", "bake", "--samples", "2", "--memory-cap", "0.0001",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    runs = json.loads((out / "scale.json").read_text())["runs"]
    assert [(r["size"], r["command"]) for r in runs] == [(16, "info"), (16, "bake"),
                                                         (24, "info"), (24, "bake")]
    # the first size runs; the cap of 0.1 MB then skips the second, saying why
    assert [r["status"] for r in runs] == ["ok", "ok", "skipped", "skipped"]
    assert runs[1]["texels"] > 0 and runs[0]["peak_mb"] > 10
    assert "needs about" in runs[2]["note"] and "needs about" in printed
    assert (out / "scale.png").stat().st_size > 1000 and (out / "table.txt").exists()
