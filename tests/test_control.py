"""Controller: actuator limits under any input, thrust vectoring, attitude loop on a rigid body, touchdown cut."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gnc.control import (
    ActuatorCommand,
    ContactMessage,
    ControlConfig,
    Controller,
    VehicleParams,
    attitude_command_LB,
    attitude_torque_B,
    make_controller,
    thrust_vector_command,
)
from gnc.guidance import (
    PHASE_APPROACH,
    PHASE_TERMINAL,
    GuidanceCommand,
    GuidanceConfig,
    LandingTarget,
    TiltLimitConfig,
    make_guidance,
)
from gnc.navstate import NavState

G_L = np.array([0.0, 0.0, -1.62])
NS_PER_S = 1_000_000_000
CONTROL_DT_S = 0.02
Q_UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])
E_Z = np.array([0.0, 0.0, 1.0])


def nav(r=(0.0, 0.0, 200.0), v=(0.0, 0.0, -5.0), q=Q_UPRIGHT, omega=(0.0, 0.0, 0.0), mass=2000.0, t_s=0.0) -> NavState:
    return NavState(int(round(t_s * NS_PER_S)), np.asarray(r, float), np.asarray(v, float), np.asarray(q, float),
                    np.asarray(omega, float), float(mass))


def gcmd(a_L, valid=True, t_s=0.0) -> GuidanceCommand:
    return GuidanceCommand(int(round(t_s * NS_PER_S)), np.asarray(a_L, float), PHASE_APPROACH, 10.0, valid=valid)


def body_z_L(q) -> np.ndarray:
    return Rotation.from_quat(q, scalar_first=True).apply(E_Z)


def assert_within_limits(act: ActuatorCommand, veh: VehicleParams) -> None:
    assert np.isfinite(act.thrust_N) and np.all(np.isfinite(act.torque_B_Nm)) and np.all(np.isfinite(act.q_LB_cmd))
    assert np.all(np.abs(act.torque_B_Nm) <= veh.rcs_torque_max_Nm)
    if act.engine_on:
        assert veh.thrust_min_N <= act.thrust_N <= veh.thrust_max_N
    else:
        assert act.thrust_N == 0.0
    assert np.linalg.norm(act.q_LB_cmd) == pytest.approx(1.0)


# --------------------------------------------------------------------------- safety under any input
def _maybe_bad(rng, x, p=0.15):
    x = np.array(x, float)
    if rng.random() < p:
        x.flat[rng.integers(x.size)] = rng.choice([np.nan, np.inf, -np.inf, 1e300, -1e300])
    return x


def test_no_limit_violation_for_random_and_non_finite_inputs():
    rng = np.random.default_rng(11)
    veh = VehicleParams()
    ctl = Controller()
    for k in range(1500):
        if k % 300 == 0:
            ctl.reset()
        q = _maybe_bad(rng, Rotation.random(random_state=rng).as_quat(scalar_first=True) * rng.uniform(0.5, 2.0))
        n = nav(
            r=_maybe_bad(rng, [rng.uniform(-500, 500), rng.uniform(-500, 500), rng.uniform(-10, 1000)]),
            v=_maybe_bad(rng, rng.uniform(-50, 50, 3)),
            q=q,
            omega=_maybe_bad(rng, rng.uniform(-3, 3, 3)),
            mass=float(_maybe_bad(rng, [rng.uniform(-100, 3000)])[0]),
            t_s=k * CONTROL_DT_S,
        )
        c = gcmd(_maybe_bad(rng, rng.uniform(-30, 30, 3)), valid=bool(rng.random() > 0.1), t_s=k * CONTROL_DT_S)
        contact = ContactMessage(n.t_ns, rng.random(4) < 0.02) if rng.random() < 0.5 else None
        act = ctl.update(n, c, contact)
        assert_within_limits(act, veh)
        if act.engine_on:  # commanded attitude within the tilt limit of the highest altitude
            tilt = np.arccos(np.clip(body_z_L(act.q_LB_cmd)[2], -1.0, 1.0))
            assert tilt <= np.deg2rad(ControlConfig().tilt.tilt_max_high_deg) + 1e-9


def test_invalid_guidance_holds_the_last_good_command_and_bad_attitude_gives_zero_torque():
    ctl = Controller()
    good = ctl.update(nav(), gcmd([0.3, 0.0, 0.2]))
    held = ctl.update(nav(), gcmd([np.nan, 0.0, 0.0]))
    assert held.thrust_N == good.thrust_N
    np.testing.assert_array_equal(held.q_LB_cmd, good.q_LB_cmd)
    held2 = ctl.update(nav(), gcmd([5.0, 5.0, 5.0], valid=False))
    assert held2.thrust_N == good.thrust_N
    bad_q = ctl.update(nav(q=[np.nan, 0, 0, 0]), gcmd([0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(bad_q.torque_B_Nm, 0.0)
    assert bad_q.engine_on


def test_before_any_good_command_the_hold_is_minimum_thrust_upright():
    act = Controller().update(nav(mass=np.nan), gcmd([0.0, 0.0, 0.0]))
    assert act.engine_on and act.thrust_N == VehicleParams().thrust_min_N
    np.testing.assert_allclose(body_z_L(act.q_LB_cmd), E_Z, atol=1e-12)


# --------------------------------------------------------------------------- thrust vector and attitude command
def test_thrust_vector_inside_the_limits_is_exact():
    veh, tilt = VehicleParams(), TiltLimitConfig()
    a = np.array([0.4, -0.3, 0.5])
    thrust, z = thrust_vector_command(a, G_L, 2000.0, 300.0, veh, tilt)
    f = a - G_L
    assert thrust == pytest.approx(2000.0 * np.linalg.norm(f))
    np.testing.assert_allclose(z, f / np.linalg.norm(f))


def test_thrust_vector_beyond_the_tilt_limit_keeps_the_vertical_and_sits_on_the_limit():
    veh, tilt = VehicleParams(), TiltLimitConfig()
    for altitude in (0.0, 20.0, 60.0, 500.0):
        a = np.array([3.0, 2.0, 0.0])
        thrust, z = thrust_vector_command(a, G_L, 2000.0, altitude, veh, tilt)
        limit = tilt.tilt_max_rad(altitude)
        assert np.arccos(z[2]) == pytest.approx(limit, abs=1e-9)
        assert thrust * z[2] == pytest.approx(2000.0 * -G_L[2])  # vertical force kept
        np.testing.assert_allclose(z[:2] / np.linalg.norm(z[:2]), a[:2] / np.linalg.norm(a[:2]))


def test_thrust_clamps_and_downward_requests():
    veh, tilt = VehicleParams(), TiltLimitConfig()
    thrust, z = thrust_vector_command(np.array([1.0, 0.0, -5.0]), G_L, 2000.0, 300.0, veh, tilt)  # f_z < 0
    assert thrust == veh.thrust_min_N
    np.testing.assert_array_equal(z, E_Z)
    thrust, _ = thrust_vector_command(np.array([0.0, 0.0, 50.0]), G_L, 2000.0, 300.0, veh, tilt)
    assert thrust == veh.thrust_max_N
    thrust, _ = thrust_vector_command(np.array([0.0, 0.0, -1.5]), G_L, 2000.0, 300.0, veh, tilt)
    assert thrust == veh.thrust_min_N


def test_attitude_command_points_body_z_along_thrust_and_holds_yaw():
    rng = np.random.default_rng(3)
    for _ in range(50):
        yaw = rng.uniform(-np.pi, np.pi)
        tilt, az = rng.uniform(0.0, np.deg2rad(30.0)), rng.uniform(-np.pi, np.pi)
        z_cmd = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        R = Rotation.from_quat(attitude_command_LB(z_cmd, yaw), scalar_first=True).as_matrix()
        np.testing.assert_allclose(R[:, 2], z_cmd, atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert np.arctan2(R[1, 0], R[0, 0]) == pytest.approx(yaw, abs=1e-9)  # body x's horizontal heading
    # Upright with yaw 0 is the identity.
    np.testing.assert_allclose(np.abs(attitude_command_LB(E_Z, 0.0)), [1, 0, 0, 0], atol=1e-12)


# --------------------------------------------------------------------------- attitude loop
def test_small_error_torque_is_the_inertia_scaled_pd():
    cfg, veh = ControlConfig(), VehicleParams()
    inertia = veh.inertia_B_kgm2(2100.0)
    e = np.array([0.002, -0.001, 0.0015])  # rotation of B relative to the command [rad]
    omega = np.array([0.001, 0.002, -0.001])
    q = Rotation.from_rotvec(e).as_quat(scalar_first=True)
    tau = attitude_torque_B(q, omega, Q_UPRIGHT, inertia, cfg, veh.rcs_torque_max_Nm)
    wn, zeta = cfg.attitude_bandwidth_radps, cfg.attitude_damping_ratio
    expected = -inertia * wn**2 * e - 2 * zeta * wn * inertia * omega + np.cross(omega, inertia * omega)
    np.testing.assert_allclose(tau, expected, rtol=1e-5)


def test_inertia_includes_the_propellant_sphere():
    veh = VehicleParams()
    np.testing.assert_allclose(veh.inertia_B_kgm2(2100.0), [781.25 + 86.4, 781.25 + 86.4, 1000.0 + 86.4])
    np.testing.assert_allclose(veh.inertia_B_kgm2(1400.0), veh.dry_inertia_B_kgm2)


def fly_attitude(q0: Rotation, omega0, q_cmd, mass_kg=2100.0, t_end_s=8.0, dt_s=0.002):
    """Rigid body (Euler's equations, body-frame rate, exponential-map attitude update); control at 50 Hz."""
    veh, cfg = VehicleParams(), ControlConfig()
    inertia = veh.inertia_B_kgm2(mass_kg)
    ctl = Controller(cfg, veh)
    q, omega = q0, np.array(omega0, float)
    steps_per_control = int(round(CONTROL_DT_S / dt_s))
    errors, torques = [], []
    tau = np.zeros(3)
    for k in range(int(round(t_end_s / dt_s))):
        if k % steps_per_control == 0:
            tau = attitude_torque_B(q.as_quat(scalar_first=True), omega, q_cmd, inertia, cfg, veh.rcs_torque_max_Nm)
            torques.append(tau)
            assert np.all(np.abs(tau) <= veh.rcs_torque_max_Nm)
        omega = omega + (tau - np.cross(omega, inertia * omega)) / inertia * dt_s
        q = q * Rotation.from_rotvec(omega * dt_s)
        errors.append((Rotation.from_quat(q_cmd, scalar_first=True).inv() * q).magnitude())
    del ctl
    return np.rad2deg(np.array(errors)), np.array(torques), omega


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.3, -1.0, 0.2), (1.0, 1.0, 1.0)])
def test_attitude_converges_from_20_degrees_within_torque_limits(axis):
    axis = np.array(axis) / np.linalg.norm(axis)
    q_cmd = attitude_command_LB(np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0]), 0.3)
    q0 = Rotation.from_quat(q_cmd, scalar_first=True) * Rotation.from_rotvec(np.deg2rad(20.0) * axis)
    err_deg, torques, omega = fly_attitude(q0, [0.0, 0.0, 0.0], q_cmd)
    assert err_deg[0] == pytest.approx(20.0, abs=0.1)
    assert err_deg[-1] < 0.05
    t_half_deg = np.argmax(err_deg < 0.5) * 0.002
    assert 0.5 < t_half_deg < 5.0
    assert err_deg[int(5.0 / 0.002):].max() < 0.5  # no large overshoot once settled
    assert np.abs(torques).max() == pytest.approx(VehicleParams().rcs_torque_max_Nm)  # saturates, never exceeds
    assert np.linalg.norm(omega) < 1e-3


