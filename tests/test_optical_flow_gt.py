"""Tracks against ground-truth flow computed from depth and camera poses.

1. A textured ground plane rendered exactly (per-pixel ray casting) from two camera poses:
   the ground-truth flow helper is checked against the plane's homography, and the tracker
   against the ground-truth flow.
2. The test-bench's pre-rendered sequences (assets/sequences/<scenario>/): over consecutive
   frame pairs, median error < 0.3 px and fewer than 2 % of tracks off by more than 2 px.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from granite.camera import make_camera
from granite.optical_flow import FrameToFrameOpticalFlow
from granite.optical_flow.gt_flow import depth_at, ground_truth_flow
from granite.optical_flow.synthetic import textured_image

W, H = 640, 480
INTRINSICS = {"fx": 420.0, "fy": 420.0, "cx": 319.5, "cy": 239.5}
TEX_RES = 0.004  # metres per texture pixel
TEX = textured_image(1500, 1500, seed=21)


def pose(x: float, y: float, height: float, yaw_deg: float, tilt_deg: float) -> np.ndarray:
    """Camera looking down at the z = 0 plane (camera z = world -z), yawed and tilted."""
    down = np.diag([1.0, -1.0, -1.0])  # camera x = world x, camera y = -world y, z = -world z
    r = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ down
    r = r @ Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = r
    T[:3, 3] = (x, y, height)
    return T


def render(T_w_c: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """Exact image and planar depth of the textured plane z = 0 (bilinear texture lookup)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    bearings, ok = camera.unproject(np.c_[u.ravel(), v.ravel()])
    d_w = bearings @ T_w_c[:3, :3].T
    s = -T_w_c[2, 3] / d_w[:, 2]  # ray length to z = 0
    p_w = T_w_c[:3, 3] + s[:, None] * d_w
    tx = (p_w[:, 0] / TEX_RES + TEX.shape[1] / 2).reshape(H, W).astype(np.float32)
    ty = (p_w[:, 1] / TEX_RES + TEX.shape[0] / 2).reshape(H, W).astype(np.float32)
    img = cv2.remap(TEX.astype(np.float32), tx, ty, cv2.INTER_LINEAR)
    depth = (s * bearings[:, 2]).reshape(H, W).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), depth


def test_depth_interpolation_rejects_discontinuities():
    depth = np.full((10, 10), 2.0, np.float32)
    depth[:, 5:] = 4.0
    depth[0, 0] = np.inf
    z = depth_at(depth, np.array([[2.5, 3.5], [4.5, 3.0], [6.2, 7.7], [0.5, 0.5], [9.5, 2.0]]))
    np.testing.assert_allclose(z[[0, 2]], [2.0, 4.0])
    assert np.isnan(z[[1, 3, 4]]).all()  # edge, unknown depth, outside


