"""Re-anchoring a lost scale (``[backend] reanchor_lost_scale``): the prior's scale information."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend.marginalization import UNANCHORED_SCALE_REL, prior_scale_information
from granite.backend.priors import MargPrior


def _bearing_only_prior(t, gauge=1e8, distance=None):
    """Information of pairwise direction measurements between frames at positions ``t``
    (scale-free: the displacement across each direction), unit rotation information, a gauge
    prior on frame 0, and optionally one distance measurement ``(i, j, weight)``."""
    n = len(t)
    rows = []
    for i in range(n):
        for j in range(i + 1, n):
            d = (t[j] - t[i]) / np.linalg.norm(t[j] - t[i])
            P = np.eye(3) - np.outer(d, d)
            J = np.zeros((3, 6 * n))
            J[:, 6 * j:6 * j + 3] = P
            J[:, 6 * i:6 * i + 3] = -P
            rows.append(J)
    for i in range(n):
        J = np.zeros((3, 6 * n))
        J[:, 6 * i + 3:6 * i + 6] = np.eye(3)
        rows.append(J)
    J = np.vstack(rows)
    H = J.T @ J
    H[:6, :6] += gauge * np.eye(6)
    if distance is not None:
        i, j, w = distance
        d = (t[j] - t[i]) / np.linalg.norm(t[j] - t[i])
        row = np.zeros(6 * n)
        row[6 * j:6 * j + 3] = d
        row[6 * i:6 * i + 3] = -d
        H += w * np.outer(row, row)
    poses = {}
    for k in range(n):
        T = np.eye(4)
        T[:3, 3] = t[k]
        poses[k] = T
    return MargPrior(list(range(n)), H, np.zeros(6 * n), poses)


@pytest.mark.parametrize("offset", [0.0, 50.0])
def test_scale_free_prior_has_no_scale_information_despite_its_gauge(offset):
    t = np.random.default_rng(4).normal(size=(5, 3)) * 3.0 + offset
    free = prior_scale_information(_bearing_only_prior(t))
    assert free <= 1e-14  # the rigid motions (gauge 1e8) are projected out
    anchored = prior_scale_information(_bearing_only_prior(t, distance=(1, 3, 100.0)))
    assert anchored > 100 * UNANCHORED_SCALE_REL  # weight 100 against the gauge 1e8
    assert free <= UNANCHORED_SCALE_REL


def test_fewer_than_two_frames_hold_no_scale():
    T = np.eye(4)
    assert prior_scale_information(MargPrior.gauge(3, T, 1e8)) == 0.0
    assert prior_scale_information(MargPrior.empty()) == 0.0


def test_window_that_lost_its_scale_is_anchored_again_only_with_the_option():
    """A window without scale fix loses nothing it had when a keyframe leaves (its scale was
    free already): the prior has no scale information, so with ``reanchor_lost_scale`` a scale
    fix holds the current distance of the two oldest keyframes and the window has no null
    space left; without the option the scale stays free. A prior that carries the scale (the
    scale fix marginalised into it) is left alone."""
    from granite.backend import BackendConfig
    from granite.backend.synthetic import build_window, make_scene

    for option in (False, True):
        for with_scale in (False, True):
            scene = make_scene(sigma=0.5, seed=6, num_frames=6, num_points=150)
            win = build_window(scene, BackendConfig(huber_threshold=1e6, reanchor_lost_scale=option),
                               pose_noise=(0.01, 0.005), inv_dist_noise=0.1, seed=7)
            f = scene.frame_ids
            if with_scale:
                length = float(np.linalg.norm(scene.pose_of(f[0])[:3, 3] - scene.pose_of(f[1])[:3, 3]))
                win.set_scale_fix(f[0], f[1], length)
            win.optimize(max_iterations=3)
            win.marginalize([f[0]])
            H = win.hessian_blocks().H
            d = np.sqrt(np.diag(H))
            ev = np.linalg.eigvalsh(H / d[:, None] / d[None, :])
            null = int(np.sum(ev < 1e-9 * ev.max()))
            reanchored = option and not with_scale
            if reanchored:
                sf = win.scale_fix
                kfs = win.keyframe_ids
                assert sf is not None and (sf.frame_i, sf.frame_j) == (kfs[0], kfs[1])
                assert sf.length == pytest.approx(float(np.linalg.norm(
                    win.pose(kfs[0])[:3, 3] - win.pose(kfs[1])[:3, 3])))
                assert prior_scale_information(win.prior) <= UNANCHORED_SCALE_REL
            else:
                assert win.scale_fix is None
            assert null == (1 if not with_scale and not option else 0)
