"""Image post-processing in pure numpy: linear radiance -> 8-bit sRGB (Blender's "Standard"
view transform), exposure, seeded sensor noise, grayscale; and conversion of the renderer's
depth to planar camera z."""

from __future__ import annotations

import numpy as np


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def to_8bit(linear_rgb: np.ndarray, exposure: float = 0.0, noise_std: float = 0.0,
            grayscale: bool = False, rng: np.random.Generator | None = None) -> np.ndarray:
    """uint8 image (H, W, 3) RGB or (H, W) gray from linear RGB (H, W, 3).

    ``exposure`` in stops scales the radiance; ``noise_std`` adds Gaussian noise of that
    standard deviation in digital numbers (seeded by ``rng``) before quantisation.
    Gray = Rec. 601 luma of the sRGB-encoded channels (as ``cv2.cvtColor``).
    """
    img = linear_to_srgb(np.asarray(linear_rgb, dtype=np.float64) * 2.0**exposure) * 255.0
    if grayscale:
        img = img @ np.array([0.299, 0.587, 0.114])
    if noise_std > 0:
        if rng is None:
            raise ValueError("noise needs a seeded rng")
        img = img + rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def ray_distance_to_planar(distance: np.ndarray, bearings_z: np.ndarray) -> np.ndarray:
    """Planar depth z from distance along the ray and the unit bearing's z component."""
    return (distance * bearings_z).astype(np.float32)
