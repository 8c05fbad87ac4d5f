"""Camera sensor model (numpy, one numba kernel): the rendered linear radiance becomes the digital image a
real global-shutter navigation camera would deliver.

Chain, per frame (every step documented with its default in ``docs/simulation.md``):

1. optics on the linear radiance: motion blur over the exposure time (from the planar depth
   and the poses at sub-exposure times, see :func:`motion_blur`), a Gaussian lens PSF,
   vignetting (relative illumination falling to ``corner_illumination`` at the image corner);
2. photo-electrons: radiance x exposure scale (auto exposure: the frame's mean radiance, before
   the optics, lands at ``ae_target`` of the ADC range; or fixed) x (1 + PRNU), plus the dark
   signal (dark current x exposure time + DSNU); photon shot noise (Poisson on the electrons),
   read noise (Gaussian), clipped at the full-well capacity;
3. ADC: ``adc_bits`` with conversion gain ``analog_gain * (2^adc_bits - 1) / full_well`` DN per
   electron; then the output encoding (``linear`` or ``srgb``) at ``output_bits``, and optional
   JPEG compression.

Determinism: the fixed pattern (PRNU, DSNU) depends on the scenario seed only (it is the same
for every frame, as on a real sensor); the temporal noise on the seed and the frame index.

The *ideal camera* (``[sensor] enabled = false`` or ``granite-sim render --no-sensor``) keeps the
same exposure, output encoding and bit depth but has no noise, fixed pattern, optics or JPEG:
the difference between the two renders of a frame is the sensor model's doing.

Conventions: images are (H, W) or (H, W, 3) arrays, the centre of the top-left pixel is (0, 0);
poses ``T_w_c`` map camera into world, camera x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from simulation.imaging import linear_to_srgb

#: Rec. 709 relative luminance of linear RGB: the spectral response of the monochrome sensor.
LUMA_709 = np.array([0.2126, 0.7152, 0.0722])
MODEL_NAME = "granite-sim linear CMOS sensor v1"
#: Largest number of sub-exposure images averaged for motion blur.
MAX_BLUR_TAPS = 16


@dataclass(frozen=True)
class FixedPattern:
    """Per-pixel gain (1 + PRNU) and dark offset (DSNU, electrons) of one sensor."""

    gain: np.ndarray
    offset: np.ndarray


def fixed_pattern(cfg, shape: tuple[int, int], seed: int) -> FixedPattern:
    """The sensor's fixed pattern, deterministic in ``seed`` (same for every frame)."""
    rng = np.random.default_rng([seed, 0xF1C5])
    gain = 1.0 + cfg.prnu * rng.standard_normal(shape)
    offset = cfg.dsnu * rng.standard_normal(shape)
    return FixedPattern(gain.astype(np.float32), offset.astype(np.float32))


def conversion_gain(cfg) -> float:
    """ADC digital numbers per electron."""
    return cfg.analog_gain * (2**cfg.adc_bits - 1) / cfg.full_well


def output_gain(cfg) -> float:
    """Output digital numbers per electron for the linear encoding (the slope of the noise
    variance against the signal, both in output DN)."""
    return conversion_gain(cfg) * (2**cfg.output_bits - 1) / (2**cfg.adc_bits - 1)


def exposure_scale(cfg, radiance: np.ndarray, fixed_stops: float = 0.0) -> float:
    """Electrons per unit of linear radiance for this frame. ``auto``: the mean radiance maps
    to ``ae_target`` of the ADC range; ``fixed``: radiance 2^-fixed_stops fills the ADC."""
    full_scale_e = (2**cfg.adc_bits - 1) / conversion_gain(cfg)
    if cfg.exposure_mode == "auto":
        mean = float(np.mean(radiance))
        if mean > 0 and np.isfinite(mean):
            return cfg.ae_target * full_scale_e / mean
    return full_scale_e * 2.0**fixed_stops


def vignetting(cfg, shape: tuple[int, int], cx: float, cy: float) -> np.ndarray:
    """Relative illumination (H, W): a cos^4-like falloff 1 / (1 + a r^2)^2 from the principal
    point, equal to ``corner_illumination`` at the farthest image corner."""
    h, w = shape
    c = cfg.corner_illumination
    if c >= 1.0:
        return np.ones(shape, np.float32)
    r_corner2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, w - 1) for y in (0, h - 1))
    a = (c ** -0.5 - 1.0) / r_corner2
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return (1.0 / (1.0 + a * ((u - cx) ** 2 + (v - cy) ** 2)) ** 2).astype(np.float32)


# --------------------------------------------------------------------------- motion blur