def test_large_slews_are_rate_limited_and_do_not_overshoot():
    err_deg, torques, omega = fly_attitude(Rotation.from_rotvec(np.deg2rad(120.0) * np.array([0.6, 0.8, 0.0])),
                                           [0.0, 0.0, 0.0], Q_UPRIGHT, t_end_s=14.0)
    rate_degps = -np.diff(err_deg) / 0.002
    assert rate_degps.max() < ControlConfig().slew_rate_max_degps * 1.05
    first_small = int(np.argmax(err_deg < 1.0))
    assert 0 < first_small and err_deg[first_small:].max() < 1.0  # no overshoot back out
    assert err_deg[-1] < 0.05 and np.linalg.norm(omega) < 1e-3


def test_attitude_recovers_from_an_initial_tumble_at_dry_mass():
    q_cmd = Q_UPRIGHT
    err_deg, _, omega = fly_attitude(Rotation.from_rotvec(np.deg2rad([12.0, -15.0, 5.0])), [0.15, -0.1, 0.2],
                                     q_cmd, mass_kg=1500.0, t_end_s=12.0)
    assert err_deg[-1] < 0.05 and np.linalg.norm(omega) < 1e-3


# --------------------------------------------------------------------------- touchdown
def test_engine_cut_on_leg_contact_is_latched():
    ctl = Controller()
    assert ctl.update(nav(), gcmd([0, 0, 0.2]), ContactMessage(0, np.zeros(4, bool))).engine_on
    cut = ctl.update(nav(), gcmd([0, 0, 0.2]), ContactMessage(1, np.array([False, False, True, False])))
    assert not cut.engine_on and cut.thrust_N == 0.0
    np.testing.assert_array_equal(cut.torque_B_Nm, 0.0)
    after = ctl.update(nav(), gcmd([0, 0, 0.2]), ContactMessage(2, np.zeros(4, bool)))  # bounce: stays off
    assert not after.engine_on and after.thrust_N == 0.0
    ctl.reset()
    assert ctl.update(nav(), gcmd([0, 0, 0.2])).engine_on


