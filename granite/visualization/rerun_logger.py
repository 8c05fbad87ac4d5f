"""Thin, typed wrapper around a rerun recording with granite's entity layout.

Entity layout (world frame z up for the test-bench; all poses ``T_w_c``):

==============================  ==========================================================
``world``                       view coordinates (right-handed, z up)
``world/groundtruth``           ground-truth trajectory, green line strip (static)
``world/estimate``              estimated trajectory (aligned to the ground truth), red
``world/camera``                current camera pose (transform + pinhole frustum)
``world/camera/image``          the camera image
``world/camera/depth``          planar depth in metres (dataset recordings only)
``world/camera/image/tracks``   tracked points, coloured by inverse distance
                                (:mod:`granite.visualization.colors`), radius = patch size
``world/keyframes/<slot>``      keyframes of the current window as frustums (slot = rank
                                in the window, oldest first; unused slots are cleared)
``world/landmarks``             landmarks of the window, same colours as the 2D points
``plots/<name>``                time series (tracked points, landmarks, entropy, relative scale error)
==============================  ==========================================================

Timelines: ``frame`` (sequence, dataset frame index) and ``time`` (seconds since the first
frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from granite.geometry import rotation_to_quat
from granite.visualization.colors import inverse_distance_colors

#: Radius of the reference patch pattern (52 samples on a 2 px lattice, scaled 0.75), level 0.
PATCH_RADIUS_PX = 5.25

GROUNDTRUTH_COLOR = (40, 200, 40)
ESTIMATE_COLOR = (230, 40, 40)


def default_blueprint() -> rrb.Blueprint:
    """Camera image with tracks beside the 3D world, time series underneath."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(name="camera", origin="world/camera/image"),
                rrb.Spatial3DView(name="world", origin="world"),
            ),
            rrb.TimeSeriesView(name="diagnostics", origin="plots"),
            row_shares=[3, 1],
        ),
        collapse_panels=True,
    )


class RerunLogger:
    """Logs one recording, saved to ``rrd_path`` or (``spawn``) streamed to a new viewer."""

    def __init__(self, name: str, rrd_path: str | Path | None = None, spawn: bool = False):
        self.rec = rr.RecordingStream("granite", recording_id=name)
        if rrd_path is not None:
            Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(rrd_path), default_blueprint=default_blueprint())
        elif spawn:
            self.rec.spawn(default_blueprint=default_blueprint())
        self._t0: float | None = None
        self._K: np.ndarray | None = None
        self._resolution: list[int] | None = None
        self._keyframe_slots = 0
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # -- time ---------------------------------------------------------------------------
    def set_frame(self, index: int, timestamp: float) -> None:
        if self._t0 is None:
            self._t0 = timestamp
        self.rec.set_time("frame", sequence=int(index))
        self.rec.set_time("time", duration=float(timestamp - self._t0))

    # -- static content -------------------------------------------------------------------
    def log_camera_model(self, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
        """Pinhole frustum of ``world/camera`` (intrinsics of the linear part for fisheyes)."""
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self._K, self._resolution = K, [width, height]
        self.rec.log(
            "world/camera",
            rr.Pinhole(image_from_camera=K, resolution=[width, height], camera_xyz=rr.ViewCoordinates.RDF),
            static=True,
        )

    def log_trajectory(self, entity: str, positions: np.ndarray, color, static: bool = True) -> None:
        """Trajectory as one line strip per contiguous block (``positions`` may hold NaN gaps)."""
        positions = np.asarray(positions, dtype=np.float64)
        finite = np.all(np.isfinite(positions), axis=1)
        breaks = np.flatnonzero(np.diff(finite.astype(int)) != 0) + 1
        strips = [s[np.all(np.isfinite(s), axis=1)] for s in np.split(positions, breaks)]
        strips = [s for s in strips if len(s) > 1]
        self.rec.log(entity, rr.LineStrips3D(strips, colors=[color] * len(strips)), static=static)

    # -- per frame ------------------------------------------------------------------------
    def log_camera_pose(self, T_w_c: np.ndarray) -> None:
        q = rotation_to_quat(T_w_c[:3, :3])
        self.rec.log("world/camera", rr.Transform3D(translation=T_w_c[:3, 3], quaternion=q))

    def log_depth(self, depth: np.ndarray) -> None:
        """Planar depth (H, W) in metres, 0 where there is no surface."""
        self.rec.log("world/camera/depth", rr.DepthImage(depth, meter=1.0))

    def log_keyframes(self, poses_w_c: list[np.ndarray], frustum_depth: float) -> None:
        """The window's keyframes ``T_w_c`` as frustums ``frustum_depth`` deep (world units);
        slots left over from a larger window are cleared."""
        for slot, T in enumerate(poses_w_c):
            entity = f"world/keyframes/{slot}"
            q = rotation_to_quat(T[:3, :3])
            self.rec.log(entity, rr.Transform3D(translation=T[:3, 3], quaternion=q))
            if self._K is not None:
                self.rec.log(entity, rr.Pinhole(image_from_camera=self._K, resolution=self._resolution,
                                                camera_xyz=rr.ViewCoordinates.RDF,
                                                image_plane_distance=frustum_depth))
        for slot in range(len(poses_w_c), self._keyframe_slots):
            self.rec.log(f"world/keyframes/{slot}", rr.Clear(recursive=True))
        self._keyframe_slots = max(self._keyframe_slots, len(poses_w_c))

    def log_image(self, image: np.ndarray) -> None:
        self.rec.log("world/camera/image", rr.Image(image))

    def log_tracks(
        self,
        positions: np.ndarray,
        levels: np.ndarray,
        inverse_distance: np.ndarray | None = None,
        d_max: float = 1.0,
    ) -> None:
        """2D tracks; ``inverse_distance`` NaN = no landmark, 0 = at infinity."""
        n = len(positions)
        d = np.full(n, np.nan) if inverse_distance is None else np.asarray(inverse_distance)
        radii = PATCH_RADIUS_PX * np.power(2.0, np.asarray(levels, dtype=np.float64))
        self.rec.log(
            "world/camera/image/tracks",
            rr.Points2D(positions, radii=radii, colors=inverse_distance_colors(d, d_max)),
        )

    def log_points3d(self, entity: str, points: np.ndarray, colors, radius: float = 0.02) -> None:
        self.rec.log(entity, rr.Points3D(points, colors=colors, radii=radius))

    def log_scalar(self, name: str, value: float) -> None:
        if value is not None and np.isfinite(value):
            self.rec.log(f"plots/{name}", rr.Scalars(float(value)))

    def close(self) -> None:
        """Flush everything logged so far to the file or viewer."""
        self.rec.flush(blocking=True)
