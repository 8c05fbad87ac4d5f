"""Everything that is decided before Blender starts (pure numpy): the terrain model, the
flight, frame times and poses, dropped frames and the checks that reject a bad flight.

A :class:`RunPlan` is all the writer and the renderer need; building it raises
:class:`granite.errors.ConfigError` for a flight that goes below ground or off the terrain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.errors import ConfigError
from simulation.flights import Flight, frame_drops, frame_times, make_flight
from simulation.terrain.model import TerrainModel, make_terrain_model

#: Extra samples between frames for the clearance check.
_CHECK_OVERSAMPLING = 4


@dataclass(frozen=True, eq=False)
class RunPlan:
    scenario: object
    model: TerrainModel
    flight: Flight
    times: np.ndarray  # (N,) seconds
    timestamps_ns: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) T_w_c
    dropped: np.ndarray  # (N,) bool

    def motion_poses(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses at shutter open and close of frame ``i`` (for motion blur)."""
        s = self.scenario
        half = 0.5 * s.render.shutter / s.camera.rate_hz
        t = np.clip(self.times[i] + np.array([-half, half]), 0.0, self.flight.duration)
        P = self.flight.poses(t)
        return P[0], P[1]


    def exposure_poses(self, i: int, exposure_time: float, k: int) -> np.ndarray:
        """``k`` poses ``T_w_c`` evenly spread over the exposure of frame ``i`` (centred on the
        frame time; the sensor's motion blur)."""
        if k <= 1:
            return self.poses[i][None]
        half = 0.5 * exposure_time
        t = np.clip(self.times[i] + np.linspace(-half, half, k), 0.0, self.flight.duration)
        return self.flight.poses(t)


def reference_xy(flight_cfg) -> tuple[float, float]:
    """The point whose terrain height the flight's altitudes refer to."""
    ref = flight_cfg.start if flight_cfg.type == "rotation" else flight_cfg.center
    return float(ref[0]), float(ref[1])


def check_flight(model: TerrainModel, flight: Flight, clearance: float, rate_hz: float) -> None:
    """Reject a flight that leaves the detailed terrain or comes closer than ``clearance`` to
    the terrain or a rock (checked at ``_CHECK_OVERSAMPLING`` times the frame rate)."""
    t = frame_times(flight.duration, rate_hz * _CHECK_OVERSAMPLING)
    p = flight.poses(t)[:, :3, 3]
    half = model.heightfield.half_extent
    out = np.flatnonzero(np.max(np.abs(p[:, :2]), axis=1) > half)
    if out.size:
        k = out[0]
        raise ConfigError(
            f"flight: leaves the detailed terrain (|x|, |y| <= {half:g} m) at t={t[k]:.2f} s "
            f"(x={p[k, 0]:.1f}, y={p[k, 1]:.1f}); move it or enlarge terrain.extent")
    ground = model.surface_height(p[:, 0], p[:, 1])
    height = p[:, 2] - ground
    bad = np.flatnonzero(height < clearance)
    if bad.size:
        k = bad[np.argmin(height[bad])]
        raise ConfigError(
            f"flight: goes below the terrain clearance at t={t[k]:.2f} s: the camera at "
            f"(x={p[k, 0]:.1f}, y={p[k, 1]:.1f}, z={p[k, 2]:.2f}) is {height[k]:.2f} m above "
            f"the surface (flight.clearance = {clearance:g} m); raise the altitude or move "
            "the flight")


def make_plan(scenario) -> RunPlan:
    """Terrain, flight, frames and drops for ``scenario``, checked (see module doc)."""
    model = make_terrain_model(scenario.terrain, scenario.seed)
    x0, y0 = reference_xy(scenario.flight)
    ground = float(model.ground_height(x0, y0))
    if not np.isfinite(ground):
        raise ConfigError(f"flight: reference point ({x0:g}, {y0:g}) is outside the terrain")
    flight = make_flight(scenario.flight, ground, scenario.seed)
    check_flight(model, flight, scenario.flight.clearance, scenario.camera.rate_hz)
    rate = scenario.camera.rate_hz
    n = scenario.n_frames
    index = np.arange(n, dtype=np.int64)
    timestamps_ns = np.round(index * (1e9 / rate)).astype(np.int64)
    times = frame_times(scenario.flight.duration, rate)
    assert len(times) == n
    poses = flight.poses(times)
    dropped = frame_drops(n, scenario.frame_drops, scenario.seed)
    return RunPlan(scenario, model, flight, times, timestamps_ns, poses, dropped)
