"""The terrain surface in pure numpy: multi-octave relief with ridges and smooth plains, and
craters with raised rims, sampled on a tensor-product grid (uniform ``resolution`` over the
central ``extent`` square, geometrically coarser out to ``far_extent``).

The rendered mesh is exactly this grid, each cell split into the triangles
(i, j)-(i+1, j)-(i+1, j+1) and (i, j)-(i+1, j+1)-(i, j+1); :meth:`Heightfield.height_at`
interpolates on the same triangles, so it returns the height of the rendered surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulation.terrain.noise import fbm, ridged, smoothstep


def grid_axis(extent: float, resolution: float, far_extent: float, growth: float = 1.25) -> np.ndarray:
    """Sorted 1-D grid coordinates: uniform in [-extent/2, extent/2], then steps growing by
    ``growth`` until ``far_extent``."""
    n = int(round(extent / resolution))
    half = 0.5 * n * resolution
    inner = np.linspace(-half, half, n + 1)
    outer, pos, step = [], half, resolution
    while pos < far_extent:
        step *= growth
        pos += step
        outer.append(pos)
    outer = np.array(outer)
    return np.concatenate([-outer[::-1], inner, outer])


@dataclass(frozen=True)
class Craters:
    """Crater centres (K, 2), diameters (K,), depths (K,) and rim heights (K,) in metres."""

    centers: np.ndarray
    diameters: np.ndarray
    depths: np.ndarray
    rims: np.ndarray


def power_law_sizes(rng: np.random.Generator, n: int, d_min: float, d_max: float,
                    exponent: float) -> np.ndarray:
    """``n`` diameters with cumulative distribution N(>D) ~ D^-exponent on [d_min, d_max]."""
    u = rng.random(n)
    a, b = d_min ** -exponent, d_max ** -exponent
    return (a - u * (a - b)) ** (-1.0 / exponent)


def golombek_rapp_q(k: float) -> float:
    """Decay constant q(k) = 1.79 + 0.152 / k (1/m) of the Golombek-Rapp model."""
    return 1.79 + 0.152 / k


def golombek_rapp_density(d: np.ndarray, k: float) -> np.ndarray:
    """Rocks per m^2 per metre of diameter of the Golombek-Rapp (1997) rock model: the
    cumulative fraction of the area covered by rocks of diameter >= D is F(D) = k exp(-q D),
    so n(D) = -F'(D) / (pi D^2 / 4) = k q exp(-q D) 4 / (pi D^2)."""
    q = golombek_rapp_q(k)
    return k * q * np.exp(-q * d) * 4.0 / (np.pi * d * d)


def golombek_rapp_sizes(rng: np.random.Generator, area: float, d_min: float, d_max: float,
                        k: float) -> np.ndarray:
    """Seeded rock diameters on ``area`` m^2 between ``d_min`` and ``d_max`` (Poisson count,
    inverse-CDF sampling of :func:`golombek_rapp_density` on a fine log grid)."""
    grid = np.geomspace(d_min, d_max, 2049)
    dens = golombek_rapp_density(grid, k)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    n = int(rng.poisson(cdf[-1] * area))
    return np.interp(rng.random(n) * cdf[-1], cdf, grid)


def make_craters(cfg, seed: int) -> Craters:
    """Seeded crater population over the detailed square (``crater_density`` per hectare)."""
    rng = np.random.default_rng([seed, 0xC2A])
    area_ha = cfg.extent**2 / 1e4
    n = rng.poisson(cfg.crater_density * area_ha)
    d = power_law_sizes(rng, n, cfg.crater_min_diameter, cfg.crater_max_diameter,
                        cfg.crater_size_exponent)
    centers = rng.uniform(-cfg.extent / 2, cfg.extent / 2, (n, 2))
    fresh = rng.uniform(0.35, 1.0, n)  # degradation: old craters are shallower
    depths = cfg.crater_depth_ratio * d * fresh
    rims = 0.25 * depths
    return Craters(centers, d, depths, rims)


