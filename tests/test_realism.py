"""Issue 17, realism: each realistic model against an independent computation, and the ideal switch."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.scenario import ScenarioError, load_scenario
from bench.sim.run import OUTCOMES, run
from models.actuators import G0_MPS2, PropulsionModel
from models.camera import CameraConfig
from models.lander import (EngineConfig, LanderConfig, RcsConfig, com_position_B, footpad_positions_B,
                           static_tipover_deg, support_margin_m)
from models.sensors import StarTrackerConfig, StarTrackerModel
from models.world import SunConfig, World
from tests.conftest import SMALL_SET

SNAPSHOT = Path(__file__).parent / "snapshots" / "ideal_vehicle_before_realism.npz"
QUIET = ['nav="truth"', 'vision="off"', "camera.enabled=false", *SMALL_SET]
DT_NS = 2_000_000
DT_S = DT_NS / 1e9
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


# --------------------------------------------------------------------------- the switch
def test_ideal_realism_flies_exactly_as_before_issue_17():
    # The telemetry of this short flight (every 10th control tick of 6 s) was written by the code at
    # f2dac0d, main just before realism was merged. realism = "ideal" must reproduce it: measured bit for bit
    # on the machine that wrote it; the tolerance only allows another CPU's last-bit rounding, far below
    # what any realistic model changes (engine lag alone moves the thrust by tens of newtons).
    sets = [*QUIET, "seed=11", "initial.r_BL_L_m=[8.0, 6.0, 20.0]", "initial.v_BL_L_mps=[0.5, 0.0, -1.0]",
            "initial.euler_LB_deg=[2.0, -1.0, 3.0]", "sim.t_max_ns=6000000000", 'realism="ideal"']
    tel = run(load_scenario(None, sets)).telemetry
    ref = np.load(SNAPSHOT)
    assert len(ref.files) > 60
    for name in ref.files:
        np.testing.assert_allclose(tel[name][::10], ref[name], rtol=1e-9, atol=1e-9, err_msg=name)
    real = run(load_scenario(None, [*sets[:-1], 'realism="realistic"', "lander.propellant_kg=600"])).telemetry
    assert np.max(np.abs(real["thrust_N"][::10] - ref["thrust_N"])) > 1.0  # the test can fail


# --------------------------------------------------------------------------- engine
def _engine(**engine) -> PropulsionModel:
    return PropulsionModel(LanderConfig(engine=EngineConfig(**engine), rcs=RcsConfig(mode="continuous",
                                                                                      draws_propellant=False)))


def test_throttle_step_response_is_the_first_order_solution():
    tau, t0, t1 = 0.1, 2000.0, 6000.0
    p = _engine(time_constant_s=tau, slew_rate_Nps=math.inf)
    assert not p.instant
    assert p.physics_step(t0, np.zeros(3), 0, DT_NS)[0] == t0  # burning at the first command
    thrust = np.array([p.physics_step(t1, np.zeros(3), k, DT_NS)[0] for k in range(1, 301)])
    t = np.arange(1, 301) * DT_S
    np.testing.assert_allclose(thrust, t1 + (t0 - t1) * np.exp(-t / tau), rtol=1e-12)
    assert abs(thrust[int(tau / DT_S) - 1] - (t1 + (t0 - t1) / math.e)) < 1e-9  # 63 % at one time constant


def test_throttle_slew_limit_ramps_at_the_rate_then_holds():
    rate, t0, t1 = 20000.0, 2000.0, 6000.0
    p = _engine(time_constant_s=0.0, slew_rate_Nps=rate)
    p.physics_step(t0, np.zeros(3), 0, DT_NS)
    thrust = np.array([p.physics_step(t1, np.zeros(3), k, DT_NS)[0] for k in range(1, 151)])
    t = np.arange(1, 151) * DT_S
    np.testing.assert_allclose(thrust, np.minimum(t0 + rate * t, t1), rtol=1e-12)
    # Down through the minimum thrust to off (the engine cut): the same rate.
    down = [p.physics_step(0.0, np.zeros(3), k, DT_NS)[0] for k in range(151, 161)]
    np.testing.assert_allclose(down, t1 - rate * DT_S * np.arange(1, 11), rtol=1e-12)


def test_misalignment_and_com_offset_torque_is_r_cross_f(flat_terrain):
    cfg = LanderConfig(engine=EngineConfig(misalignment_deg=0.5, misalignment_azimuth_deg=30.0),
                       com_offset_B_m=(0.02, -0.01, 0.03), propellant_kg=400.0)
    world = World(flat_terrain, cfg, CameraConfig(width_px=64, height_px=64), SunConfig(), DT_NS, 1.62,
                  realism="realistic")
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.zeros(3))
    thrust = 5000.0
    world.data.ctrl[world.model.actuator("engine").id] = thrust
    import mujoco

    mujoco.mj_forward(world.model, world.data)
    alpha_B = world.data.qacc[3:6].copy()
    # Independent: force along the tilted axis at the engine mount, moment about the total centre of mass.
    a, az = math.radians(0.5), math.radians(30.0)
    F_B = thrust * np.array([math.sin(a) * math.cos(az), math.sin(a) * math.sin(az), math.cos(a)])
    m_dry, m_tank = cfg.dry_mass_kg, cfg.propellant_kg
    c_dry, c_tank = np.array(cfg.com_offset_B_m), np.zeros(3)
    com = (m_dry * c_dry + m_tank * c_tank) / (m_dry + m_tank)
    np.testing.assert_allclose(com_position_B(cfg, m_tank), com, rtol=1e-12)
    r_engine = np.array([0.0, 0.0, -cfg.body_half_extents_m[2]])
    torque = np.cross(r_engine - com, F_B)
    hx, hy, hz = (2 * h for h in cfg.body_half_extents_m)
    I_dry = np.diag([m_dry * (hy**2 + hz**2), m_dry * (hx**2 + hz**2), m_dry * (hx**2 + hy**2)]) / 12.0
    I_tank = np.eye(3) * 0.4 * m_tank * cfg.tank_radius_m**2

    def shifted(m, d):  # parallel axis
        return m * (d @ d * np.eye(3) - np.outer(d, d))

    inertia = I_dry + shifted(m_dry, c_dry - com) + I_tank + shifted(m_tank, c_tank - com)
    np.testing.assert_allclose(alpha_B, np.linalg.solve(inertia, torque), rtol=1e-6, atol=1e-12)
    assert np.linalg.norm(torque) > 50.0  # a real disturbance: a quarter of the RCS authority
    world.close()


# --------------------------------------------------------------------------- RCS
def _rcs(mode="pwm", draws=False, **kw) -> PropulsionModel:
    return PropulsionModel(LanderConfig(rcs=RcsConfig(mode=mode, draws_propellant=draws, **kw),
                                        engine=EngineConfig(time_constant_s=0.0, slew_rate_Nps=math.inf)))


def test_pwm_average_torque_and_minimum_impulse_bit():
    period_ns, min_on_ns, tau_max = 20_000_000, 4_000_000, 200.0
    steps, period_s = period_ns // DT_NS, period_ns / 1e9
    mib = tau_max * min_on_ns / 1e9  # [N m s]
    # One window: a command of at least the minimum impulse fires exactly its impulse, in full-torque
    # pulses with at most one partial step per axis; a smaller one fires nothing (yet).
    for cmd in ([37.0, -150.0, 5.0], [41.0, 199.9, -60.3], [-200.0, 0.0, 123.4]):
        p = _rcs(pwm_period_ns=period_ns, min_on_ns=min_on_ns)
        cmd = np.array(cmd)
        window = np.array([p.physics_step(0.0, cmd, k, DT_NS)[1] for k in range(3 * steps, 4 * steps)])
        impulse = window.sum(axis=0) * DT_S
        fired = np.abs(cmd) * period_s >= mib
        np.testing.assert_allclose(impulse[fired], cmd[fired] * period_s, rtol=1e-12)
        assert np.all(impulse[~fired] == 0.0)
        partial = (np.abs(window) > 0) & (np.abs(window) < tau_max)
        assert np.all(partial.sum(axis=0) <= 1)
    # Many windows: every pulse is at least the minimum impulse bit, and the average torque is the
    # commanded one, below the minimum impulse too (an explicit loop over windows as the reference).
    cmd = np.array([12.5, -31.0, 70.0])  # 0.25, 0.62 and 1.4 minimum impulse bits per window
    p = _rcs(pwm_period_ns=period_ns, min_on_ns=min_on_ns)
    n_windows = 200
    torque = np.array([p.physics_step(0.0, cmd, k, DT_NS)[1] for k in range(n_windows * steps)])
    per_window = torque.reshape(n_windows, steps, 3).sum(axis=1) * DT_S
    pulses = per_window[per_window != 0.0]
    assert pulses.size > 0 and np.all(np.abs(pulses) >= mib - 1e-12)
    assert np.count_nonzero(per_window[:, 0]) == n_windows // 4  # one minimum pulse every 4th window
    np.testing.assert_allclose(torque.mean(axis=0), cmd, rtol=0, atol=mib / (n_windows * period_s) + 1e-9)
    # Continuous mode: the saturated command, every step.
    p = _rcs(mode="continuous")
    np.testing.assert_array_equal(p.physics_step(0.0, np.array([37.0, -500.0, 5.0]), 3, DT_NS)[1], [37.0, -200.0, 5.0])


def test_rcs_propellant_is_torque_over_arm_over_isp_g0():
    p = _rcs(mode="continuous", draws=True, moment_arm_m=1.2, isp_s=220.0)
    p0 = p.propellant_kg
    cmd = np.array([50.0, -80.0, 20.0])
    for k in range(500):
        p.physics_step(0.0, cmd, k, DT_NS)
    expected = 150.0 / 1.2 / (220.0 * G0_MPS2) * 500 * DT_S
    # Each step subtracts ~1e-4 kg from ~600 kg (ulp 1.1e-13): 500 roundings, at most 3e-11 kg, 1e-9 of the draw.
    assert p0 - p.propellant_kg == pytest.approx(expected, rel=1e-9)


# --------------------------------------------------------------------------- flight computer latency
@pytest.mark.parametrize("latency", [0, 1, 2])
def test_latency_delays_the_applied_command_by_whole_ticks(latency):
    sc = load_scenario(None, [*QUIET, 'realism="realistic"', f"sim.compute_latency_ticks={latency}",
                              "initial.r_BL_L_m=[5.0, 3.0, 60.0]", "initial.v_BL_L_mps=[0.5, 0.0, -3.0]",
                              "sim.t_max_ns=1500000000"])
    tel = run(sc).telemetry
    cmd, applied = tel["thrust_cmd_N"], tel["thrust_applied_cmd_N"]
    assert np.ptp(cmd) > 1.0  # the command moves, so a shift shows
    np.testing.assert_array_equal(applied[latency:], cmd[:len(cmd) - latency])
    np.testing.assert_array_equal(applied[:latency], cmd[0])
    for a in "xyz":
        tq, tq_applied = tel[f"torque_{a}_Nm"], tel[f"torque_applied_{a}_Nm"]
        np.testing.assert_array_equal(tq_applied[latency:], tq[:len(tq) - latency])


# --------------------------------------------------------------------------- star tracker
def test_star_tracker_error_covariance_follows_its_axes():
    cfg = StarTrackerConfig(cross_boresight_sigma_arcsec=3.0, about_boresight_sigma_arcsec=20.0,
                            boresight_B=(0.0, 0.6, 0.8))
    st = StarTrackerModel(cfg, np.random.default_rng(9), anisotropic=True)
    from scipy.spatial.transform import Rotation

    q_true = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    errs = np.array([(q_true.inv() * Rotation.from_quat(st.sample(0, q_true.as_quat(scalar_first=True)).q_LB,
                                                        scalar_first=True)).as_rotvec() for _ in range(8000)])
    # Independent axes: the boresight, body x (perpendicular to it) and their cross product.
    b = np.array([0.0, 0.6, 0.8])
    u1 = np.array([1.0, 0.0, 0.0])
    u2 = np.cross(b, u1)
    arcsec = math.radians(1 / 3600)
    C = np.cov(errs @ np.column_stack([u1, u2, b]), rowvar=False) / arcsec**2
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [3.0, 3.0, 20.0], rtol=0.04)
    corr = C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
    assert np.all(np.abs(corr[np.triu_indices(3, 1)]) < 0.045)
    np.testing.assert_allclose(np.cov(errs, rowvar=False), cfg.error_covariance_B(), rtol=0.06,
                               atol=0.03 * (20 * arcsec) ** 2)


def test_filter_attitude_noise_is_the_worst_axis_of_the_tracker_specification():
    # The flight software knows the specification (the top of each dispersed range), never a case's draw;
    # its isotropic attitude sigma must cover the worst (about-boresight) axis.
    sc = load_scenario()
    st, spec = sc.sensors.star_tracker, sc.estimator.attitude_sigma_arcsec
    for path in ("sensors.star_tracker.cross_boresight_sigma_arcsec", "sensors.star_tracker.about_boresight_sigma_arcsec"):
        assert sc.dispersions[path].high <= spec, path
    assert max(st.cross_boresight_sigma_arcsec, st.about_boresight_sigma_arcsec) <= spec
    assert st.about_boresight_sigma_arcsec >= 5 * st.cross_boresight_sigma_arcsec  # real trackers: 5-8x worse


# --------------------------------------------------------------------------- propellant budget
def test_propellant_budget_is_nominal_need_plus_a_60_s_hover_at_landing_mass():
    sc = load_scenario(None, ['realism="realistic"'])
    lander, budget = sc.lander, sc.propellant
    reserve = lander.propellant_kg - budget.nominal_need_kg
    landing_mass = lander.dry_mass_kg + reserve
    hover_flow = landing_mass * sc.sim.gravity_mps2 / (lander.engine.isp_s * G0_MPS2)
    assert reserve == pytest.approx(budget.reserve_hover_s * hover_flow, rel=1e-12)
    assert budget.reserve_hover_s == 60.0 and 40.0 < reserve < 60.0
    # An explicit load wins; the ideal vehicle keeps its 600 kg; the default (realistic) vehicle flies the budget.
    assert load_scenario(None, ['realism="realistic"', "lander.propellant_kg=300"]).lander.propellant_kg == 300.0
    assert load_scenario(None, ['realism="ideal"']).lander.propellant_kg == 600.0
    assert load_scenario().lander.propellant_kg == lander.propellant_kg
    with pytest.raises(ScenarioError, match="reserve_hover_s"):
        load_scenario(None, ['realism="realistic"', "propellant.reserve_hover_s=5000"])


def test_hover_longer_than_the_reserve_ends_in_fuel_exhausted():
    # Loaded with the reserve alone, the lander hovers (descending at 1 cm/s from 15 m) until the tanks
    # run dry. A hover at decreasing mass lasts t = Isp g0 / g ln(m0 / m_dry) (Tsiolkovsky), a little
    # over the 60 s the reserve is sized for at landing mass.
    base = load_scenario(None, ['realism="realistic"'])
    reserve = base.lander.propellant_kg - base.propellant.nominal_need_kg
    sc = load_scenario(None, [*QUIET, 'realism="realistic"', f"lander.propellant_kg={reserve}",
                              "initial.r_BL_L_m=[0.0, 0.0, 15.0]", "initial.v_BL_L_mps=[0.0, 0.0, 0.0]",
                              "guidance.terminal_descent_rate_mps=0.01", "sim.t_max_ns=120000000000"])
    s = run(sc).summary
    assert s["outcome"] == "fuel_exhausted" and not s["landed"], s["outcome"]
    lander, g = sc.lander, sc.sim.gravity_mps2
    t_hover = lander.engine.isp_s * G0_MPS2 / g * math.log((lander.dry_mass_kg + reserve) / lander.dry_mass_kg)
    assert 60.0 < t_hover < 62.0
    # The RCS and the control's transients burn a little too: exhausted within 3 % before the ideal hover.
    assert 0.97 * t_hover < s["fuel_exhausted_t_s"] <= t_hover + 0.05, (s["fuel_exhausted_t_s"], t_hover)


# --------------------------------------------------------------------------- outcomes
def test_static_tipover_angle_of_the_default_legs():
    cfg = LanderConfig()
    assert static_tipover_deg(cfg, 0.0) == pytest.approx(math.degrees(math.atan((2.2 / math.sqrt(2)) / 2.1)))
    assert 36.0 < static_tipover_deg(cfg, 0.0) < 37.0
    # A centre of mass off the axis: the nearer edge sets the angle; outside the footpad square it is negative
    # (before, the distance's absolute value gave a positive angle to a lander that cannot stand level).
    half = 2.2 / math.sqrt(2.0)  # the footpad square's half side [m]
    for x_m, d_m in ((0.5, half - 0.5), (1.9, half - 1.9), (-3.0, half - 3.0)):
        off = LanderConfig(com_offset_B_m=(x_m, 0.0, 0.0))
        h_m = com_position_B(off, 0.0)[2] + off.leg_drop_m + off.footpad_radius_m
        assert static_tipover_deg(off, 0.0) == pytest.approx(math.degrees(math.atan2(d_m, h_m))), x_m
    assert static_tipover_deg(LanderConfig(com_offset_B_m=(1.9, 0.0, 0.0)), 0.0) < 0.0
    feet = footpad_positions_B(cfg)[:, :2]
    assert support_margin_m(feet, np.zeros(2)) == pytest.approx(2.2 / math.sqrt(2))
    assert support_margin_m(feet, np.array([2.0, 0.0])) == pytest.approx(2.2 / math.sqrt(2) - 2.0)
    assert "slope_exceeded" in OUTCOMES and "tipped_over" in OUTCOMES


def _slope_dem(tmp_path, slope_deg: float) -> list[str]:
    spacing, n = 4.0, 65
    x = (np.arange(n) - (n - 1) / 2) * spacing
    np.save(tmp_path / "slope.npy", np.tile(math.tan(math.radians(slope_deg)) * x, (n, 1)))
    return ['terrain.kind="dem"', f'terrain.dem_path="{tmp_path / "slope.npy"}"', f"terrain.dem_spacing_m={spacing}",
            "terrain.geometry_px=65", "terrain.texture_px=1024", "terrain.roughness_rms_m=0.0",
            "terrain.crater_density_per_km2=0.0", "terrain.boulder_density_per_km2=0.0"]


def test_upright_on_a_slope_beyond_the_tilt_limit_is_slope_exceeded(tmp_path):
    sc = load_scenario(None, ['nav="truth"', 'vision="off"', "camera.enabled=false", *_slope_dem(tmp_path, 15.0),
                              "initial.r_BL_L_m=[0.0, 0.0, 8.0]", "initial.v_BL_L_mps=[0.0, 0.0, -0.8]"])
    s = run(sc).summary
    assert s["outcome"] == "slope_exceeded", (s["outcome"], s["final_tilt_deg"], s["stability"])
    assert 13.0 < s["final_tilt_deg"] < 17.0 and s["stability"]["support_margin_m"] > 0.5
    assert s["touchdown"]["tilt_deg"] < sc.landing.tilt_max_deg  # it came down upright: not a hard landing


def test_falling_over_is_tipped_over_even_within_a_loose_tilt_limit():
    # Dropped from 4 m at 50 deg with the tilt limit at 80 deg: a slope limit that loose would call it
    # landed; the lander falls over (beyond its static tip-over angle), so it is tipped_over.
    sc = load_scenario(None, [*QUIET, 'guidance.law="off"', "initial.r_BL_L_m=[0.0, 0.0, 4.0]",
                              "initial.v_BL_L_mps=[0.0, 0.0, 0.0]", "initial.euler_LB_deg=[50.0, 0.0, 0.0]",
                              "landing.tilt_max_deg=80", "landing.v_vertical_max_mps=5",
                              "landing.v_horizontal_max_mps=5"])
    s = run(sc).summary
    assert s["outcome"] == "tipped_over", s
    assert s["final_tilt_deg"] > s["stability"]["static_tipover_deg"] or s["stability"]["support_margin_m"] < 0.0


def test_integrating_gyro_reports_the_rotation_the_simulator_made(flat_terrain):
    # Under PWM torque pulses the body rate changes every physics step. The realistic gyro reports the
    # interval's delta-angle as a mean rate: held over the interval it gives the truth rotation (to the
    # coning of a rotation this small), where the trapezoid of point-sampled rates is off.
    from scipy.spatial.transform import Rotation
    cfg = LanderConfig(com_offset_B_m=(0.03, -0.02, 0.0))
    world = World(flat_terrain, cfg, CameraConfig(width_px=64, height_px=64), SunConfig(), DT_NS, 1.62,
                  realism="realistic")
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.array([0.01, -0.02, 0.005]))
    torque = np.array([150.0, -70.0, 40.0])
    world.step(5, 5000.0, torque)
    world.imu_mean_B()  # start a fresh interval
    q0, w0 = world.truth().q_LB, world.angular_rate_B()
    world.step(5, 5000.0, torque)
    _, omega_mean = world.imu_mean_B()
    q1, w1 = world.truth().q_LB, world.angular_rate_B()
    turn = (Rotation.from_quat(q0, scalar_first=True).inv() * Rotation.from_quat(q1, scalar_first=True)).as_rotvec()
    np.testing.assert_allclose(omega_mean * 5 * DT_S, turn, rtol=0, atol=1e-4 * np.linalg.norm(turn))
    trapezoid = 0.5 * (w0 + w1) * 5 * DT_S
    assert np.linalg.norm(trapezoid - turn) > 10 * np.linalg.norm(omega_mean * 5 * DT_S - turn)


def test_integrating_accelerometer_reports_the_interval_delta_v(flat_terrain):
    # With PWM pulses and a centre-of-mass offset the specific force at the IMU (the body origin) jumps
    # with every pulse (alpha x r); the realistic accelerometer reports its mean over the interval,
    # which is the interval's delta-velocity (MuJoCo's own integration) over its duration.
    cfg = LanderConfig(com_offset_B_m=(0.03, -0.02, 0.0))
    world = World(flat_terrain, cfg, CameraConfig(width_px=64, height_px=64), SunConfig(), DT_NS, 1.62,
                  realism="realistic")
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.zeros(3))
    world.step(5, 5000.0, np.array([150.0, -70.0, 0.0]))
    world.imu_mean_B()  # start a fresh interval
    v0 = world.truth().v_BL_L
    world.step(5, 5000.0, np.array([150.0, -70.0, 0.0]))
    mean, _ = world.imu_mean_B()
    dv_dt = (world.truth().v_BL_L - v0) / (5 * DT_S) - np.array([0.0, 0.0, -1.62])
    # The attitude turns by ~1e-5 rad over the interval: the body-frame mean equals the L-frame one to that.
    np.testing.assert_allclose(mean, dv_dt, rtol=0, atol=1e-4 * np.linalg.norm(dv_dt))
    assert world.imu_mean_B() is None  # read once per interval
    point = world.specific_force_B()
    assert abs(point[2] - mean[2]) > 1e-3  # a point sample sees the pulse phase (alpha x r along z)
    world.close()


def test_campaign_reports_count_every_run_outcome_in_order():
    from bench.report.mc_report import OUTCOMES as REPORT_OUTCOMES
    from bench.report.mc_report import outcome_counts

    assert set(OUTCOMES) <= set(REPORT_OUTCOMES)  # none falls into "other"
    rows = [{"outcome": o, "landed": o == "landed"} for o in ("slope_exceeded", "landed", "tipped_over", "landed")]
    assert list(outcome_counts(rows).items()) == [("landed", 2), ("tipped_over", 1), ("slope_exceeded", 1)]
