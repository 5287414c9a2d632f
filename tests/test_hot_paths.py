"""The per-tick fast paths against the routines they replaced, bit for bit.

Each hand-written float path of the closed loop (per physics step, per control tick) is checked
here against the (3,)-array form it replaced, kept below as the reference, on random and
special inputs. Equality is exact: the float64 bit patterns (signed zeros included) must match.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from models import actuators
from models.actuators import G0_MPS2, PropulsionModel
from models.camera import CameraConfig
from models.lander import EngineConfig, LanderConfig, RcsConfig
from models.world import NS_PER_S, PhysicsDivergedError, SunConfig, World

DT_NS = 2_000_000
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _bits(x) -> np.ndarray:
    return np.asarray(x, np.float64).view(np.uint64)


def _same(a, b) -> bool:
    """Bitwise equality of float scalars/arrays (NaN payloads and signed zeros included)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return a.shape == b.shape and np.array_equal(_bits(a), _bits(b))


# --------------------------------------------------------------------------- scalar helpers
_SPECIAL = [0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 1e-300, -1e-300, 1e308, -1e308, math.inf, -math.inf, math.nan,
            5e-324, -5e-324, 4.0, -4.0, 0.08, -0.08]


def test_clip_matches_np_clip_on_random_and_special_floats():
    rng = np.random.default_rng(1)
    values = _SPECIAL + list(rng.normal(0.0, 3.0, 2000)) + list(rng.uniform(-1.0, 2.0, 2000))
    bounds = [(0.0, 1.0), (-0.0, 0.0), (-4.0, 4.0), (-0.08, 0.08), (-1e-300, 1e-300)]
    for lo, hi in bounds:
        want = np.clip(np.array(values), lo, hi)
        got = np.array([actuators._clip(v, lo, hi) for v in values])
        assert _same(got, want), (lo, hi)


def test_sign_matches_np_sign():
    rng = np.random.default_rng(2)
    values = _SPECIAL + list(rng.normal(0.0, 1.0, 1000))
    assert _same([actuators._sign(v) for v in values], np.sign(np.array(values)))


def test_sum_of_three_abs_matches_np_sum_order():
    # physics_step_xyz writes (|x| + |y|) + |z| for float(np.sum(np.abs(torque))).
    rng = np.random.default_rng(3)
    t = rng.normal(0.0, 1.0, (20000, 3)) * 10.0 ** rng.uniform(-6, 6, (20000, 3))
    for x, y, z in t:
        assert float(np.sum(np.abs(np.array([x, y, z])))) == abs(x) + abs(y) + abs(z)


def test_rcs_draw_matches_the_array_expression():
    lander = LanderConfig(rcs=RcsConfig(moment_arm_m=1.3, isp_s=217.0))
    prop, rcs = PropulsionModel(lander), lander.rcs
    rng = np.random.default_rng(4)
    t = rng.normal(0.0, 100.0, (20000, 3)) * 10.0 ** rng.uniform(-3, 1, (20000, 3))
    for torque in [*t, np.array([200.0, -200.0, 0.0]), np.array([-0.0, 0.0, 199.99])]:
        for dt_s in (0.002, 0.001):
            want = float(np.sum(np.abs(torque))) / rcs.moment_arm_m / (rcs.isp_s * G0_MPS2) * dt_s
            assert prop._rcs_draw_kg(*torque.tolist(), dt_s) == want


