"""Motion-guided tracking: predicted positions from a known camera motion
(:mod:`granite.optical_flow.prediction`) and the frontend's guided pass that starts from them."""

from __future__ import annotations

import numpy as np
import pytest

from granite.camera import make_camera
from granite.geometry import so3_exp
from granite.optical_flow import FrameToFrameOpticalFlow, OpticalFlowConfig
from granite.optical_flow.prediction import predict_positions, predict_positions_rotation
from granite.optical_flow.synthetic import apply_affine, similarity, textured_image, warp

H, W = 480, 640
CENTRE = (W / 2, H / 2)
FX, FY, CX, CY = 400.0, 410.0, 318.0, 242.0


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return textured_image(H, W, seed=3)


def _pinhole():
    return make_camera("pinhole", {"fx": FX, "fy": FY, "cx": CX, "cy": CY}, W, H)


def _by_hand(points_c: np.ndarray) -> np.ndarray:
    """Pinhole projection written out (independent of granite.camera)."""
    return np.column_stack([FX * points_c[:, 0] / points_c[:, 2] + CX,
                            FY * points_c[:, 1] / points_c[:, 2] + CY])


def test_points_with_depth_land_where_the_moved_point_projects():
    rng = np.random.default_rng(0)
    p_old = np.column_stack([rng.uniform(-4, 4, 50), rng.uniform(-3, 3, 50), rng.uniform(5, 20, 50)])
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.02, -0.05, 0.03]))
    T[:3, 3] = [0.3, -0.1, 0.4]
    uv, valid = predict_positions(_by_hand(p_old), _pinhole(), T, depths=p_old[:, 2])
    assert valid.all()
    np.testing.assert_allclose(uv, _by_hand(p_old @ T[:3, :3].T + T[:3, 3]), atol=1e-9)


def test_points_without_depth_follow_the_infinite_homography():
    rng = np.random.default_rng(1)
    uv_old = np.column_stack([rng.uniform(0, W, 40), rng.uniform(0, H, 40)])
    R = so3_exp(np.array([0.01, 0.08, -0.02]))
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
    h = (K @ R @ np.linalg.inv(K) @ np.column_stack([uv_old, np.ones(40)]).T).T
    expected = h[:, :2] / h[:, 2:]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [5.0, 1.0, -2.0]  # the translation must be ignored without depth
    depths = np.full(40, np.nan)
    depths[::3] = 0.0
    depths[1::3] = np.inf
    for uv, valid in (predict_positions(uv_old, _pinhole(), T, depths),
                      predict_positions_rotation(uv_old, _pinhole(), R)):
        assert valid.all()
        np.testing.assert_allclose(uv, expected, atol=1e-9)


def test_points_moving_behind_the_camera_are_invalid():
    T = np.eye(4)
    T[2, 3] = -10.0  # the new camera is 10 m in front of the old one
    uv, valid = predict_positions(np.array([[CX, CY], [CX + 10, CY]]), _pinhole(), T,
                                  depths=np.array([5.0, np.nan]))
    assert list(valid) == [False, True] and np.isnan(uv[0]).all()


def _guided_pair(img0, img1, config, prediction_of):
    """Track img0 -> img1 with predictions ``prediction_of(positions0)``; returns the common
    tracks' positions in both frames."""
    flow = FrameToFrameOpticalFlow(config)
    r0 = flow.process(0.0, img0)
    predicted = None if prediction_of is None else (r0.ids, prediction_of(r0.positions))
    r1 = flow.process(0.1, img1, predicted=predicted)
    _, i0, i1 = np.intersect1d(r0.ids, r1.ids, return_indices=True)
    return r0.positions[i0], r1.positions[i1], r0


def _in_view(points: np.ndarray, margin: float = 25) -> np.ndarray:
    return (points >= margin).all(axis=1) & (points[:, 0] < W - margin) & (points[:, 1] < H - margin)


