"""Powered-descent guidance: from the navigated state to a commanded acceleration.

Ports (every law behind :class:`GuidanceLaw`):
    Inputs: :class:`gnc.navstate.NavState` (``t_ns``, ``r_BL_L``, ``v_BL_L``,
        ``mass_kg``) and a :class:`LandingTarget` (landing site in L).
    Output: :class:`GuidanceCommand`: the commanded acceleration ``a_cmd_L``,
        the phase name and the time to go.
    Rate: the control rate (default 50 Hz), once per control period, before
        :mod:`gnc.control`. A law is stateful (phase latch and planned gate
        time); call :meth:`GuidanceLaw.reset` before a new descent.

Acceleration convention: ``a_cmd_L`` (3,) [m/s^2] is the desired *total*
acceleration of the vehicle in L, gravity included, i.e. the desired
``d v_BL_L / dt``. The controller turns it into the thrust vector
``F_L = m (a_cmd_L - g_L)``; ``a_cmd_L - g_L`` is the specific force (the
non-gravitational acceleration) the engine must produce.

Phases:
    ``approach``: a polynomial law takes the vehicle from hand-over to the gate,
        ``gate_altitude_m`` above the target, arriving with the gate velocity
        (straight down at ``terminal_descent_rate_mps``). The law is a feedback
        until ``open_loop_t_go_s`` before the gate; from there its feedback gains
        (growing as ``1/t_go^2``) are too high to use, so the rest of its path
        is flown open loop: the polynomial (:meth:`GuidanceLaw.coeffs`) evaluated
        once from the state at that moment. Two laws:

        * ``apollo``: Apollo lunar-descent (E-guidance) quadratic-acceleration
          polynomial (Klumpp 1974) that meets the gate position, velocity and
          acceleration (zero total acceleration at the gate, i.e. hover-like
          thrust, so the hand-off to the terminal phase is smooth)::

              a = a_f - 6 (v_f + v) / t_go + 12 (r_f - r) / t_go^2

        * ``zem_zev``: zero-effort-miss / zero-effort-velocity optimal feedback
          (energy-optimal for the double integrator in uniform gravity, free
          final acceleration; Ebrahimi et al. 2008, Guo et al. 2013)::

              ZEM = r_f - (r + v t_go + g t_go^2 / 2),  ZEV = v_f - (v + g t_go)
              a - g = 6 ZEM / t_go^2 - 2 ZEV / t_go

    ``terminal``: starts at the gate (``t_go`` reaches zero), or earlier if the
        vehicle sinks ``GATE_FLOOR_M`` below the gate altitude. Constant-rate
        vertical descent at ``terminal_descent_rate_mps`` until touchdown (the
        controller cuts the engine on leg contact), while a PD law nulls the
        horizontal velocity and holds over the target. If the gate was missed
        by more than ``terminal_hold_radius_m`` the descent rate blends to a
        hover (zero at twice that distance) while the vehicle translates back
        over the target at up to ``terminal_speed_max_mps``. That fly-out burns
        hover propellant: the flight software calls a **bingo** when what its
        gauge says is left, less ``terminal_reserve_kg``, would no longer cover
        the descent from where the vehicle is, and the law then lands there
        (:meth:`GuidanceLaw.land_here`) rather than run dry in the air: once its
        horizontal speed is nulled, down at up to ``bingo_descent_rate_mps``,
        slowing at 0.2 m/s^2 to the terminal rate 5 m above the ground.

Time to go (both laws): a fixed final time, planned and re-planned only when
needed. At the first call (and after a target change, or new limits from
:meth:`GuidanceLaw.set_limits` when the engine turns out weaker) the law scans candidate
``t_go`` in ``[t_go_min_s, t_go_max_s]``; for each, the law's own polynomial
trajectory to the gate is evaluated in closed form and checked against the
limits *along the whole path*: thrust within ``[plan_thrust_min_frac *
thrust_min_N, plan_thrust_max_frac * thrust_max_N]`` at the current mass, tilt
within ``plan_tilt_frac`` times the altitude-dependent tilt limit at every
point, and no dip of more than ``GATE_UNDERSHOOT_TOL_M`` below the gate
before the gate; and the vehicle must be able to turn its thrust axis onto the
path's first thrust direction in time: the rest-to-rest slew at the attitude
control's angular acceleration (``limits.slew_accel_max_radps2``),
``2 sqrt(angle / accel)``, within ``plan_slew_time_frac`` of the path's time to
go. Without that check a late re-plan (a hazard divert at 100 m) could pick a
9 s path whose first thrust direction lay 20 degrees from the attitude flown:
the torque-limited attitude loop took 2-3 s to get there, the feedback then
asked for more, and the vehicle reached the gate 14 m past the new site at
4 m/s, too far to fly back before the propellant ran out. Among the feasible
ones the least delta-v (``integral |a - g| dt``, a fuel proxy) is chosen; when
none is feasible, the least tilt-violating path within the thrust and altitude
limits, whatever its slew (capping then enforces the tilt at
the price of a small miss at the gate, which the terminal phase flies out),
else the least violating one. Then ``t_go = t_final - t`` counts down. For
both laws the remaining path from a point on the planned path is the rest of
the same path, so a tracked plan stays valid; if disturbances make the
remaining path violate the hard limits (margins dropped: a hysteresis), a new
plan is searched at most once per ``REPLAN_MIN_INTERVAL_NS`` while more than
``REPLAN_MIN_T_GO_S`` remain, and adopted if it violates less. The open-loop
end of the approach flies the same polynomial, so the planner's checks cover
the whole path that is flown; the phase switches to terminal when ``t_go``
reaches zero, i.e. at the gate, or ``GATE_FLOOR_M`` below the gate altitude.

ZEM/ZEV leaves the acceleration at the gate free: its path may still be
braking hard when it reaches the gate (default scenario: 1.2 m/s^2 upward,
thrust 1.75 times the lunar weight), where Apollo's ends at zero total
acceleration. Both reach the gate at the gate velocity, so the terminal phase
starts at the gate rate (to within the navigation and attitude-tracking
errors); for ZEM/ZEV the thrust then steps down to the terminal law's command
(about hover). Switching to terminal at ``t_go = 2 s`` while still on the
feedback, as this module used to, handed ZEM/ZEV over up to 4 m above the gate
at up to 4 times the gate rate (default scenario: 3.1 m/s at 34 m; its last
2 s of path would have taken off the other 2.3 m/s). With the default tilt
schedule, ZEM/ZEV has no feasible path for a few per cent of extreme
hand-overs (moving away from the target at ~10 m/s while sinking at ~20 m/s)
and flies the least-violating one.

Limits: whatever the law asks, the output is capped to what the engine can
deliver: the vertical specific force is kept within ``[thrust_min_N,
thrust_max_N] / m`` (vertical first), then the horizontal part is cut to the
tilt limit and to the thrust left over.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gnc.config import validate_options, validated_config
from gnc.navstate import NavState
from gnc.numeric import clip_float, norm
from gnc.plugins import build_law, check_law_vector
from gnc.quat import body_z_L, unit_quaternion

NS_PER_S = 1_000_000_000
LUNAR_GRAVITY_MPS2 = 1.62

PHASE_APPROACH = "approach"
PHASE_OFF = "off"
PHASE_TERMINAL = "terminal"
Phase = Literal["approach", "terminal"]

# Planning grid: candidate t_go spacing [s] and samples along each candidate path.
T_GO_GRID_STEP_S = 0.5
PLAN_SAMPLES = 41
# Re-plan an infeasible remaining path only while at least this much time remains [s],
# at most once per REPLAN_MIN_INTERVAL_NS, and only for a less violating path.
REPLAN_MIN_T_GO_S = 8.0
REPLAN_MIN_INTERVAL_NS = 1_000_000_000
# A planned path may dip this far below the gate altitude before reaching the gate [m];
# the terminal phase starts early if the vehicle sinks GATE_FLOOR_M below the gate.
GATE_UNDERSHOOT_TOL_M = 1.0
GATE_FLOOR_M = 2.0 * GATE_UNDERSHOOT_TOL_M
# Apollo's targeted total acceleration at the gate (zero: hover-like hand-off) [m/s^2].
APOLLO_GATE_ACCEL_L = np.zeros(3)
# A bingo descent (GuidanceLaw.land_here) slows at this rate to the terminal rate, which it reaches this high
# above the ground it was given (the body origin's height) [m/s^2, m].
BINGO_BRAKE_MPS2 = 0.2
BINGO_PAD_M = 5.0
# A bingo descends faster than the terminal rate only once the fly-out's horizontal speed is nulled: fully below
# the first speed, not at all above the second (the low tilt limit brakes slowly near the ground) [m/s].
BINGO_VH_FULL_MPS, BINGO_VH_NONE_MPS = 0.3, 0.5
# Denominators below this are treated as zero.
_EPS = 1e-9
_PLAN_SIGMA = np.linspace(0.0, 1.0, PLAN_SAMPLES)  # the sampled fractions of a path's time to go
_ONE_DEG_RAD = float(np.deg2rad(1.0))


# --------------------------------------------------------------------------- configuration
def guidance_inputs(nav: NavState, target: LandingTarget
                    ) -> tuple[int, np.ndarray | None, np.ndarray, np.ndarray, float]:
    """A guidance step's inputs: ``(t_ns, target_L, r_BL_L, v_BL_L, mass_kg)`` as arrays and floats.

    ``target_L`` is None when they are unusable (a non-finite position, velocity or target, or a
    mass that is not a finite positive number): the step then returns an invalid command.
    """
    t_ns = int(nav.t_ns)
    target_L = np.asarray(target.r_L, float)
    r = np.asarray(nav.r_BL_L, float)
    v = np.asarray(nav.v_BL_L, float)
    m = float(nav.mass_kg)
    # The arrays' own all(): NumPy's np.all wrapper costs more than the test, every control tick.
    usable = np.isfinite(r).all() and np.isfinite(v).all() and np.isfinite(target_L).all()
    if not (usable and np.isfinite(m) and m > 0.0):
        return t_ns, None, r, v, m
    return t_ns, target_L, r, v, m


class TiltLimitConfig(BaseModel):
    """Maximum tilt of the thrust axis from vertical, tightening near the ground.

    The limit is ``tilt_max_touchdown_deg`` at zero altitude, grows linearly
    with altitude and reaches ``tilt_max_high_deg`` at ``taper_altitude_m``;
    above that it is constant. Altitude is the height above the landing-frame
    origin (the target), ``r_BL_L[2]``. Shared by guidance (planning, capping)
    and control (attitude command).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    tilt_max_high_deg: float = Field(30.0, gt=0.0, lt=80.0, description="tilt limit above taper_altitude_m [deg]")
    tilt_max_touchdown_deg: float = Field(5.0, ge=0.0, lt=80.0, description="tilt limit at zero altitude [deg]")
    taper_altitude_m: float = Field(100.0, gt=0.0, description="altitude where the limit reaches its high value [m]")

    @model_validator(mode="after")
    def _touchdown_below_high(self) -> "TiltLimitConfig":
        if self.tilt_max_touchdown_deg > self.tilt_max_high_deg:
            raise ValueError(
                f"tilt_max_touchdown_deg = {self.tilt_max_touchdown_deg} exceeds tilt_max_high_deg = "
                f"{self.tilt_max_high_deg}; allowed: tilt_max_touchdown_deg <= tilt_max_high_deg"
            )
        return self

    def tilt_max_rad(self, altitude_m: float | np.ndarray) -> float | np.ndarray:
        """Tilt limit at an altitude.

        Args:
            altitude_m: Height above the target, scalar or any shape [m].

        Returns:
            Limit of the same shape [rad].
        """
        if isinstance(altitude_m, float):  # one altitude (every control tick): the same operations on floats
            frac_1 = clip_float(altitude_m / self.taper_altitude_m, 0.0, 1.0)
            return math.radians(self.tilt_max_touchdown_deg
                                + (self.tilt_max_high_deg - self.tilt_max_touchdown_deg) * frac_1)
        frac = np.clip(np.asarray(altitude_m, float) / self.taper_altitude_m, 0.0, 1.0)
        deg = self.tilt_max_touchdown_deg + (self.tilt_max_high_deg - self.tilt_max_touchdown_deg) * frac
        out = np.deg2rad(deg)
        return float(out) if out.ndim == 0 else out


