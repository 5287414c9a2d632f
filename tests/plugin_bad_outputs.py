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


class RaisingLaw(NanLateLaw):
    """Raises inside accel_L 25 s before the gate (a bug in the user's code)."""

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):
        if np.ndim(t_go_s) == 0 and t_go_s < 25.0:
            return np.zeros(3) + 1.0 / (float(t_go_s) - float(t_go_s))  # ZeroDivisionError
        return super().accel_L(r_L, v_L, r_f_L, v_f_L, t_go_s)


class TorqueListController(Controller):
    """Returns its torque as a list of three floats (the bench takes it as an array)."""

    def update(self, nav, cmd, contact=None):
        act = super().update(nav, cmd, contact)
        return type(act)(act.thrust_N, act.torque_B_Nm.tolist(), act.engine_on, act.t_ns, act.q_LB_cmd)


class StringTgoLaw(NanLateLaw):
    """Returns its time to go as text."""

    def update(self, nav, target):
        cmd = super().update(nav, target)
        return type(cmd)(cmd.t_ns, cmd.a_cmd_L, cmd.phase, "soon", cmd.saturated, cmd.valid)


class InitRaisingController(Controller):
    """Its constructor raises (a bug in the user's code)."""

    def __init__(self, cfg=None, vehicle=None):
        super().__init__(cfg, vehicle)
        self.gains = {}["kp"]