def test_a_good_prediction_follows_motion_the_unguided_tracker_loses(texture):
    """One pyramid level cannot follow 55 px (see test_optical_flow); a prediction within a
    pixel or two of the truth can."""
    affine = similarity(45.5, -30.2, np.radians(3), 1.0, CENTRE)
    img1 = warp(texture, affine)
    single = OpticalFlowConfig(levels=1, retry_min_flow=0.0, global_retry_min_lost=0.0)
    rng = np.random.default_rng(2)
    noisy_truth = lambda p: apply_affine(affine, p) + rng.normal(0, 1.0, p.shape)  # noqa: E731
    p0_u, _, _ = _guided_pair(texture, img1, single, None)
    p0, p1, r0 = _guided_pair(texture, img1, single, noisy_truth)
    truth = apply_affine(affine, p0)
    err = np.linalg.norm(p1 - truth, axis=1)
    n_visible = _in_view(apply_affine(affine, r0.positions)).sum()
    assert len(p0_u) < 0.1 * n_visible < 0.9 * n_visible < len(p0)
    assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.98


def test_a_wrong_prediction_falls_back_to_the_unguided_passes(texture):
    affine = similarity(6.0, -4.0, np.radians(1), 1.0, CENTRE)
    img1 = warp(texture, affine)
    rng = np.random.default_rng(4)
    wrong = lambda p: p + rng.uniform(-40, 40, p.shape)  # noqa: E731
    p0_u, p1_u, _ = _guided_pair(texture, img1, None, None)
    p0, p1, _ = _guided_pair(texture, img1, None, wrong)
    err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    assert len(p0) >= 0.97 * len(p0_u)
    assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.98  # the ZNCC gate stops false matches


def test_no_usable_prediction_gives_the_unguided_result_bit_for_bit(texture):
    img1 = warp(texture, similarity(3.0, 2.0, 0.01, 1.0, CENTRE))
    results = []
    for predicted in (None, (np.zeros(0, dtype=np.int64), np.zeros((0, 2))),
                      (np.array([10**6]), np.array([[5.0, 5.0]])),  # an id that is not tracked
                      "nan"):
        flow = FrameToFrameOpticalFlow()
        r0 = flow.process(0.0, texture)
        if isinstance(predicted, str):
            predicted = (r0.ids, np.full((len(r0.ids), 2), np.nan))
        results.append(flow.process(0.1, img1, predicted=predicted))
    for r in results[1:]:
        np.testing.assert_array_equal(r.ids, results[0].ids)
        np.testing.assert_array_equal(r.positions, results[0].positions)


def test_malformed_prediction_is_a_clear_error(texture):
    flow = FrameToFrameOpticalFlow()
    r0 = flow.process(0.0, texture)
    with pytest.raises(ValueError, match="shape"):
        flow.process(0.1, texture, predicted=(r0.ids, np.zeros((len(r0.ids), 3))))
    with pytest.raises(ValueError, match="pair"):
        flow.process(0.2, texture, predicted=np.zeros(3))



def _fine_pass_only(img0, img1, displacement_guess, above=1):
    """The guided pass that starts ``above`` levels above the creation level, alone (kernel
    call, fixed forward-backward limit): the corners of img0 tracked into img1 from
    ``displacement_guess(positions)``. Returns (positions, new positions, status, levels)."""
    from granite.optical_flow.pyramid import build_pyramid
    from granite.optical_flow.tracking import PASS_GUESS_FINE, new_template_cache, track_points

    cfg = OpticalFlowConfig(fb_noise_factor=0.0, guided_levels_above=above)
    flow = FrameToFrameOpticalFlow(cfg)
    r0 = flow.process(0.0, img0)
    pyr_a = flow._pyramid
    pyr_b = build_pyramid(img1, cfg.levels, presmooth_sigma=cfg.presmooth_sigma)
    n, p = len(r0.ids), len(flow._pattern)
    out, _, status = track_points(
        pyr_a.data, pyr_a.offsets, pyr_a.widths, pyr_a.heights,
        pyr_b.data, pyr_b.offsets, pyr_b.widths, pyr_b.heights,
        r0.positions, r0.levels, np.full(n, -1), *new_template_cache(0, cfg.levels, p),
        *new_template_cache(n, cfg.levels, p), flow._pattern, cfg.margin, cfg.iterations,
        cfg.fb_threshold_sq, 0.0, guess=displacement_guess(r0.positions),
        order=np.array([PASS_GUESS_FINE]), min_zncc_guess=cfg.guess_min_zncc,
        guided_levels_above=cfg.guided_levels_above,
    )
    return r0.positions, out, status, r0.levels


