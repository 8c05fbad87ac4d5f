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
                                (:mod:`granite.visualization.colors`)
``world/camera/image/patches``  a square per track: its patch extent at the creation level
``world/keyframes``             keyframes of the current window as blue wireframe frustums
``world/landmarks``             landmarks of the window, same colours as the 2D points
``plots/<name>``                time series (tracked points, landmarks, entropy, relative scale error,
                                the scale-drift indicator Λ ``scale_drift_indicator`` and its
                                reference variant ``scale_drift_indicator_ref``, and
                                ``log10_scale_drift_indicator``: rerun 0.23's time-series views
                                have no logarithmic axis, and Λ spans decades;
                                ``scale_unobservable``: 1 where Λ found no scale information
                                in the window, 0 where it is defined)
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
from granite.io import PendingFile, check_writable
from granite.visualization.colors import inverse_distance_colors

#: Radius of the reference patch pattern (52 samples on a 2 px lattice, scaled 0.75), level 0.
PATCH_RADIUS_PX = 5.25

#: Time-series points are sent in batches of this many when streaming to a viewer (which then
#: lags by at most as many frames); a recording written to a file gets them all at the end.
SERIES_BATCH = 20
#: Image files logged as they are (``rr.EncodedImage``), without re-encoding.
ENCODED_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

GROUNDTRUTH_COLOR = (40, 200, 40)
ESTIMATE_COLOR = (230, 40, 40)
KEYFRAME_COLOR = (40, 80, 255)


#: Dot radius of a track and line radius of its patch outline, in image pixels.
TRACK_DOT_RADIUS_PX = 2.0
PATCH_RING_WIDTH_PX = 0.5


def recording_path(rerun: str | Path | None, spawn: bool, default: str | Path) -> Path | None:
    """The recording a viewing command writes (``None``: streamed to a viewer only): ``rerun``,
    else ``default`` unless ``spawn``. Checked before any work: raises InputError naming it
    when it cannot be written as a file."""
    path = None if spawn and not rerun else Path(rerun or default)
    if path is not None:
        check_writable(path, folder=False)
    return path


def frustum_wireframes(poses_w_c: np.ndarray, K: np.ndarray, resolution, depth: float) -> np.ndarray:
    """Line strips (N, 10, 3) drawing the frustum of each pose ``T_w_c`` (N, 4, 4): apex to the
    four image corners unprojected to planar depth ``depth`` through the pinhole ``K``, and the
    rectangle between them (one strip per camera)."""
    w, h = resolution
    corners_px = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], dtype=np.float64)
    corners_c = depth * corners_px @ np.linalg.inv(K).T  # (4, 3), camera frame, z = depth
    # One strip over all 8 edges: the rectangle, then the four edges to the apex (None).
    walk = [0, 1, 2, 3, 0, None, 1, 2, None, 3]
    local = np.array([np.zeros(3) if i is None else corners_c[i] for i in walk])  # (10, 3)
    R, t = poses_w_c[:, :3, :3], poses_w_c[:, :3, 3]
    return np.einsum("nij,kj->nki", R, local) + t[:, None, :]


