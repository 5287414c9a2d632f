"""Guidance plug-ins for the tests (``guidance.law = "plugin_laws:..."``; tests/ is on the path under pytest).

``ScaledZemZev`` is a real law that flies and lands; the others are the mistakes a user makes.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.guidance import GuidanceLaw


class ScaledZemZevOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    position_gain: float = Field(6.0, ge=4.5, le=12.0, description="ZEM gain k_r [-] (6: energy-optimal)")


class ScaledZemZev(GuidanceLaw):
    """Generalised ZEM/ZEV written out independently of gnc.guidance: a - g = k_r ZEM/t^2 - k_v ZEV/t.

    ``k_v = 2 (k_r - 3) / 3`` puts the closed loop's modes at t_go^3 and t_go^(k_r/3), so position and
    velocity both reach the target (k_r = 6: k_v = 2, the energy-optimal law). The open-loop path for the
    planner is the optimal (k_r = 6) one, a linear acceleration in time.
    """

    Options = ScaledZemZevOptions

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        t = t_go_s
        k_r = self.options.position_gain
        k_v = 2.0 * (k_r - 3.0) / 3.0
        zem = r_f_L - (r_L + v_L * t + 0.5 * self.g_L * t * t)
        zev = v_f_L - (v_L + self.g_L * t)
        return k_r * zem / (t * t) - k_v * zev / t + self.g_L

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        t = t_go_s
        # a(s) = c0 + c1 s reaching (r_f, v_f) at s = t:  c0 t + c1 t^2/2 = dv,  c0 t^2/2 + c1 t^3/6 = dr
        dr = r_f_L - r_L - v_L * t
        dv = v_f_L - v_L
        c1 = (dv * t / 2.0 - dr) * 12.0 / t**3
        c0 = dv / t - c1 * t / 2.0
        return c0, c1, np.zeros_like(c0)


class NotALaw:
    """Has update() but is not a GuidanceLaw."""

    def update(self, nav, target):
        return None


class HalfALaw(GuidanceLaw):
    """Forgets coeffs."""

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        return np.zeros(3)


# --------------------------------------------------------------------------- a controller plug-in
from gnc.control import Controller  # noqa: E402


class BandwidthOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    attitude_bandwidth_radps: float = Field(3.0, gt=0.0, le=10.0)


class RetunedController(Controller):
    """The built-in controller with its attitude bandwidth taken from [control.options]."""

    Options = BandwidthOptions

    def __init__(self, cfg=None, vehicle=None):
        super().__init__(cfg, vehicle)
        self.cfg = self.cfg.model_copy(update={"attitude_bandwidth_radps": self.options.attitude_bandwidth_radps})