def test_the_fine_guided_pass_needs_the_prediction_within_its_reach(texture):
    """Starting one level above the creation level is enough for a prediction within a few
    pixels and not for one 14 px off: that is what the whole-pyramid guided pass after it is
    for."""
    affine = similarity(30.0, -20.0, np.radians(2), 1.0, CENTRE)
    img1 = warp(texture, affine)
    rng = np.random.default_rng(5)
    close = lambda p: apply_affine(affine, p) - p + rng.normal(0, 1.0, p.shape)  # noqa: E731
    far = lambda p: apply_affine(affine, p) - p + np.array([14.0, -10.0])  # noqa: E731
    p0, p1, ok, _ = _fine_pass_only(texture, img1, close)
    inside = _in_view(apply_affine(affine, p0))
    err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    assert ok[inside].mean() > 0.9 and np.median(err[ok]) < 0.1 and np.mean(err[ok] < 1.0) > 0.98
    _, _, ok_far, _ = _fine_pass_only(texture, img1, far)
    assert ok_far[inside].mean() < 0.2


def test_the_creation_level_pass_keeps_only_tracks_within_half_a_pixel_of_their_prediction(texture):
    """From the creation level alone (``guided_levels_above = 0``) a track is kept only when
    its match lies within 0.5 px (creation-level pixels) of the prediction: predictions 0.3 px
    off pass, 1-2 px off do not (the pass from one level above takes those), and what passes
    is right."""
    affine = similarity(30.0, -20.0, np.radians(2), 1.0, CENTRE)
    img1 = warp(texture, affine)
    rng = np.random.default_rng(6)
    angle = rng.uniform(0, 2 * np.pi, 5000)
    ring = lambda r: np.column_stack([np.cos(angle), np.sin(angle)]) * r  # noqa: E731
    for radius, lo, hi in ((0.3, 0.9, 1.0), (1.5, 0.0, 0.02)):
        guess = lambda p: apply_affine(affine, p) - p + ring(radius)[:len(p)]  # noqa: E731
        p0, p1, ok, levels = _fine_pass_only(texture, img1, guess, above=0)
        level0 = _in_view(apply_affine(affine, p0)) & (levels == 0)  # the ring is in level-0 px
        err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
        assert lo <= ok[level0].mean() <= hi, (radius, ok[level0].mean())
        if ok.any():
            assert np.median(err[ok]) < 0.1 and np.mean(err[ok] < 1.0) > 0.98


@pytest.mark.parametrize("offset", [(0.0, 0.0), (14.0, -10.0)])
def test_the_frontend_tracks_from_a_prediction_near_or_far_as_the_whole_pyramid_does(texture, offset):
    """The default frontend (fine guided pass first, then the whole-pyramid guided pass, then
    the unguided ones) keeps as many correct tracks as guided tracking over the whole pyramid
    only (``guided_levels_above = -1``), whether the prediction is right or 17 px off. Four
    levels and no median retry: the unguided passes cannot follow the 55 px shift, so the
    tracks far from their prediction live only if the whole-pyramid guided pass follows."""
    affine = similarity(45.5, -30.2, np.radians(2), 1.0, CENTRE)
    img1 = warp(texture, affine)
    guess = lambda p: apply_affine(affine, p) + np.array(offset)  # noqa: E731
    kept = []
    for above in (1, 0, -1):
        cfg = OpticalFlowConfig(levels=4, retry_min_flow=0.0, guided_levels_above=above)
        p0, p1, r0 = _guided_pair(texture, img1, cfg, guess)
        err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
        assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.98
        kept.append(len(p0))
    n_visible = _in_view(apply_affine(affine, r0.positions)).sum()
    assert 0.85 * n_visible < kept[2] and min(kept[:2]) >= 0.97 * kept[2]


