"""Landmark creation for a keyframe's tracks and re-triangulation of points at infinity
(paper IV-B), checked against the points of a generated scene."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from granite.backend import SlidingWindow
from granite.camera import make_camera
from granite.estimator.landmark_creation import LandmarkTriangulator
from granite.estimator.tracks import FrameTracks


def _camera():
    return make_camera("pinhole", {"fx": 400.0, "fy": 400.0, "cx": 319.5, "cy": 239.5}, 640, 480)


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _scene(seed=0, n=60):
    """World points 4-12 m in front of the first camera and four camera poses ``T_w_c``:
    0 (host), 1 at 0.3 m, 2 at 0.01 m (below the triangulation baseline), 3 at 0.6 m."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 12, n)])
    poses = {0: _pose([0, 0, 0], [0, 0, 0]), 1: _pose([0.01, -0.02, 0.0], [0.3, 0.0, 0.05]),
             2: _pose([0.0, 0.01, 0.0], [0.01, 0.0, 0.0]), 3: _pose([-0.01, 0.03, 0.01], [0.6, 0.1, 0.0])}
    return pts, poses


def _tracks(camera, pts, T_w_c, ids):
    p_c = (pts[ids] - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    uv, ok = camera.project(p_c)
    assert ok.all()
    return FrameTracks({int(i): uv[k] for k, i in enumerate(ids)}, {int(i): 0 for i in ids})


def test_new_landmarks_get_the_inverse_distance_of_the_scene_point():
    camera = _camera()
    pts, poses = _scene()
    ids = np.arange(len(pts))
    win = SlidingWindow(camera)
    for f in (0, 1, 2):
        win.add_frame(f, poses[f], is_keyframe=f == 0)
    # frame 1 sees the even points, frame 2 (too short a baseline) all of them
    tracks = {0: _tracks(camera, pts, poses[0], ids), 1: _tracks(camera, pts, poses[1], ids[::2]),
              2: _tracks(camera, pts, poses[2], ids)}
    tri = LandmarkTriangulator(win, camera, min_triangulation_distance=0.03)
    assert tri.add_hosted_by(tracks, 0) == len(pts)
    inv = win.landmarks.inverse_distances(ids)
    truth = 1.0 / np.linalg.norm(pts, axis=1)  # host at the origin
    np.testing.assert_allclose(inv[::2], truth[::2], rtol=1e-9)
    assert np.all(inv[1::2] == 0.0)  # seen only with 0.01 m of baseline: at infinity
    assert tri.add_hosted_by(tracks, 0) == 0  # already landmarks
    # every frame that saw a point observes it
    for i in ids[:4].tolist():
        assert win.landmarks.has_observation(i, 2) and win.landmarks.has_observation(i, 1) == (i % 2 == 0)


def test_points_at_infinity_are_triangulated_once_a_frame_has_the_baseline():
    camera = _camera()
    pts, poses = _scene(seed=1)
    ids = np.arange(len(pts))
    win = SlidingWindow(camera)
    win.add_frame(0, poses[0], is_keyframe=True)
    tri = LandmarkTriangulator(win, camera, min_triangulation_distance=0.03)
    tri.add_hosted_by({0: _tracks(camera, pts, poses[0], ids)}, 0)
    assert np.all(win.landmarks.inverse_distances(ids) == 0.0)
    for f in (2, 3):
        win.add_frame(f, poses[f])
        tr = _tracks(camera, pts, poses[f], ids)
        win.add_observations(f, tr.ids, tr.uv, np.zeros(len(ids), dtype=np.int64))
        tri.retriangulate_infinite(f)
        inv = win.landmarks.inverse_distances(ids)
        if f == 2:  # 0.01 m: no attempt
            assert np.all(inv == 0.0)
    np.testing.assert_allclose(inv, 1.0 / np.linalg.norm(pts, axis=1), rtol=1e-9)