def crater_profile(rho: np.ndarray, depth: float, rim: float) -> np.ndarray:
    """Height of a crater at normalised radius ``rho = r / R``: parabolic bowl from ``-depth``
    to a rounded rim crest of ``rim`` near rho = 1, ejecta decaying to 0 at rho = 2.2."""
    bowl = -depth + (depth + rim) * rho**2
    ejecta = rim * np.clip(rho, 1e-3, None) ** -3 * smoothstep(2.2, 1.4, rho)
    k = 0.25 * (depth + rim) + 1e-9  # polynomial smooth minimum rounds the crest
    h = np.clip(0.5 + 0.5 * (ejecta - bowl) / k, 0.0, 1.0)
    return ejecta * (1 - h) + bowl * h - k * h * (1 - h)


def relief(cfg, seed: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Large- and metre-scale relief (no craters) at points (x, y)."""
    L = cfg.relief_wavelength
    base = fbm(x / L, y / L, seed + 1, octaves=5)
    ridge = ridged(x / (1.3 * L), y / (1.3 * L), seed + 2, octaves=4) - 0.5
    plains = smoothstep(-0.15, 0.25, fbm(x / (2.5 * L), y / (2.5 * L), seed + 3, octaves=2))
    h = cfg.relief * ((1.0 - cfg.ridges) * base + cfg.ridges * 1.6 * ridge)
    h *= 1.0 - cfg.plains * plains
    h += cfg.detail * fbm(x / 6.0, y / 6.0, seed + 4, octaves=4)
    return h


def add_craters(h: np.ndarray, xs: np.ndarray, ys: np.ndarray, craters: Craters) -> np.ndarray:
    """Add craters to heights ``h`` on the tensor grid ``ys`` (rows) x ``xs`` (columns)."""
    h = h.copy()
    for (cx, cy), d, depth, rim in zip(craters.centers, craters.diameters, craters.depths,
                                       craters.rims):
        r = 0.5 * d
        i0, i1 = np.searchsorted(ys, [cy - 2.3 * r, cy + 2.3 * r])
        j0, j1 = np.searchsorted(xs, [cx - 2.3 * r, cx + 2.3 * r])
        if i1 <= i0 or j1 <= j0:
            continue
        gx, gy = np.meshgrid(xs[j0:j1], ys[i0:i1])
        rho = np.hypot(gx - cx, gy - cy) / r
        # Craters carve into the local mean level: blend bowl over the existing surface.
        h[i0:i1, j0:j1] += crater_profile(rho, depth, rim)
    return h


class Heightfield:
    """Terrain heights ``z[i, j]`` at ``(xs[j], ys[i])`` plus crater list; see module doc."""

    def __init__(self, cfg, seed: int):
        self.xs = grid_axis(cfg.extent, cfg.resolution, max(cfg.far_extent, cfg.extent / 2))
        self.ys = self.xs.copy()
        gx, gy = np.meshgrid(self.xs, self.ys)
        self.craters = make_craters(cfg, seed)
        self.z = add_craters(relief(cfg, seed, gx, gy), self.xs, self.ys, self.craters)
        self.half_extent = 0.5 * cfg.extent

    def height_at(self, x, y) -> np.ndarray:
        """Height of the rendered (triangulated) surface at points (x, y); NaN outside."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        xs, ys, z = self.xs, self.ys, self.z
        j = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, len(xs) - 2)
        i = np.clip(np.searchsorted(ys, y, side="right") - 1, 0, len(ys) - 2)
        s = (x - xs[j]) / (xs[j + 1] - xs[j])
        t = (y - ys[i]) / (ys[i + 1] - ys[i])
        z00, z10, z11, z01 = z[i, j], z[i, j + 1], z[i + 1, j + 1], z[i + 1, j]
        lower = z00 + s * (z10 - z00) + t * (z11 - z10)  # triangle (00, 10, 11), s >= t
        upper = z00 + t * (z01 - z00) + s * (z11 - z01)  # triangle (00, 11, 01), s < t
        out = np.where(s >= t, lower, upper)
        inside = (x >= xs[0]) & (x <= xs[-1]) & (y >= ys[0]) & (y <= ys[-1])
        return np.where(inside, out, np.nan)

    def triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """Mesh arrays: vertices (V, 3) float and triangles (F, 3) int (see module doc)."""
        ny, nx = self.z.shape
        gx, gy = np.meshgrid(self.xs, self.ys)
        verts = np.stack([gx.ravel(), gy.ravel(), self.z.ravel()], axis=1)
        idx = np.arange(ny * nx).reshape(ny, nx)
        v00, v10 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        v11, v01 = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
        tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
        return verts, tris
