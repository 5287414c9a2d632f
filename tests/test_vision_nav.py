"""The vision measurement (mean ground flow between two frames) against a synthetic scene with known motion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scipy.stats import chi2

from gnc.vision_nav import VisionNavConfig, vision_measurement
from vision.tracks import Tracks

K = np.array([[221.7, 0.0, 127.5], [0.0, 221.7, 127.5], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])
R_CAM_B = np.array([0.0, 0.0, -0.77])
CFG = VisionNavConfig()


def _scene(rng, r_B0, r_B1, q0, q1, n=80, noise_px=0.0, relief_m=0.0, slope=(0.0, 0.0)):
    """Project random ground points (z ~ 0, or on a plane of ``slope`` through the point under the
    first camera) into both frames; returns Tracks of frame 1."""
    R0 = Rotation.from_quat(q0, scalar_first=True).as_matrix()
    R1 = Rotation.from_quat(q1, scalar_first=True).as_matrix()
    c0, c1 = r_B0 + R0 @ R_CAM_B, r_B1 + R1 @ R_CAM_B
    # Points seen by the first camera: random pixels back-projected onto the plane.
    pix = rng.uniform(10, 245, (n, 2))
    rays = (R0 @ R_BC @ np.linalg.solve(K, np.column_stack([pix, np.ones(n)]).T)).T
    sl = np.asarray(slope, float)
    # The ray c0 + t d meets z = sl . (p_xy - c0_xy) at t = -c0_z / (d_z - sl . d_xy).
    pts = c0 + rays * (-c0[2] / (rays[:, 2:3] - rays[:, :2] @ sl[:, None]))
    pts[:, 2] += rng.normal(0.0, relief_m, n) if relief_m else 0.0

    def project(c, R):
        p_C = (R_BC.T @ R.T @ (pts - c).T).T
        uv = (K @ p_C.T).T
        return uv[:, :2] / uv[:, 2:3]

    xy0, xy1 = project(c0, R0), project(c1, R1)
    xy0 += rng.normal(0, noise_px, xy0.shape) if noise_px else 0.0
    xy1 += rng.normal(0, noise_px, xy1.shape) if noise_px else 0.0
    return Tracks(ids=np.arange(n, dtype=np.int64), xy=xy1, prev_xy=xy0, age=np.ones(n, np.int64)), c0


def _q(euler_deg):
    return Rotation.from_euler("xyz", euler_deg, degrees=True).as_quat(scalar_first=True)


def _R(q):
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


def _measure(tracks, r0, r1, q0, q1, h_view=0.0, cfg=CFG, dt=0.1, s_view=None):
    return vision_measurement(tracks, 0, int(round(dt * 1e9)), K, R_BC, R_CAM_B, _R(q0), _R(q1), r0, r1, h_view,
                              0.0, cfg, s_view=s_view)


def _random_pair(rng, xy_m, z_range_m, v_sigma_mps, v_z_mps, noise_px):
    """A random frame pair 0.1 s apart: position within +-xy_m and z_range_m, velocity ~ N(0, v_sigma_mps) plus
    v_z_mps downwards, attitude ~ 3 deg turning ~ 0.1 deg, noisy tracks. Returns (tracks, r0, r1, q0, q1)."""
    r0 = np.array([rng.uniform(-xy_m, xy_m), rng.uniform(-xy_m, xy_m), rng.uniform(*z_range_m)])
    v = rng.normal(0, v_sigma_mps) + np.array([0, 0, v_z_mps])
    r1 = r0 + v * 0.1
    q0 = _q(rng.normal(0, 3, 3))
    q1 = _q(Rotation.from_quat(q0, scalar_first=True).as_euler("xyz", degrees=True) + rng.normal(0, 0.1, 3))
    tracks, _ = _scene(rng, r0, r1, q0, q1, noise_px=noise_px)
    return tracks, r0, r1, q0, q1


def _flow_model(r0, r1, q0, q1, h_view, b_mean):
    """The measurement model written out: mean ray-difference of a plane at h_view, for given mean ray b."""
    c0, c1 = r0 + _R(q0) @ R_CAM_B, r1 + _R(q1) @ R_CAM_B
    h0 = c0[2] - h_view
    return ((c1 - c0)[:2] + (c1 - c0)[2] * b_mean) / h0


def test_noise_free_scene_is_predicted_exactly_and_the_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    r0, v, a = np.array([20.0, -10.0, 300.0]), np.array([4.0, -3.0, -12.0]), np.array([0.1, -0.2, 0.5])
    dt = 0.1
    r1 = r0 + v * dt + 0.5 * a * dt**2
    q0, q1 = _q([3.0, -2.0, 10.0]), _q([3.4, -1.7, 10.5])
    tracks, _ = _scene(rng, r0, r1, q0, q1)
    m = _measure(tracks, r0, r1, q0, q1)
    assert m is not None and m.n_used == 80
    np.testing.assert_allclose(m.z, m.hx, rtol=0, atol=1e-12)  # the truth predicts the measurement
    # The telemetry velocity is the mean velocity over the interval.
    np.testing.assert_allclose(m.v_L, ((r1 - r0) / dt)[:2], atol=1e-6)
    # Jacobians by central differences of the model written out above (the mean ray b is held).
    b_mean = (m.hx * (r0 + _R(q0) @ R_CAM_B)[2] - ((r1 + _R(q1) @ R_CAM_B) - (r0 + _R(q0) @ R_CAM_B))[:2]) \
        / ((r1 + _R(q1) @ R_CAM_B) - (r0 + _R(q0) @ R_CAM_B))[2]
    np.testing.assert_allclose(_flow_model(r0, r1, q0, q1, 0.0, b_mean), m.hx, atol=1e-14)
    eps = 1e-3
    for k in range(3):  # all three (the filter takes the vertical ones as consider columns)
        d = np.zeros(3)
        d[k] = eps
        num_r = (_flow_model(r0, r1 + d, q0, q1, 0.0, b_mean) - _flow_model(r0, r1 - d, q0, q1, 0.0, b_mean)) / (2 * eps)
        num_c = (_flow_model(r0 + d, r1, q0, q1, 0.0, b_mean) - _flow_model(r0 - d, r1, q0, q1, 0.0, b_mean)) / (2 * eps)
        np.testing.assert_allclose(m.H_r[:, k], num_r, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(m.H_c[:, k], num_c, rtol=1e-6, atol=1e-12)
    assert m.H_r[:, 2].any() and m.H_c[:, 2].any()  # the divergence term: dz b_mean
    num_g = (_flow_model(r0, r1, q0, q1, eps, b_mean) - _flow_model(r0, r1, q0, q1, -eps, b_mean)) / (2 * eps)
    np.testing.assert_allclose(m.H_g, num_g, rtol=1e-6, atol=1e-12)


def test_a_raised_ground_is_a_scale_error_of_its_height_over_the_camera_height():
    # Unless the filter knows the ground's height (h_view), which then predicts it exactly.
    rng = np.random.default_rng(5)
    r0, v = np.array([0.0, 0.0, 120.0]), np.array([3.0, 1.0, 0.0])
    q = _q([0.0, 0.0, 0.0])
    dh = 7.0
    r0_ground = r0 - np.array([0.0, 0.0, dh])  # the same scene with the ground 7 m up is the lander 7 m down
    tracks, _ = _scene(rng, r0_ground, r0_ground + v * 0.1, q, q)
    m = _measure(tracks, r0, r0 + v * 0.1, q, q)
    h0 = (r0 + R_CAM_B)[2]
    np.testing.assert_allclose(m.z, m.hx * h0 / (h0 - dh), rtol=1e-9)
    np.testing.assert_allclose(m.z, _measure(tracks, r0, r0 + v * 0.1, q, q, h_view=dh).hx, rtol=1e-9)


def test_noisy_tracks_are_consistent_with_the_reported_covariance():
    # Independent pixel noise in both frames: the error of z has covariance R + 2 R_frame (the two frames'
    # offsets), which must be honest: the mean NEES over the trials lies in its chi-square 99.9 % band.
    rng = np.random.default_rng(1)
    nees = []
    for _ in range(200):
        tracks, r0, r1, q0, q1 = _random_pair(rng, 100.0, (50.0, 500.0), [5, 5, 3], -8.0, 0.4)
        m = _measure(tracks, r0, r1, q0, q1)
        e = m.z - m.hx
        nees.append(e @ np.linalg.solve(m.R + 2.0 * m.R_frame, e))
    n = len(nees)
    lo, hi = chi2.ppf([0.0005, 0.9995], 2 * n) / n
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


def test_wrong_tracks_are_rejected():
    rng = np.random.default_rng(2)
    r0, v = np.array([0.0, 0.0, 200.0]), np.array([3.0, 1.0, -6.0])
    r1 = r0 + v * 0.1
    q = _q([0.0, 0.0, 0.0])
    tracks, _ = _scene(rng, r0, r1, q, q, noise_px=0.3)
    xy = tracks.xy.copy()
    xy[:15] += rng.uniform(-8, 8, (15, 2))  # a burst of wrong correspondences
    bad = Tracks(ids=tracks.ids, xy=xy, prev_xy=tracks.prev_xy, age=tracks.age)
    m = _measure(bad, r0, r1, q, q)
    assert m is not None and m.n_used <= 80 - 12
    e = m.z - m.hx
    assert e @ np.linalg.solve(m.R + 2.0 * m.R_frame, e) < chi2.ppf(0.999, 2)  # consistent with its covariance
    # Without the rejection the burst would have pulled the estimate far off.
    naive = _measure(bad, r0, r1, q, q, cfg=VisionNavConfig(outlier_iterations=0, outlier_mad_k=1e9,
                                                                  max_track_scatter_px=1e9))
    assert np.linalg.norm(naive.z - naive.hx) > 5 * np.linalg.norm(e)


def test_too_few_or_unusable_inputs_give_none():
    rng = np.random.default_rng(3)
    q = _q([0.0, 0.0, 0.0])
    r0, r1 = np.array([0.0, 0.0, 100.0]), np.array([0.1, 0.0, 99.0])
    tracks, _ = _scene(rng, r0, r1, q, q, n=5)
    assert _measure(tracks, r0, r1, q, q) is None  # fewer than min_tracks
    tracks, _ = _scene(rng, r0, r1, q, q, n=40)
    assert _measure(tracks, r0, r1, q, q, dt=0.0) is None  # no interval
    assert _measure(tracks, np.array([0.0, 0.0, math.nan]), r1, q, q) is None  # non-finite prior
    assert _measure(tracks, r0 * [1, 1, 0] + [0, 0, 1.2], r1, q, q) is None  # camera at the ground
    empty = Tracks(ids=np.zeros(0, np.int64), xy=np.zeros((0, 2)), prev_xy=np.zeros((0, 2)), age=np.zeros(0, np.int64))
    assert _measure(empty, r0, r1, q, q) is None


@pytest.mark.parametrize("relief", [0.0, 2.0])
def test_relief_under_the_view_scatters_but_hardly_biases(relief):
    rng = np.random.default_rng(4)
    r0, v = np.array([0.0, 0.0, 100.0]), np.array([2.0, -1.0, -4.0])
    q = _q([1.0, 1.0, 0.0])
    tracks, _ = _scene(rng, r0, r0 + v * 0.1, q, q, n=100, relief_m=relief)
    m = _measure(tracks, r0, r0 + v * 0.1, q, q)
    # Relative error of the flow: relief of sigma s at height h scales each track by ~s/h; the mean by s/h/sqrt(n).
    assert np.linalg.norm(m.z - m.hx) < 1e-9 + 4 * relief / 100.0 / 10.0 * np.linalg.norm(m.hx)


def test_a_sloped_ground_is_predicted_exactly_with_its_slope_and_its_jacobian_matches_the_explicit_sum():
    # A steep, tilted descent over a 6 % slope: the level-ground model reads the slope as
    # horizontal motion; with the slope the model predicts the flow exactly, and H_s matches
    # central differences of the per-track flow written out (features on the sloped plane).
    rng = np.random.default_rng(11)
    r0, v = np.array([0.0, 0.0, 120.0]), np.array([2.0, -1.0, -12.0])
    dt = 0.1
    r1 = r0 + v * dt
    q0, q1 = _q([8.0, -5.0, 30.0]), _q([8.1, -5.1, 30.0])
    slope = np.array([0.06, -0.04])
    tracks, c0 = _scene(rng, r0, r1, q0, q1, slope=slope)
    level = _measure(tracks, r0, r1, q0, q1)
    sloped = _measure(tracks, r0, r1, q0, q1, s_view=slope)
    np.testing.assert_allclose(sloped.z, sloped.hx, rtol=0, atol=1e-12)
    level_err_mps = np.abs(level.z - level.hx) * (c0[2] / dt)
    assert np.max(level_err_mps) > 0.02, level_err_mps  # what the slope costs the level model [m/s]
    # H_s by central differences of mean_i (dr + dz b_i)(1 + s . a_i) / h0, rays held.
    R0, R1 = _R(q0), _R(q1)
    Kinv = np.linalg.inv(K)
    d0 = (R0 @ R_BC @ Kinv @ np.column_stack([tracks.prev_xy, np.ones(len(tracks))]).T).T
    d1 = (R1 @ R_BC @ Kinv @ np.column_stack([tracks.xy, np.ones(len(tracks))]).T).T
    a, b = d0[:, :2] / -d0[:, 2:3], d1[:, :2] / -d1[:, 2:3]
    c1 = r1 + R1 @ R_CAM_B

    def model(sv):
        return np.mean([((c1 - c0)[:2] + (c1 - c0)[2] * bi) * (1.0 + sv @ ai) for ai, bi in zip(a, b)], axis=0) / c0[2]

    np.testing.assert_allclose(model(slope), sloped.hx, rtol=1e-9)
    eps = 1e-4
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        np.testing.assert_allclose(sloped.H_s[:, k], (model(slope + d) - model(slope - d)) / (2 * eps), rtol=1e-6)


def test_the_per_frame_share_of_the_error_follows_the_calibrated_pixel_noise():
    # Each frame's tracks carry independent pixel noise sigma: a pair's per-track error variance is
    # 2 sigma^2 per axis, of which 2 frame_pixel_sigma_px^2 is per-frame. At sigma = the calibration,
    # all of it (capped at 1); at twice the calibration, a quarter. No slew, no rotation error.
    rng = np.random.default_rng(21)
    r0, r1 = np.array([0.0, 0.0, 200.0]), np.array([0.5, -0.3, 198.8])
    q = _q([0.0, 0.0, 0.0])
    cfg = VisionNavConfig(rotation_error_frac=0.0)
    for noise_px, expected in ((cfg.frame_pixel_sigma_px, 1.0), (2.0 * cfg.frame_pixel_sigma_px, 0.25)):
        shares = []
        for _ in range(20):
            tracks, _ = _scene(rng, r0, r1, q, q, n=200, noise_px=noise_px)
            m = _measure(tracks, r0, r1, q, q, cfg=cfg)
            total = np.trace(m.R + 2.0 * m.R_frame)
            shares.append(np.trace(2.0 * m.R_frame) / total)
        assert abs(np.mean(shares) - expected) < 0.08 * expected + 0.02, (noise_px, np.mean(shares))


# --------------------------------------------------------------------------- divergence (no altimeter)
def _measure_div(tracks, r0, r1, q0, q1, h_view=0.0, s_view=None, dt=0.1):
    return vision_measurement(tracks, 0, int(round(dt * 1e9)), K, R_BC, R_CAM_B, _R(q0), _R(q1), r0, r1, h_view,
                              0.0, CFG, s_view=s_view, with_divergence=True)


def _div_model(tracks, r0, r1, q0, q1, h_view, sv):
    """The divergence written out: the least-squares slope w of g_i = u + w b_i (2-D, u free), solved with
    lstsq on the stacked per-track equations, of the flows a plane of slope ``sv`` predicts for these rays."""
    R0, R1 = _R(q0), _R(q1)
    Kinv = np.linalg.inv(K)
    d0 = (R0 @ R_BC @ Kinv @ np.column_stack([tracks.prev_xy, np.ones(len(tracks))]).T).T
    d1 = (R1 @ R_BC @ Kinv @ np.column_stack([tracks.xy, np.ones(len(tracks))]).T).T
    a, b = d0[:, :2] / -d0[:, 2:3], d1[:, :2] / -d1[:, 2:3]
    c0, c1 = r0 + R0 @ R_CAM_B, r1 + R1 @ R_CAM_B
    h0 = c0[2] - h_view
    g = ((c1 - c0)[:2][None, :] + (c1 - c0)[2] * b) * (1.0 + a @ sv)[:, None] / h0
    n = len(b)
    X = np.zeros((2 * n, 3))
    X[0::2, 0] = 1.0
    X[1::2, 1] = 1.0
    X[0::2, 2] = b[:, 0]
    X[1::2, 2] = b[:, 1]
    return float(np.linalg.lstsq(X, g.reshape(-1), rcond=None)[0][2])


def test_divergence_is_the_vertical_displacement_over_the_height_and_its_jacobians_match_finite_differences():
    """On level ground every track's flow is (dr + dz b_i) / h0, so the fitted slope is dz / h0 exactly; over
    a 6 % slope the model with the slope predicts it exactly too, while dz / h0 alone is off. The Jacobians
    (positions, ground height, slope) match central differences of the fit written out with lstsq."""
    rng = np.random.default_rng(21)
    dt = 0.1
    for slope in ((0.0, 0.0), (0.06, -0.04)):
        sl = np.array(slope)
        r0, v = np.array([15.0, -8.0, 40.0]), np.array([1.5, -1.0, -2.5])
        r1 = r0 + v * dt
        q0, q1 = _q([4.0, -3.0, 20.0]), _q([4.2, -3.1, 20.2])
        tracks, c0 = _scene(rng, r0, r1, q0, q1, slope=slope)
        m = _measure_div(tracks, r0, r1, q0, q1, s_view=sl)
        d = m.divergence
        assert d is not None
        np.testing.assert_allclose(d.z, d.hx, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d.hx, _div_model(tracks, r0, r1, q0, q1, 0.0, sl), rtol=1e-9)
        c1 = r1 + _R(q1) @ R_CAM_B
        if not sl.any():
            np.testing.assert_allclose(d.z, (c1 - c0)[2] / c0[2], rtol=1e-9)
        else:
            assert abs(d.z - (c1 - c0)[2] / c0[2]) > 0.02 * abs(d.z)  # the slope matters
        eps = 1e-4
        for k in range(3):
            e = np.zeros(3)
            e[k] = eps
            num_r = (_div_model(tracks, r0, r1 + e, q0, q1, 0.0, sl) - _div_model(tracks, r0, r1 - e, q0, q1, 0.0, sl)) / (2 * eps)
            num_c = (_div_model(tracks, r0 + e, r1, q0, q1, 0.0, sl) - _div_model(tracks, r0 - e, r1, q0, q1, 0.0, sl)) / (2 * eps)
            np.testing.assert_allclose(d.H_r[k], num_r, rtol=1e-5, atol=1e-10)
            np.testing.assert_allclose(d.H_c[k], num_c, rtol=1e-5, atol=1e-10)
        num_g = (_div_model(tracks, r0, r1, q0, q1, eps, sl) - _div_model(tracks, r0, r1, q0, q1, -eps, sl)) / (2 * eps)
        np.testing.assert_allclose(d.H_g, num_g, rtol=1e-5, atol=1e-12)
        for k in range(2):
            e = np.zeros(2)
            e[k] = eps
            num_s = (_div_model(tracks, r0, r1, q0, q1, 0.0, sl + e) - _div_model(tracks, r0, r1, q0, q1, 0.0, sl - e)) / (2 * eps)
            np.testing.assert_allclose(d.H_s[k], num_s, rtol=1e-5, atol=1e-12)
    assert _measure(tracks, r0, r1, q0, q1).divergence is None  # only when asked for


def test_divergence_noise_is_consistent_with_its_reported_variance():
    """Independent pixel noise in both frames: the divergence's normalised error squared, over 300 random
    descents, has its mean inside the chi-square 99.9 % band (the variance is honest, not just an upper
    bound: 1 dof per trial)."""
    rng = np.random.default_rng(4)
    nees = []
    for _ in range(300):
        tracks, r0, r1, q0, q1 = _random_pair(rng, 50.0, (10.0, 400.0), [3, 3, 1], -5.0, 0.3)
        d = _measure_div(tracks, r0, r1, q0, q1).divergence
        nees.append((d.z - d.hx) ** 2 / (d.R / CFG.covariance_inflation))
    n = len(nees)
    lo, hi = chi2.ppf([0.0005, 0.9995], n) / n
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


def _cells_scene(rng, cells, common_px, n_per_cell=12, noise_px=0.05):
    """Tracks in ``cells`` (column, row) cells of 64 px only, each cell's tracks displaced together by their
    own N(0, common_px) offset in the second frame (a template that slipped) plus N(0, noise_px) each; level
    flight at 300 m, 1 m/s along x. Returns (tracks, r0, r1, q)."""
    q = _q([0.0, 0.0, 0.0])
    r0, r1 = np.array([0.0, 0.0, 300.0]), np.array([0.1, 0.0, 300.0])
    tracks, _ = _scene(rng, r0, r1, q, q, n=4000)
    cell = np.floor(tracks.prev_xy / 64.0).astype(int)
    xy, prev = [], []
    for cx, cy in cells:
        idx = np.flatnonzero((cell[:, 0] == cx) & (cell[:, 1] == cy))[:n_per_cell]
        xy.append(tracks.xy[idx] + rng.normal(0.0, common_px, 2) + rng.normal(0.0, noise_px, (idx.size, 2)))
        prev.append(tracks.prev_xy[idx])
    xy, prev = np.concatenate(xy), np.concatenate(prev)
    n = xy.shape[0]
    return Tracks(ids=np.arange(n, dtype=np.int64), xy=xy, prev_xy=prev, age=np.ones(n, np.int64)), r0, r1, q


def test_tracks_in_too_few_image_cells_give_no_measurement():
    """The covariance is cluster-robust over 64 px cells: it estimates the error a cell's tracks share (one
    template's features slip together) from the spread between the cells. With one cell that spread is zero by
    construction (the residuals sum to zero), so a slip of a few tenths of a pixel came out with the floor's
    1-sigma of hundredths (on a featureless mare: velocities metres per second off, believed to centimetres per
    second); with two cells the two sums are opposite and the covariance has rank one: no variance across the
    line between the cells but the floor's. Below ``min_clusters`` (5) cells vision gives no measurement; from 5
    cells on it does, the same one as without the limit."""
    rng = np.random.default_rng(11)
    one_cell = VisionNavConfig(min_clusters=1)
    nis = []
    for trial in range(100):
        tracks, r0, r1, q = _cells_scene(rng, [(1, 1)], common_px=0.3)
        assert _measure(tracks, r0, r1, q, q) is None
        m = _measure(tracks, r0, r1, q, q, cfg=one_cell)
        e = m.z - m.hx
        nis.append(float(e @ np.linalg.solve(m.R + 2.0 * m.R_frame, e)))
        tracks, r0, r1, q = _cells_scene(rng, [(1, 1), (2, 1)], common_px=0.3)
        assert _measure(tracks, r0, r1, q, q) is None
        m = _measure(tracks, r0, r1, q, q, cfg=one_cell)
        floor = CFG.covariance_inflation * (CFG.pixel_sigma_px / K[0, 0]) ** 2 / m.n_used  # the mean's, per axis
        assert np.linalg.eigvalsh(m.R)[0] <= floor * (1.0 + 1e-9)  # rank one but for the floor
    # A consistent 2-dof NIS exceeds 13.8 once in a thousand; with one cell the shared slip is not in it at all.
    assert np.mean(np.array(nis) > 13.8) > 0.9
    for cells in ([(0, 0), (3, 0), (1, 3)], [(0, 0), (3, 0), (1, 3), (2, 2)]):
        tracks, r0, r1, q = _cells_scene(rng, cells, common_px=0.3)
        assert _measure(tracks, r0, r1, q, q) is None
    for cells in ([(0, 0), (3, 0), (1, 3), (2, 2), (3, 3)], [(0, 0), (3, 0), (1, 3), (2, 2), (3, 3), (0, 2), (2, 0)]):
        tracks, r0, r1, q = _cells_scene(rng, cells, common_px=0.3)
        m, m1 = _measure(tracks, r0, r1, q, q), _measure(tracks, r0, r1, q, q, cfg=one_cell)
        assert m is not None and np.array_equal(m.R, m1.R) and np.array_equal(m.z, m1.z)
        lo, hi = np.linalg.eigvalsh(m.R)
        assert lo > 1e-2 * hi  # full rank


def test_tracks_that_do_not_follow_the_ground_give_no_measurement():
    """LK tracks of ground texture scatter about their common motion by tenths of a pixel (rendered descents: at
    most 0.16 px); on a near-featureless frame they wander over the detector noise by pixels, all the same way or
    none, so their mean is no ground flow at all (a 75 deg camera over the featureless mare at 500 m: 1.6-5.7 px,
    velocities 10-200 m/s off, each within its own wide covariance, and eighty of them moved the filter's
    velocity 2.5 m/s). Beyond ``max_track_scatter_px`` (1 px RMS per axis) the pair gives no measurement; below
    it, the same measurement as without the limit."""
    rng = np.random.default_rng(12)
    q = _q([0.0, 0.0, 0.0])
    r0, r1 = np.array([0.0, 0.0, 450.0]), np.array([0.6, -0.3, 449.0])  # 6 m/s, 3 m/s and 10 m/s down
    no_limit = VisionNavConfig(max_track_scatter_px=1e9)
    for sigma_px, given in ((0.05, True), (0.7, True), (1.4, False), (3.0, False)):
        for trial in range(20):
            tracks, _ = _scene(rng, r0, r1, q, q, n=80)
            wandered = Tracks(ids=tracks.ids, xy=tracks.xy + rng.normal(0.0, sigma_px, tracks.xy.shape),
                              prev_xy=tracks.prev_xy, age=tracks.age)
            m, m_all = _measure(wandered, r0, r1, q, q), _measure(wandered, r0, r1, q, q, cfg=no_limit)
            assert m_all is not None
            assert (m is not None) == given, (sigma_px, m_all.residual_px)
            if given:
                assert np.array_equal(m.z, m_all.z) and np.array_equal(m.R, m_all.R)
            else:
                assert m_all.residual_px > CFG.max_track_scatter_px
    # Tracks that wander together by pixels while their scatter stays small are a slip, not noise: the
    # cluster-robust covariance carries them (the cells' test above), this limit does not refuse them.
    tracks, _ = _scene(rng, r0, r1, q, q, n=80, noise_px=0.05)
    slipped = Tracks(ids=tracks.ids, xy=tracks.xy + [2.0, -1.0], prev_xy=tracks.prev_xy, age=tracks.age)
    assert _measure(slipped, r0, r1, q, q) is not None


def test_the_cells_keep_their_share_of_the_frame():
    """The cells are ``cluster_px`` (64 px) in a frame of 256 px or more and shrink with a smaller one: 32 px at
    128 px, 48 px in a 192 x 256 frame (its shorter side, read from the principal point). So a 128 px frame,
    whose 64 px cells were four, can still give a measurement: tracks in five of its 32 px cells do."""
    from gnc.vision_nav import cluster_cell_px

    def k_for(w, h):
        return np.array([[200.0, 0.0, (w - 1) / 2], [0.0, 200.0, (h - 1) / 2], [0.0, 0.0, 1.0]])

    for (w, h), cell in (((256, 256), 64.0), ((128, 128), 32.0), ((512, 512), 64.0), ((640, 480), 64.0),
                         ((192, 256), 48.0)):
        assert cluster_cell_px(k_for(w, h), CFG) == cell
    rng = np.random.default_rng(5)
    tracks, r0, r1, q = _cells_scene(rng, [(0, 0), (1, 0), (0, 1), (1, 1), (2, 1)], common_px=0.1, n_per_cell=40)
    # The same tracks moved 64 px up and left, into a 128 px frame (its 32 px cells); those that leave it dropped.
    k128 = K.copy()
    k128[:2, 2] = 63.5
    small = Tracks(ids=tracks.ids, xy=tracks.xy - 64.0, prev_xy=tracks.prev_xy - 64.0, age=tracks.age)
    inside = np.all((small.prev_xy >= 0) & (small.prev_xy < 128) & (small.xy >= 0) & (small.xy < 128), axis=1)
    small = Tracks(ids=small.ids[inside], xy=small.xy[inside], prev_xy=small.prev_xy[inside], age=small.age[inside])
    cells = np.unique(np.floor(small.prev_xy / 32.0).astype(int), axis=0)
    assert len(cells) >= 5 and len(np.unique(np.floor(small.prev_xy / 64.0).astype(int), axis=0)) <= 4
    m = vision_measurement(small, 0, 100_000_000, k128, R_BC, R_CAM_B, _R(q), _R(q), r0, r1, 0.0, 0.0, CFG)
    assert m is not None
