"""Map-initialisation candidates by rotation-compensated parallax, and the initialisation-delay
metric (synthetic geometry with known truth)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from granite.backend import BackendConfig, SlidingWindow
from granite.camera import make_camera
from granite.estimator.landmark_creation import LandmarkTriangulator
from granite.estimator.map_initialization import init_candidates, quantile_linear, rotation_compensated_parallax
from granite.estimator.tracks import FrameTracks, shared_tracks
from granite.evaluation.initialization import initialization_delay, parallax_available, parallax_baseline
from granite.trajectory import Trajectory


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _scene(rng, n=300):
    """Points 5-15 m in front of a camera at the origin looking along +z."""
    return np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(5, 15, n)])


def _true_parallax_deg(points_w, R_c_w, t_c_w):
    """Angle between the bearing of each point in camera k (= world) rotated into c and its
    bearing in c: the parallax with the exact rotation removed (independent of the code)."""
    b_k = _unit(points_w)
    p_c = points_w @ R_c_w.T + t_c_w
    b_c = _unit(p_c)
    return np.degrees(np.arccos(np.clip(np.sum((b_k @ R_c_w.T) * b_c, axis=1), -1, 1)))


def test_pure_rotation_has_no_parallax():
    rng = np.random.default_rng(1)
    pts = _scene(rng)
    R = Rotation.from_rotvec([0.05, -0.2, 0.1]).as_matrix()
    angles = rotation_compensated_parallax(_unit(pts), _unit(pts @ R.T))
    assert np.max(angles) < 1e-4  # degrees (arccos resolution)


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_parallax_matches_the_exact_rotation_removed(seed):
    """Mostly forward translation with a rotation: the estimate (rotation fitted on the
    bearings) is close to the parallax with the true rotation removed. In any direction it
    grows with the baseline and is at most the true one (a fitted rotation absorbs the part of
    a sideways translation that looks like a rotation)."""
    rng = np.random.default_rng(seed)
    pts = _scene(rng)
    R = Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix()
    for direction, close in (([0.2, 0.1, 1.0], True), ([0.6, 0.1, 1.0], False), ([1.0, 0, 0], False)):
        quantiles = []
        for baseline in (0.2, 0.5, 1.0):
            t = baseline * _unit(np.array(direction))
            C = -R @ t  # camera c at world position t, rotated by R: p_c = R (p - t)
            truth = np.quantile(_true_parallax_deg(pts, R, C), 0.75)
            est = np.quantile(rotation_compensated_parallax(_unit(pts), _unit(pts @ R.T + C)), 0.75)
            assert est <= truth * 1.02
            if close:
                assert est == pytest.approx(truth, rel=0.2)
            quantiles.append(est)
        assert quantiles[0] < quantiles[1] < quantiles[2]


def _parallax_numpy(bk, bc):
    """The numpy version the numba kernel replaced (independent arithmetic: BLAS products,
    numpy's quantile)."""
    use = np.ones(len(bk), dtype=bool)
    angles = np.zeros(len(bk))
    for _ in range(2):
        u, _, vt = np.linalg.svd(bc[use].T @ bk[use])
        R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        angles = np.degrees(np.arccos(np.clip(np.sum((bk @ R.T) * bc, axis=1), -1.0, 1.0)))
        use = angles <= np.quantile(angles, 0.75)
        if use.sum() < 3:
            break
    return angles


def test_parallax_kernel_agrees_with_the_numpy_computation():
    rng = np.random.default_rng(7)
    for n in (3, 4, 17, 250, 901):
        bk = _unit(rng.normal(size=(n, 3)))
        bc = _unit(bk + 0.03 * rng.normal(size=(n, 3)))
        np.testing.assert_allclose(rotation_compensated_parallax(bk, bc), _parallax_numpy(bk, bc),
                                   rtol=0, atol=1e-8)
    assert rotation_compensated_parallax(bk[:2], bc[:2]).shape == (0,)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 10, 101, 1000])
