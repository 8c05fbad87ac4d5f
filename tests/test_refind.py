"""Re-finding points from predicted positions (granite.optical_flow.refind) against the exact
displacement of a synthetic image pair."""

from __future__ import annotations

import cv2
import numpy as np

from granite.optical_flow import OpticalFlowConfig, build_pyramid
from granite.optical_flow.patterns import pattern52
from granite.optical_flow.refind import refind_points
from planar_scene import make_texture

CFG = OpticalFlowConfig()


def _pair(shift=(23.4, -11.7), angle_deg=2.0, seed=0):
    """Host image and a current image moved by a rotation about the centre plus ``shift``;
    returns both and the affine map (2x3) from host to current pixels."""
    tex = make_texture(1024, seed)
    host = np.ascontiguousarray(tex[200:680, 200:840])
    A = cv2.getRotationMatrix2D((319.5, 239.5), angle_deg, 1.0)
    A[:, 2] += shift
    cur = cv2.warpAffine(tex[200:680, 200:840], A, (640, 480), flags=cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REFLECT)
    return host, cur, A


def _points():
    g = np.stack(np.meshgrid(np.linspace(120, 520, 6), np.linspace(100, 380, 5)), -1).reshape(-1, 2)
    levels = np.arange(len(g)) % 3  # creation levels 0, 1, 2
    return g, levels


def _refind(host, cur, uv, levels, guess, min_zncc=0.8):
    hp = build_pyramid(host, CFG.levels)
    cp = build_pyramid(cur, CFG.levels)
    return refind_points(hp, cp, uv, levels, guess, pattern52(CFG.pattern_scale), CFG.margin,
                         CFG.iterations, 0.3, min_zncc)


def test_points_are_refound_at_their_true_position():
    host, cur, A = _pair()
    uv, levels = _points()
    truth = uv @ A[:, :2].T + A[:, 2]
    rng = np.random.default_rng(3)
    guess = truth + rng.uniform(-4, 4, truth.shape)  # a prediction a few pixels off
    found, ok, zncc = _refind(host, cur, uv, levels, guess)
    assert ok.mean() > 0.9
    err = np.linalg.norm(found[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.1 and np.max(err) < 0.5
    assert np.all(zncc[ok] >= 0.8)
    assert np.all(np.isnan(found[~ok]))


def test_unrelated_image_and_missing_predictions_are_rejected():
    host, _, A = _pair()
    other = make_texture(1024, seed=7)[100:580, 300:940].copy()
    uv, levels = _points()
    truth = uv @ A[:, :2].T + A[:, 2]
    _, ok, _ = _refind(host, other, uv, levels, truth)
    assert ok.mean() < 0.1
    guess = truth.copy()
    guess[::2] = np.nan  # no prediction: not tried
    _, ok, zncc = _refind(*_pair()[:2], uv, levels, guess)
    assert not ok[::2].any() and np.all(zncc[::2] == -2.0)
    assert ok[1::2].mean() > 0.9
