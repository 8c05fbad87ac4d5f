"""Recovery across frame drops: re-find the window's landmarks before declaring failure.

When a mapped frame observes fewer than ``refind_below_finite`` finite landmarks (after a burst
of dropped images or a fast motion the frame-to-frame tracks are gone), every finite landmark
of the window that the frame does not observe is projected with the frame's predicted
(constant-velocity) pose and its patch is tracked from its host keyframe's image to there
(:func:`granite.optical_flow.refind.refind_points`: forward-backward check and ZNCC against the
host patch). Accepted points become observations of the current frame, so the window's
optimisation sees them; outliers among them go with the usual outlier removal.

Not in the reference. The keyframe images are kept while their keyframe is in the window (one
reference per image, no copy); their pyramids are built only when re-finding runs.
"""

from __future__ import annotations

import numpy as np

from granite.backend import SlidingWindow
from granite.geometry import se3_inverse
from granite.optical_flow import OpticalFlowConfig, build_pyramid
from granite.optical_flow.patterns import make_pattern
from granite.optical_flow.refind import refind_points


class LandmarkRefinder:
    """Keeps the images of the window's frames and re-finds landmarks in a new frame."""

    def __init__(self, window: SlidingWindow, camera, flow_config: OpticalFlowConfig,
                 fb_threshold_sq: float, min_zncc: float):
        self.window = window
        self.camera = camera
        self.flow_config = flow_config
        self.fb_threshold_sq = fb_threshold_sq
        self.min_zncc = min_zncc
        self._pattern = make_pattern(flow_config.pattern, flow_config.pattern_scale)
        self._images: dict[int, np.ndarray] = {}
        self._pyramids: dict[int, object] = {}
        self.last_refound = 0  # points re-found in the last call

    def add_image(self, frame_id: int, image: np.ndarray) -> None:
        self._images[frame_id] = image

    def prune(self) -> None:
        """Forget the images of frames that left the window."""
        for f in [f for f in self._images if f not in self.window]:
            self._images.pop(f, None)
            self._pyramids.pop(f, None)

    def reset(self) -> None:
        self._images.clear()
        self._pyramids.clear()

    def _pyramid(self, frame_id: int):
        pyr = self._pyramids.get(frame_id)
        if pyr is None:
            cfg = self.flow_config
            pyr = build_pyramid(self._images[frame_id], cfg.levels, cfg.presmooth_sigma)
            self._pyramids[frame_id] = pyr
        return pyr

    def refind(self, frame_id: int, T_w_c: np.ndarray) -> int:
        """Re-find the finite landmarks of the window not observed in ``frame_id`` (pose guess
        ``T_w_c``) and add the accepted ones as its observations. Returns their number."""
        win, db = self.window, self.window.landmarks
        seen = db.observed_in(frame_id)
        current = self._pyramid(frame_id)
        T_c_w = se3_inverse(T_w_c)
        margin = float(self.flow_config.border)
        found = 0
        for host in win.keyframe_ids:
            if host == frame_id or host not in self._images:
                continue
            ids = np.array(sorted(i for i in db.hosted_by(host) if i not in seen), dtype=np.int64)
            if not len(ids):
                continue
            inv = db.inverse_distances(ids)
            ids = ids[inv > 0.0]
            if not len(ids):
                continue
            points_c = win.landmark_points(ids, T_c_w)
            uv, valid = self.camera.project(points_c)
            valid &= points_c[:, 2] > 0.0
            valid &= self.camera.in_image(uv, margin)
            if not valid.any():
                continue
            ids, uv = ids[valid], uv[valid]
            obs = [db.observation(int(i), host) for i in ids]
            host_uv = np.array([o.uv for o in obs], dtype=np.float64)
            levels = np.array([o.level for o in obs], dtype=np.int64)
            new_uv, ok, _ = refind_points(
                self._pyramid(host), current, host_uv, levels, uv, self._pattern,
                self.flow_config.margin, self.flow_config.iterations, self.fb_threshold_sq,
                self.min_zncc,
            )
            for i, p, lvl in zip(ids[ok], new_uv[ok], levels[ok]):
                win.add_observation(int(i), frame_id, p, int(lvl))
            found += int(ok.sum())
        self.last_refound = found
        return found
