"""benchmarks/bench_scale_drift.py --cost keeps timing the indicator the VO computes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
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


def test_lambda_steps_against_a_frame_by_frame_count():
    """lambda_steps on a synthetic series (flat stretches with round-off wiggle, a spike on each
    keyframe frame, NaN gaps) agrees with a plain loop over the frames."""
    rng = np.random.default_rng(3)
    n = 400
    keyframe = np.zeros(n, dtype=bool)
    keyframe[[20, 75, 76, 150, 230, 231, 232, 330, 399]] = True
    lam = np.empty(n)
    level = 0.01
    for k in range(n):
        if keyframe[k]:
            level *= 1.0 + rng.uniform(0.0, 0.05)
            lam[k] = level * (1.0 + rng.uniform(0.02, 0.1))  # the keyframe frame's spike
        else:
            lam[k] = level * (1.0 + rng.normal(0.0, 3e-5))
    lam[[0, 1, 2, 100, 101, 231]] = np.nan

    steps = _bench_module().lambda_steps(lam, keyframe)

    pairs = still = 0
    at_kf, after_kf = [], []
    for k in range(1, n):
        a, b = lam[k - 1], lam[k]
        if not (math.isfinite(a) and math.isfinite(b)):
            continue
        pairs += 1
        still += abs(b / a - 1.0) < 1e-4
        if keyframe[k]:
            at_kf.append(b / a - 1.0)
            if k + 1 < n and math.isfinite(lam[k + 1]):
                after_kf.append(lam[k + 1] / a - 1.0)
    assert steps["still_share"] == pytest.approx(still / pairs, abs=1e-12)
    assert 0.3 < steps["still_share"] < 1.0  # the wiggle straddles the threshold
    assert steps["keyframe_events"] == len(at_kf) == 7  # of 9: 231 is NaN, 232 follows it
    assert steps["keyframe_change_median"] == pytest.approx(float(np.median(at_kf)), abs=1e-12)
    assert steps["after_keyframe_change_median"] == pytest.approx(float(np.median(after_kf)), abs=1e-12)
    none = _bench_module().lambda_steps(np.full(5, np.nan), np.ones(5, dtype=bool))
    assert none == {"still_share": None, "keyframe_events": 0, "keyframe_change_median": None,
                    "after_keyframe_change_median": None}
