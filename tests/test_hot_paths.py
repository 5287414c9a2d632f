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

    def _ref_rcs_faulted(self, torque_B_Nm: np.ndarray) -> np.ndarray:
        if self._rcs_fault is None:
            return torque_B_Nm
        pos, neg, stuck = self._rcs_fault
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
        had = prop.propellant_kg > 0.0
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
        exhausted = had and prop.propellant_kg <= 0.0 and (thrust_cmd_N > 0.0 or burn_steps > 0)
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
