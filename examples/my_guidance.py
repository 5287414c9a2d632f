"""An example guidance plug-in: copy this file, rename the class, change the law.

Use it with ``guidance.law = "my_guidance:GateAccelApollo"`` (run landbench from
this folder, or put the folder on PYTHONPATH) and its options in the scenario::

    [guidance]
    law = "my_guidance:GateAccelApollo"

    [guidance.options]
    gate_accel_up_mps2 = 0.3

The interface (README, "Controller design studies"): subclass
``gnc.guidance.GuidanceLaw``. Either implement ``accel_L`` (the approach-phase
feedback) and ``coeffs`` (its open-loop path as a quadratic in time, which the
built-in planner checks against the thrust, tilt and gate-altitude limits and
uses to choose the time to go), and get the planner, the terminal descent and
the thrust/tilt capping for free, as here; or override ``update(nav,
target) -> GuidanceCommand`` altogether. A law sees only the flight
software's navigation state (``NavState``: time, position, velocity, attitude,
rate, gauged mass) and the landing target, never the truth; it may import
numpy, scipy and gnc, never mujoco, models or bench.

Ports: NavState + LandingTarget in, GuidanceCommand (total acceleration in L,
phase, time to go) out, at the control rate (default 50 Hz).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.guidance import GuidanceLaw, apollo_accel_L, apollo_coeffs


class GateAccelApolloOptions(BaseModel):
    """The ``[guidance.options]`` table of this law (validated at scenario load)."""

    model_config = ConfigDict(extra="forbid")

    gate_accel_up_mps2: float = Field(
        0.0, ge=-1.0, le=2.0, description="total upward acceleration targeted at the gate [m/s^2] (0: Apollo's hover-like hand-off)"
    )


class GateAccelApollo(GuidanceLaw):
    """Apollo E-guidance with a chosen total acceleration at the gate.

    ``a = a_f - 6 (v_f + v) / t_go + 12 (r_f - r) / t_go^2`` with ``a_f = (0, 0, gate_accel_up_mps2)``.
    """

    name = "gate_accel_apollo"
    Options = GateAccelApolloOptions

    def _a_f_L(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.options.gate_accel_up_mps2])

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        return apollo_accel_L(r_L, v_L, r_f_L, v_f_L, self._a_f_L(), t_go_s)

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        return apollo_coeffs(r_L, v_L, r_f_L, v_f_L, self._a_f_L(), t_go_s)
