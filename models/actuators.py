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
``clamped * (1 + thrust_error_frac)``. Mass flows at ``T / (Isp * g0)``.
"""

from __future__ import annotations

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
        exhausted: True when the tanks ran dry inside the interval.
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

    def cut(self) -> None:
        """Permanent engine cut-off (touchdown)."""
        self.is_cut = True

    def mass_flow_kgps(self, thrust_N: float) -> float:
        """Propellant mass flow at a delivered thrust [kg/s]."""
        return thrust_N / (self.cfg.engine.isp_s * G0_MPS2)

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
        torque = self.clamp_torque(torque_cmd_B_Nm)
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
