"""Image pyramid stored in one flat float32 buffer, ready for the numba kernels.

Level ``l+1`` is ``cv2.pyrDown`` of level ``l`` (5x5 Gaussian, then every second pixel), so
level-``l+1`` pixel ``i`` is centred on level-``l`` pixel ``2 i``: with pixel centres at integer
coordinates (the top-left pixel centre is (0, 0)), a point ``x_0`` at level 0 is at
``x_l = x_0 / 2**l``. Odd sizes round up (``(w + 1) // 2``), so any image size works.
Intensities keep the input's units (8-bit or 16-bit values as float32).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Input dtypes the frontend accepts, with the factor mapping them to 8-bit units for FAST.
SUPPORTED_DTYPES: dict[np.dtype, float] = {
    np.dtype(np.uint8): 1.0,
    np.dtype(np.uint16): 255.0 / 65535.0,
}


@dataclass(frozen=True)
class ImagePyramid:
    """Pyramid levels concatenated row-major in ``data``.

    Level ``l`` is ``data[offsets[l] : offsets[l] + heights[l] * widths[l]]`` reshaped to
    ``(heights[l], widths[l])``. ``to_uint8`` maps intensities to 8-bit units (used by FAST).
    """

    data: np.ndarray  # (total,) float32
    offsets: np.ndarray  # (levels,) int64
    widths: np.ndarray  # (levels,) int64
    heights: np.ndarray  # (levels,) int64
    to_uint8: float

    @property
    def num_levels(self) -> int:
        return int(self.offsets.shape[0])

    def level(self, index: int) -> np.ndarray:
        """View of one level, shape (height, width), float32."""
        start = int(self.offsets[index])
        h, w = int(self.heights[index]), int(self.widths[index])
        return self.data[start : start + h * w].reshape(h, w)

    def level_uint8(self, index: int) -> np.ndarray:
        """One level rounded and saturated to uint8 (8-bit intensity units)."""
        return cv2.convertScaleAbs(self.level(index), alpha=self.to_uint8)


def build_pyramid(image: np.ndarray, levels: int, presmooth_sigma: float = 0.0) -> ImagePyramid:
    """Build a ``levels``-level pyramid of a 2-D uint8 or uint16 image; level 0 is the image
    blurred by a Gaussian of ``presmooth_sigma`` pixels when that is > 0."""
    if image.ndim != 2 or image.dtype not in SUPPORTED_DTYPES:
        raise ValueError(f"expected a 2-D uint8 or uint16 image, got {image.dtype} {image.shape}")
    widths = [int(image.shape[1])]
    heights = [int(image.shape[0])]
    for _ in range(1, levels):
        widths.append((widths[-1] + 1) // 2)
        heights.append((heights[-1] + 1) // 2)
    w_arr = np.array(widths, dtype=np.int64)
    h_arr = np.array(heights, dtype=np.int64)
    sizes = w_arr * h_arr
    offsets = np.zeros(levels, dtype=np.int64)
    offsets[1:] = np.cumsum(sizes)[:-1]
    data = np.empty(int(sizes.sum()), dtype=np.float32)
    views = [data[o : o + n].reshape(h, w) for o, n, h, w in zip(offsets, sizes, heights, widths)]
    np.copyto(views[0], image, casting="unsafe")
    if presmooth_sigma > 0.0:
        cv2.GaussianBlur(views[0], (0, 0), presmooth_sigma, dst=views[0],
                         borderType=cv2.BORDER_REFLECT_101)
    for lvl in range(1, levels):
        out = cv2.pyrDown(views[lvl - 1], dst=views[lvl], dstsize=(widths[lvl], heights[lvl]))
        if out is not views[lvl] and not np.shares_memory(out, views[lvl]):  # pragma: no cover
            views[lvl][...] = out
    return ImagePyramid(data, offsets, w_arr, h_arr, SUPPORTED_DTYPES[image.dtype])
