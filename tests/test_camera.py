"""Tests of granite.camera: Jacobians vs central differences, round trips, OpenCV cross-checks,
validity flags and the factory."""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
import pytest

from granite.camera import (
    DoubleSphereCamera,
    KannalaBrandtCamera,
    PinholeCamera,
    make_camera,
)
from granite.camera import batch
from granite.errors import ConfigError

SEED = 1234

# EuRoC cam0 pinhole, TUM-VI kb4 and ds calibrations (Basalt), plus a ds with xi > 0, alpha < 0.5
PINHOLE = ("pinhole", dict(fx=458.654, fy=457.296, cx=367.215, cy=248.375), 752, 480)
KB4 = (
    "kb4",
    dict(fx=190.97847715128717, fy=190.9733070521226, cx=254.93170605935475, cy=256.8974428996504,
         k1=0.0034823894022493434, k2=0.0007150348452162257, k3=-0.0020532361418706202,
         k4=0.00020293673591811182),
    512, 512,
)
DS = (
    "ds",
    dict(fx=158.28600034966977, fy=158.2743455478755, cx=254.96116578191653, cy=256.8894394501779,
         xi=-0.17734252518173106, alpha=0.5929564608700182),
    512, 512,
)
DS2 = ("ds", dict(fx=300.0, fy=290.0, cx=320.0, cy=240.0, xi=0.6, alpha=0.4), 640, 480)

ALL = {"pinhole": PINHOLE, "kb4": KB4, "ds": DS, "ds2": DS2}
MAX_ANGLE_DEG = {"pinhole": 60.0, "kb4": 100.0, "ds": 100.0, "ds2": 100.0}


def _camera(key: str):
    t, intr, w, h = ALL[key]
    return make_camera(t, intr, w, h)


