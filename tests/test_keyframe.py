"""Keyframe registration below the last map fix (issue 14): the filter's keyframe state and the keyframe fix.

Frames are rendered independently of the flight code (``bench.maps.synthetic.render_map_frame``: each
pixel's ray intersected with the map's DEM and the ground image sampled with SciPy).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.maps import onboard_map_from_product
from bench.maps.synthetic import render_map_frame
from bench.scenario.seeding import component_rng
from gnc.estimator import IDX_KZ, IDX_MB, make_estimator
from gnc.map_nav import MapMatcher, MapNavConfig, MapNavigator, make_keyframe
from gnc.messages import AttitudeMessage
from models.orbital_map import OrbitalMapConfig, render_orbital_map
from models.terrain import TerrainConfig, generate_surface

TERRAIN = TerrainConfig(size_m=320.0, texture_px=1280, geometry_px=81, patch_size_m=0.0, target_clear_radius_m=20.0)
MAPCFG = OrbitalMapConfig(size_m=300.0, image_noise_dn=1.0, dem_noise_m=0.0)
F_PX = 128.0 / math.tan(math.radians(30.0))
K = np.array([[F_PX, 0.0, 127.5], [0.0, F_PX, 127.5], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def onboard():
    surface = generate_surface(TERRAIN, component_rng(21, "terrain"))
    return onboard_map_from_product(render_orbital_map(surface, MAPCFG, (0.0, 0.0), np.random.default_rng(1)),
                                    MAPCFG)


def _R_LC(roll, pitch, yaw):
    return Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix() @ R_BC


def test_the_keyframe_state_is_minus_the_camera_position_estimates_error():
    f = make_estimator(None, np.array([3.0, -2.0, 45.0]), np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3),
                       map_bias_sigma_m=0.5)
    rng = np.random.default_rng(4)
    n = f.x.size
    A = rng.normal(size=(n, n)) * 0.1
    f.ekf.P = f.P + A @ A.T
    f.ekf.x = f.x + rng.normal(size=n) * 0.1
    x0, P0 = f.x, f.P
    t_ns, extra = 40_000_000, 0.02  # the frame 40 ms after the filter time
    f.map_bias_to_keyframe(t_ns, extra)
    # Independent: the new error state is J e with (b_map, b_kz)'s rows -(r + lag v), the old ones dropped.
    lag = 0.04
    J = np.eye(n)
    J[24:27, :] = 0.0
    for k, i in enumerate((24, 25, IDX_KZ)):
        J[i, k] = -1.0
        J[i, 3 + k] = -lag
    want = J @ P0 @ J.T
    want[24:26, 24:26] += np.eye(2) * extra**2
    np.testing.assert_allclose(f.P, want, rtol=1e-12, atol=1e-15)
    assert np.array_equal(f.x[:24], x0[:24]) and not f.x[IDX_MB].any() and f.x[IDX_KZ] == 0.0
    # A fix at that instant would say nothing new: r + v lag + b (+ g b_kz, the keyframe's height error
    # seen g away from its nadir: zero there) is known to the keyframe's own error.
    np.testing.assert_allclose(f.map_prior_cov_xy(t_ns), np.eye(2) * extra**2, atol=1e-12)
    # Away from the keyframe's nadir its height error shows: g = displacement / height.
    g = np.array([0.2, -0.1])
    H = np.zeros((2, n))
    H[0, 0] = H[1, 1] = 1.0
    H[0, 3] = H[1, 4] = lag
    H[:, 24:26] = np.eye(2)
    H[:, IDX_KZ] = g
    np.testing.assert_allclose(f.map_prior_cov_xy(t_ns, g), H @ f.P @ H.T, atol=1e-12)
    var_z = (P0[2, 2] + 2 * lag * P0[2, 5] + lag**2 * P0[5, 5])
    np.testing.assert_allclose(f.map_prior_cov_xy(t_ns, g), np.eye(2) * extra**2 + np.outer(g, g) * var_z, atol=1e-12)
    with pytest.raises(ValueError, match="no map bias"):
        make_estimator(None, np.zeros(3) + 40.0, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3)
                       ).map_bias_to_keyframe(0)


@pytest.mark.parametrize("e_k, e_now, move, att_k, att_now", [
    ((0.8, -0.5, 0.3), (0.4, 0.7, -0.2), (1.2, -0.6), (2.0, -1.0, 20.0), (-1.0, 1.5, 24.0)),
    ((-1.5, 0.9, -0.4), (-0.3, -0.2, 0.5), (-0.5, 2.0), (-3.0, 0.5, -60.0), (1.0, 0.0, -55.0)),
    # A 2 m height error of the keyframe's pose, 6.4 m of travel since: its magnification moves the fix 0.28 m.
    ((0.3, -0.2, 2.0), (0.1, 0.2, 0.0), (5.0, -4.0), (0.0, 0.0, 0.0), (1.0, -1.0, 5.0)),
])
def test_a_keyframe_fix_measures_the_camera_in_the_keyframes_frame(onboard, e_k, e_now, move, att_k, att_now):
    # The keyframe is laid down from an estimate off by e_k: it is the map shifted by e_k, so a later frame
    # matched against it reads its camera's true position plus e_k (horizontally), whatever its own estimate.
    xy = np.array([10.0, -12.0])
    r_k = np.array([*xy, float(onboard.dem_height(*xy)) + 45.0])
    R_k = _R_LC(*att_k)
    frame_k = render_map_frame(onboard, K, r_k, R_k, np.random.default_rng(0))
    made = make_keyframe(onboard, frame_k, K, R_k, r_k + np.array(e_k), 320)
    assert made is not None
    keyframe, height = made
    r_est_k = r_k + np.array(e_k)  # its height is taken above the DEM under the estimated position
    assert height == pytest.approx(r_est_k[2] - float(onboard.dem_height(*r_est_k[:2])), rel=1e-12)
    xy2 = xy + np.array(move)
    r_now = np.array([*xy2, float(onboard.dem_height(*xy2)) + 20.0])
    R_now = _R_LC(*att_now)
    frame = render_map_frame(onboard, K, r_now, R_now, np.random.default_rng(1))
    r_est = r_now + np.array(e_now)
    fix = MapMatcher(keyframe).fix(frame, K, R_now, r_est, 0.5, 0.0,
                                   keyframe_view=((r_k + np.array(e_k))[:2], height))
    assert fix.ok, fix.reason
    # Plus the keyframe's magnification about its nadir by its height error: g dz_k (NavFilter's model).
    g = (r_est[:2] - r_est_k[:2]) / height
    want = r_now[:2] + np.array(e_k[:2]) + g * e_k[2]
    err_px = (fix.r_CM_xy_m - want) / fix.work_res_m
    assert np.all(np.abs(err_px) < 0.3), err_px
    assert fix.peak > 0.8


def test_the_navigator_takes_a_keyframe_below_its_fix_window_then_fixes_against_it(onboard):
    rot = Rotation.from_euler("xyz", [1.0, -2.0, 30.0], degrees=True)
    q, R_LB = rot.as_quat(scalar_first=True), rot.as_matrix()
    r_B = np.array([5.0, 8.0, float(onboard.dem_height(5.0, 8.0)) + 40.0])
    e = np.array([0.6, -0.4, 0.0])
    f = make_estimator(None, r_B + e, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3), map_bias_sigma_m=0.5)
    f.set_attitude(AttitudeMessage(0, q))
    frame = render_map_frame(onboard, K, r_B, R_LB @ R_BC, np.random.default_rng(0))
    # A navigator whose map fixes never locked takes no keyframe: laid through the unlocked pose it would carry
    # the hand-over error as the map's (a 100 m georeferencing error: 32 keyframe fixes, NIS 208, 196 m miss).
    unlocked = MapNavigator(onboard, MapNavConfig(period_ns=100_000_000), K, R_BC, np.zeros(3))
    assert unlocked.on_frame(0, frame, f) is None and unlocked.stats.keyframe_t_ns is None
    assert unlocked.stats.never_locked and not unlocked.wants_frame(100_000_000, 40.0)
    nav = MapNavigator(onboard, MapNavConfig(period_ns=100_000_000), K, R_BC, np.zeros(3))
    nav.stats.locked = True  # its map fixes above 50 m had located the lander
    assert nav.wants_frame(0, 40.0) and not nav.wants_frame(0, 4.0)  # below 50 m: the keyframe's window
    assert nav.on_frame(0, frame, f) is None  # the keyframe
    assert nav.stats.keyframe_t_ns == 0 and nav.stats.attempts == 0 and nav.stats.frames_used == 1
    np.testing.assert_allclose(nav.stats.keyframe_r_C_m, r_B + e)
    np.testing.assert_allclose(f.P[24:26, 0:2], -f.P[0:2, 0:2])
    # The lander moved (truth 0.5 m east, 15 m lower); its estimate drifted 0.3 m north meanwhile.
    r_B2 = r_B + np.array([0.5, 0.0, -15.0])
    f.ekf.x[0:3] = r_B2 + e + np.array([0.0, 0.3, 0.0])
    f.ekf.P[0:2, 0:2] += np.eye(2) * 0.3**2
    frame2 = render_map_frame(onboard, K, r_B2, R_LB @ R_BC, np.random.default_rng(1))
    fix = nav.on_frame(100_000_000, frame2, f)
    assert fix is not None and fix.ok and nav.stats.keyframe_updates == 1 and nav.stats.keyframe_gate_rejected == 0
    assert nav.stats.updates == 0  # no map fix
    # The fix tells r - r_keyframe: the estimate's error since the keyframe (the 0.3 m drift) mostly goes.
    err = f.x[0:2] - (r_B2[:2] + e[:2])
    assert abs(err[1]) < 0.1 and abs(err[0]) < 0.1, err
    # A filter without b_map cannot hold a keyframe: none is taken, and no more frames are asked for.
    plain = make_estimator(None, r_B, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3))
    plain.set_attitude(AttitudeMessage(0, q))
    nav2 = MapNavigator(onboard, MapNavConfig(), K, R_BC, np.zeros(3))
    nav2.stats.locked = True
    assert nav2.on_frame(0, frame, plain) is None and nav2.stats.keyframe_t_ns is None
    assert not nav2.wants_frame(2_000_000_000, 40.0)
    # Switched off: no frame below the fix window.
    assert not MapNavigator(onboard, MapNavConfig(keyframe=False), K, R_BC, np.zeros(3)).wants_frame(0, 40.0)


def test_the_keyframe_summary_scores_each_fix_against_truth_and_its_own_sigma():
    """A keyframe fix's error is measured against truth + map shift + the keyframe's own pose error
    (horizontal e_k, and the height error dz_k magnified by g = (r_C - r_C,k)/h_k); a false lock is one
    beyond 5 of its own sigmas. Written out by hand for three fixes: one exact, one 2 sigma off, one
    6 sigma off, and one the matcher refused (not scored)."""
    from types import SimpleNamespace

    from bench.sim.run import _keyframe_summary

    shift = np.array([1.0, -2.0])
    r_k = np.array([3.0, 4.0, 50.0])  # the estimated camera position the keyframe was laid with
    truth_at = {0: np.array([2.5, 6.2, 50.4]), 1: np.array([7.0, 4.0, 30.0]), 2: np.array([3.0, 9.0, 20.0]),
                3: np.array([3.0, 9.0, 19.0])}
    e_k, dz_k = r_k[:2] - (truth_at[0][:2] + shift), r_k[2] - truth_at[0][2]

    def fix(t, err_xy, sigma, ok=True):
        offset = np.array([0.2, -0.1])
        r_est = truth_at[t][:2] + np.array([0.3, 0.1])  # the fix's own estimate of the camera: g from it
        g = (r_est - r_k[:2]) / r_k[2]
        r_cm = truth_at[t][:2] + shift + e_k + g * dz_k + np.asarray(err_xy)
        return SimpleNamespace(ok=ok, r_CM_xy_m=r_cm, offset_xy_m=r_cm - r_est,
                               total_cov_xy_m2=np.eye(2) * sigma**2) if ok else SimpleNamespace(ok=False)

    log = [(1, fix(1, [0.0, 0.0], 0.1), True, True), (2, fix(2, [0.0, 0.2], 0.1), True, True),
           (3, fix(3, [0.6, 0.0], 0.1), True, False), (3, fix(3, [9.0, 9.0], 0.1, ok=False), False, None)]
    stats = SimpleNamespace(keyframe_log=log, keyframe_attempts=4, keyframe_refused=1, keyframe_updates=3,
                            keyframe_gate_rejected=1, keyframes=[(0, r_k, r_k[2])])
    s = _keyframe_summary(stats, shift, truth_at)
    assert s["keyframes"] == 1
    assert s["keyframe_err_xy_m"] == pytest.approx(list(e_k)) and s["keyframe_err_z_m"] == pytest.approx(dz_k)
    assert s["keyframe_fix_err_max_m"] == pytest.approx(0.6)
    assert s["keyframe_fix_err_rms_m"] == pytest.approx(np.sqrt((0.0 + 0.04 + 0.36) / 3))
    assert s["keyframe_fix_nis_mean"] == pytest.approx((0.0 + 4.0 + 36.0) / 3)
    assert s["keyframe_false_locks"] == 1


def test_fixes_after_a_second_keyframe_are_scored_against_it():
    """The lander flew off its first keyframe and a second was taken at t = 2 (laid through another pose, with
    another error): the fix at t = 1 is scored against the first, those at t = 3 and 4 against the second,
    each written out by hand; the summary's keyframe fields stay the first's."""
    from types import SimpleNamespace

    from bench.sim.run import _keyframe_summary

    shift = np.array([0.5, 0.5])
    truth_at = {0: np.array([0.0, 0.0, 45.0]), 1: np.array([4.0, 1.0, 35.0]), 2: np.array([12.0, 3.0, 30.0]),
                3: np.array([15.0, 4.0, 29.0]), 4: np.array([18.0, 5.0, 28.0])}
    keyframes = [(0, np.array([0.2, -0.1, 45.3]), 45.3), (2, np.array([11.6, 3.3, 29.8]), 29.8)]

    def fix(t, k, err_xy):
        _, r_k, h_k = keyframes[k]
        e_k, dz_k = r_k[:2] - (truth_at[k * 2][:2] + shift), r_k[2] - truth_at[k * 2][2]
        r_est = truth_at[t][:2] + np.array([0.1, -0.2])
        r_cm = truth_at[t][:2] + shift + e_k + (r_est - r_k[:2]) / h_k * dz_k + np.asarray(err_xy)
        return SimpleNamespace(ok=True, r_CM_xy_m=r_cm, offset_xy_m=r_cm - r_est, total_cov_xy_m2=np.eye(2) * 0.01)

    log = [(1, fix(1, 0, [0.0, 0.1]), True, True), (3, fix(3, 1, [0.2, 0.0]), True, True),
           (4, fix(4, 1, [0.0, 0.0]), True, True)]
    stats = SimpleNamespace(keyframe_log=log, keyframe_attempts=3, keyframe_refused=0, keyframe_updates=3,
                            keyframe_gate_rejected=0, keyframes=keyframes)
    s = _keyframe_summary(stats, shift, truth_at)
    assert s["keyframes"] == 2 and s["keyframe_t_s"] == 0.0 and s["keyframe_height_m"] == 45.3
    assert s["keyframe_fix_err_max_m"] == pytest.approx(0.2)
    assert s["keyframe_fix_err_rms_m"] == pytest.approx(np.sqrt((0.01 + 0.04 + 0.0) / 3))


@pytest.mark.parametrize("rekeyframe", [True, False])
def test_a_lander_that_flies_off_its_keyframe_takes_another(onboard, rekeyframe):
    """A late divert below the map fixes: the keyframe taken at 40 m, then the lander 10 m lower and 16-19 m
    to the east, its estimate drifting a little (the filter's sigma grown by 0.3 m each frame): the template
    and its window no longer fit in the keyframe, so its fixes are refused. With ``rekeyframe`` the first such
    refusal lays that frame as a second keyframe and the next fixes match against it; without, every one is
    refused. A frame that fails near the keyframe's centre (a blank one) takes no new keyframe."""
    rot = Rotation.from_euler("xyz", [1.0, -2.0, 30.0], degrees=True)
    q, R_LB = rot.as_quat(scalar_first=True), rot.as_matrix()
    r_B = np.array([-10.0, 8.0, float(onboard.dem_height(-10.0, 8.0)) + 40.0])
    f = make_estimator(None, r_B, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3), map_bias_sigma_m=0.5)
    f.set_attitude(AttitudeMessage(0, q))
    nav = MapNavigator(onboard, MapNavConfig(period_ns=10_000_000, rekeyframe=rekeyframe), K, R_BC, np.zeros(3))
    nav.stats.locked = True
    nav.on_frame(0, render_map_frame(onboard, K, r_B, R_LB @ R_BC, np.random.default_rng(0)), f)
    assert len(nav.stats.keyframes) == 1
    blank = np.full((256, 256), 120, np.uint8)
    assert not nav.on_frame(10_000_000, blank, f).ok and len(nav.stats.keyframes) == 1
    outcomes = []
    for k in range(2, 6):
        r_now = r_B + np.array([14.0 + k, 0.0, -10.0])
        f.ekf.x[0:3] = r_now
        f.ekf.P[0:2, 0:2] += np.eye(2) * 0.3**2
        frame = render_map_frame(onboard, K, r_now, R_LB @ R_BC, np.random.default_rng(k))
        outcomes.append(nav.on_frame(k * 10_000_000, frame, f).ok)
    if rekeyframe:
        assert len(nav.stats.keyframes) == 2 and not outcomes[0] and any(outcomes[1:]), outcomes
        t_k, r_k, h_k = nav.stats.keyframes[1]
        assert t_k == 20_000_000 and r_k[0] == pytest.approx(r_B[0] + 16.0) and 28.0 < h_k < 32.0
        assert nav.stats.keyframe_t_ns == 0  # the summary's keyframe is the first
    else:
        assert len(nav.stats.keyframes) == 1 and not any(outcomes), outcomes