def test_ground_truth_flow_matches_the_plane_homography():
    camera = make_camera("pinhole", INTRINSICS, W, H)
    Ti, Tj = pose(0.0, 0.0, 2.0, 0.0, 5.0), pose(0.06, -0.03, 1.97, 2.0, 3.0)
    _, depth = render(Ti, camera)
    uv = np.random.default_rng(0).uniform([20, 20], [W - 20, H - 20], (200, 2))
    uv_j, ok = ground_truth_flow(uv, depth, Ti, Tj, camera)
    assert ok.all()
    # Independent: plane-induced homography H = K (R - t n^T / d) K^-1 (plane in camera i).
    K = np.array([[420.0, 0, 319.5], [0, 420.0, 239.5], [0, 0, 1]])
    T_j_i = np.linalg.inv(Tj) @ Ti
    n_i = Ti[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # plane normal in camera i
    d_i = -(n_i @ (Ti[:3, :3].T @ -Ti[:3, 3]))  # n . p + d = 0 for plane points p
    Hm = K @ (T_j_i[:3, :3] - np.outer(T_j_i[:3, 3], n_i) / d_i) @ np.linalg.inv(K)
    q = np.c_[uv, np.ones(len(uv))] @ Hm.T
    np.testing.assert_allclose(uv_j, q[:, :2] / q[:, 2:], atol=2e-3)


def test_tracks_agree_with_depth_based_flow_on_a_rendered_plane():
    camera = make_camera("pinhole", INTRINSICS, W, H)
    poses = [pose(0.0, 0.0, 2.0, 0.0, 5.0), pose(0.05, -0.03, 1.97, 2.0, 3.0),
             pose(0.12, -0.05, 1.93, 3.5, 1.0)]
    flow = FrameToFrameOpticalFlow()
    frames = [render(T, camera) for T in poses]
    results = [flow.process(0.1 * k, img) for k, (img, _) in enumerate(frames)]
    errors = []
    for i in (0, 1):
        a, b = results[i], results[i + 1]
        _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        assert len(ia) > 0.8 * len(a)
        uv_gt, ok = ground_truth_flow(a.positions[ia], frames[i][1], poses[i], poses[i + 1], camera)
        errors.append(np.linalg.norm(b.positions[ib] - uv_gt, axis=1)[ok])
    e = np.concatenate(errors)
    assert np.median(e) < 0.1 and np.mean(e > 2.0) < 0.01


# --------------------------------------------------------------------------- test-bench data

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"
MAX_FRAMES = 60  # per sequence, to keep the test fast


def _sequences() -> list[Path]:
    if not SEQUENCES.is_dir():
        return []
    # Finished renders only: the image list is written when a render completes.
    return sorted(p for p in SEQUENCES.iterdir()
                  if (p / "mav0" / "depth0" / "data").is_dir() and (p / "mav0" / "cam0" / "data.csv").is_file())


def _depth_path(root: Path, ns: int) -> Path:
    for ext in (".npy", ".png"):
        path = root / "mav0" / "depth0" / "data" / f"{ns}{ext}"
        if path.is_file():
            return path
    raise FileNotFoundError(f"no depth map for {ns} in {root}")


def sequence_flow_errors(root: Path, max_frames: int = MAX_FRAMES) -> tuple[np.ndarray, int]:
    """Tracking errors (px) against depth-based ground-truth flow over consecutive processed
    frames of a test-bench sequence, and the number of frame pairs."""
    from granite.geometry import interpolate_poses
    from granite.io import open_dataset
    from simulation.depth import read_depth

    ds = open_dataset(root)
    camera = ds.calibration.camera()
    stamps = ds.timestamps[:max_frames]
    poses = interpolate_poses(ds.ground_truth.timestamps, ds.ground_truth.poses, stamps)
    flow = FrameToFrameOpticalFlow(image_size=(camera.width, camera.height))
    errors, pairs, prev = [], 0, None
    for frame in ds.frames(0, max_frames):
        result = flow.process(frame.timestamp, frame.image)
        if result.rejected:
            continue
        if prev is not None:
            (i, a), b = prev, result
            _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
            depth = read_depth(_depth_path(root, int(ds.timestamps_ns[i])))
            uv_gt, ok = ground_truth_flow(a.positions[ia], depth, poses[i], poses[frame.index], camera)
            errors.append(np.linalg.norm(b.positions[ib] - uv_gt, axis=1)[ok])
            pairs += 1
        prev = (frame.index, result)
    return (np.concatenate(errors) if errors else np.zeros(0)), pairs


@pytest.mark.slow
@pytest.mark.parametrize(
    "root",
    _sequences() or [pytest.param(None, marks=pytest.mark.skip(reason="no pre-rendered sequence in assets/sequences"))],
    ids=lambda p: getattr(p, "name", "none"),
)
def test_tracks_agree_with_ground_truth_flow_on_prerendered_sequences(root):
    errors, pairs = sequence_flow_errors(root)
    assert pairs >= 5 and len(errors) >= 20 * pairs
    assert np.median(errors) < 0.3, np.median(errors)
    assert np.mean(errors > 2.0) < 0.02, np.mean(errors > 2.0)