def test_legs_for_engine_cut_is_configurable():
    ctl = Controller({"legs_for_engine_cut": 2})
    assert ctl.update(nav(), gcmd([0, 0, 0]), ContactMessage(0, np.array([True, False, False, False]))).engine_on
    assert not ctl.update(nav(), gcmd([0, 0, 0]), ContactMessage(0, np.array([True, True, False, False]))).engine_on


def test_contact_message_shape_is_checked():
    with pytest.raises(ValueError, match="legs"):
        ContactMessage(0, np.array([True, False, True]))


# --------------------------------------------------------------------------- closed loop with attitude dynamics
def test_guidance_and_control_land_a_rigid_body_with_attitude_dynamics():
    """Translation + rotation: the thrust acts along the *actual* body +z, the RCS turns the body."""
    veh = VehicleParams()
    ctl = Controller(vehicle=veh)
    gd = make_guidance({"law": "apollo"}, ctl.guidance_limits())
    r, v, m = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0]), 2100.0
    q, omega = Rotation.identity(), np.zeros(3)
    dt, sub = 0.005, int(round(CONTROL_DT_S / 0.005))
    contact, t = None, 0.0
    max_tilt_err = 0.0
    for _ in range(int(200.0 / CONTROL_DT_S)):
        n = NavState(int(round(t * NS_PER_S)), r.copy(), v.copy(), q.as_quat(scalar_first=True), omega.copy(), m)
        cmd = gd.update(n, LandingTarget())
        act = ctl.update(n, cmd, contact)
        assert_within_limits(act, veh)
        if not act.engine_on:
            break
        if cmd.phase == PHASE_TERMINAL:
            max_tilt_err = max(max_tilt_err, np.arccos(np.clip(body_z_L(act.q_LB_cmd) @ q.apply(E_Z), -1, 1)))
        inertia = veh.inertia_B_kgm2(m)
        for _ in range(sub):
            a = act.thrust_N * q.apply(E_Z) / m + G_L
            r, v = r + v * dt, v + a * dt
            m -= act.thrust_N / (310.0 * 9.80665) * dt
            omega = omega + (act.torque_B_Nm - np.cross(omega, inertia * omega)) / inertia * dt
            q = q * Rotation.from_rotvec(omega * dt)
            t += dt
        if r[2] <= 2.1:
            contact = ContactMessage(int(round(t * NS_PER_S)), np.array([True, True, False, False]))
    else:
        raise AssertionError("no touchdown")
    rate = GuidanceConfig().terminal_descent_rate_mps
    assert abs(v[2] + rate) < 0.1 and np.linalg.norm(v[:2]) < 0.2 and np.linalg.norm(r[:2]) < 1.0
    assert np.rad2deg(max_tilt_err) < 2.0  # the attitude loop keeps up with the terminal phase


