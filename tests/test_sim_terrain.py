"""Terrain model in pure numpy: heightfield interpolation, craters, rocks, tiling texture,
determinism; depth files and image post-processing."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from simulation.depth import read_depth, write_depth
from simulation.imaging import linear_to_srgb
from simulation.scenario import TerrainConfig
from simulation.terrain.appearance import rotated_tile, tile_uv
from simulation.terrain.heightfield import Heightfield, crater_profile, grid_axis
from simulation.terrain.model import make_terrain_model
from simulation.terrain.noise import perlin
from simulation.terrain.rocks import N_PROTOTYPES
from simulation.terrain.textures import periodic_gradient, make_surface_texture

SMALL = TerrainConfig(extent=64.0, resolution=0.5, far_extent=200.0, crater_density=30.0,
                      crater_max_diameter=20.0, rock_density=0.2, rock_model="power_law",
                      rock_min_diameter=0.1)


@pytest.fixture(scope="module")
def model():
    return make_terrain_model(SMALL, 3)


def test_grid_axis_is_uniform_inside_and_grows_outside():
    xs = grid_axis(64.0, 0.5, 200.0)
    inner = xs[(xs >= -32) & (xs <= 32)]
    np.testing.assert_allclose(np.diff(inner), 0.5)
    assert xs[0] <= -200 and xs[-1] >= 200 and np.all(np.diff(xs) > 0)
    steps = np.diff(xs[xs > 32])
    assert np.all(steps[1:] > steps[:-1])


def test_height_at_matches_the_rendered_triangles(model):
    hf = model.heightfield
    verts, tris = hf.triangles()
    # at vertices: exactly the grid
    i, j = 70, 41
    assert hf.height_at(hf.xs[j], hf.ys[i]) == hf.z[i, j]
    # inside triangles: the plane through the triangle's three vertices
    rng = np.random.default_rng(0)
    for t in rng.choice(len(tris), 50, replace=False):
        a, b, c = verts[tris[t]]
        w = rng.dirichlet([1, 1, 1])
        p = w @ np.stack([a, b, c])
        assert abs(hf.height_at(p[0], p[1]) - p[2]) < 1e-9


def test_same_seed_same_terrain_other_seed_other_terrain():
    a = Heightfield(SMALL, 5)
    b = Heightfield(SMALL, 5)
    c = Heightfield(SMALL, 6)
    np.testing.assert_array_equal(a.z, b.z)
    assert np.abs(a.z - c.z).mean() > 0.1


def test_noise_is_continuous_and_seeded():
    x = np.linspace(0, 3, 3001)
    n = perlin(x, 0.37 * np.ones_like(x), 1)
    assert np.max(np.abs(np.diff(n))) < 0.01  # no jumps at lattice lines
    assert np.allclose(perlin(np.arange(5.0), np.arange(5.0), 1), 0.0)  # zero on the lattice
    assert not np.allclose(n, perlin(x, 0.37 * np.ones_like(x), 2))


def test_crater_has_bowl_and_raised_rim():
    rho = np.linspace(0, 3, 601)
    h = crater_profile(rho, depth=2.0, rim=0.5)
    assert h[0] == pytest.approx(-2.0, abs=0.05)
    k = np.argmax(h)
    assert 0.85 < rho[k] < 1.15 and 0.3 < h[k] <= 0.5  # rounded rim crest
    assert np.all(h[rho >= 2.2] == 0.0)
    assert np.max(np.abs(np.diff(h))) < 0.05  # continuous


def test_craters_are_carved_into_the_terrain(model):
    hf = model.heightfield
    big = np.argmax(hf.craters.diameters)
    (cx, cy), d = hf.craters.centers[big], hf.craters.diameters[big]
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = hf.height_at(cx + 0.5 * d * np.cos(ang), cy + 0.5 * d * np.sin(ang)).mean()
    centre = hf.height_at(cx, cy)
    assert rim - centre > 0.5 * hf.craters.depths[big]


def test_rocks_power_law_and_resting_on_ground(model):
    rocks = model.rocks
    n = len(rocks)
    assert n > 200
    d = 2 * rocks.scale[:, 0]
    assert d.min() >= SMALL.rock_min_diameter - 1e-9 and d.max() <= SMALL.rock_max_diameter
    # cumulative N(>D) ~ D^-2.2: twice the diameter, 2^-2.2 of the rocks
    ratio = np.mean(d > 2 * SMALL.rock_min_diameter)
    assert ratio == pytest.approx(2 ** -SMALL.rock_size_exponent, rel=0.2)
    ground = model.ground_height(rocks.location[:, 0], rocks.location[:, 1])
    assert np.all(rocks.location[:, 2] < ground)  # partly buried
    assert np.all(rocks.top > ground)  # but sticking out
    assert rocks.proto.max() < 2 * N_PROTOTYPES
    # small rocks use the coarse prototypes
    assert np.all(rocks.proto[d < 0.3] >= N_PROTOTYPES)


def test_surface_height_includes_rock_tops(model):
    rocks = model.rocks
    k = int(np.argmax(rocks.top - model.ground_height(rocks.location[:, 0], rocks.location[:, 1])))
    x, y = rocks.location[k, :2]
    assert model.surface_height(x, y)[0] >= rocks.top[k]
    assert model.surface_height(x, y)[0] > model.ground_height(x, y)


def test_texture_tiles_seamlessly_and_slopes_are_exact():
    tex = make_surface_texture(4, size=128)
    height = tex[..., 3]
    # periodic: the wrap-around step is like any other step
    inner = np.abs(np.diff(height, axis=1)).max()
    assert np.abs(height[:, 0] - height[:, -1]).max() <= 1.5 * inner
    # stored slopes are the derivative of the stored height (up to the RMS normalisation)
    gu, gv = periodic_gradient(height)
    scale = np.sum(tex[..., 0] * gu) / np.sum(gu * gu)
    np.testing.assert_allclose(tex[..., 0], scale * gu, atol=1e-3 * np.abs(tex[..., 0]).max())
    np.testing.assert_allclose(tex[..., 1], scale * gv, atol=1e-3 * np.abs(tex[..., 1]).max())
    np.testing.assert_array_equal(tex, make_surface_texture(4, size=128))
    assert abs(tex[..., 2].mean() - 0.5) < 1e-3


def _fourier_eval(img: np.ndarray, uv: np.ndarray) -> float:
    """Band-limited periodic interpolant of ``img`` (rows = v) at tile coordinates uv."""
    n = img.shape[0]
    f = np.fft.fftfreq(n) * n
    # texel (row r, column c) sits at uv = ((c + 0.5) / n, (r + 0.5) / n)
    u, v = uv[0] * n - 0.5, uv[1] * n - 0.5
    phase = np.exp(2j * np.pi * (f[None, :] * u + f[:, None] * v) / n)
    return float(np.real(np.sum(np.fft.fft2(img) * phase)) / n**2)


def test_rotated_slopes_match_world_gradient():
    """Layer k stores the world-frame gradient of its relief s * height(u(p)) (amplitude
    proportional to the tile size s), normalised by the tile's RMS slope."""
    tex = make_surface_texture(2, size=256)  # the production size (band-limited below Nyquist)
    gu, gv = periodic_gradient(tex[..., 3].astype(np.float64))
    rms = np.sqrt(np.mean(gu**2 + gv**2) / 2.0)
    for k, scale in ((0, 0.7), (2, 3.0)):
        layer = rotated_tile(tex, k)
        for p in (np.array([0.31, -0.47]), np.array([2.2, 5.9])):
            eps = 2e-4 * scale  # tile_uv is float32: not smaller, to keep rounding small

            def relief(q):
                return scale * _fourier_eval(tex[..., 3], tile_uv(q[None], scale, k)[0] % 1.0)

            g = np.array([relief(p + [eps, 0]) - relief(p - [eps, 0]),
                          relief(p + [0, eps]) - relief(p - [0, eps])]) / (2 * eps)
            uv = tile_uv(p[None], scale, k)[0].astype(np.float64) % 1.0
            stored = np.array([_fourier_eval(layer[..., 0], uv), _fourier_eval(layer[..., 1], uv)])
            np.testing.assert_allclose(stored * rms, g, rtol=1e-2, atol=1e-2 * np.abs(g).max())


def test_depth_files_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.6, 300.0, (24, 32)).astype(np.float32)
    depth[0, :5] = np.inf
    write_depth(tmp_path / "d.npy", depth, "npy")
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy"), depth)
    write_depth(tmp_path / "d.png", depth, "inv16")
    back = read_depth(tmp_path / "d.png")
    assert np.all(np.isinf(back[0, :5]))
    fin = np.isfinite(depth)
    # inverse depth quantised to 1 / 32767.5 per metre
    np.testing.assert_allclose(1 / back[fin], 1 / depth[fin], atol=0.51 / 32767.5)


def test_srgb_transfer_function():
    x = np.array([0.0, 0.002, 0.0031308, 0.2, 1.0, 1.5])
    y = linear_to_srgb(x)
    assert y[1] == pytest.approx(12.92 * 0.002)
    assert y[3] == pytest.approx(1.055 * 0.2 ** (1 / 2.4) - 0.055)
    assert y[4] == pytest.approx(1.0) and y[5] == pytest.approx(1.0)  # clipped
    assert np.all(np.diff(y[:5]) > 0)


def test_config_is_hashable_for_the_model_cache():
    assert hash(dataclasses.replace(SMALL, seed_offset=0) if False else SMALL)
