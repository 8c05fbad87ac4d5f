"""benchmarks/bench_track_passes.py: the replays of the frontend's tracking passes inside the VO."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from granite.estimator.runner import run_vo
from granite.io import open_dataset
from _benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
ASSET = ROOT / "assets" / "sequences" / "aggressive"


def _bench_module():
    return load_benchmark("bench_track_passes")


@pytest.fixture(scope="module")
def measured():
    return _bench_module().measure(ASSET, 5, None)


def test_each_pass_only_adds_tracks_and_the_vo_runs_unchanged(measured):
    """A later pass only tries the tracks the earlier ones lost, so the tracked sets of the
    growing pass prefixes are nested; the replays work on copies, so the VO's trajectory is
    that of a plain sequential run."""
    calls = measured["calls"]
    assert len(calls) >= 8
    for call in calls:
        tracked = [status for _, _, status in call["prefixes"]]
        assert len(tracked) == len(call["order"]) >= 3
        for before, after in zip(tracked, tracked[1:]):
            assert np.all(after[before])  # nothing tracked by a prefix is lost by a longer one
        assert tracked[0].sum() > 0.5 * len(tracked[0])
        # ground truth from the asset's depth maps: the first pass's tracks are where the image moved
        known = call["known"] & tracked[0]
        err = np.linalg.norm(call["prefixes"][0][1][known] - call["truth"][known], axis=1)
        assert known.sum() > 10 and np.median(err) < 0.5
    plain = run_vo(open_dataset(ASSET), VoConfig(), progress=False, concurrent=False)
    np.testing.assert_array_equal(measured["poses"], plain.trajectory.poses)


def test_out_of_view_counts_follow_the_predictions(measured):
    """The tracks counted as predicted outside the image are those whose prediction is."""
    n_out = 0
    for call in measured["calls"]:
        (w, h), p = call["size"], call["predicted"]
        with np.errstate(invalid="ignore"):
            inside = (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)
        np.testing.assert_array_equal(call["out_of_view"], ~inside & np.isfinite(p).all(axis=1))
        n_out += call["out_of_view"].sum()
    assert n_out > 0  # the fast flight carries tracks out of the view
    lines = _bench_module().report(measured)
    assert lines[0].startswith("aggressive: ") and any(line.startswith("| guided, creation level |")
                                                       for line in lines)
    assert any("predicted outside the image" in line for line in lines)


def test_bad_input_is_one_line_and_status_2(capsys):
    module = _bench_module()
    import sys
    argv = sys.argv
    try:
        sys.argv = ["bench_track_passes.py", str(ROOT / "no-such-dataset")]
        assert module.main() == 2
        sys.argv = ["bench_track_passes.py", str(ASSET), "--every", "0"]
        assert module.main() == 2
    finally:
        sys.argv = argv
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("error: ") for line in err)