def test_tracking_from_the_creation_level_keeps_the_tracks_of_the_level_above(texture):
    """``guided_levels_above = 0`` (track from the prediction on the creation level only,
    then from one level above, then the whole pyramid) keeps the same tracks as 1 at the same
    positions, the ones near the image border included: a track whose patch would not fit the
    level above is rejected as the coarse-to-fine passes reject it. With a prediction 1 px
    off."""
    affine = similarity(-21.3, 12.8, np.radians(1.5), 1.0, CENTRE)
    img1 = warp(texture, affine)
    rng = np.random.default_rng(8)
    noise = rng.normal(0, 0.7, (5000, 2))
    guess = lambda p: apply_affine(affine, p) + noise[:len(p)]  # noqa: E731
    runs = {}
    for above in (1, 0):
        flow = FrameToFrameOpticalFlow(OpticalFlowConfig(guided_levels_above=above))
        r0 = flow.process(0.0, texture)
        r1 = flow.process(0.1, img1, predicted=(r0.ids, guess(r0.positions)))
        tracked = np.isin(r1.ids, r0.ids)  # not the corners detected in img1
        runs[above] = (r1.ids[tracked], r1.positions[tracked], r1.levels[tracked])
    ids1, ids0 = runs[1][0], runs[0][0]
    assert len(ids1) > 150
    common, i1, i0 = np.intersect1d(ids1, ids0, return_indices=True)
    assert len(common) >= 0.995 * max(len(ids1), len(ids0))
    gap = np.linalg.norm(runs[1][1][i1] - runs[0][1][i0], axis=1)
    assert np.quantile(gap, 0.99) < 0.02 and gap.max() < 0.2
    border = lambda p: np.minimum.reduce([p[:, 0], W - 1 - p[:, 0], p[:, 1], H - 1 - p[:, 1]])  # noqa: E731
    # level-0 tracks end as close to the border as the level-1 patch allows, in both modes
    for _, positions, levels in runs.values():
        assert border(positions[levels == 0]).min() > 3.9


def test_bearing_rotation_recovers_the_rotation_between_predicted_and_tracked_pixels():
    """The rotation that corrects a predicted camera orientation (``predict_before_estimate``):
    pixels of random points seen by a camera and by the same camera rotated by R_err; with a
    fifth of the pairs replaced by wrong matches it is still found."""
    from granite.estimator.motion_model import bearing_rotation
    from granite.geometry import so3_log

    rng = np.random.default_rng(7)
    cam = _pinhole()
    uv_pred = np.column_stack([rng.uniform(20, W - 20, 200), rng.uniform(20, H - 20, 200)])
    b_pred, _ = cam.unproject(uv_pred)
    R_err = so3_exp(np.array([0.01, -0.03, 0.02]))
    uv_tracked, valid = cam.project(b_pred @ R_err.T)
    assert valid.all()
    R = bearing_rotation(cam, uv_pred, uv_tracked)
    assert np.linalg.norm(so3_log(R @ R_err.T)) < 1e-9
    wrong = rng.choice(200, 40, replace=False)
    uv_tracked[wrong] += rng.uniform(-40, 40, (40, 2))
    R = bearing_rotation(cam, uv_pred, uv_tracked)
    assert np.degrees(np.linalg.norm(so3_log(R @ R_err.T))) < 0.05
    assert bearing_rotation(cam, uv_pred[:5], uv_tracked[:5]) is None  # too few pairs


def test_prediction_basis_puts_tracks_where_the_predicted_camera_sees_them():
    """A track of a landmark at depth z, basis at pose T_w_old: at a later time the prediction
    is the projection of the landmark into the constant-velocity pose (by hand), and a track
    without a landmark follows the infinite homography."""
    from granite.estimator.motion_model import ConstantVelocityModel, PredictionBasis

    model = ConstantVelocityModel(True, 5.0)
    T_step = np.eye(4)
    T_step[:3, :3], T_step[:3, 3] = so3_exp(np.array([0.0, 0.02, 0.0])), [0.2, 0.0, 0.1]
    model.update(np.eye(4), 0.0, measure_motion=False)
    model.update(T_step, 0.1, measure_motion=True)
    X_old = np.array([[1.0, -0.5, 8.0], [0.0, 0.0, 1.0]])  # in the camera at t = 0.1
    uv = _by_hand(X_old)
    basis = PredictionBasis(0.1, model.copy(), T_step.copy(), np.array([4, 9]), uv,
                            np.array([8.0, np.nan]))
    ids, uv_new = basis.predict(_pinhole(), 0.2)  # one more step of T_step
    assert list(ids) == [4, 9]
    X_new = X_old[:1] @ T_step[:3, :3] + (-T_step[:3, :3].T @ T_step[:3, 3])  # T_step^-1 X
    np.testing.assert_allclose(uv_new[0], _by_hand(X_new)[0], atol=1e-9)
    ray = X_old[1] @ T_step[:3, :3]  # rotation only
    np.testing.assert_allclose(uv_new[1], _by_hand(ray[None])[0], atol=1e-9)


