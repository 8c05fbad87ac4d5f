"""Camera sensor model (numpy and numba, no bpy): noise statistics against the configured
electronics, fixed pattern, auto exposure, vignetting, motion blur against an independent
box filter; Mars terrain appearance statistics (Golombek-Rapp rocks, crater sizes, ripples);
validation of the [sensor] table."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from granite.errors import ConfigError
from simulation.scenario import CameraConfig, SensorConfig, TerrainConfig, load_scenario
from simulation.sensor import (
    Sensor,
    blur_taps,
    conversion_gain,
    exposure_scale,
    motion_blur,
    output_gain,
    vignetting,
)

CAM = CameraConfig(width=320, height=240, fx=200.0, fy=200.0, cx=159.5, cy=119.5)
#: only the electronics: no optics, no fixed pattern
BARE = SensorConfig(psf_sigma=0.0, corner_illumination=1.0, prnu=0.0, dsnu=0.0,
                    motion_blur=False)


def _ramp(lo=0.005, hi=0.7) -> np.ndarray:
    """Linear RGB (240, 320, 3): radiance growing along x, constant down each column."""
    r = np.tile(np.linspace(lo, hi, 320, dtype=np.float32), (240, 1))
    return np.dstack([r, r, r])


def _noise_fit(cfg, frame=0):
    noisy, _ = Sensor(cfg, CAM, 11, grayscale=True).capture(_ramp(), frame)
    clean, _ = Sensor(cfg, CAM, 11, grayscale=True, ideal=True).capture(_ramp(), frame)
    d = noisy.astype(np.float64) - clean
    mean, var = clean.mean(axis=0), d.var(axis=0)
    ok = (mean > 3) & (mean < 250)  # away from the black and white clips
    slope, intercept = np.polyfit(mean[ok], var[ok], 1)
    return slope, intercept, mean, var


def test_noise_variance_grows_linearly_with_the_signal_at_the_configured_gain():
    for cfg in (BARE, dataclasses.replace(BARE, full_well=2000.0, read_noise=6.0),
                dataclasses.replace(BARE, analog_gain=2.0)):
        slope, intercept, _, _ = _noise_fit(cfg)
        assert slope == pytest.approx(output_gain(cfg), rel=0.2)
        # the floor: read noise in output DN, plus the rounding of both images
        k = output_gain(cfg)
        floor = (cfg.read_noise * k) ** 2
        assert intercept < floor + 0.5
        assert intercept > -0.5


def test_shot_noise_dominates_the_read_noise_floor_in_bright_pixels():
    slope, intercept, mean, var = _noise_fit(BARE)
    bright = var[(mean > 150) & (mean < 240)].mean()
    assert bright > 4 * (BARE.read_noise * output_gain(BARE)) ** 2 + 1.0


def test_same_seed_and_frame_bit_identical_other_frame_other_noise():
    s = Sensor(SensorConfig(motion_blur=False), CAM, 3, grayscale=True)
    a, _ = s.capture(_ramp(), 7)
    b, _ = Sensor(SensorConfig(motion_blur=False), CAM, 3, grayscale=True).capture(_ramp(), 7)
    c, _ = s.capture(_ramp(), 8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_fixed_pattern_is_fixed_and_has_the_configured_prnu():
    cfg = dataclasses.replace(BARE, prnu=0.05, read_noise=0.0)
    s = Sensor(cfg, CAM, 5, grayscale=True)
    flat = np.full((240, 320, 3), 0.4, np.float32)
    frames = np.stack([s.capture(flat, i)[0].astype(np.float64) for i in range(12)])
    temporal_mean = frames.mean(axis=0)  # shot noise averages out, the pattern stays
    rel = temporal_mean.std() / temporal_mean.mean()
    shot = np.sqrt(output_gain(cfg) * temporal_mean.mean() / 12) / temporal_mean.mean()
    assert np.sqrt(max(rel**2 - shot**2, 0.0)) == pytest.approx(0.05, rel=0.15)
    other = Sensor(cfg, CAM, 6, grayscale=True).capture(flat, 0)[0].astype(np.float64)
    assert np.corrcoef(other.ravel(), temporal_mean.ravel())[0, 1] < 0.3  # other sensor


def test_auto_exposure_puts_the_mean_at_the_target():
    cfg = dataclasses.replace(BARE, ae_target=0.25)
    rad = _ramp()[..., 0] * 0.01  # a dim scene: exposure compensates
    scale = exposure_scale(cfg, rad)
    adc_mean = np.mean(rad) * scale * conversion_gain(cfg)
    assert adc_mean == pytest.approx(0.25 * (2**cfg.adc_bits - 1), rel=1e-6)
    img, _ = Sensor(cfg, CAM, 1, grayscale=True, ideal=True).capture(np.dstack([rad] * 3), 0)
    assert img.mean() == pytest.approx(0.25 * 255, rel=0.02)


def test_vignetting_corner_and_centre():
    cfg = SensorConfig(corner_illumination=0.6)
    v = vignetting(cfg, (240, 320), CAM.cx, CAM.cy)
    assert v[0, 0] == pytest.approx(0.6, rel=1e-6)
    assert v[120, 160] == pytest.approx(1.0, abs=1e-4)
    assert np.all(np.diff(v[120, 160:]) <= 0)  # falls off monotonically


@pytest.mark.parametrize("model", ["pinhole", "kb4"])
def test_blur_sampling_maps_follow_the_scene_points_through_the_camera_models(model):
    """The one-pass kernel's sampling maps q - f(q) equal those of the vectorised camera
    model (unproject at the planar depth, move into the sub-exposure camera, project), sky
    pixels included, for a turned and moved camera."""
    from scipy.spatial.transform import Rotation

    from simulation.sensor import _blur_maps, _project, _unproject

    cam = dataclasses.replace(CAM, model=model)
    rng = np.random.default_rng(3)
    depth = rng.uniform(2.0, 30.0, (240, 320)).astype(np.float32)
    depth[:20] = np.inf  # sky
    T_mid, T_k = np.eye(4), np.eye(4)
    T_mid[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    T_mid[:3, 3] = [1.0, 2.0, 3.0]
    T_k[:3, :3] = T_mid[:3, :3] @ Rotation.from_rotvec([0.004, 0.006, -0.003]).as_matrix()
    T_k[:3, 3] = T_mid[:3, 3] + [0.05, -0.02, 0.03]
    p_w = _unproject(cam, depth) @ T_mid[:3, :3].T + T_mid[:3, 3]
    q = _project(cam, (p_w - T_k[:3, 3]) @ T_k[:3, :3])
    v, u = np.mgrid[0:240, 0:320]
    map_u, map_v = np.empty((240, 320), np.float32), np.empty((240, 320), np.float32)
    M = T_k[:3, :3].T @ T_mid[:3, :3]
    b = T_k[:3, :3].T @ (T_mid[:3, 3] - T_k[:3, 3])
    _blur_maps(depth, model != "pinhole", cam.fx, cam.fy, cam.cx, cam.cy, M, b, map_u, map_v)
    assert np.abs(q[..., 0] - u).max() > 1.0  # the camera moved: a real flow
    np.testing.assert_allclose(map_u, 2 * u - q[..., 0], atol=1e-3)
    np.testing.assert_allclose(map_v, 2 * v - q[..., 1], atol=1e-3)


def test_motion_blur_of_a_sideways_move_is_a_box_filter():
    """Camera moving along x past a fronto-parallel plane at 5 m: the flow is the same at
    every pixel, so the blur must equal an independent horizontal box average."""
    rng = np.random.default_rng(0)
    img = rng.random((240, 320)).astype(np.float32)
    depth = np.full((240, 320), 5.0, np.float32)
    T = np.eye(4)
    k = 5
    shift_px = 8.0  # total blur length over the exposure
    poses = []
    for tau in np.linspace(-0.5, 0.5, k):
        P = np.eye(4)
        P[0, 3] = tau * shift_px * 5.0 / CAM.fx
        poses.append(P)
    blurred = motion_blur(img, depth, CAM, T, np.array(poses))
    # camera moves +x: the scene moves -x in the image by tau * shift_px
    expected = np.zeros_like(img)
    xs = np.arange(320, dtype=np.float64)
    for tau in np.linspace(-0.5, 0.5, k):
        src = xs + tau * shift_px  # pixel q shows the mid-exposure image at q - flow
        expected += np.array([np.interp(src, xs, row) for row in img])
    expected /= k
    inner = np.s_[:, 12:-12]
    np.testing.assert_allclose(blurred[inner], expected[inner], atol=1e-4)
    assert blur_taps(depth, CAM, T, (poses[0], poses[-1])) == 9  # one per pixel of blur


def test_golombek_rapp_rocks_cover_the_modelled_area():
    from simulation.terrain.heightfield import golombek_rapp_q, golombek_rapp_sizes

    k, d_min, d_max, area = 0.08, 0.15, 2.0, 40000.0
    d = golombek_rapp_sizes(np.random.default_rng(1), area, d_min, d_max, k)
    q = golombek_rapp_q(k)
    covered = np.sum(np.pi * d**2 / 4) / area
    assert covered == pytest.approx(k * (np.exp(-q * d_min) - np.exp(-q * d_max)), rel=0.08)
    # and the cumulative area of rocks >= 0.5 m follows F(D) = k exp(-q D)
    big = np.sum(np.pi * d[d >= 0.5] ** 2 / 4) / area
    assert big == pytest.approx(k * (np.exp(-q * 0.5) - np.exp(-q * d_max)), rel=0.2)


def test_crater_sizes_follow_the_configured_exponent():
    from simulation.terrain.heightfield import make_craters

    cfg = TerrainConfig(extent=1000.0, crater_density=40.0, crater_min_diameter=2.0,
                        crater_max_diameter=200.0, crater_size_exponent=2.5)
    d = make_craters(cfg, 4).diameters
    assert np.mean(d > 4.0) == pytest.approx(2.0**-2.5, rel=0.15)


def test_ripples_cover_the_configured_fraction_and_run_across_the_wind():
    from simulation.terrain.appearance import ripple_mask, ripple_uv

    cfg = TerrainConfig(ripple_coverage=0.3, ripple_azimuth=90.0, ripple_wavelength=0.5)
    xy = np.random.default_rng(2).uniform(-128, 128, (20000, 2))
    assert np.mean(ripple_mask(cfg, 9, xy)) == pytest.approx(0.3, abs=0.06)
    # wind from the east (azimuth 90): u advances one tile per RIPPLES_PER_TILE wavelengths
    # along +x and not at all along +y
    from simulation.terrain.textures import RIPPLES_PER_TILE

    uv = ripple_uv(np.array([[0.0, 0.0], [0.5 * RIPPLES_PER_TILE, 0.0], [0.0, 3.0]]), cfg)
    assert uv[1, 0] - uv[0, 0] == pytest.approx(1.0, abs=1e-6)
    assert uv[2, 0] - uv[0, 0] == pytest.approx(0.0, abs=1e-6)


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, message", [
    ("[sensor]\nfull_well = 10.0\n", "sensor.full_well must be in [100, 1e+07], got 10.0"),
    ("[sensor]\nprnu = 0.9\n", "sensor.prnu must be in"),
    ("[sensor]\nadc_bits = 20\n", "sensor.adc_bits must be in"),
    ("[sensor]\noutput_bits = 12\n", "sensor.output_bits must be one of"),
    ("[sensor]\ntransfer = \"log\"\n", "sensor.transfer must be one of"),
    ("[sensor]\nexposure_time = 0.2\n", "must be shorter than the frame interval"),
    ("[sensor]\nenabled = 1\n", "sensor.enabled must be true or false"),
    ("[sensor]\nshutter = 1\n", "unknown key sensor.shutter"),
    ("[render]\nmotion_blur = true\n", "are both on"),
    ("[terrain]\nripple_coverage = 2.0\n", "terrain.ripple_coverage must be in"),
    ("[terrain]\nrock_model = \"poisson\"\n", "terrain.rock_model must be one of"),
])
def test_bad_sensor_and_terrain_values(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("(", r"\(")
                       .replace("+", r"\+")):
        load_scenario(path)


def test_cli_bad_sensor_value_one_line_exit_2_before_rendering(tmp_path, capsys):
    from simulation import cli

    path = _write(tmp_path, "[sensor]\nread_noise = -1.0\n")
    code = cli.main(["render", str(path), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and "sensor.read_noise" in err
    assert not (tmp_path / "o").exists()


def test_every_bundled_scenario_has_the_sensor_on():
    from simulation.scenario import SCENARIO_DIR

    for path in sorted(SCENARIO_DIR.glob("*.toml")):
        s = load_scenario(path)
        assert s.sensor.enabled, path.name
        assert "[sensor]" in path.read_text()
