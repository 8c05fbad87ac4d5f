"""Seamlessly tiling surface texture in pure numpy. The scene maps the same tile onto the
ground at several scales (``terrain.texture_scales``), which gives the fine, strongly
self-similar, repetitive texture of Martian regolith that defeats descriptor matching.

Channels of the returned (S, S, 4) float32 image (u = column / S, v = row / S):
R, G = slope of the micro-relief dh/du, dh/dv normalised to unit RMS (the shader tilts the
normal by these slopes: cheaper than a bump node and exactly view-independent),
B = albedo modulation in [0, 1] (grain and pebbles), A = micro-relief height in [0, 1].
The slopes come first so that the shader can rotate (R, G, B) as one vector about z.
"""

from __future__ import annotations

import numpy as np

from simulation.terrain.heightfield import power_law_sizes
from simulation.terrain.noise import tileable_texture


def _splat_pebbles(size: int, rng: np.random.Generator, count: int):
    """Wrapped, randomly sized dome-shaped pebbles: (height, albedo offset, mask)."""
    height = np.zeros((size, size))
    albedo = np.zeros((size, size))
    mask = np.zeros((size, size))
    radii = power_law_sizes(rng, count, size / 80.0, size / 20.0, 2.2)
    for r in radii:
        c = rng.uniform(0, size, 2)
        stretch = rng.uniform(0.6, 1.0)
        ang = rng.uniform(0, np.pi)
        R = int(np.ceil(r)) + 1
        iy = np.arange(int(c[1]) - R, int(c[1]) + R + 1)
        ix = np.arange(int(c[0]) - R, int(c[0]) + R + 1)
        gx, gy = np.meshgrid(ix - c[0], iy - c[1])
        u = (np.cos(ang) * gx + np.sin(ang) * gy) / r
        v = (-np.sin(ang) * gx + np.cos(ang) * gy) / (r * stretch)
        q = np.clip(1.0 - (u * u + v * v), 0.0, None)
        dome = np.sqrt(q) * r / (size / 40.0)
        rows, cols = np.ix_(iy % size, ix % size)
        sel = dome > height[rows, cols]
        height[rows, cols] = np.where(sel, dome, height[rows, cols])
        tone = rng.uniform(-0.5, 0.35)
        albedo[rows, cols] = np.where(sel & (q > 0), tone, albedo[rows, cols])
        mask[rows, cols] = np.maximum(mask[rows, cols], (q > 0).astype(float))
    return height, albedo, mask


