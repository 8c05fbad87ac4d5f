"""Optical-flow frontend: pyramid, patterns, patch kernels, detection and tracking on
synthetic images warped by known transforms (ground truth = the analytic mapping)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from granite.errors import ConfigError
from granite.optical_flow import (
    FrameRejectedWarning,
    FrameToFrameOpticalFlow,
    OpticalFlowConfig,
    build_pyramid,
)
from granite.optical_flow.detection import (
    _mark_occupied,
    cell_layout,
    detect_in_cells,
    detect_new_points,
    occupied_cells,
)
from granite.optical_flow.patch import interp, interp_grad, make_template
from granite.optical_flow.patterns import pattern52, pattern52_raw
from granite.optical_flow.synthetic import apply_affine, similarity, textured_image, warp
from granite.optical_flow.tracking import new_template_cache, track_points

H, W = 480, 640
CENTRE = (W / 2, H / 2)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return textured_image(H, W, seed=1)


def track_pair(img0, img1, config=None):
    """Run the frontend on two frames; return (positions in 0, positions in 1, result0, result1)
    for the tracks present in both."""
    flow = FrameToFrameOpticalFlow(config)
    r0 = flow.process(0.0, img0)
    r1 = flow.process(0.1, img1)
    _, i0, i1 = np.intersect1d(r0.ids, r1.ids, return_indices=True)
    return r0.positions[i0], r1.positions[i1], r0, r1


# --------------------------------------------------------------------------- config


def test_config_defaults_are_the_reference_values():
    c = OpticalFlowConfig()
    assert (c.levels, c.grid_size, c.iterations, c.border) == (6, 40, 6, 19)
    assert c.pattern_scale == 0.75 and c.fb_threshold_sq == 0.03
    assert c.fast_thresholds == (40, 20, 10, 5)
    assert c.detection_levels == (0, 1, 2, 3, 4)
    assert OpticalFlowConfig(detect_all_levels=False).detection_levels == (0,)
    assert OpticalFlowConfig.from_dict(c.to_dict()) == c


@pytest.mark.parametrize(
    "values",
    [{"levels": 6, "grid": 40}, {"levels": 0}, {"levels": 2.5}, {"detect_all_levels": 1},
     {"fb_threshold_sq": -1.0}, {"fast_min_threshold": 50}, {"margin": 1.0}],
)
def test_config_rejects_unknown_keys_and_bad_values(values):
    with pytest.raises(ConfigError):
        OpticalFlowConfig.from_dict(values)


# --------------------------------------------------------------------------- building blocks


def test_pattern52_is_the_reference_diamond():
    raw = pattern52_raw()
    assert raw.shape == (52, 2) and len({tuple(p) for p in raw}) == 52
    assert np.all(np.abs(raw) <= 7) and np.all(raw % 2 == 1)  # odd offsets: 2 px lattice
    np.testing.assert_array_equal(np.sort(raw, axis=0), np.sort(-raw, axis=0))  # symmetric
    assert np.all(np.abs(raw).sum(axis=1) <= 10)  # diamond: |x| + |y| <= 10
    np.testing.assert_allclose(pattern52(0.75), 0.75 * raw)


def test_pyramid_maps_level0_coordinates_by_powers_of_two():
    """A Gaussian blob at a known sub-pixel position: its intensity centroid on level l is
    at x0 / 2**l (the convention the tracker relies on)."""
    x0, y0 = 301.3, 170.6
    yy, xx = np.mgrid[0:H, 0:W]
    blob = 20 + 200 * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / 12.0**2)
    pyr = build_pyramid(np.rint(blob).astype(np.uint8), 5)
    for lvl in range(5):
        im = pyr.level(lvl).astype(np.float64) - 20.0
        ly, lx = np.mgrid[0 : im.shape[0], 0 : im.shape[1]]
        cx, cy = (im * lx).sum() / im.sum(), (im * ly).sum() / im.sum()
        assert abs(cx - x0 / 2**lvl) < 0.02 and abs(cy - y0 / 2**lvl) < 0.02, lvl


@pytest.mark.parametrize("shape", [(370, 1226), (33, 17), (1, 1)])
def test_pyramid_handles_odd_sizes_and_16_bit(shape):
    img = (np.arange(shape[0] * shape[1]) % 4096).reshape(shape).astype(np.uint16)
    pyr = build_pyramid(img, 6)
    h, w = shape
    for lvl in range(6):
        assert pyr.level(lvl).shape == (h, w) and pyr.level(lvl).dtype == np.float32
        h, w = (h + 1) // 2, (w + 1) // 2
    np.testing.assert_array_equal(pyr.level(0), img.astype(np.float32))
    np.testing.assert_allclose(pyr.level(1), cv2.pyrDown(img.astype(np.float32)))
    assert pyr.level_uint8(0).max() == round(img.max() * 255 / 65535)


def test_bilinear_value_and_gradient_are_exact_on_a_plane():
    yy, xx = np.mgrid[0:20, 0:30].astype(np.float32)
    plane = (5.0 + 1.5 * xx + 0.25 * yy).ravel()
    for x, y in [(2.0, 2.0), (7.3, 11.9), (26.99, 16.5)]:
        assert interp(plane, 0, 30, x, y) == pytest.approx(5 + 1.5 * x + 0.25 * y, abs=1e-4)
        v, gx, gy = interp_grad(plane, 0, 30, x, y)
        assert (v, gx, gy) == pytest.approx((5 + 1.5 * x + 0.25 * y, 1.5, 0.25), abs=1e-4)


def test_template_jacobian_matches_finite_differences():
    """J of the mean-normalised patch w.r.t. an SE(2) increment on the pattern side, checked
    by central differences of the analytic patch of a smooth image."""

    def intensity(x, y):
        return 100 + 30 * np.sin(x / 9.0 + 0.3) * np.cos(y / 7.0) + 20 * np.cos((x + 2 * y) / 13.0)

    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = intensity(xx, yy).astype(np.float32)
    pat = pattern52(0.75)
    st, data, valid, jac, aux = (a[0, 0] for a in new_template_cache(1, 1, 52))
    cx, cy = 211.4, 137.7
    assert make_template(img.ravel(), 0, W, H, cx, cy, pat, 2.0, data, valid, jac, aux) == 2

    def patch(xi):
        c, s = np.cos(xi[2]), np.sin(xi[2])
        a, b = (np.sin(xi[2]) / xi[2], (1 - np.cos(xi[2])) / xi[2]) if xi[2] else (1.0, 0.0)
        t = np.array([a * xi[0] - b * xi[1], b * xi[0] + a * xi[1]])
        pts = pat @ np.array([[c, -s], [s, c]]).T + t + (cx, cy)
        v = intensity(pts[:, 0], pts[:, 1])
        return v / v.mean()

    np.testing.assert_allclose(data, patch(np.zeros(3)), atol=2e-3)  # bilinear vs analytic
    eps = 1e-4
    numeric = np.stack([(patch(eps * e) - patch(-eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
    scale = np.abs(numeric).max(axis=0)
    assert np.all(np.abs(jac - numeric).max(axis=0) < 0.03 * scale)
    normal = jac.astype(np.float64).T @ jac
    np.testing.assert_allclose(aux[:3] @ normal, np.eye(3), atol=1e-3)
    np.testing.assert_allclose(aux[3], jac.astype(np.float64).T @ data, rtol=1e-4, atol=1e-4)


def test_patch_zncc_of_the_template_arrays_is_the_correlation_of_the_samples(texture):
    """``patch_zncc_at`` (the tracker's ZNCC on its template arrays) against the correlation
    computed with numpy from the samples: inside the image (the vectorised path for a complete
    template), near the border (the sample-by-sample path) and for a template with invalid
    samples."""
    from granite.optical_flow.patch import interp, patch_zncc_at, pattern_radius
    from granite.optical_flow.patterns import grid_pattern

    img = texture.astype(np.float32)
    buf = img.ravel()
    pat = grid_pattern(11, 0.75)
    st, data, valid, jac, aux = new_template_cache(3, 1, len(pat))
    centres = [(211.4, 137.7), (5.3, 150.2), (3.1, 4.2)]  # inside, at the border, mostly outside
    for k, (cx, cy) in enumerate(centres):
        st[k, 0] = make_template(buf, 0, W, H, cx, cy, pat, 2.0, data[k, 0], valid[k, 0], jac[k, 0],
                                 aux[k, 0])
    assert list(st[:, 0]) == [2, 1, 0]
    radius = pattern_radius(pat)
    for k, (cx, cy) in enumerate(centres[:2]):
        tx, ty, theta = cx + 0.4, cy - 0.3, 0.05
        c, s = np.cos(theta), np.sin(theta)
        xy = pat @ np.array([[c, -s], [s, c]]).T + (tx, ty)
        use = valid[k, 0] & (xy[:, 0] >= 2) & (xy[:, 1] >= 2) & (xy[:, 0] <= W - 3) & (xy[:, 1] <= H - 3)
        v = np.array([interp(buf, 0, W, x, y) for x, y in xy[use]])
        expected = np.corrcoef(data[k, 0][use].astype(np.float64), v)[0, 1]
        zn = patch_zncc_at(buf, 0, W, H, tx, ty, theta, pat, radius, 2.0, st[k, 0], data, valid, k, 0)
        assert zn == pytest.approx(expected, abs=1e-6) and 0.5 < zn < 1.0  # one-pass sums


# --------------------------------------------------------------------------- tracking accuracy


@pytest.mark.parametrize(
    "name, affine",
    [
        ("translation", similarity(12.3, -7.6, 0.0, 1.0, CENTRE)),
        ("rotation 5 deg", similarity(0.0, 0.0, np.radians(5), 1.0, CENTRE)),
        ("scale 3 %", similarity(0.0, 0.0, 0.0, 1.03, CENTRE)),
        ("combined", similarity(9.4, 5.2, np.radians(4), 1.02, CENTRE)),
        ("large translation", similarity(45.5, -30.2, np.radians(2), 1.0, CENTRE)),
    ],
)
def test_tracks_a_known_warp_with_sub_tenth_pixel_median_error(texture, name, affine):
    p0, p1, r0, _ = track_pair(texture, warp(texture, affine))
    err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    inside = apply_affine(affine, r0.positions)
    n_visible = np.sum((inside >= 25).all(axis=1) & (inside[:, 0] < W - 25) & (inside[:, 1] < H - 25))
    assert len(p0) >= 0.7 * n_visible, name
    assert np.median(err) < 0.1, name
    assert np.mean(err < 1.0) > 0.98, name


def test_coarse_to_fine_is_what_follows_large_motion(texture):
    affine = similarity(45.5, -30.2, 0.0, 1.0, CENTRE)
    single = OpticalFlowConfig(levels=1, retry_min_flow=0.0, global_retry_min_lost=0.0)
    p0, p1, _, _ = track_pair(texture, warp(texture, affine), single)
    good = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1) < 0.5
    assert good.sum() < 5  # a single level cannot follow 55 px


def test_median_flow_retry_recovers_points_without_usable_coarse_levels(texture):
    """80 px: only points whose coarsest levels hold a whole patch follow on the first pass;
    the retry from their median displacement recovers most of the others. (Reference pyramid,
    no pre-smoothing: on this smooth synthetic texture, pre-smoothing lets a few zero-motion
    tracks settle in a false minimum that the forward-backward check accepts; see
    docs/optical_flow.md.)"""
    affine = similarity(80.0, -20.0, np.radians(2), 1.0, CENTRE)
    img1 = warp(texture, affine)
    counts = {}
    for retry in (0.0, 2.0):
        config = OpticalFlowConfig(retry_min_flow=retry, local_retry_rounds=0, presmooth_sigma=0.0,
                                   global_retry_min_lost=0.0)
        p0, p1, r0, _ = track_pair(texture, img1, config)
        truth = apply_affine(affine, p0)
        # The warp mirrors the image at its border: judge points that stay in view.
        visible = (truth >= 10).all(axis=1) & (truth[:, 0] < W - 10) & (truth[:, 1] < H - 10)
        err = np.linalg.norm(p1 - truth, axis=1)[visible]
        assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.95  # 80 px: a rare false match
        counts[retry] = len(p0)
    pred = apply_affine(affine, r0.positions)
    n_visible = np.sum((pred >= 25).all(axis=1) & (pred[:, 0] < W - 25) & (pred[:, 1] < H - 25))
    assert counts[0.0] < 0.5 * n_visible and counts[2.0] > 0.9 * n_visible


def test_brightness_change_is_tolerated(texture):
    affine = similarity(5.2, -3.1, np.radians(2), 1.0, CENTRE)
    dark = (warp(texture, affine) * 0.6).astype(np.uint8)
    p0, p1, r0, _ = track_pair(texture, dark)
    err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    assert len(p0) > 0.85 * len(r0) and np.median(err) < 0.1


def test_presmoothing_keeps_tracks_on_noisy_images():
    """Independent per-frame noise (6 DN on a low-contrast texture) makes the forward-backward
    check drop tracks; a 0.7 px Gaussian before the pyramid keeps them, at equal accuracy."""
    img0 = textured_image(H, W, seed=1, contrast=0.4)
    affine = similarity(5.3, -2.2, np.radians(1), 1.0, CENTRE)
    rng = np.random.default_rng(5)
    frames = [np.clip(im + rng.normal(0.0, 6.0, im.shape), 0, 255).astype(np.uint8)
              for im in (img0, warp(img0, affine))]
    kept, median = {}, {}
    for sigma in (0.0, 0.7):  # with the reference's pattern and fixed limit (isolates the blur)
        config = OpticalFlowConfig(presmooth_sigma=sigma, pattern="pattern52", fb_noise_factor=0.0)
        p0, p1, r0, _ = track_pair(*frames, config)
        kept[sigma] = len(p0) / len(r0)
        median[sigma] = np.median(np.linalg.norm(p1 - apply_affine(affine, p0), axis=1))
    assert kept[0.7] > 0.97 and kept[0.7] > kept[0.0] + 0.08
    assert median[0.7] < 0.2 and median[0.0] < 0.2


@pytest.mark.parametrize("noise", [8.0, 12.0])
def test_dense_pattern_and_noise_scaled_limit_keep_tracks_under_strong_noise(noise):
    """Strong per-frame noise (8-12 DN on a low-contrast texture): the reference's 52-sample
    diamond with the fixed 0.17 px forward-backward limit loses many tracks; the defaults (the
    11x11 lattice, the limit scaled by the expected precision) keep nearly all, and the kept
    tracks stay accurate against the exact motion."""
    img0 = textured_image(H, W, seed=1, contrast=0.4)
    affine = similarity(5.3, -2.2, np.radians(1), 1.0, CENTRE)
    rng = np.random.default_rng(7)
    frames = [np.clip(im + rng.normal(0.0, noise, im.shape), 0, 255).astype(np.uint8)
              for im in (img0, warp(img0, affine))]
    kept, err = {}, {}
    for name, config in (("reference", OpticalFlowConfig(pattern="pattern52", fb_noise_factor=0.0)),
                         ("defaults", OpticalFlowConfig())):
        p0, p1, r0, _ = track_pair(*frames, config)
        kept[name] = len(p0) / len(r0)
        err[name] = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    assert kept["defaults"] > 0.95 and kept["defaults"] > kept["reference"] + 0.1
    # accurate: no worse than the few the reference keeps, within 2x of OpenCV's 21x21 LK (no
    # forward-backward check) on the same points, no gross errors
    pts = r0.positions.astype(np.float32)
    lk, _, _ = cv2.calcOpticalFlowPyrLK(frames[0], frames[1], pts, None, winSize=(21, 21), maxLevel=3)
    lk_median = np.median(np.linalg.norm(lk - apply_affine(affine, pts), axis=1))
    assert np.median(err["defaults"]) <= np.median(err["reference"]) < 2.0 * lk_median
    assert np.median(err["defaults"]) < 2.0 * lk_median and np.mean(err["defaults"] > 2.0) < 0.01


def test_grid_pattern_spans_the_diamond_extent():
    from granite.optical_flow.patterns import grid_pattern, make_pattern
    g = make_pattern("grid11", 0.75)
    assert g.shape == (121, 2) and np.allclose(np.abs(g).max(axis=0), 0.75 * 7.0)
    assert np.allclose(np.diff(np.unique(g[:, 0])), 0.75 * 1.4)
    np.testing.assert_allclose(g.mean(axis=0), 0.0, atol=1e-12)  # centred: no bias
    np.testing.assert_array_equal(make_pattern("pattern52", 0.75), pattern52(0.75))
    with pytest.raises(ValueError):
        make_pattern("grid5")
    assert grid_pattern(2, 1.0).shape == (4, 2)


def test_unit_lattice_is_recognised_exactly():
    """A grid pattern scaled to one-pixel spacing lies on whole (or half) pixels and is taken
    for the unit lattice; any other pattern, or the lattice in another order or shifted by a
    tenth of a pixel, is not."""
    from granite.optical_flow.patch import unit_lattice_side
    from granite.optical_flow.patterns import grid_pattern
    for m in (7, 9, 11, 13):
        g = grid_pattern(m, (m - 1) / 14)
        np.testing.assert_array_equal(2 * g, np.round(2 * g))
        assert unit_lattice_side(g) == m
        assert unit_lattice_side(grid_pattern(m, 0.75)) == 0
    g = grid_pattern(11, 5 / 7)
    assert unit_lattice_side(g[::-1].copy()) == 0
    assert unit_lattice_side(g + 0.1) == 0
    assert unit_lattice_side(pattern52(0.75)) == 0 and unit_lattice_side(pattern52(1.0)) == 0


@pytest.mark.parametrize("m", [7, 11])
def test_lattice_template_equals_the_sample_by_sample_template(m):
    """The separable template of a unit lattice against the general per-sample path on the
    same pattern: centres anywhere, near the border (lattice partly outside: the general path
    runs) and outside."""
    from granite.optical_flow.patch import lattice_workspace, make_template_at, unit_lattice_side
    from granite.optical_flow.patterns import grid_pattern
    img = textured_image(90, 120, seed=5).astype(np.float32) + 20.0
    h, w = img.shape
    pat = grid_pattern(m, (m - 1) / 14)
    assert unit_lattice_side(pat) == m
    rng = np.random.default_rng(3)
    centres = np.vstack([np.column_stack([rng.uniform(0, w, 200), rng.uniform(0, h, 200)]),
                         [[4.3, 40.0], [w - 5.5, 7.25], [60.0, 60.0], [1.0, 1.0]]])
    caches = [new_template_cache(len(centres), 1, m * m) for _ in range(2)]
    ws = lattice_workspace(m)
    states = [[], []]
    for k, (cx, cy) in enumerate(centres):
        for j, lattice in enumerate((m, 0)):
            st, data, valid, jac, aux = caches[j]
            states[j].append(make_template_at(img.ravel(), 0, w, h, cx, cy, pat, 2.0, data, valid,
                                              jac, aux, k, 0, lattice, ws))
    assert states[0] == states[1] and states[0].count(2) > 100 and 0 in states[0] and 1 in states[0]
    ok = np.array(states[0]) > 0
    for a, b in zip(caches[0][1:], caches[1][1:]):
        np.testing.assert_allclose(a[ok], b[ok], rtol=1e-5, atol=1e-5)


def test_presmoothed_pyramid_is_the_blurred_image():
    img = textured_image(60, 80, seed=9)
    pyr = build_pyramid(img, 3, presmooth_sigma=0.7)
    blurred = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7, borderType=cv2.BORDER_REFLECT_101)
    np.testing.assert_allclose(pyr.level(0), blurred, atol=1e-4)
    np.testing.assert_allclose(pyr.level(1), cv2.pyrDown(blurred), atol=1e-4)


@pytest.mark.parametrize("seed", [7, 8])
def test_forward_backward_check_rejects_occluded_patches(texture, seed):
    affine = similarity(3.2, -2.1, np.radians(1), 1.0, CENTRE)
    img1 = warp(texture, affine)
    x0, x1, y0, y1 = 200, 440, 120, 360
    img1[y0:y1, x0:x1] = textured_image(H, W, seed=seed)[y0:y1, x0:x1]
    results = {}
    configs = {"defaults": OpticalFlowConfig(),  # the noise-scaled limit (at most fb_max_sq)
               0.03: OpticalFlowConfig(fb_threshold_sq=0.03, fb_noise_factor=0.0),  # reference
               1e9: OpticalFlowConfig(fb_threshold_sq=1e9, fb_noise_factor=0.0)}  # effectively none
    for thr, config in configs.items():
        flow = FrameToFrameOpticalFlow(config)
        r0 = flow.process(0.0, texture)
        r1 = flow.process(0.1, img1)
        pred = apply_affine(affine, r0.positions)
        m = 12  # patches (±7 px incl. margin) entirely on one side of the boundary
        occluded = (pred[:, 0] > x0 + m) & (pred[:, 0] < x1 - m) & (pred[:, 1] > y0 + m) & (pred[:, 1] < y1 - m)
        clear = (pred[:, 0] < x0 - m) | (pred[:, 0] > x1 + m) | (pred[:, 1] < y0 - m) | (pred[:, 1] > y1 + m)
        survived = np.isin(r0.ids, r1.ids)
        results[thr] = (survived[occluded].mean(), survived[clear].mean(), occluded.sum())
    for limit in ("defaults", 0.03):
        occluded_kept, clear_kept, n_occluded = results[limit]
        assert n_occluded >= 20
        assert occluded_kept <= 0.05 and clear_kept >= 0.9
    assert results[1e9][0] >= 0.9  # without the check the occluded tracks would be kept


# --------------------------------------------------------------------------- detection


def _cell_of(points, lvl, width, height, grid):
    x0, y0, _, _ = cell_layout(width, height, grid)
    q = points / 2**lvl
    return [(int((y - y0) // grid), int((x - x0) // grid)) for x, y in q]


def test_detection_grid_border_and_levels(texture):
    cfg = OpticalFlowConfig()
    pyr = build_pyramid(texture, cfg.levels)
    pts, lvls = detect_new_points(pyr, cfg, np.zeros((0, 2)), np.zeros(0, np.int64))
    assert set(lvls) >= {0, 2}  # corners on coarser levels too
    for lvl in np.unique(lvls):
        w, h = int(pyr.widths[lvl]), int(pyr.heights[lvl])
        q = pts[lvls == lvl] / 2**lvl
        assert np.all(q >= cfg.border) and np.all(q[:, 0] <= w - 1 - cfg.border)
        assert np.all(q[:, 1] <= h - 1 - cfg.border)
        cells = _cell_of(pts[lvls == lvl], lvl, w, h, cfg.grid_size)
        assert len(set(cells)) == len(cells)  # at most one new corner per cell
        assert np.all(np.asarray(cells) >= 0)
    # Neighbouring-level rule: no new corner on level l in a cell holding one from l +- 1.
    for lvl in np.unique(lvls):
        w, h = int(pyr.widths[lvl]), int(pyr.heights[lvl])
        cells = set(_cell_of(pts[lvls == lvl], lvl, w, h, cfg.grid_size))
        for other in (lvl - 1, lvl + 1):
            assert not cells & set(_cell_of(pts[lvls == other], lvl, w, h, cfg.grid_size))
    # 640x480 level 0 has 16 x 12 cells, all textured.
    assert np.sum(lvls == 0) == 16 * 12


def test_occupancy_kernel_matches_the_array_computation():
    """The detection's numba occupancy pass marks exactly the cells :func:`occupied_cells`
    finds for the points within one level, including points on cell edges, outside the grid
    and not finite."""
    rng = np.random.default_rng(3)
    grid = 40
    pts = np.concatenate([
        rng.uniform(-30.0, 680.0, (400, 2)),
        np.array([[40.0 * k, 20.0 * k] for k in range(17)]),  # on cell edges at level 0
        np.array([[np.nan, 10.0], [np.inf, 5.0], [100.0, -np.inf]]),
    ])
    lvls = rng.integers(0, 6, len(pts))
    for lvl in range(4):  # level 4 of 640x480 has no full 40 px cell row
        w, h = (W + (1 << lvl) - 1) >> lvl, (H + (1 << lvl) - 1) >> lvl
        x0, y0, nc, nr = cell_layout(w, h, grid)
        near = (np.abs(lvls - lvl) <= 1) & np.isfinite(pts).all(axis=1)
        expected = occupied_cells(pts[near] / float(1 << lvl), w, h, grid)
        got = np.zeros((nr, nc), dtype=bool)
        _mark_occupied(got, pts, lvls, lvl, x0, y0, grid)
        assert got.any() and (lvl > 0 or not got.all())
        np.testing.assert_array_equal(got, expected)


def test_ablation_detects_on_the_finest_level_only(texture):
    flow = FrameToFrameOpticalFlow(OpticalFlowConfig(detect_all_levels=False))
    r = flow.process(0.0, texture)
    assert len(r) == 192 and np.all(r.levels == 0) and np.all(r.weights == 1.0)


def test_existing_points_block_cells_of_neighbouring_levels_only(texture):
    cfg = OpticalFlowConfig()
    pyr = build_pyramid(texture, cfg.levels)

    def new_cells(existing_level):
        existing = np.array([[300.0, 220.0]])
        pts, lvls = detect_new_points(pyr, cfg, existing, np.array([existing_level]))
        out = {}
        for lvl in (0, 2):
            w, h = int(pyr.widths[lvl]), int(pyr.heights[lvl])
            blocked = _cell_of(existing, lvl, w, h, cfg.grid_size)[0]
            out[lvl] = blocked in _cell_of(pts[lvls == lvl], lvl, w, h, cfg.grid_size)
        return out

    assert new_cells(existing_level=5) == {0: True, 2: True}  # too far from both
    assert new_cells(existing_level=1) == {0: False, 2: False}  # neighbour of both
    assert new_cells(existing_level=2) == {0: True, 2: False}
    assert new_cells(existing_level=0) == {0: False, 2: True}


def test_detection_picks_the_strongest_fast_corner_of_each_cell(texture):
    """Independent check with OpenCV's FAST on the whole image: per cell, the corner with the
    highest response at the first threshold of the halving sequence that finds one."""
    cfg = OpticalFlowConfig()
    pts = detect_in_cells(texture, np.zeros((12, 16), bool), cfg)
    mine = dict(zip(_cell_of(pts, 0, W, H, 40), map(tuple, pts)))
    # This texture has a corner above the initial threshold in every cell.
    kps = cv2.FastFeatureDetector_create(threshold=cfg.fast_threshold).detect(texture)
    best: dict = {}
    for k in kps:
        x, y = k.pt
        if not (19 <= x <= W - 20 and 19 <= y <= H - 20):
            continue
        cell = (int(y // 40), int(x // 40))
        if cell not in best or k.response > best[cell][0]:
            best[cell] = (k.response, (x, y))
    assert len(best) == 192
    same = sum(1 for c, (_, p) in best.items() if mine.get(c) == p)
    assert same >= 0.95 * 192


def test_fast_threshold_halving_finds_corners_in_low_contrast():
    img = textured_image(H, W, seed=4, contrast=0.12)
    found = FrameToFrameOpticalFlow(OpticalFlowConfig(detect_all_levels=False)).process(0, img)
    no_halving = OpticalFlowConfig(detect_all_levels=False, fast_min_threshold=40)
    strict = FrameToFrameOpticalFlow(no_halving).process(0, img)
    assert len(found) > 150 and len(strict) < 0.5 * len(found)


# --------------------------------------------------------------------------- frontend behaviour


def test_sequence_ids_weights_and_positions(texture):
    big = textured_image(700, 900, seed=5)
    flow = FrameToFrameOpticalFlow()
    previous = None
    seen: set[int] = set()
    for k in range(6):
        affine = similarity(-100 - 4.0 * k, -80 - 2.5 * k, np.radians(0.5 * k), 1.0, (450, 350))
        r = flow.process(0.05 * k, warp(big, affine, (W, H)))
        np.testing.assert_array_equal(r.weights, 0.5 ** r.levels.astype(float))
        assert np.all(np.diff(r.ids) > 0)
        assert not (set(r.ids[r.new]) & seen)  # ids are never reused
        seen |= set(r.ids)
        if previous is not None:
            r_prev, a_prev = previous
            _, i0, i1 = np.intersect1d(r_prev.ids, r.ids, return_indices=True)
            assert not r.new[i1].any() and len(i1) > 0.8 * len(r_prev)
            # Map each tracked point back to the big image and forward again.
            inv = cv2.invertAffineTransform(a_prev)
            pred = apply_affine(affine, apply_affine(inv, r_prev.positions[i0]))
            assert np.median(np.linalg.norm(r.positions[i1] - pred, axis=1)) < 0.1
            np.testing.assert_array_equal(r.levels[i1], r_prev.levels[i0])
        assert set(r.timing) == {"pyramid", "detection", "tracking", "total"}
        previous = (r, affine)


@pytest.mark.parametrize(
    "bad, reason",
    [
        (None, "no image"),
        (np.zeros((H, W), np.float32), "uint8 or uint16"),
        (np.zeros((H, W, 3), np.uint8), "uint8 or uint16"),
        (np.zeros((H // 2, W), np.uint8) + 7, "size"),
        (np.full((H, W), 90, np.uint8), "blank"),
    ],
)
def test_unusable_frames_warn_and_give_zero_tracks(texture, bad, reason):
    affine = similarity(4.0, 2.0, 0.0, 1.0, CENTRE)
    flow = FrameToFrameOpticalFlow()
    r0 = flow.process(0.0, texture)
    with pytest.warns(FrameRejectedWarning, match=reason):
        rb = flow.process(0.1, bad)
    assert len(rb) == 0 and rb.rejected and rb.positions.shape == (0, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r2 = flow.process(0.2, warp(texture, affine))  # tracked from the last good frame
    _, i0, i2 = np.intersect1d(r0.ids, r2.ids, return_indices=True)
    assert len(i0) > 0.8 * len(r0)
    assert np.median(np.linalg.norm(r2.positions[i2] - apply_affine(affine, r0.positions[i0]), axis=1)) < 0.1


def test_kitti_sized_16_bit_images():
    h, w = 370, 1226
    img8 = textured_image(h, w, seed=6)
    img16 = (img8.astype(np.uint16) * 200 + 300).astype(np.uint16)
    affine = similarity(17.7, 3.3, np.radians(1), 1.0, (w / 2, h / 2))
    p0, p1, r0, _ = track_pair(img16, warp(img16, affine), OpticalFlowConfig())
    err = np.linalg.norm(p1 - apply_affine(affine, p0), axis=1)
    assert len(r0) > 200 and len(p0) > 0.7 * len(r0) and np.median(err) < 0.1


@pytest.mark.filterwarnings("ignore::granite.optical_flow.FrameRejectedWarning")
@pytest.mark.parametrize("shape", [(1, 1), (9, 13), (40, 30)])
def test_tiny_images_do_not_crash(shape):
    img = textured_image(*shape, seed=2)
    flow = FrameToFrameOpticalFlow()
    for k in range(3):
        r = flow.process(float(k), np.roll(img, k, axis=1))
        assert np.all(np.isfinite(r.positions))


def test_template_cache_reuse_gives_identical_tracks(texture):
    """The backward pass's templates are reused as the next forward pass's; the result must
    equal a run that recomputes every template."""
    cfg = OpticalFlowConfig(fb_noise_factor=0.0)  # the kernel call below uses the fixed limit
    a1 = similarity(6.0, 3.0, 0.02, 1.0, CENTRE)
    a2 = similarity(11.0, 5.0, 0.035, 1.0, CENTRE)
    flow = FrameToFrameOpticalFlow(cfg)
    flow.process(0.0, texture)
    flow.process(0.1, warp(texture, a1))
    pyr_a, cache_a, rows = flow._pyramid, flow._cache, flow._rows
    assert np.any(rows >= 0)
    pyr_b = build_pyramid(warp(texture, a2), cfg.levels, presmooth_sigma=cfg.presmooth_sigma)
    outputs = []
    p = len(flow._pattern)
    for use_cache in (True, False):
        n = len(rows)
        cache_in = cache_a if use_cache else new_template_cache(0, cfg.levels, p)
        outputs.append(track_points(
            pyr_a.data, pyr_a.offsets, pyr_a.widths, pyr_a.heights,
            pyr_b.data, pyr_b.offsets, pyr_b.widths, pyr_b.heights,
            flow._points, flow._levels, rows if use_cache else np.full(n, -1), *cache_in,
            *new_template_cache(n, cfg.levels, p), flow._pattern, 2.0, 6, 0.03, 2.0,
        ))
    for x, y in zip(*outputs):
        np.testing.assert_array_equal(x, y)


def test_deterministic(texture):
    affine = similarity(8.0, -3.0, 0.03, 1.01, CENTRE)
    runs = [track_pair(texture, warp(texture, affine))[3] for _ in range(2)]
    np.testing.assert_array_equal(runs[0].ids, runs[1].ids)
    np.testing.assert_array_equal(runs[0].positions, runs[1].positions)


def test_crowded_cells_keep_their_oldest_tracks():
    from granite.optical_flow.frame_to_frame import crowded_tracks_kept

    rng = np.random.default_rng(3)
    n = 400
    points = rng.uniform(0, 320, (n, 2))
    levels = rng.integers(0, 3, n)
    ids = rng.permutation(n).astype(np.int64)
    keep = crowded_tracks_kept(ids, points, levels, 40, 2)
    # independent count: per (level, cell) the kept ones are exactly the min(2, count) smallest ids
    cells = {}
    for k in range(n):
        c = (int(levels[k]), int(points[k, 0] / 2 ** levels[k] // 40), int(points[k, 1] / 2 ** levels[k] // 40))
        cells.setdefault(c, []).append(k)
    for members in cells.values():
        oldest = sorted(members, key=lambda k: ids[k])[:2]
        assert set(np.flatnonzero(keep[members]).tolist()) == {members.index(k) for k in oldest}
    assert keep.sum() == sum(min(2, len(m)) for m in cells.values())


def test_coarse_levels_use_the_coarse_pattern_and_the_creation_level_the_fine_one(texture):
    """With ``pattern_coarse`` the templates the backward pass leaves for the next frame are,
    on every level above a point's creation level, the coarse pattern's template at the new
    position (made here independently with :func:`make_template`), and on the creation level
    the fine pattern's; the tracks still follow the exact motion."""
    from granite.optical_flow.patterns import make_pattern

    cfg = OpticalFlowConfig()
    fine, coarse = make_pattern("grid11", 0.75), make_pattern("grid7", 0.75)
    affine = similarity(7.3, -4.1, np.radians(2), 1.0, CENTRE)
    img1 = warp(texture, affine)
    flow = FrameToFrameOpticalFlow(cfg)
    flow.process(0.0, texture)
    pyr_a = flow._pyramid
    pyr_b = build_pyramid(img1, cfg.levels, presmooth_sigma=cfg.presmooth_sigma)
    n, p = len(flow._points), len(fine)
    cache_b = new_template_cache(n, cfg.levels, p)
    out, _, status = track_points(
        pyr_a.data, pyr_a.offsets, pyr_a.widths, pyr_a.heights,
        pyr_b.data, pyr_b.offsets, pyr_b.widths, pyr_b.heights,
        flow._points, flow._levels, np.full(n, -1), *new_template_cache(0, cfg.levels, p),
        *cache_b, fine, cfg.margin, cfg.iterations, cfg.fb_threshold_sq, 0.0, pattern_coarse=coarse,
    )
    assert status.mean() > 0.9
    err = np.linalg.norm(out[status] - apply_affine(affine, flow._points[status]), axis=1)
    assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.98
    st, data, valid, jac, aux = cache_b
    checked = 0
    for k in np.flatnonzero(status)[::7]:
        c = int(flow._levels[k])
        for lvl in range(c, cfg.levels):
            if st[k, lvl] <= 0:
                continue
            pat = fine if lvl == c else coarse
            m = len(pat)
            scale = float(1 << lvl)
            d, v, j, a = (np.empty(m, np.float32), np.empty(m, np.bool_),
                          np.empty((m, 3), np.float32), np.empty((5, 3), np.float32))
            make_template(pyr_b.data, pyr_b.offsets[lvl], pyr_b.widths[lvl], pyr_b.heights[lvl],
                          out[k, 0] / scale, out[k, 1] / scale, pat, cfg.margin, d, v, j, a)
            np.testing.assert_array_equal(data[k, lvl, :m], d)
            np.testing.assert_array_equal(jac[k, lvl, :m], j)
            np.testing.assert_array_equal(aux[k, lvl], a)
            checked += 1
    assert checked > 20


def test_coarse_pattern_may_not_have_more_samples_than_the_pattern():
    with pytest.raises(ConfigError, match="coarse_pattern"):
        OpticalFlowConfig(pattern="grid9", coarse_pattern="grid11")
    assert OpticalFlowConfig(pattern="grid9", coarse_pattern="grid7").coarse_pattern == "grid7"
