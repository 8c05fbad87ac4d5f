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
    angle, _ = layer_transform(k)
    out = tex.copy()
    g = tex[..., :2] @ _rot(angle)  # row vector g @ R == (R^T g^T)^T
    out[..., :2] = g
    return out


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