# --------------------------------------------------------------------------- propulsion, per physics step
class _ArrayPropulsion(PropulsionModel):
    """The per-step actuators as they were: (3,) arrays, np.clip/np.sign/np.where (the reference)."""

    def __init__(self, cfg: LanderConfig):
        super().__init__(cfg)
        self._ref_on_s = np.zeros(3)
        self._ref_sign = np.zeros(3)
        self._ref_carry = np.zeros(3)
        self._ref_fault = None  # the reference's RCS faults as (3,) arrays; set by set_rcs_fault

    def set_rcs_fault(self, fault):
        super().set_rcs_fault(fault)  # the new path's floats; the reference keeps its own arrays, as before
        self._ref_fault = None if fault is None else (
            np.asarray(fault[0], float), np.asarray(fault[1], float),
            np.asarray(fault[2], float) * float(self.cfg.rcs_torque_max_Nm))

    def _ref_rcs_faulted(self, torque_B_Nm: np.ndarray) -> np.ndarray:
        if self._ref_fault is None:
            return torque_B_Nm
        pos, neg, stuck = self._ref_fault
        return np.where(torque_B_Nm > 0.0, torque_B_Nm * pos, torque_B_Nm * neg) + stuck

    def _ref_rcs_step(self, torque_cmd_B_Nm: np.ndarray, step_index: int, dt_ns: int) -> np.ndarray:
        rcs, tau_max = self.cfg.rcs, float(self.cfg.rcs_torque_max_Nm)
        torque = np.clip(np.nan_to_num(np.asarray(torque_cmd_B_Nm, float)), -tau_max, tau_max)
        if rcs.mode == "continuous":
            return torque
        steps_per_window = rcs.pwm_period_ns // dt_ns
        window, k = divmod(step_index, steps_per_window)
        period_s = rcs.pwm_period_ns / 1e9
        if window != self._pwm_window:
            self._pwm_window = window
            mib = tau_max * rcs.min_on_ns / 1e9
            demand = torque * period_s + self._ref_carry
            fired = np.clip(demand, -tau_max * period_s, tau_max * period_s)
            fired[np.abs(fired) < mib] = 0.0
            self._ref_carry = np.clip(demand - fired, -mib, mib)
            self._ref_on_s = np.abs(fired) / tau_max
            self._ref_sign = np.sign(fired)
        dt_s = dt_ns / 1e9
        frac = np.clip((self._ref_on_s - k * dt_s) / dt_s, 0.0, 1.0)
        return self._ref_sign * tau_max * frac

    def physics_step(self, thrust_cmd_N, torque_cmd_B_Nm, step_index, dt_ns):
        dt_s = dt_ns / 1e9
        rcs = self.cfg.rcs
        if self.propellant_kg <= 0.0:
            self.engine_thrust_N = 0.0
            return 0.0, (np.zeros(3) if rcs.draws_propellant
                         else self._ref_rcs_faulted(self._ref_rcs_step(torque_cmd_B_Nm, step_index, dt_ns))), False
        thrust = self._engine_step(thrust_cmd_N, dt_s) * (1.0 + self.cfg.engine.thrust_error_frac)
        if self.fault_gain != 1.0:
            thrust *= self.fault_gain
        torque = self._ref_rcs_faulted(self._ref_rcs_step(torque_cmd_B_Nm, step_index, dt_ns))
        used = thrust / (self.cfg.engine.isp_s * G0_MPS2) * dt_s
        if rcs.draws_propellant:
            used += float(np.sum(np.abs(torque))) / rcs.moment_arm_m / (rcs.isp_s * G0_MPS2) * dt_s
        if used >= self.propellant_kg:
            self.propellant_kg = 0.0
        else:
            self.propellant_kg -= used
        return thrust, torque, thrust > 0.0


def _landers() -> list[LanderConfig]:
    base = LanderConfig(engine=EngineConfig(time_constant_s=0.05, slew_rate_Nps=20000.0, thrust_error_frac=0.013))
    return [
        base,
        base.model_copy(update={"rcs": RcsConfig(min_on_ns=0)}),
        base.model_copy(update={"rcs": RcsConfig(pwm_period_ns=10_000_000, min_on_ns=6_000_000)}),
        base.model_copy(update={"rcs": RcsConfig(mode="continuous")}),
        base.model_copy(update={"rcs": RcsConfig(draws_propellant=False)}),
        base.model_copy(update={"propellant_kg": 0.4}),  # runs dry inside the test
        base.model_copy(update={"propellant_kg": 0.4, "rcs": RcsConfig(draws_propellant=False)}),
    ]