class GuidanceConfig(BaseModel):
    """Guidance law selection and tuning."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    law: str = Field(
        "zem_zev",
        description="approach-phase guidance law: apollo, zem_zev, gfold (fuel-optimal, needs landbench[opt]), "
                    "'off' (free fall, failure studies), or a plug-in 'package.module:ClassName'",
    )
    options: dict[str, Any] = Field(
        default_factory=dict,
        description="the law's own options, validated by its Options model (plug-ins and gfold; empty otherwise)",
    )
    gate_altitude_m: float = Field(30.0, gt=0.0, description="gate height above the target [m]")
    terminal_descent_rate_mps: float = Field(
        0.8, gt=0.0, le=5.0, description="gate and terminal-phase vertical descent speed [m/s]"
    )
    gravity_mps2: float = Field(LUNAR_GRAVITY_MPS2, gt=0.0, description="surface gravity magnitude [m/s^2]")
    t_go_min_s: float = Field(5.0, gt=0.0, description="shortest approach time considered by the planner [s]")
    t_go_max_s: float = Field(300.0, gt=0.0, description="longest approach time considered by the planner [s]")
    open_loop_t_go_s: float = Field(
        2.0,
        gt=0.0,
        description="fly the rest of the approach path open loop once the time to the gate falls to this [s]",
    )
    plan_thrust_max_frac: float = Field(
        0.8, gt=0.0, le=1.0, description="fraction of the maximum thrust a planned path may use [-]"
    )
    plan_thrust_min_frac: float = Field(
        1.1, ge=1.0, le=3.0, description="planned paths keep thrust above this multiple of the minimum [-]"
    )
    plan_tilt_frac: float = Field(0.9, gt=0.0, le=1.0, description="fraction of the tilt limit a planned path may use [-]")
    plan_slew_time_frac: float = Field(
        0.15, gt=0.0, le=1.0,
        description="a planned path's first thrust direction must be reachable from the current thrust axis by a "
                    "rest-to-rest slew at the attitude control's angular acceleration within this fraction of the "
                    "path's time to go [-]",
    )
    terminal_position_bandwidth_radps: float = Field(
        0.5, gt=0.0, le=5.0, description="terminal horizontal position-hold natural frequency [rad/s]"
    )
    terminal_damping_ratio: float = Field(1.0, gt=0.0, le=3.0, description="terminal horizontal damping ratio [-]")
    terminal_speed_max_mps: float = Field(
        2.0, gt=0.0, le=10.0, description="largest horizontal speed the terminal phase commands [m/s]"
    )
    terminal_hold_radius_m: float = Field(
        3.0, gt=0.0, description="full-rate descent within this horizontal distance of the target; hover beyond twice it [m]"
    )
    terminal_rate_gain_per_s: float = Field(
        1.0, gt=0.0, le=10.0, description="terminal vertical-rate loop gain [1/s]"
    )
    terminal_bingo: bool = Field(
        True,
        description="propellant bingo: while the terminal phase flies out a missed gate (hovering more than "
                    "twice terminal_hold_radius_m from the target), the flight software lands where the "
                    "vehicle is once its propellant gauge less terminal_reserve_kg no longer covers a descent "
                    "from its height (bingo_descent_rate_mps); false: fly out whatever is left",
    )
    terminal_reserve_kg: float = Field(
        18.0, ge=0.0,
        description="propellant the bingo keeps beyond that descent's need, for the gauge's error (the loaded "
                    "mass is not measured on board: 18 kg is 15 % of the default load) [kg]",
    )
    bingo_descent_rate_mps: float = Field(
        2.0, gt=0.0, le=5.0,
        description="a bingo's descent: at most this fast, slowing at 0.2 m/s^2 to terminal_descent_rate_mps, "
                    "which it keeps for its last 5 m above the ground (the body origin's height), once the "
                    "horizontal speed is below 0.3 m/s [m/s]",
    )

    @field_validator("law")
    @classmethod
    def _law_resolves(cls, law: str) -> str:
        guidance_class(law)  # raises a one-line ValueError: unknown name, bad import path, missing class, interface
        return law

    @field_validator("options")
    @classmethod
    def _options_valid(cls, options: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        law = info.data.get("law")
        if law is None:  # the law itself was refused; that error is reported
            return options
        validate_law_options(guidance_class(law), law, options)
        return options

    @model_validator(mode="after")
    def _t_go_bounds(self) -> "GuidanceConfig":
        if not self.open_loop_t_go_s < self.t_go_min_s < self.t_go_max_s:
            raise ValueError(
                f"open_loop_t_go_s = {self.open_loop_t_go_s}, t_go_min_s = {self.t_go_min_s}, "
                f"t_go_max_s = {self.t_go_max_s}; allowed: open_loop_t_go_s < t_go_min_s < t_go_max_s"
            )
        return self

    def g_L(self) -> np.ndarray:
        """Gravity in L, (3,) [m/s^2]."""
        return np.array([0.0, 0.0, -self.gravity_mps2])


@dataclass(frozen=True, slots=True)
class GuidanceLimits:
    """What the vehicle can do, as guidance plans with it (defaults: the default lander).

    Attributes:
        thrust_min_N: Minimum thrust of the lit engine [N].
        thrust_max_N: Maximum thrust [N].
        tilt: Altitude-dependent tilt limit (the controller's, see
            :func:`gnc.control.guidance_limits`).
        isp_s: Engine specific impulse as the flight software knows it [s], for
            laws that model the mass flow (G-FOLD); None when not given.
        slew_accel_max_radps2: The largest angular acceleration the attitude
            control can give the thrust axis (RCS torque over the lateral
            inertia) [rad/s^2], for the planner's slew check; None: no check.
    """

    thrust_min_N: float = 1500.0
    thrust_max_N: float = 7500.0
    tilt: TiltLimitConfig = field(default_factory=TiltLimitConfig)
    isp_s: float | None = None
    slew_accel_max_radps2: float | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.thrust_max_N) and self.thrust_max_N > 0.0):
            raise ValueError(f"limits.thrust_max_N = {self.thrust_max_N!r}; allowed: a finite value > 0")
        if not (np.isfinite(self.thrust_min_N) and 0.0 <= self.thrust_min_N < self.thrust_max_N):
            raise ValueError(
                f"limits.thrust_min_N = {self.thrust_min_N!r}; allowed: 0 <= thrust_min_N < thrust_max_N = {self.thrust_max_N}"
            )
        if self.isp_s is not None and not (np.isfinite(self.isp_s) and self.isp_s > 0.0):
            raise ValueError(f"limits.isp_s = {self.isp_s!r}; allowed: a finite value > 0, or None")
        a = self.slew_accel_max_radps2
        if a is not None and not (np.isfinite(a) and a > 0.0):
            raise ValueError(f"limits.slew_accel_max_radps2 = {a!r}; allowed: a finite value > 0, or None")
        if not isinstance(self.tilt, TiltLimitConfig):
            raise ValueError(f"limits.tilt = {self.tilt!r}; allowed: a TiltLimitConfig")


@dataclass(frozen=True, slots=True)
class LandingTarget:
    """The landing site.

    Attributes:
        r_L: Landing site on the surface, in L, (3,) [m]; the L origin by default.
    """

    r_L: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, slots=True)
class GuidanceCommand:
    """Guidance output for one control period.

    Attributes:
        t_ns: Time of validity (the navigation state's) [ns].
        a_cmd_L: Commanded total acceleration (gravity included), in L, (3,) [m/s^2].
        phase: ``"approach"`` or ``"terminal"``.
        t_go_s: Approach: time to the gate [s]. Terminal: height above the
            target divided by the descent rate, an upper bound on the time to
            touchdown [s].
        saturated: True when the law's acceleration was cut to the thrust or tilt limits.
        valid: False when the navigation state was not usable (non-finite
            position, velocity or target, or a non-finite or non-positive
            mass); ``a_cmd_L`` is then zero and the controller keeps its last
            good command.
    """

    t_ns: int
    a_cmd_L: np.ndarray
    phase: str
    t_go_s: float
    saturated: bool = False
    valid: bool = True


# --------------------------------------------------------------------------- the law formulas
def zem_zev_accel_L(
    r_L: np.ndarray, v_L: np.ndarray, r_f_L: np.ndarray, v_f_L: np.ndarray, t_go_s: float | np.ndarray, g_L: np.ndarray
) -> np.ndarray:
    """ZEM/ZEV optimal feedback, as a total acceleration.

    Args:
        r_L: Position, (..., 3) [m].
        v_L: Velocity, (..., 3) [m/s].
        r_f_L: Target position, (3,) or (..., 3) [m].
        v_f_L: Target velocity, (3,) or (..., 3) [m/s].
        t_go_s: Time to go, scalar or (..., 1) [s], > 0.
        g_L: Gravity, (3,) [m/s^2].

    Returns:
        Total acceleration ``6 ZEM/t^2 - 2 ZEV/t + g``, (..., 3) [m/s^2].
    """
    t = t_go_s
    zem = r_f_L - (r_L + v_L * t + 0.5 * g_L * t * t)
    zev = v_f_L - (v_L + g_L * t)
    return 6.0 * zem / (t * t) - 2.0 * zev / t + g_L


def apollo_accel_L(
    r_L: np.ndarray,
    v_L: np.ndarray,
    r_f_L: np.ndarray,
    v_f_L: np.ndarray,
    a_f_L: np.ndarray,
    t_go_s: float | np.ndarray,
) -> np.ndarray:
    """Apollo E-guidance (quadratic acceleration polynomial), as a total acceleration.

    Args:
        r_L: Position, (..., 3) [m].
        v_L: Velocity, (..., 3) [m/s].
        r_f_L: Target position, (3,) or (..., 3) [m].
        v_f_L: Target velocity, (3,) or (..., 3) [m/s].
        a_f_L: Target total acceleration, (3,) [m/s^2].
        t_go_s: Time to go, scalar or (..., 1) [s], > 0.

    Returns:
        ``a_f - 6 (v_f + v)/t + 12 (r_f - r)/t^2``, (..., 3) [m/s^2].
    """
    t = t_go_s
    return a_f_L - 6.0 * (v_f_L + v_L) / t + 12.0 * (r_f_L - r_L) / (t * t)


def zem_zev_coeffs(
    r_L: np.ndarray, v_L: np.ndarray, r_f_L: np.ndarray, v_f_L: np.ndarray, t_go_s: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ZEM/ZEV open-loop path: total acceleration ``c0 + c1 s + c2 s^2`` (``c2 = 0``).

    ``s`` is the time elapsed from now. Same shapes as :func:`zem_zev_accel_L`;
    gravity cancels out of the total acceleration.

    Returns:
        ``(c0, c1, c2)``, each (..., 3) [m/s^2, m/s^3, m/s^4].
    """
    t = t_go_s
    dr = r_f_L - r_L - v_L * t
    dv = v_f_L - v_L
    c0 = 6.0 * dr / (t * t) - 2.0 * dv / t
    c1 = (6.0 * dv / t - 12.0 * dr / (t * t)) / t
    return c0, c1, np.zeros_like(c0)


def apollo_coeffs(
    r_L: np.ndarray, v_L: np.ndarray, r_f_L: np.ndarray, v_f_L: np.ndarray, a_f_L: np.ndarray, t_go_s: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Apollo open-loop path: total acceleration ``c0 + c1 s + c2 s^2``.

    Solves ``a(T) = a_f``, ``v(T) = v_f``, ``r(T) = r_f`` for the quadratic;
    same shapes as :func:`apollo_accel_L`.

    Returns:
        ``(c0, c1, c2)``, each (..., 3) [m/s^2, m/s^3, m/s^4].
    """
    t = t_go_s
    dr = r_f_L - r_L - v_L * t
    dv = v_f_L - v_L
    c0 = a_f_L + 12.0 * dr / (t * t) - 6.0 * dv / t
    c2_t2 = 3.0 * c0 + 3.0 * a_f_L - 6.0 * dv / t  # c2 * t^2
    c1 = (a_f_L - c0 - c2_t2) / t
    return c0, c1, c2_t2 / (t * t)


def cap_acceleration_L(
    a_cmd_L: np.ndarray, g_L: np.ndarray, mass_kg: float, limits: GuidanceLimits, altitude_m: float
) -> tuple[np.ndarray, bool]:
    """Cut a commanded total acceleration to what thrust and tilt allow.

    The vertical specific force is clamped to ``[thrust_min_N, thrust_max_N] /
    m`` first; the horizontal part is then cut to ``tan(tilt_max) * f_z`` and to
    the thrust left over (``sqrt(f_max^2 - f_z^2)``), keeping its direction.

    Args:
        a_cmd_L: Commanded total acceleration, (3,) [m/s^2].
        g_L: Gravity, (3,) [m/s^2].
        mass_kg: Vehicle mass [kg], > 0.
        limits: Thrust and tilt limits.
        altitude_m: Height above the target, for the tilt limit [m].

    Returns:
        ``(a_L, saturated)``: the capped total acceleration (3,) [m/s^2] and
        whether anything was cut.
    """
    f = np.asarray(a_cmd_L, float) - g_L
    f_max = limits.thrust_max_N / mass_kg
    f_min = limits.thrust_min_N / mass_kg
    fz = clip_float(float(f[2]), f_min, f_max)
    fh = f[:2].copy()
    fh_norm = norm(fh)
    fh_max = min(np.tan(limits.tilt.tilt_max_rad(altitude_m)) * fz, np.sqrt(max(f_max * f_max - fz * fz, 0.0)))
    if fh_norm > fh_max:
        fh *= fh_max / fh_norm
    out = np.array([fh[0], fh[1], fz]) + g_L
    saturated = bool(fz != f[2] or fh_norm > fh_max)
    return out, saturated


def _thrust_axis_L(q_LB: Any) -> np.ndarray | None:
    """Body +z (the thrust axis) in L from a (w, x, y, z) attitude, (3,) unit; None when it is not a usable quaternion."""
    q = unit_quaternion(q_LB)
    return None if q is None else body_z_L(q)


# --------------------------------------------------------------------------- the interface
class GuidanceLaw(ABC):
    """A guidance law: ``update(NavState, LandingTarget) -> GuidanceCommand``.

    Ports:
        Inputs: navigation state (position, velocity, mass, time) and the
            landing target.
        Output: :class:`GuidanceCommand` (total acceleration in L, phase, t_go).
        Rate: control rate (default 50 Hz). Stateful: the phase latches from
            approach to terminal, the planned gate time persists, and so does
            the open-loop end of the path once it has started.

    Subclasses provide the approach-phase formula (:meth:`accel_L`) and its
    open-loop polynomial (:meth:`coeffs`), which the planner evaluates; a law
    may instead override :meth:`update` altogether (as G-FOLD does). This is
    also the plug-in interface (``guidance.law = "package.module:ClassName"``,
    README "Controller design studies"): a plug-in subclasses this class,
    implements every abstract method, and may declare ``Options``, a pydantic
    model of its ``[guidance.options]`` table; the validated options are
    ``self.options`` (None when the class declares no ``Options``).
    """

    name: ClassVar[str]
    Options: ClassVar[type[BaseModel] | None] = None

    def __init__(self, cfg: GuidanceConfig, limits: GuidanceLimits):
        self.cfg = cfg
        self.limits = limits
        self.options: BaseModel | None = validate_law_options(type(self), cfg.law, cfg.options)
        self.g_L = cfg.g_L()
        self.n_plans = 0  # plans adopted since construction (telemetry)
        self.reset()

    def reset(self) -> None:
        """Forget the phase and the plan (start of a new descent)."""
        self.phase: str = PHASE_APPROACH
        self.t_final_ns: int | None = None
        self.plan_feasible = False
        self._t_plan_ns = 0
        self._target_L: np.ndarray | None = None
        # Open-loop end of the approach: (start time [ns], (c0, c1, c2)), once started.
        self._open_loop: tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        # Once the target was given up (:meth:`land_here`, a bingo): the ground's elevation under the vehicle [m]
        # and, once the horizontal speed was nulled, the point the terminal phase holds over (2,) [m], in L.
        self.bingo = False
        self.bingo_ground_z_L = 0.0
        self.hold_xy_L: np.ndarray | None = None

    def land_here(self, ground_z_L: float) -> None:
        """Give up the target (a propellant bingo, :class:`gnc.flight.FlightSoftware`): the terminal phase nulls
        the horizontal speed, then holds where the vehicle is when it falls below ``BINGO_VH_FULL_MPS``, and
        descends to the ground at ``ground_z_L`` [m] (L; the caller may update :attr:`bingo_ground_z_L` as the
        vehicle goes, NaN: unknown) by :meth:`bingo_rate_mps`'s profile."""
        self.bingo = True
        self.bingo_ground_z_L = float(ground_z_L)

    def bingo_rate_mps(self, height_m: float) -> tuple[float, float]:
        """A bingo descent's vertical speed at ``height_m`` above the ground (the body origin's) [m/s], and the
        deceleration it is slowing at there [m/s^2]: ``min(bingo_descent_rate_mps, sqrt(v_t^2 + 2 a (h - pad)))``,
        ``v_t`` the terminal rate, ``a`` = ``BINGO_BRAKE_MPS2``, ``pad`` = ``BINGO_PAD_M`` (``v_t`` below it, and for
        a NaN height: the ground unknown)."""
        v_t, v_max = self.cfg.terminal_descent_rate_mps, max(self.cfg.bingo_descent_rate_mps,
                                                             self.cfg.terminal_descent_rate_mps)
        above = height_m - BINGO_PAD_M
        if not above > 0.0:  # also NaN: the ground unknown, the terminal rate
            return v_t, 0.0
        v = math.sqrt(v_t * v_t + 2.0 * BINGO_BRAKE_MPS2 * above)
        return (v_max, 0.0) if v >= v_max else (v, BINGO_BRAKE_MPS2)

    def set_limits(self, limits: GuidanceLimits) -> None:
        """New limits to plan within (the flight software found the engine delivers less than commanded and
        recalibrated it): the approach is planned again from the next step, as for a moved target."""
        if not isinstance(limits, GuidanceLimits):
            raise ValueError(f"limits must be a GuidanceLimits, got {type(limits).__name__}")
        self.limits = limits
        if self.phase == PHASE_APPROACH:
            self.t_final_ns = None

    # -- the law
    @abstractmethod
    def accel_L(
        self, r_L: np.ndarray, v_L: np.ndarray, r_f_L: np.ndarray, v_f_L: np.ndarray, t_go_s: float | np.ndarray
    ) -> np.ndarray:
        """Approach-phase total acceleration toward ``(r_f, v_f)`` in ``t_go``, (..., 3) [m/s^2]."""

    @abstractmethod
    def coeffs(
        self, r_L: np.ndarray, v_L: np.ndarray, r_f_L: np.ndarray, v_f_L: np.ndarray, t_go_s: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Open-loop path of the law: total acceleration ``c0 + c1 s + c2 s^2``, each (..., 3)."""

    # -- geometry
    def gate_L(self, target: LandingTarget) -> tuple[np.ndarray, np.ndarray]:
        """Gate position and velocity for a target, each (3,) [m], [m/s]."""
        r_f = np.asarray(target.r_L, float) + np.array([0.0, 0.0, self.cfg.gate_altitude_m])
        v_f = np.array([0.0, 0.0, -self.cfg.terminal_descent_rate_mps])
        return r_f, v_f

    # -- planning
    def path_violation(
        self,
        r_L: np.ndarray,
        v_L: np.ndarray,
        mass_kg: float,
        r_f_L: np.ndarray,
        v_f_L: np.ndarray,
        t_go_s: np.ndarray,
        with_margins: bool,
        z_B_L: np.ndarray | None = None,
        want_delta_v: bool = True,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Check the law's paths to the gate for several candidate times to go.

        Args:
            r_L: Position, (3,) [m].
            v_L: Velocity, (3,) [m/s].
            mass_kg: Mass [kg].
            r_f_L: Gate position, (3,) [m].
            v_f_L: Gate velocity, (3,) [m/s].
            t_go_s: Candidate times to go, (N,) [s].
            with_margins: Apply the planning margins (``plan_*_frac``); False
                checks the hard limits.
            z_B_L: The current thrust axis (body +z in L), (3,) unit, for the
                slew check; None (or no ``limits.slew_accel_max_radps2``): no
                slew check.
            want_delta_v: Compute the paths' delta-v (False: None is returned
                for it; the re-plan check reads only the violations).

        Returns:
            ``(violation, delta_v)``: the worst normalised violation along each
            path of the thrust, tilt and gate-altitude limits and of the slew
            to its first thrust direction, (N, 4) [-] (all <= 0: feasible), and
            each path's ``integral |a - g| dt``, (N,) [m/s]. The slew is a
            planning margin: the rest-to-rest slew time ``2 sqrt(angle /
            slew_accel_max)`` from ``z_B_L`` to the path's first thrust
            direction over ``plan_slew_time_frac`` times its time to go, minus
            1; without margins (the hard limits) it is never violated (-1).
        """
        cfg, lim = self.cfg, self.limits
        T = np.asarray(t_go_s, float)[:, None]  # (N, 1)
        c0, c1, c2 = self.coeffs(r_L[None, :], v_L[None, :], r_f_L[None, :], v_f_L[None, :], T)  # (N, 3)
        s = T * _PLAN_SIGMA  # (N, M) [s]
        # Per axis on (N, M) arrays, each operation as the (N, M, 3) expression in the comment above it
        # (the same products and sums in the same order, so the same bits: tested against it).
        # a = c0 + c1 s + c2 s s;  f = a - g   (the specific force along the path)
        g_x, g_y, g_z = self.g_L.tolist()
        f_x = c0[:, 0:1] + c1[:, 0:1] * s + c2[:, 0:1] * s * s - g_x
        f_y = c0[:, 1:2] + c1[:, 1:2] * s + c2[:, 1:2] * s * s - g_y
        f_z = c0[:, 2:3] + c1[:, 2:3] * s + c2[:, 2:3] * s * s - g_z
        z = (
            r_L[2] + v_L[2] * s + c0[:, 2:3] * s ** 2 / 2.0
            + c1[:, 2:3] * s ** 3 / 6.0 + c2[:, 2:3] * s ** 4 / 12.0
        )  # (N, M)
        h2 = f_x * f_x + f_y * f_y  # np.linalg.norm(f, axis=-1)**2 sums x, y, z in this order
        f_norm = np.sqrt(h2 + f_z * f_z)
        max_frac = cfg.plan_thrust_max_frac if with_margins else 1.0
        min_frac = cfg.plan_thrust_min_frac if with_margins else 1.0
        tilt_frac = cfg.plan_tilt_frac if with_margins else 1.0
        f_max = max_frac * lim.thrust_max_N / mass_kg
        f_min = min_frac * lim.thrust_min_N / mass_kg
        target_z = r_f_L[2] - cfg.gate_altitude_m
        tilt_lim = tilt_frac * np.asarray(lim.tilt.tilt_max_rad(z - target_z))
        tilt = np.arctan2(np.sqrt(h2), f_z)
        out = np.empty((T.shape[0], 4))
        out[:, 0] = np.maximum(f_norm / f_max - 1.0, 1.0 - f_norm / max(f_min, _EPS)).max(axis=1)
        out[:, 1] = ((tilt - tilt_lim) / np.maximum(tilt_lim, _ONE_DEG_RAD)).max(axis=1)
        out[:, 2] = ((r_f_L[2] - GATE_UNDERSHOOT_TOL_M - z) / GATE_UNDERSHOOT_TOL_M).max(axis=1)
        out[:, 3] = -1.0
        if with_margins and z_B_L is not None and lim.slew_accel_max_radps2 is not None:
            f0 = np.stack([f_x[:, 0], f_y[:, 0], f_z[:, 0]], axis=1)  # each path's first specific force
            cos = (f0 @ np.asarray(z_B_L, float)) / np.maximum(f_norm[:, 0], _EPS)
            angle = np.arccos(np.clip(cos, -1.0, 1.0))
            t_slew = 2.0 * np.sqrt(angle / lim.slew_accel_max_radps2)  # rest to rest, torque-limited
            out[:, 3] = t_slew / (cfg.plan_slew_time_frac * T[:, 0]) - 1.0
        if not want_delta_v:
            return out, None
        delta_v = np.trapezoid(f_norm, s, axis=1)
        return out, delta_v

    def plan_t_go(
        self, r_L: np.ndarray, v_L: np.ndarray, mass_kg: float, r_f_L: np.ndarray, v_f_L: np.ndarray,
        z_B_L: np.ndarray | None = None,
    ) -> tuple[float, float]:
        """Choose the time to the gate (see the module docstring).

        Args:
            r_L: Position, (3,) [m].
            v_L: Velocity, (3,) [m/s].
            mass_kg: Mass [kg].
            r_f_L: Gate position, (3,) [m].
            v_f_L: Gate velocity, (3,) [m/s].
            z_B_L: The current thrust axis, (3,) unit, for the slew check
                (:meth:`path_violation`); None: none.

        Returns:
            ``(t_go_s, violation)``: the least-delta-v candidate that is
            feasible with the planning margins (``violation <= 0``); when none
            is, the least tilt-violating one among those within the thrust and
            altitude limits (tilt is then enforced by capping, at the price of
            a small miss at the gate), else the least violating one.
        """
        cfg = self.cfg
        cand = np.arange(cfg.t_go_min_s, cfg.t_go_max_s + 0.5 * T_GO_GRID_STEP_S, T_GO_GRID_STEP_S)
        viol3, delta_v = self.path_violation(r_L, v_L, mass_kg, r_f_L, v_f_L, cand, with_margins=True, z_B_L=z_B_L)
        viol = viol3.max(axis=1)
        ok = viol <= 0.0
        if ok.any():
            i = int(np.argmin(np.where(ok, delta_v, np.inf)))
        elif (ok_thrust_alt := np.maximum(viol3[:, 0], viol3[:, 2]) <= 0.0).any():
            i = int(np.argmin(np.where(ok_thrust_alt, viol3[:, 1], np.inf)))
        else:
            i = int(np.argmin(viol))
        return float(cand[i]), float(viol[i])

    # -- the step
    def update(self, nav: NavState, target: LandingTarget) -> GuidanceCommand:
        """One guidance step.

        Args:
            nav: Navigation state.
            target: Landing target.

        Returns:
            The guidance command for this control period.
        """
        t_ns, target_L, r, v, m = guidance_inputs(nav, target)
        if target_L is None:  # attitude is not needed here
            return GuidanceCommand(t_ns, np.zeros(3), self.phase, float("nan"), saturated=False, valid=False)
        r_f, v_f = self.gate_L(target)
        # np.array_equal's test, by the arrays' own operations (every control tick; its wrapper costs more).
        last = self._target_L
        if last is None or last.shape != target_L.shape or not (last == target_L).all():
            self._target_L = target_L.copy()
            self.t_final_ns = None  # re-plan for the new target

        if self.phase == PHASE_APPROACH:
            if self.t_final_ns is None:
                self._plan(t_ns, r, v, m, r_f, v_f, _thrust_axis_L(nav.q_LB))
            t_go = (self.t_final_ns - t_ns) / NS_PER_S
            if t_go <= 0.0 or r[2] <= r_f[2] - GATE_FLOOR_M:
                self.phase = PHASE_TERMINAL
            elif t_go <= self.cfg.open_loop_t_go_s:
                a = self._open_loop_accel_L(t_ns, r, v, r_f, v_f, t_go)
                source = "coeffs (the open-loop path, evaluated)"
            else:
                if t_go > REPLAN_MIN_T_GO_S and t_ns - self._t_plan_ns >= REPLAN_MIN_INTERVAL_NS:
                    t_go = self._maybe_replan(t_ns, r, v, m, r_f, v_f, t_go, nav.q_LB)
                a = self.accel_L(r, v, r_f, v_f, t_go)
                source = "accel_L"
        if self.phase == PHASE_TERMINAL:
            a = self.terminal_accel_L(r, v, target_L)
            source = "terminal_accel_L"
            t_go = max(r[2] - target_L[2], 0.0) / self.cfg.terminal_descent_rate_mps
        # A law's output is checked before it is capped (a NaN would pass through the cap to the controller,
        # which holds its last good command: flown silently).
        check_law_vector(a, 3, "guidance.law", self.cfg.law, source, t_ns, "m/s^2")
        a_capped, saturated = cap_acceleration_L(a, self.g_L, m, self.limits, r[2] - target_L[2])
        return GuidanceCommand(t_ns, a_capped, self.phase, float(t_go), saturated=saturated, valid=True)

    def _open_loop_accel_L(
        self, t_ns: int, r: np.ndarray, v: np.ndarray, r_f: np.ndarray, v_f: np.ndarray, t_go: float
    ) -> np.ndarray:
        """End of the approach: the law's path from the state where it started, flown open loop."""
        if self._open_loop is None:
            self._open_loop = (t_ns, self.coeffs(r, v, r_f, v_f, t_go))
        t0_ns, (c0, c1, c2) = self._open_loop
        s = (t_ns - t0_ns) / NS_PER_S
        return c0 + c1 * s + c2 * s * s

    def _plan(self, t_ns: int, r: np.ndarray, v: np.ndarray, m: float, r_f: np.ndarray, v_f: np.ndarray,
              z_B_L: np.ndarray | None = None) -> None:
        t_go, viol = self.plan_t_go(r, v, m, r_f, v_f, z_B_L)
        self._adopt(t_ns, t_go, viol)

    def _adopt(self, t_ns: int, t_go: float, viol: float) -> None:
        self.t_final_ns = t_ns + int(round(t_go * NS_PER_S))
        self._t_plan_ns = t_ns
        self._open_loop = None
        self.plan_feasible = viol <= 0.0
        self.n_plans += 1

    def _maybe_replan(
        self, t_ns: int, r: np.ndarray, v: np.ndarray, m: float, r_f: np.ndarray, v_f: np.ndarray, t_go: float,
        q_LB: Any = None,
    ) -> float:
        """Re-plan when the remaining path breaks the hard limits and a better one exists; returns t_go [s].

        ``q_LB``: the attitude, whose thrust axis the slew check reads (only when a re-plan is weighed)."""
        hard, _ = self.path_violation(r, v, m, r_f, v_f, np.array([t_go]), with_margins=False, want_delta_v=False)
        if hard.max() <= 0.0:
            return t_go
        z_B_L = None if q_LB is None else _thrust_axis_L(q_LB)
        current, _ = self.path_violation(r, v, m, r_f, v_f, np.array([t_go]), with_margins=True, z_B_L=z_B_L,
                                         want_delta_v=False)
        t_new, viol_new = self.plan_t_go(r, v, m, r_f, v_f, z_B_L)
        self._t_plan_ns = t_ns  # rate-limits the attempts, adopted or not
        if viol_new < current.max():
            self._adopt(t_ns, t_new, viol_new)
            return t_new
        return t_go

    def terminal_accel_L(self, r_L: np.ndarray, v_L: np.ndarray, target_L: np.ndarray) -> np.ndarray:
        """Terminal phase: constant-rate vertical descent, horizontal hold over the target.

        Horizontal: a PD on the position error written as a cascade, the
        velocity reference ``-(w / 2 zeta) e_h`` limited to
        ``terminal_speed_max_mps`` and tracked with gain ``2 zeta w``
        (unsaturated: ``-w^2 e_h - 2 zeta w v_h``). Vertical: the rate
        reference is ``-terminal_descent_rate_mps`` within
        ``terminal_hold_radius_m`` of the target, blending linearly to zero
        (hover) at twice that distance, so a missed gate is flown out at the
        gate altitude rather than into the ground; tracked with gain
        ``terminal_rate_gain_per_s``. After :meth:`land_here`: :meth:`_bingo_accel_L`.

        Args:
            r_L: Position, (3,) [m].
            v_L: Velocity, (3,) [m/s].
            target_L: Landing site, (3,) [m].

        Returns:
            Total acceleration, (3,) [m/s^2] (before capping).
        """
        if self.bingo:
            return self._bingo_accel_L(r_L, v_L)
        cfg = self.cfg
        e_h = r_L[:2] - target_L[:2]
        a_h = self._hold_accel_h(e_h, v_L[:2])
        hold_r = cfg.terminal_hold_radius_m
        descent_frac = clip_float((2.0 * hold_r - norm(e_h)) / hold_r, 0.0, 1.0)
        a_z = cfg.terminal_rate_gain_per_s * (-descent_frac * cfg.terminal_descent_rate_mps - v_L[2])
        return np.array([a_h[0], a_h[1], a_z])

    def _hold_accel_h(self, e_h: np.ndarray, v_h: np.ndarray) -> np.ndarray:
        """The terminal phase's horizontal position hold (:meth:`terminal_accel_L`), (2,) [m/s^2]: the velocity
        reference ``-(w / 2 zeta) e_h`` (``e_h`` [m] from the held point), limited to ``terminal_speed_max_mps``,
        tracked with gain ``2 zeta w``."""
        cfg = self.cfg
        w, zeta = cfg.terminal_position_bandwidth_radps, cfg.terminal_damping_ratio
        v_ref_h = -(w / (2.0 * zeta)) * e_h
        speed = norm(v_ref_h)
        if speed > cfg.terminal_speed_max_mps:
            v_ref_h *= cfg.terminal_speed_max_mps / speed
        return 2.0 * zeta * w * (v_ref_h - v_h)

    def _bingo_accel_L(self, r_L: np.ndarray, v_L: np.ndarray) -> np.ndarray:
        """The terminal phase after a bingo (:meth:`land_here`): horizontal speed nulled (the velocity loop of
        :meth:`terminal_accel_L` with a zero reference: a fly-out's 2 m/s braked by the low tilt limit, no
        position loop to overshoot), then the position held where it fell below ``BINGO_VH_FULL_MPS``. Vertical:
        :meth:`bingo_rate_mps` with its deceleration fed forward, blended from the terminal rate while the
        horizontal speed is above ``BINGO_VH_FULL_MPS`` (fully the terminal rate above ``BINGO_VH_NONE_MPS``)."""
        cfg = self.cfg
        w, zeta = cfg.terminal_position_bandwidth_radps, cfg.terminal_damping_ratio
        speed_h = norm(v_L[:2])
        if self.hold_xy_L is None and speed_h < BINGO_VH_FULL_MPS:
            self.hold_xy_L = np.array(r_L[:2], dtype=float)
        if self.hold_xy_L is None:
            a_h = -2.0 * zeta * w * v_L[:2]
        else:
            a_h = self._hold_accel_h(r_L[:2] - self.hold_xy_L, v_L[:2])
        rate, brake = self.bingo_rate_mps(float(r_L[2]) - self.bingo_ground_z_L)
        fast = clip_float((BINGO_VH_NONE_MPS - speed_h) / (BINGO_VH_NONE_MPS - BINGO_VH_FULL_MPS), 0.0, 1.0)
        v_t = cfg.terminal_descent_rate_mps
        rate, brake = v_t + fast * (rate - v_t), fast * brake
        return np.array([a_h[0], a_h[1], cfg.terminal_rate_gain_per_s * (-rate - v_L[2]) + brake])


class ApolloGuidance(GuidanceLaw):
    """Apollo E-guidance to the gate (zero total acceleration there), then terminal descent.

    Ports: as :class:`GuidanceLaw` (inputs NavState + LandingTarget, output
    GuidanceCommand, control rate).
    """

    name = "apollo"

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102 (documented on the base)
        return apollo_accel_L(r_L, v_L, r_f_L, v_f_L, APOLLO_GATE_ACCEL_L, t_go_s)

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102
        return apollo_coeffs(r_L, v_L, r_f_L, v_f_L, APOLLO_GATE_ACCEL_L, t_go_s)


class ZemZevGuidance(GuidanceLaw):
    """ZEM/ZEV optimal feedback to the gate, then terminal descent.

    Ports: as :class:`GuidanceLaw` (inputs NavState + LandingTarget, output
    GuidanceCommand, control rate).
    """

    name = "zem_zev"

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102
        return zem_zev_accel_L(r_L, v_L, r_f_L, v_f_L, t_go_s, self.g_L)

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102
        return zem_zev_coeffs(r_L, v_L, r_f_L, v_f_L, t_go_s)


class NoGuidance(GuidanceLaw):
    """Guidance switched off: commands free fall, so the engine stays off.

    For failure studies (what the lander does with no guidance at all); it
    never lands safely from altitude.

    Ports: as :class:`GuidanceLaw`; the phase is always ``"off"``.
    """

    name = "off"

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102 (free fall)
        return np.broadcast_to(self.g_L, np.shape(r_L)).copy()

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102 (constant gravity)
        zero = np.zeros(np.shape(r_L))
        return np.broadcast_to(self.g_L, np.shape(r_L)).copy(), zero, zero

    def update(self, nav: NavState, target: LandingTarget) -> GuidanceCommand:
        return GuidanceCommand(int(nav.t_ns), self.g_L.copy(), PHASE_OFF, float("nan"))


GUIDANCE_LAWS: dict[str, type[GuidanceLaw]] = {cls.name: cls for cls in (ApolloGuidance, ZemZevGuidance, NoGuidance)}
# Built-in laws that live in their own module (imported only when chosen: G-FOLD needs cvxpy).
BUILTIN_PLUGINS: dict[str, str] = {"gfold": "gnc.gfold:GfoldGuidance"}


def guidance_class(law: str) -> type[GuidanceLaw]:
    """The class of a ``guidance.law`` value: a built-in name or a plug-in ``package.module:ClassName``.

    Raises:
        ValueError: One line naming the value and what is wrong (unknown name,
            module that does not import, missing class, class that lacks the
            interface, or a module that crosses the flight-software boundary).
    """
    from gnc.plugins import load_law_class

    if law in GUIDANCE_LAWS:
        return GUIDANCE_LAWS[law]
    if law in BUILTIN_PLUGINS:
        import importlib.util

        if law == "gfold" and importlib.util.find_spec("cvxpy") is None:
            raise ValueError("guidance.law = 'gfold' needs cvxpy and a conic solver, the optional extra: "
                             "pip install 'landbench[opt]'")
        return load_law_class(BUILTIN_PLUGINS[law], GuidanceLaw, shown=law)
    if ":" not in law:
        raise ValueError(f"guidance.law = {law!r}: unknown law; allowed: {', '.join([*GUIDANCE_LAWS, *BUILTIN_PLUGINS])}, "
                         "or a plug-in 'package.module:ClassName'")
    return load_law_class(law, GuidanceLaw)


def validate_law_options(law_cls: type, law: str, options: Mapping[str, Any] | None) -> BaseModel | None:
    """Validate ``[guidance.options]`` with the law's own ``Options`` model.

    Returns:
        The validated options, or None when the law declares no ``Options`` (then
        the table must be empty).

    Raises:
        ValueError: One line naming ``guidance.options.<field>``, the bad value and what is allowed.
    """
    return validate_options(law_cls, law, options, "guidance.options", "law")


def make_guidance(
    cfg: GuidanceConfig | Mapping[str, Any] | None = None, limits: GuidanceLimits | None = None
) -> GuidanceLaw:
    """Build the configured guidance law.

    Args:
        cfg: Guidance configuration (model, mapping or None for defaults).
        limits: Vehicle limits (None: the default lander's).

    Returns:
        A fresh :class:`GuidanceLaw`.

    Raises:
        ValueError: A bad law name or parameter; the message names the field,
            the bad value and what is allowed.
    """
    cfg = validated_config(GuidanceConfig, cfg, "guidance")
    law_cls = guidance_class(cfg.law)  # validated already; resolves plug-ins and gfold
    if limits is None:
        limits = GuidanceLimits()
    if not isinstance(limits, GuidanceLimits):
        raise ValueError(f"limits = {limits!r}; allowed: a GuidanceLimits")
    return build_law(law_cls, cfg.law, "guidance.law", cfg, limits)
