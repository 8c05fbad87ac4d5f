"""Robustness of the frontend (issue 12, frontend part): level-0 track survival and accuracy
against ground-truth flow on the pre-rendered test-bench sequences, clean and with seeded
sensor-like noise added here; the local-flow retry and its neighbour search."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from granite.optical_flow import FrameToFrameOpticalFlow, OpticalFlowConfig
from granite.optical_flow.gt_flow import ground_truth_flow
from granite.optical_flow.noise import estimate_noise
from granite.optical_flow.synthetic import add_noise, apply_affine, similarity, textured_image, warp
from granite.optical_flow.local_flow import local_guesses

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"
#: The noisy versions: seeded Gaussian noise added to every frame so that the total noise is
#: NOISE_DN (``granite.optical_flow.noise.estimate_noise`` of the first frame, the renders' own
#: noise included; real KITTI frames measure 1.5-2 DN with it).
NOISE_DN = 3.0
#: The reference frontend (no pre-smoothing, no local-flow retry).
REFERENCE = dict(presmooth_sigma=0.0, local_retry_rounds=0, pattern="pattern52", fb_noise_factor=0.0)


def _sequences() -> list[Path]:
    if not SEQUENCES.is_dir():
        return []
    return sorted(p for p in SEQUENCES.iterdir()
                  if (p / "mav0" / "depth0" / "data").is_dir() and (p / "mav0" / "cam0" / "data.csv").is_file())


def run_sequence(root: Path, config: OpticalFlowConfig, noisy: bool = False):
    """Run the frontend (unguided, as ``granite track``) over a test-bench sequence. Returns
    (level-0 per-step survival: median over steps of the share of frame k's level-0 tracks
    still tracked in frame k+1; errors (px) of all tracks that survived a step against the
    depth-based ground-truth flow; per-step median share of level-0 tracks whose true next
    position stays at least 3 px inside the image)."""
    from granite.geometry import interpolate_poses
    from granite.io import open_dataset
    from simulation.depth import read_depth

    ds = open_dataset(root)
    camera = ds.calibration.camera()
    poses = interpolate_poses(ds.ground_truth.timestamps, ds.ground_truth.poses, ds.timestamps)
    flow = FrameToFrameOpticalFlow(config, image_size=(camera.width, camera.height))
    survival, in_view, errors, prev = [], [], [], None
    added = None
    for frame in ds.frames():
        image = frame.image
        if noisy:
            if added is None:
                added = np.sqrt(max(NOISE_DN**2 - estimate_noise(image, stride=1) ** 2, 0.0))
            image = add_noise(image, added, 0.0, (2021, frame.index))
        r = flow.process(frame.timestamp, image)
        if r.rejected:
            continue
        if prev is not None:
            i, a = prev
            lvl0 = a.levels == 0
            if lvl0.any():
                survival.append(np.isin(a.ids[lvl0], r.ids).mean())
            ns = int(ds.timestamps_ns[i])
            depth = read_depth(next(root.glob(f"mav0/depth0/data/{ns}.*")))
            uv_all, ok_all = ground_truth_flow(a.positions, depth, poses[i], poses[frame.index], camera)
            h, w = image.shape
            inside = ok_all & (uv_all >= 3).all(axis=1) & (uv_all[:, 0] <= w - 4) & (uv_all[:, 1] <= h - 4)
            if (lvl0 & ok_all).any():
                in_view.append(inside[lvl0 & ok_all].mean())
            _, ia, ib = np.intersect1d(a.ids, r.ids, return_indices=True)
            errors.append(np.linalg.norm(r.positions[ib] - uv_all[ia], axis=1)[ok_all[ia]])
        prev = (frame.index, r)
    return float(np.median(survival)), np.concatenate(errors), float(np.median(in_view))


#: Level-0 survival bound. `aggressive` (7 m/s at 3-8 m, banked turns) loses about one track
#: in ten per frame out of the image alone (its "in view" share), so it gets a bound relative
#: to that share instead: 0.18 below it (measured with the defaults, 0.5 px pre-smoothing and
#: no local-flow retry: 0.76 with the added noise, in view 0.93; the frontend before issue 12:
#: 0.65-0.76).
SURVIVAL = 0.95
AGGRESSIVE_MARGIN = 0.18
#: Ground-truth flow error bounds (issue 12): median and share beyond 2 px. On `aggressive`
#: with the added noise the median is 0.141 px on the first renders and 0.154 px on the
#: renders with the camera sensor model (0.137 px without the added noise): the per-frame
#: perspective change of its low, fast, banked flight is not an SE(2) warp. That case gets a
#: bound of 0.17 px.
MEDIAN_ERROR = 0.15
MEDIAN_ERROR_AGGRESSIVE_NOISY = 0.17
OUTLIERS = 0.01


@pytest.mark.parametrize("noisy", [False, True], ids=["clean", "noisy"])
@pytest.mark.parametrize(
    "root",
    _sequences() or [pytest.param(None, marks=pytest.mark.skip(reason="no pre-rendered sequence in assets/sequences"))],
    ids=lambda p: getattr(p, "name", "none"),
)
def test_level0_tracks_survive_and_agree_with_ground_truth(root, noisy):
    survival, errors, in_view = run_sequence(root, OpticalFlowConfig(), noisy)
    assert len(errors) > 1000
    if root.name == "aggressive":
        assert survival >= in_view - AGGRESSIVE_MARGIN, (survival, in_view)
    else:
        assert survival >= SURVIVAL, survival
    bound = MEDIAN_ERROR_AGGRESSIVE_NOISY if (root.name == "aggressive" and noisy) else MEDIAN_ERROR
    assert np.median(errors) <= bound, np.median(errors)
    assert np.mean(errors > 2.0) <= OUTLIERS, np.mean(errors > 2.0)


@pytest.mark.parametrize("noisy", [False, True], ids=["clean", "noisy"])
def test_reference_frontend_keeps_fewer_level0_tracks_in_fast_flight(noisy):
    """The same measurement separates the two frontends: with the reference's settings
    (no pre-smoothing, no median-flow retry) the fast `aggressive` flight loses more level-0
    tracks per frame, clean and noisy (measured with the defaults: 0.81 against 0.76 clean,
    0.76 against 0.72 noisy)."""
    root = SEQUENCES / "aggressive"
    if not root.is_dir():
        pytest.skip("no pre-rendered sequence aggressive")
    ours, _, _ = run_sequence(root, OpticalFlowConfig(), noisy)
    reference, _, _ = run_sequence(root, OpticalFlowConfig(**REFERENCE), noisy)
    assert ours >= reference + 0.03, (reference, ours)


# --------------------------------------------------------------------------- local-flow retry


def test_local_guesses_are_the_median_flow_of_the_nearest_tracked_points():
    rng = np.random.default_rng(4)
    n = 60
    points = rng.uniform(0, 300, (n, 2))
    flow = np.c_[0.05 * points[:, 1] + 3.0, -0.04 * points[:, 0]] + rng.normal(0, 0.3, (n, 2))
    out = points + flow
    status = rng.uniform(size=n) < 0.6
    status[[0, 1]] = False, True
    out[0] = points[0] + 0.2  # an untracked point's own result must not matter
    guess = np.empty((n, 2))
    assert local_guesses(points, out, status, 5, guess)
    tracked = np.flatnonzero(status)
    for k in range(n):
        if status[k]:
            assert np.isnan(guess[k]).all()
            continue
        d = np.linalg.norm(points[tracked] - points[k], axis=1)
        near = tracked[np.argsort(d, kind="stable")[:5]]
        expected = np.median(out[near] - points[near], axis=0)
        if np.linalg.norm(expected) < 1.0 or np.linalg.norm(points[k] + expected - out[k]) < 2.0:
            assert np.isnan(guess[k]).all()
        else:
            np.testing.assert_allclose(guess[k], expected, atol=1e-12)
    # fewer than 3 tracked points: nothing to try
    few = np.zeros(n, bool)
    few[:2] = True
    assert not local_guesses(points, out, few, 5, guess)


def test_local_retry_follows_a_large_rotation_the_median_retry_cannot():
    """A 9 deg roll about the image centre of a 320x240 image: flow up to ~30 px in every
    direction, so the median displacement is near zero; points near the border, whose coarse
    levels are unusable, need their neighbours' flow."""
    h, w = 240, 320
    texture = textured_image(h, w, seed=12)
    affine = similarity(0.0, 0.0, np.radians(9), 1.0, (w / 2, h / 2))
    img1 = warp(texture, affine)
    kept, errs = {}, {}
    for rounds in (0, 1):
        flow = FrameToFrameOpticalFlow(OpticalFlowConfig(local_retry_rounds=rounds))
        r0 = flow.process(0.0, texture)
        r1 = flow.process(0.1, img1)
        truth = apply_affine(affine, r0.positions)
        visible = (truth >= 10).all(axis=1) & (truth[:, 0] < w - 10) & (truth[:, 1] < h - 10)
        _, i0, i1 = np.intersect1d(r0.ids, r1.ids, return_indices=True)
        kept[rounds] = np.isin(r0.ids[visible], r1.ids).mean()
        errs[rounds] = np.linalg.norm(r1.positions[i1] - truth[i0], axis=1)
    assert kept[1] >= kept[0] + 0.05 and kept[1] > 0.9, kept
    assert np.median(errs[1]) < 0.1 and np.mean(errs[1] > 1.0) < 0.02
