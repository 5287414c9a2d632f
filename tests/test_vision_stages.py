"""Unit tests of the vision stages against independent computations."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from vision import (
    LAPLACIAN8_KERNEL,
    bilinear_patches,
    block_average,
    detect_features,
    detect_in_subimages,
    eigen_threshold_test,
    fixation_areas,
    forward_backward,
    gradients,
    laplacian8,
    lucas_kanade,
    lucas_kanade_opencv,
    match_templates,
    min_eigenvalue,
    p_lambda,
    select_templates,
    structure_tensor,
    variance_map,
)
from vision.lk import OPENCV_MIN_EIG_SCALE


def smooth_periodic_texture(n: int, sigma: float, seed: int = 0) -> np.ndarray:
    """Gaussian-filtered white noise made periodic (filtered in Fourier space),
    scaled to mean 128 and standard deviation 40 DN; float64 (n, n)."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n)
    gain = np.exp(-2 * np.pi**2 * sigma**2 * (f[:, None] ** 2 + f[None, :] ** 2))
    img = np.real(np.fft.ifft2(np.fft.fft2(rng.random((n, n))) * gain))
    return (img - img.mean()) / img.std() * 40.0 + 128.0


def fourier_shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Exact sub-pixel translation of a periodic band-limited image: content
    at (x, y) moves to (x + dx, y + dy)."""
    n_r, n_c = img.shape
    ky = np.fft.fftfreq(n_r)[:, None]
    kx = np.fft.fftfreq(n_c)[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (kx * dx + ky * dy))))


# ------------------------------------------------------------------ §2 stages
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_block_average_matches_explicit_loop(dtype):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (23, 31)).astype(dtype)
    sx, sy = 5, 3
    out = block_average(img, sx, sy)
    assert out.shape == (23 // sy, 31 // sx)
    ref = np.zeros(out.shape)
    for v in range(out.shape[0]):
        for u in range(out.shape[1]):
            acc = 0.0
            for i in range(sx):
                for j in range(sy):
                    acc += float(img[sy * v + j, sx * u + i])  # E(Sx u + i, Sy v + j), eq. (2.1)
            ref[v, u] = acc / (sx * sy)
    np.testing.assert_allclose(out, ref, atol=1e-4)


def test_block_average_rejects_bad_factors():
    img = np.zeros((10, 10), np.uint8)
    for bad in (0, -1, 2.5, 11):
        with pytest.raises(ValueError, match="sx|sub-sampling"):
            block_average(img, bad, 2)


def test_laplacian8_interior_matches_neighbour_sum():
    rng = np.random.default_rng(2)
    img = rng.random((12, 15)).astype(np.float32) * 255
    out = laplacian8(img)
    p = img.astype(np.float64)
    ref = -9 * p[1:-1, 1:-1]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            ref = ref + p[1 + dr : p.shape[0] - 1 + dr, 1 + dc : p.shape[1] - 1 + dc]
    np.testing.assert_allclose(out[1:-1, 1:-1], ref, atol=1e-3)
    assert LAPLACIAN8_KERNEL.sum() == 0
    assert np.all(laplacian8(np.full((6, 6), 77, np.uint8)) == 0)  # flat -> zero, borders too


def test_variance_map_matches_numpy_var():
    rng = np.random.default_rng(3)
    img = (rng.standard_normal((17, 21)) * 30).astype(np.float32)
    wx, wy = 4, 3
    v = variance_map(img, wx, wy)
    assert v.shape == (17 - wy + 1, 21 - wx + 1)
    for r in range(v.shape[0]):
        for c in range(v.shape[1]):
            assert v[r, c] == pytest.approx(np.var(img[r : r + wy, c : c + wx].astype(np.float64)), rel=1e-6, abs=1e-6)
    with pytest.raises(ValueError, match="wx"):
        variance_map(img, 0, 2)
    with pytest.raises(ValueError, match="fit"):
        variance_map(img, 30, 2)


def test_select_templates_rules():
    var = np.zeros((40, 40))
    # Peaks: (row, col) -> value. The two strongest are close together.
    peaks = {(10, 10): 100.0, (11, 12): 90.0, (30, 30): 80.0, (1, 20): 500.0, (20, 25): 70.0}
    for (r, c), val in peaks.items():
        var[r, c] = val
    s = 5
    tl = select_templates(var, 3, s, s, (20, 20), (220, 220), border_px=10, min_separation_px=40.0)
    got = [tuple(p) for p in tl.tolist()]
    # (1, 20) is too near the top border; (11, 12) is too close to (10, 10).
    assert got == [(50, 50), (150, 150), (125, 100)]
    # Fixed number: asking for fewer gives the strongest valid ones.
    assert select_templates(var, 1, s, s, (20, 20), (220, 220), 10, 40.0).tolist() == [[50, 50]]
    # Occupied areas are avoided.
    occ = np.array([[59.5, 59.5]])
    tl2 = select_templates(var, 3, s, s, (20, 20), (220, 220), 10, 40.0, occupied_xy=occ)
    assert [50, 50] not in tl2.tolist() and [55, 60] not in tl2.tolist()
    # Featureless -> none.
    assert select_templates(np.zeros((40, 40)), 5, s, s, (20, 20), (220, 220), 10, 40.0).shape == (0, 2)


def test_select_templates_takes_high_variance_blocks_that_are_not_local_maxima():
    # One broad high-variance area whose peak, at map row 1 (y = 5 px), lies
    # inside the 20 px border: no block inside the border is a 3 x 3 local
    # maximum, yet the highest-variance blocks there must become templates
    # (paper §2.3: "the high-local-variance points are selected").
    s = 5
    r, c = np.mgrid[0:40, 0:40]
    var = 1000.0 - ((r - 1.0) ** 2 + (c - 20.3) ** 2)
    tl = select_templates(var, 3, s, s, (20, 20), (220, 220), border_px=20, min_separation_px=40.0)
    # Greedy by variance inside the border (rows >= 4): (4, 20) first, then
    # the best blocks 40 px (8 blocks) away from the chosen ones: (4, 28) with
    # 1000 - 68.29, then (4, 12) with 1000 - 77.89.
    assert tl.tolist() == [[100, 20], [140, 20], [60, 20]]
    # A ridge of equal variance (a plateau along a row): templates along it,
    # spread by the separation.
    ridge = np.zeros((40, 40))
    ridge[20, 5:36] = 50.0
    ridge[19, 5:36] = ridge[21, 5:36] = 10.0
    tl = select_templates(ridge, 4, s, s, (20, 20), (220, 220), border_px=10, min_separation_px=50.0)
    assert tl.tolist() == [[25, 100], [75, 100], [125, 100], [175, 100]]
    # An occupied peak: the next-best free blocks on its flank are used.
    hill = 1000.0 - ((r - 20.0) ** 2 + (c - 20.0) ** 2)
    occ = np.array([[109.5, 109.5]])  # centre of the template at the peak (100, 100)
    tl = select_templates(hill, 1, s, s, (20, 20), (220, 220), 10, 40.0, occupied_xy=occ)
    assert tl.tolist() == [[100, 60]]  # 8 blocks up (the first of the four ties in raster order)


def test_fixation_areas_refuses_a_template_size_the_block_size_does_not_divide():
    img = np.clip(smooth_periodic_texture(120, 1.5, seed=24), 0, 255).astype(np.uint8)
    # 20 = 4 x 5: the variance window of eq. (2.2) is 4 x 4 blocks.
    ok = fixation_areas(img, 3, 5, 5, 20, 10, 30.0)
    assert ok.variance.shape == (120 // 5 - 4 + 1,) * 2 and len(ok.top_left) == 3
    # 22 / 5 is not whole: refused, not rounded down to a 4 x 4 (20 px) window.
    for sx, sy, size in ((5, 5, 22), (5, 3, 20), (3, 5, 20)):
        msg = rf"template_size \({size}\) must be a multiple of sx \({sx}\) and sy \({sy}\)"
        with pytest.raises(ValueError, match=msg):
            fixation_areas(img, 3, sx, sy, size, 10, 30.0)
    with pytest.raises(ValueError, match="sx must be a positive integer"):
        fixation_areas(img, 3, 0, 5, 20, 10, 30.0)


@pytest.mark.parametrize("shift", [(3, -2), (-7, 5), (0, 0)])
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_match_templates_finds_integer_shift_exactly(shift, dtype):
    tex = smooth_periodic_texture(128, 1.5, seed=4)
    a = np.clip(tex, 0, 255).astype(dtype)
    b = np.roll(a, (shift[1], shift[0]), axis=(0, 1))
    tl = np.array([[30, 40], [70, 60], [50, 80]])
    m = match_templates(a, b, tl, (20, 20), search_radius=8)
    np.testing.assert_array_equal(m.shift, np.tile(shift, (3, 1)))
    assert (m.rel_ssd < 1e-4).all()  # exact match up to float rounding of the SSD expansion
    assert not m.at_edge.any()
    # With a prediction the same shift is found with a small window.
    m2 = match_templates(a, b, tl, (20, 20), search_radius=2, predicted_shift=np.tile(shift, (3, 1)))
    np.testing.assert_array_equal(m2.shift, m.shift)


def test_match_templates_flags_shift_beyond_window():
    tex = np.clip(smooth_periodic_texture(128, 1.5, seed=5), 0, 255).astype(np.uint8)
    b = np.roll(tex, 9, axis=1)
    m = match_templates(tex, b, np.array([[50, 50]]), (20, 20), search_radius=4)
    assert m.at_edge[0] and m.rel_ssd[0] > 0.05
    with pytest.raises(ValueError, match="shape"):
        match_templates(tex, tex[:-1], np.array([[50, 50]]), (20, 20), 4)
    with pytest.raises(ValueError, match="inside"):
        match_templates(tex, b, np.array([[120, 50]]), (20, 20), 4)


# ------------------------------------------------------------------ §3 stages
def test_gradients_and_structure_tensor_match_loops():
    rng = np.random.default_rng(6)
    img = rng.random((9, 11)) * 255
    ix, iy = gradients(img)
    for r in range(9):
        for c in range(1, 10):
            assert ix[r, c] == pytest.approx((img[r, c + 1] - img[r, c - 1]) / 2, abs=1e-3)  # eq. (3.1)
    for r in range(1, 8):
        for c in range(11):
            assert iy[r, c] == pytest.approx((img[r + 1, c] - img[r - 1, c]) / 2, abs=1e-3)  # eq. (3.2)
    w1 = 3
    a, b, c = structure_tensor(ix, iy, w1)
    for r in range(1, 8):
        for col in range(1, 10):
            px = ix[r - 1 : r + 2, col - 1 : col + 2].astype(np.float64)
            py = iy[r - 1 : r + 2, col - 1 : col + 2].astype(np.float64)
            assert a[r, col] == pytest.approx((px * px).sum(), rel=1e-5)
            assert b[r, col] == pytest.approx((px * py).sum(), rel=1e-5, abs=1e-3)
            assert c[r, col] == pytest.approx((py * py).sum(), rel=1e-5)
    assert a[0].max() == 0 and a[:, -1].max() == 0
    with pytest.raises(ValueError, match="odd"):
        structure_tensor(ix, iy, 4)


def test_sqrt_free_test_agrees_with_eigenvalues():
    rng = np.random.default_rng(7)
    n = 20000
    m = rng.standard_normal((n, 2, 2)) * 30
    g = m @ m.transpose(0, 2, 1)  # random symmetric positive semi-definite G
    a, b, c = g[:, 0, 0], g[:, 0, 1], g[:, 1, 1]
    eig_min = np.linalg.eigvalsh(g)[:, 0]
    for lam in (0.0, 100.0, 1500.0, float(np.median(eig_min))):
        expected = eig_min > lam
        got = eigen_threshold_test(a, b, c, lam)
        np.testing.assert_array_equal(got, expected)
        # P(lambda) is the characteristic polynomial det(G - lambda I).
        np.testing.assert_allclose(p_lambda(a, b, c, lam), np.linalg.det(g - lam * np.eye(2)), rtol=1e-6, atol=1e-3)
    np.testing.assert_allclose(min_eigenvalue(a, b, c), eig_min, rtol=1e-9, atol=1e-6)
    assert expected.any() and (~expected).any()  # the test can fail both ways


def corner_image() -> tuple[np.ndarray, np.ndarray]:
    """Bright squares on dark: their corners are the true feature points."""
    img = np.full((64, 64), 40.0, np.float32)
    img[10:25, 12:30] = 200.0
    img[38:54, 36:50] = 200.0
    corners = np.array(
        [[12, 10], [29, 10], [12, 24], [29, 24], [36, 38], [49, 38], [36, 53], [49, 53]], dtype=np.float64
    )
    return img, corners


def test_detect_features_exhaustive_finds_corners_with_nms():
    img, corners = corner_image()
    f = detect_features(img, window=3, lambda_t=1500.0, max_features=50, nms_radius=2)
    assert len(f.xy) >= len(corners)
    d = np.linalg.norm(f.xy[:, None, :] - corners[None, :, :], axis=2)
    assert (d.min(axis=0) <= 1.5).all(), "every true corner has a detection next to it"
    assert (d.min(axis=1) <= 2.5).all(), "no detection away from the corners (edges are rejected)"
    pair = np.abs(f.xy[:, None, :] - f.xy[None, :, :]).max(axis=2) + np.eye(len(f.xy)) * 99
    assert pair.min() > 2, "non-maximum suppression spreads points"
    assert np.all(np.diff(f.score) <= 0)
    # A flat image gives nothing.
    assert len(detect_features(np.full((30, 30), 9, np.uint8), lambda_t=1.0).xy) == 0


def test_nms_keeps_one_point_of_a_tie():
    img = np.full((40, 48), 40.0, np.float32)
    img[10, 12:14] = 200.0  # horizontal domino: lambda_1 ties at (12, 10) and (13, 10)
    img[25:27, 30] = 200.0  # vertical domino: ties at (30, 25) and (30, 26)
    img[12:14, 34:36] = 200.0  # 2 x 2 square: four-way tie
    ix, iy = gradients(img)
    lam = min_eigenvalue(*structure_tensor(ix, iy, 3))
    assert lam[10, 12] == lam[10, 13] == lam[10].max()
    assert lam[25, 30] == lam[26, 30] == lam[:, 30].max()
    assert lam[12, 34] == lam[12, 35] == lam[13, 34] == lam[13, 35] == lam.max()
    for r in (1, 2):
        f = detect_features(img, window=3, lambda_t=1000.0, max_features=50, nms_radius=r)
        # Exactly one point per plateau: the first in raster order.
        assert f.xy.tolist() == [[34.0, 12.0], [12.0, 10.0], [30.0, 25.0]], r
        np.testing.assert_array_equal(f.score, [lam[12, 34], lam[10, 12], lam[25, 30]])
    # Same rule in a stack of sub-images.
    g = detect_in_subimages(img, np.array([[6, 4], [26, 6]]), (16, 16), lambda_t=1000.0, nms_radius=1)
    assert sorted(g.xy.tolist()) == [[12.0, 10.0], [34.0, 12.0]]
    # Many ties (a two-level image): no two kept points within the radius.
    rng = np.random.default_rng(23)
    blocks = (rng.random((16, 16)) < 0.5).astype(np.float32) * 120
    two_level = np.kron(blocks, np.ones((3, 3), np.float32))
    for r in (1, 2, 3):
        f = detect_features(two_level, window=3, lambda_t=100.0, max_features=10_000, nms_radius=r)
        assert len(f.xy) > 20
        pair = np.abs(f.xy[:, None, :] - f.xy[None, :, :]).max(axis=2) + np.eye(len(f.xy)) * 99
        assert pair.min() > r, r


def test_detect_in_subimages_limits_and_regions():
    img, corners = corner_image()
    tl = np.array([[8, 6], [32, 34]])
    f = detect_in_subimages(img, tl, (24, 22), lambda_t=1500.0, max_features=3, nms_radius=1)
    assert np.bincount(f.region, minlength=2).tolist() == [3, 3]
    for k in range(2):
        xy = f.xy[f.region == k]
        assert (xy >= tl[k]).all() and (xy < tl[k] + (24, 22)).all()
    with pytest.raises(ValueError, match="margin"):
        detect_in_subimages(img, np.array([[0, 0]]), (10, 10))


def test_random_search_uses_only_the_given_generator():
    img, corners = corner_image()
    state = np.random.get_state()
    f1 = detect_features(img, lambda_t=1500.0, max_features=6, nms_radius=2, strategy="random", rng=np.random.default_rng(3))
    f2 = detect_features(img, lambda_t=1500.0, max_features=6, nms_radius=2, strategy="random", rng=np.random.default_rng(3))
    assert np.random.get_state()[1].tolist() == state[1].tolist()
    np.testing.assert_array_equal(f1.xy, f2.xy)
    assert len(f1.xy) == 6
    # Every accepted pixel passes the eq. (3.4) test ...
    ix, iy = gradients(img)
    a, b, c = structure_tensor(ix, iy, 3)
    r, col = f1.xy[:, 1].astype(int), f1.xy[:, 0].astype(int)
    assert eigen_threshold_test(a[r, col], b[r, col], c[r, col], 1500.0).all()
    # ... and accepted points are not adjacent.
    pair = np.abs(f1.xy[:, None, :] - f1.xy[None, :, :]).max(axis=2) + np.eye(6) * 99
    assert pair.min() > 2
    with pytest.raises(ValueError, match="Generator"):
        detect_features(img, strategy="random", rng=None)
    with pytest.raises(ValueError, match="strategy"):
        detect_features(img, strategy="greedy")


# ------------------------------------------------------------------ §4 stages
def test_bilinear_patches_match_scipy():
    rng = np.random.default_rng(8)
    img = (rng.random((40, 50)) * 255).astype(np.float32)
    xy = rng.uniform(6, 33, (7, 2))
    patches, inside = bilinear_patches(img, xy, 3)
    assert inside.all()
    off = np.arange(-3, 4)
    for p in range(7):
        rr = xy[p, 1] + off[:, None] + 0 * off[None, :]
        cc = xy[p, 0] + off[None, :] + 0 * off[:, None]
        ref = ndimage.map_coordinates(img.astype(np.float64), [rr, cc], order=1)
        np.testing.assert_allclose(patches[p], ref, atol=1e-3)
    _, inside = bilinear_patches(img, np.array([[2.0, 20.0], [20.0, 36.5]]), 3)
    assert not inside.any()


@pytest.mark.parametrize("shift", [(0.37, -0.61), (0.5, 0.5), (-0.23, 0.11)])
def test_lucas_kanade_recovers_subpixel_shift(shift):
    tex = smooth_periodic_texture(128, 2.0, seed=9)
    a = tex.astype(np.float32)
    b = fourier_shift(tex, *shift).astype(np.float32)
    rng = np.random.default_rng(10)
    xy = rng.integers(20, 108, (60, 2)).astype(np.float64)
    res = lucas_kanade(a, b, xy, init_xy=xy + np.round(shift), window=15, eps=1e-3)
    assert res.status.all()
    err = np.linalg.norm(res.xy - xy - shift, axis=1)
    assert np.median(err) < 0.02
    assert err.max() < 0.06
    assert np.abs((res.xy - xy).mean(axis=0) - shift).max() < 0.02


def test_lucas_kanade_reports_unconverged_points_invalid():
    tex = smooth_periodic_texture(128, 2.0, seed=9)
    a = tex.astype(np.float32)
    shift = (1.7, -1.2)
    b = fourier_shift(tex, *shift).astype(np.float32)
    rng = np.random.default_rng(22)
    xy = rng.integers(24, 104, (40, 2)).astype(np.float64)
    # From 2 px away, one Newton step moves by ~2 px >> eps: no point can have
    # converged when the iteration cap is 1, so none may be reported valid.
    capped = lucas_kanade(a, b, xy, window=15, max_iter=1, eps=1e-3)
    assert (capped.iterations == 1).all()
    assert not capped.status.any()
    # Two steps do not reach 1e-3 either (each one still moves the point).
    assert not lucas_kanade(a, b, xy, window=15, max_iter=2, eps=1e-3).status.any()
    # With room to iterate, the same points converge and are valid and accurate.
    free = lucas_kanade(a, b, xy, window=15, max_iter=30, eps=1e-3)
    assert free.status.all()
    assert (free.iterations < 30).all()
    assert np.linalg.norm(free.xy - xy - shift, axis=1).max() < 0.06
    # A point that is pushed off the image is invalid too.
    edge = lucas_kanade(a, b, np.array([[64.0, 64.0]]), init_xy=np.array([[2.0, 64.0]]), window=15)
    assert not edge.status[0]


def test_lucas_kanade_needs_the_seed_for_large_motion():
    tex = smooth_periodic_texture(128, 1.5, seed=11)
    a = tex.astype(np.float32)
    shift = (9.3, -6.6)
    b = fourier_shift(tex, *shift).astype(np.float32)
    xy = np.array([[50.0, 50.0], [70.0, 64.0], [60.0, 40.0]])
    seeded = lucas_kanade(a, b, xy, init_xy=xy + np.round(shift), window=9)
    assert seeded.status.all()
    np.testing.assert_allclose(seeded.xy - xy, np.tile(shift, (3, 1)), atol=0.1)
    unseeded = lucas_kanade(a, b, xy, window=9)
    assert (np.linalg.norm(unseeded.xy - xy - shift, axis=1) > 1.0).any()


def test_numpy_lk_equals_opencv_lk_on_same_inputs():
    tex = smooth_periodic_texture(128, 2.0, seed=12)
    a = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    b = np.clip(np.rint(fourier_shift(tex, 2.3, -1.4)), 0, 255).astype(np.uint8)
    rng = np.random.default_rng(13)
    xy = rng.uniform(20, 108, (80, 2))
    init = xy + (2.0, -1.0)
    ours = lucas_kanade(a, b, xy, init, window=9, eps=1e-3)
    cv = lucas_kanade_opencv(a, b, xy, init, window=9, eps=1e-3)
    ok = ours.status & cv.status
    assert ok.mean() > 0.95
    d = np.linalg.norm(ours.xy[ok] - cv.xy[ok], axis=1)
    assert np.median(d) < 0.01 and d.max() < 0.05


def _numpy_lk_gate_value(img: np.ndarray, xy: np.ndarray, window: int) -> np.ndarray:
    """What :func:`lucas_kanade` compares with ``min_eig``: lambda_1 of G built
    from central differences (eqs. 3.1-3.3, 4.5) over the window, / window^2."""
    ix, iy = gradients(img)
    a, b, c = structure_tensor(ix, iy, window)
    col, row = xy[:, 0].astype(int), xy[:, 1].astype(int)
    f64 = np.float64
    return min_eigenvalue(a[row, col].astype(f64), b[row, col].astype(f64), c[row, col].astype(f64)) / window**2


def _opencv_lk_min_eig(img: np.ndarray, xy: np.ndarray, window: int) -> np.ndarray:
    """The minimum eigenvalue OpenCV's LK reports (OPTFLOW_LK_GET_MIN_EIGENVALS)
    and compares with minEigThreshold."""
    pts = xy.astype(np.float32).reshape(-1, 1, 2)
    _, _, err = cv2.calcOpticalFlowPyrLK(
        img, img, pts, None, winSize=(window, window), maxLevel=0,
        flags=cv2.OPTFLOW_LK_GET_MIN_EIGENVALS, minEigThreshold=0.0,
    )
    return err.ravel().astype(np.float64)


def test_opencv_min_eig_scale_matches_what_opencv_reports():
    window = 9
    rng = np.random.default_rng(21)
    # I(x, y) = f(x) + g(y): OpenCV's Scharr derivative is then exactly 32 x the
    # central difference (its 3-10-3 cross smoothing acts on a constant), so the
    # two minimum eigenvalues differ only by the normalisation under test.
    f, g = rng.integers(0, 128, 64), rng.integers(0, 128, 64)
    sep = (f[None, :] + g[:, None]).astype(np.uint8)
    xy = rng.integers(8, 56, (100, 2)).astype(np.float64)
    ours = _numpy_lk_gate_value(sep, xy, window)
    assert ours.min() > 0
    np.testing.assert_allclose(_opencv_lk_min_eig(sep, xy, window) / OPENCV_MIN_EIG_SCALE, ours, rtol=1e-4)
    # Real textured windows: equal up to the difference between Scharr and
    # central differences, a few per cent on smooth texture.
    tex = np.clip(np.rint(smooth_periodic_texture(128, 3.0, seed=12)), 0, 255).astype(np.uint8)
    xy = rng.integers(12, 116, (300, 2)).astype(np.float64)
    ours = _numpy_lk_gate_value(tex, xy, window)
    ratio = _opencv_lk_min_eig(tex, xy, window) / OPENCV_MIN_EIG_SCALE / ours
    assert abs(np.median(ratio) - 1.0) < 0.04, np.median(ratio)
    assert np.abs(ratio - 1.0).max() < 0.1, (ratio.min(), ratio.max())
    # Hence one min_eig gates both backends alike: with the threshold at the
    # median window, they accept and reject the same points (bar those within
    # 10 % of the threshold, where the derivative filters may disagree).
    thr = float(np.median(ours))
    st_np = lucas_kanade(tex, tex, xy, window=window, min_eig=thr).status
    st_cv = lucas_kanade_opencv(tex, tex, xy, window=window, min_eig=thr).status
    clear = np.abs(ours / thr - 1.0) > 0.1
    assert clear.sum() > 200
    np.testing.assert_array_equal(st_cv[clear], st_np[clear])
    np.testing.assert_array_equal(st_np[clear], ours[clear] >= thr)


def test_forward_backward_rejects_inconsistent_points():
    tex = smooth_periodic_texture(128, 1.5, seed=14)
    a = np.clip(tex, 0, 255).astype(np.uint8)
    b = np.roll(a, (1, 2), axis=(0, 1))
    # Replace one region of frame k+1 with unrelated texture.
    b[60:100, 60:100] = np.clip(smooth_periodic_texture(40, 1.5, seed=15), 0, 255).astype(np.uint8)
    xy = np.array([[30.0, 30.0], [40.0, 90.0], [80.0, 80.0], [75.0, 85.0]])
    init = xy + (2, 1)
    for backend in ("numpy", "opencv"):
        fb = forward_backward(a, b, xy, init, None, 0.5, backend=backend)
        assert fb.ok[:2].all(), backend
        np.testing.assert_allclose(fb.xy[:2] - xy[:2], [[2, 1], [2, 1]], atol=0.05)
        assert not fb.ok[2:].any(), backend
    with pytest.raises(ValueError, match="backend"):
        forward_backward(a, b, xy, init, None, 0.5, backend="gpu")


def test_lk_rejects_bad_arguments():
    a = np.zeros((20, 20), np.float32)
    with pytest.raises(ValueError, match="window"):
        lucas_kanade(a, a, np.zeros((1, 2)), window=4)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        lucas_kanade(a, a, np.zeros((3,)))
    with pytest.raises(ValueError, match="finite"):
        lucas_kanade(a, a, np.array([[np.nan, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        lucas_kanade(a, a[:10], np.zeros((1, 2)))
    # A flat window is an aperture problem: status False, no crash.
    assert not lucas_kanade(a, a, np.array([[10.0, 10.0]])).status[0]


@pytest.mark.parametrize("shift", [(2.3, -1.6), (-0.3, 0.35), (1.25, -0.2)])
def test_match_one_refines_a_subpixel_shift(shift):
    # An exact sub-pixel translation (Fourier shift of a periodic band-limited
    # texture): the integer minimum is the rounded shift, and the parabola
    # through the SSD minimum and its neighbours recovers the fraction.
    from vision.fixation import match_one

    a = smooth_periodic_texture(128, 2.5, seed=6).astype(np.float32)
    b = fourier_shift(a, *shift).astype(np.float32)
    errs, int_errs = [], []
    for x, y in ((30, 40), (70, 60), (50, 80)):
        bx, by, ssd, at_edge, fx, fy = match_one(b, a[y : y + 30, x : x + 30], x, y, 4, 128 - 30, 128 - 30)
        assert (bx - x, by - y) == tuple(np.rint(shift).astype(int)) and not at_edge
        # The same SSD minimum as an explicit loop over the placements.
        tpl = a[y : y + 30, x : x + 30].astype(np.float64)
        ssd_loop = min(((b[y + dy : y + dy + 30, x + dx : x + dx + 30] - tpl) ** 2).sum()
                       for dy in range(-4, 5) for dx in range(-4, 5))
        assert ssd == pytest.approx(ssd_loop, rel=1e-4)
        errs.append(np.abs(np.array([bx - x + fx, by - y + fy]) - shift))
        int_errs.append(np.abs(np.array([bx - x, by - y]) - shift))
    assert np.max(errs) < 0.15, errs
    assert np.mean(errs) < 0.5 * np.mean(int_errs)  # much better than the integer shift


def test_parabola_vertex_is_the_vertex_of_the_fitted_parabola():
    from vision.fixation import parabola_vertex

    rng = np.random.default_rng(3)
    for _ in range(200):
        a, v, c = rng.uniform(0.1, 5.0), rng.uniform(-0.5, 0.5), rng.uniform(-3, 3)
        lo, mid, hi = (a * (t - v) ** 2 + c for t in (-1.0, 0.0, 1.0))
        coef = np.polyfit([-1.0, 0.0, 1.0], [lo, mid, hi], 2)  # independent: least-squares fit
        assert parabola_vertex(lo, mid, hi) == pytest.approx(-coef[1] / (2 * coef[0]), abs=1e-9)
    assert parabola_vertex(1.0, 1.0, 1.0) == 0.0  # flat: no vertex
    assert parabola_vertex(0.0, 1.0, 0.0) == 0.0  # a maximum, not a minimum
    assert parabola_vertex(10.0, 1.0, 0.0) == 0.5  # vertex at 0.56: clamped to half a pixel


@pytest.mark.parametrize("backend", ["numpy", "opencv"])
def test_forward_backward_back_window_is_a_second_solve_in_that_window(backend):
    # The backward solve of the check runs in its own (smaller) window: the
    # same as tracking forward in one window and back in the other by hand.
    from vision import lucas_kanade, lucas_kanade_opencv

    a = smooth_periodic_texture(96, 2.0, seed=9)
    b = fourier_shift(a, 0.7, -0.4)
    if backend == "opencv":
        a, b = (np.clip(np.rint(x), 0, 255).astype(np.uint8) for x in (a, b))
    solve = lucas_kanade if backend == "numpy" else lucas_kanade_opencv
    xy = np.random.default_rng(4).uniform(25, 70, (30, 2))
    init = xy + np.array([0.5, -0.5])
    fb = forward_backward(a, b, xy, init, None, 0.5, backend=backend, window=13, back_window=9)
    fwd = solve(a, b, xy, init, window=13)
    bwd = solve(b, a, fwd.xy, fwd.xy - (init - xy), window=9)
    np.testing.assert_allclose(fb.xy, fwd.xy)
    np.testing.assert_allclose(fb.fb_error, np.linalg.norm(bwd.xy - xy, axis=1))
    same = forward_backward(a, b, xy, init, None, 0.5, backend=backend, window=13)
    assert not np.allclose(same.fb_error, fb.fb_error)  # the window did change the backward solve
