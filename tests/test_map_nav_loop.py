"""Map fixes in the filter (issue 14): the EKF position update, the first-fix confirmation, the scenario switch."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.maps import onboard_map_from_product
from bench.maps.synthetic import render_map_frame
from bench.scenario import ScenarioError, load_scenario
from bench.scenario.seeding import component_rng
from bench.sim.flight_build import build_flight_software
from gnc.estimator import IDX_MB, KIND_MAP, make_estimator
from gnc.map_nav import REFUSALS, MapNavConfig, MapNavigator
from gnc.messages import AttitudeMessage
from models.orbital_map import OrbitalMapConfig, render_orbital_map
from models.terrain import TerrainConfig, generate_surface

TERRAIN = TerrainConfig(size_m=320.0, texture_px=1280, geometry_px=81, patch_size_m=0.0, target_clear_radius_m=20.0)
MAPCFG = OrbitalMapConfig(size_m=300.0, image_noise_dn=1.0, dem_noise_m=0.0)
F_PX = 128.0 / math.tan(math.radians(30.0))
K = np.array([[F_PX, 0.0, 127.5], [0.0, F_PX, 127.5], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])
LEVER_B = np.array([0.3, -0.2, -1.0])  # camera position in B [m]


@pytest.fixture(scope="module")
def onboard():
    surface = generate_surface(TERRAIN, component_rng(21, "terrain"))
    return onboard_map_from_product(render_orbital_map(surface, MAPCFG, (0.0, 0.0), np.random.default_rng(1)),
                                    MAPCFG)


def _filter(r0, q_LB):
    f = make_estimator(None, r0, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3))
    f.set_attitude(AttitudeMessage(0, np.asarray(q_LB, float)))
    return f


def test_map_position_update_is_the_kalman_update_under_the_gate():
    f = _filter(np.array([10.0, -5.0, 300.0]), [1.0, 0.0, 0.0, 0.0])
    assert KIND_MAP not in f.counters  # counted only once a fix is made: summaries without maps are unchanged
    x0, P0 = f.x, f.P
    lever = np.array([0.4, -0.1])
    z = x0[:2] + lever + np.array([3.0, -2.0])
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    rec = f.update_map_position(0, z, R, lever)
    assert rec.accepted and f.counters[KIND_MAP]["accepted"] == 1
    # Independent: the textbook update with H picking the horizontal position.
    H = np.zeros((2, x0.size))
    H[0, 0] = H[1, 1] = 1.0
    S = H @ P0 @ H.T + R
    Kg = P0 @ H.T @ np.linalg.inv(S)
    y = z - (x0[:2] + lever)
    assert np.allclose(f.x, x0 + Kg @ y, atol=1e-9)
    assert np.allclose(f.P, (np.eye(x0.size) - Kg @ H) @ P0, atol=1e-6)
    assert rec.nis == pytest.approx(float(y @ np.linalg.solve(S, y)))
    # A fix far outside the gate changes nothing.
    x1 = f.x
    far = f.update_map_position(0, x1[:2] + lever + 500.0, R, lever)
    assert not far.accepted and far.reason == "gate" and np.array_equal(f.x, x1)
    assert f.counters[KIND_MAP]["rejected"] == 1


@pytest.mark.parametrize("bias", [False, True])
def test_a_fix_off_the_filter_time_is_predicted_and_linearised_through_the_velocity(bias):
    """A fix stamped 80 ms after the filter time predicts ``r + v lag``, and its Jacobian carries the velocity
    column ``lag I`` as well: the update is the textbook one with that H, and its innovation covariance is
    :meth:`map_prior_cov_xy` plus R (the two share one model of the fix)."""
    f = make_estimator(None, np.array([10.0, -5.0, 300.0]), np.array([4.0, -3.0, -20.0]), 0,
                       altimeter_mount_B_m=np.zeros(3), map_bias_sigma_m=1.5 if bias else None)
    f.set_attitude(AttitudeMessage(0, np.array([1.0, 0.0, 0.0, 0.0])))
    assert f.has_map_bias == bias
    lag_s, t_ns = 0.08, 80_000_000
    x0, P0 = f.x, f.P
    lever = np.array([0.4, -0.1])
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    prior = f.map_prior_cov_xy(t_ns)
    H = np.zeros((2, x0.size))
    H[0, 0] = H[1, 1] = 1.0
    H[0, 3] = H[1, 4] = lag_s
    if bias:
        H[:, IDX_MB] = np.eye(2)
    z = x0[:2] + x0[3:5] * lag_s + lever + np.array([1.0, -0.5])
    rec = f.update_map_position(t_ns, z, R, lever)
    assert rec.accepted
    S = H @ P0 @ H.T + R
    np.testing.assert_allclose(rec.S, S, atol=1e-9)
    np.testing.assert_allclose(prior, H @ P0 @ H.T, atol=1e-9)
    Kg = P0 @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(f.x, x0 + Kg @ (z - H @ x0 - lever), atol=1e-9)


def _attitude(yaw_deg):
    return Rotation.from_euler("xyz", [2.0, -1.0, yaw_deg], degrees=True)


def test_first_fix_waits_for_a_consecutive_agreeing_one_then_updates_the_filter(onboard):
    rot = _attitude(25.0)
    q = rot.as_quat(scalar_first=True)
    R_LB = rot.as_matrix()
    r_B = np.array([12.0, -8.0, float(onboard.dem_height(12.0, -8.0)) + 150.0])
    est = r_B + np.array([9.0, -6.0, 0.0])  # a hand-over error well inside the filter's own sigma
    f = _filter(est, q)
    nav = MapNavigator(onboard, MapNavConfig(period_ns=100_000_000), K, R_BC, LEVER_B)
    frame = render_map_frame(onboard, K, r_B + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(0))
    fix = nav.on_frame(0, frame, f)
    assert fix is not None and fix.ok and nav.stats.unconfirmed == 1 and nav.stats.updates == 0
    assert np.array_equal(f.x[:3], est)  # not used yet
    assert nav.on_frame(50_000_000, frame, f) is None  # not due: period 100 ms
    fix2 = nav.on_frame(100_000_000, frame, f)
    assert fix2.ok and nav.stats.locked and nav.stats.updates == 1 and nav.stats.gate_rejected == 0
    # The body position moved to the truth (the map has no shift here), within the fix's own sigma.
    err = f.x[:2] - r_B[:2]
    assert np.all(np.abs(err) < 3.0 * np.sqrt(np.diag(fix2.cov_xy_m2)) + 0.05), err


def test_disagreeing_consecutive_fixes_are_not_used(onboard):
    rot = _attitude(-40.0)
    R_LB = rot.as_matrix()
    r_B = np.array([-20.0, 10.0, float(onboard.dem_height(-20.0, 10.0)) + 140.0])
    f = _filter(r_B + np.array([4.0, 3.0, 0.0]), rot.as_quat(scalar_first=True))
    nav = MapNavigator(onboard, MapNavConfig(period_ns=100_000_000), K, R_BC, LEVER_B)
    frame_a = render_map_frame(onboard, K, r_B + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(0))
    r_B2 = r_B + np.array([15.0, 0.0, 0.0])  # the second frame shows ground 15 m away: a jump no filter makes
    frame_b = render_map_frame(onboard, K, r_B2 + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(1))
    assert nav.on_frame(0, frame_a, f).ok
    assert nav.on_frame(100_000_000, frame_b, f).ok
    assert nav.stats.updates == 0 and nav.stats.unconfirmed == 2 and not nav.stats.locked
    # Refusals are counted under fixed identifiers (a campaign's columns do not depend on what happened).
    assert set(nav.stats.refused) == set(REFUSALS.values()) and sum(nav.stats.refused.values()) == 0
    blank = np.full_like(frame_a, 120)
    assert not nav.on_frame(200_000_000, blank, f).ok and nav.stats.refused["peak_not_clear"] == 1


def test_a_hand_over_error_beyond_the_search_window_is_acquired_by_widening_it(onboard):
    # 72 m off with the filter's 20 m sigma: 3.6 sigma, outside the 3-sigma coarse window, so every fix is
    # refused and, without widening, the lander would fly its hand-over error to touchdown.
    rot = _attitude(10.0)
    q, R_LB = rot.as_quat(scalar_first=True), rot.as_matrix()
    r_B = np.array([-40.0, 5.0, float(onboard.dem_height(-40.0, 5.0)) + 90.0])
    est = r_B + np.array([72.0, 0.0, 0.0])
    frame = render_map_frame(onboard, K, r_B + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(0))
    runs = {}
    for name, cfg in (("fixed", MapNavConfig(period_ns=10_000_000, acquire_widen_factor=1.0)),
                      ("widening", MapNavConfig(period_ns=10_000_000))):
        f = _filter(est, q)
        nav = MapNavigator(onboard, cfg, K, R_BC, LEVER_B)
        for k in range(8):  # 10 ms apart: within the filter's update lag of its (unpropagated) time
            nav.on_frame(k * 10_000_000, frame, f)
        runs[name] = (f, nav)
    f, nav = runs["fixed"]
    assert not nav.stats.locked and nav.stats.updates == 0 and nav.stats.search_sigmas_max == 3.0
    assert nav.stats.refused["peak_not_clear"] + nav.stats.refused["peak_on_window_edge"] == 8
    assert np.array_equal(f.x[:3], est)
    f, nav = runs["widening"]
    # Three refusals at 3 sigma, then 4.5 sigma: a fix, confirmed by the next, and the filter moves to the truth.
    assert nav.stats.refused["peak_not_clear"] + nav.stats.refused["peak_on_window_edge"] == 3
    assert nav.stats.search_sigmas_max == pytest.approx(4.5) and nav.stats.locked and nav.stats.updates >= 1
    # The lock scaled the horizontal sigmas by the window's factor first, so the 3.6-sigma fix passes the gate.
    assert nav.stats.gate_rejected == 0
    assert np.all(np.abs(f.x[:2] - r_B[:2]) < 1.0), f.x[:2] - r_B[:2]


def _locked_then_overconfident(onboard, cfg, bias_xy_m):
    """A navigator locked at the truth (two agreeing fixes of a frame from it), then the filter's horizontal
    position moved by ``bias_xy_m`` and its horizontal sigmas shrunk 20-fold: the state a biased fix that the
    filter trusted leaves behind. Returns the filter, the navigator, the frame, the body's truth and the time."""
    rot = _attitude(15.0)
    q, R_LB = rot.as_quat(scalar_first=True), rot.as_matrix()
    r_B = np.array([8.0, -12.0, float(onboard.dem_height(8.0, -12.0)) + 150.0])
    f = _filter(r_B + np.array([2.0, -1.5, 0.0]), q)
    nav = MapNavigator(onboard, cfg, K, R_BC, LEVER_B)
    frame = render_map_frame(onboard, K, r_B + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(0))
    nav.on_frame(0, frame, f)
    nav.on_frame(10_000_000, frame, f)
    assert nav.stats.locked and nav.stats.updates == 1 and nav.stats.gate_rejected == 0
    f.ekf.x[0:2] += bias_xy_m
    d = np.ones(f.P.shape[0])
    d[0:2] = 0.05
    f.ekf.P = f.P * np.outer(d, d)
    return f, nav, frame, r_B, 20_000_000