def default_blueprint() -> rrb.Blueprint:
    """Camera image with tracks beside the 3D world; underneath, the time series: point
    counts, negative entropy with keyframe events, the relative scale error, and beside it the
    scale-drift indicator Λ (Eq. 17 and the reference variant) and log10 Λ with
    ``scale_unobservable`` (1 where Λ found no scale information, 0 where it is defined)."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(name="camera", origin="world/camera/image"),
                rrb.Spatial3DView(name="world", origin="world"),
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(name="points", origin="plots", contents=[
                    "plots/tracked_points", "plots/finite_landmarks", "plots/infinite_landmarks"]),
                rrb.TimeSeriesView(name="negative entropy, keyframes", origin="plots", contents=[
                    "plots/negative_entropy", "plots/keyframe", "plots/submap"]),
                rrb.TimeSeriesView(name="relative scale error", origin="plots", contents=[
                    "plots/relative_scale_error"]),
                rrb.TimeSeriesView(name="scale-drift indicator Λ (Eq. 17, reference variant)",
                                   origin="plots", contents=[
                                       "plots/scale_drift_indicator",
                                       "plots/scale_drift_indicator_ref"]),
                rrb.TimeSeriesView(name="log10 Λ; 1 = no scale information", origin="plots", contents=[
                    "plots/log10_scale_drift_indicator", "plots/scale_unobservable"]),
            ),
            row_shares=[3, 1],
        ),
        collapse_panels=True,
    )


class RerunLogger:
    """Logs one recording, saved to ``rrd_path`` or (``spawn``) streamed to a new viewer. The
    file is written atomically: logged to a temporary file beside it, moved onto ``rrd_path``
    by :meth:`close`; :meth:`discard` (on an error) removes it."""

    def __init__(self, name: str, rrd_path: str | Path | None = None, spawn: bool = False):
        self.rec = rr.RecordingStream("granite", recording_id=name)
        self._file = None if rrd_path is None else PendingFile(rrd_path)
        if self._file is not None:
            self.rec.save(str(self._file.tmp), default_blueprint=default_blueprint())
        elif spawn:
            self.rec.spawn(default_blueprint=default_blueprint())
        self._t0: float | None = None
        self._K: np.ndarray | None = None
        self._resolution: list[int] | None = None
        self._series: dict[str, list[tuple[int, float, float]]] = {}
        self._series_batch = SERIES_BATCH if rrd_path is None else None
        self._frame = 0
        self._time = 0.0
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # -- time ---------------------------------------------------------------------------
    def set_frame(self, index: int, timestamp: float) -> None:
        if self._t0 is None:
            self._t0 = timestamp
        self._frame, self._time = int(index), float(timestamp - self._t0)
        self.rec.set_time("frame", sequence=self._frame)
        self.rec.set_time("time", duration=self._time)

    def elapsed(self, timestamp: float) -> float:
        """Seconds since the first frame (the ``time`` timeline)."""
        if self._t0 is None:
            self._t0 = float(timestamp)
        return float(timestamp) - self._t0

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

    # -- many frames at once (column-wise: one call per entity) -------------------------
    def _time_columns(self, frames, timestamps) -> list:
        stamps = np.asarray(timestamps, dtype=np.float64)
        if self._t0 is None and len(stamps):
            self._t0 = float(stamps[0])
        return [rr.TimeColumn("frame", sequence=np.asarray(frames, dtype=np.int64)),
                rr.TimeColumn("time", duration=stamps - (self._t0 or 0.0))]

    def send_camera_poses(self, frames, timestamps, poses_w_c: np.ndarray) -> None:
        """``world/camera`` at ``poses_w_c`` (N, 4, 4) for frames (N,) at timestamps (N,)."""
        poses_w_c = np.asarray(poses_w_c, dtype=np.float64).reshape(-1, 4, 4)
        if not len(poses_w_c):
            return
        quats = np.array([rotation_to_quat(T[:3, :3]) for T in poses_w_c])
        self.rec.send_columns(
            "world/camera", indexes=self._time_columns(frames, timestamps),
            columns=rr.Transform3D.columns(translation=poses_w_c[:, :3, 3], quaternion=quats))

    def send_keyframes(self, frames, timestamps, keyframe_poses: list[np.ndarray], frustum_depth: float) -> None:
        """``world/keyframes``: per frame, the window's keyframes ``T_w_c`` ((M_i, 4, 4) each) as
        blue wireframe frustums ``frustum_depth`` deep (world units)."""
        if self._K is None or not len(frames):
            return
        counts = [len(p) for p in keyframe_poses]
        poses = np.concatenate([np.asarray(p).reshape(-1, 4, 4) for p in keyframe_poses])
        strips = frustum_wireframes(poses, self._K, self._resolution, frustum_depth)
        colors = np.tile(np.array(KEYFRAME_COLOR, dtype=np.uint8), (len(strips), 1))
        self.rec.send_columns(
            "world/keyframes", indexes=self._time_columns(frames, timestamps),
            columns=rr.LineStrips3D.columns(strips=strips, colors=colors).partition(counts))

    def send_points3d(self, entity: str, frames, timestamps, points: list[np.ndarray],
                      colors: list[np.ndarray], radius: float) -> None:
        """Per frame a point cloud (``points[i]`` (M_i, 3), ``colors[i]`` (M_i, 3) uint8)."""
        if not len(frames):
            return
        counts = [len(p) for p in points]
        positions = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points])
        rgb = np.concatenate([np.asarray(c, dtype=np.uint8).reshape(-1, 3) for c in colors])
        self.rec.send_columns(
            entity, indexes=self._time_columns(frames, timestamps),
            columns=rr.Points3D.columns(positions=positions, colors=rgb,
                                        radii=np.full(len(positions), radius)).partition(counts))

    # -- per frame ------------------------------------------------------------------------
    def log_depth(self, depth: np.ndarray) -> None:
        """Planar depth (H, W) in metres, 0 where there is no surface."""
        self.rec.log("world/camera/depth", rr.DepthImage(depth, meter=1.0))

    def log_image(self, image: np.ndarray, source: str | Path | None = None) -> None:
        """A grayscale (H, W) or colour (H, W, 3) image (8 or 16 bit). When ``source`` is the
        PNG or JPEG file the image was read from, its bytes are logged as they are (cheaper than
        the raw pixels, and the recording stays about as small as the dataset)."""
        if source is not None and Path(source).suffix.lower() in ENCODED_IMAGE_SUFFIXES:
            self.rec.log("world/camera/image", rr.EncodedImage(path=source))
            return
        model = "L" if image.ndim == 2 else "RGB"
        self.rec.log("world/camera/image", rr.Image(image, color_model=model))

    def log_tracks(
        self,
        positions: np.ndarray,
        levels: np.ndarray,
        inverse_distance: np.ndarray | None = None,
        d_max: float = 1.0,
    ) -> None:
        """2D tracks; ``inverse_distance`` NaN = no landmark, 0 = at infinity. Each track is a
        dot (``world/camera/image/tracks``) and a square outline of its patch extent at the
        creation level (``world/camera/image/patches``, half size = patch radius; squares cost
        a tenth of drawn circles), both in the inverse-distance colour."""
        n = len(positions)
        d = np.full(n, np.nan) if inverse_distance is None else np.asarray(inverse_distance)
        colors = inverse_distance_colors(d, d_max)
        radii = PATCH_RADIUS_PX * np.power(2.0, np.asarray(levels, dtype=np.float64))
        self.rec.log("world/camera/image/tracks",
                     rr.Points2D(positions, radii=TRACK_DOT_RADIUS_PX, colors=colors))
        self.rec.log("world/camera/image/patches",
                     rr.Boxes2D(centers=positions, half_sizes=np.stack([radii, radii], axis=1),
                                colors=colors, radii=PATCH_RING_WIDTH_PX))

    def log_scalar(self, name: str, value: float) -> None:
        """A point of the time series ``plots/<name>`` at the current frame. Points are buffered
        and sent column-wise (one call per series, a fraction of the cost of one log call per
        point): every :data:`SERIES_BATCH` frames to a viewer, and on :meth:`flush_series` /
        :meth:`close`."""
        self.add_scalar(name, self._frame, self._time, value)

    def add_scalar(self, name: str, frame: int, time: float, value: float) -> None:
        """:meth:`log_scalar` at an explicit frame and time (seconds since the first frame)."""
        if value is None or not np.isfinite(value):
            return
        points = self._series.setdefault(name, [])
        points.append((int(frame), float(time), float(value)))
        if self._series_batch is not None and len(points) >= self._series_batch:
            self._send_series(name)

    def flush_series(self) -> None:
        for name in list(self._series):
            self._send_series(name)

    def _send_series(self, name: str) -> None:
        points = self._series.pop(name, [])
        if not points:
            return
        frames, times, values = zip(*points)
        self.rec.send_columns(
            f"plots/{name}",
            indexes=[rr.TimeColumn("frame", sequence=frames), rr.TimeColumn("time", duration=times)],
            columns=rr.Scalars.columns(scalars=values),
        )

    def close(self) -> None:
        """Flush everything logged so far to the viewer, or to the file and move it in place."""
        self.flush_series()
        self.rec.flush(blocking=True)
        if self._file is not None:
            self.rec.disconnect()
            self._file.commit()

    def discard(self) -> None:
        """Give up the recording: no file is written (a no-op after :meth:`close`)."""
        if self._file is not None:
            self.rec.disconnect()
            self._file.discard()
