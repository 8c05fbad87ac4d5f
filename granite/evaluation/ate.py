"""Absolute trajectory error (ATE) after Umeyama alignment.

The estimate is associated with the interpolated ground truth
(:func:`granite.evaluation.association.associate`). With ``align="sim3"`` (monocular) or
``"se3"`` the estimated positions of every sub-map are aligned *separately* to the ground
truth (paper Fig. 3: each sub-map has its own origin and scale); ``"none"`` compares raw
positions. The error of a pose is the distance between its aligned position and the ground
truth position; statistics are over all associated poses of all aligned sub-maps.

When the positions of a sub-map are collinear (a straight leg, possibly with turns in place),
Umeyama cannot fix the rotation about that line; the rotation is then taken from the
orientations (chordal mean of ``R_gt R_est^T``) and scale and translation from the positions.
A sub-map whose alignment is still undetermined (fewer than 3 associated poses, all positions
coincident) is left out and reported in ``skipped_submaps``; if none can be aligned an
InputError is raised.

``align_frames = N`` estimates each sub-map's alignment from its first ``N`` associated poses
only (all of them when it has fewer) and applies it to the whole sub-map, as the paper's Fig. 4
does with ``N = 100``: the error then grows with the drift since the start (scale drift
included) instead of being spread over the sub-map by a best fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from granite.errors import InputError
from granite.evaluation.association import associate
from granite.geometry import umeyama_alignment
from granite.trajectory import Trajectory

ALIGNMENTS = ("sim3", "se3", "none")


@dataclass(frozen=True, eq=False)
class AteResult:
    """ATE statistics (metres of the ground truth) and the aligned estimate.

    Attributes:
        align: ``"sim3"``, ``"se3"`` or ``"none"``.
        rmse, mean, median, max: statistics of ``errors``.
        errors: ``(M,)`` position error per evaluated pose.
        aligned: the evaluated estimate poses after alignment (with their sub-map indices).
        reference: the ground truth interpolated at the same timestamps.
        scales: per sub-map index, the alignment scale (1 for se3 / none).
        skipped_submaps: sub-map index -> reason it could not be aligned.
        transforms: per sub-map index, the similarity ``(s, R, t)`` mapping estimate
            positions into the ground-truth frame, ``x -> s R x + t``.
    """

    align: str
    rmse: float
    mean: float
    median: float
    max: float
    errors: np.ndarray
    aligned: Trajectory
    reference: Trajectory
    scales: dict[int, float] = field(default_factory=dict)
    skipped_submaps: dict[int, str] = field(default_factory=dict)
    transforms: dict[int, tuple[float, np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def num_poses(self) -> int:
        return int(self.errors.shape[0])


def align_poses(poses: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply the similarity ``x -> s R x + t`` to camera poses: rotations ``R @ R_w_c``,
    positions ``s R p + t`` (the camera frame itself is not scaled)."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    return out


def _align_with_orientations(est: np.ndarray, gt: np.ndarray, with_scale: bool):
    """Similarity from orientations (rotation) and positions (scale, translation)."""
    M = np.einsum("nij,nkj->ik", gt[:, :3, :3], est[:, :3, :3])  # sum of R_gt R_est^T
    u, _, vt = np.linalg.svd(M)
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    p_est, p_gt = est[:, :3, 3], gt[:, :3, 3]
    a = (p_est - p_est.mean(axis=0)) @ R.T
    b = p_gt - p_gt.mean(axis=0)
    denom = float(np.sum(a * a))
    if denom <= 1e-24:
        raise ValueError("umeyama alignment is degenerate: all points coincide")
    s = float(np.sum(a * b) / denom) if with_scale else 1.0
    if s <= 0:
        raise ValueError("alignment from orientations gives a non-positive scale")
    return s, R, p_gt.mean(axis=0) - s * R @ p_est.mean(axis=0)


def check_align_frames(align_frames: int | None) -> None:
    """ValueError unless ``align_frames`` is None or an integer of at least 3."""
    if align_frames is None:
        return
    if isinstance(align_frames, bool) or not isinstance(align_frames, (int, np.integer)) or align_frames < 3:
        raise ValueError(f"align_frames must be an integer of at least 3 (poses), got {align_frames!r}")


def ate(est: Trajectory, gt: Trajectory, align: str = "sim3", align_frames: int | None = None) -> AteResult:
    """ATE of ``est`` against ``gt`` with per-sub-map ``align``, estimated from all poses of a
    sub-map or from its first ``align_frames`` (see the module docstring)."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    check_align_frames(align_frames)
    indices, gt_poses = associate(est, gt)
    ids = est.submap_ids()[indices]
    est_poses = est.poses[indices]
    aligned = np.array(est_poses)
    keep = np.ones(indices.size, dtype=bool)
    scales: dict[int, float] = {}
    transforms: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
    skipped: dict[int, str] = {}
    for sid in np.unique(ids):
        mask = ids == sid
        if align == "none":
            scales[int(sid)] = 1.0
            transforms[int(sid)] = (1.0, np.eye(3), np.zeros(3))
            continue
        with_scale = align == "sim3"
        fit = np.flatnonzero(mask)[:align_frames]  # associated poses are in time order
        try:
            try:
                s, R, t = umeyama_alignment(est_poses[fit, :3, 3], gt_poses[fit, :3, 3], with_scale)
            except ValueError as error:
                if "collinear" not in str(error):
                    raise
                s, R, t = _align_with_orientations(est_poses[fit], gt_poses[fit], with_scale)
        except ValueError as error:
            skipped[int(sid)] = str(error)
            keep[mask] = False
            continue
        scales[int(sid)] = float(s)
        transforms[int(sid)] = (float(s), R, t)
        aligned[mask] = align_poses(est_poses[mask], s, R, t)
    if not keep.any():
        reasons = "; ".join(f"sub-map {k}: {v}" for k, v in skipped.items())
        raise InputError(f"cannot align the estimate to the ground truth ({reasons})")
    errors = np.linalg.norm(aligned[keep, :3, 3] - gt_poses[keep, :3, 3], axis=1)
    times = est.timestamps[indices][keep]
    sub = None if est.submap is None else ids[keep]
    return AteResult(
        align=align,
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(np.mean(errors)),
        median=float(np.median(errors)),
        max=float(np.max(errors)),
        errors=errors,
        aligned=Trajectory(times, aligned[keep], sub),
        reference=Trajectory(times, gt_poses[keep]),
        scales=scales,
        skipped_submaps=skipped,
        transforms=transforms,
    )
