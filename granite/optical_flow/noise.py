"""Image noise level and the expected tracking precision of a patch.

The tracker's translation estimate of a patch has (Gauss-Newton, independent pixel noise) the
covariance ``sigma_n**2 * C`` with ``C`` the translation block of ``(J^T J)^-1`` of its
template (normalised intensities, see :mod:`granite.optical_flow.patch`) and ``sigma_n`` the
noise of the normalised intensities, ``sigma_l / mean``: ``sigma_l`` the noise of pyramid
level ``l`` in intensity units, ``mean`` the patch mean. Its square root along the worst
direction, ``sigma_l / mean * sqrt(lambda_max(C))``, is the patch's expected tracking standard
deviation in level pixels; it grows with the image noise and shrinks with the patch's texture
(the smallest eigenvalue of its structure tensor).

``sigma_0`` is estimated per frame from the input image (Immerkaer's 3x3 operator, which
cancels intensity planes, made robust to texture by taking the median absolute response;
``median / (0.6745 * 6)`` is the noise standard deviation for white Gaussian noise), on a grid
of every ``stride``-th pixel. ``sigma_l = gain_l * sigma_0``, where ``gain_l`` is the exact
noise gain of the pyramid filters (pre-smoothing, ``l`` times ``pyrDown``) for white noise.

The model treats the pattern's samples as independent with the pixel noise. Bilinear
interpolation averages neighbouring pixels, so a sample's noise is lower by
``sqrt(sum of squared weights)``: 0.625 for the 0.75-scaled pattern on integer or
half-integer centres, 0.67 on average; a test checks the predicted scatter with that factor.
The factor of the noise-scaled forward-backward limit absorbs it.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numba import njit

from granite.optical_flow.patch import FASTMATH as _FASTMATH
from granite.optical_flow.patch import AUX_ROWS, make_template

#: Median absolute value of a zero-mean Gaussian, in standard deviations.
_MAD_GAUSS = 0.6744897501960817
#: L2 norm of Immerkaer's operator [[1, -2, 1], [-2, 4, -2], [1, -2, 1]].
_OPERATOR_NORM = 6.0


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def _select(values, k):
    """The k-th smallest of ``values`` (modified in place), Hoare's quickselect with a
    median-of-three pivot (deterministic)."""
    lo = 0
    hi = values.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        a, b, c = values[lo], values[mid], values[hi]
        pivot = max(min(a, b), min(max(a, b), c))
        i = lo
        j = hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return values[k]
    return values[k]


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _noise_sigma(image, stride):
    h, w = image.shape
    ny = (h - 2 + stride - 1) // stride
    nx = (w - 2 + stride - 1) // stride
    values = np.empty(max(ny * nx, 1), dtype=np.float64)
    m = 0
    for y in range(1, h - 1, stride):
        for x in range(1, w - 1, stride):
            r = (
                float(image[y - 1, x - 1]) + float(image[y - 1, x + 1])
                + float(image[y + 1, x - 1]) + float(image[y + 1, x + 1])
                - 2.0 * (float(image[y - 1, x]) + float(image[y + 1, x])
                         + float(image[y, x - 1]) + float(image[y, x + 1]))
                + 4.0 * float(image[y, x])
            )
            values[m] = abs(r)
            m += 1
    if m == 0:
        return 0.0
    return _select(values[:m], m // 2) / (_MAD_GAUSS * _OPERATOR_NORM)


def estimate_noise(image: np.ndarray, stride: int = 2) -> float:
    """Robust standard deviation of white noise in a 2-D image (its intensity units), from
    the median absolute response of Immerkaer's operator on a ``stride`` grid. Texture
    raises it only where the operator responds on more than half of the pixels."""
    if image.ndim != 2 or min(image.shape) < 3:
        return 0.0
    return float(_noise_sigma(np.ascontiguousarray(image), int(stride)))


@functools.lru_cache(maxsize=16)
def level_noise_gains(levels: int, presmooth_sigma: float) -> tuple[float, ...]:
    """Noise standard deviation of each pyramid level per unit white noise in the input, for
    the filters of :func:`granite.optical_flow.pyramid.build_pyramid` (pre-smoothing, then
    ``pyrDown``), computed exactly from their impulse responses: the filters are separable,
    so the 2-D gain is the product of two 1-D variance gains, each the sum over the ``2**l``
    input phases of the energy of the response to a line impulse (OpenCV's own filters run
    on a 16-row image whose rows are equal)."""
    size = 16 * 2 ** max(levels, 1) + 64
    gains = []
    for lvl in range(levels):
        total = 0.0
        for phase in range(2**lvl):
            img = np.zeros((16, size), np.float32)
            img[:, size // 2 + phase] = 1.0
            if presmooth_sigma > 0.0:
                img = cv2.GaussianBlur(img, (0, 0), presmooth_sigma, borderType=cv2.BORDER_REFLECT_101)
            for _ in range(lvl):
                img = cv2.pyrDown(img)
            row = img[img.shape[0] // 2].astype(np.float64)
            total += float(np.sum(row * row))
        gains.append(total)  # 1-D variance gain; the 2-D standard deviation gain is the same number
    return tuple(gains)


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def unit_noise_std(buf, off, w, h, points, pattern, margin):
    """Expected tracking standard deviation (level pixels, worst direction) of patches
    centred at ``points`` (M, 2, level pixels) per unit noise of the level's intensities:
    ``sqrt(lambda_max(C)) / mean`` with ``C`` the translation block of ``(J^T J)^-1`` of the
    template and ``mean`` the patch mean. inf where no template can be made."""
    n = points.shape[0]
    p = pattern.shape[0]
    out = np.empty(n)
    data = np.empty(p, dtype=np.float32)
    valid = np.empty(p, dtype=np.bool_)
    jac = np.empty((p, 3), dtype=np.float32)
    aux = np.empty((AUX_ROWS, 3), dtype=np.float32)
    for k in range(n):
        st = make_template(buf, off, w, h, points[k, 0], points[k, 1], pattern, margin, data, valid, jac, aux)
        if st <= 0:
            out[k] = np.inf
            continue
        mean = float(aux[4, 0])
        out[k] = math.sqrt(translation_lambda_max(aux)) / mean
    return out


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def translation_lambda_max(aux) -> float:
    """Largest eigenvalue of the 2x2 translation block of ``(J^T J)^-1`` (``aux`` rows 0-1
    of a template, see :func:`granite.optical_flow.patch.make_template`)."""
    a = float(aux[0, 0])
    b = float(aux[0, 1])
    d = float(aux[1, 1])
    half_tr = 0.5 * (a + d)
    disc = math.sqrt(max(0.25 * (a - d) * (a - d) + b * b, 0.0))
    return half_tr + disc