def _project(cam, p: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of camera points (..., 3); pinhole or equidistant fisheye."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if cam.model == "pinhole":
        zs = np.where(z > 1e-9, z, 1e-9)
        return np.stack([cam.fx * x / zs + cam.cx, cam.fy * y / zs + cam.cy], -1)
    r = np.hypot(x, y)
    theta = np.arctan2(r, z)
    scale = np.where(r > 1e-12, theta / np.maximum(r, 1e-12), 1.0 / np.maximum(z, 1e-12))
    return np.stack([cam.fx * x * scale + cam.cx, cam.fy * y * scale + cam.cy], -1)


def _unproject(cam, depth: np.ndarray, step: tuple[int, int] = (1, 1)) -> np.ndarray:
    """Camera points at the planar depth ``depth`` (H, W) of every ``step`` = (rows, columns)
    pixel (sky: 1e6 m along the ray); shape (ceil(H / rows), ceil(W / columns), 3)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h:step[0], 0:w:step[1]].astype(np.float64)
    depth = depth[:: step[0], :: step[1]]
    mx, my = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    if cam.model == "pinhole":
        ray = np.stack([mx, my, np.ones_like(mx)], -1)
    else:
        theta = np.hypot(mx, my)
        s = np.where(theta > 1e-12, np.sin(theta) / np.maximum(theta, 1e-12), 1.0)
        ray = np.stack([mx * s, my * s, np.cos(theta)], -1)
        ray /= np.maximum(ray[..., 2:3], 1e-6)  # planar z = 1
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 1e6).astype(np.float64)
    return ray * z[..., None]


@numba.njit(cache=True, nogil=True)
def _blur_maps(depth, fisheye, fx, fy, cx, cy, M, b, map_u, map_v):
    """Where pixel q samples the mid-exposure image at one sub-exposure time: q - f(q), f the
    flow of the scene point at q (planar depth; sky at 1e6 m along the ray) into the camera
    p_k = M p + b; :func:`_unproject` and :func:`_project` per pixel, in one pass."""
    h, w = depth.shape
    for v in range(h):
        for u in range(w):
            mx, my = (u - cx) / fx, (v - cy) / fy
            if fisheye:
                theta = np.hypot(mx, my)
                s = np.sin(theta) / theta if theta > 1e-12 else 1.0
                zr = max(np.cos(theta), 1e-6)  # planar z = 1
                rx, ry, rz = mx * s / zr, my * s / zr, np.cos(theta) / zr
            else:
                rx, ry, rz = mx, my, 1.0
            z = depth[v, u]
            if not (np.isfinite(z) and z > 0):
                z = 1e6
            px, py, pz = rx * z, ry * z, rz * z
            x = M[0, 0] * px + M[0, 1] * py + M[0, 2] * pz + b[0]
            y = M[1, 0] * px + M[1, 1] * py + M[1, 2] * pz + b[1]
            zz = M[2, 0] * px + M[2, 1] * py + M[2, 2] * pz + b[2]
            if fisheye:
                r = np.hypot(x, y)
                theta = np.arctan2(r, zz)
                scale = theta / max(r, 1e-12) if r > 1e-12 else 1.0 / max(zz, 1e-12)
            else:
                scale = 1.0 / (zz if zz > 1e-9 else 1e-9)
            map_u[v, u] = 2.0 * u - (fx * x * scale + cx)
            map_v[v, u] = 2.0 * v - (fy * y * scale + cy)


def motion_blur(image: np.ndarray, depth: np.ndarray, cam, T_w_c: np.ndarray,
                poses: np.ndarray) -> np.ndarray:
    """Average of the image seen from the sub-exposure poses ``poses`` (K, 4, 4) ``T_w_c``.

    Pixel q at sub-time k shows what the mid-exposure image shows at q - f_k(q), where f_k is
    the flow of the scene point at q (planar depth ``depth``, static scene) from the
    mid-exposure pose ``T_w_c`` to pose k; exact for a rigid scene up to the variation of the
    flow over one blur length.
    """
    if len(poses) <= 1:
        return image
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    map_u = np.empty(depth.shape, np.float32)
    map_v = np.empty(depth.shape, np.float32)
    acc = np.zeros_like(image, dtype=np.float32)
    src = np.ascontiguousarray(image, dtype=np.float32)
    for T in poses:
        R, t = T[:3, :3], T[:3, 3]
        # p_k = R^T (R_mid p + t_mid - t)
        M = np.ascontiguousarray(R.T @ T_w_c[:3, :3], dtype=np.float64)
        b = np.ascontiguousarray(R.T @ (T_w_c[:3, 3] - t), dtype=np.float64)
        _blur_maps(depth, cam.model != "pinhole", float(cam.fx), float(cam.fy), float(cam.cx),
                   float(cam.cy), M, b, map_u, map_v)
        acc += cv2.remap(src, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / len(poses)


def blur_taps(depth: np.ndarray, cam, T_w_c: np.ndarray, open_close: tuple) -> int:
    """Sub-exposure images needed: one per pixel of the largest flow over the exposure."""
    h, w = depth.shape
    p_c = _unproject(cam, depth, (max(1, h // 24), max(1, w // 32)))
    p_w = p_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    ends = [_project(cam, (p_w - T[:3, 3]) @ T[:3, :3]) for T in open_close]
    span = float(np.nanmax(np.linalg.norm(ends[1] - ends[0], axis=-1)))
    return int(np.clip(np.ceil(span - 1e-6) + 1, 1, MAX_BLUR_TAPS))


# --------------------------------------------------------------------------- the sensor


def expose(cfg, radiance: np.ndarray, scale: float, pattern: FixedPattern | None,
           rng: np.random.Generator | None, ideal: bool = False) -> np.ndarray:
    """Linear radiance (H, W[, 3]) after the optics -> ADC digital numbers (float64, integer
    valued). ``ideal``: expected electrons without noise or fixed pattern."""
    electrons = radiance.astype(np.float64) * scale
    if not ideal:
        g = pattern.gain if radiance.ndim == 2 else pattern.gain[..., None]
        o = pattern.offset if radiance.ndim == 2 else pattern.offset[..., None]
        dark = cfg.dark_current * cfg.exposure_time
        electrons = np.clip(electrons * g + dark + o, 0.0, None)
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons += cfg.read_noise * rng.standard_normal(electrons.shape)
    electrons = np.clip(electrons, 0.0, cfg.full_well)
    adc_max = 2**cfg.adc_bits - 1
    return np.clip(np.round(electrons * conversion_gain(cfg)), 0, adc_max)


def encode(cfg, adc: np.ndarray, jpeg: bool) -> np.ndarray:
    """ADC numbers -> output image (uint8 or uint16) with the configured encoding."""
    x = adc / (2**cfg.adc_bits - 1)
    if cfg.transfer == "srgb":
        x = linear_to_srgb(x)
    out_max = 2**cfg.output_bits - 1
    img = np.clip(np.round(x * out_max), 0, out_max).astype(np.uint8 if cfg.output_bits == 8 else np.uint16)
    if jpeg and cfg.jpeg_quality > 0:
        if img.dtype != np.uint8:
            raise ValueError("JPEG compression needs 8-bit output")
        bgr = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
        dec = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        img = dec if dec.ndim == 2 else cv2.cvtColor(dec, cv2.COLOR_BGR2RGB)
    return img


class Sensor:
    """The camera of one run: ``Sensor(cfg, camera_cfg, seed, grayscale)``, then
    :meth:`capture` per frame. ``cfg.enabled = False`` (or ``ideal=True``) gives the ideal
    camera (module docstring)."""

    def __init__(self, cfg, cam, seed: int, grayscale: bool, fixed_stops: float = 0.0,
                 ideal: bool | None = None):
        self.cfg, self.cam, self.seed = cfg, cam, seed
        self.grayscale = grayscale
        self.fixed_stops = fixed_stops
        self.ideal = (not cfg.enabled) if ideal is None else ideal
        shape = (cam.height, cam.width)
        self.pattern = None if self.ideal else fixed_pattern(cfg, shape, seed)
        self.vignette = None
        if not self.ideal and cfg.corner_illumination < 1.0:
            self.vignette = vignetting(cfg, shape, cam.cx, cam.cy)

    @property
    def blurs(self) -> bool:
        """Whether frames need the sub-exposure poses (:meth:`capture`'s ``blur_poses``)."""
        return not self.ideal and self.cfg.motion_blur and self.cfg.exposure_time > 0

    def capture(self, rgb: np.ndarray, frame_index: int, depth: np.ndarray | None = None,
                T_w_c: np.ndarray | None = None, blur_poses: np.ndarray | None = None):
        """Linear RGB (H, W, 3) -> (image uint8/uint16, info dict). ``blur_poses`` (K, 4, 4)
        ``T_w_c`` at sub-exposure times (with ``depth`` and ``T_w_c``) for motion blur."""
        cfg = self.cfg
        rad = np.asarray(rgb, dtype=np.float32)
        if self.grayscale:
            rad = (rad @ LUMA_709.astype(np.float32)).astype(np.float32)
        scale = exposure_scale(cfg, rad, self.fixed_stops)
        info = {"electrons_per_radiance": scale, "blur_taps": 1}
        if not self.ideal:
            if blur_poses is not None and len(blur_poses) > 1 and depth is not None:
                rad = motion_blur(rad, depth, self.cam, T_w_c, blur_poses)
                info["blur_taps"] = len(blur_poses)
            if cfg.psf_sigma > 0:
                rad = cv2.GaussianBlur(rad, (0, 0), cfg.psf_sigma, borderType=cv2.BORDER_REFLECT)
            if self.vignette is not None:
                rad = rad * (self.vignette if rad.ndim == 2 else self.vignette[..., None])
        rng = None if self.ideal else np.random.default_rng([self.seed, 0x5E5, frame_index])
        adc = expose(cfg, rad, scale, self.pattern, rng, ideal=self.ideal)
        return encode(cfg, adc, jpeg=not self.ideal), info


def describe(cfg) -> dict:
    """Manifest entry: the model, its parameters and derived figures."""
    import dataclasses

    return {"model": MODEL_NAME, "enabled": bool(cfg.enabled),
            "parameters": dataclasses.asdict(cfg),
            "conversion_gain_dn_per_electron": conversion_gain(cfg),
            "output_gain_dn_per_electron": output_gain(cfg)}
