"""Velocity from tracks against a synthetic scene with known motion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gnc.vision_nav import VisionNavConfig, velocity_from_tracks
from vision.tracks import Tracks

K = np.array([[221.7, 0.0, 127.5], [0.0, 221.7, 127.5], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])
R_CAM_B = np.array([0.0, 0.0, -0.77])
CFG = VisionNavConfig()


def _scene(rng, r_B0, r_B1, q0, q1, n=80, noise_px=0.0, relief_m=0.0):
    """Project random ground points (z ~ 0) into both frames; returns Tracks of frame 1."""
    R0 = Rotation.from_quat(q0, scalar_first=True).as_matrix()
    R1 = Rotation.from_quat(q1, scalar_first=True).as_matrix()
    c0, c1 = r_B0 + R0 @ R_CAM_B, r_B1 + R1 @ R_CAM_B
    # Points seen by the first camera: random pixels back-projected onto the plane.
    pix = rng.uniform(10, 245, (n, 2))
    rays = (R0 @ R_BC @ np.linalg.solve(K, np.column_stack([pix, np.ones(n)]).T)).T
    pts = c0 + rays * (-c0[2] / rays[:, 2:3])
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


def test_noise_free_scene_gives_the_exact_velocity():
    rng = np.random.default_rng(0)
    r0, v, a = np.array([20.0, -10.0, 300.0]), np.array([4.0, -3.0, -12.0]), np.array([0.1, -0.2, 0.5])
    dt = 0.1
    r1 = r0 + v * dt + 0.5 * a * dt**2
    q0, q1 = _q([3.0, -2.0, 10.0]), _q([3.4, -1.7, 10.5])
    tracks, c0 = _scene(rng, r0, r1, q0, q1)
    dz = (r1 - r0)[2] + ((Rotation.from_quat(q1, scalar_first=True).as_matrix()
                          - Rotation.from_quat(q0, scalar_first=True).as_matrix()) @ R_CAM_B)[2]
    m = velocity_from_tracks(tracks, 0, int(dt * 1e9), K, R_BC, R_CAM_B, q0, q1, c0[2], 0.0, a * dt, dz, 0.0, CFG)
    assert m is not None and m.n_used == 80
    np.testing.assert_allclose(m.v_L, (v + a * dt)[:2], atol=1e-6)  # horizontal velocity at the second frame


def test_noisy_tracks_are_consistent_with_the_reported_covariance():
    rng = np.random.default_rng(1)
    nees = []
    for _ in range(200):
        r0 = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(50, 500)])
        v = rng.normal(0, [5, 5, 3]) + np.array([0, 0, -8])
        dt = 0.1
        r1 = r0 + v * dt
        q0 = _q(rng.normal(0, 3, 3))
        q1 = _q(Rotation.from_quat(q0, scalar_first=True).as_euler("xyz", degrees=True) + rng.normal(0, 0.1, 3))
        tracks, c0 = _scene(rng, r0, r1, q0, q1, noise_px=0.08)
        sigma_h = 0.5
        h0 = c0[2] + rng.normal(0, sigma_h)
        sigma_dz = 0.01
        dz = v[2] * dt + rng.normal(0, sigma_dz)  # the filter's vertical displacement, with its error
        m = velocity_from_tracks(tracks, 0, int(dt * 1e9), K, R_BC, R_CAM_B, q0, q1, h0, sigma_h, np.zeros(3),
                                 dz, sigma_dz, CFG)
        e = m.v_L - v[:2]
        nees.append(e @ np.linalg.solve(m.R, e))
    # The covariance is honest (the inflation factor makes it a little conservative).
    assert 0.6 < np.mean(nees) < 2.5, np.mean(nees)
    assert np.mean(np.array(nees) < 9.21) > 0.97  # chi2(2) 99 %


def test_wrong_tracks_are_rejected():
    rng = np.random.default_rng(2)
    r0, v = np.array([0.0, 0.0, 200.0]), np.array([3.0, 1.0, -6.0])
    r1 = r0 + v * 0.1
    q = _q([0.0, 0.0, 0.0])
    tracks, c0 = _scene(rng, r0, r1, q, q, noise_px=0.05)
    xy = tracks.xy.copy()
    xy[:15] += rng.uniform(-8, 8, (15, 2))  # a burst of wrong correspondences
    bad = Tracks(ids=tracks.ids, xy=xy, prev_xy=tracks.prev_xy, age=tracks.age)
    m = velocity_from_tracks(bad, 0, 100_000_000, K, R_BC, R_CAM_B, q, q, c0[2], 0.2, np.zeros(3), v[2] * 0.1,
                             0.01, CFG)
    assert m is not None and m.n_used <= 80 - 12
    e = m.v_L - v[:2]
    assert np.hypot(e[0], e[1]) < 0.1
    assert e @ np.linalg.solve(m.R, e) < 13.82  # and consistent with its covariance (chi2(2) 99.9 %)
    # Without the rejection the burst would have pulled the estimate far off.
    naive = velocity_from_tracks(bad, 0, 100_000_000, K, R_BC, R_CAM_B, q, q, c0[2], 0.2, np.zeros(3), v[2] * 0.1,
                                 0.01, VisionNavConfig(outlier_iterations=0, outlier_mad_k=1e9))
    assert np.linalg.norm(naive.v_L - v[:2]) > 2 * np.linalg.norm(e)


def test_too_few_or_unusable_inputs_give_none():
    rng = np.random.default_rng(3)
    q = _q([0.0, 0.0, 0.0])
    tracks, c0 = _scene(rng, np.array([0.0, 0.0, 100.0]), np.array([0.1, 0.0, 99.0]), q, q, n=5)
    args = (K, R_BC, R_CAM_B, q, q)
    assert velocity_from_tracks(tracks, 0, 100_000_000, *args, c0[2], 0.1, np.zeros(3), -1.0, 0.01, CFG) is None
    tracks, c0 = _scene(rng, np.array([0.0, 0.0, 100.0]), np.array([0.1, 0.0, 99.0]), q, q, n=40)
    for h0, t1, dz in ((float("nan"), 100_000_000, -1.0), (-5.0, 100_000_000, -1.0), (c0[2], 0, -1.0),
                       (c0[2], 100_000_000, float("nan"))):
        assert velocity_from_tracks(tracks, 0, t1, *args, h0, 0.1, np.zeros(3), dz, 0.01, CFG) is None
    empty = Tracks(ids=np.zeros(0, np.int64), xy=np.zeros((0, 2)), prev_xy=np.zeros((0, 2)), age=np.zeros(0, np.int64))
    assert velocity_from_tracks(empty, 0, 100_000_000, *args, 100.0, 0.1, np.zeros(3), -1.0, 0.01, CFG) is None


@pytest.mark.parametrize("relief", [0.0, 2.0])
def test_relief_under_the_view_biases_only_mildly(relief):
    rng = np.random.default_rng(4)
    r0, v = np.array([0.0, 0.0, 100.0]), np.array([2.0, -1.0, -4.0])
    q = _q([1.0, 1.0, 0.0])
    tracks, c0 = _scene(rng, r0, r0 + v * 0.1, q, q, n=100, relief_m=relief)
    m = velocity_from_tracks(tracks, 0, 100_000_000, K, R_BC, R_CAM_B, q, q, c0[2], 0.5, np.zeros(3), v[2] * 0.1,
                             0.01, CFG)
    assert np.linalg.norm(m.v_L - v[:2]) < 0.05 + 0.05 * relief
