"""benchmarks/bench_paired.py: paired speed comparison of two VO variants."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from granite.estimator.pipeline import VoPipeline
from granite.estimator.vo import MonocularVO
from granite.io import open_dataset
from _benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
ASSET = ROOT / "assets" / "sequences" / "default"


@pytest.mark.parametrize("extra, message", [
    (["--rounds", "0"], "--rounds must be at least 1"),
    (["--frames", "10"], "more than the 30 warm-up frames"),
    (["--tree-b", "/"], "no granite package there"),
])
def test_bad_arguments_are_one_line_errors_with_status_2(extra, message, capsys):
    assert load_benchmark("bench_paired").main([str(ASSET), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err


def test_a_missing_dataset_and_an_invalid_config_are_errors(tmp_path, capsys):
    bench = load_benchmark("bench_paired")
    assert bench.main([str(tmp_path / "nothing")]) == 2
    assert "not found" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[backend]\nmax_iterations = -3\n")
    assert bench.main([str(ASSET), "--config-b", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --config-b") and "max_iterations" in err


def test_summary_medians_and_ratios():
    """The summary's figures, against a computation by hand on made-up runs."""
    runs = [{"a": {"wall_ms": a, "cpu_ms": 2 * a, "checksum": "x"},
             "b": {"wall_ms": b, "cpu_ms": 2 * b + 1, "checksum": "y"}}
            for a, b in [(10.0, 9.0), (20.0, 22.0), (12.0, 6.0)]]
    s = load_benchmark("bench_paired").summarise(runs)
    assert s["wall_ratio_median"] == pytest.approx(0.9)  # ratios 0.9, 1.1, 0.5
    assert s["cpu_ratio_median"] == pytest.approx(19.0 / 20.0)  # 19/20, 45/40, 13/24
    assert s["b_faster_rounds"] == 2
    assert s["a_wall_ms_median"] == 12.0 and s["b_wall_ms_median"] == 9.0
    assert s["a_checksums"] == ["x"] and s["b_checksums"] == ["y"]


@pytest.mark.slow
def test_one_round_runs_both_sides_with_their_own_configuration(tmp_path):
    """Side A is the defaults, side B a configuration that changes the trajectory: each side's
    checksum is that of a direct run of the VO with its configuration."""
    cfg = tmp_path / "b.toml"
    cfg.write_text("[optical_flow]\ngrid_size = 50\n")
    out = tmp_path / "paired.json"
    frames = 45
    assert load_benchmark("bench_paired").main(
        [str(ASSET), "--rounds", "1", "--frames", str(frames), "--config-b", str(cfg), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    dataset = open_dataset(ASSET)
    loaded = list(dataset.frames(0, frames))
    for side, config in (("a", VoConfig()), ("b", VoConfig.load(cfg))):
        vo = MonocularVO(dataset.calibration.camera(), config)
        poses = [o.T_w_c for _, o in VoPipeline(vo, concurrent=False).run(loaded)]
        assert run[side]["checksum"] == float(np.sum(np.abs(np.array(poses)))).hex()
        assert run[side]["frames"] == frames and run[side]["wall_ms"] > 0 and run[side]["cpu_ms"] > 0
        assert Path(run[side]["granite"]) == ROOT / "granite"
    assert run["a"]["checksum"] != run["b"]["checksum"]
    assert result["summary"]["wall_ratio_median"] == pytest.approx(run["b"]["wall_ms"] / run["a"]["wall_ms"])
