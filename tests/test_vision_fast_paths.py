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


def _random_selection_case(rng, odd):
    """A random template-selection problem: (variance map, n, sx, sy, size, frame shape, separation, occupied)."""
    sx, sy = (5, 5) if odd else (4, 3)
    size = int(np.lcm(sx, sy)) * 2
    shape = (int(rng.integers(120, 200)), int(rng.integers(120, 200)))
    var = rng.integers(0, 6, (shape[0] // sy - size // sy + 1, shape[1] // sx - size // sx + 1)).astype(np.float64)
    sep = float(rng.uniform(0.0, 60.0))
    occ = rng.uniform(0, 200, (int(rng.integers(0, 5)), 2))
    n = int(rng.integers(1, 12))
    return var, n, sx, sy, size, shape, sep, occ


@pytest.mark.parametrize("seed", range(6))
def test_select_templates_equals_the_greedy_written_out(seed):
    from vision.fixation import select_templates

    var, n, sx, sy, size, shape, sep, occ = _random_selection_case(np.random.default_rng(seed), seed % 2)
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


# ------------------------------------------------------------------ issue 11, item 4 (h11d): the 256^2 time
def test_lk_without_the_residual_output_gives_the_same_points_and_status():
    from vision.lk import _seeded_lk_kwargs

    rng = np.random.default_rng(21)
    base = cv2.GaussianBlur(rng.random((70, 260)).astype(np.float32) * 255, (0, 0), 1.4)
    prev = np.clip(base, 0, 255).astype(np.uint8)
    cur = cv2.warpAffine(prev, np.float32([[1, 0, -0.6], [0, 1, 0.35]]), (260, 70), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
    cur[:, 180:] = rng.integers(0, 256, (70, 80))
    prev[:, :50] = 128  # flat: OpenCV's eigenvalue gate fails there
    p0 = np.column_stack([rng.uniform(10, 250, 150), rng.uniform(10, 60, 150)]).astype(np.float32)
    init = (p0 + np.float32([-0.6, 0.35]) + rng.normal(0.0, 0.2, p0.shape)).astype(np.float32)
    for window in (13, 9):
        with_res = _seeded_lk_kwargs(window, 20, 0.03, 1e-2, residual=True)
        without = _seeded_lk_kwargs(window, 20, 0.03, 1e-2, residual=False)
        assert without["flags"] == with_res["flags"] | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
        a_xy, a_st, a_err = cv2.calcOpticalFlowPyrLK(prev, cur, p0, init.copy(), **with_res)
        b_xy, b_st, b_eig = cv2.calcOpticalFlowPyrLK(prev, cur, p0, init.copy(), **without)
        np.testing.assert_array_equal(b_xy, a_xy)
        np.testing.assert_array_equal(b_st, a_st)
        assert 0 < a_st.sum() < a_st.size
        # The third output is now the window's min-eigenvalue, not the residual.
        assert not np.array_equal(a_err, b_eig)


def _ssd_map_reference(window, tpl):
    ny, nx = window.shape[0] - tpl.shape[0] + 1, window.shape[1] - tpl.shape[1] + 1
    out = np.empty((ny, nx))
    for j in range(ny):
        for i in range(nx):
            d = window[j : j + tpl.shape[0], i : i + tpl.shape[1]].astype(np.float64) - tpl
            out[j, i] = (d * d).sum()
    return out


def test_map_minimum_is_the_first_minimum_in_raster_order_with_its_parabola():
    from vision.fixation import parabola_vertex
    from vision.tracker import _map_minimum

    rng = np.random.default_rng(4)
    for trial in range(40):
        n_side = int(rng.choice([3, 5]))
        vals = rng.integers(0, 6, n_side * n_side).astype(float)  # small integers: ties occur
        if trial % 4 == 0:
            vals[:] = 3.0  # a flat map: the first placement
        bx, by, ssd, at_edge, fx, fy = _map_minimum(vals.tolist(), n_side, 10, 20)
        grid = vals.reshape(n_side, n_side)
        k = int(np.argmin(vals))  # argmin: first in raster order
        my, mx = divmod(k, n_side)
        assert (bx, by, ssd) == (10 + mx, 20 + my, grid[my, mx])
        assert at_edge == (mx in (0, n_side - 1) or my in (0, n_side - 1))
        ref_fx = parabola_vertex(grid[my, mx - 1], grid[my, mx], grid[my, mx + 1]) if 0 < mx < n_side - 1 else 0.0
        ref_fy = parabola_vertex(grid[my - 1, mx], grid[my, mx], grid[my + 1, mx]) if 0 < my < n_side - 1 else 0.0
        assert (fx, fy) == (ref_fx, ref_fy)


def test_match_near_equals_match_region_and_an_explicit_ssd():
    from vision.tracker import _match_near, _match_region

    rng = np.random.default_rng(9)
    frame = cv2.GaussianBlur(rng.random((90, 110)).astype(np.float32) * 255, (0, 0), 1.2).round().astype(np.uint8)
    tpl = frame[30:60, 40:70].astype(np.float32)
    xmax, ymax = 110 - 30, 90 - 30
    # Inside the frame (the exact SSD map), and at its edges (match_region clips there).
    for cx, cy in ((41, 29), (39, 31), (40, 30), (0, 5), (xmax, ymax), (3, 59)):
        got = _match_near(frame, tpl, cx, cy, 1, xmax, ymax)
        ref = _match_region(frame, tpl, cx, cy, 1, xmax, ymax)
        assert got[:2] == ref[:2] and got[3] == ref[3]
        assert got[2] == pytest.approx(ref[2], rel=1e-4, abs=1.0)
        assert got[4:] == pytest.approx(ref[4:], abs=1e-3)
        if 1 <= cx <= xmax - 1 and 1 <= cy <= ymax - 1:
            exact = _ssd_map_reference(frame[cy - 1 : cy + 31, cx - 1 : cx + 31], tpl)
            my, mx = np.unravel_index(np.argmin(exact), exact.shape)
            assert (got[0], got[1], got[2]) == (cx - 1 + mx, cy - 1 + my, exact[my, mx])


def _shifted_frames(shift_xy, n=3, size=160, seed=3):
    """Frames of one random texture, each shifted by ``shift_xy`` px from the last."""
    rng = np.random.default_rng(seed)
    big = cv2.GaussianBlur(rng.random((size + 40, size + 40)).astype(np.float32) * 255, (0, 0), 1.5)
    big = np.clip(big, 0, 255).astype(np.uint8)
    dx, dy = shift_xy
    return [big[20 - k * dy : 20 - k * dy + size, 20 - k * dx : 20 - k * dx + size].copy() for k in range(n)]


def test_following_the_narrow_minimum_finds_what_the_wide_search_finds(monkeypatch):
    import vision.tracker as vt
    from vision import Tracker, TrackerConfig

    frames = _shifted_frames((3, -2))  # 3 px from the prediction (0): beyond one narrow follow
    wide_calls = []
    region = vt._match_region

    def counting(img, tpl, cx, cy, radius, xmax, ymax):
        if radius > 1:
            wide_calls.append(radius)
        return region(img, tpl, cx, cy, radius, xmax, ymax)

    monkeypatch.setattr(vt, "_match_region", counting)
    out = {}
    for follow in (1, 4):
        wide_calls.clear()
        tr = Tracker(TrackerConfig(search_follow_steps=follow))
        tr.step(frames[0])
        n_tpl = tr.templates.shape[0]
        out[follow] = (tr.step(frames[1]), tr.templates, len(wide_calls))
        assert tr.templates.shape[0] == n_tpl  # every template found
    (t1, tpl1, wide1), (t4, tpl4, wide4) = out[1], out[4]
    assert wide1 >= 1 and wide4 == 0  # the descent replaced the wide searches
    np.testing.assert_array_equal(tpl4, tpl1)
    np.testing.assert_array_equal(t4.ids, t1.ids)
    np.testing.assert_allclose(t4.xy, t1.xy, atol=1e-6)
    np.testing.assert_allclose(t4.xy - t4.prev_xy, np.broadcast_to([3.0, -2.0], t4.xy.shape), atol=0.05)


class _NoReuseTracker:
    """A Tracker that forgets its last LK mosaic before every step."""

    def __init__(self, tracker):
        self.t = tracker

    def step(self, img):
        self.t._mos_cache = None
        return self.t.step(img)


def _run(stepper, frames):
    return [stepper.step(f) for f in frames]


def _assert_same_tracks(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.ids, y.ids)
        np.testing.assert_array_equal(x.xy, y.xy)
        np.testing.assert_array_equal(x.prev_xy, y.prev_xy)
        np.testing.assert_array_equal(x.age, y.age)


def test_reusing_last_steps_mosaic_gives_the_same_tracks(monkeypatch):
    import vision.tracker as vt
    from bench.evaluation.tracking_eval import synthetic_descent
    from vision import Tracker

    frames = synthetic_descent(size=256, n_frames=20, altitude_m=(120.0, 40.0)).frames
    reused = []
    fb = vt.forward_backward_opencv_ok

    def spy(prev_image, image, *args):
        reused.append(any(prev_image is c[1] for c in cache_seen))
        cache_seen.append((None, image))
        return fb(prev_image, image, *args)

    cache_seen: list = []
    monkeypatch.setattr(vt, "forward_backward_opencv_ok", spy)
    with_reuse = _run(Tracker(), frames)
    assert sum(reused) >= 5  # most frames' frame-k mosaic was last step's frame-(k+1) one
    cache_seen.clear()
    reused.clear()
    without = _run(_NoReuseTracker(Tracker()), frames)
    assert not any(reused)
    _assert_same_tracks(with_reuse, without)


def test_one_detection_pass_for_refill_and_top_up_equals_two(monkeypatch):
    import vision.tracker as vt
    from bench.evaluation.tracking_eval import synthetic_descent
    from vision import Tracker

    frames = synthetic_descent(size=256, n_frames=30, altitude_m=(120.0, 40.0)).frames
    merged_calls = []
    add = vt.Tracker._add_templates

    def spy(self, img, top_up=None):
        if top_up is not None and top_up.size:
            merged_calls.append(top_up.size)
        return add(self, img, top_up)

    monkeypatch.setattr(vt.Tracker, "_add_templates", spy)
    one = _run(Tracker(), frames)
    assert merged_calls  # the sequence has frames that refill and top up together
    two_t = Tracker()
    two = [two_t.step(frames[0])]
    assert two_t._merge_top_up  # the default geometry allows it ...
    two_t._merge_top_up = False  # ... and this tracker runs two passes instead
    merged_calls.clear()
    two += _run(two_t, frames[1:])
    assert not merged_calls
    _assert_same_tracks(one, two)


def test_merging_is_off_when_sub_images_can_hold_close_points():
    from vision import Tracker, TrackerConfig

    img = np.zeros((256, 256), np.uint8)
    t = Tracker(TrackerConfig(template_separation_frac=0.1))  # 25.6 px apart: boxes of 30 px may touch
    t.config_for(img.shape)
    assert not t._merge_top_up
    t = Tracker()
    t.config_for(img.shape)
    assert t._merge_top_up


@pytest.mark.parametrize(("n_t", "wy", "wx", "ry", "rx"), [(7, 30, 30, 1, 1), (3, 12, 17, 2, 3), (1, 5, 5, 1, 2)])
def test_ssd_maps_rows_equal_ssd_maps_and_an_explicit_loop(n_t, wy, wx, ry, rx):
    from vision.fixation import ssd_maps_rows

    rng = np.random.default_rng(31)
    windows = rng.integers(0, 256, (n_t, wy + 2 * ry, wx + 2 * rx)).astype(np.float32)
    templates = rng.integers(0, 256, (n_t, wy, wx)).astype(np.float32)
    row = wx + 2 * rx
    win_rows = np.full((n_t, (wy + 2 * ry) * row + 2 * rx), 77.0, np.float32)  # finite padding
    win_rows[:, : (wy + 2 * ry) * row] = windows.reshape(n_t, -1)
    tpl_rows = np.zeros((n_t, wy, row), np.float32)
    tpl_rows[:, :, :wx] = templates
    got = ssd_maps_rows(win_rows, tpl_rows.reshape(n_t, -1), wy, wx, ry, rx)
    np.testing.assert_array_equal(got, ssd_maps(windows, templates))
    for t in range(n_t):
        np.testing.assert_array_equal(got[t], _ssd_map_reference(windows[t], templates[t]))
    # Zero padding leaves the template's centred energy as it is.
    np.testing.assert_array_equal(centred_energy(tpl_rows, wy * wx), centred_energy(templates))


# ------------------------------------------- trk-256: seeds, refills, blend
def _preferred_reference(variance, n, sx, sy, size, shape, border, sep, min_var, occupied, preferred):
    """The greedy of §2.3 with a preference, written out: the preferred
    candidates first (greedy among them), then the others, the separation
    applying to everything chosen."""
    height, width = shape
    cand = [(v, u) for v in range(variance.shape[0]) for u in range(variance.shape[1])
            if not (u * sx < border or v * sy < border or u * sx + size > width - border
                    or v * sy + size > height - border) and variance[v, u] > min_var]
    centre = {c: (c[1] * sx + 0.5 * (size - 1), c[0] * sy + 0.5 * (size - 1)) for c in cand}
    taken = [tuple(o) for o in occupied]
    chosen = []
    for group in (True, False):
        while len(chosen) < n:
            best = None
            for c in cand:  # raster order: the first of equal variances wins
                if bool(preferred[c]) != group:
                    continue
                cx, cy = centre[c]
                if any((cx - ox) ** 2 + (cy - oy) ** 2 < sep * sep for ox, oy in taken):
                    continue
                if best is None or variance[c] > variance[best]:
                    best = c
            if best is None:
                break
            chosen.append([best[1] * sx, best[0] * sy])
            taken.append(centre[best])
    return chosen


@pytest.mark.parametrize("seed", range(8))
def test_select_templates_with_a_preference_equals_the_greedy_written_out(seed):
    from vision.fixation import select_templates

    rng = np.random.default_rng(100 + seed)
    var, n, sx, sy, size, shape, sep, occ = _random_selection_case(rng, seed % 2)
    pref = rng.random(var.shape) < (0.0 if seed == 0 else 1.0 if seed == 1 else 0.4)
    got = select_templates(var, n, sx, sy, (size, size), shape, 9, sep, 1.0, occupied_xy=occ, preferred=pref)
    ref = _preferred_reference(var, n, sx, sy, size, shape, 9, sep, 1.0, occ.tolist(), pref)
    assert got.tolist() == ref
    if seed == 1:  # all preferred: the paper's selection unchanged
        assert got.tolist() == select_templates(var, n, sx, sy, (size, size), shape, 9, sep, 1.0, occupied_xy=occ).tolist()


def test_similarity_prediction_equals_least_squares_and_recovers_a_similarity():
    from vision.tracker import similarity_prediction

    rng = np.random.default_rng(3)
    xy = rng.uniform(20, 230, (7, 2))
    disp = rng.normal(0.0, 2.0, (7, 2))
    new = rng.uniform(20, 230, (3, 2))
    # Reference: np.linalg.lstsq on d = t + [[a, -b], [b, a]] (x - m), unknowns (tx, ty, a, b).
    m = xy.mean(axis=0)
    rows, rhs = [], []
    for (x, y), (dx, dy) in zip(xy - m, disp):
        rows += [[1.0, 0.0, x, -y], [0.0, 1.0, y, x]]
        rhs += [dx, dy]
    tx, ty, a, b = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    r = new - m
    ref = np.column_stack([tx + a * r[:, 0] - b * r[:, 1], ty + b * r[:, 0] + a * r[:, 1]])
    np.testing.assert_allclose(similarity_prediction(xy, disp, new), ref, atol=1e-9)
    # An exact zoom about the image centre plus a drift is recovered anywhere.
    c, s, drift = np.array([127.5, 127.5]), 0.02, np.array([0.6, -2.1])
    exact = drift + s * (xy - c)
    np.testing.assert_allclose(similarity_prediction(xy, exact, new), drift + s * (new - c), atol=1e-9)
    # Fallbacks: one template -> its displacement, none -> zero.
    np.testing.assert_allclose(similarity_prediction(xy[:1], disp[:1], new), np.tile(disp[0], (3, 1)))
    np.testing.assert_array_equal(similarity_prediction(xy[:0], disp[:0], new), np.zeros((3, 2)))


def test_lasting_areas_equal_an_explicit_loop():
    from vision import Tracker, TrackerConfig
    from vision.tracker import similarity_prediction

    cfg = TrackerConfig(template_lookahead_frames=6)
    tr = Tracker(cfg)
    tr.config_for((256, 256))
    tr._tpl_xy = np.array([[30, 40], [150, 60], [100, 180], [190, 190]])
    tr._tpl_sub = np.array([[-1.1, -2.4], [1.2, -2.9], [0.2, 0.7], [1.9, 1.3]])
    got = tr._lasting_areas((256, 256), tr._cfg)
    size, e = cfg.template_size, cfg.edge_margin_px
    assert got.shape == (256 // 5 - size // 5 + 1, 256 // 5 - size // 5 + 1)
    for v in range(got.shape[0]):
        for u in range(got.shape[1]):
            d = similarity_prediction(tr._tpl_xy.astype(float), tr._tpl_sub, np.array([[5.0 * u, 5.0 * v]]))[0]
            x, y = 5 * u + 6 * d[0], 5 * v + 6 * d[1]
            assert got[v, u] == (e <= x <= 256 - size - e and e <= y <= 256 - size - e), (u, v)
    assert got.any() and not got.all()


def test_forward_backward_blend_moves_back_by_a_fraction_of_the_round_trip():
    rng = np.random.default_rng(8)
    base = cv2.GaussianBlur(rng.random((80, 300)).astype(np.float32) * 255, (0, 0), 1.5)
    prev = np.clip(base, 0, 255).astype(np.uint8)
    cur = cv2.warpAffine(prev, np.float32([[1.02, 0, -1.0], [0, 1.02, -0.5]]), (300, 80), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
    xy = np.column_stack([rng.uniform(15, 285, 120), rng.uniform(15, 65, 120)])
    init = xy + rng.normal(0.0, 0.15, xy.shape)
    pts = np.stack([xy, init, -(init - xy)]).astype(np.float32)
    kw_fwd, kw_back = seeded_lk_kwargs(13, 20, 0.03, 1e-2, 7)
    fwd, ok = forward_backward_opencv_ok(prev, cur, pts, kw_fwd, kw_back, 0.5)
    # The two solves by hand: the backward one from the forward result.
    f2, _, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts[0], pts[1].copy(), **kw_fwd)
    b2, _, _ = cv2.calcOpticalFlowPyrLK(cur, prev, f2, f2 + pts[2], **kw_back)
    round_trip = b2.reshape(-1, 2).astype(np.float64) - pts[0]
    for w in (0.3, 1.0):
        got, ok_w = forward_backward_opencv_ok(prev, cur, pts, kw_fwd, kw_back, 0.5, blend=w)
        np.testing.assert_array_equal(ok_w, ok)  # the verdict does not depend on the blend
        np.testing.assert_allclose(got, fwd - w * round_trip, atol=1e-5)
    assert np.abs(round_trip[ok]).max() > 1e-3  # the windows (13 and 7 px) do disagree


def test_tracker_blend_numpy_backend_follows_the_same_rule():
    # With the NumPy reference LK the blend is applied the same way: the
    # position is the forward result minus w x the round trip.
    from vision.lk import forward_backward

    rng = np.random.default_rng(4)
    prev = np.clip(cv2.GaussianBlur(rng.random((60, 60)).astype(np.float32) * 255, (0, 0), 1.2), 0, 255)
    cur = cv2.warpAffine(prev, np.float32([[1.02, 0, 0.3], [0, 1.02, -0.4]]), (60, 60), flags=cv2.INTER_LINEAR)
    xy = rng.uniform(15, 45, (20, 2))
    fb = forward_backward(prev, cur, xy, xy + [0.3, -0.4], None, 0.5, window=13, back_window=7)
    assert fb.back_xy is not None and fb.back_xy.shape == xy.shape
    np.testing.assert_allclose(np.linalg.norm(fb.back_xy - xy, axis=1)[fb.ok], fb.fb_error[fb.ok])


def test_a_poor_match_inside_the_narrow_window_is_dropped_without_the_wide_search(monkeypatch):
    # Frame 2 is frame 1 under strong independent noise: every template's
    # narrow minimum is inside its window (no motion) but fails max_rel_ssd.
    # With wide_search_on_poor_match the +-12 px search runs for each and
    # finds nothing better; without it the templates are dropped at once.
    # Either way the same templates are lost.
    import vision.tracker as vt
    from vision import Tracker, TrackerConfig

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((160, 160)).astype(np.float32) * 255, (0, 0), 2.0)
    f1 = np.clip(128 + 3.0 * (base - base.mean()), 0, 255).astype(np.uint8)
    f2 = np.clip(f1 + rng.normal(0.0, 1.2 * f1.std(), f1.shape), 0, 255).astype(np.uint8)
    calls = []
    region = vt._match_region

    def spy(img, tpl, cx, cy, radius, xmax, ymax):
        calls.append(radius)
        return region(img, tpl, cx, cy, radius, xmax, ymax)

    monkeypatch.setattr(vt, "_match_region", spy)
    lost = {}
    for wide in (True, False):
        calls.clear()
        tr = Tracker(TrackerConfig(wide_search_on_poor_match=wide))
        tr.step(f1)
        n0 = tr.templates.shape[0]
        assert n0 > 0
        tr._track(tr._prev, f2)  # the matching alone, before any refill
        lost[wide] = n0 - tr.templates.shape[0]
        wide_calls = [r for r in calls if r == tr._cfg.search_radius_px]
        assert (len(wide_calls) == n0) if wide else not wide_calls
    assert lost[True] == lost[False] > 0