@pytest.mark.parametrize("lander", _landers(), ids=lambda c: f"{c.rcs.mode}-{c.rcs.min_on_ns}-{c.propellant_kg}")
def test_physics_step_matches_the_array_reference(lander):
    rng = np.random.default_rng(lander.rcs.min_on_ns + int(lander.propellant_kg * 10))
    new, ref = PropulsionModel(lander), _ArrayPropulsion(lander)
    tau = lander.rcs_torque_max_Nm
    special = [np.array([np.nan, np.inf, -np.inf]), np.array([0.0, -0.0, 0.0]), np.array([-0.0, -0.0, -0.0]),
               np.array([tau, -tau, 1e-9]), np.array([0.2 * tau, -0.2 * tau, 0.1999 * tau])]
    step = 0
    for hold in range(400):
        if hold % 50 == 7:
            fault = (rng.uniform(0, 1, 3), rng.uniform(0, 1, 3), rng.choice([0.0, 0.3, -0.5], 3))
            new.set_rcs_fault(fault)
            ref.set_rcs_fault(fault)
        elif hold % 50 == 31:
            new.set_rcs_fault(None)
            ref.set_rcs_fault(None)
        if hold % 40 == 20:
            new.fault_gain = ref.fault_gain = float(rng.uniform(0.5, 1.0))
        cmd = special[hold % len(special)] if hold % 9 == 0 else rng.normal(0.0, 0.3 * tau, 3)
        thrust_cmd = float(rng.choice([0.0, -5.0, rng.uniform(0.0, 9000.0)]))
        n_steps = int(rng.integers(1, 25))
        for _ in range(n_steps):
            a = new.physics_step(thrust_cmd, cmd, step, DT_NS)
            b = ref.physics_step(thrust_cmd, cmd, step, DT_NS)
            assert _same(a[0], b[0]) and _same(a[1], b[1]) and a[2] == b[2], (hold, step)
            assert _same(new.propellant_kg, ref.propellant_kg)
            step += 1
    assert new.propellant_kg == ref.propellant_kg


def test_physics_step_xyz_equals_physics_step():
    lander = _landers()[0]
    a, b = PropulsionModel(lander), PropulsionModel(lander)
    rng = np.random.default_rng(5)
    for k in range(2000):
        cmd = rng.normal(0.0, 150.0, 3) if k % 13 else np.array([np.nan, 1e9, -0.0])
        thrust_cmd = float(rng.uniform(0.0, 8000.0))
        thrust, torque, fired = a.physics_step(thrust_cmd, cmd, k, DT_NS)
        got = b.physics_step_xyz(thrust_cmd, *b.clamp_torque(cmd).tolist(), k, DT_NS)
        assert _same(got[:4], [thrust, *torque]) and got[4] == fired


# --------------------------------------------------------------------------- the world's per-step loop
class _ArrayWorld(World):
    """The per-physics-step loop as it was: (3,) array sums and a warning check around every mj_step."""

    def _step_each(self, n_steps, thrust_cmd_N, torque_cmd_B_Nm):
        import mujoco

        prop = self.propulsion
        used0 = prop.propellant_kg
        burn_steps = 0
        thrust = 0.0
        impulse_B = np.zeros(3)
        imu_sum = np.array(self._imu_sum, float)
        gyro_sum = np.array(self._gyro_sum, float)
        for _ in range(n_steps):
            thrust, torque, fired = prop.physics_step(thrust_cmd_N, torque_cmd_B_Nm, self._step_count,
                                                      self.physics_dt_ns)
            burn_steps += fired
            impulse_B += torque
            self.data.ctrl[self._act_rcs] = torque
            self.data.ctrl[self._act_engine] = thrust
            self._apply_fault_torque(thrust > 0.0)
            before = [int(self.data.warning[w].number) for w in self._i_divergence]
            mujoco.mj_step(self.model, self.data, nstep=1)
            self._step_count += 1
            after = [int(self.data.warning[w].number) for w in self._i_divergence]
            if after != before:
                raise PhysicsDivergedError(f"physics diverged at t = {self.t_ns / NS_PER_S:.3f} s")
            imu_sum += self.data.sensordata[self._sens_acc]
            gyro_sum += self.data.qvel[3:6]
            self._imu_steps += 1
        self._imu_sum, self._gyro_sum = list(imu_sum), list(gyro_sum)
        self._set_propellant(prop.propellant_kg)
        mujoco.mj_forward(self.model, self.data)
        exhausted = prop.propellant_kg <= 0.0 and (thrust_cmd_N > 0.0 or burn_steps > 0)  # dry: ran or was
        return actuators.PropulsionOutput(thrust, impulse_B / max(n_steps, 1), burn_steps,
                                          used0 - prop.propellant_kg, exhausted)


def _realistic_world(cls, terrain, lander):
    return cls(terrain, lander, CameraConfig(width_px=64, height_px=64), SunConfig(), DT_NS, 1.62, realism="realistic")