@pytest.mark.parametrize("relock_after", [0, 2, 3])
def test_fixes_the_gate_refuses_that_agree_with_one_another_re_lock_the_filter(onboard, relock_after):
    # 3 m off with sigmas of centimetres: every fix of the truth's frame is far outside the gate. Without a
    # re-lock the filter keeps its error to the end; with one, the n-th agreeing refused fix scales the
    # horizontal sigmas until its innovation is about 2 sigma-squared and is applied: the filter is back at
    # the truth.
    cfg = MapNavConfig(period_ns=10_000_000, relock_after=relock_after)
    bias = np.array([3.0, -2.0])
    f, nav, frame, r_B, t0 = _locked_then_overconfident(onboard, cfg, bias)
    sigma_before = np.sqrt(np.diag(f.P)[:2])
    for k in range(5):
        nav.on_frame(t0 + k * 10_000_000, frame, f)
        if relock_after and k + 1 < relock_after:
            assert nav.stats.relocks == 0 and nav.stats.gate_rejected == k + 1
    err = f.x[:2] - r_B[:2]
    if relock_after == 0:
        assert nav.stats.relocks == 0 and nav.stats.gate_rejected == 5
        assert np.all(np.abs(err - bias) < 0.5), err  # still where the bias put it
    else:
        assert nav.stats.relocks == 1 and nav.stats.gate_rejected == relock_after
        assert np.all(np.abs(err) < 0.3), err
        assert np.all(np.sqrt(np.diag(f.P)[:2]) > sigma_before)
    # Every fix was handed to the filter, and the log says which the gate took in the end.
    assert nav.stats.updates == 6
    assert sum(1 for *_, used, ok in nav.stats.log if used and ok) == 6 - nav.stats.gate_rejected + nav.stats.relocks