def _ground_plane_view(rng, n):
    """Pixels and planar depths of ``n`` random points of a tilted ground plane (camera 10 m
    above it, looking 45 degrees down), and the points themselves in the camera frame."""
    uv = np.column_stack([rng.uniform(10, W - 10, n), rng.uniform(10, H - 10, n)])
    rays = np.column_stack([(uv[:, 0] - CX) / FX, (uv[:, 1] - CY) / FY, np.ones(n)])
    # plane n . X = 10 with the normal 45 degrees between the camera's y and z axes
    normal = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5)])
    z = 10.0 / (rays @ normal)
    return uv, z, rays * z[:, None]


def test_neighbour_depths_fill_tracks_without_landmark_from_the_surface_around_them():
    """Tracks without a landmark (NaN depth) on a ground plane get their neighbours' median
    depth: within 5 % of their true depth (median; 12 % at the 90th percentile), and their predicted positions under a forward step
    are then within a pixel of the truth where the infinite homography is 10+ px off;
    landmarks at infinity (inf) and known depths are kept."""
    from granite.estimator.motion_model import neighbour_depths

    rng = np.random.default_rng(11)
    uv, z, X = _ground_plane_view(rng, 400)
    depths = z.copy()
    unknown = rng.choice(400, 250, replace=False)  # most tracks have no landmark
    depths[unknown] = np.nan
    depths[unknown[:5]] = np.inf  # landmarks at infinity stay there
    filled = neighbour_depths(uv, depths, 8)
    fill = unknown[5:]
    rel = np.abs(filled[fill] / z[fill] - 1.0)
    assert np.median(rel) < 0.05 and np.quantile(rel, 0.9) < 0.12
    known = np.setdiff1d(np.arange(400), fill)
    np.testing.assert_array_equal(filled[known], depths[known])
    assert np.isnan(depths[fill]).all()  # the input is not modified

    T = np.eye(4)
    T[:3, 3] = [0.0, -0.3, -1.0]  # 1 m forward, 0.3 m down (T_new_old: points move to -z)
    truth = _by_hand(X[fill] + T[:3, 3])
    with_fill, ok = predict_positions(uv[fill], _pinhole(), T, filled[fill])
    without, ok2 = predict_positions(uv[fill], _pinhole(), T, depths[fill])
    assert ok.all() and ok2.all()
    err_fill = np.linalg.norm(with_fill - truth, axis=1)
    err_inf = np.linalg.norm(without - truth, axis=1)
    assert np.median(err_fill) < 1.0 and np.median(err_inf) > 10.0


def test_neighbour_depths_need_three_known_depths():
    from granite.estimator.motion_model import neighbour_depths

    uv = np.array([[10.0, 10.0], [20.0, 10.0], [30.0, 10.0], [40.0, 10.0]])
    few = np.array([5.0, 6.0, np.nan, np.nan])
    assert neighbour_depths(uv, few, 8) is few
    three = np.array([5.0, 6.0, 7.0, np.nan])
    np.testing.assert_array_equal(neighbour_depths(uv, three, 8), [5.0, 6.0, 7.0, 6.0])
    np.testing.assert_array_equal(neighbour_depths(uv, three, 1), [5.0, 6.0, 7.0, 7.0])
    # a point at a non-finite pixel neither gives nor gets a depth
    uv_nan = np.vstack([uv, [[np.nan, 10.0], [35.0, 10.0]]])
    d_nan = np.array([5.0, 6.0, 7.0, np.nan, 100.0, np.nan])
    np.testing.assert_array_equal(neighbour_depths(uv_nan, d_nan, 1)[[3, 5]], [7.0, 7.0])
    assert np.isnan(neighbour_depths(uv_nan[[4, 0, 1, 2]], np.array([np.nan, 5.0, 6.0, 7.0]), 2)[0])


