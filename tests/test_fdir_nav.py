"""Issue 13's navigation-consistency detections (gnc/fdir.py, gnc/flight.py), each against an independent construction.

* the lateral accelerometer bias check: a filter bias far from the accelerometer's own mean lateral specific
  force must be detected and re-initialised to it; a consistent one must not;
* the noisy altimeter's line fit: slope, intercept and their statistics against the normal equations summed in
  a loop; a self-consistent fit that the gate refuses re-initialises the vertical channel (a filter made
  confidently wrong about its vertical velocity is brought back to the truth), and a right filter is left alone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gnc.control import Controller, VehicleParams
from gnc.estimator import IDX_BA, IDX_H, make_estimator
from gnc.fdir import FdirConfig, HealthMonitor, SensorSpec, line_fit
from gnc.flight import FlightSoftware, OnboardKnowledge
from gnc.guidance import make_guidance
from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage
from gnc.vision_nav import VisionNavConfig

NS = 1_000_000_000
IMU_NS, ALT_NS, TICK_NS = 10_000_000, 50_000_000, 20_000_000
SPEC = SensorSpec(imu_period_ns=IMU_NS, altimeter_period_ns=ALT_NS, star_tracker_period_ns=100_000_000,
                  camera_period_ns=100_000_000, altimeter_max_range_m=3000.0)
DOWN = np.array([0.0, 0.0, -1.0])
G = 1.62


def _fly_lateral(m: HealthMonitor, bias_xy, b_hat_xy, var_xy, seconds: float, rng) -> list:
    """Thrusting at 2 m/s^2 along +z, the accelerometer reading its bias laterally (plus white noise)."""
    out = []
    t = 0
    m.start(0)
    while t < seconds * NS:
        if t % TICK_NS == 0:
            m.control_tick(t, 4000.0, 1.0, 2000.0, False)
            out.append(m.bias_check(t, b_hat_xy, var_xy, 1e-3, 0.007))
        f = np.array([bias_xy[0], bias_xy[1], 2.0]) + rng.normal(0.0, 1e-3 / math.sqrt(IMU_NS / NS), 3)
        m.imu(ImuMessage(t + IMU_NS, f, rng.normal(0.0, 1e-5, 3)))
        t += IMU_NS
    return out


def test_lateral_bias_check_detects_a_wrong_filter_bias_and_gives_the_measured_one():
    rng = np.random.default_rng(3)
    bias = (0.004, -0.003)
    m = HealthMonitor(FdirConfig(), SPEC)
    out = _fly_lateral(m, bias, (-0.025, 0.005), (1e-6, 1e-6), 3.0, rng)
    fired = [(k, r) for k, r in enumerate(out) if r is not None]
    assert fired, "a bias estimate 0.029 m/s^2 off the accelerometer's lateral reading went unnoticed"
    k, (fx, fy, var) = fired[0]
    # A full 1 s window, then half a window of ticks in a row beyond the gate.
    assert 1.3 <= k * TICK_NS / NS <= 1.8
    # The mean of 100 samples of 0.01 m/s^2 white noise: 1-sigma 1e-3 about the bias (the estimate was 0.029 off).
    assert fx == pytest.approx(bias[0], abs=4e-3) and fy == pytest.approx(bias[1], abs=4e-3)
    c = FdirConfig()
    assert var == pytest.approx(c.bias_check_model_mps2**2 + (math.radians(c.engine_alignment_deg) / math.sqrt(6.0) * 2.0) ** 2
                                + 1e-6 / 1.0, rel=0.05)
    ev = [e for e in m.events if "accelerometer bias estimate" in e.reason]
    assert len(ev) == 1 and ev[0].subsystem == "navigation"


def test_lateral_bias_check_is_quiet_for_a_consistent_filter_and_for_a_real_lateral_force():
    rng = np.random.default_rng(4)
    bias = (0.004, -0.003)
    m = HealthMonitor(FdirConfig(), SPEC)
    # The filter's estimate within its own 1-sigma of the truth: no detection over 10 s.
    assert all(r is None for r in _fly_lateral(m, bias, (0.006, -0.001), (2e-3**2, 2e-3**2), 10.0, rng))
    assert not any(e.subsystem == "navigation" for e in m.events)
    # A large but true bias (beyond 3 sigma of the specification), which the accelerometer reads: no detection.
    m = HealthMonitor(FdirConfig(), SPEC)
    assert all(r is None for r in _fly_lateral(m, (0.025, 0.0), (0.024, 0.0), (1e-6, 1e-6), 5.0, rng))
    # A plausible estimate that the accelerometer does not read (a misaligned thrust's lateral force): none.
    m = HealthMonitor(FdirConfig(), SPEC)
    assert all(r is None for r in _fly_lateral(m, (0.1, 0.0), (0.0, 0.0), (1e-6, 1e-6), 5.0, rng))
    assert not any("bias estimate" in e.reason for e in m.events)


def test_line_fit_against_the_normal_equations():
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(-3.0, 0.0, 57))
    d = 0.7 - 0.21 * t + rng.normal(0.0, 0.4, t.size)
    n = st = sd = stt = std = 0.0
    for ti, di in zip(t, d):  # the 2x2 normal equations, summed explicitly
        n += 1
        st += ti
        sd += di
        stt += ti * ti
        std += ti * di
    det = n * stt - st * st
    slope = (n * std - st * sd) / det
    icpt = (stt * sd - st * std) / det
    rss = sum((di - slope * ti - icpt) ** 2 for ti, di in zip(t, d))
    s2 = rss / (n - 2)
    got = line_fit(t, d)
    assert got[0] == pytest.approx(slope, rel=1e-12) and got[1] == pytest.approx(icpt, rel=1e-12)
    assert got[3] == pytest.approx(s2, rel=1e-12)
    assert got[2] == pytest.approx(s2 * n / det, rel=1e-12)  # the slope's variance: s2 (X^T X)^-1 [1, 1]


def _knowledge() -> OnboardKnowledge:
    K = np.array([[221.7, 0.0, 127.5], [0.0, 221.7, 127.5], [0.0, 0.0, 1.0]])
    return OnboardKnowledge(vehicle=VehicleParams(), wet_mass_kg=2100.0, isp_s=310.0, K=K,
                            R_BC=np.diag([1.0, -1.0, -1.0]), r_cam_B_m=np.array([0.0, 0.0, -0.77]),
                            r_alt_B_m=np.array([0.0, 0.0, -0.77]))


def _noisy_altimeter_descent(v_err_mps: float, seed: int) -> tuple[FlightSoftware, float, float]:
    """A 6 s descent at -1 m/s from 30 m (truth), the filter started with ``v_err_mps`` of vertical-velocity error
    and a vertical covariance that does not admit it; the altimeter 5x noisier than its specification, which
    the health monitor has already detected (ranges fitted 50 at a time). Returns (the flight software, the
    true height of the altimeter at the end, the true vertical velocity)."""
    k = _knowledge()
    controller = Controller(None, k.vehicle)
    guidance = make_guidance(None, controller.guidance_limits())
    z0, v_true = 30.0, -1.0
    nav = make_estimator(None, [0.0, 0.0, z0], [0.0, 0.0, v_true + v_err_mps], 0, q0_LB=[1, 0, 0, 0],
                         altimeter_mount_B_m=k.r_alt_B_m)
    P = nav.ekf.P
    P[2, 2], P[5, 5] = 0.05**2, 0.01**2  # confident
    for i in range(2, 24):
        if i not in (2, 5):
            P[2, i] = P[i, 2] = P[5, i] = P[i, 5] = 0.0
    P[IDX_BA, IDX_BA] = np.eye(3) * 1e-3**2
    fd = HealthMonitor(FdirConfig(), SPEC)
    fsw = FlightSoftware(guidance, controller, nav, None, VisionNavConfig(), False, k, fdir=fd)
    fd.alt_average_n, fd.alt_noise_factor = 50, 5.0
    fsw._discounted = True  # the detection's one-off discount is not what is tested here
    rng = np.random.default_rng(seed)
    t = 0
    fsw.on_attitude(AttitudeMessage(0, np.array([1.0, 0.0, 0.0, 0.0])))
    while t < 6 * NS:
        t += IMU_NS
        fsw.on_imu(ImuMessage(t, np.array([0.0, 0.0, G]) + rng.normal(0.0, 1e-3, 3), rng.normal(0.0, 1e-5, 3)))
        if t % ALT_NS == 0:
            h = z0 + v_true * t / NS - 0.77
            sigma = nav.altimeter_sigma_m(h, include_relief=False)
            fsw.on_altimeter(AltimeterMessage(t, h + rng.normal(0.0, 5.0 * sigma), True, DOWN))
    return fsw, z0 + v_true * t / NS, v_true


def test_noisy_altimeter_fit_reinitialises_a_confidently_wrong_vertical_channel():
    fsw, z_true, v_true = _noisy_altimeter_descent(0.5, seed=6)
    x = fsw.filter.ekf.x
    reasons = [e.reason for e in fsw.fdir.events]
    assert any("self-consistent altimeter fit" in r for r in reasons), reasons
    # Dead reckoning alone would end 3 m high at 0.5 m/s too slow a descent.
    assert abs(x[5] - v_true) < 0.1 and abs(x[2] - x[IDX_H] - z_true) < 0.5  # the height above its ground
    assert "altimeter" not in fsw.fdir.failed


def test_noisy_altimeter_fit_leaves_a_right_filter_alone():
    fsw, z_true, v_true = _noisy_altimeter_descent(0.0, seed=7)
    x = fsw.filter.ekf.x
    assert not any("self-consistent altimeter fit" in e.reason for e in fsw.fdir.events)
    assert abs(x[5] - v_true) < 0.05 and abs(x[2] - x[IDX_H] - z_true) < 0.3
