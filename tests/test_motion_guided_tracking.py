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
    single = OpticalFlowConfig(levels=1, retry_min_flow=0.0)
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
