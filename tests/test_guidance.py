"""Guidance laws against independent computations, and closed-loop point-mass landings."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from gnc.control import Controller, ContactMessage, VehicleParams, thrust_vector_command
from gnc.guidance import (
    PHASE_APPROACH,
    PHASE_TERMINAL,
    ApolloGuidance,
    GuidanceConfig,
    GuidanceLimits,
    LandingTarget,
    TiltLimitConfig,
    ZemZevGuidance,
    apollo_accel_L,
    apollo_coeffs,
    cap_acceleration_L,
    make_guidance,
    zem_zev_accel_L,
    zem_zev_coeffs,
)
from gnc.navstate import NavState

G_L = np.array([0.0, 0.0, -1.62])
G0_MPS2 = 9.80665
ISP_S = 310.0
WET_MASS_KG = 2100.0
NS_PER_S = 1_000_000_000
CONTROL_DT_S = 0.02
# Height of the body origin above flat ground when standing on its legs (default lander) [m].
TOUCHDOWN_Z_M = 2.1
Q_UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])


def nav_at(t_s: float, r, v, mass=WET_MASS_KG, q=Q_UPRIGHT) -> NavState:
    return NavState(int(round(t_s * NS_PER_S)), np.asarray(r, float), np.asarray(v, float), np.asarray(q, float),
                    np.zeros(3), float(mass))


# --------------------------------------------------------------------------- the formulas
def test_zem_zev_matches_the_discretised_energy_optimal_control():
    """First control of min integral |u|^2 (u = a - g) to (r_f, v_f) in T, by least norm over K pieces."""
    r0, v0 = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0])
    r_f, v_f, T, K = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -1.0]), 45.0, 600
    dt = T / K
    t_mid = (np.arange(K) + 0.5) * dt
    B = np.vstack([dt * (T - t_mid), np.full(K, dt)])  # final [r, v] per unit piecewise-constant u
    u0 = []
    for axis in range(3):
        d = np.array([
            r_f[axis] - r0[axis] - v0[axis] * T - 0.5 * G_L[axis] * T * T,
            v_f[axis] - v0[axis] - G_L[axis] * T,
        ])
        u = np.linalg.lstsq(B, d, rcond=None)[0]  # minimum-norm solution
        u0.append(1.5 * u[0] - 0.5 * u[1])  # linear extrapolation from the first two midpoints to t = 0
    expected = np.array(u0)
    got = zem_zev_accel_L(r0, v0, r_f, v_f, T, G_L) - G_L
    np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-5)


def _fly_unconstrained(law_accel, r0, v0, r_f, v_f, T, dt=0.005):
    """Double integrator (exact for zero-order-held acceleration), law re-evaluated each step with exact t_go."""
    r, v = np.array(r0, float), np.array(v0, float)
    accels = []
    n = int(round(T / dt))
    for k in range(n):
        a = law_accel(r, v, r_f, v_f, T - k * dt)
        accels.append(a)
        r = r + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
    return r, v, np.array(accels), dt * np.arange(n)


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
def test_closed_loop_with_exact_t_go_hits_the_gate_along_the_open_loop_polynomial(law):
    r0, v0 = np.array([150.0, -90.0, 480.0]), np.array([5.0, 3.0, -18.0])
    r_f, v_f, T = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -1.0]), 50.0
    a_f = np.zeros(3)
    if law == "zem_zev":
        def law_accel(r, v, rf, vf, t):
            return zem_zev_accel_L(r, v, rf, vf, t, G_L)
        c0, c1, c2 = zem_zev_coeffs(r0, v0, r_f, v_f, T)
    else:
        def law_accel(r, v, rf, vf, t):
            return apollo_accel_L(r, v, rf, vf, a_f, t)
        c0, c1, c2 = apollo_coeffs(r0, v0, r_f, v_f, a_f, T)
    r, v, accels, s = _fly_unconstrained(law_accel, r0, v0, r_f, v_f, T)
    np.testing.assert_allclose(r, r_f, atol=0.02)
    np.testing.assert_allclose(v, v_f, atol=0.02)
    # Feedback with exact t_go replays the open-loop optimal path.
    planned = c0 + c1 * s[:, None] + c2 * s[:, None] ** 2
    np.testing.assert_allclose(accels[: len(s) * 9 // 10], planned[: len(s) * 9 // 10], atol=2e-3)


def test_zem_zev_total_acceleration_is_linear_in_time_and_free_at_the_end():
    r0, v0 = np.array([-200.0, 150.0, 500.0]), np.array([-5.0, 5.0, -20.0])
    r_f, v_f, T = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -1.0]), 60.0
    c0, c1, c2 = zem_zev_coeffs(r0, v0, r_f, v_f, T)
    # Fly the feedback law (exact t_go) with an adaptive integrator, stopping short of the
    # 1/t_go^2 singularity, and read the law's acceleration along its own path.
    s_end = 0.98 * T
    sol = solve_ivp(lambda s, x: np.r_[x[3:], zem_zev_accel_L(x[:3], x[3:], r_f, v_f, T - s, G_L)],
                    (0.0, s_end), np.r_[r0, v0], method="DOP853", rtol=1e-11, atol=1e-10, dense_output=True)
    s = np.linspace(0.0, s_end, 61)
    x = sol.sol(s)
    a = np.array([zem_zev_accel_L(x[:3, k], x[3:, k], r_f, v_f, T - s[k], G_L) for k in range(len(s))])
    # Linear in time: the straight line through the first and last samples goes through every sample.
    line = a[0] + (a[-1] - a[0]) * (s / s_end)[:, None]
    np.testing.assert_allclose(a, line, atol=1e-9)
    # The closed-form path describes it, and reaches the gate position and velocity at T.
    np.testing.assert_allclose(a, c0 + c1 * s[:, None] + c2 * s[:, None] ** 2, atol=1e-9)
    np.testing.assert_allclose(r0 + v0 * T + c0 * T**2 / 2 + c1 * T**3 / 6 + c2 * T**4 / 12, r_f, atol=1e-9)
    np.testing.assert_allclose(v0 + c0 * T + c1 * T**2 / 2 + c2 * T**3 / 3, v_f, atol=1e-9)
    # Free at the end: the flown line, extrapolated to the gate, is not hover-like (zero) there.
    a_end = a[0] + (a[-1] - a[0]) * T / s_end
    assert np.linalg.norm(a_end) > 0.5


def test_apollo_polynomial_meets_its_boundary_conditions():
    rng = np.random.default_rng(4)
    for _ in range(5):
        r0, v0 = rng.uniform(-300, 300, 3), rng.uniform(-20, 20, 3)
        r_f, v_f, a_f = rng.uniform(-50, 50, 3), rng.uniform(-3, 3, 3), rng.uniform(-1, 1, 3)
        T = rng.uniform(10.0, 90.0)
        c0, c1, c2 = apollo_coeffs(r0, v0, r_f, v_f, a_f, T)
        np.testing.assert_allclose(apollo_accel_L(r0, v0, r_f, v_f, a_f, T), c0, rtol=1e-12, atol=1e-12)
        sol = solve_ivp(lambda s, x: np.r_[x[3:], c0 + c1 * s + c2 * s * s], (0.0, T), np.r_[r0, v0],
                        rtol=1e-11, atol=1e-9)
        np.testing.assert_allclose(sol.y[:3, -1], r_f, atol=1e-5)
        np.testing.assert_allclose(sol.y[3:, -1], v_f, atol=1e-6)
        np.testing.assert_allclose(c0 + c1 * T + c2 * T * T, a_f, atol=1e-9)


def test_zem_zev_accel_equals_its_polynomial_start():
    rng = np.random.default_rng(5)
    r0, v0, r_f, v_f = rng.normal(size=(4, 3)) * 50
    np.testing.assert_allclose(zem_zev_accel_L(r0, v0, r_f, v_f, 33.0, G_L), zem_zev_coeffs(r0, v0, r_f, v_f, 33.0)[0])


# --------------------------------------------------------------------------- planning and limits
@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
def test_planned_path_is_feasible_on_a_fine_independent_check(law):
    gd = make_guidance({"law": law})
    r0, v0 = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0])
    cmd = gd.update(nav_at(0.0, r0, v0), LandingTarget())
    assert cmd.phase == PHASE_APPROACH and gd.plan_feasible
    r_f, v_f = gd.gate_L(LandingTarget())
    c0, c1, c2 = gd.coeffs(r0, v0, r_f, v_f, cmd.t_go_s)
    s = np.linspace(0.0, cmd.t_go_s, 2001)[:, None]
    a = c0 + c1 * s + c2 * s * s
    z = r0[2] + v0[2] * s[:, 0] + c0[2] * s[:, 0] ** 2 / 2 + c1[2] * s[:, 0] ** 3 / 6 + c2[2] * s[:, 0] ** 4 / 12
    f = a - G_L
    thrust = WET_MASS_KG * np.linalg.norm(f, axis=1)
    tilt = np.arctan2(np.hypot(f[:, 0], f[:, 1]), f[:, 2])
    assert thrust.max() <= 7500.0 and thrust.min() >= 1500.0
    assert np.all(tilt <= TiltLimitConfig().tilt_max_rad(z) + 1e-9)
    assert z.min() >= r_f[2] - 1.0
    # t_go counts down with the clock on the planned path.
    nxt = gd.update(nav_at(CONTROL_DT_S, r0 + v0 * CONTROL_DT_S, v0 + cmd.a_cmd_L * CONTROL_DT_S), LandingTarget())
    assert nxt.t_go_s == pytest.approx(cmd.t_go_s - CONTROL_DT_S, abs=1e-9)


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
def test_the_last_seconds_fly_the_planned_path_open_loop_to_the_gate(law):
    gd = make_guidance({"law": law})
    r0, v0 = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0])
    T = gd.update(nav_at(0.0, r0, v0), LandingTarget()).t_go_s
    r_f, v_f = gd.gate_L(LandingTarget())
    c0, c1, c2 = gd.coeffs(r0, v0, r_f, v_f, T)

    def on_path(s):  # the planned path, integrated in closed form
        r = r0 + v0 * s + c0 * s**2 / 2 + c1 * s**3 / 6 + c2 * s**4 / 12
        return r, v0 + c0 * s + c1 * s**2 / 2 + c2 * s**3 / 3, c0 + c1 * s + c2 * s * s

    t_open = T - 0.9 * GuidanceConfig().open_loop_t_go_s
    r, v, a = on_path(t_open)
    cmd = gd.update(nav_at(t_open, r, v), LandingTarget())
    assert cmd.phase == PHASE_APPROACH and not cmd.saturated
    np.testing.assert_allclose(cmd.a_cmd_L, a, atol=1e-6)
    # Open loop from here: a disturbed state does not change the command, which stays on the path.
    r, v, a = on_path(T - 0.5)
    cmd = gd.update(nav_at(T - 0.5, r + 0.3, v + 0.2), LandingTarget())
    assert cmd.phase == PHASE_APPROACH
    np.testing.assert_allclose(cmd.a_cmd_L, a, atol=1e-6)
    np.testing.assert_allclose(on_path(T)[:2], (r_f, v_f), atol=1e-6)
    # The terminal phase starts at the gate time.
    assert gd.update(nav_at(T, r_f, v_f), LandingTarget()).phase == PHASE_TERMINAL


def test_without_a_feasible_path_the_plan_keeps_thrust_and_altitude_and_minimises_tilt_excess():
    gd = make_guidance({"law": "zem_zev"})
    r0, v0 = np.array([-200.0, 150.0, 500.0]), np.array([-5.0, 5.0, -20.0])  # flying away, sinking fast
    r_f, v_f = gd.gate_L(LandingTarget())
    t_go, violation = gd.plan_t_go(r0, v0, WET_MASS_KG, r_f, v_f)
    assert violation > 0.0
    grid = np.arange(5.0, 300.25, 0.5)
    viol3, _ = gd.path_violation(r0, v0, WET_MASS_KG, r_f, v_f, grid, with_margins=True)
    assert not np.any(np.all(viol3 <= 0.0, axis=1))  # truly none feasible
    chosen, _ = gd.path_violation(r0, v0, WET_MASS_KG, r_f, v_f, np.array([t_go]), with_margins=True)
    assert chosen[0, 0] <= 0.0 and chosen[0, 2] <= 0.0  # thrust and gate altitude kept
    thrust_alt_ok = np.maximum(viol3[:, 0], viol3[:, 2]) <= 0.0
    assert chosen[0, 1] == pytest.approx(viol3[thrust_alt_ok, 1].min())


def test_guidance_output_respects_thrust_and_tilt_limits_for_random_states():
    rng = np.random.default_rng(6)
    limits = GuidanceLimits()
    for law in ("zem_zev", "apollo"):
        for _ in range(60):
            gd = make_guidance({"law": law}, limits)
            mass = rng.uniform(1500.0, 2100.0)
            r = np.r_[rng.uniform(-400, 400, 2), rng.uniform(0.0, 800.0)]
            v = rng.uniform(-40, 40, 3)
            cmd = gd.update(nav_at(0.0, r, v, mass), LandingTarget())
            f = cmd.a_cmd_L - G_L
            thrust = mass * np.linalg.norm(f)
            assert limits.thrust_min_N - 1e-6 <= thrust <= limits.thrust_max_N + 1e-6
            assert np.arctan2(np.hypot(f[0], f[1]), f[2]) <= limits.tilt.tilt_max_rad(r[2]) + 1e-9


def test_cap_keeps_the_vertical_first():
    # Wanted: a large horizontal and a full vertical specific force; vertical is kept, horizontal cut.
    mass = 2000.0
    a_cmd = np.array([5.0, 0.0, 7500.0 / mass + G_L[2] - 0.1])
    out, sat = cap_acceleration_L(a_cmd, G_L, mass, GuidanceLimits(), altitude_m=500.0)
    assert sat
    assert out[2] == pytest.approx(a_cmd[2])
    f = out - G_L
    assert mass * np.linalg.norm(f) == pytest.approx(7500.0)


def test_tilt_schedule_tightens_linearly_near_the_ground():
    tilt = TiltLimitConfig()
    np.testing.assert_allclose(np.rad2deg(tilt.tilt_max_rad(np.array([-5.0, 0.0, 50.0, 100.0, 400.0]))),
                               [5.0, 5.0, 17.5, 30.0, 30.0])


# --------------------------------------------------------------------------- closed loop
def fly_point_mass(law: str, r0, v0, t_max_s: float = 200.0):
    """3-DOF point mass: explicit Euler, gravity, engine limits and mass flow, ideal attitude.

    Guidance and the controller run every step; the thrust acts along the
    controller's commanded body +z axis (attitude assumed perfectly tracked).
    """
    ctl = Controller()
    gd = make_guidance({"law": law}, ctl.guidance_limits())
    target = LandingTarget()
    r, v, m = np.array(r0, float), np.array(v0, float), WET_MASS_KG
    q = Q_UPRIGHT
    gate = None
    log = []
    contact = None
    for k in range(int(t_max_s / CONTROL_DT_S)):
        t = k * CONTROL_DT_S
        nav = nav_at(t, r, v, m, q)
        cmd = gd.update(nav, target)
        if gate is None and cmd.phase == PHASE_TERMINAL:
            gate = (r.copy(), v.copy())
        act = ctl.update(nav, cmd, contact)
        if not act.engine_on:
            return gate, (r, v, m), np.array(log)
        q = act.q_LB_cmd
        z_B_L = Rotation.from_quat(q, scalar_first=True).apply([0.0, 0.0, 1.0])
        log.append((act.thrust_N, np.arccos(np.clip(z_B_L[2], -1, 1)), r[2]))
        a = act.thrust_N * z_B_L / m + G_L
        r, v = r + v * CONTROL_DT_S, v + a * CONTROL_DT_S
        m -= act.thrust_N / (ISP_S * G0_MPS2) * CONTROL_DT_S
        if r[2] <= TOUCHDOWN_Z_M:
            contact = ContactMessage(int(round((t + CONTROL_DT_S) * NS_PER_S)), np.array([True, False, False, False]))
    raise AssertionError(f"no touchdown within {t_max_s} s; last state r={r}, v={v}")


HANDOVERS = [
    ((-120.0, 80.0, 500.0), (6.0, -4.0, -15.0)),  # the default scenario
    ((200.0, -200.0, 500.0), (0.0, 0.0, -10.0)),
    ((-200.0, 150.0, 500.0), (-5.0, 5.0, -20.0)),  # flying away and sinking fast: ZEM/ZEV's fallback path
]


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
@pytest.mark.parametrize("r0,v0", HANDOVERS)
def test_point_mass_reaches_the_gate_and_touches_down_softly_over_the_target(law, r0, v0):
    gate, (r, v, m), log = fly_point_mass(law, r0, v0)
    cfg = GuidanceConfig()
    assert gate is not None
    r_gate, v_gate = gate
    assert np.linalg.norm(r_gate - np.array([0.0, 0.0, cfg.gate_altitude_m])) < 5.0
    assert np.linalg.norm(v_gate[:2]) < 1.0
    assert abs(-v_gate[2] - cfg.terminal_descent_rate_mps) <= 0.3
    assert abs(v[2] + cfg.terminal_descent_rate_mps) < 0.05
    assert np.linalg.norm(v[:2]) < 0.2
    assert np.linalg.norm(r[:2]) < 0.5
    assert 1500.0 < m < WET_MASS_KG
    thrust, tilt, z = log.T
    assert thrust.min() >= 1500.0 and thrust.max() <= 7500.0
    assert np.all(tilt <= TiltLimitConfig().tilt_max_rad(z) + 1e-9)


def _fly_to_the_terminal_switch(law: str, r0, v0):
    """Guidance + the controller's thrust capping on an exact double integrator, until the phase switch.

    The thrust (the controller's clamped magnitude along its tilt-limited axis,
    attitude assumed tracked) is held over each control period; the state is
    propagated exactly for that constant acceleration and the mass drops at
    ``T / (Isp g0)``. Returns the state at the first tick whose phase is terminal.
    """
    ctl = Controller()
    gd = make_guidance({"law": law}, ctl.guidance_limits())
    vehicle, tilt = VehicleParams(), ctl.cfg.tilt
    r, v, m = np.array(r0, float), np.array(v0, float), WET_MASS_KG
    for k in range(int(200.0 / CONTROL_DT_S)):
        cmd = gd.update(nav_at(k * CONTROL_DT_S, r, v, m), LandingTarget())
        if cmd.phase == PHASE_TERMINAL:
            return r, v
        thrust, z_L = thrust_vector_command(cmd.a_cmd_L, G_L, m, r[2], vehicle, tilt)
        a = thrust * z_L / m + G_L
        r, v = r + v * CONTROL_DT_S + 0.5 * a * CONTROL_DT_S**2, v + a * CONTROL_DT_S
        m -= thrust / (ISP_S * G0_MPS2) * CONTROL_DT_S
    raise AssertionError(f"no switch to the terminal phase; last state r={r}, v={v}")


def _dispersed_handovers(n: int = 8, seed: int = 12):
    """The default hand-over, (-120, 80, 500) m and (6, -4, -15) m/s, its corners (+-25 m
    horizontally, +-1 m/s on each velocity axis) and uniform draws in between."""
    r_nom, v_nom = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0])
    out = [(r_nom, v_nom)]
    for sx, sy, sv in ((1, 1, 1), (-1, -1, -1), (1, -1, -1), (-1, 1, 1)):
        out.append((r_nom + [25.0 * sx, 25.0 * sy, 0.0], v_nom + [sv, -sv, sv]))
    rng = np.random.default_rng(seed)
    for _ in range(n):
        out.append((r_nom + np.r_[rng.uniform(-25.0, 25.0, 2), 0.0], v_nom + rng.uniform(-1.0, 1.0, 3)))
    return out


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
@pytest.mark.parametrize("which", ["corners", pytest.param("draws", marks=pytest.mark.slow)])
def test_terminal_phase_starts_at_the_gate_rate_from_dispersed_handovers(law, which):
    # make test flies the nominal hand-over and the four corners of the dispersion; make test-slow the eight
    # uniform draws between them as well.
    cfg = GuidanceConfig()
    handovers = _dispersed_handovers()
    for r0, v0 in handovers[:5] if which == "corners" else handovers[5:]:
        r, v = _fly_to_the_terminal_switch(law, r0, v0)
        assert abs(-v[2] - cfg.terminal_descent_rate_mps) <= 0.3, (r0, v0, r, v)
        # ... and at the gate, not above it or through its floor.
        assert abs(r[2] - cfg.gate_altitude_m) <= 1.0, (r0, v0, r, v)


def test_missed_gate_hovers_translates_back_and_lands_on_target():
    cfg = GuidanceConfig()
    gate, (r, v, _), log = fly_point_mass("apollo", (15.0, -10.0, 27.0), (0.0, 0.0, -1.0))
    _, _, z = log.T
    # Starts below the gate floor: terminal at once, holds height until back within the hold radius.
    assert gate is not None and gate[0][2] == pytest.approx(27.0)
    assert z.min() > TOUCHDOWN_Z_M - 0.1
    assert z[: int(5.0 / CONTROL_DT_S)].min() > 24.0
    assert np.linalg.norm(r[:2]) < 0.5 and np.linalg.norm(v[:2]) < 0.2
    assert abs(v[2] + cfg.terminal_descent_rate_mps) < 0.05


def test_phase_latches_and_reset_restarts():
    gd = make_guidance({"law": "apollo"})
    assert gd.update(nav_at(0.0, [0, 0, 20.0], [0, 0, -1.0]), LandingTarget()).phase == PHASE_TERMINAL
    assert gd.update(nav_at(0.02, [0, 0, 400.0], [0, 0, -1.0]), LandingTarget()).phase == PHASE_TERMINAL
    gd.reset()
    assert gd.update(nav_at(0.04, [0, 0, 400.0], [0, 0, -10.0]), LandingTarget()).phase == PHASE_APPROACH


def test_non_finite_navigation_gives_an_invalid_finite_command():
    gd = make_guidance()
    for bad in (
        nav_at(0.0, [np.nan, 0, 100.0], [0, 0, -5.0]),
        nav_at(0.0, [0, 0, 100.0], [0, np.inf, -5.0]),
        nav_at(0.0, [0, 0, 100.0], [0, 0, -5.0], mass=np.nan),
        nav_at(0.0, [0, 0, 100.0], [0, 0, -5.0], mass=0.0),
    ):
        cmd = gd.update(bad, LandingTarget())
        assert not cmd.valid and np.all(np.isfinite(cmd.a_cmd_L))
    # Guidance does not need the attitude: a failed attitude solution leaves it valid.
    assert gd.update(nav_at(0.0, [0, 0, 100.0], [0, 0, -5.0], q=[np.nan] * 4), LandingTarget()).valid


# --------------------------------------------------------------------------- configuration
def test_factory_selects_the_law_by_name():
    assert isinstance(make_guidance({"law": "apollo"}), ApolloGuidance)
    assert isinstance(make_guidance(GuidanceConfig(law="zem_zev")), ZemZevGuidance)
    assert isinstance(make_guidance(), ZemZevGuidance)


@pytest.mark.parametrize(
    "cfg,needles",
    [
        ({"law": "pdg"}, ["guidance.law", "'pdg'", "apollo", "zem_zev"]),
        ({"gate_altitude_m": -5.0}, ["guidance.gate_altitude_m", "-5.0", "greater than 0"]),
        ({"terminal_descent_rate_mps": 0.0}, ["guidance.terminal_descent_rate_mps", "0.0"]),
        ({"plan_thrust_max_frac": 1.5}, ["guidance.plan_thrust_max_frac", "1.5", "less than or equal to 1"]),
        ({"t_go_min_s": 400.0}, ["t_go_min_s = 400.0", "t_go_max_s = 300.0", "allowed"]),
        ({"gate_altitude": 30.0}, ["unknown field 'guidance.gate_altitude'", "gate_altitude_m"]),
        ({"law": "apollo", "gravity_mps2": "moon"}, ["guidance.gravity_mps2", "'moon'"]),
    ],
)
def test_bad_guidance_config_names_the_field_value_and_allowed(cfg, needles):
    with pytest.raises(ValueError) as exc:
        make_guidance(cfg)
    msg = str(exc.value)
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_bad_limits_name_the_field():
    with pytest.raises(ValueError, match="thrust_min_N = 8000.0"):
        GuidanceLimits(thrust_min_N=8000.0)
    with pytest.raises(ValueError, match="tilt_max_touchdown_deg"):
        TiltLimitConfig(tilt_max_touchdown_deg=40.0)


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
def test_a_moved_target_is_planned_for_and_the_same_one_is_not(law):
    """Guidance plans again when the target moves (a retarget), by any amount in any axis, and keeps its
    plan for the same target given again (another object holding the same coordinates)."""
    gd = make_guidance({"law": law})
    r0, v0 = np.array([-120.0, 80.0, 400.0]), np.array([6.0, -4.0, -18.0])
    gd.update(nav_at(0.0, r0, v0), LandingTarget())
    n = gd.n_plans
    gd.update(nav_at(0.02, r0 + 0.02 * v0, v0), LandingTarget(np.zeros(3)))
    assert gd.n_plans == n  # the same target
    for k, moved in enumerate(([0.0, 1e-9, 0.0], [0.0, 0.0, -0.5], [30.0, -20.0, 0.0])):
        t = 0.04 + 0.02 * k
        gd.update(nav_at(t, r0 + t * v0, v0), LandingTarget(np.array(moved)))
        assert gd.n_plans == n + 1 + k, moved
        np.testing.assert_array_equal(gd._target_L, moved)


@pytest.mark.parametrize("law", ["zem_zev", "apollo"])
def test_lower_thrust_limits_replan_within_them(law):
    """After an engine loss the flight software lowers the limits (``set_limits``): the next step plans again,
    and the new path keeps the thrust the engine now gives along its whole length on the same fine independent
    check as above, where the old plan's path needed more than that."""
    gd = make_guidance({"law": law})
    r0, v0 = np.array([-120.0, 80.0, 400.0]), np.array([6.0, -4.0, -18.0])
    first = gd.update(nav_at(0.0, r0, v0), LandingTarget())
    r_f, v_f = gd.gate_L(LandingTarget())
    r1, v1 = r0 + v0 * 1.0, v0 + first.a_cmd_L * 1.0
    lower = GuidanceLimits(thrust_min_N=0.65 * 1500.0, thrust_max_N=0.65 * 7500.0)

    def peak_thrust(t_go):
        c0, c1, c2 = gd.coeffs(r1, v1, r_f, v_f, t_go)
        s = np.linspace(0.0, t_go, 2001)[:, None]
        return WET_MASS_KG * np.linalg.norm(c0 + c1 * s + c2 * s * s - G_L, axis=1).max()

    old_t_go = first.t_go_s - 1.0
    assert peak_thrust(old_t_go) > lower.thrust_max_N  # the old plan needs more than is left
    n = gd.n_plans
    gd.set_limits(lower)
    cmd = gd.update(nav_at(1.0, r1, v1), LandingTarget())
    assert gd.n_plans == n + 1 and gd.limits is lower and cmd.phase == PHASE_APPROACH
    assert peak_thrust(cmd.t_go_s) <= lower.thrust_max_N
    with pytest.raises(ValueError, match="GuidanceLimits"):
        gd.set_limits({"thrust_max_N": 1.0})