def test_neighbour_depths_are_the_median_of_the_exact_nearest_neighbours():
    """The grid search against brute force (all pairwise distances, numpy), on random point
    sets in and around a 640x480 image, k from 1 to more than the known points."""
    from granite.estimator.motion_model import neighbour_depths

    rng = np.random.default_rng(5)
    for trial in range(40):
        n = int(rng.integers(4, 600))
        uv = rng.uniform(-30, 680, (n, 2))
        depths = rng.uniform(2.0, 50.0, n)
        depths[rng.random(n) < 0.6] = np.nan
        known = np.flatnonzero(np.isfinite(depths))
        unknown = np.flatnonzero(np.isnan(depths))
        if len(known) < 3 or len(unknown) == 0:
            continue
        k = int(rng.integers(1, 12))
        kk = min(k, len(known))
        dist = np.linalg.norm(uv[unknown][:, None, :] - uv[known][None, :, :], axis=2)
        nearest = np.argsort(dist, axis=1)[:, :kk]
        expected = np.median(depths[known][nearest], axis=1)
        np.testing.assert_allclose(neighbour_depths(uv, depths, k)[unknown], expected,
                                   rtol=0, atol=1e-12, err_msg=f"trial {trial}, k {k}")


def test_prediction_correction_recovers_the_homography_of_the_prediction_error():
    """Probes whose predictions are off by one homography (plus a quarter of wrong matches):
    the correction is that homography, and it maps every prediction to the truth."""
    from granite.optical_flow.probe import corrected_guess, prediction_correction, probe_indices

    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(0, W, 400), rng.uniform(0, H, 400)])
    truth_shift = rng.normal(0, 3.0, (400, 2))  # the true motion of each track
    H_err = np.array([[0.995, -0.03, 14.0], [0.028, 1.004, -9.0], [1e-5, -2e-5, 1.0]])
    truth = points + truth_shift
    # predictions off by the inverse of H_err: H_err maps each prediction to the truth
    h = np.c_[truth, np.ones(400)] @ np.linalg.inv(H_err).T
    guess = h[:, :2] / h[:, 2:] - points
    guess[::7] = np.nan  # tracks without a prediction
    idx = probe_indices(guess, 32)
    assert len(idx) == 32 and np.isfinite(guess[idx]).all() and np.all(np.diff(idx) > 0)
    assert idx[0] == np.flatnonzero(np.isfinite(guess[:, 0]))[0]
    tracked = truth[idx].copy()
    tracked[::4] += rng.uniform(-30, 30, (8, 2))  # wrong matches
    H_fit = prediction_correction(points[idx] + guess[idx], tracked)
    np.testing.assert_allclose(H_fit / H_fit[2, 2], H_err, rtol=1e-4, atol=1e-7)
    fixed = corrected_guess(points, guess, H_fit)
    has = np.isfinite(guess[:, 0])
    np.testing.assert_allclose((points + fixed)[has], truth[has], atol=1e-3)
    assert np.isnan(fixed[~has]).all()
    # too few probes, or too few agreeing: no correction
    assert prediction_correction(points[idx[:7]] + guess[idx[:7]], truth[idx[:7]]) is None
    scattered = truth[idx] + rng.uniform(-40, 40, (32, 2))
    scattered[:10] = truth[idx[:10]]
    assert prediction_correction(points[idx] + guess[idx], scattered) is None
    assert len(probe_indices(guess, 0)) == 0 and len(probe_indices(guess[:5], 32)) == 0


