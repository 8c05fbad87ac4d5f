"""The VO on the committed pre-rendered Mars sequences, against their exact ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from granite.estimator.runner import run_vo
from granite.evaluation import evaluate
from granite.io import open_dataset

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"


def _run(name: str):
    dataset = open_dataset(SEQUENCES / name)
    result = run_vo(dataset, VoConfig(), progress=False)
    assert np.all(np.isfinite(result.trajectory.poses))
    return result, evaluate(result.trajectory, dataset.ground_truth, delta=1.0)


@pytest.mark.parametrize("name", ["default", "spiral"])
def test_smooth_flights_are_tracked_completely_and_accurately(name):
    result, ev = _run(name)
    assert ev.restarts == 0
    assert ev.tracking_percentage == pytest.approx(100.0)
    # RMS RPE over 1 s (Eq. 18-20, direction error of ~1-3 m motions) and Sim(3) ATE.
    assert ev.rpe.rmse < 0.15
    assert ev.ate.rmse / ev.path_length < 0.02
    initialised = next(i for i, d in enumerate(result.diagnostics) if d.state == "tracking")
    assert initialised < 20  # within one second of flight
