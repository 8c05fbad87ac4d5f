"""Flights (pure numpy): camera convention, smoothness, the defining motion of each type,
frame drops."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from granite.errors import ConfigError
from simulation import flights
from simulation.scenario import (
    AggressiveFlight,
    FrameDropsConfig,
    HoverFlight,
    RotationFlight,
    SpiralFlight,
    SurveyFlight,
)

ALL = [SpiralFlight(), RotationFlight(), HoverFlight(), SurveyFlight(), AggressiveFlight()]


def test_camera_rotation_is_cv_convention():
    # Facing +x (alpha = 0), level: z forward = +x, x right = -y (right of +x when z is up),
    # y down = -z.
    R = flights.camera_rotation(0.0, 0.0, 0.0)[0]
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)
    # Nadir: looks down; positive roll turns the image's right side down.
    R = flights.camera_rotation(0.3, np.pi / 2, 0.0)[0]
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-12)
    R = flights.camera_rotation(0.0, 0.0, 0.2)[0]
    assert R[2, 0] < 0  # the x axis (image right) points downwards


@pytest.mark.parametrize("cfg", ALL, ids=lambda c: c.type)
def test_poses_are_rigid(cfg):
    f = flights.make_flight(cfg, ground=1.5, seed=3)
    T = f.poses(np.linspace(0, f.duration, 200))
    R = T[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(T[:, 3], np.broadcast_to([0, 0, 0, 1.0], (200, 4)))


def _third_difference(f, n: int) -> np.ndarray:
    T = f.poses(np.linspace(0, f.duration, n))
    series = np.concatenate([T[:, :3, 3], T[:, :3, 2], T[:, :3, 0]], axis=1)
    return np.max(np.abs(np.diff(series, n=3, axis=0)), axis=0)


@pytest.mark.parametrize("cfg", ALL, ids=lambda c: c.type)
def test_motion_is_smooth(cfg):
    """Continuous acceleration (of position and of the camera axes): halving the time step
    divides the largest third difference by ~8 (bounded jerk: dt^3). A jump in acceleration
    would divide it by only 4 (jump x dt^2), a jump in velocity by 2."""
    f = flights.make_flight(cfg, ground=0.0, seed=5)
    coarse, fine = _third_difference(f, 2001), _third_difference(f, 4001)
    moving = coarse > 1e-12
    assert np.all(coarse[moving] / fine[moving] > 6.5), (cfg.type, coarse / fine)


def test_smoothness_check_detects_an_acceleration_jump():
    """The criterion above fails on a flight whose acceleration jumps (a parabola glued to a
    straight line)."""
    def position(t):
        t = np.asarray(t, dtype=np.float64)
        x = np.where(t < 5.0, 0.5 * t**2, 12.5 + 5.0 * (t - 5.0))
        return np.stack([x, 0 * t, 0 * t + 3.0], axis=-1)

    def attitude(t):
        z = np.zeros_like(np.asarray(t, dtype=np.float64))
        return z, z + 0.5, z

    f = flights.Flight("test", 10.0, position, attitude)
    coarse, fine = _third_difference(f, 2001), _third_difference(f, 4001)
    assert coarse[0] / fine[0] < 5.0


def test_spiral_constant_speed_up_and_down():
    cfg = SpiralFlight(duration=40.0, radius=12.0, altitude_min=4.0, altitude_max=40.0, speed=4.0)
    f = flights.make_flight(cfg, ground=2.0)
    t = np.linspace(0, cfg.duration, 8001)
    p = f.poses(t)[:, :3, 3]
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / (t[1] - t[0])
    np.testing.assert_allclose(speed, 4.0, rtol=1e-4)
    r = np.hypot(p[:, 0] - cfg.center[0], p[:, 1] - cfg.center[1])
    np.testing.assert_allclose(r, 12.0, atol=1e-9)
    np.testing.assert_allclose(p[[0, -1], 2], 6.0, atol=1e-9)
    assert abs(p[4000, 2] - 42.0) < 1e-6  # top of the climb at half time


def test_spiral_too_slow_for_climb_is_refused():
    with pytest.raises(ConfigError, match="too low for the climb"):
        flights.make_flight(SpiralFlight(duration=5.0, altitude_min=0, altitude_max=40, speed=3))


def test_rotation_turns_in_place():
    cfg = RotationFlight(duration=20.0, rotation_duration=8.0, yaw_sweep=270.0, pitch_sweep=10.0,
                         leg_length=6.0, heading=30.0)
    f = flights.make_flight(cfg, ground=0.0)
    leg = (cfg.duration - cfg.rotation_duration) / 2
    t = np.linspace(leg, leg + cfg.rotation_duration, 300)
    T = f.poses(t)
    np.testing.assert_allclose(T[:, :3, 3] - T[0, :3, 3], 0.0, atol=1e-12)  # centre fixed
    fwd = T[:, :3, 2]
    yaw = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    assert np.isclose(yaw[0] - yaw[-1], np.deg2rad(270.0), atol=1e-9)  # clockwise sweep
    pitch = np.rad2deg(-np.arcsin(fwd[:, 2]))
    assert np.isclose(pitch.max() - cfg.pitch, 10.0, atol=0.05)
    # the first leg goes along the compass heading 30 deg (x east, y north)
    p = f.poses(np.array([0.0, leg]))[:, :3, 3]
    d = (p[1] - p[0]) / np.linalg.norm(p[1] - p[0])
    np.testing.assert_allclose(d[:2], [np.sin(np.deg2rad(30)), np.cos(np.deg2rad(30))], atol=1e-12)


def test_hover_stays_close():
    cfg = HoverFlight(duration=30.0, amplitude=0.3, altitude=5.0)
    p = flights.make_flight(cfg, ground=1.0, seed=2).poses(np.linspace(0, 30, 500))[:, :3, 3]
    assert np.max(np.linalg.norm(p - p[0], axis=1)) < 2 * 0.3 * np.sqrt(2.25) + 1e-9
    np.testing.assert_allclose(p[0], [cfg.center[0], cfg.center[1], 6.0], atol=1e-12)


def test_survey_covers_the_area_with_parallel_legs():
    cfg = SurveyFlight(duration=80.0, width=30.0, length=40.0, spacing=10.0, heading=0.0)
    p = flights.make_flight(cfg, ground=0.0).poses(np.linspace(0, 80, 4000))[:, :3, 3]
    # heading 0 = legs along y (north), legs spread across x
    assert np.ptp(p[:, 1]) >= 40.0 - 1e-6 and np.ptp(p[:, 0]) >= 30.0 - 1e-6
    assert np.ptp(p[:, 2]) < 1e-6


def test_aggressive_banks_into_turns_and_stays_inside():
    cfg = AggressiveFlight(duration=20.0, speed=8.0, radius=25.0, bank=1.0)
    f = flights.make_flight(cfg, ground=0.0, seed=9)
    t = np.linspace(0.5, 19.5, 2000)
    T = f.poses(t)
    p = T[:, :3, 3]
    assert np.max(np.hypot(p[:, 0] - cfg.center[0], p[:, 1] - cfg.center[1])) < 1.5 * cfg.radius
    dt = t[1] - t[0]
    v = np.gradient(p, dt, axis=0)
    a = np.gradient(v, dt, axis=0)
    right = T[:, :3, 0]
    a_right = np.sum(a[:, :2] * np.stack([np.sin(np.arctan2(v[:, 1], v[:, 0])),
                                          -np.cos(np.arctan2(v[:, 1], v[:, 0]))], 1), axis=1)
    strong = np.abs(a_right) > 3.0
    assert strong.sum() > 20
    # accelerating to the right -> right side of the image down (x axis has negative z)
    assert np.all(np.sign(right[strong, 2]) == -np.sign(a_right[strong]))
    tilt = np.rad2deg(np.arccos(np.clip(-T[:, 2, 1], -1, 1)))  # y axis vs straight down
    assert tilt.max() < 90.0
    # same seed, same flight; another seed, another flight
    np.testing.assert_array_equal(f.poses(t), flights.make_flight(cfg, 0.0, seed=9).poses(t))
    assert not np.allclose(f.poses(t), flights.make_flight(cfg, 0.0, seed=10).poses(t))


def test_frame_drops_are_seeded_bursts():
    cfg = FrameDropsConfig(probability=0.05, min_burst=3, max_burst=6, keep_first=25)
    m = flights.frame_drops(2000, cfg, seed=1)
    np.testing.assert_array_equal(m, flights.frame_drops(2000, cfg, seed=1))
    assert not np.array_equal(m, flights.frame_drops(2000, cfg, seed=2))
    assert not m[:25].any()
    edges = np.diff(np.concatenate([[0], m.astype(int), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    lengths = stops - starts
    assert len(lengths) > 20
    assert lengths.min() >= 3 and lengths[:-1].max() <= 6  # the last burst may be cut off
    assert not flights.frame_drops(100, dataclasses.replace(cfg, probability=0.0), 1).any()


def test_frame_times_include_both_ends():
    t = flights.frame_times(6.0, 20.0)
    assert len(t) == 121 and t[-1] == 6.0 and t[1] == 0.05