@pytest.mark.parametrize("above", [1, 0])
def test_probes_correct_predictions_that_are_all_off_by_the_same_image_motion(texture, above):
    """Predictions 18 px and 2 degrees off (a wrong camera rotation moves every prediction by
    about the same image transformation): with probe tracking the frontend keeps the same
    tracks at the same positions as without, and starts the other tracks from corrected
    predictions (within half a pixel of the truth)."""
    from granite.optical_flow.frame_to_frame import _probe

    affine = similarity(21.0, 9.0, np.radians(1.0), 1.0, CENTRE)
    off = similarity(-15.0, 10.0, np.radians(2.0), 1.0, CENTRE)
    img1 = warp(texture, affine)
    guess_of = lambda p: apply_affine(off, apply_affine(affine, p))  # noqa: E731
    results = {}
    for probes in (0, 32):
        cfg = OpticalFlowConfig(probe_points=probes, guided_levels_above=above)
        p0, p1, r0 = _guided_pair(texture, img1, cfg, guess_of)
        err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
        assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.98
        results[probes] = dict(zip(map(tuple, p0), p1))
    common = set(results[0]) & set(results[32])
    assert len(common) >= 0.99 * max(len(results[0]), len(results[32]))
    gap = [np.linalg.norm(results[0][k] - results[32][k]) for k in common]
    assert np.quantile(gap, 0.99) < 0.05
    # the corrected predictions themselves
    cfg = OpticalFlowConfig(guided_levels_above=above)
    flow = FrameToFrameOpticalFlow(cfg)
    r0 = flow.process(0.0, texture)
    from granite.optical_flow.pyramid import build_pyramid
    from granite.optical_flow.tracking import new_template_cache, pass_order
    pyr_a, pyr_b = flow._pyramid, build_pyramid(img1, cfg.levels, presmooth_sigma=cfg.presmooth_sigma)
    n, p = len(r0.ids), len(flow._pattern)
    guess = guess_of(r0.positions) - r0.positions
    images = (pyr_a.data, pyr_a.offsets, pyr_a.widths, pyr_a.heights,
              pyr_b.data, pyr_b.offsets, pyr_b.widths, pyr_b.heights)
    tail = (flow._pattern, cfg.margin, cfg.iterations, cfg.fb_threshold_sq, cfg.retry_min_flow)
    cache_b = new_template_cache(n, cfg.levels, p)
    fixed, (done, done_points, _), confirmed = _probe(
        images, r0.positions, r0.levels, np.full(n, -1), new_template_cache(0, cfg.levels, p), cache_b,
        tail, guess, pass_order(True, 0, True, above == 0), 32, dict(min_zncc_guess=cfg.guess_min_zncc))
    truth = apply_affine(affine, r0.positions)
    inside = _in_view(truth)
    assert np.median(np.linalg.norm(guess[inside] + r0.positions[inside] - truth[inside], axis=1)) > 15
    assert np.quantile(np.linalg.norm(fixed[inside] + r0.positions[inside] - truth[inside], axis=1), 0.9) < 0.5
    assert 24 <= done.sum() <= 32 and (cache_b[0][done] >= 0).any(axis=1).all()
    np.testing.assert_allclose(done_points[done], truth[done], atol=0.5)
    assert confirmed


def _probed_pair(config, wrong_every=10, outside_every=0):
    """A 6 px, 1 degree image motion tracked with predictions 0.3 px off, except every
    ``wrong_every``-th track's, which is 70 px off in a random direction, and every
    ``outside_every``-th track's (0: none), which is predicted 40 px beyond the nearest image
    border (as if it had left the view): the probes confirm the predictions unless most are
    wrong. Returns (masks of the wrong and the outside predictions, frame 0 and frame 1
    results, the image motion)."""
    texture = textured_image(H, W, seed=3)
    affine = similarity(6.0, -4.0, np.radians(1), 1.0, CENTRE)
    flow = FrameToFrameOpticalFlow(config)
    r0 = flow.process(0.0, texture)
    rng = np.random.default_rng(5)
    predicted = apply_affine(affine, r0.positions) + rng.normal(0, 0.3, r0.positions.shape)
    index = np.arange(len(r0.ids))
    wrong = index % wrong_every == 3 % wrong_every
    angle = rng.uniform(0, 2 * np.pi, wrong.sum())
    predicted[wrong] += 70 * np.c_[np.cos(angle), np.sin(angle)]
    outside = (index % outside_every == 4 % outside_every) & ~wrong if outside_every else np.zeros_like(wrong)
    x, y = r0.positions[outside].T
    gaps = np.c_[x, W - 1 - x, y, H - 1 - y]  # distances to the left, right, top, bottom border
    beyond = np.c_[-40.0 + 0 * x, W + 39.0 + 0 * x, -40.0 + 0 * y, H + 39.0 + 0 * y]
    nearest = gaps.argmin(axis=1)
    moved = predicted[outside]
    moved[nearest < 2, 0] = beyond[nearest < 2, nearest[nearest < 2]]
    moved[nearest >= 2, 1] = beyond[nearest >= 2, nearest[nearest >= 2]]
    predicted[outside] = moved
    r1 = flow.process(0.1, warp(texture, affine), predicted=(r0.ids, predicted))
    return wrong, outside, r0, r1, affine


