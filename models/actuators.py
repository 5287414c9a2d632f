"""Propulsion: throttleable main engine, RCS torques and propellant bookkeeping.

Ports:
    Input: commanded thrust [N] and commanded body torque (3,) [N m], held
        (zero-order) over a control period.
    Output: delivered thrust [N] and torques [N m] for MuJoCo's actuators,
        and the propellant consumed.
    Rate: evaluated once per control period; propellant is integrated over
        the physics steps it covers.

Engine logic: a command <= 0 (or ``cut()``) means the engine is off; any
positive command is clamped to ``[thrust_min_N, thrust_max_N]``, because a
lit deep-throttle engine cannot go below its minimum. The delivered thrust is
``clamped * (1 + thrust_error_frac)`` (times ``fault_gain`` under a thrust-loss
fault, :mod:`models.faults`). Mass flows at ``T / (Isp * g0)``. Under an RCS
fault (:meth:`PropulsionModel.set_rcs_fault`) the delivered torque (saturated,
or the PWM pulses) is scaled per axis and sense, and a stuck-on thruster's
torque is added.

Two paths (:attr:`PropulsionModel.instant`):

* Instant (idealised actuators, :meth:`models.lander.LanderConfig.ideal`): the
  engine delivers the clamped command at once and the RCS the saturated torque,
  held over the whole interval; one closed-form propellant draw per interval
  (:meth:`PropulsionModel.apply`).
* Per physics step (:meth:`PropulsionModel.physics_step`), when any of the
  realistic models is on:

  - throttle response: the engine's thrust ``T`` (before the thrust error)
    follows the clamped command ``c`` (0 when off) as a first-order lag, exact
    for a command held over the step, ``T_k+1 = c + (T_k - c) exp(-dt / tau)``,
    with the change per step limited to ``slew_rate_Nps * dt``. At the first
    command the engine is already burning at it (hand-over mid-descent).
    Propellant running out stops the engine at once.
  - RCS pulse-width modulation (``rcs.mode = "pwm"``): per axis, at the start
    of every ``pwm_period_ns`` window (aligned on whole periods of simulation
    time) the held command's impulse ``tau * period`` plus the impulse carried
    from earlier windows sets an on-time ``|impulse| / tau_max``; an impulse
    below the minimum impulse bit ``tau_max * min_on_ns`` fires nothing and is
    carried to the next window (the carry is held within one minimum impulse
    bit), so a small command fires a minimum pulse every few windows, as a
    pulse-width pulse-frequency modulator does, instead of leaving a dead zone.
    During the window the axis delivers ``+-tau_max`` while on; the step in
    which the pulse ends delivers the on-fraction of that step, so each
    window's impulse is exactly the on-time's (the physics step resolves it no
    finer).
  - RCS propellant: ``sum |tau_axis| / moment_arm_m`` of thrust at the RCS
    ``isp_s``, from the main tanks; with the tanks dry the RCS stops too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from models.lander import LanderConfig

G0_MPS2 = 9.80665  # standard gravity, defines Isp [m/s^2]


@dataclass(frozen=True)
class PropulsionOutput:
    """What the actuators deliver over one hold interval.

    Attributes:
        thrust_N: Delivered engine thrust [N] before exhaustion.
        torque_B_Nm: Delivered RCS torque (3,) [N m].
        burn_steps: Physics steps for which the engine fires (fewer than the
            interval when the propellant runs out inside it).
        propellant_used_kg: Propellant consumed over the interval [kg].
        exhausted: True when the tanks are dry at the end of the interval and thrust was asked for or
            burned in it (they ran dry inside it, or were dry already).
    """

    thrust_N: float
    torque_B_Nm: np.ndarray
    burn_steps: int
    propellant_used_kg: float
    exhausted: bool


class PropulsionModel:
    """Main engine + RCS with saturation and propellant flow."""

    def __init__(self, cfg: LanderConfig):
        self.cfg = cfg
        self.propellant_kg = cfg.propellant_kg
        self.is_cut = False
        self.fault_gain = 1.0  # factor on the delivered thrust set by a thrust-loss fault (models.faults)
        eng, rcs = cfg.engine, cfg.rcs
        self.instant = (eng.time_constant_s == 0.0 and math.isinf(eng.slew_rate_Nps)
                        and rcs.mode == "continuous" and not rcs.draws_propellant)
        self.engine_thrust_N: float | None = None  # engine state before the thrust error; None before any command
        self._decay = math.nan  # exp(-dt / tau) of the current step size
        self._decay_dt_s = math.nan
        # PWM state per axis (x, y, z) as floats: the per-physics-step path works on scalars, not (3,) arrays.
        self._pwm_on_s = (0.0, 0.0, 0.0)  # on-time of the current PWM window per axis [s]
        self._pwm_sign = (0.0, 0.0, 0.0)
        self._pwm_window = -1
        self._pwm_carry_Nms = (0.0, 0.0, 0.0)  # impulse commanded but not yet fired, per axis [N m s]
        # RCS faults per axis as floats: ((gain +, gain -, stuck [N m]) of x, y, z); None: none.
        self._rcs_fault_xyz: tuple[tuple[float, float, float], ...] | None = None
        # Per-step constants: the engine's exhaust velocity Isp g0 [m/s] and the RCS's [m/s].
        self._engine_ve_mps = cfg.engine.isp_s * G0_MPS2
        self._rcs_ve_mps = rcs.isp_s * G0_MPS2

    def set_rcs_fault(self, fault: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> None:
        """Hold the RCS faults active now (:meth:`models.faults.FaultInjector.rcs_fault`): per axis the factor on
        a positive and on a negative torque and the stuck-on torque as a fraction of the limit; None: none."""
        if fault is None:
            self._rcs_fault_xyz = None
            return
        pos, neg, stuck = (np.asarray(v, float) for v in fault)
        stuck_Nm = stuck * float(self.cfg.rcs_torque_max_Nm)
        self._rcs_fault_xyz = tuple(zip(pos.tolist(), neg.tolist(), stuck_Nm.tolist()))

    def _rcs_faulted(self, torque_B_Nm: np.ndarray) -> np.ndarray:
        """The delivered torque under the RCS faults (3,) [N m] (the instant path's; see :meth:`_rcs_faulted_xyz`)."""
        if self._rcs_fault_xyz is None:
            return torque_B_Nm
        return np.array(self._rcs_faulted_xyz(*torque_B_Nm.tolist()))

    def delivered_thrust_N(self, thrust_cmd_N: float) -> float:
        """Thrust the engine delivers now for a command [N] (instant path: the clamped command times the error)."""
        gain = 1.0 + self.cfg.engine.thrust_error_frac
        if self.fault_gain != 1.0:
            gain *= self.fault_gain
        if self.instant:
            return self.clamp_thrust(thrust_cmd_N) * gain
        if self.engine_thrust_N is None:
            return self.clamp_thrust(thrust_cmd_N) * gain
        return self.engine_thrust_N * gain

    def cut(self) -> None:
        """Permanent engine cut-off (touchdown)."""
        self.is_cut = True

    def mass_flow_kgps(self, thrust_N: float) -> float:
        """Propellant mass flow at a delivered thrust [kg/s]."""
        return thrust_N / self._engine_ve_mps

    def clamp_thrust(self, thrust_cmd_N: float) -> float:
        """Thrust the engine actually produces for a command [N] (no error term)."""
        eng = self.cfg.engine
        if self.is_cut or self.propellant_kg <= 0.0 or not thrust_cmd_N > 0.0:
            return 0.0
        return float(min(max(float(thrust_cmd_N), eng.thrust_min_N), eng.thrust_max_N))

    def clamp_torque(self, torque_cmd_B_Nm: np.ndarray) -> np.ndarray:
        """RCS torque after per-axis saturation (3,) [N m]."""
        tau = float(self.cfg.rcs_torque_max_Nm)
        t = np.asarray(torque_cmd_B_Nm, float)
        if t.shape != (3,):
            return np.clip(np.nan_to_num(t), -tau, tau)
        # Per-axis on floats (called every physics tick): NaN -> 0, +-inf and beyond -> +-tau,
        # as np.clip(np.nan_to_num(t), -tau, tau).
        return np.array([0.0 if v != v else (tau if v > tau else (-tau if v < -tau else v)) for v in t.tolist()])

    def apply(self, thrust_cmd_N: float, torque_cmd_B_Nm: np.ndarray, n_steps: int, dt_s: float) -> PropulsionOutput:
        """Evaluate the commands over ``n_steps`` physics steps and burn propellant.

        Args:
            thrust_cmd_N: Commanded thrust [N].
            torque_cmd_B_Nm: Commanded body torque (3,) [N m].
            n_steps: Physics steps in the hold interval.
            dt_s: Physics step [s].

        Returns:
            The delivered output; ``self.propellant_kg`` is decreased.
        """
        thrust = self.clamp_thrust(thrust_cmd_N) * (1.0 + self.cfg.engine.thrust_error_frac)
        if self.fault_gain != 1.0:
            thrust *= self.fault_gain
        torque = self._rcs_faulted(self.clamp_torque(torque_cmd_B_Nm))
        if thrust <= 0.0:
            return PropulsionOutput(0.0, torque, 0, 0.0, False)
        per_step_kg = self.mass_flow_kgps(thrust) * dt_s
        steps_available = int(self.propellant_kg // per_step_kg)
        if steps_available >= n_steps:
            used = per_step_kg * n_steps
            self.propellant_kg -= used
            return PropulsionOutput(thrust, torque, n_steps, used, False)
        used = self.propellant_kg  # the last partial step's worth is spent too
        self.propellant_kg = 0.0
        return PropulsionOutput(thrust, torque, steps_available, used, True)

    # ----------------------------------------------------------------- per physics step (realistic path)
    def _engine_step(self, thrust_cmd_N: float, dt_s: float) -> float:
        """Advance the throttle response one step; returns the engine's thrust over the step [N] (before the error)."""
        eng = self.cfg.engine
        target = self.clamp_thrust(thrust_cmd_N)
        if self.engine_thrust_N is None:
            self.engine_thrust_N = target  # already burning at the first command
            return target
        t = self.engine_thrust_N
        if eng.time_constant_s > 0.0:
            if dt_s != self._decay_dt_s:
                self._decay, self._decay_dt_s = math.exp(-dt_s / eng.time_constant_s), dt_s
            new = target + (t - target) * self._decay
        else:
            new = target
        max_change = eng.slew_rate_Nps * dt_s
        if new - t > max_change:
            new = t + max_change
        elif t - new > max_change:
            new = t - max_change
        self.engine_thrust_N = new
        return new

    def _rcs_step_xyz(self, tx: float, ty: float, tz: float, step_index: int,
                      dt_ns: int) -> tuple[float, float, float]:
        """RCS torque over physics step ``step_index`` [N m] per body axis: continuous, or the PWM window's pulses.

        The saturated command's axes ``tx, ty, tz`` [N m] in, the delivered torque's out.

        Per axis, the same operations in the same order as on (3,) arrays (``np.clip``, ``np.sign``,
        ``np.abs``), so the result is bit for bit the array form's (tests/test_hot_paths.py).
        """
        rcs = self.cfg.rcs
        if rcs.mode == "continuous":
            return tx, ty, tz
        tau_max = float(self.cfg.rcs_torque_max_Nm)
        steps_per_window = rcs.pwm_period_ns // dt_ns
        window, k = divmod(step_index, steps_per_window)
        if window != self._pwm_window:  # a new window: the held command (plus the carry) sets each axis's pulse
            self._pwm_window = window
            period_s = rcs.pwm_period_ns / 1e9
            mib = tau_max * rcs.min_on_ns / 1e9
            fired_max = tau_max * period_s
            on_s, sign, carry = [], [], []
            for t, c in zip((tx, ty, tz), self._pwm_carry_Nms):
                demand = t * period_s + c
                fired = _clip(demand, -fired_max, fired_max)
                if abs(fired) < mib:
                    fired = 0.0
                carry.append(_clip(demand - fired, -mib, mib))
                on_s.append(abs(fired) / tau_max)
                sign.append(_sign(fired))
            self._pwm_carry_Nms, self._pwm_on_s, self._pwm_sign = tuple(carry), tuple(on_s), tuple(sign)
        dt_s = dt_ns / 1e9
        elapsed_s = k * dt_s
        (on_x, on_y, on_z), (s_x, s_y, s_z) = self._pwm_on_s, self._pwm_sign
        return (s_x * tau_max * _clip((on_x - elapsed_s) / dt_s, 0.0, 1.0),
                s_y * tau_max * _clip((on_y - elapsed_s) / dt_s, 0.0, 1.0),
                s_z * tau_max * _clip((on_z - elapsed_s) / dt_s, 0.0, 1.0))

    def _rcs_faulted_xyz(self, tx: float, ty: float, tz: float) -> tuple[float, float, float]:
        """The delivered torque under the RCS faults, per body axis [N m] (the array form's operations, bit for bit)."""
        fault = self._rcs_fault_xyz
        if fault is None:
            return tx, ty, tz
        return tuple((t * pos if t > 0.0 else t * neg) + stuck
                     for t, (pos, neg, stuck) in zip((tx, ty, tz), fault))

    def physics_step(self, thrust_cmd_N: float, torque_cmd_B_Nm: np.ndarray, step_index: int,
                     dt_ns: int) -> tuple[float, np.ndarray, bool]:
        """One physics step of the realistic actuators.

        Args:
            thrust_cmd_N: Commanded thrust, held [N].
            torque_cmd_B_Nm: Commanded torque, held (3,) [N m].
            step_index: Index of this physics step since t = 0 (PWM windows are aligned on it).
            dt_ns: Physics step [ns]; ``rcs.pwm_period_ns`` must be a whole multiple of it.

        Returns:
            (delivered thrust [N], delivered torque (3,) [N m], whether the engine fired
            this step); ``self.propellant_kg`` is decreased by this step's draw.
        """
        tx, ty, tz = self.clamp_torque(torque_cmd_B_Nm).tolist()
        thrust, tx, ty, tz, fired = self.physics_step_xyz(thrust_cmd_N, tx, ty, tz, step_index, dt_ns)
        return thrust, np.array([tx, ty, tz]), fired

    def physics_step_xyz(self, thrust_cmd_N: float, tx: float, ty: float, tz: float, step_index: int,
                         dt_ns: int) -> tuple[float, float, float, float, bool]:
        """:meth:`physics_step` on floats, for the per-physics-step loop (bit for bit the same).

        Args:
            thrust_cmd_N: Commanded thrust, held [N].
            tx, ty, tz: The commanded torque's body axes, already saturated by :meth:`clamp_torque` [N m].
            step_index: Index of this physics step since t = 0.
            dt_ns: Physics step [ns].

        Returns:
            (delivered thrust [N], delivered torque's x, y, z [N m], whether the engine fired).
        """
        dt_s = dt_ns / 1e9
        rcs = self.cfg.rcs
        if self.propellant_kg <= 0.0:
            self.engine_thrust_N = 0.0
            if rcs.draws_propellant:
                return 0.0, 0.0, 0.0, 0.0, False
            return (0.0, *self._rcs_faulted_xyz(*self._rcs_step_xyz(tx, ty, tz, step_index, dt_ns)), False)
        thrust = self._engine_step(thrust_cmd_N, dt_s) * (1.0 + self.cfg.engine.thrust_error_frac)
        if self.fault_gain != 1.0:
            thrust *= self.fault_gain
        tx, ty, tz = self._rcs_faulted_xyz(*self._rcs_step_xyz(tx, ty, tz, step_index, dt_ns))
        used = thrust / self._engine_ve_mps * dt_s
        if rcs.draws_propellant:
            used += self._rcs_draw_kg(tx, ty, tz, dt_s)
        if used >= self.propellant_kg:  # the last partial step's worth is spent too
            self.propellant_kg = 0.0
        else:
            self.propellant_kg -= used
        return thrust, tx, ty, tz, thrust > 0.0

    def _rcs_draw_kg(self, tx: float, ty: float, tz: float, dt_s: float) -> float:
        """The RCS's propellant over one step delivering torque ``(tx, ty, tz)`` [N m] for ``dt_s`` [s] [kg]."""
        # (|x| + |y|) + |z|: the order float(np.sum(np.abs(torque))) adds three elements in.
        return (abs(tx) + abs(ty) + abs(tz)) / self.cfg.rcs.moment_arm_m / self._rcs_ve_mps * dt_s


def _clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one float: ``x`` itself at a tie (signed zeros kept) and NaN passed through."""
    return lo if x < lo else (hi if x > hi else x)


def _sign(x: float) -> float:
    """``np.sign`` of one float: +-1.0, 0.0 for either zero, NaN for NaN."""
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else (0.0 if x == 0.0 else x))
