"""Rocks and boulders in pure numpy: a few seeded low-poly prototype meshes and their
placements (power-law sizes, more of them around crater rims), resting partly buried on the
heightfield. :mod:`simulation.terrain.scene` instances the prototypes in Blender."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulation.terrain.heightfield import Heightfield, golombek_rapp_sizes, power_law_sizes
from simulation.terrain.noise import perlin

N_PROTOTYPES = 8  #: per level of detail
SMALL_ROCK = 0.3  #: rocks below this diameter (m) use the coarse prototypes


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: vertices (V, 3) and outward-oriented triangles (F, 3)."""
    p = (1.0 + 5**0.5) / 2.0
    v = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p),
         (0, 1, -p), (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(x, dtype=np.float64) / np.linalg.norm(x) for x in v]
    faces = f
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.array(verts), np.array(faces, dtype=np.int64)


def rock_prototype(seed: int, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One angular rock of radius ~1 with its base at z = 0: an icosphere with noisy radius,
    cut by a few random planes (facets) and flattened at the bottom."""
    rng = np.random.default_rng([seed, 0x80C])
    v, f = icosphere(subdivisions)
    r = 1.0 + 0.22 * perlin(1.7 * v[:, 0] + 3 * v[:, 2], 1.7 * v[:, 1] - 2 * v[:, 2], seed)
    v = v * r[:, None]
    for _ in range(rng.integers(3, 7)):  # facets: project vertices beyond a plane onto it
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d = rng.uniform(0.55, 0.85)
        excess = v @ n - d
        v -= np.clip(excess, 0.0, None)[:, None] * n
    v[:, 2] = np.maximum(v[:, 2], -0.35)  # flat bottom, sunk into the ground when placed
    v[:, 2] -= v[:, 2].min()
    return v, f


@dataclass(frozen=True)
class Rocks:
    """Placements: ``location`` (N, 3) of each prototype's base origin, ``scale`` (N, 3),
    ``yaw`` (N,) radians, ``proto`` (N,) prototype index, ``radius`` (N,) horizontal
    bounding radius and ``top`` (N,) world height of the highest point."""

    location: np.ndarray
    scale: np.ndarray
    yaw: np.ndarray
    proto: np.ndarray
    radius: np.ndarray
    top: np.ndarray

    def __len__(self) -> int:
        return len(self.proto)


def make_rocks(cfg, hf: Heightfield, seed: int,
               prototypes: list[tuple[np.ndarray, np.ndarray]]) -> Rocks:
    """Seeded rock field over the detailed square: diameters from the Golombek-Rapp model
    (``rock_abundance``) or a power law (``rock_density`` per m^2); 30 % are ejecta near
    crater rims. ``prototypes`` holds
    ``N_PROTOTYPES`` detailed ones followed by as many coarse ones (for small rocks)."""
    rng = np.random.default_rng([seed, 0x20C])
    half = cfg.extent / 2
    if cfg.rock_model == "golombek_rapp":
        d = golombek_rapp_sizes(rng, cfg.extent**2, cfg.rock_min_diameter,
                                cfg.rock_max_diameter, cfg.rock_abundance)
        n = len(d)
    else:
        n = int(rng.poisson(cfg.rock_density * cfg.extent**2))
        d = power_law_sizes(rng, n, cfg.rock_min_diameter, cfg.rock_max_diameter,
                            cfg.rock_size_exponent)
    xy = rng.uniform(-half, half, (n, 2))
    craters = hf.craters
    if len(craters.diameters) and n:
        ejecta = rng.random(n) < 0.3
        w = craters.diameters**2
        k = rng.choice(len(w), size=n, p=w / w.sum())
        ang = rng.uniform(0, 2 * np.pi, n)
        rad = 0.5 * craters.diameters[k] * rng.uniform(0.85, 1.9, n)
        around = craters.centers[k] + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        xy = np.where(ejecta[:, None], np.clip(around, -half, half), xy)
    proto = rng.integers(0, N_PROTOTYPES, n) + np.where(d < SMALL_ROCK, N_PROTOTYPES, 0)
    proto = np.minimum(proto, len(prototypes) - 1)
    half_d = 0.5 * d
    scale = np.stack([half_d, half_d * rng.uniform(0.6, 1.0, n),
                      half_d * rng.uniform(0.35, 0.75, n)], axis=1)
    yaw = rng.uniform(0, 2 * np.pi, n)
    ext_xy = np.array([np.max(np.linalg.norm(v[:, :2], axis=1)) for v, _ in prototypes])
    ext_z = np.array([v[:, 2].max() for v, _ in prototypes])
    ground = hf.height_at(xy[:, 0], xy[:, 1])
    bury = rng.uniform(0.15, 0.35, n) * scale[:, 2] * ext_z[proto]
    loc = np.column_stack([xy, ground - bury])
    radius = np.max(scale[:, :2], axis=1) * ext_xy[proto]
    top = loc[:, 2] + scale[:, 2] * ext_z[proto]
    return Rocks(loc, scale, yaw, proto, radius, top)


def surface_height_at(hf: Heightfield, rocks: Rocks, x, y) -> np.ndarray:
    """Conservative height of the solid surface (terrain, or the top of any rock whose
    horizontal bounding circle contains the point) at points (x, y)."""
    from scipy.spatial import cKDTree

    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    h = hf.height_at(x, y)
    if len(rocks) == 0:
        return h
    tree = cKDTree(rocks.location[:, :2])
    pts = np.column_stack([x, y])
    for k, near in enumerate(tree.query_ball_point(pts, float(rocks.radius.max()))):
        if near:
            near = np.asarray(near)
            inside = near[np.hypot(*(rocks.location[near, :2] - pts[k]).T) <= rocks.radius[near]]
            if inside.size:
                h[k] = max(h[k], float(rocks.top[inside].max()))
    return h
