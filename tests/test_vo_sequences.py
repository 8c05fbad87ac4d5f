"""The VO on the committed pre-rendered Mars sequences, against their exact ground truth."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from granite.estimator.runner import run_vo
from granite.evaluation import evaluate
from granite.io import open_dataset

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"

pytestmark = pytest.mark.slow  # whole VO runs


@functools.lru_cache(maxsize=None)  # one VO run per asset for all tests of this module
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


@pytest.mark.parametrize("name", ["aggressive", "framedrop"])
def test_fast_turns_and_frame_drops_are_tracked_without_restart(name):
    """Sharp low-altitude turns and bursts of
    missing frames: motion-guided tracking keeps the tracks, so no restart is needed."""
    _, ev = _run(name)
    assert ev.restarts == 0
    assert ev.tracking_percentage == pytest.approx(100.0)
    assert ev.rpe.rmse < 0.25
    assert ev.ate.rmse / ev.path_length < 0.02


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_rotation_in_place_is_tracked_within_one_degree():
    from granite.geometry import interpolate_poses

    result, ev = _run("rotation")
    assert ev.restarts == 0
    assert ev.tracking_percentage == pytest.approx(100.0)
    dataset = open_dataset(SEQUENCES / "rotation")
    est = result.trajectory
    gt = interpolate_poses(dataset.ground_truth.timestamps, dataset.ground_truth.poses, est.timestamps)
    # The sweep: from the last frame before the ground truth starts turning to the end.
    turned = [_angle_deg(gt[0, :3, :3].T @ g[:3, :3]) for g in gt]
    start = next(i for i, a in enumerate(turned) if a > 0.5) - 1
    assert max(turned) > 90  # the asset really holds a large in-place turn
    errors = [
        _angle_deg((est.poses[start, :3, :3].T @ e[:3, :3]).T @ (gt[start, :3, :3].T @ g[:3, :3]))
        for e, g in zip(est.poses[start:], gt[start:])
    ]
    assert max(errors) < 1.0


@pytest.mark.parametrize("name", ["default", "spiral", "rotation", "framedrop", "aggressive"])
def test_map_initialises_within_a_second_of_parallax_and_never_restarts(name):
    """Issue 12: the map exists within 1 s of the first frame whose ground-truth camera
    centre is 5 cm from an earlier one (granite.evaluation.initialization), no restart."""
    from granite.evaluation.initialization import initialization_delay

    result, ev = _run(name)
    assert ev.restarts == 0
    dataset = open_dataset(SEQUENCES / name)
    delay = initialization_delay([d.timestamp for d in result.diagnostics],
                                 [d.state for d in result.diagnostics], dataset.ground_truth)
    assert delay.seconds is not None and delay.seconds <= 1.0


def _noisy_copy(name: str, out: Path, sigma: float) -> Path:
    """The asset with seeded Gaussian noise of ``sigma`` DN added to every image (depth maps
    left out: the VO does not read them)."""
    import shutil

    import cv2

    dst = out / name
    shutil.copytree(SEQUENCES / name, dst, ignore=shutil.ignore_patterns("depth0"))
    rng = np.random.default_rng(0)
    for f in sorted((dst / "mav0" / "cam0" / "data").glob("*.png")):
        image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(f), np.clip(np.rint(image + rng.normal(0.0, sigma, image.shape)), 0, 255).astype(np.uint8))
    return dst


def test_strong_image_noise_costs_no_restart(tmp_path):
    """Issue 12 (second round): with 8 DN of noise added to the sharp low turns of
    `aggressive`, the defaults (11x11 lattice, noise-scaled forward-backward limit) track it all
    without restart; the reference's 52-point diamond with the fixed limit loses the tracks
    and restarts (measured: 1 restart, 58 % tracked)."""
    import dataclasses

    dataset = open_dataset(_noisy_copy("aggressive", tmp_path, 8.0))
    result = run_vo(dataset, VoConfig(), progress=False)
    ev = evaluate(result.trajectory, dataset.ground_truth, delta=1.0)
    assert ev.restarts == 0 and ev.tracking_percentage == pytest.approx(100.0)
    assert ev.ate.rmse / ev.path_length < 0.03
    base = VoConfig()
    old = dataclasses.replace(base, optical_flow=dataclasses.replace(
        base.optical_flow, pattern="pattern52", fb_noise_factor=0.0))
    old_ev = evaluate(run_vo(dataset, old, progress=False).trajectory, dataset.ground_truth, delta=1.0)
    assert old_ev.restarts >= 1 or old_ev.tracking_percentage < 90.0