def test_predicted_out_of_view_is_outside_the_pixel_centres():
    from granite.optical_flow.frame_to_frame import predicted_out_of_view

    p = np.array([[0.0, 0.0], [639.0, 479.0], [-0.01, 5.0], [5.0, 479.01], [639.5, 3.0], [np.nan, np.nan]])
    np.testing.assert_array_equal(predicted_out_of_view(p, 640, 480), [False, False, True, True, True, False])


def test_confirmed_predictions_out_of_view_are_not_retried_blindly():
    """When the probes confirm the predictions, a lost track predicted outside the image is not
    tracked again from zero motion or the median flow (``retry_out_of_view = false``, the
    default): here the predictions lie, the tracks are in view, and ``true`` finds them all. Lost
    tracks predicted inside the image are retried either way, and the other tracks are the same
    bit for bit."""
    runs = {retry: _probed_pair(OpticalFlowConfig(retry_out_of_view=retry), outside_every=10)
            for retry in (False, True)}
    wrong, outside, r0, _, affine = runs[False]
    kept = {retry: np.isin(r0.ids, r1.ids) for retry, (_, _, _, r1, _) in runs.items()}
    assert wrong.sum() >= 15 and outside.sum() >= 15
    assert kept[False][outside].mean() < 0.5  # only the guided pass from the coarsest level finds some
    assert kept[True][outside].mean() >= 0.95
    assert kept[False][wrong].mean() >= 0.95 and kept[True][wrong].mean() >= 0.95
    assert kept[False][~outside].mean() >= 0.98
    r1_off, r1_on = runs[False][3], runs[True][3]
    same = np.intersect1d(r0.ids[~outside], r1_off.ids)
    np.testing.assert_array_equal(r1_off.positions[np.isin(r1_off.ids, same)],
                                  r1_on.positions[np.isin(r1_on.ids, same)])
    # what the retries found is where the image moved
    for r1 in (r1_off, r1_on):
        found = np.isin(r1.ids, r0.ids[wrong | outside])
        start = r0.positions[np.searchsorted(r0.ids, r1.ids[found])]
        err = np.linalg.norm(r1.positions[found] - apply_affine(affine, start), axis=1)
        assert np.median(err) < 0.1 and err.max() < 1.0


def test_a_fallback_mask_of_the_wrong_length_is_a_clear_error(texture):
    from granite.optical_flow.patterns import make_pattern
    from granite.optical_flow.pyramid import build_pyramid
    from granite.optical_flow.tracking import new_template_cache, track_points

    pyr = build_pyramid(texture, 3)
    points, levels = np.array([[100.0, 100.0], [200.0, 150.0]]), np.zeros(2, dtype=np.int64)
    images = (pyr.data, pyr.offsets, pyr.widths, pyr.heights) * 2
    with pytest.raises(ValueError, match="fallback must have shape"):
        track_points(*images, points, levels, np.full(2, -1), *new_template_cache(0, 3, 121),
                     *new_template_cache(2, 3, 121), make_pattern("grid11"), 2.0, 6, 0.03, 2.0,
                     fallback=np.ones(3, dtype=bool))


def test_unconfirmed_predictions_retry_every_lost_track():
    """Predictions that the probes do not confirm (here each is 70 px off in a random
    direction or 40 px beyond the image border) leave every retry on: the tracks are those of
    ``retry_out_of_view = true``, bit for bit, and the zero-motion pass finds them."""
    runs = [_probed_pair(OpticalFlowConfig(retry_out_of_view=retry), wrong_every=2, outside_every=2)
            for retry in (False, True)]
    (wrong, outside, r0, a, _), (_, _, _, b, _) = runs
    assert (wrong | outside).all() and outside.sum() >= 50
    assert np.isin(r0.ids, a.ids).mean() >= 0.95
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.positions, b.positions)
