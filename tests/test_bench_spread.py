"""benchmarks/bench_spread.py: round-off-sized perturbations of the VO and their summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from _benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
ASSET = ROOT / "assets" / "sequences" / "default"


def _bench_module():
    return load_benchmark("bench_spread")


def test_steps_alternate_around_the_unperturbed_run():
    steps = _bench_module().perturbation_steps(6)
    assert steps == [0, 1, -1, 2, -2, 3]
    assert len(set(steps)) == len(steps)


def test_perturbed_config_changes_only_the_landmark_damping():
    bench = _bench_module()
    base = VoConfig()
    cfg = bench.perturbed_config(base, 0.01, -2)
    assert cfg.backend.landmark_damping == pytest.approx(base.backend.landmark_damping * 0.98)
    # every other key as in the base configuration
    assert cfg.to_toml().splitlines() != base.to_toml().splitlines()
    differing = [a for a, b in zip(cfg.to_toml().splitlines(), base.to_toml().splitlines())
                 if a != b]
    assert len(differing) == 1 and differing[0].startswith("landmark_damping")
    assert bench.perturbed_config(base, 0.01, 0) == base


def test_summary_counts_broken_runs_against_numpy_percentiles():
    rows = [{"ate_rmse": a, "rpe_rmse": r, "restarts": n}
            for a, r, n in [(0.1, 0.05, 0), (3.5, 3.2, 0), (0.2, 0.06, 1), (1.5, 0.1, 0)]]
    s = _bench_module().summarize(rows, fail_ate=1.0)
    assert s["ate_above"] == 2 and s["with_restarts"] == 1 and s["runs"] == 4
    np.testing.assert_allclose(s["ate_quartiles"], np.percentile([0.1, 3.5, 0.2, 1.5], [25, 50, 75]))
    np.testing.assert_allclose(s["rpe_quartiles"], np.percentile([0.05, 3.2, 0.06, 0.1], [25, 50, 75]))


def test_bad_input_is_one_line_and_status_2(tmp_path):
    for args in ([str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
                 [str(ASSET), "--out", str(tmp_path / "o"), "--runs", "0"],
                 [str(ASSET), "--out", str(tmp_path / "o"), "--config", str(tmp_path / "no.toml")]):
        proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_spread.py"), *args],
                              capture_output=True, text=True)
        assert proc.returncode == 2
        assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_first_run_is_the_plain_run_and_the_second_is_perturbed(tmp_path):
    """Run 1 (no perturbation) gives exactly the figures of a plain `granite run`; run 2 runs
    with its own configuration (damping x 1.01) and is evaluated too."""
    plain = tmp_path / "plain"
    subprocess.run([sys.executable, "-m", "granite.cli.main", "run", str(ASSET), "--out",
                    str(plain), "--quiet"], check=True, capture_output=True)
    expected = json.loads((plain / "evaluation.json").read_text())
    out = tmp_path / "spread"
    assert _bench_module().main([str(ASSET), "--out", str(out), "--runs", "2"]) == 0
    result = json.loads((out / "spread.json").read_text())["default"]
    first, second = result["runs"]
    assert first["ate_rmse"] == expected["ate_rmse"] and first["rpe_rmse"] == expected["rpe_rmse"]
    assert second["step"] == 1
    assert "landmark_damping = 1.01e-09" in (out / "default" / "+1.toml").read_text()
    assert np.isfinite(second["ate_rmse"]) and second["ate_rmse"] < 1.0
