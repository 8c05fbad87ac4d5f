"""Camera flights in pure numpy: continuous-time poses ``T_w_c`` (computer-vision camera:
x right, y down, z forward; world z up, metres).

Every flight is smooth: positions and attitudes are built from minimum-jerk blends, sinusoids
or quintic splines, so velocity and acceleration are continuous. A flight is evaluated at any
time (``Flight.poses(t)``), which also serves motion blur. Altitudes are metres above
``ground`` (the terrain height at the flight's reference point, supplied by the caller).

Attitude angles: ``alpha`` = direction the camera faces, counter-clockwise from world +x
(compass heading h corresponds to alpha = 90 deg - h); ``pitch`` = look-down angle below the
horizon; ``roll`` = rotation about the optical axis, positive = image right side down.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_interp_spline

from granite.errors import ConfigError

_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_G = 9.81  # banking reference acceleration (m/s^2)
_MAX_TILT = np.deg2rad(40.0)  # banking saturates smoothly at this tilt


@dataclass(frozen=True)
class Flight:
    """A camera trajectory defined for ``0 <= t <= duration``.

    ``position(t) -> (N, 3)``; ``attitude(t) -> (alpha, pitch, roll)`` each ``(N,)`` radians.
    """

    kind: str
    duration: float
    position: Callable[[np.ndarray], np.ndarray]
    attitude: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

    def poses(self, t: np.ndarray | float) -> np.ndarray:
        """``(N, 4, 4)`` camera poses ``T_w_c`` at times ``t`` (seconds)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        T = np.zeros((t.size, 4, 4))
        T[:, 3, 3] = 1.0
        alpha, pitch, roll = self.attitude(t)
        T[:, :3, :3] = camera_rotation(alpha, pitch, roll)
        T[:, :3, 3] = self.position(t)
        return T


def frame_times(duration: float, rate_hz: float) -> np.ndarray:
    """Frame times ``i / rate_hz`` for ``i = 0 .. floor(duration * rate_hz)`` (seconds)."""
    n = int(np.floor(duration * rate_hz + 1e-9)) + 1
    return np.arange(n, dtype=np.float64) / rate_hz


def camera_rotation(alpha, pitch, roll) -> np.ndarray:
    """``(N, 3, 3)`` rotations ``R_w_c`` of a CV camera facing ``alpha`` (CCW from +x),
    tilted ``pitch`` below the horizon and rolled by ``roll`` (radians)."""
    a, p, r = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (alpha, pitch, roll))
    a, p, r = np.broadcast_arrays(a, p, r)
    z = np.stack([np.cos(a) * np.cos(p), np.sin(a) * np.cos(p), -np.sin(p)], axis=-1)
    x0 = np.stack([np.sin(a), -np.cos(a), np.zeros_like(a)], axis=-1)
    y0 = np.cross(z, x0)
    c, s = np.cos(r)[..., None], np.sin(r)[..., None]
    x = c * x0 + s * y0
    y = -s * x0 + c * y0
    return np.stack([x, y, z], axis=-1)