def periodic_gradient(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact spectral derivatives (d/du along columns, d/dv along rows) of a periodic image
    over a unit tile."""
    n = h.shape[0]
    k = 2j * np.pi * np.fft.fftfreq(n) * n
    H = np.fft.fft2(h)
    return np.real(np.fft.ifft2(H * k[None, :])), np.real(np.fft.ifft2(H * k[:, None]))


#: The tile holds wavelengths from 1/4 to 1/FINEST_CYCLES of its size (band-limited), so a
#: layer of tile size s has no detail finer than s / FINEST_CYCLES; the shader fades a layer
#: out (to its mean) as that wavelength shrinks from 2 to 1 pixel, like a mip-map would.
COARSEST_CYCLES = 4.0
FINEST_CYCLES = 40.0


def _band_limit(img: np.ndarray) -> np.ndarray:
    """Keep (smoothly) the wavelengths between 1/FINEST_CYCLES and 1/COARSEST_CYCLES."""
    n = img.shape[0]
    k = np.fft.fftfreq(n) * n
    kk = np.sqrt(k[:, None] ** 2 + k[None, :] ** 2)
    low = np.exp(-0.5 * (kk / (0.75 * FINEST_CYCLES)) ** 4)
    high = 1.0 - np.exp(-0.5 * (kk / COARSEST_CYCLES) ** 4)
    return np.real(np.fft.ifft2(np.fft.fft2(img) * low * high))


def _pack_tile(height: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """The (S, S, 4) tile of a periodic micro-relief and albedo (module docstring)."""
    gu, gv = periodic_gradient(height)
    rms = np.sqrt(np.mean(gu**2 + gv**2) / 2.0)
    out = np.empty((*height.shape, 4), dtype=np.float32)
    out[..., 0] = gu / rms
    out[..., 1] = gv / rms
    out[..., 2] = np.clip(albedo, 0.0, 1.0)
    out[..., 3] = (height - height.min()) / max(np.ptp(height), 1e-9)
    return out


def make_surface_texture(seed: int, size: int = 256) -> np.ndarray:
    """The tiling texture (see module docstring), deterministic in ``seed``."""
    rng = np.random.default_rng([seed, 0x7E5])
    grain = tileable_texture(size, 1.2, rng, min_period=2.0, min_cycles=COARSEST_CYCLES)
    relief = tileable_texture(size, 1.4, rng, min_period=2.0, min_cycles=COARSEST_CYCLES)
    p_height, p_albedo, _ = _splat_pebbles(size, rng, count=size * size // 300)
    albedo = _band_limit(0.6 * (grain - 0.5) + 0.35 * p_albedo)
    height = _band_limit(0.6 * relief + 0.6 * np.clip(p_height, 0.0, 1.0))
    albedo = albedo / max(np.percentile(np.abs(albedo), 99.5), 1e-9)
    albedo = 0.5 + 0.5 * (albedo - albedo.mean())  # mean exactly 0.5: the shader's fade target
    return _pack_tile(height, albedo)


#: Ripple crests per ripple tile (the tile is RIPPLES_PER_TILE wavelengths wide).
RIPPLES_PER_TILE = 8
#: Finest detail of the ripple tile, in cycles per tile (grain on the ripples).
RIPPLE_FINEST_CYCLES = 48.0


def make_ripple_texture(seed: int, size: int = 256) -> np.ndarray:
    """Tiling aeolian-ripple tile, channels as :func:`make_surface_texture`.

    Crests run along v (rows vary along u = the wind direction): an asymmetric profile (gentle
    stoss slope, steeper lee slope) of phase 2 pi RIPPLES_PER_TILE u, the crest lines bent,
    forked and broken by a tileable noise phase so that neighbouring crests are alike but not
    identical, plus fine grain; brighter coarse grains on the crests (albedo follows height).
    """
    rng = np.random.default_rng([seed, 0x819])
    u = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(u, u)
    bend = tileable_texture(size, 2.2, rng, min_period=8.0, min_cycles=1.0) - 0.5
    wiggle = tileable_texture(size, 1.6, rng, min_period=4.0, min_cycles=4.0) - 0.5
    phase = 2.0 * np.pi * (RIPPLES_PER_TILE * uu + 1.2 * bend + 0.35 * wiggle)
    profile = np.sin(phase) + 0.35 * np.sin(2.0 * phase) + 0.08 * np.sin(3.0 * phase)
    strength = 0.55 + 0.45 * tileable_texture(size, 2.0, rng, min_period=8.0, min_cycles=2.0)
    height = profile * strength
    grain = tileable_texture(size, 1.0, rng, min_period=2.0, min_cycles=COARSEST_CYCLES)
    k = np.fft.fftfreq(size) * size
    kk = np.sqrt(k[:, None] ** 2 + k[None, :] ** 2)
    low = np.exp(-0.5 * (kk / (0.75 * RIPPLE_FINEST_CYCLES)) ** 4)
    band = lambda img: np.real(np.fft.ifft2(np.fft.fft2(img) * low))  # noqa: E731
    height = band(height + 0.25 * (grain - 0.5))
    albedo = band(0.6 * height / np.max(np.abs(height)) + 0.5 * (grain - 0.5))
    albedo = albedo / max(np.percentile(np.abs(albedo - albedo.mean()), 99.5), 1e-9)
    albedo = 0.5 + 0.5 * (albedo - albedo.mean())
    return _pack_tile(height, albedo)