# --------------------------------------------------------------------------- the slew check
def test_the_plan_leaves_time_to_slew_onto_its_first_thrust_direction():
    """A late divert (about 100 m up, the new site 5 m away, the vehicle tilted the other way): the planner
    must not pick a path whose first thrust direction the attitude control cannot reach in time. Checked
    against an explicit loop over the candidates: the rest-to-rest slew time under the RCS's angular
    acceleration, 2 sqrt(angle / accel), within plan_slew_time_frac of the time to go."""
    vehicle = VehicleParams()
    limits = Controller(vehicle=vehicle).guidance_limits()
    accel = limits.slew_accel_max_radps2
    assert accel == pytest.approx(vehicle.rcs_torque_max_Nm / max(vehicle.dry_inertia_B_kgm2[:2]))
    gd = make_guidance({"law": "zem_zev"}, limits)
    cfg = gd.cfg
    r0, v0, mass = np.array([3.9, 3.7, 95.4]), np.array([1.4, -1.0, -12.3]), 1800.0
    r_f, v_f = gd.gate_L(LandingTarget())
    q = Rotation.from_rotvec(np.deg2rad(3.3) * np.array([0.6, -0.8, 0.0])).as_quat(scalar_first=True)
    z_B = Rotation.from_quat(q, scalar_first=True).apply([0.0, 0.0, 1.0])

    free, _ = gd.plan_t_go(r0, v0, mass, r_f, v_f)  # no attitude given: no slew check
    t_go, viol = gd.plan_t_go(r0, v0, mass, r_f, v_f, z_B)
    assert viol <= 0.0

    grid = np.arange(cfg.t_go_min_s, cfg.t_go_max_s + 0.25, 0.5)
    viol4, delta_v = gd.path_violation(r0, v0, mass, r_f, v_f, grid, with_margins=True)
    slew_ok = []
    for T in grid:
        c0, _, _ = zem_zev_coeffs(r0, v0, r_f, v_f, T)
        f0 = c0 - G_L
        angle = np.arccos(np.clip(f0 @ z_B / np.linalg.norm(f0), -1.0, 1.0))
        slew_ok.append(2.0 * np.sqrt(angle / accel) <= cfg.plan_slew_time_frac * T)
    slew_ok = np.array(slew_ok)
    other_ok = np.all(viol4[:, :3] <= 0.0, axis=1)
    expected = grid[np.argmin(np.where(other_ok & slew_ok, delta_v, np.inf))]
    assert t_go == pytest.approx(expected)
    # The check binds here: the least-delta-v path of the other limits starts with a slew it has no time for.
    assert not slew_ok[np.flatnonzero(grid == free)[0]] and free < t_go
    # Upright and already pointing along the free plan's first direction: that plan is kept.
    c0, _, _ = zem_zev_coeffs(r0, v0, r_f, v_f, free)
    f0 = c0 - G_L
    assert gd.plan_t_go(r0, v0, mass, r_f, v_f, f0 / np.linalg.norm(f0))[0] == pytest.approx(free)
    # The hard limits (the re-plan trigger) carry no slew term.
    hard, _ = gd.path_violation(r0, v0, mass, r_f, v_f, grid, with_margins=False, z_B_L=z_B)
    assert np.all(hard[:, 3] == -1.0)