def _points(rng: np.random.Generator, n: int, max_angle_deg: float) -> np.ndarray:
    """Points with off-axis angle uniform in [0, max_angle], random azimuth, distance 0.3..20."""
    ang = np.deg2rad(rng.uniform(0.0, max_angle_deg, size=n))
    az = rng.uniform(-np.pi, np.pi, size=n)
    dist = rng.uniform(0.3, 20.0, size=n)
    d = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], axis=1)
    return d * dist[:, None]


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-entry relative Frobenius error over the trailing two axes."""
    return np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))


# ----------------------------------------------------------------------------- Jacobians

@pytest.mark.parametrize("key", list(ALL))
def test_project_point_jacobian_central_differences(key):
    cam = _camera(key)
    rng = np.random.default_rng(SEED)
    pts = _points(rng, 300, MAX_ANGLE_DEG[key])
    uv, jp, jk, valid = cam.project_jacobians(pts)
    assert valid.all()
    uv2, valid2 = cam.project(pts)
    np.testing.assert_array_equal(uv, uv2)
    np.testing.assert_array_equal(valid, valid2)
    num = np.zeros_like(jp)
    h = 1e-5 * np.linalg.norm(pts, axis=1)
    for k in range(3):
        d = np.zeros_like(pts)
        d[:, k] = h
        up, vp = cam.project(pts + d)
        um, vm = cam.project(pts - d)
        assert vp.all() and vm.all()
        num[:, :, k] = (up - um) / (2 * h[:, None])
    assert _rel(jp, num).max() < 1e-6


@pytest.mark.parametrize("key", list(ALL))
def test_project_param_jacobian_central_differences(key):
    cam = _camera(key)
    rng = np.random.default_rng(SEED + 1)
    pts = _points(rng, 300, MAX_ANGLE_DEG[key])
    _, _, jk, valid = cam.project_jacobians(pts)
    assert valid.all()
    assert jk.shape == (300, 2, cam.n_params)
    num = np.zeros_like(jk)
    for k in range(cam.n_params):
        h = 1e-3 if k < 4 else 1e-6
        pp = cam.params.copy()
        pm = cam.params.copy()
        pp[k] += h
        pm[k] -= h
        cp = type(cam)(pp, cam.width, cam.height)
        cm = type(cam)(pm, cam.width, cam.height)
        up, vp = cp.project(pts)
        um, vm = cm.project(pts)
        assert vp.all() and vm.all()
        num[:, :, k] = (up - um) / (2 * h)
        # every parameter column on its own, relative over all points
        col_err = np.linalg.norm(jk[:, :, k] - num[:, :, k]) / np.linalg.norm(num[:, :, k])
        assert col_err < 1e-6, (cam.param_names[k], col_err)
    assert _rel(jk, num).max() < 1e-6


@pytest.mark.parametrize("key", list(ALL))
def test_unproject_jacobian_central_differences(key):
    cam = _camera(key)
    rng = np.random.default_rng(SEED + 2)
    uv, _ = cam.project(_points(rng, 300, MAX_ANGLE_DEG[key] - 2.0))
    # include pixels near and at the principal point
    c = cam.params[2:4]
    uv = np.vstack([uv, c, c + [1e-9, 0.0], c + [0.3, -0.2]])
    b, jb, valid = cam.unproject_jacobians(uv)
    assert valid.all()
    b2, valid2 = cam.unproject(uv)
    np.testing.assert_array_equal(b, b2)
    np.testing.assert_array_equal(valid, valid2)
    h = 1e-3
    num = np.zeros_like(jb)
    for k in range(2):
        d = np.zeros_like(uv)
        d[:, k] = h
        bp, vp = cam.unproject(uv + d)
        bm, vm = cam.unproject(uv - d)
        assert vp.all() and vm.all()
        num[:, :, k] = (bp - bm) / (2 * h)
    assert _rel(jb, num).max() < 1e-6


# ----------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("key", list(ALL))
def test_unproject_project_round_trip(key):
    cam = _camera(key)
    rng = np.random.default_rng(SEED + 3)
    pts = _points(rng, 2000, MAX_ANGLE_DEG[key])
    # explicit wide-angle and on-axis cases
    extra = np.array([[0.0, 0.0, 1.0], [1e-12, -1e-12, 2.0], [1e-7, 0.0, 1.0]])
    pts = np.vstack([pts, extra])
    uv, valid = cam.project(pts)
    assert valid.all()
    b, bvalid = cam.unproject(uv)
    assert bvalid.all()
    expected = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.abs(b - expected).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-14)
    # and in the other direction, on a grid of pixels inside the image
    uu, vv = np.meshgrid(np.linspace(0, cam.width - 1, 40), np.linspace(0, cam.height - 1, 30))
    grid = np.stack([uu.ravel(), vv.ravel()], axis=1)
    b, bvalid = cam.unproject(grid)
    uv2, v2 = cam.project(b[bvalid] * 3.0)
    assert v2.all()
    assert np.abs(uv2 - grid[bvalid]).max() < 1e-9


def test_wide_angle_round_trip_kb4_ds_beyond_90_degrees():
    rng = np.random.default_rng(SEED + 4)
    for key in ("kb4", "ds", "ds2"):
        cam = _camera(key)
        ang = np.deg2rad(np.linspace(80.0, 100.0, 41))
        az = rng.uniform(-np.pi, np.pi, size=ang.size)
        d = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], axis=1)
        uv, valid = cam.project(5.0 * d)
        assert valid.all()
        b, bvalid = cam.unproject(uv)
        assert bvalid.all()
        assert np.abs(b - d).max() < 1e-9


# ----------------------------------------------------------------------------- OpenCV cross-checks

def test_pinhole_matches_opencv():
    cam = _camera("pinhole")
    rng = np.random.default_rng(SEED + 5)
    pts = _points(rng, 500, 60.0)
    fx, fy, cx, cy = cam.params
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, None)
    uv, valid = cam.project(pts)
    assert valid.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-9)


def test_kb4_matches_opencv_fisheye():
    cam = _camera("kb4")
    rng = np.random.default_rng(SEED + 6)
    pts = _points(rng, 500, 85.0)  # OpenCV's fisheye model uses atan(r/z): front hemisphere only
    fx, fy, cx, cy, k1, k2, k3, k4 = cam.params
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    D = np.array([k1, k2, k3, k4])
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), np.zeros(3), np.zeros(3), K, D)
    uv, valid = cam.project(pts)
    assert valid.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-8)


def test_ds_against_paper_formula_and_pinhole_limit():
    # direct transcription of Usenko et al. 2018, Eq. 40-45, in plain numpy
    rng = np.random.default_rng(SEED + 7)
    for key in ("ds", "ds2"):
        cam = _camera(key)
        fx, fy, cx, cy, xi, alpha = cam.params
        pts = _points(rng, 300, 100.0)
        x, y, z = pts.T
        d1 = np.sqrt(x**2 + y**2 + z**2)
        d2 = np.sqrt(x**2 + y**2 + (xi * d1 + z) ** 2)
        den = alpha * d2 + (1 - alpha) * (xi * d1 + z)
        ref = np.stack([fx * x / den + cx, fy * y / den + cy], axis=1)
        uv, valid = cam.project(pts)
        assert valid.all()
        np.testing.assert_allclose(uv, ref, rtol=0, atol=1e-9)
    # xi = alpha = 0 is the pinhole model
    ds0 = DoubleSphereCamera([400.0, 410.0, 320.0, 240.0, 0.0, 0.0], 640, 480)
    pin = PinholeCamera([400.0, 410.0, 320.0, 240.0], 640, 480)
    pts = _points(rng, 100, 60.0)
    np.testing.assert_allclose(ds0.project(pts)[0], pin.project(pts)[0], atol=1e-10)


# ----------------------------------------------------------------------------- validity

@pytest.mark.parametrize("key", list(ALL))
def test_nan_and_zero_inputs_are_invalid(key):
    cam = _camera(key)
    pts = np.array([[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 0.0, np.nan], [0.0, 0.0, 0.0],
                    [0.1, 0.2, 1.0]])
    uv, valid = cam.project(pts)
    np.testing.assert_array_equal(valid, [False, False, False, False, True])
    assert np.all(np.isfinite(uv))
    uv, jp, jk, valid = cam.project_jacobians(pts)
    np.testing.assert_array_equal(valid, [False, False, False, False, True])
    assert np.all(np.isfinite(uv)) and np.all(np.isfinite(jp)) and np.all(np.isfinite(jk))
    assert np.all(jp[~valid] == 0) and np.all(uv[~valid] == 0)
    pix = np.array([[np.nan, 10.0], [10.0, np.inf], [cam.params[2], cam.params[3]]])
    b, valid = cam.unproject(pix)
    np.testing.assert_array_equal(valid, [False, False, True])
    assert np.all(np.isfinite(b))
    np.testing.assert_allclose(b[2], [0.0, 0.0, 1.0], atol=1e-15)
    b, jb, valid = cam.unproject_jacobians(pix)
    np.testing.assert_array_equal(valid, [False, False, True])
    assert np.all(np.isfinite(jb))


def test_pinhole_behind_camera_invalid():
    cam = _camera("pinhole")
    pts = np.array([[0.1, 0.1, -1.0], [0.0, 0.0, -1e-3], [1.0, 0.0, 0.0], [0.0, 0.0, 1e-9],
                    [0.1, 0.1, 1e-3]])
    uv, valid = cam.project(pts)
    np.testing.assert_array_equal(valid, [False, False, False, False, True])
    _, _, _, valid_j = cam.project_jacobians(pts)
    np.testing.assert_array_equal(valid_j, valid)


def test_ds_validity_regions():
    cam = _camera("ds")
    fx, fy, cx, cy, xi, alpha = cam.params
    w1 = (1 - alpha) / alpha if alpha > 0.5 else alpha / (1 - alpha)
    w2 = (w1 + xi) / math.sqrt(2 * w1 * xi + xi * xi + 1)
    limit = math.acos(-w2)  # off-axis angle where z = -w2 |p|
    ang = np.array([limit - 1e-3, limit + 1e-3, math.pi])
    pts = np.stack([np.sin(ang), np.zeros(3), np.cos(ang)], axis=1)
    _, valid = cam.project(pts)
    np.testing.assert_array_equal(valid, [True, False, False])
    # unprojection: r^2 < 1 / (2 alpha - 1) in normalised coordinates
    r_max = 1.0 / math.sqrt(2 * alpha - 1)
    pix = np.array([[cx + fx * r_max * 1.0001, cy], [cx, cy + fy * r_max * 1.01]])
    _, valid = cam.unproject(pix)
    assert not valid.any()


def test_kb4_non_monotonic_polynomial_limits_validity():
    # theta_d' = 1 - 0.6 theta^2 vanishes at theta_max = 1/sqrt(0.6) (~74.5 deg)
    cam = KannalaBrandtCamera([300.0, 300.0, 320.0, 240.0, -0.2, 0.0, 0.0, 0.0], 640, 480)
    theta_max = 1.0 / math.sqrt(0.6)
    ang = np.array([theta_max - 1e-3, theta_max + 1e-3, 2.5])
    pts = np.stack([np.sin(ang), np.zeros(3), np.cos(ang)], axis=1)
    _, valid = cam.project(pts)
    np.testing.assert_array_equal(valid, [True, False, False])
    td_max = theta_max * (1 - 0.2 * theta_max**2)
    pix = np.array([[320.0 + 300.0 * td_max * 0.999, 240.0], [320.0 + 300.0 * td_max * 1.001, 240.0]])
    b, valid = cam.unproject(pix)
    np.testing.assert_array_equal(valid, [True, False])
    uv, v2 = cam.project(b[:1])
    assert v2.all() and np.abs(uv - pix[:1]).max() < 1e-6


def test_in_image():
    cam = _camera("pinhole")
    W, H = cam.width, cam.height
    uv = np.array([[0.0, 0.0], [W - 1.0, H - 1.0], [-0.01, 5.0], [5.0, H - 0.99], [np.nan, 1.0],
                   [3.0, 3.0]])
    np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, False, True])
    np.testing.assert_array_equal(cam.in_image(uv, margin=3.0), [False] * 5 + [True])


# ----------------------------------------------------------------------------- factory

@pytest.mark.parametrize("key", list(ALL))
def test_make_camera_and_to_basalt(key):
    t, intr, w, h = ALL[key]
    cam = make_camera(t, intr, w, h)
    assert cam.name == t and cam.width == w and cam.height == h
    expected_cls = {"pinhole": PinholeCamera, "kb4": KannalaBrandtCamera, "ds": DoubleSphereCamera}[t]
    assert type(cam) is expected_cls
    assert list(cam.params) == [intr[n] for n in cam.param_names]
    t2, intr2 = cam.to_basalt()
    assert t2 == t and intr2 == intr
    cam2 = make_camera(t2, intr2, w, h)
    np.testing.assert_array_equal(cam2.params, cam.params)


def test_make_camera_errors():
    t, intr, w, h = KB4
    with pytest.raises(ConfigError, match="unknown camera type"):
        make_camera("eucm", intr, w, h)
    missing = dict(intr)
    del missing["k3"]
    with pytest.raises(ConfigError, match="k3"):
        make_camera(t, missing, w, h)
    for bad in (float("nan"), float("inf"), "abc", None):
        with pytest.raises(ConfigError, match="k2"):
            make_camera(t, {**intr, "k2": bad}, w, h)
    with pytest.raises(ConfigError, match="k5"):
        make_camera(t, {**intr, "k5": 0.0}, w, h)
    with pytest.raises(ConfigError, match="width"):
        make_camera(t, intr, 0, h)
    with pytest.raises(ConfigError, match="height"):
        make_camera(t, intr, w, 10.5)
    with pytest.raises(ConfigError, match="fx"):
        make_camera("pinhole", dict(fx=-1.0, fy=1.0, cx=0.0, cy=0.0), 10, 10)
    with pytest.raises(ConfigError, match="alpha"):
        make_camera("ds", {**DS[1], "alpha": 1.5}, 10, 10)
    # messages are one line
    try:
        make_camera("nope", intr, w, h)
    except ConfigError as e:
        assert "\n" not in str(e)


def test_bad_array_shapes_raise_value_error():
    cam = _camera("pinhole")
    with pytest.raises(ValueError):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError):
        cam.unproject(np.zeros(2))


@numba.njit(cache=True)
def _njit_kb4_ds(kp_kb4, kp_ds, pts):
    uv1, jp1, jk1, v1 = batch.project_points(batch.KB4, kp_kb4, pts, True)
    b1, jb1, w1 = batch.unproject_pixels(batch.KB4, kp_kb4, uv1, True)
    uv2, _, _, v2 = batch.project_points(batch.DS, kp_ds, pts, False)
    b2, _, w2 = batch.unproject_pixels(batch.DS, kp_ds, uv2, False)
    return uv1, jp1, b1, jb1, uv2, b2


def test_kernels_callable_from_njit():
    kb4 = _camera("kb4")
    ds = _camera("ds")
    pts = _points(np.random.default_rng(SEED + 8), 50, 90.0)
    uv1, jp1, b1, jb1, uv2, b2 = _njit_kb4_ds(kb4.kernel_params, ds.kernel_params, pts)
    np.testing.assert_array_equal(uv1, kb4.project(pts)[0])
    np.testing.assert_array_equal(jp1, kb4.project_jacobians(pts)[1])
    np.testing.assert_array_equal(b1, kb4.unproject(uv1)[0])
    np.testing.assert_array_equal(jb1, kb4.unproject_jacobians(uv1)[1])
    np.testing.assert_array_equal(uv2, ds.project(pts)[0])
    np.testing.assert_array_equal(b2, ds.unproject(uv2)[0])
