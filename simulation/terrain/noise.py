"""Seeded, vectorised 2-D gradient noise in pure numpy (no ``bpy``).

The same functions build the rendered heightfield and answer height queries (below-ground
checks), so both always agree. Values are deterministic for a given seed on any machine.
"""

from __future__ import annotations

import numba
import numpy as np

_M1 = 0x9E3779B97F4A7C15
_M2 = 0xC2B2AE3D27D4EB4F


@numba.njit(cache=True)
def _hash_angle(ix: np.int64, iy: np.int64, salt: np.uint64) -> float:
    """Angle in [0, 2 pi) from a 64-bit hash (splitmix64 finaliser) of a lattice point."""
    h = (np.uint64(ix) * np.uint64(_M1)) ^ (np.uint64(iy) * np.uint64(_M2)) ^ salt
    h ^= h >> np.uint64(30)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(27)
    h *= np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    return float(h >> np.uint64(11)) * (2.0 * np.pi / 2.0**53)


@numba.njit(cache=True)
def _perlin_flat(x: np.ndarray, y: np.ndarray, salt: np.uint64, out: np.ndarray) -> None:
    for n in range(x.size):
        fx, fy = np.floor(x[n]), np.floor(y[n])
        ix, iy = np.int64(fx), np.int64(fy)
        dx, dy = x[n] - fx, y[n] - fy
        u = dx * dx * dx * (dx * (dx * 6.0 - 15.0) + 10.0)  # quintic fade: C2 noise
        v = dy * dy * dy * (dy * (dy * 6.0 - 15.0) + 10.0)
        total = 0.0
        for ox in range(2):
            for oy in range(2):
                a = _hash_angle(ix + ox, iy + oy, salt)
                wx = u if ox else 1.0 - u
                wy = v if oy else 1.0 - v
                total += wx * wy * (np.cos(a) * (dx - ox) + np.sin(a) * (dy - oy))
        out[n] = total


def _salt(seed: int) -> np.uint64:
    return np.uint64((seed * 0x165667B19E3779F9 + 0x27D4EB2F165667C5) & 0xFFFFFFFFFFFFFFFF)


def perlin(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Gradient noise with unit lattice spacing, roughly in [-0.7, 0.7], zero at lattice
    points; quintic interpolation makes it C2 (continuous curvature of the terrain)."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    out = np.empty(x.shape)
    _perlin_flat(np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel(), _salt(seed),
                 out.reshape(-1))
    return out


def fbm(x, y, seed: int, octaves: int, lacunarity: float = 2.0, gain: float = 0.5) -> np.ndarray:
    """Fractal sum of ``octaves`` noise layers, normalised so the amplitude is ~[-1, 1]."""
    total = np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
    amp, freq, norm = 1.0, 1.0, 0.0
    for o in range(octaves):
        # A per-octave offset and rotation avoid aligned lattice artefacts between octaves.
        c, s = np.cos(0.7 * o + 0.3), np.sin(0.7 * o + 0.3)
        xr, yr = c * x - s * y, s * x + c * y
        total += amp * perlin(xr * freq + 17.31 * o, yr * freq - 9.17 * o, seed + 101 * o)
        norm += amp
        amp *= gain
        freq *= lacunarity
    return total / (0.7 * norm)


def ridged(x, y, seed: int, octaves: int) -> np.ndarray:
    """Ridged multifractal in ~[0, 1]: sharp crests where the noise crosses zero."""
    total = np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
    amp, freq, norm = 1.0, 1.0, 0.0
    for o in range(octaves):
        r = 1.0 - np.abs(perlin(x * freq + 3.7 * o, y * freq + 5.3 * o, seed + 977 * o)) / 0.7
        total += amp * r * r
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def tileable_texture(size: int, beta: float, rng: np.random.Generator,
                     min_period: float = 1.5, min_cycles: float = 1.0) -> np.ndarray:
    """Periodic (seamlessly tiling) 1/f^beta noise image of shape (size, size) in [0, 1].

    Spectral synthesis with random phases; wavelengths shorter than ``min_period`` texels are
    removed so bilinear lookups do not alias, and frequencies below ``min_cycles`` per tile
    so the tile period itself does not show as a lattice.
    """
    k = np.fft.fftfreq(size) * size
    kk = np.sqrt(k[:, None] ** 2 + k[None, :] ** 2)
    amp = np.zeros_like(kk)
    valid = (kk >= min_cycles) & (kk <= size / min_period)
    amp[valid] = kk[valid] ** (-beta / 2.0 - 0.5)
    phase = rng.uniform(0.0, 2.0 * np.pi, kk.shape)
    field = np.real(np.fft.ifft2(amp * np.exp(1j * phase)))
    lo, hi = np.percentile(field, [0.5, 99.5])
    return np.clip((field - lo) / (hi - lo), 0.0, 1.0)
