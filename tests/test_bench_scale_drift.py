"""benchmarks/bench_scale_drift.py --cost keeps timing the indicator the VO computes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

import granite.estimator.vo as vo_module
from granite.backend.scale_drift import MIN_KEYFRAMES, scale_drift_task
from granite.estimator.config import VoConfig
from granite.estimator.runner import run_vo
from granite.io import open_dataset
from _benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
ASSET = ROOT / "assets" / "sequences" / "default"


def _bench_module():
    return load_benchmark("bench_scale_drift")


@pytest.mark.slow
def test_cost_times_every_frame_the_vo_computes_lambda_on():
    """One timing sample per frame whose window held at least 3 keyframes when the VO computed
    Λ (counted from a plain sequential run's diagnostics: Λ defined, or empty for a reason
    other than too few keyframes). It found none after the VO moved to ``scale_drift_task``."""
    result = run_vo(open_dataset(ASSET), VoConfig(), progress=False, concurrent=False)
    too_few = f"fewer than {MIN_KEYFRAMES} keyframes"
    expected = sum(1 for d in result.diagnostics
                   if d.scale_drift_indicator is not None
                   or d.scale_drift_reason not in ("", too_few))
    assert expected > 50  # the asset's window holds 3 keyframes for most of its 110 frames

    cost = _bench_module().cost(str(ASSET))

    assert cost["frames"] == expected
    assert cost["max_keyframes"] >= 3
    timings = [cost["cold_ms_mean"], cost["keyframe_system_ms_mean"], cost["chain_ms_mean"],
               *cost["total_ms"].values()]
    assert all(math.isfinite(t) and t > 0.0 for t in timings)
    assert vo_module.scale_drift_task is scale_drift_task  # the VO is left as it was
