"""Surface appearance in pure numpy: per-vertex texture coordinates of every tile layer and
per-vertex base colours, baked into mesh attributes so that the Cycles shader needs only
cheap attribute reads and one image lookup per layer (a procedural node graph of the same
look costs several times more render time).

Layer k maps the world point p = (x, y) to tile coordinates u = R(angle_k) p / s_k + o_k.
The tile's micro-relief has height amplitude proportional to s_k, so its world slope is
R(angle_k)^T (tile slope): each layer gets its own copy of the tile with the slope channels
pre-rotated. Affine maps are interpolated exactly across triangles.
"""

from __future__ import annotations

import numpy as np

from simulation.terrain.noise import fbm


def layer_transform(k: int) -> tuple[float, np.ndarray]:
    """Rotation angle (rad) and offset of tile layer ``k`` (layers are turned against each
    other so their lattices never align)."""
    return 0.61 * (k + 1), np.array([0.37 * k, 0.71 * k])


def _rot(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def tile_uv(xy: np.ndarray, scale: float, k: int) -> np.ndarray:
    """(N, 2) float32 tile coordinates of layer ``k`` with tile size ``scale`` metres."""
    angle, offset = layer_transform(k)
    return (xy @ _rot(angle).T / scale + offset).astype(np.float32)


def rotated_tile(tex: np.ndarray, k: int) -> np.ndarray:
    """Copy of the tile (channels: du-slope, dv-slope, albedo, height) for layer ``k`` with
    the slopes expressed in world x, y."""
    return tile_in_world(tex, layer_transform(k)[0])


def tile_in_world(tex: np.ndarray, angle: float) -> np.ndarray:
    """Copy of a tile mapped by u = R(angle) p / s with its slopes expressed in world x, y."""
    out = tex.copy()
    out[..., :2] = tex[..., :2] @ _rot(angle)  # row vector g @ R == (R^T g^T)^T
    return out


def ripple_angle(azimuth_deg: float) -> float:
    """Tile rotation that puts the ripple tile's u axis (across the crests) along the compass
    ``azimuth`` (clockwise from north = +y): u = R p must grow along (sin az, cos az)."""
    az = np.deg2rad(azimuth_deg)
    return -float(np.arctan2(np.cos(az), np.sin(az)))


def ripple_uv(xy: np.ndarray, cfg) -> np.ndarray:
    """(N, 2) float32 coordinates of the ripple tile (RIPPLES_PER_TILE crests per tile)."""
    from simulation.terrain.textures import RIPPLES_PER_TILE

    tile = cfg.ripple_wavelength * RIPPLES_PER_TILE
    return (xy @ _rot(ripple_angle(cfg.ripple_azimuth)).T / tile).astype(np.float32)


def ripple_mask(cfg, seed: int, xy: np.ndarray) -> np.ndarray:
    """(N,) float32 weight in [0, 1] of the ripples: fields of about ``ripple_patch_size``
    covering ``ripple_coverage`` of the ground (a threshold on seeded fbm at its quantile,
    with soft edges over a tenth of the patch size)."""
    c = cfg.ripple_coverage
    if c <= 0.0 or cfg.ripple_strength <= 0.0 or len(xy) == 0:
        return np.zeros(len(xy), np.float32)
    if c >= 1.0:
        return np.ones(len(xy), np.float32)
    L = cfg.ripple_patch_size
    f = fbm(xy[:, 0] / L, xy[:, 1] / L, seed + 29, octaves=3)
    # quantile of the field over a seeded sample of the detailed square (stable, cheap)
    rng = np.random.default_rng([seed, 0x819])
    probe = rng.uniform(-cfg.extent / 2, cfg.extent / 2, (4096, 2))
    thr = np.quantile(fbm(probe[:, 0] / L, probe[:, 1] / L, seed + 29, octaves=3), 1.0 - c)
    edge = 0.1 * np.std(f) + 1e-9
    return np.clip((f - thr) / edge + 0.5, 0.0, 1.0).astype(np.float32)


def terrain_base_color(cfg, seed: int, xy: np.ndarray) -> np.ndarray:
    """(N, 3) linear base colour: ochre dust with darker, rockier patches (~60 m wide)."""
    f = fbm(xy[:, 0] / 60.0, xy[:, 1] / 60.0, seed + 11, octaves=3)
    w = np.clip((f + 0.05) / 0.35, 0.0, 1.0)[:, None]
    w = w * w * (3.0 - 2.0 * w)
    return ((1.0 - w) * np.asarray(cfg.color) + w * np.asarray(cfg.color_dark)).astype(np.float32)


def rock_base_color(cfg, rng: np.random.Generator, n_rocks: int) -> np.ndarray:
    """(n_rocks, 3) per-rock colours around ``rock_color`` (brightness and hue jitter)."""
    gain = rng.uniform(0.7, 1.3, (n_rocks, 1))
    hue = rng.uniform(-0.03, 0.03, (n_rocks, 3))
    return np.clip(np.asarray(cfg.rock_color) * gain + hue * np.asarray(cfg.rock_color), 0, 1)


def rock_projection(p: np.ndarray) -> np.ndarray:
    """World points of rock surfaces -> (N, 2) plane coordinates that do not collapse on
    vertical faces (an oblique projection)."""
    return np.column_stack([p[:, 0] + 0.55 * p[:, 2], p[:, 1] - 0.45 * p[:, 2]])
