"""The tracker's lean hot-path routines against the reference computations
they replace (issue 11, item 4: the tracker's time at 256^2)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision.fixation import centred_energy, ssd_maps
from vision.lk import forward_backward_opencv_fast, forward_backward_opencv_ok, seeded_lk_kwargs


@pytest.mark.parametrize(("n_t", "wy", "wx", "ry", "rx"), [(7, 30, 30, 1, 1), (3, 12, 17, 2, 0), (1, 5, 5, 3, 4)])
def test_ssd_maps_equal_an_explicit_loop_and_match_template(n_t, wy, wx, ry, rx):
    rng = np.random.default_rng(11)
    windows = rng.integers(0, 256, (n_t, wy + 2 * ry, wx + 2 * rx)).astype(np.float32)
    templates = rng.integers(0, 256, (n_t, wy, wx)).astype(np.float32)
    got = ssd_maps(windows, templates)
    assert got.shape == (n_t, 2 * ry + 1, 2 * rx + 1)
    for t in range(n_t):
        for j in range(2 * ry + 1):
            for i in range(2 * rx + 1):
                d = windows[t, j : j + wy, i : i + wx].astype(np.float64) - templates[t]
                # Integer differences: the float32 sum is exact below 2^24.
                assert got[t, j, i] == pytest.approx((d * d).sum(), rel=1e-6)
        ref = cv2.matchTemplate(windows[t], templates[t], cv2.TM_SQDIFF)
        np.testing.assert_allclose(got[t], ref, rtol=1e-4, atol=1.0)


def test_ssd_maps_minimum_is_the_true_shift():
    rng = np.random.default_rng(2)
    frame = rng.integers(0, 256, (60, 60)).astype(np.float32)
    tpl = frame[20:40, 22:42]
    # Window of +-2 px around (21, 19): the template's own place is at (1, 3).
    win = frame[17:17 + 24, 21 - 2 : 21 - 2 + 24]
    got = ssd_maps(win[None], tpl[None])[0]
    assert got[3, 3] == 0.0 and np.unravel_index(np.argmin(got), got.shape) == (3, 3)


def test_centred_energy_equals_variance_times_area():
    rng = np.random.default_rng(5)
    templates = rng.normal(120.0, 30.0, (6, 30, 30)).astype(np.float32)
    templates[2] = 77.0  # flat: zero energy, not a small negative
    got = centred_energy(templates)
    ref = np.array([cv2.meanStdDev(t)[1][0, 0] ** 2 * t.size for t in templates])
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(got, templates.astype(np.float64).reshape(6, -1).var(axis=1) * 900, rtol=1e-9)
    assert got[2] == 0.0


def test_forward_backward_opencv_ok_matches_the_checked_lean_path():
    rng = np.random.default_rng(8)
    base = cv2.GaussianBlur(rng.random((80, 300)).astype(np.float32) * 255, (0, 0), 1.5)
    prev = np.clip(base, 0, 255).astype(np.uint8)
    shift = np.float32([[1, 0, 0.4], [0, 1, -0.3]])
    cur = cv2.warpAffine(prev, shift, (300, 80), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    cur[:, 200:] = rng.integers(0, 256, (80, 100))  # unrelated content: those round trips fail
    xy = np.column_stack([rng.uniform(15, 285, 120), rng.uniform(15, 65, 120)])
    init = xy + np.array([0.4, -0.3]) + rng.normal(0.0, 0.15, xy.shape)
    back = -(init - xy)
    for window, back_window, fb_max in ((13, 9, 0.5), (9, None, 0.2)):
        xy1, err = forward_backward_opencv_fast(prev, cur, xy, init, back, window, 20, 0.03, 1e-2, back_window)
        pts = np.stack([xy, init, back]).astype(np.float32)
        kw_fwd, kw_back = seeded_lk_kwargs(window, 20, 0.03, 1e-2, back_window)
        got_xy, ok = forward_backward_opencv_ok(prev, cur, pts, kw_fwd, kw_back, fb_max)
        np.testing.assert_array_equal(got_xy, xy1.astype(np.float32))
        np.testing.assert_array_equal(ok, err <= fb_max)
        assert 0 < ok.sum() < ok.size  # both verdicts occur


def _select_templates_reference(variance, n, sx, sy, size, shape, border, sep, min_var, occupied):
    """The greedy selection of §2.3 written out with explicit loops."""
    height, width = shape
    cand = []
    for v in range(variance.shape[0]):
        for u in range(variance.shape[1]):
            x, y = u * sx, v * sy
            if x < border or y < border or x + size > width - border or y + size > height - border:
                continue
            if variance[v, u] > min_var:
                cand.append((v, u))
    centres = [((u * sx + 0.5 * (size - 1)), (v * sy + 0.5 * (size - 1))) for v, u in cand]
    alive = [all((cx - ox) ** 2 + (cy - oy) ** 2 >= sep * sep for ox, oy in occupied) for cx, cy in centres]
    chosen = []
    while len(chosen) < n:
        best = None
        for i, (v, u) in enumerate(cand):  # raster order: the first of equal variances wins
            if alive[i] and (best is None or variance[v, u] > variance[cand[best]]):
                best = i
        if best is None:
            break
        v, u = cand[best]
        chosen.append([u * sx, v * sy])
        bx, by = centres[best]
        for i, (cx, cy) in enumerate(centres):
            if (cx - bx) ** 2 + (cy - by) ** 2 < sep * sep:
                alive[i] = False
    return chosen


@pytest.mark.parametrize("seed", range(6))
def test_select_templates_equals_the_greedy_written_out(seed):
    from vision.fixation import select_templates

    rng = np.random.default_rng(seed)
    sx, sy = (5, 5) if seed % 2 else (4, 3)
    size = int(np.lcm(sx, sy)) * 2
    shape = (int(rng.integers(120, 200)), int(rng.integers(120, 200)))
    var = rng.integers(0, 6, (shape[0] // sy - size // sy + 1, shape[1] // sx - size // sx + 1)).astype(np.float64)
    sep = float(rng.uniform(0.0, 60.0))
    occ = rng.uniform(0, 200, (int(rng.integers(0, 5)), 2))
    n = int(rng.integers(1, 12))
    got = select_templates(var, n, sx, sy, (size, size), shape, 9, sep, 1.0, occupied_xy=occ)
    ref = _select_templates_reference(var, n, sx, sy, size, shape, 9, sep, 1.0, occ.tolist())
    assert got.tolist() == ref


@pytest.mark.parametrize("window", [1, 3, 5])
def test_inner_structure_tensor_equals_gradients_then_structure_tensor(window):
    from vision.features import _inner_structure_tensor, detection_margin, gradients, structure_tensor

    rng = np.random.default_rng(window)
    m, h, w = detection_margin(window), 30, 26
    stack = rng.integers(0, 256, (4, h + 2 * m, w + 2 * m)).astype(np.float32)
    ix, iy = gradients(stack)
    ref = structure_tensor(ix, iy, window)
    got = _inner_structure_tensor(stack, window, m, h, w)
    for g, r in zip(got, ref):
        np.testing.assert_array_equal(g, r[:, m : m + h, m : m + w])  # exact on 8-bit data
    # Central differences by hand, summed over the window with explicit loops.
    t, yy, xx = 2, m + 7, m + 11
    r = window // 2
    gx = [[0.5 * (stack[t, y, x + 1] - stack[t, y, x - 1]) for x in range(xx - r, xx + r + 1)] for y in range(yy - r, yy + r + 1)]
    gy = [[0.5 * (stack[t, y + 1, x] - stack[t, y - 1, x]) for x in range(xx - r, xx + r + 1)] for y in range(yy - r, yy + r + 1)]
    a = sum(v * v for row in gx for v in row)
    b = sum(u * v for ru, rv in zip(gx, gy) for u, v in zip(ru, rv))
    c = sum(v * v for row in gy for v in row)
    assert (got[0][t, yy - m, xx - m], got[1][t, yy - m, xx - m], got[2][t, yy - m, xx - m]) == (a, b, c)