def test_world_step_each_matches_the_array_loop(flat_terrain):
    lander = _landers()[0].model_copy(update={"propellant_kg": 3.0})  # runs dry inside the test
    new, ref = _realistic_world(World, flat_terrain, lander), _realistic_world(_ArrayWorld, flat_terrain, lander)
    rng = np.random.default_rng(7)
    for w in (new, ref):
        w.reset(np.array([3.0, -2.0, 60.0]), np.array([0.5, 0.0, -3.0]), np.array([0.99, 0.05, -0.03, 0.02]),
                np.array([0.01, -0.02, 0.03]))
    for hold in range(300):
        if hold == 40:
            for w in (new, ref):
                w.set_engine_fault(0.7, np.array([0.0, 40.0, -5.0]), (2.0, 30.0))
        cmd = rng.normal(0.0, 80.0, 3)
        thrust_cmd = float(rng.uniform(2000.0, 7000.0))
        n = int(rng.integers(1, 12))
        a, b = new.step(n, thrust_cmd, cmd), ref.step(n, thrust_cmd, cmd)
        assert _same(a.thrust_N, b.thrust_N) and _same(a.torque_B_Nm, b.torque_B_Nm)
        assert (a.burn_steps, a.exhausted) == (b.burn_steps, b.exhausted) and _same(a.propellant_used_kg,
                                                                                     b.propellant_used_kg)
        ta, tb = new.truth(), ref.truth()
        for f in ("r_BL_L", "v_BL_L", "q_LB", "omega_B", "mass_kg", "propellant_kg"):
            assert _same(getattr(ta, f), getattr(tb, f)), (hold, f)
        if hold % 2:
            ia, ib = new.imu_mean_B(), ref.imu_mean_B()
            assert _same(ia[0], ib[0]) and _same(ia[1], ib[1])
    assert new.propulsion.propellant_kg == 0.0  # the dry-tank path was exercised


def test_divergence_names_the_step_it_happened_in(flat_terrain):
    world = _realistic_world(World, flat_terrain, _landers()[0])
    world.reset(np.array([0.0, 0.0, 50.0]), np.zeros(3), LEVEL, np.zeros(3))
    world.step(7, 3000.0, np.zeros(3))
    world.data.qvel[0] = 1e12  # beyond MuJoCo's mjMAXVAL: diverges in the next step
    with pytest.raises(PhysicsDivergedError, match=r"t = 0\.016 s.*physics_dt_ns"):
        world.step(5, 3000.0, np.zeros(3))


# --------------------------------------------------------------------------- flight software, per control tick
def test_gnc_numeric_helpers_match_numpy():
    from gnc.numeric import clip_float, cross3, max_abs3, norm

    rng = np.random.default_rng(8)
    vecs = list(rng.normal(0.0, 1.0, (3000, 3)) * 10.0 ** rng.uniform(-8, 8, (3000, 3)))
    vecs += [np.array(v) for v in ([0.0, -0.0, 0.0], [np.nan, 1.0, 2.0], [np.inf, -1.0, 0.0], [1e-300, 1e300, -2.0])]
    with np.errstate(over="ignore", invalid="ignore"):  # the 1e300 case overflows in both
        for a, b in zip(vecs, vecs[1:] + vecs[:1]):
            assert _same(cross3(*a.tolist(), *b.tolist()), np.cross(a, b))
            assert _same(norm(a), np.linalg.norm(a))
            assert _same(max_abs3(*a.tolist()), np.max(np.abs(a)))
            for lo, hi in ((-1.0, 1.0), (-200.0, 200.0), (-0.0, 0.0)):
                assert _same([clip_float(v, lo, hi) for v in a.tolist()], np.clip(a, lo, hi))
    assert _same(norm(np.arange(12.0)[::3]), np.linalg.norm(np.arange(12.0)[::3]))  # a strided view
    q = rng.normal(0.0, 1.0, (500, 4))
    for v in q:
        assert _same(norm(v), np.linalg.norm(v))


def _ref_attitude_command_LB(z_cmd_L, yaw_rad):
    from gnc.control import _EZ
    from gnc.quat import quat_from_matrix

    z = np.asarray(z_cmd_L, float)
    z = z / np.linalg.norm(z)
    h = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    x = h - (h @ z) / z[2] * _EZ
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return quat_from_matrix(np.column_stack([x, y, z]))