def min_jerk(u: np.ndarray) -> np.ndarray:
    """Quintic 0 -> 1 blend on ``u`` in [0, 1] with zero velocity and acceleration at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 + u * (-15.0 + 6.0 * u))


def _heading_to_alpha(heading_deg: float) -> float:
    return np.deg2rad(90.0 - heading_deg)


def _err(message: str) -> ConfigError:
    return ConfigError(f"flight: {message}")


# ----------------------------------------------------------------------------- spiral


def spiral(cfg, ground: float = 0.0) -> Flight:
    """Helix around ``center``: up from ``altitude_min`` to ``altitude_max`` and down again
    (raised-cosine altitude profile) at constant path speed, counter-clockwise."""
    T, R, v = cfg.duration, cfg.radius, cfg.speed
    dz = cfg.altitude_max - cfg.altitude_min
    vz_max = dz * np.pi / T
    if vz_max >= v:
        raise _err(f"speed {v:g} m/s is too low for the climb (needs > {vz_max:.3g} m/s)")
    cx, cy = cfg.center
    z0 = ground + cfg.altitude_min
    w = 2.0 * np.pi / T

    def vz(t):
        return 0.5 * dz * w * np.sin(w * t)

    def angle(t):
        # phi(t) = int_0^t sqrt(v^2 - vz^2) / R ds, by Gauss-Legendre (integrand is analytic).
        t = np.asarray(t, dtype=np.float64)
        s = 0.5 * t[..., None] * (_GL_X + 1.0)
        return 0.5 * t * np.sum(_GL_W * np.sqrt(v * v - vz(s) ** 2), axis=-1) / R

    def position(t):
        phi = angle(t)
        z = z0 + 0.5 * dz * (1.0 - np.cos(w * t))
        return np.stack([cx + R * np.cos(phi), cy + R * np.sin(phi), z], axis=-1)

    def attitude(t):
        alpha = angle(t) + np.pi / 2 + np.deg2rad(cfg.yaw_offset)
        return alpha, np.full_like(alpha, np.deg2rad(cfg.pitch)), np.zeros_like(alpha)

    return Flight("spiral", T, position, attitude)


# ----------------------------------------------------------------------------- rotation


def rotation(cfg, ground: float = 0.0) -> Flight:
    """Straight leg, rotation in place about the camera centre (yaw sweep plus a pitch nod),
    straight leg in the new heading. Each phase starts and ends at rest."""
    T = cfg.duration
    Tr = cfg.rotation_duration
    Tl = 0.5 * (T - Tr)
    a0 = _heading_to_alpha(cfg.heading)
    sweep = -np.deg2rad(cfg.yaw_sweep)  # compass degrees clockwise -> alpha decreases
    a1 = a0 + sweep
    p0 = np.array([cfg.start[0], cfg.start[1], ground + cfg.altitude])
    p1 = p0 + cfg.leg_length * np.array([np.cos(a0), np.sin(a0), 0.0])
    d1 = np.array([np.cos(a1), np.sin(a1), 0.0])
    pitch0, nod = np.deg2rad(cfg.pitch), np.deg2rad(cfg.pitch_sweep)

    def position(t):
        t = np.asarray(t, dtype=np.float64)[..., None]
        leg1 = p0 + (p1 - p0) * min_jerk(t / Tl)
        leg2 = p1 + cfg.leg_length * d1 * min_jerk((t - Tl - Tr) / Tl)
        return np.where(t <= Tl + Tr, leg1, leg2)

    def attitude(t):
        t = np.asarray(t, dtype=np.float64)
        u = min_jerk((t - Tl) / Tr)
        alpha = a0 + sweep * u
        pitch = pitch0 + nod * np.sin(2.0 * np.pi * u)
        return alpha, pitch, np.zeros_like(alpha)

    return Flight("rotation", T, position, attitude)


# ----------------------------------------------------------------------------- hover


def hover(cfg, ground: float = 0.0, seed: int = 0) -> Flight:
    """Station keeping: sums of slow sinusoids (seeded phases) in position and yaw."""
    rng = np.random.default_rng([seed, 0x4F0])
    ph = rng.uniform(0.0, 2.0 * np.pi, 4)
    P, A = cfg.period, cfg.amplitude
    c = np.array([cfg.center[0], cfg.center[1], ground + cfg.altitude])
    a0 = _heading_to_alpha(cfg.heading)
    ya = np.deg2rad(cfg.yaw_amplitude)

    def position(t):
        t = np.asarray(t, dtype=np.float64)
        k = 2.0 * np.pi * t
        off = np.stack([A * np.sin(k / P + ph[0]) - A * np.sin(ph[0]),
                        A * np.sin(k / (1.37 * P) + ph[1]) - A * np.sin(ph[1]),
                        0.5 * A * (np.sin(k / (0.71 * P) + ph[2]) - np.sin(ph[2]))], axis=-1)
        return c + off

    def attitude(t):
        t = np.asarray(t, dtype=np.float64)
        alpha = a0 + ya * np.sin(2.0 * np.pi * t / (1.9 * P) + ph[3])
        return alpha, np.full_like(alpha, np.deg2rad(cfg.pitch)), np.zeros_like(alpha)

    return Flight("hover", cfg.duration, position, attitude)


# ----------------------------------------------------------------------------- splines


def _tilt(ratio: np.ndarray) -> np.ndarray:
    """Quadrotor tilt atan(a / g), smoothly saturated at ``_MAX_TILT``."""
    return _MAX_TILT * np.tanh(np.arctan(ratio) / _MAX_TILT)


def _spline_flight(kind: str, waypoints: np.ndarray, duration: float, pitch_deg: float,
                   bank: float) -> Flight:
    """Quintic (C4) spline through ``waypoints`` (M, 3), timed by chord length over
    ``duration``, entering and leaving along the first / last chord at the mean speed.
    The camera faces the horizontal velocity; ``bank`` tilts it like a quadrotor."""
    chords = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    if np.any(chords < 1e-6):
        raise _err("consecutive waypoints coincide")
    knots = np.concatenate([[0.0], np.cumsum(chords)])
    speed = knots[-1] / duration
    knots = knots / speed
    v0 = (waypoints[1] - waypoints[0]) / chords[0] * speed
    v1 = (waypoints[-1] - waypoints[-2]) / chords[-1] * speed
    zero = np.zeros(3)
    spline = make_interp_spline(knots, waypoints, k=5,
                                bc_type=([(1, v0), (2, zero)], [(1, v1), (2, zero)]))
    vel, acc = spline.derivative(1), spline.derivative(2)
    pitch0 = np.deg2rad(pitch_deg)

    def position(t):
        return spline(np.clip(np.asarray(t, dtype=np.float64), 0.0, duration))

    def attitude(t):
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, duration)
        v, a = vel(t), acc(t)
        alpha = np.arctan2(v[..., 1], v[..., 0])
        fwd = np.stack([np.cos(alpha), np.sin(alpha)], axis=-1)
        right = np.stack([np.sin(alpha), -np.cos(alpha)], axis=-1)
        a_fwd = np.sum(a[..., :2] * fwd, axis=-1)
        a_right = np.sum(a[..., :2] * right, axis=-1)
        pitch = pitch0 + _tilt(bank * a_fwd / _G)
        roll = _tilt(bank * a_right / _G)
        return alpha, pitch, roll

    return Flight(kind, duration, position, attitude)


def survey(cfg, ground: float = 0.0) -> Flight:
    """Lawnmower over a ``length`` x ``width`` rectangle; legs ``spacing`` apart, flown in
    alternating directions and joined by smooth turns."""
    a0 = _heading_to_alpha(cfg.heading)
    d = np.array([np.cos(a0), np.sin(a0)])
    side = np.array([np.sin(a0), -np.cos(a0)])  # to the right of the first leg
    n_legs = int(np.floor(cfg.width / cfg.spacing + 1e-9)) + 1
    if n_legs < 2:
        raise _err("survey needs width >= spacing (at least two legs)")
    per_leg = max(2, int(np.ceil(cfg.length / cfg.spacing)) + 1)
    c = np.asarray(cfg.center, dtype=np.float64)
    pts = []
    for k in range(n_legs):
        across = (k - (n_legs - 1) / 2) * cfg.spacing
        along = np.linspace(-cfg.length / 2, cfg.length / 2, per_leg)
        if k % 2:
            along = along[::-1]
        for s in along:
            xy = c + s * d + across * side
            pts.append([xy[0], xy[1], ground + cfg.altitude])
    return _spline_flight("survey", np.array(pts), cfg.duration, cfg.pitch, bank=0.0)


def aggressive(cfg, ground: float = 0.0, seed: int = 0) -> Flight:
    """Seeded random walk of waypoints (sharp turns, altitude changes) inside ``radius`` of
    ``center``, flown fast on a quintic spline with quadrotor-like banking."""
    rng = np.random.default_rng([seed, 0xA66])
    c = np.asarray(cfg.center, dtype=np.float64)
    n = max(3, int(np.ceil(cfg.duration * cfg.speed / cfg.turn_distance)) + 1)
    heading = rng.uniform(0, 2 * np.pi)
    xy = c + rng.uniform(-0.3, 0.3, 2) * cfg.radius
    pts = []
    for _ in range(n):
        z = ground + rng.uniform(cfg.altitude_min, cfg.altitude_max)
        pts.append([xy[0], xy[1], z])
        for _attempt in range(64):
            turn = rng.choice([-1.0, 1.0]) * rng.uniform(np.deg2rad(40), np.deg2rad(110))
            step = cfg.turn_distance * rng.uniform(0.7, 1.3)
            h = heading + turn
            nxt = xy + step * np.array([np.cos(h), np.sin(h)])
            if np.linalg.norm(nxt - c) <= cfg.radius:
                break
        else:  # head back towards the centre
            h = np.arctan2(*(c - xy)[::-1])
            nxt = xy + step * np.array([np.cos(h), np.sin(h)])
        heading, xy = h, nxt
    return _spline_flight("aggressive", np.array(pts), cfg.duration, cfg.pitch, bank=cfg.bank)


def make_flight(cfg, ground: float = 0.0, seed: int = 0) -> Flight:
    """The :class:`Flight` for a flight config of :mod:`simulation.scenario`."""
    if cfg.type == "spiral":
        return spiral(cfg, ground)
    if cfg.type == "rotation":
        return rotation(cfg, ground)
    if cfg.type == "hover":
        return hover(cfg, ground, seed)
    if cfg.type == "survey":
        return survey(cfg, ground)
    if cfg.type == "aggressive":
        return aggressive(cfg, ground, seed)
    raise _err(f"unknown flight type {cfg.type!r}")


def frame_drops(n: int, cfg, seed: int) -> np.ndarray:
    """``(n,)`` bool mask of dropped frames: after ``keep_first`` frames, a burst of
    ``min_burst..max_burst`` frames starts with probability ``probability`` per frame; at
    least one frame is kept between bursts. Deterministic in ``seed``."""
    mask = np.zeros(n, dtype=bool)
    if cfg.probability <= 0.0:
        return mask
    rng = np.random.default_rng([seed, 0xD40])
    i = cfg.keep_first
    while i < n:
        if rng.random() < cfg.probability:
            length = int(rng.integers(cfg.min_burst, cfg.max_burst + 1))
            mask[i:i + length] = True
            i += length + 1
        else:
            i += 1
    return mask