def test_the_slew_check_uses_the_attitude_of_the_navigation_state():
    # The law reads the thrust axis from nav.q_LB at a plan: pointing along the free plan's first thrust
    # direction it flies that plan; tilted 20 degrees the other way it plans a longer approach.
    limits = Controller(vehicle=VehicleParams()).guidance_limits()
    r0, v0, mass = np.array([3.9, 3.7, 95.4]), np.array([1.4, -1.0, -12.3]), 1800.0
    probe = make_guidance({"law": "zem_zev"}, limits)
    r_f, v_f = probe.gate_L(LandingTarget())
    free, _ = probe.plan_t_go(r0, v0, mass, r_f, v_f)
    c0, _, _ = zem_zev_coeffs(r0, v0, r_f, v_f, free)
    u = (c0 - G_L) / np.linalg.norm(c0 - G_L)
    axis = np.cross([0.0, 0.0, 1.0], u)
    onto = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arcsin(np.linalg.norm(axis)))
    away = Rotation.from_rotvec(-axis / np.linalg.norm(axis) * np.deg2rad(20.0))
    np.testing.assert_allclose(onto.apply([0.0, 0.0, 1.0]), u, atol=1e-12)
    t_go = {}
    for name, rot in (("onto", onto), ("away", away)):
        gd = make_guidance({"law": "zem_zev"}, limits)
        t_go[name] = gd.update(nav_at(0.0, r0, v0, mass, rot.as_quat(scalar_first=True)), LandingTarget()).t_go_s
    assert t_go["onto"] == pytest.approx(free) and t_go["away"] > free + 1.0
    with pytest.raises(ValueError, match="slew_accel_max_radps2"):
        GuidanceLimits(slew_accel_max_radps2=0.0)
