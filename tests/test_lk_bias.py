"""The LK bias correction (``vision.lk.lk_bias_gain``, ``TrackerConfig.lk_affine_correction``).

A translational LK window on a motion that varies across it (a descent's zoom and turn) returns
the gradient-weighted mean of the displacement over the window, not the displacement at the point:
``b = G^-1 sum g g^T A (x - xy)``. Checked against an explicit loop, against the error of the
reference LK solve on a frame pair warped by a known affine motion, and in the tracker against the
truth of a warped texture.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from bench.evaluation.textures_eval import DescentWarp, _pair_errors, descent_homographies, warp_frames
from bench.evaluation.tracking_eval import lunar_texture
from vision import Tracker, TrackerConfig
from vision.lk import AFFINE_MAX_NORM, lk_bias, lk_bias_gain, lucas_kanade
from vision.tracker import LK_BIAS_AUTO_MIN_SIDE_PX, _affine_from_templates


def _bias_loop(image: np.ndarray, xy: np.ndarray, a: np.ndarray, window: int, centres=None) -> np.ndarray:
    """G^-1 sum g g^T A (x - xy) pixel by pixel: central differences, the integer window nearest xy
    (or centred on ``centres``)."""
    f = image.astype(np.float64)
    h = window // 2
    out = []
    for k, (x, y) in enumerate(xy):
        xi, yi = (int(np.rint(x)), int(np.rint(y))) if centres is None else centres[k]
        g_sum, t_sum = np.zeros((2, 2)), np.zeros(2)
        for v in range(yi - h, yi + h + 1):
            for u in range(xi - h, xi + h + 1):
                g = np.array([(f[v, u + 1] - f[v, u - 1]) / 2.0, (f[v + 1, u] - f[v - 1, u]) / 2.0])
                r = np.array([u - x, v - y])
                g_sum += np.outer(g, g)
                t_sum += g * (g @ (a @ r))
        out.append(np.linalg.solve(g_sum, t_sum))
    return np.array(out)


@pytest.mark.parametrize("window", [9, 11, 13])
def test_lk_bias_gain_matches_an_explicit_loop(window):
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (48, 300)).astype(np.uint8)
    xy = np.column_stack([rng.uniform(10, 290, 12), rng.uniform(10, 38, 12)])
    xy[0] = (20.5, 20.5)  # a half-pixel point: rounded half to even, as the gain does
    for _ in range(3):
        a = rng.normal(0.0, 0.02, (2, 2))
        got = lk_bias(lk_bias_gain(image, xy, window), a)
        np.testing.assert_allclose(got, _bias_loop(image, xy, a, window), rtol=2e-4, atol=1e-7)


def test_the_blended_gain_weights_the_two_windows_gains():
    """The forward-backward blend reports (1 - w) x the forward (13 px) solve + w x the backward (9 px)
    one, whose motion is the inverse, -A to first order: its bias is (1 - w) b_13 + w b_9."""
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (40, 200)).astype(np.uint8)
    xy = np.column_stack([rng.uniform(10, 190, 8), rng.uniform(10, 30, 8)])
    a = rng.normal(0.0, 0.02, (2, 2))
    got = lk_bias(lk_bias_gain(image, xy, 13, 9, 0.3), a)
    want = 0.7 * _bias_loop(image, xy, a, 13) + 0.3 * _bias_loop(image, xy, a, 9)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-9)
    # No blend, or a backward window as large as the forward one: the one window's gain.
    np.testing.assert_array_equal(lk_bias_gain(image, xy, 13, 9, 0.0), lk_bias_gain(image, xy, 13))
    np.testing.assert_allclose(lk_bias_gain(image, xy, 11, 13, 0.3), lk_bias_gain(image, xy, 11), rtol=1e-12)


def test_lk_bias_gain_of_an_empty_set_and_points_at_the_edge():
    image = np.random.default_rng(0).integers(0, 256, (40, 40)).astype(np.uint8)
    assert lk_bias_gain(image, np.zeros((0, 2)), 13).shape == (0, 2, 4)
    # A window that would leave the image (with its ring) is moved inside it; x - xy stays measured
    # from the point.
    a = np.array([[0.02, -0.01], [0.01, 0.02]])
    xy = np.array([[2.0, 37.6], [0.2, 0.7]])
    got = lk_bias(lk_bias_gain(image, xy, 13), a)
    np.testing.assert_allclose(got, _bias_loop(image, xy, a, 13, centres=[(7, 32), (7, 7)]), rtol=2e-4)


def test_the_bias_is_what_the_reference_lk_solve_gets_wrong_under_a_zoom():
    """Independent of the gain's own algebra: the numpy LK of eqs. (4.5)-(4.7) on a frame pair related
    by a known affine motion (3 % zoom, 0.6 deg turn, a sub-pixel shift) errs by the predicted bias."""
    rng = np.random.default_rng(7)
    frame0 = cv2.GaussianBlur(lunar_texture(256, rng), (0, 0), 1.0)
    c = np.array([128.0, 128.0])
    th = np.radians(0.6)
    lin = 1.03 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    m = np.column_stack([lin, c - lin @ c + (0.3, -0.2)])
    frame1 = cv2.warpAffine(frame0, m, (256, 256), flags=cv2.INTER_CUBIC)
    corners = cv2.goodFeaturesToTrack(frame0[40:216, 40:216], 60, 0.01, 8).reshape(-1, 2) + 40.0
    truth = corners @ lin.T + m[:, 2]
    res = lucas_kanade(frame0, frame1, corners, truth, window=13, max_iter=50, eps=1e-5)
    ok = res.status
    assert ok.sum() >= 40
    err = (res.xy - truth)[ok]
    b = lk_bias(lk_bias_gain(frame0, corners[ok], 13), lin - np.eye(2))
    e_mag = np.median(np.linalg.norm(err, axis=1))
    assert e_mag > 0.02  # the bias is there to be found
    slope = float((err * b).sum() / (b * b).sum())
    assert 0.85 <= slope <= 1.15
    # What is left is the solve's own bilinear sampling: 0.06 px here with no zoom at all.
    assert np.median(np.linalg.norm(err - b, axis=1)) < 0.5 * e_mag


def test_the_templates_fit_recovers_the_motion_gradient_and_refuses_what_it_cannot_fit():
    """The tracker's fit of ``A`` over its templates' block matches ``(t, new corner bx, by, displacement sx,
    sy)``, in plain floats."""

    def kept(xy, disp):
        return [(t, x + u, y + v, u, v) for t, ((x, y), (u, v)) in enumerate(zip(xy.tolist(), disp.tolist()))]

    rng = np.random.default_rng(1)
    a = np.array([[0.021, -0.004], [0.005, 0.018]])
    xy = rng.uniform(0, 256, (60, 2))
    disp = np.array([0.7, -0.3]) + xy @ a.T + rng.normal(0.0, 0.02, xy.shape)
    np.testing.assert_allclose(_affine_from_templates(kept(xy, disp)), a, atol=5e-4)
    assert _affine_from_templates(kept(xy[:3], disp[:3])) is None  # too few
    line = np.column_stack([np.arange(10.0), 2.0 * np.arange(10.0)])
    assert _affine_from_templates(kept(line, line @ a.T)) is None  # on a line
    big = np.eye(2) * AFFINE_MAX_NORM
    assert _affine_from_templates(kept(xy, xy @ big.T)) is None  # no frame-to-frame motion a tracker follows
    # Seven templates: the least-squares solution of disp = c + A xy, computed independently.
    coef = np.linalg.lstsq(np.column_stack([np.ones(7), xy[:7]]), disp[:7], rcond=None)[0]
    np.testing.assert_allclose(_affine_from_templates(kept(xy[:7], disp[:7])), coef[1:].T, rtol=1e-9)


def _warped_sequence(size: int, frames: int = 20) -> tuple[list[np.ndarray], list[np.ndarray], tuple[int, int]]:
    tex = lunar_texture(512, np.random.default_rng(11))
    warp = DescentWarp().for_size(size)
    hs = descent_homographies(tex.shape, size, frames, warp)
    return warp_frames(tex, hs, size, warp.noise_dn, seed=2), hs, tex.shape


def _run(cfg: TrackerConfig, imgs: list[np.ndarray]) -> list:
    tr = Tracker(cfg)
    return [tr.step(im) for im in imgs]


def test_the_tracker_with_the_correction_is_closer_to_the_truth_of_a_zooming_texture():
    imgs, hs, shape = _warped_sequence(256)
    pair = _pair_errors(hs, shape, 256)
    med = {}
    for mode in ("off", "on"):
        outs = _run(TrackerConfig(lk_affine_correction=mode), imgs)
        med[mode] = float(np.median(np.concatenate([pair(k, outs[k], outs[k + 1]) for k in range(len(imgs) - 1)])))
    assert med["on"] < 0.8 * med["off"], med


def test_auto_is_off_at_the_reference_size_and_on_above_it():
    cfg = TrackerConfig()
    assert cfg.lk_affine_correction == "auto"
    assert not cfg.corrects_lk_bias(LK_BIAS_AUTO_MIN_SIDE_PX) and cfg.corrects_lk_bias(LK_BIAS_AUTO_MIN_SIDE_PX + 1)
    assert cfg.subpixel_setup(256) == {"lk_bias_correction": False, "fb_blend": 0.3}
    assert cfg.subpixel_setup(512) == {"lk_bias_correction": True, "fb_blend": 0.3}
    # Without the forward-backward check there is no backward solve to blend with.
    assert TrackerConfig(fb_check=False).subpixel_setup(256) == {"lk_bias_correction": False, "fb_blend": 0.0}
    assert not TrackerConfig(lk_affine_correction="off").corrects_lk_bias(512)
    assert TrackerConfig(lk_affine_correction="on").corrects_lk_bias(128)
    # The same tracks as 'off' at 256 px, as 'on' above it.
    imgs, _, _ = _warped_sequence(256, 8)
    for a, b in zip(_run(TrackerConfig(), imgs), _run(TrackerConfig(lk_affine_correction="off"), imgs)):
        np.testing.assert_array_equal(a.xy, b.xy)
    imgs, _, _ = _warped_sequence(320, 8)
    for a, b in zip(_run(TrackerConfig(), imgs), _run(TrackerConfig(lk_affine_correction="on"), imgs)):
        np.testing.assert_array_equal(a.xy, b.xy)
    off = _run(TrackerConfig(lk_affine_correction="off"), imgs)
    assert not np.array_equal(off[-1].xy, _run(TrackerConfig(), imgs)[-1].xy)
