"""Synthetic bundle-adjustment scenes (no images) for tests and benchmarks.

A pinhole camera moves along a gently curving path looking at random 3-D points; landmarks are
hosted by keyframes and observed in the following frames with Gaussian pixel noise whose
standard deviation is ``sigma * 2**(level/2)`` (so that the backend's weight ``2**-level /
sigma^2`` is exactly the information of the observation). All poses are ``T_w_c``
(camera-to-world, z forward), map units are metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from granite.backend.config import BackendConfig
from granite.backend.window import SlidingWindow
from granite.camera import PinholeCamera
from granite.geometry import decoupled_increment, so3_exp


@dataclasses.dataclass
class SyntheticScene:
    camera: PinholeCamera
    frame_ids: list[int]
    keyframe: list[bool]
    poses: np.ndarray  # (K,4,4) true T_w_c
    lm_ids: list[int]
    lm_host: list[int]  # frame id of the host
    lm_bearing: np.ndarray  # (M,3) true unit bearing in the host frame
    lm_inv_dist: np.ndarray  # (M,) true inverse distance
    observations: list[tuple[int, int, np.ndarray, int]]  # (lm id, frame id, uv, level)
    sigma: float

    def pose_of(self, frame_id: int) -> np.ndarray:
        return self.poses[self.frame_ids.index(frame_id)]


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_w_c`` of a camera at ``center`` looking at ``target`` (z forward, y down)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = center
    return T


def observe_points(camera, poses: np.ndarray, frame_ids: list[int], keyframe: list[bool],
                   points_w: np.ndarray, hosts: np.ndarray, sigma: float,
                   obs_per_landmark: int, levels: np.ndarray, rng: np.random.Generator,
                   first_id: int = 1000) -> SyntheticScene:
    """Scene of world points ``points_w`` (M,3), point ``i`` hosted by frame index ``hosts[i]``
    (a keyframe that sees it) and observed there and in up to ``obs_per_landmark - 1`` later
    frames where it projects into the image; points seen fewer than twice are skipped."""
    lm_ids, lm_host, bearings, inv_dists, obs = [], [], [], [], []
    T_c_w = np.linalg.inv(poses)
    for i in range(points_w.shape[0]):
        h = int(hosts[i])
        seen = []
        for t in range(h, len(frame_ids)):
            if len(seen) >= obs_per_landmark:
                break
            p_c = T_c_w[t, :3, :3] @ points_w[i] + T_c_w[t, :3, 3]
            uv, valid = camera.project(p_c[None])
            if valid[0] and camera.in_image(uv, margin=2.0)[0]:
                seen.append((t, uv[0]))
        if len(seen) < 2 or seen[0][0] != h:
            continue
        lm_id = first_id + len(lm_ids)
        level = int(levels[i])
        for t, uv in seen:
            noisy = uv + rng.normal(0.0, sigma * 2.0 ** (0.5 * level), 2)
            obs.append((lm_id, frame_ids[t], noisy, level))
        p_h = T_c_w[h, :3, :3] @ points_w[i] + T_c_w[h, :3, 3]
        dist = float(np.linalg.norm(p_h))
        lm_ids.append(lm_id)
        lm_host.append(frame_ids[h])
        bearings.append(p_h / dist)
        inv_dists.append(1.0 / dist)
    return SyntheticScene(camera, list(frame_ids), list(keyframe), poses, lm_ids, lm_host,
                          np.asarray(bearings).reshape(-1, 3), np.asarray(inv_dists), obs, sigma)


def default_camera() -> PinholeCamera:
    """Pinhole 640x480, f = 500 px."""
    return PinholeCamera(np.array([500.0, 500.0, 319.5, 239.5]), 640, 480)


def make_scene(num_frames: int = 10, num_points: int = 300, sigma: float = 0.5,
               baseline: float = 0.25, obs_per_landmark: int = 5, keyframe_every: int = 1,
               depth: tuple[float, float] = (4.0, 10.0), max_level: int = 0,
               pure_rotation: bool = False, recent_frames: int = 0, camera=None,
               seed: int = 0) -> SyntheticScene:
    """Random scene: ``num_frames`` frames (every ``keyframe_every``-th is a keyframe, the first
    always; the last ``recent_frames`` frames are not keyframes), ``num_points`` landmarks
    hosted by random keyframes at a distance drawn from ``depth`` along a random pixel ray, and
    observed in the host and up to ``obs_per_landmark - 1`` later frames where they project
    into the image. Frame ids are ``10 k + 3`` (not contiguous on purpose).

    With ``pure_rotation`` all cameras share the centre and only rotate (panning). ``camera``
    defaults to :func:`default_camera` (any model of :mod:`granite.camera` works).
    """
    rng = np.random.default_rng(seed)
    cam = default_camera() if camera is None else camera
    poses = np.empty((num_frames, 4, 4))
    for k in range(num_frames):
        if pure_rotation:
            yaw = 0.04 * k
            T = look_at(np.zeros(3), np.array([np.sin(yaw), np.cos(yaw), 0.05 * np.sin(k)]))
        else:
            c = np.array([baseline * k, 0.05 * np.sin(0.7 * k), 0.03 * np.cos(0.5 * k)])
            T = look_at(c, np.array([baseline * k * 0.8 + 0.3 * np.sin(k), 7.0, 0.2]))
        poses[k] = T
    frame_ids = [10 * k + 3 for k in range(num_frames)]
    keyframe = [k % keyframe_every == 0 and k < num_frames - recent_frames
                for k in range(num_frames)]
    kf_idx = np.array([k for k in range(num_frames) if keyframe[k]])
    # oversample candidate points, keep the first num_points that are seen at least twice
    n_cand = 4 * num_points
    hosts = rng.choice(kf_idx, n_cand)
    uv = np.stack([rng.uniform(20, cam.width - 20, n_cand),
                   rng.uniform(20, cam.height - 20, n_cand)], axis=1)
    rays, _ = cam.unproject(uv)
    dist = rng.uniform(depth[0], depth[1], n_cand)
    pts_c = rays * dist[:, None]
    points_w = np.einsum("nij,nj->ni", poses[hosts, :3, :3], pts_c) + poses[hosts, :3, 3]
    levels = rng.integers(0, max_level + 1, n_cand)
    scene = observe_points(cam, poses, frame_ids, keyframe, points_w, hosts, sigma,
                           obs_per_landmark, levels, rng)
    return _truncate(scene, num_points)


def _truncate(scene: SyntheticScene, num_points: int) -> SyntheticScene:
    keep = set(scene.lm_ids[:num_points])
    scene.lm_host = scene.lm_host[:num_points]
    scene.lm_bearing = scene.lm_bearing[:num_points]
    scene.lm_inv_dist = scene.lm_inv_dist[:num_points]
    scene.lm_ids = scene.lm_ids[:num_points]
    scene.observations = [o for o in scene.observations if o[0] in keep]
    return scene


def build_window(scene: SyntheticScene, config: BackendConfig | None = None,
                 pose_noise: tuple[float, float] = (0.0, 0.0), bearing_noise: float = 0.0,
                 inv_dist_noise: float = 0.0, initial_inv_dist: float | None = None,
                 seed: int = 1) -> SlidingWindow:
    """A window holding the scene with perturbed initial values: poses (except the first,
    which carries the gauge prior) by ``pose_noise = (translation [m], rotation [rad])`` std,
    bearings by ``bearing_noise`` [rad], inverse distances by a relative ``inv_dist_noise``
    (or all set to ``initial_inv_dist``)."""
    rng = np.random.default_rng(seed)
    win = SlidingWindow(scene.camera, config)
    for k, fid in enumerate(scene.frame_ids):
        T = scene.poses[k]
        if k > 0:
            xi = np.concatenate([rng.normal(0, pose_noise[0], 3), rng.normal(0, pose_noise[1], 3)])
            T = decoupled_increment(T, xi)
        win.add_frame(fid, T, is_keyframe=scene.keyframe[k])
    for i, lm_id in enumerate(scene.lm_ids):
        b = so3_exp(rng.normal(0, bearing_noise, 3)) @ scene.lm_bearing[i]
        if initial_inv_dist is not None:
            d = initial_inv_dist
        else:
            d = scene.lm_inv_dist[i] * max(0.05, 1.0 + rng.normal(0, inv_dist_noise))
        win.add_landmark(lm_id, scene.lm_host[i], b, d)
    for lm_id, fid, uv, level in scene.observations:
        win.add_observation(lm_id, fid, uv, level)
    return win


def make_hover_scene(num_frames: int = 10, num_near: int = 300, num_far: int = 300,
                     baseline: float = 0.5, sigma: float = 0.5, obs_per_landmark: int = 10,
                     seed: int = 0) -> SyntheticScene:
    """Map initialisation followed by rotation in place: frame 0 is ``baseline`` metres to the
    side of the others, frames 1.. share the centre and yaw by 0.05 rad per frame. Near points
    (5-10 m, hosted by frame 0) and far points (1-10 km, hosted by a random frame that sees
    them; far points hosted by frame ``k >= 1`` are only seen from the common centre)."""
    rng = np.random.default_rng(seed)
    cam = default_camera()
    poses = []
    for k in range(num_frames):
        c = np.array([-baseline, 0.0, 0.0]) if k == 0 else np.zeros(3)
        yaw = 0.0 if k == 0 else 0.05 * (k - 1)
        poses.append(look_at(c, c + np.array([np.sin(yaw), np.cos(yaw), 0.0])))
    poses = np.array(poses)
    ang = rng.uniform(-0.55, 0.55, num_near)
    r = rng.uniform(5.0, 10.0, num_near)
    near = np.stack([r * np.sin(ang), r * np.cos(ang), rng.uniform(-2.0, 2.0, num_near)], 1)
    ang = rng.uniform(-0.5, 1.0, num_far)
    r = rng.uniform(1e3, 1e4, num_far)
    far = np.stack([r * np.sin(ang), r * np.cos(ang), r * rng.uniform(-0.3, 0.3, num_far)], 1)
    points = np.concatenate([near, far])
    T_c_w = np.linalg.inv(poses)
    hosts = np.zeros(len(points), dtype=np.int64)
    for i in range(num_near, len(points)):
        seeing = []
        for k in range(num_frames - 1):
            p_c = T_c_w[k, :3, :3] @ points[i] + T_c_w[k, :3, 3]
            uv, valid = cam.project(p_c[None])
            if valid[0] and cam.in_image(uv, 2.0)[0]:
                seeing.append(k)
        hosts[i] = rng.choice(seeing) if seeing else num_frames - 1
    frame_ids = list(range(num_frames))
    return observe_points(cam, poses, frame_ids, [True] * num_frames, points, hosts, sigma,
                          obs_per_landmark, np.zeros(len(points), dtype=np.int64), rng)