def _ref_attitude_torque_B(q_LB, omega_B, q_LB_cmd, inertia_B_kgm2, cfg, torque_max_Nm):
    from gnc.quat import quat_error

    q_e = quat_error(q_LB_cmd, q_LB)
    e = 2.0 * np.copysign(1.0, q_e[0]) * q_e[1:]
    wn, zeta = cfg.attitude_bandwidth_radps, cfg.attitude_damping_ratio
    omega_ref = -(wn / (2.0 * zeta)) * e
    slew_max = np.deg2rad(cfg.slew_rate_max_degps)
    ref_norm = float(np.linalg.norm(omega_ref))
    if ref_norm > slew_max:
        omega_ref *= slew_max / ref_norm
    omega = np.asarray(omega_B, float)
    inertia = np.asarray(inertia_B_kgm2, float)
    tau = inertia * (2.0 * zeta * wn) * (omega_ref - omega) + np.cross(omega, inertia * omega)
    peak = float(np.max(np.abs(tau)))
    if peak > torque_max_Nm:
        tau *= torque_max_Nm / peak
    return np.clip(tau, -torque_max_Nm, torque_max_Nm)


def _ref_thrust_vector_command(a_cmd_L, g_L, mass_kg, altitude_m, vehicle, tilt, z_B_L=None):
    from gnc.control import _EZ, _F_Z_MIN_MPS2

    f = np.asarray(a_cmd_L, float) - g_L
    if not f[2] > _F_Z_MIN_MPS2:
        return float(vehicle.thrust_min_N), _EZ.copy()
    scale = float(np.max(np.abs(f)))
    u = f / scale
    tan_max = np.tan(tilt.tilt_max_rad(altitude_m))
    uh_norm = float(np.hypot(u[0], u[1]))
    if uh_norm > tan_max * u[2]:
        u[:2] *= tan_max * u[2] / uh_norm
    u_norm = float(np.linalg.norm(u))
    along = u_norm if z_B_L is None else max(float(u @ z_B_L), 0.0)
    thrust = float(np.clip(mass_kg * scale * along / vehicle.thrust_scale, vehicle.thrust_min_N, vehicle.thrust_max_N))
    return thrust, u / u_norm


def _ref_unit_quaternion(q):
    q = np.asarray(q, float)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        return None
    scale = float(np.max(np.abs(q)))
    if scale == 0.0:
        return None
    q = q / scale
    return q / np.linalg.norm(q)