def test_refused_fixes_that_disagree_with_one_another_do_not_re_lock(onboard):
    # The gate refuses both, but the second shows ground 6 m from the first: one of them is wrong, and a
    # re-lock would trust it, so the filter keeps its state.
    cfg = MapNavConfig(period_ns=10_000_000, relock_after=2)
    f, nav, frame, r_B, t0 = _locked_then_overconfident(onboard, cfg, np.array([3.0, -2.0]))
    rot = _attitude(15.0)
    R_LB = rot.as_matrix()
    moved = r_B + np.array([0.0, 6.0, 0.0])
    frame_b = render_map_frame(onboard, K, moved + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(1))
    x0 = f.x
    for k, fr in enumerate((frame, frame_b, frame, frame_b)):
        nav.on_frame(t0 + k * 10_000_000, fr, f)
    assert nav.stats.gate_rejected == 4 and nav.stats.relocks == 0
    assert np.array_equal(f.x, x0)


@pytest.mark.parametrize("height_m, coarse", [(230.0, True), (150.0, False)])
def test_the_common_error_is_carried_for_the_correlation_time_of_the_fix_kind(onboard, height_m, coarse):
    # 230 m: 1.04 m per frame pixel over the 1 m level, a coarse fix (coarse_weight 1), whose common error lasts
    # coarse_common_time_s (20 s here; the default is common_time_s's 5 s); 150 m: 0.68 m, a fine one,
    # common_time_s. Fixes 10 ms apart: b_map is carried from one to the next with phi = exp(-0.01 s / tau)
    # (the first update resets it: phi 0).
    rot = _attitude(5.0)
    q, R_LB = rot.as_quat(scalar_first=True), rot.as_matrix()
    r_B = np.array([0.0, 0.0, float(onboard.dem_height(0.0, 0.0)) + height_m])
    f = make_estimator(None, r_B + np.array([1.5, -1.0, 0.0]), np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3),
                       map_bias_sigma_m=0.5)
    f.set_attitude(AttitudeMessage(0, q))
    phis, step = [], f.step_map_bias
    f.step_map_bias = lambda phi, sigma_m, scale=1.0: (phis.append(phi), step(phi, sigma_m, scale))
    cfg = MapNavConfig(period_ns=10_000_000, coarse_common_time_s=20.0)
    nav = MapNavigator(onboard, cfg, K, R_BC, LEVER_B)
    frame = render_map_frame(onboard, K, r_B + R_LB @ LEVER_B, R_LB @ R_BC, np.random.default_rng(0))
    fixes = [nav.on_frame(k * 10_000_000, frame, f) for k in range(4)]
    assert all(fx.ok for fx in fixes) and nav.stats.updates == 3
    assert all(fx.coarse_weight == (1.0 if coarse else 0.0) for fx in fixes)
    tau = cfg.coarse_common_time_s if coarse else cfg.common_time_s
    assert cfg.coarse_common_time_s != cfg.common_time_s
    assert phis[0] == 0.0
    np.testing.assert_allclose(phis[1:], math.exp(-0.01 / tau), rtol=1e-12)