def test_quantile_is_numpys_to_the_bit(n):
    rng = np.random.default_rng(n)
    values = rng.normal(size=n)
    for q in (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0, *rng.uniform(size=5)):
        assert quantile_linear(values, q) == np.quantile(values, q)
    values[n // 2] = np.nan
    assert np.isnan(quantile_linear(values, 0.5))


def test_shared_tracks_against_a_set_intersection():
    rng = np.random.default_rng(3)
    for n_cur, n_ref in ((0, 5), (5, 0), (40, 60), (900, 900)):
        cur_ids = rng.choice(3000, n_cur, replace=False)
        ref_ids = rng.choice(3000, n_ref, replace=False)
        cur = FrameTracks(None, None, cur_ids, rng.normal(size=(n_cur, 2)), np.zeros(n_cur, np.int64))
        ref = FrameTracks(None, None, ref_ids, rng.normal(size=(n_ref, 2)), np.zeros(n_ref, np.int64))
        common, rows_cur, rows_ref = shared_tracks(cur, ref)
        expected = [int(i) for i in cur_ids if int(i) in set(ref_ids.tolist())]
        assert common.tolist() == expected
        assert cur.ids[rows_cur].tolist() == expected and ref.ids[rows_ref].tolist() == expected


def _pinhole():
    return make_camera("pinhole", {"fx": 400.0, "fy": 400.0, "cx": 319.5, "cy": 239.5}, 640, 480)


def test_candidates_are_ranked_by_parallax_and_need_shared_tracks():
    """Keyframes at increasing distance from the current frame: the ranking follows the
    independent parallax; a keyframe sharing too few tracks is not a candidate."""
    rng = np.random.default_rng(5)
    cam = _pinhole()
    pts = _scene(rng, 400)
    win = SlidingWindow(cam, BackendConfig())
    tri = LandmarkTriangulator(win, cam, 0.03)
    current_pos = np.array([1.2, 0.0, 0.3])
    R_cur = Rotation.from_rotvec([0.0, 0.08, 0.0]).as_matrix()
    positions = {0: np.array([0.0, 0, 0]), 1: np.array([0.9, 0, 0.2]), 2: np.array([0.5, 0, 0.1]),
                 3: np.array([0.2, 0, 0.0])}
    tracks = {}

    def observe(R_c_w, C, ids):
        p_c = pts[ids] @ R_c_w.T + C
        uv, ok = cam.project(p_c)
        ok &= p_c[:, 2] > 0
        return FrameTracks({int(i): u for i, u, o in zip(ids, uv, ok) if o}, {int(i): 0 for i in ids})

    truth = {}
    for kf, pos in positions.items():
        R_kf = Rotation.from_rotvec([0.0, 0.02 * kf, 0.01]).as_matrix()
        ids = np.arange(len(pts)) if kf != 3 else np.arange(10)  # kf 3 shares only 10 tracks
        tracks[kf] = observe(R_kf, -R_kf @ pos, ids)
        win.add_frame(kf, np.eye(4), is_keyframe=True)
        # independent: parallax of the shared points with the exact relative rotation removed
        R_rel = R_cur @ R_kf.T
        p_k = pts @ R_kf.T - R_kf @ pos
        p_c = pts @ R_cur.T - R_cur @ current_pos
        ang = np.degrees(np.arccos(np.clip(np.sum((_unit(p_k) @ R_rel.T) * _unit(p_c), axis=1), -1, 1)))
        truth[kf] = np.quantile(ang, 0.75)
    tracks[9] = observe(R_cur, -R_cur @ current_pos, np.arange(len(pts)))
    win.add_frame(9, np.eye(4), is_keyframe=False)
    cands = init_candidates(win, tri, tracks, 9, min_shared=20)
    assert [c.keyframe for c in cands] == sorted((0, 1, 2), key=lambda k: -truth[k])
    for c in cands:
        assert 0.2 * truth[c.keyframe] < c.parallax_deg <= 1.02 * truth[c.keyframe]


def test_initialization_delay_counts_from_the_parallax_onset():
    t = np.arange(40) * 0.05
    pos = np.zeros((40, 3))
    pos[10:, 0] = (t[10:] - t[10]) * 2.0  # still for 10 frames, then 2 m/s
    poses = np.repeat(np.eye(4)[None], 40, axis=0)
    poses[:, :3, 3] = pos
    gt = Trajectory(t, poses)
    states = ["init"] * 16 + ["tracking"] * 24
    states[3] = "skipped"
    d = initialization_delay(t, states, gt, min_baseline=0.1)
    # onset: the first frame 0.1 m from an earlier one, frame 11 (0.1 m after frame 10);
    # indices count processed frames (frame 3 skipped), so frames 10 and 15 -> 5 frames.
    assert d.onset_time == pytest.approx(t[11])
    assert d.tracking_time == pytest.approx(t[16])
    assert d.frames == 5 and d.seconds == pytest.approx(0.25)
    never = initialization_delay(t, ["init"] * 40, gt, min_baseline=0.1)
    assert never.frames is None and never.seconds is None
    assert parallax_baseline(10.0, 5.0) == pytest.approx(2 * 10.0 * np.tan(np.radians(2.5)))


def test_parallax_available_needs_the_eq8_baseline_at_each_frames_distance():
    """2 m/s at 20 Hz after 10 still frames; the scene is 10 m away from the first 20 frames
    and 1 m from the later ones: 5 deg needs 0.873 m from an early frame (0.1 m per frame ->
    9 frames of motion) unless a later, closer frame gives 0.087 m sooner."""
    t = np.arange(40) * 0.05
    pos = np.zeros((40, 3))
    pos[10:, 0] = (t[10:] - t[10]) * 2.0
    poses = np.repeat(np.eye(4)[None], 40, axis=0)
    poses[:, :3, 3] = pos
    gt = Trajectory(t, poses)
    far = np.full(40, 10.0)
    # independent count: first k with some j < k and |x_k - x_j| >= 2 rho tan(2.5 deg)
    need = 2 * 10.0 * np.tan(np.radians(2.5))
    expected = next(k for k in range(40) if np.max(np.abs(pos[k, 0] - pos[:k, 0]), initial=0) >= need)
    assert parallax_available(t, gt, far, 5.0) == expected == 19
    mixed = far.copy()
    mixed[15:] = 1.0  # frame 15 sees a close scene: frame 16 is 0.1 m >= 0.087 m from it
    assert parallax_available(t, gt, mixed, 5.0) == 16
    assert parallax_available(t, gt, np.full(40, np.nan), 5.0) is None
    with pytest.raises(ValueError):
        parallax_available(t, gt, far[:5], 5.0)


def test_candidates_without_parallax_are_not_tried(monkeypatch):
    """With the default ``init_candidate_min_parallax``, a frame that only turned against every
    keyframe costs no two-view attempt; a keyframe with a real baseline is still tried."""
    import granite.estimator.map_initialization as mi
    from granite.estimator.config import EstimatorConfig
    from granite.estimator.initialization import InitializationConfig

    rng = np.random.default_rng(7)
    cam = _pinhole()
    pts = _scene(rng, 300)
    win = SlidingWindow(cam, BackendConfig())
    tri = LandmarkTriangulator(win, cam, 0.03)

    def observe(R_c_w, C):
        p_c = pts @ R_c_w.T + C
        uv, ok = cam.project(p_c)
        ids = np.arange(len(pts))[ok & (p_c[:, 2] > 0)]
        return FrameTracks({int(i): uv[i] for i in ids}, {int(i): 0 for i in ids})

    tried = []
    real = mi.initialize_two_view
    monkeypatch.setattr(mi, "initialize_two_view", lambda *a: tried.append(1) or real(*a))
    est, cfg = EstimatorConfig(), InitializationConfig()
    tracks = {kf: observe(Rotation.from_rotvec([0.0, 0.03 * kf, 0.0]).as_matrix(), np.zeros(3))
              for kf in range(3)}
    for kf in range(3):
        win.add_frame(kf, np.eye(4), is_keyframe=True)
    R_cur = Rotation.from_rotvec([0.0, 0.12, 0.02]).as_matrix()
    tracks[9] = observe(R_cur, np.zeros(3))  # turned in place against every keyframe
    win.add_frame(9, np.eye(4))
    assert est.init_candidate_min_parallax > 0.0
    assert mi.find_map_initialization(win, tri, tracks, 9, cfg, est.init_max_candidates,
                                      est.init_candidate_min_parallax) is None
    assert tried == []
    # the same turn plus a 1.5 m sideways baseline to keyframe 0: tried (and accepted)
    tracks[9] = observe(R_cur, -R_cur @ np.array([1.5, 0.0, 0.0]))
    init = mi.find_map_initialization(win, tri, tracks, 9, cfg, est.init_max_candidates,
                                      est.init_candidate_min_parallax)
    assert len(tried) >= 1 and init is not None