# --------------------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    "cfg,needles",
    [
        ({"attitude_bandwidth_radps": -1.0}, ["control.attitude_bandwidth_radps", "-1.0", "greater than 0"]),
        ({"legs_for_engine_cut": 5}, ["control.legs_for_engine_cut", "5", "less than or equal to 4"]),
        ({"tilt": {"tilt_max_high_deg": 95.0}}, ["control.tilt.tilt_max_high_deg", "95.0", "less than 80"]),
        ({"tilt": {"tilt_max_touchdown_deg": 40.0}}, ["tilt_max_touchdown_deg = 40.0", "tilt_max_high_deg = 30.0"]),
        ({"tilt": {"max_deg": 10.0}}, ["unknown field 'control.tilt.max_deg'", "tilt_max_high_deg"]),
        ({"yaw_deg": 10.0}, ["unknown field 'control.yaw_deg'", "yaw_hold_deg"]),
    ],
)
def test_bad_control_config_names_the_field_value_and_allowed(cfg, needles):
    with pytest.raises(ValueError) as exc:
        make_controller(cfg)
    msg = str(exc.value)
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_bad_vehicle_params_name_the_field():
    with pytest.raises(ValueError, match="vehicle.rcs_torque_max_Nm = 0.0"):
        VehicleParams(rcs_torque_max_Nm=0.0)
    with pytest.raises(ValueError, match="vehicle.thrust_min_N"):
        VehicleParams(thrust_min_N=9000.0)
    with pytest.raises(ValueError, match="dry_inertia_B_kgm2"):
        VehicleParams(dry_inertia_B_kgm2=(1.0, -1.0, 1.0))