def test_inflating_the_horizontal_position_scales_its_rows_and_columns():
    f = _filter(np.array([1.0, 2.0, 300.0]), [1.0, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(3)
    A = rng.normal(size=(f.P.shape[0], f.P.shape[0]))
    f.ekf.P = A @ A.T + np.eye(A.shape[0])  # a full covariance: every correlation in play
    P0, x0 = f.P, f.x
    f.inflate_horizontal_position(1.5)
    expected = P0.copy()
    horizontal = (0, 1, 10, 11)  # r_x, r_y and the position clone's x, y (the same prior error)
    for i in range(P0.shape[0]):  # explicit loop: those rows and columns times 1.5, their crossings 2.25
        for j in range(P0.shape[1]):
            expected[i, j] *= (1.5 if i in horizontal else 1.0) * (1.5 if j in horizontal else 1.0)
    np.testing.assert_allclose(f.P, expected, rtol=1e-15)
    assert np.array_equal(f.x, x0) and np.all(np.linalg.eigvalsh(f.P) > 0)
    # The displacement since the last frame keeps its variance, scaled: it does not take the position's.
    var_d = lambda P: P[0, 0] + P[10, 10] - 2 * P[0, 10]  # noqa: E731
    assert var_d(f.P) == pytest.approx(1.5**2 * var_d(P0), rel=1e-12)
    with pytest.raises(ValueError, match="factor"):
        f.inflate_horizontal_position(0.5)


def test_nav_map_switch_is_off_by_default_and_checked():
    s = load_scenario(None)
    assert s.nav_map == "off"
    assert build_flight_software(s, np.array([0.0, 0.0, 500.0]), np.zeros(3)).map_nav is None
    with pytest.raises(ScenarioError, match="nav_map = 'on' needs camera.enabled = true"):
        load_scenario(None, ["nav_map=on", "camera.enabled=false", "vision=off"])
    with pytest.raises(ScenarioError, match="onboard_map.size_m = 2000.0 is larger than the terrain"):
        load_scenario(None, ["nav_map=on", "onboard_map.size_m=2000.0"])
    with pytest.raises(ScenarioError, match="map_nav.period_ns = 150000000"):
        load_scenario(None, ["nav_map=on", "map_nav.period_ns=150000000"])
    # The regional relief the filter carries with map fixes must be smoother than the cleared site.
    with pytest.raises(ScenarioError, match="estimator.regional_relief_sigma_m / regional_relief_length_m = 0.05"):
        load_scenario(None, ["nav_map=on", "estimator.regional_relief_sigma_m=5.0"])
    load_scenario(None, ["estimator.regional_relief_sigma_m=5.0"])  # not read without map fixes
    # A re-lock needs two refused fixes that agree (0 turns it off).
    with pytest.raises(ScenarioError, match="map_nav.relock_after = 1: .* allowed: 0 \\(never\\) or 2 and more"):
        load_scenario(None, ["nav_map=on", "map_nav.relock_after=1"])
    assert load_scenario(None, ["nav_map=on", "map_nav.relock_after=0"]).map_nav.relock_after == 0


@pytest.mark.slow
def test_default_landing_with_map_navigation_lands_on_the_map_target():
    from bench.sim.run import run

    res = run(load_scenario(None, ["nav_map=on"]))
    m = res.summary["map_nav"]
    assert res.summary["outcome"] == "landed"
    assert m["false_locks"] == 0 and m["updates"] >= 10
    assert m["miss_vs_map_target_m"] < 3.0
    assert m["fix_err_max_m"] < 1.5
    # Below the last fix, frames registered to the keyframe hold the position to the touchdown
    # (0.07 m measured at touchdown on this run; 0.6-1.3 m without the keyframe, on IMU and altimeter).
    assert m["keyframe_t_s"] is not None and m["keyframe_updates"] >= 10 and m["keyframe_false_locks"] == 0
    assert m["nav_err_map_frame_touchdown_m"] < 0.5
    # Navigation errors are taken in the map frame: the same figure both ways.
    assert res.summary["nav"]["pos_err_touchdown_m"] < 3.0
    assert m["nav_err_map_frame_touchdown_m"] <= res.summary["nav"]["pos_err_touchdown_m"] + 1e-9
    # The error at 50 m: the first tick at or below 50 m truth height, found here with a plain loop.
    tel = res.telemetry
    k = next(i for i in range(len(tel["t_s"])) if tel["r_z_m"][i] <= 50.0)
    want = math.hypot(tel["nav_err_r_x_m"][k], tel["nav_err_r_y_m"][k])
    assert m["nav_err_map_frame_50m_m"] == pytest.approx(want, rel=1e-12)
    assert m["nav_err_map_frame_50m_xy_m"] == pytest.approx([tel["nav_err_r_x_m"][k], tel["nav_err_r_y_m"][k]])


def _filter_with_map_bias(r0, sigma_b):
    f = make_estimator(None, r0, np.zeros(3), 0, altimeter_mount_B_m=np.zeros(3), map_bias_sigma_m=sigma_b)
    f.set_attitude(AttitudeMessage(0, np.array([1.0, 0.0, 0.0, 0.0])))
    return f


def test_map_update_with_the_common_error_state_is_the_augmented_kalman_update():
    plain = _filter(np.array([10.0, -5.0, 300.0]), [1.0, 0.0, 0.0, 0.0])
    f = _filter_with_map_bias(np.array([10.0, -5.0, 300.0]), 0.7)
    assert not plain.has_map_bias and plain.x.size == 24  # the switch off: the filter is as it was
    assert f.has_map_bias and f.x.size == 27  # b_map (2) and a keyframe's height error (1)
    np.testing.assert_array_equal(f.P[:24, :24], plain.P)
    np.testing.assert_array_equal(f.P[24:, 24:], np.eye(3) * 0.7**2)
    assert not f.P[24:, :24].any() and not f.x[24:].any()
    # A correlated state first (as after other updates), then the map update against the textbook one:
    # z = r_xy + lever + b_map + w, H picking the horizontal position and the common error.
    rng = np.random.default_rng(2)
    A = rng.normal(size=(27, 27)) * 0.05
    f.ekf.P = f.P + A @ A.T
    f.ekf.x = f.x + rng.normal(size=27) * 0.1
    x0, P0 = f.x, f.P
    lever = np.array([0.4, -0.1])
    R = np.array([[0.05, 0.01], [0.01, 0.03]])
    z = x0[:2] + lever + x0[24:26] + np.array([0.8, -0.5])
    rec = f.update_map_position(0, z, R, lever)
    assert rec.accepted
    H = np.zeros((2, 27))
    H[:, 0:2] = np.eye(2)
    H[:, 24:26] = np.eye(2)
    S = H @ P0 @ H.T + R
    Kg = P0 @ H.T @ np.linalg.inv(S)
    y = z - (x0[:2] + lever + x0[24:26])
    np.testing.assert_allclose(f.x, x0 + Kg @ y, atol=1e-9)
    np.testing.assert_allclose(f.P, (np.eye(27) - Kg @ H) @ P0, atol=1e-8)
    assert rec.nis == pytest.approx(float(y @ np.linalg.solve(S, y)))


def test_map_bias_step_is_a_gauss_markov_step():
    f = _filter_with_map_bias(np.array([0.0, 0.0, 300.0]), 0.5)
    rng = np.random.default_rng(5)
    A = rng.normal(size=(27, 27)) * 0.1
    f.ekf.P = f.P + A @ A.T
    f.ekf.x = rng.normal(size=27)
    x0, P0 = f.x, f.P
    phi, sigma, scale = 0.8, 0.3, 0.6
    f.step_map_bias(phi, sigma, scale)
    a = phi * scale
    x1, P1 = x0.copy(), P0.copy()
    for i in (24, 25):  # explicit: b <- a b; its rows and columns times a; stationary noise sigma^2 (1 - phi^2)
        x1[i] *= a
    for i in range(27):
        for j in range(27):
            P1[i, j] *= (a if i in (24, 25) else 1.0) * (a if j in (24, 25) else 1.0)  # not the keyframe's height
    P1[24, 24] += sigma**2 * (1 - phi**2)
    P1[25, 25] += sigma**2 * (1 - phi**2)
    np.testing.assert_allclose(f.x, x1, rtol=1e-14)
    np.testing.assert_allclose(f.P, P1, rtol=1e-13)
    with pytest.raises(ValueError, match="no map bias"):
        _filter(np.zeros(3) + 300.0, [1.0, 0.0, 0.0, 0.0]).step_map_bias(phi, sigma)


def test_a_common_fix_error_is_not_averaged_down():
    # N fixes sharing one error b (phi = 1) and each its own w: they tell r + b to sigma_w^2 / N, so r's
    # variance cannot fall below what b leaves: sigma0^2 v / (sigma0^2 + v), v = sigma_b^2 + sigma_w^2 / N
    # (a Gaussian prior N(r0, sigma0^2) and the sufficient statistic, the mean fix). Taken as white noise of
    # variance sigma_b^2 + sigma_w^2 per fix, the same fixes would claim (sigma_b^2 + sigma_w^2) / N.
    sigma0, sigma_b, sigma_w, n = 20.0, 0.4, 0.2, 25
    f = _filter_with_map_bias(np.array([0.0, 0.0, 300.0]), 1.0)
    white = _filter(np.array([0.0, 0.0, 300.0]), [1.0, 0.0, 0.0, 0.0])
    f.step_map_bias(0.0, sigma_b)
    for k in range(n):
        f.step_map_bias(1.0, sigma_b)
        assert f.update_map_position(0, np.zeros(2), np.eye(2) * sigma_w**2, np.zeros(2)).accepted
        assert white.update_map_position(0, np.zeros(2), np.eye(2) * (sigma_b**2 + sigma_w**2), np.zeros(2)).accepted
    v = sigma_b**2 + sigma_w**2 / n
    assert f.P[0, 0] == pytest.approx(sigma0**2 * v / (sigma0**2 + v), rel=1e-9)
    assert f.P[1, 1] == pytest.approx(sigma0**2 * v / (sigma0**2 + v), rel=1e-9)
    vw = (sigma_b**2 + sigma_w**2) / n
    assert white.P[0, 0] == pytest.approx(sigma0**2 * vw / (sigma0**2 + vw), rel=1e-9)
    assert white.P[0, 0] < 0.25 * f.P[0, 0]  # the white model claims four times the information it has


@pytest.mark.parametrize("nav_map", ["off", "on"])
def test_computer_restart_keeps_the_terrain_states_and_the_regional_relief(onboard, nav_map):
    # A warm restart restores the kinematic, accelerometer-bias and terrain states from the checkpoint (carried
    # ballistically), with their covariance among themselves; with map fixes the regional relief is terrain too.
    from bench.sim.flight_build import restart_flight_software
    from gnc.estimator import DIM_REGIONAL, IDX_RR
    from gnc.fdir import restart_estimate

    sc = load_scenario(None, [f'nav_map="{nav_map}"'])
    old = build_flight_software(sc, np.array([5.0, -3.0, 400.0]), np.array([1.0, 0.0, -10.0]), 0,
                                onboard_map=onboard if nav_map == "on" else None)
    n = old.filter.dim_x
    assert n == (DIM_REGIONAL if nav_map == "on" else 24)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(n, n)) * 0.1
    P = A @ A.T + np.eye(n) * 0.01
    x = rng.normal(size=n)
    old.checkpoint = (0, x, P, 1500.0, np.array([1.0, 0.0, 0.0, 0.0]))
    new = restart_flight_software(sc, old, 2 * 10**9)
    keep = list(range(10)) + (list(range(IDX_RR, DIM_REGIONAL)) if nav_map == "on" else [])
    xr, Pr = restart_estimate(x, P, 2.0, sc.estimator.gravity_mps2)
    np.testing.assert_array_equal(new.filter.ekf.x[keep], xr[keep])
    np.testing.assert_array_equal(new.filter.ekf.P[np.ix_(keep, keep)], Pr[np.ix_(keep, keep)])
    rest = [i for i in range(n) if i not in keep]
    assert not new.filter.ekf.P[np.ix_(keep, rest)].any()
    if nav_map == "on":  # the map fixes' record and lock survive (a fresh record dropped them from the summary)
        assert new.map_nav.stats is old.map_nav.stats
