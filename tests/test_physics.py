"""Lander dynamics against closed-form physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.actuators import G0_MPS2
from models.camera import CameraConfig
from models.lander import LanderConfig
from models.world import PhysicsDivergedError, SunConfig, World

G_MOON = 1.62
DT_NS = 1_000_000
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _world(terrain, lander: LanderConfig | None = None, dt_ns: int = DT_NS) -> World:
    return World(terrain, lander or LanderConfig(), CameraConfig(width_px=64, height_px=64), SunConfig(), dt_ns, G_MOON)


def test_free_fall_impact_speed_matches_sqrt_2gh(flat_terrain):
    drop_m = 100.0
    world = _world(flat_terrain)
    clearance = world.lander_cfg.footpad_clearance_m  # body origin height when the pads touch flat ground
    world.reset(np.array([0.0, 0.0, clearance + drop_m]), np.zeros(3), LEVEL, np.zeros(3))
    # Coarse steps while high up, single steps near the ground; the speed is read in the
    # last step before any contact force acts.
    while world.truth().r_BL_L[2] - clearance > 1.0:
        world.step(50)
    while not world.footpad_contacts().any():
        v_before, z_before, t_before = world.truth().v_BL_L.copy(), world.truth().r_BL_L[2], world.t_ns / 1e9
        world.step(1)
    # What MuJoCo's implicitfast step achieves in free fall (dt = 1 ms). Under constant gravity
    # the velocity update is exact (v = g t, to rounding: measured 3e-12 m/s), but the position
    # update uses the new velocity (semi-implicit Euler), so the body leads the parabola by
    # g dt t / 2, 9 mm at impact (measured to 1e-11 m). Contacts are found at the start of a step
    # and reported after it, so contact shows about one step after the pads reach the ground.
    # The residual errors therefore come from *when* the speed and the time are read (about one
    # step): measured 1.0e-5 relative on the impact speed and 8.0e-5 on the time of flight. The
    # bounds are 10x those; either would catch a wrong gravity, mass or step size.
    dt_s = DT_NS / 1e9
    assert abs(-v_before[2] - G_MOON * t_before) < 1e-9, (v_before, t_before)
    assert abs(z_before - (clearance + drop_m - G_MOON * t_before**2 / 2 - G_MOON * dt_s * t_before / 2)) < 1e-9
    expected = math.sqrt(2.0 * G_MOON * drop_m)
    assert abs(-v_before[2] - expected) / expected < 1e-4, (v_before, expected)
    assert np.allclose(v_before[:2], 0.0, atol=1e-9)
    # Time of flight agrees too (t = sqrt(2h/g)).
    assert abs(world.t_ns / 1e9 - math.sqrt(2 * drop_m / G_MOON)) < 8e-4 * math.sqrt(2 * drop_m / G_MOON)
    # After a rigid-leg rebound it comes to rest standing on the ground (no divergence, no sinking).
    world.step(8000)
    assert abs(world.truth().r_BL_L[2] - clearance) < 0.05
    assert world.footpad_contacts().all()


def test_an_upside_down_fall_meets_the_ground_with_the_hull(flat_terrain):
    # Upside down (180 deg about x), the hull is the lowest part: it touches first, and the footpads never
    # have (the run's touchdown counts this contact; a footpad-only touchdown missed a 52 m/s crash).
    world = _world(flat_terrain)
    world.reset(np.array([0.0, 0.0, 10.0]), np.zeros(3), np.array([0.0, 1.0, 0.0, 0.0]), np.zeros(3))
    feet_ever = False
    for _ in range(20000):
        feet, hull = world.ground_contacts()
        feet_ever |= bool(feet.any())
        if hull:
            break
        world.step(1)
    assert hull and not feet_ever
    assert world.truth().r_BL_L[2] < 10.0 and np.array_equal(world.footpad_contacts(), feet)


def test_a_velocity_change_no_force_can_make_is_declared(flat_terrain, monkeypatch):
    # A tumbling lander near an empty tank once gained 350 m/s in 20 ms with no contact and no MuJoCo warning
    # (its accelerometer read 1 m/s^2): World.step bounds the change by the strongest thrust and gravity.
    import mujoco

    world = _world(flat_terrain)
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.array([0.0, 0.0, 3.0]))
    # Full thrust, spinning at 3 rad/s: a legitimate hard change passes for 2 s.
    for _ in range(200):
        world.step(5, world.lander_cfg.engine.thrust_max_N, np.array([0.0, 0.0, 200.0]))
    real_step = mujoco.mj_step

    def broken(m, d, *a, **k):  # an integration that adds 1 m/s to a call (one call here steps all five)
        real_step(m, d, *a, **k)
        d.qvel[2] += 1.0

    monkeypatch.setattr(mujoco, "mj_step", broken)
    with pytest.raises(PhysicsDivergedError, match=r"with nothing touching the ground the velocity changed by 0.99\d* m/s in 5 ms"):
        world.step(5, 0.0)


def test_propellant_flow_matches_thrust_over_isp_g0(flat_terrain):
    cfg = LanderConfig()
    world = _world(flat_terrain, cfg)
    world.reset(np.array([0.0, 0.0, 200.0]), np.zeros(3), LEVEL, np.zeros(3))
    thrust, seconds = 5000.0, 10.0
    steps = int(seconds * 1e9 / DT_NS)
    world.step(steps, thrust, np.zeros(3))
    used = cfg.propellant_kg - world.truth().propellant_kg
    expected = thrust * seconds / (cfg.engine.isp_s * G0_MPS2)
    # The flow is not integrated: each hold interval burns T / (Isp g0) * dt * n_steps in closed
    # form, so the only error is floating-point rounding (measured 3.2e-15 relative, 5e-14 kg,
    # half an ulp of the tank's mass). Bound: 10x that, far below any one-step (1e-4) error.
    assert abs(used - expected) / expected < 3e-14, (used, expected)
    # The simulated body really lost that mass (MuJoCo's own mass table).
    assert abs(world.model.body_mass.sum() - (cfg.wet_mass_kg - used)) < 1e-6


def test_thrust_is_applied_along_body_z_with_mass_from_mujoco(flat_terrain):
    world = _world(flat_terrain)
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.zeros(3))
    thrust = 6000.0
    world.step(1, thrust, np.zeros(3))
    world.step(1, thrust, np.zeros(3))  # sensors reflect the applied thrust from the second step
    m = world.model.body_mass.sum()
    f = world.specific_force_B()
    assert np.allclose(f, [0.0, 0.0, thrust / m], rtol=1e-3, atol=1e-6), (f, thrust / m)


def test_throttle_limits_and_engine_cut(flat_terrain):
    cfg = LanderConfig()
    world = _world(flat_terrain, cfg)
    p = world.propulsion
    assert p.clamp_thrust(0.0) == 0.0
    assert p.clamp_thrust(-5.0) == 0.0
    assert p.clamp_thrust(1.0) == cfg.engine.thrust_min_N
    assert p.clamp_thrust(1e9) == cfg.engine.thrust_max_N
    assert p.clamp_thrust(float("nan")) == 0.0
    assert np.allclose(p.clamp_torque(np.array([1e6, -1e6, 3.0])), [cfg.rcs_torque_max_Nm, -cfg.rcs_torque_max_Nm, 3.0])
    p.cut()
    assert p.clamp_thrust(5000.0) == 0.0


def test_fuel_runs_out_inside_a_hold_interval(flat_terrain):
    cfg = LanderConfig(propellant_kg=1.0)
    world = _world(flat_terrain, cfg)
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.zeros(3))
    thrust = cfg.engine.thrust_max_N
    burn_s = 1.0 / (thrust / (cfg.engine.isp_s * G0_MPS2))
    out = world.step(int(2 * burn_s * 1e9 / DT_NS), thrust)
    assert out.exhausted and world.truth().propellant_kg == 0.0
    assert abs(out.burn_steps * DT_NS / 1e9 - burn_s) <= DT_NS / 1e9
    assert world.data.ctrl[world.model.actuator("engine").id] == 0.0


def test_rcs_torque_spins_up_at_torque_over_inertia(flat_terrain):
    cfg = LanderConfig()
    world = _world(flat_terrain, cfg)
    world.reset(np.array([0.0, 0.0, 300.0]), np.zeros(3), LEVEL, np.zeros(3))
    tau = np.array([0.0, 0.0, 100.0])
    world.step(1000, 0.0, tau)  # 1 s
    izz = cfg.body_inertia_kgm2()[2] + cfg.tank_inertia_kgm2(cfg.propellant_kg)[2]
    assert abs(world.truth().omega_B[2] - 100.0 / izz) / (100.0 / izz) < 1e-3


@pytest.mark.parametrize("z_m, cause", [
    # Far above the ground nothing can touch it: the physics step is not the cause (before, the message blamed it).
    (50.0, "No part of it could touch the ground, so contact is not the cause and a smaller sim.physics_dt_ns "
           "(now 1000000) is unlikely to help"),
    (4.0, "Near the ground a physics step too large for the contact dynamics is the usual cause: reduce "
          "sim.physics_dt_ns (now 1000000)"),
])
def test_divergence_is_never_silent_and_says_where_to_look(flat_terrain, z_m, cause):
    world = _world(flat_terrain)
    world.reset(np.array([0.0, 0.0, z_m]), np.zeros(3), LEVEL, np.zeros(3))
    world.data.qvel[0] = 1e12  # beyond MuJoCo's mjMAXVAL: it would reset the state and carry on
    with pytest.raises(PhysicsDivergedError) as exc:
        world.step(5)
    msg = str(exc.value)
    assert msg.startswith("physics diverged at t = 0.00") and "MuJoCo reported bad qvel" in msg, msg
    assert f"the lander was at z = {z_m:g} m, moving at 1e+12 m/s and turning at 0 deg/s" in msg, msg
    assert cause in msg, msg


def test_torque_and_thrust_clamps_match_numpy_on_random_and_special_inputs():
    # The per-axis float path of clamp_torque against np.clip(np.nan_to_num(.)), the reference it replaced.
    from bench.scenario import load_scenario
    from models.actuators import PropulsionModel

    lander = load_scenario(None, []).lander
    prop = PropulsionModel(lander)
    tau = lander.rcs_torque_max_Nm
    rng = np.random.default_rng(11)
    cases = list(rng.normal(0.0, 2.0 * tau, (500, 3)))
    cases += [np.array([np.nan, np.inf, -np.inf]), np.array([tau, -tau, 0.0]), np.array([-0.0, 1e-300, -1e308])]
    for t in cases:
        got = prop.clamp_torque(t)
        assert got.shape == (3,) and np.array_equal(got, np.clip(np.nan_to_num(t), -tau, tau))
    eng = lander.engine
    for thrust in [*rng.uniform(-1e4, 2e4, 200), np.inf, 1e-9, eng.thrust_min_N, eng.thrust_max_N]:
        want = 0.0 if not thrust > 0.0 else float(np.clip(thrust, eng.thrust_min_N, eng.thrust_max_N))
        assert prop.clamp_thrust(thrust) == want


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_a_thrust_loss_torque_ends_with_its_fault_even_mid_burn(flat_terrain, realism):
    # Hovering, the engine firing throughout: a fault torque about y for 0.2 s, then none. While it acts
    # the body spins up at tau / I (MuJoCo's own inertia); once it has ended, the rate stays as it was.
    world = World(flat_terrain, LanderConfig(), CameraConfig(width_px=64, height_px=64), SunConfig(), DT_NS, G_MOON,
                  realism=realism)
    world.reset(np.array([0.0, 0.0, 50.0]), np.zeros(3), LEVEL, np.zeros(3))
    hover_N = world.truth().mass_kg * G_MOON
    tau_y = 40.0
    world.set_engine_fault(1.0, np.array([0.0, tau_y, 0.0]), None)
    world.step(200, hover_N)  # 0.2 s
    w_fault = world.truth().omega_B[1]
    cfg = world.lander_cfg
    inertia_y = cfg.body_inertia_kgm2()[1] + cfg.tank_inertia_kgm2(world.truth().propellant_kg)[1]
    assert w_fault == pytest.approx(tau_y / inertia_y * 0.2, rel=0.05)
    world.set_engine_fault(1.0, None, None)  # the fault ends, the engine still firing
    world.step(500, hover_N)  # 0.5 s more
    assert np.all(world.data.xfrc_applied[world._body_lander, 3:6] == 0.0)
    assert world.truth().omega_B[1] == pytest.approx(w_fault, abs=0.02 * abs(w_fault))