def _random_unit_quaternions(rng, n):
    q = rng.normal(0.0, 1.0, (n, 4))
    q[: n // 3, 1:] *= 0.02  # near upright, as in flight
    return q / np.linalg.norm(q, axis=1)[:, None]


def test_control_stages_match_the_array_reference():
    from gnc import control
    from gnc.quat import unit_quaternion
    from gnc.control import ControlConfig, VehicleParams

    rng = np.random.default_rng(9)
    vehicle = VehicleParams(thrust_scale=1.013)
    for cfg in (ControlConfig(), ControlConfig(slew_rate_max_degps=3.0, attitude_bandwidth_radps=6.0)):
        g_L = cfg.g_L()
        for q, q_cmd in zip(_random_unit_quaternions(rng, 1500), _random_unit_quaternions(rng, 1500)):
            omega = rng.normal(0.0, 0.05, 3) * rng.choice([0.0, 1.0, 30.0])
            inertia = np.array([781.25, 781.25, 1000.0]) + rng.uniform(0.0, 60.0)
            for torque_max in (200.0, 5.0):
                assert _same(control.attitude_torque_B(q, omega, q_cmd, inertia, cfg, torque_max),
                             _ref_attitude_torque_B(q, omega, q_cmd, inertia, cfg, torque_max))
            a_cmd = rng.normal(0.0, 1.5, 3) * rng.choice([1.0, 1e-3, 1e3])
            altitude = float(rng.uniform(-5.0, 3000.0))
            z_B_L = q[1:] / np.linalg.norm(q[1:]) if q[0] > 0.5 else None
            got = control.thrust_vector_command(a_cmd, g_L, 1800.0, altitude, vehicle, cfg.tilt, z_B_L)
            want = _ref_thrust_vector_command(a_cmd, g_L, 1800.0, altitude, vehicle, cfg.tilt, z_B_L)
            assert _same(got[0], want[0]) and _same(got[1], want[1])
            z_cmd = np.abs(rng.normal(0.0, 1.0, 3)) * [rng.choice([-1, 1]), rng.choice([-1, 1]), 1.0] + [0, 0, 0.05]
            for yaw in (0.0, float(rng.uniform(-7.0, 7.0)), np.deg2rad(90.0)):
                assert _same(control.attitude_command_LB(z_cmd, yaw), _ref_attitude_command_LB(z_cmd, yaw))
            for qq in (q, q * 1e-200, q * 1e200, np.zeros(4), np.array([np.nan, 0, 0, 1]), q[:3]):
                got, want = unit_quaternion(qq), _ref_unit_quaternion(qq)
                assert (got is None and want is None) or _same(got, want)


def test_controller_update_matches_the_array_reference():
    from gnc.control import _EZ, ActuatorCommand, ControlConfig, Controller, VehicleParams
    from gnc.guidance import GuidanceCommand
    from gnc.messages import ContactMessage
    from gnc.navstate import NavState

    class _RefController(Controller):
        """Controller.update as it was, on the reference stages above."""

        def update(self, nav, cmd, contact=None):
            t_ns = int(nav.t_ns)
            if contact is not None and int(np.count_nonzero(np.asarray(contact.legs, bool))) >= self.cfg.legs_for_engine_cut:
                self.engine_cut = True
            if self.engine_cut:
                return ActuatorCommand(0.0, np.zeros(3), False, t_ns, self._q_cmd_hold.copy())
            mass = float(nav.mass_kg) if np.isfinite(nav.mass_kg) and nav.mass_kg > 0.0 else float("nan")
            altitude = float(np.asarray(nav.r_BL_L, float)[2])
            a_cmd = np.asarray(cmd.a_cmd_L, float)
            z_B_L = None
            if self.cfg.thrust_projection == "body_axis":
                q_nav = _ref_unit_quaternion(nav.q_LB)
                if q_nav is not None:
                    w, x, y, z = q_nav
                    z_B_L = np.array([2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)])
            if cmd.valid and np.all(np.isfinite(a_cmd)) and np.isfinite(mass) and np.isfinite(altitude):
                self._thrust_hold_N, z_cmd_L = _ref_thrust_vector_command(
                    a_cmd, self.g_L, mass, altitude, self.vehicle, self.cfg.tilt, z_B_L)
                self._q_cmd_hold = _ref_attitude_command_LB(z_cmd_L, self.yaw_rad)
            q = _ref_unit_quaternion(nav.q_LB)
            omega = np.asarray(nav.omega_B, float)
            if q is not None and np.all(np.isfinite(omega)):
                inertia = self.vehicle.inertia_B_kgm2(mass if np.isfinite(mass) else self.vehicle.dry_mass_kg)
                torque = _ref_attitude_torque_B(q, omega, self._q_cmd_hold, inertia, self.cfg,
                                                self.vehicle.rcs_torque_max_Nm)
            else:
                torque = np.zeros(3)
            if not np.all(np.isfinite(torque)):
                torque = np.zeros(3)
            torque = np.clip(torque, -self.vehicle.rcs_torque_max_Nm, self.vehicle.rcs_torque_max_Nm)
            thrust = float(np.clip(self._thrust_hold_N, self.vehicle.thrust_min_N, self.vehicle.thrust_max_N))
            return ActuatorCommand(thrust, torque, True, t_ns, self._q_cmd_hold.copy())

    rng = np.random.default_rng(10)
    for cfg in (ControlConfig(), ControlConfig(thrust_projection="magnitude", yaw_hold_deg=33.0)):
        vehicle = VehicleParams(thrust_scale=0.987)
        new, ref = Controller(cfg, vehicle), _RefController(cfg, vehicle)
        for k, q in enumerate(_random_unit_quaternions(rng, 1500)):
            q = q * rng.choice([1.0, 3.0, 1e-3]) if k % 17 else np.array([np.nan, 0.0, 0.0, 1.0])
            omega = rng.normal(0.0, 0.05, 3) if k % 23 else np.array([0.0, np.inf, 0.0])
            mass = float(rng.choice([1800.0, 2093.5, np.nan, -1.0], p=[0.45, 0.45, 0.05, 0.05]))
            nav = NavState(k * 20_000_000, rng.normal(0.0, 300.0, 3), rng.normal(0.0, 10.0, 3), q, omega, mass)
            a_cmd = rng.normal(0.0, 1.0, 3) + (_EZ * rng.choice([0.0, 1.62, 3.0]))
            cmd = GuidanceCommand(nav.t_ns, a_cmd if k % 29 else np.array([np.nan, 0.0, 0.0]), "approach", 10.0,
                                  valid=bool(k % 31))
            a, b = new.update(nav, cmd), ref.update(nav, cmd)
            assert _same(a.thrust_N, b.thrust_N) and _same(a.torque_B_Nm, b.torque_B_Nm), k
            assert _same(a.q_LB_cmd, b.q_LB_cmd) and a.engine_on == b.engine_on
        legs = ContactMessage(0, np.array([True, False, False, False]))
        a, b = new.update(nav, cmd, legs), ref.update(nav, cmd, legs)
        assert not a.engine_on and _same(a.torque_B_Nm, b.torque_B_Nm) and _same(a.q_LB_cmd, b.q_LB_cmd)


