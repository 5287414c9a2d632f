"""Plug-ins whose output a vehicle cannot fly, for tests/test_plugins.py (``guidance.law = "plugin_bad_outputs:..."``).

Kept apart from plugin_laws.py, whose error messages list the laws there.
"""

from __future__ import annotations

import numpy as np

from gnc.control import Controller
from gnc.guidance import GuidanceLaw
from plugin_laws import ScaledZemZev


class NanLateLaw(ScaledZemZev):
    """Flies as ScaledZemZev until 25 s before the gate, then returns NaN (a division gone wrong)."""

    Options = None

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        zem = r_f_L - (r_L + v_L * t_go_s + 0.5 * self.g_L * t_go_s * t_go_s)
        zev = v_f_L - (v_L + self.g_L * t_go_s)
        a = 6.0 * zem / (t_go_s * t_go_s) - 2.0 * zev / t_go_s + self.g_L
        return np.where(np.asarray(t_go_s)[..., None] < 25.0, np.nan, a)


class TwoAxisLaw(ScaledZemZev):
    """Returns a 2-vector (the horizontal command only)."""

    Options = None

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        return np.zeros(2)


class TupleLaw(GuidanceLaw):
    """Overrides update and returns a tuple instead of a GuidanceCommand."""

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        return np.zeros(3)

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        z = np.zeros(3)
        return z, z, z

    def update(self, nav, target):
        return (0.0, 0.0, 1.62)


class NanTorqueController(Controller):
    """The built-in controller, but its torque turns NaN after 2 s."""

    def update(self, nav, cmd, contact=None):
        act = super().update(nav, cmd, contact)
        if nav.t_ns > 2_000_000_000:
            act.torque_B_Nm[:] = np.nan
        return act
