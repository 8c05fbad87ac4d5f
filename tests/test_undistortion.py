"""Radial-tangential cameras (EuRoC's distortion, Basalt ``pinhole-radtan8``): images undistorted
to a pinhole camera when the dataset reads them, checked against the model written out here
(OpenCV's rational radial-tangential formula, inverted by Newton's method), not OpenCV's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from granite.errors import ConfigError, InputError
from granite.estimator.config import VoConfig
from granite.estimator.runner import run_vo
from granite.evaluation.ate import ate as absolute_trajectory_error
from granite.io import Calibration, open_dataset, read_calibration, read_image, write_calibration
from granite.io.euroc import write_sensor_yaml
from granite.io.undistortion import Undistortion

ASSET = Path(__file__).resolve().parents[1] / "assets" / "sequences" / "default"
#: EuRoC MH_01's cam0 (k1, k2, p1, p2)
EUROC_COEFFS = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)


def distort(x: np.ndarray, y: np.ndarray, c: dict) -> tuple[np.ndarray, np.ndarray]:
    """Normalised undistorted -> distorted coordinates (rational radial-tangential model)."""
    r2 = x * x + y * y
    radial = (1 + c["k1"] * r2 + c["k2"] * r2**2 + c["k3"] * r2**3) / (
        1 + c["k4"] * r2 + c["k5"] * r2**2 + c["k6"] * r2**3)
    xd = x * radial + 2 * c["p1"] * x * y + c["p2"] * (r2 + 2 * x * x)
    yd = y * radial + c["p1"] * (r2 + 2 * y * y) + 2 * c["p2"] * x * y
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, c: dict) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`distort` by Newton's method with a numerical Jacobian."""
    x, y = xd.copy(), yd.copy()
    h = 1e-7
    for _ in range(30):
        fx, fy = distort(x, y, c)
        ex, ey = fx - xd, fy - yd
        ax, ay = distort(x + h, y, c)
        bx, by = distort(x, y + h, c)
        j11, j21, j12, j22 = (ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h
        det = j11 * j22 - j12 * j21
        x, y = x - (j22 * ex - j12 * ey) / det, y - (j11 * ey - j21 * ex) / det
    assert np.max(np.hypot(*(np.array(distort(x, y, c)) - np.array([xd, yd])))) < 1e-10
    return x, y


def coefficients(k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0) -> dict:
    return dict(k1=k1, k2=k2, p1=p1, p2=p2, k3=k3, k4=k4, k5=k5, k6=k6)


def radtan(fx, fy, cx, cy, w, h, c) -> Calibration:
    return Calibration("pinhole-radtan8", dict(fx=fx, fy=fy, cx=cx, cy=cy, **c), w, h)


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth pattern over normalised image coordinates (period about 25 px at f = 450)."""
    return (128 + 50 * np.sin(17 * x + 3 * y) + 40 * np.cos(13 * y - 5 * x)
            + 20 * np.sin(23 * (x + y))).astype(np.float32)


def pixels(w, h):
    return np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))


CAMERAS = [
    ("euroc", (458.654, 457.296, 367.215, 248.375, 752, 480), coefficients(*EUROC_COEFFS)),
    ("pincushion_rational", (300.0, 310.0, 161.0, 118.0, 320, 240),
     coefficients(k1=0.12, k2=0.02, p1=-0.001, p2=0.002, k3=0.01, k4=0.05)),
]


@pytest.mark.parametrize("name, K, c", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_the_undistorted_image_is_the_pinhole_view_of_the_scene(name, K, c):
    fx, fy, cx, cy, w, h = K
    calib = radtan(fx, fy, cx, cy, w, h, c)
    u, v = pixels(w, h)
    x, y = undistort((u - cx) / fx, (v - cy) / fy, c)
    distorted = texture(x, y)  # what the distorted camera sees of the pattern
    und = Undistortion(calib)
    p = und.target.intrinsics
    assert und.target.camera_type == "pinhole" and (und.target.width, und.target.height) == (w, h)
    expected = texture((u - p["cx"]) / p["fx"], (v - p["cy"]) / p["fy"])
    inner = (slice(3, -3), slice(3, -3))
    err = np.abs(und.apply(distorted) - expected)[inner]
    # bilinear resampling (fixed-point maps) of a pattern of 25 px period: measured 0.02 grey
    # levels on average, 0.08 at the 99th percentile
    assert np.mean(err) < 0.1 and np.percentile(err, 99) < 0.5
    # the same images taken as pinhole (distortion ignored) differ many times more
    ignored = np.abs(distorted - texture((u - cx) / fx, (v - cy) / fy))[inner]
    assert np.mean(ignored) > 10.0 * np.mean(err)


@pytest.mark.parametrize("name, K, c", CAMERAS, ids=[c[0] for c in CAMERAS])
def test_every_pixel_of_the_pinhole_view_lies_inside_the_distorted_image(name, K, c):
    fx, fy, cx, cy, w, h = K
    und = Undistortion(radtan(fx, fy, cx, cy, w, h, c))
    p = und.target.intrinsics
    u, v = pixels(w, h)
    xd, yd = distort((u - p["cx"]) / p["fx"], (v - p["cy"]) / p["fy"], c)
    ud, vd = fx * xd + cx, fy * yd + cy
    assert ud.min() > -1.0 and vd.min() > -1.0 and ud.max() < w and vd.max() < h
    # and the view is not needlessly small: an edge of the pinhole view touches the border
    assert min(ud.min(), vd.min(), w - 1 - ud.max(), h - 1 - vd.max()) < 2.0


def test_calibration_files_and_sensor_yaml_with_radial_tangential_distortion(tmp_path):
    calib = radtan(458.654, 457.296, 367.215, 248.375, 752, 480, coefficients(*EUROC_COEFFS))
    write_calibration(tmp_path / "calib.json", calib)
    back = read_calibration(tmp_path / "calib.json")
    assert back.camera_type == "pinhole-radtan8" and back.intrinsics == calib.intrinsics
    with pytest.raises(ConfigError, match="undistorted"):
        back.camera()
    # k3..k6 are optional (Basalt writes them and rpmax); p2 is required
    data = json.loads((tmp_path / "calib.json").read_text())
    params = data["value0"]["intrinsics"][0]["intrinsics"]
    for k in ("k3", "k4", "k5", "k6"):
        del params[k]
    params["rpmax"] = 1.5
    (tmp_path / "short.json").write_text(json.dumps(data))
    assert read_calibration(tmp_path / "short.json").intrinsics == calib.intrinsics
    del params["p2"]
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"intrinsics\.p2"):
        read_calibration(tmp_path / "bad.json")

    # an EuRoC folder whose sensor.yaml has EuRoC's distortion
    root = tmp_path / "euroc"
    cam0 = root / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 255, (480, 752), dtype=np.uint8), (0, 0), 2.0)
    lines = ["#timestamp [ns],filename"]
    for i in range(3):
        cv2.imwrite(str(cam0 / "data" / f"{1000 + i}.png"), image)
        lines.append(f"{1000 + i},{1000 + i}.png")
    (cam0 / "data.csv").write_text("\n".join(lines) + "\n")
    write_sensor_yaml(cam0 / "sensor.yaml", np.eye(4), (752, 480), [458.654, 457.296, 367.215, 248.375],
                      distortion_model="radial-tangential", distortion_coefficients=list(EUROC_COEFFS))
    ds = open_dataset(root)
    assert ds.calibration.camera_type == "pinhole"
    assert ds.undistortion is not None and ds.undistortion.source.intrinsics == calib.intrinsics
    assert ds.calibration.intrinsics == Undistortion(calib).target.intrinsics
    assert any("undistorted from radial-tangential" in n for n in ds.notes)
    frame = ds.frame(1)
    assert np.array_equal(frame.image, ds.undistortion.apply(read_image(frame.path)))
    assert not np.array_equal(frame.image, read_image(frame.path))
    ds.calibration.camera()  # the VO's camera: a pinhole
    # an image of another size is left for the frontend to reject
    small = np.zeros((240, 376), np.uint8)
    assert ds.undistortion.apply(small) is small


@pytest.mark.slow
def test_the_vo_on_a_distorted_rendering_is_as_accurate_as_on_the_original(tmp_path):
    """The `default` asset re-imaged through an EuRoC-like radial-tangential camera (sensor.yaml
    only, as in an EuRoC folder): the VO on it against the VO on the original images."""
    src = open_dataset(ASSET)
    pin = src.calibration.intrinsics
    w, h = src.calibration.width, src.calibration.height
    c = coefficients(*EUROC_COEFFS)
    # the distorted camera's focal length: the smallest (of a 2 % ladder) whose every pixel
    # the original pinhole image covers
    u, v = pixels(w, h)
    for f in pin["fx"] * 1.02 ** np.arange(40):
        x, y = undistort((u - pin["cx"]) / f, (v - pin["cy"]) / f, c)
        map_u = (pin["fx"] * x + pin["cx"]).astype(np.float32)
        map_v = (pin["fy"] * y + pin["cy"]).astype(np.float32)
        if map_u.min() >= 0 and map_v.min() >= 0 and map_u.max() <= w - 1 and map_v.max() <= h - 1:
            break
    root = tmp_path / "distorted"
    shutil.copytree(ASSET, root, ignore=shutil.ignore_patterns("calib.json", "*.png"))
    for frame in src.frames():
        out = cv2.remap(frame.image, map_u, map_v, cv2.INTER_LINEAR)
        cv2.imwrite(str(root / "mav0" / "cam0" / "data" / frame.path.name), out)
    write_sensor_yaml(root / "mav0" / "cam0" / "sensor.yaml", np.eye(4), (w, h),
                      [f, f, pin["cx"], pin["cy"]], distortion_model="radial-tangential",
                      distortion_coefficients=list(EUROC_COEFFS))
    distorted = open_dataset(root)
    assert distorted.undistortion is not None

    def ate(dataset) -> float:
        result = run_vo(dataset, VoConfig(), progress=False)
        assert result.restarts == 0
        return absolute_trajectory_error(result.trajectory, dataset.ground_truth).rmse

    reference = ate(src)  # measured: 0.096 m over 18 m
    undistorted = ate(distorted)  # 0.091 m; with the distortion ignored 0.33 m
    path = src.ground_truth.path_length()
    assert undistorted < max(2.0 * reference, 0.01 * path)
    # the same images with the distortion ignored (a pinhole of the same focal length)
    write_calibration(root / "calib.json", Calibration("pinhole", dict(fx=f, fy=f, cx=pin["cx"],
                                                                        cy=pin["cy"]), w, h))
    ignored = open_dataset(root)
    assert ignored.undistortion is None
    assert ate(ignored) > 2.0 * undistorted