def test_guidance_scalar_paths_match_the_array_reference():
    from gnc.control import ControlConfig, VehicleParams, guidance_limits
    from gnc.guidance import TiltLimitConfig, cap_acceleration_L, make_guidance

    rng = np.random.default_rng(12)
    tilt = TiltLimitConfig()
    for alt in [*rng.uniform(-50.0, 2000.0, 3000), 0.0, -0.0, tilt.taper_altitude_m, np.nan, np.inf]:
        want = tilt.tilt_max_rad(np.asarray(alt))  # the array path on a 0-d array
        assert _same(tilt.tilt_max_rad(float(alt)), want) and _same(tilt.tilt_max_rad(np.float64(alt)), want)

    def ref_cap(a_cmd_L, g_L, mass_kg, limits, altitude_m):
        f = np.asarray(a_cmd_L, float) - g_L
        f_max = limits.thrust_max_N / mass_kg
        f_min = limits.thrust_min_N / mass_kg
        fz = float(np.clip(f[2], f_min, f_max))
        fh = f[:2].copy()
        fh_norm = float(np.linalg.norm(fh))
        fh_max = min(np.tan(float(limits.tilt.tilt_max_rad(np.asarray(altitude_m)))) * fz,
                     np.sqrt(max(f_max * f_max - fz * fz, 0.0)))
        if fh_norm > fh_max:
            fh *= fh_max / fh_norm
        return np.array([fh[0], fh[1], fz]) + g_L, bool(fz != f[2] or fh_norm > fh_max)

    cfg = ControlConfig()
    limits = guidance_limits(VehicleParams(), cfg)
    for _ in range(3000):
        a = rng.normal(0.0, 2.0, 3) * rng.choice([0.1, 1.0, 5.0])
        mass, alt = float(rng.uniform(1500.0, 2100.0)), float(rng.uniform(0.0, 1500.0))
        got, want = cap_acceleration_L(a, cfg.g_L(), mass, limits, alt), ref_cap(a, cfg.g_L(), mass, limits, alt)
        assert _same(got[0], want[0]) and got[1] == want[1]

    law = make_guidance(None, limits)
    c = law.cfg

    def ref_terminal(r_L, v_L, target_L):
        w, zeta = c.terminal_position_bandwidth_radps, c.terminal_damping_ratio
        e_h = r_L[:2] - target_L[:2]
        v_ref_h = -(w / (2.0 * zeta)) * e_h
        speed = float(np.linalg.norm(v_ref_h))
        if speed > c.terminal_speed_max_mps:
            v_ref_h *= c.terminal_speed_max_mps / speed
        a_h = 2.0 * zeta * w * (v_ref_h - v_L[:2])
        hold_r = c.terminal_hold_radius_m
        descent_frac = float(np.clip((2.0 * hold_r - np.linalg.norm(e_h)) / hold_r, 0.0, 1.0))
        a_z = c.terminal_rate_gain_per_s * (-descent_frac * c.terminal_descent_rate_mps - v_L[2])
        return np.array([a_h[0], a_h[1], a_z])

    for _ in range(3000):
        r, v, target = rng.normal(0.0, 5.0, 3) * rng.choice([0.1, 1.0, 10.0]), rng.normal(0.0, 1.0, 3), rng.normal(0, 2, 3)
        assert _same(law.terminal_accel_L(r, v, target), ref_terminal(r, v, target))


def _ref_path_violation(law, r_L, v_L, mass_kg, r_f_L, v_f_L, t_go_s, with_margins, z_B_L=None):
    """GuidanceLaw.path_violation as it was written on (N, M, 3) arrays (the reference)."""
    from gnc.guidance import _EPS, GATE_UNDERSHOOT_TOL_M, PLAN_SAMPLES

    cfg, lim = law.cfg, law.limits
    T = np.asarray(t_go_s, float)[:, None]
    c0, c1, c2 = law.coeffs(r_L[None, :], v_L[None, :], r_f_L[None, :], v_f_L[None, :], T)
    sigma = np.linspace(0.0, 1.0, PLAN_SAMPLES)
    s = (T * sigma)[:, :, None]
    a = c0[:, None, :] + c1[:, None, :] * s + c2[:, None, :] * s * s
    z = (r_L[2] + v_L[2] * s[..., 0] + c0[:, None, 2] * s[..., 0] ** 2 / 2.0
         + c1[:, None, 2] * s[..., 0] ** 3 / 6.0 + c2[:, None, 2] * s[..., 0] ** 4 / 12.0)
    f = a - law.g_L
    f_norm = np.linalg.norm(f, axis=-1)
    max_frac = cfg.plan_thrust_max_frac if with_margins else 1.0
    min_frac = cfg.plan_thrust_min_frac if with_margins else 1.0
    tilt_frac = cfg.plan_tilt_frac if with_margins else 1.0
    f_max = max_frac * lim.thrust_max_N / mass_kg
    f_min = min_frac * lim.thrust_min_N / mass_kg
    tilt_lim = tilt_frac * np.asarray(lim.tilt.tilt_max_rad(z - (r_f_L[2] - cfg.gate_altitude_m)))
    tilt = np.arctan2(np.linalg.norm(f[..., :2], axis=-1), f[..., 2])
    viol = np.stack([
        np.maximum(f_norm / f_max - 1.0, 1.0 - f_norm / max(f_min, _EPS)),
        (tilt - tilt_lim) / np.maximum(tilt_lim, np.deg2rad(1.0)),
        (r_f_L[2] - GATE_UNDERSHOOT_TOL_M - z) / GATE_UNDERSHOOT_TOL_M,
    ], axis=-1).max(axis=1)
    slew = np.full((viol.shape[0], 1), -1.0)
    if with_margins and z_B_L is not None and lim.slew_accel_max_radps2 is not None:
        f0 = f[:, 0, :]
        cos = (f0 @ np.asarray(z_B_L, float)) / np.maximum(f_norm[:, 0], _EPS)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        slew[:, 0] = 2.0 * np.sqrt(angle / lim.slew_accel_max_radps2) / (cfg.plan_slew_time_frac * T[:, 0]) - 1.0
    return np.concatenate([viol, slew], axis=1), np.trapezoid(f_norm, s[..., 0], axis=1)


@pytest.mark.parametrize("law_name", ["apollo", "zem_zev"])
def test_path_violation_matches_the_array_reference(law_name):
    """The planner's path check, per axis on (N, M) arrays, against the (N, M, 3) form it replaced:
    the re-plan check (one time to go, hard limits) and the planning grid (margins, slew)."""
    from gnc.control import ControlConfig, VehicleParams, guidance_limits
    from gnc.guidance import make_guidance

    law = make_guidance({"law": law_name}, guidance_limits(VehicleParams(), ControlConfig()))
    rng = np.random.default_rng(5)
    grid = np.arange(law.cfg.t_go_min_s, law.cfg.t_go_max_s + 0.25, 0.5)
    for i in range(200):
        r = rng.normal([0.0, 0.0, 300.0], [300.0, 300.0, 200.0])
        v = rng.normal([0.0, 0.0, -20.0], [15.0, 15.0, 15.0])
        r_f, v_f = np.array([0.0, 0.0, 30.0]) + rng.normal(0.0, 5.0, 3), np.array([0.0, 0.0, -1.0])
        mass = float(rng.uniform(1500.0, 2100.0))
        z_B = rng.normal(0.0, 0.3, 3) + [0.0, 0.0, 1.0]
        t_go = grid if i % 20 == 0 else np.array([rng.uniform(1.0, 90.0)])
        for margins, axis in ((False, None), (True, None), (True, z_B)):
            viol, dv = law.path_violation(r, v, mass, r_f, v_f, t_go, with_margins=margins, z_B_L=axis)
            want_viol, want_dv = _ref_path_violation(law, r, v, mass, r_f, v_f, t_go, margins, axis)
            assert _same(viol, want_viol) and _same(dv, want_dv)
            alone, none = law.path_violation(r, v, mass, r_f, v_f, t_go, with_margins=margins, z_B_L=axis,
                                             want_delta_v=False)
            assert _same(alone, want_viol) and none is None
