"""Descent control: commanded acceleration to engine thrust and RCS torques.

Ports (:class:`Controller`):
    Inputs: :class:`gnc.navstate.NavState` (``r_BL_L[2]``, ``q_LB``,
        ``omega_B``, ``mass_kg``), :class:`gnc.guidance.GuidanceCommand`
        (``a_cmd_L``, the desired total acceleration in L) and, optionally, a
        :class:`ContactMessage` (footpad contacts).
    Output: :class:`ActuatorCommand`: thrust [N], body torque (3,) [N m],
        engine on/off, and (telemetry) the commanded attitude.
    Rate: the control rate (default 50 Hz), right after guidance. The output
        is held (zero-order) by the propulsion model until the next period.

Stages:
    1. Thrust vector (:func:`thrust_vector_command`): the specific force
       ``f = a_cmd_L - g_L`` is tilt-limited (the vertical part is kept, the
       horizontal part cut to ``tan(tilt_max(h)) f_z``; the limit tightens
       linearly from ``tilt.tilt_max_high_deg`` above ``tilt.taper_altitude_m``
       to ``tilt.tilt_max_touchdown_deg`` at zero height). The thrust is
       ``m |f|`` clamped to ``[thrust_min_N, thrust_max_N]`` (a lit
       deep-throttle engine cannot go lower; it is never shut down in flight).
       If ``f_z <= 0`` (guidance wants to fall faster than gravity) the thrust
       axis goes vertical at minimum thrust. With ``thrust_projection =
       "body_axis"`` the magnitude is instead ``m f . z_B``, the commanded
       specific force projected on the *current* body +z (the navigation
       attitude's): the engine can only push along its axis, so while the body
       still turns towards the command, only the projection is asked for (the
       usual thrust-vector-control law; never below the minimum thrust).
    2. Attitude command (:func:`attitude_command_LB`): body +z along the thrust
       direction, body +x's horizontal projection held at ``yaw_hold_deg``.
    3. Attitude control (:func:`attitude_torque_B`): quaternion PD with gains
       scaled by the current inertia (dry body + propellant sphere), natural
       frequency ``attitude_bandwidth_radps`` and damping
       ``attitude_damping_ratio``, written as a cascade whose rate reference is
       limited to ``slew_rate_max_degps`` so large errors are slewed at a
       bounded rate instead of overshooting against the RCS saturation; plus
       gyroscopic compensation. The torque vector is scaled down (direction
       kept) to ``rcs_torque_max_Nm`` per axis.
    4. Touchdown: once ``legs_for_engine_cut`` footpads report contact the
       engine is cut and the RCS idled, latched until :meth:`Controller.reset`.

Safety: the output never violates the actuator limits and is always finite.
A non-finite or invalid input makes the controller hold its last good thrust
and attitude command (the minimum thrust and an upright attitude before any);
a non-finite attitude or rate gives zero torque.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from gnc.config import validate_options, validated_config
from gnc.guidance import LUNAR_GRAVITY_MPS2, GuidanceCommand, GuidanceLimits, TiltLimitConfig
from gnc.messages import N_LEGS, ContactMessage
from gnc.plugins import build_law
from gnc.navstate import NavState
from gnc.numeric import clip_float, cross3, finite_small, max_abs3, norm
from gnc.quat import body_z_L, quat_error, quat_from_elements, unit_quaternion

# Propellant modelled as a uniform sphere: I = SPHERE_INERTIA_FACTOR * m * r^2.
SPHERE_INERTIA_FACTOR = 0.4
# Specific force (vertical) at or below this is "no upward thrust wanted" [m/s^2].
_F_Z_MIN_MPS2 = 1e-6
_EZ = np.array([0.0, 0.0, 1.0])
_Q_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True, slots=True)
class ActuatorCommand:
    """Controller output, held over one control period.

    Attributes:
        thrust_N: Engine thrust command [N]: in ``[thrust_min_N,
            thrust_max_N]`` when ``engine_on``, else 0.
        torque_B_Nm: RCS torque command in B, (3,) [N m], each axis within
            ``+-rcs_torque_max_Nm``.
        engine_on: False once the engine is cut (touchdown).
        t_ns: Time of validity [ns].
        q_LB_cmd: Commanded attitude (telemetry), (4,) scalar-first.
    """

    thrust_N: float
    torque_B_Nm: np.ndarray
    engine_on: bool
    t_ns: int = 0
    q_LB_cmd: np.ndarray = field(default_factory=lambda: _Q_IDENTITY.copy())


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """The flight software's knowledge of the vehicle (defaults: the default lander).

    Attributes:
        thrust_min_N: Minimum thrust of the lit engine [N].
        thrust_max_N: Maximum thrust [N].
        rcs_torque_max_Nm: RCS torque saturation per body axis [N m].
        dry_mass_kg: Dry mass [kg]; propellant = nav mass - dry mass.
        dry_inertia_B_kgm2: Principal inertia of the dry vehicle, (3,) [kg m^2].
        tank_radius_m: Radius of the spherical propellant tank at the centre of mass [m].
        thrust_scale: Delivered thrust per unit of command, as the flight software
            believes it (its engine calibration; 1 + the calibration error) [-].
    """

    thrust_min_N: float = 1500.0
    thrust_max_N: float = 7500.0
    rcs_torque_max_Nm: float = 200.0
    dry_mass_kg: float = 1500.0
    dry_inertia_B_kgm2: tuple[float, float, float] = (781.25, 781.25, 1000.0)
    tank_radius_m: float = 0.6
    thrust_scale: float = 1.0

    def __post_init__(self) -> None:
        positive = {
            "thrust_max_N": self.thrust_max_N,
            "rcs_torque_max_Nm": self.rcs_torque_max_Nm,
            "dry_mass_kg": self.dry_mass_kg,
            "tank_radius_m": self.tank_radius_m,
            "thrust_scale": self.thrust_scale,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"vehicle.{name} = {value!r}; allowed: a finite value > 0")
        if not (np.isfinite(self.thrust_min_N) and 0.0 <= self.thrust_min_N < self.thrust_max_N):
            raise ValueError(
                f"vehicle.thrust_min_N = {self.thrust_min_N!r}; allowed: 0 <= thrust_min_N < thrust_max_N = {self.thrust_max_N}"
            )
        inertia = np.asarray(self.dry_inertia_B_kgm2, float)
        if inertia.shape != (3,) or not np.all(np.isfinite(inertia)) or np.any(inertia <= 0.0):
            raise ValueError(f"vehicle.dry_inertia_B_kgm2 = {self.dry_inertia_B_kgm2!r}; allowed: three finite values > 0")

    def inertia_B_kgm2(self, mass_kg: float) -> np.ndarray:
        """Principal inertia at a total mass (dry + propellant sphere), (3,) [kg m^2]."""
        propellant = max(float(mass_kg) - self.dry_mass_kg, 0.0)
        return np.asarray(self.dry_inertia_B_kgm2, float) + SPHERE_INERTIA_FACTOR * propellant * self.tank_radius_m**2


CONTROLLER_DEFAULT = "quaternion_pd"


class ControlConfig(BaseModel):
    """Controller selection and tuning."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    law: str = Field(
        CONTROLLER_DEFAULT,
        description="the controller: 'quaternion_pd' (this module's), or a plug-in 'package.module:ClassName' "
                    "subclassing gnc.control.Controller",
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="the plug-in controller's options, validated by its Options model"
    )
    tilt: TiltLimitConfig = TiltLimitConfig()
    yaw_hold_deg: float = Field(
        0.0, ge=-360.0, le=360.0,
        description="heading of body +x's horizontal projection, from L +x (east) counter-clockwise about +z [deg]",
    )
    attitude_bandwidth_radps: float = Field(2.0, gt=0.0, le=20.0, description="attitude loop natural frequency [rad/s]")
    attitude_damping_ratio: float = Field(0.9, gt=0.0, le=3.0, description="attitude loop damping ratio [-]")
    slew_rate_max_degps: float = Field(15.0, gt=0.0, le=90.0, description="largest commanded slew rate [deg/s]")
    gravity_mps2: float = Field(LUNAR_GRAVITY_MPS2, gt=0.0, description="surface gravity magnitude [m/s^2]")
    legs_for_engine_cut: int = Field(1, ge=1, le=N_LEGS, description="footpads in contact that cut the engine [-]")
    thrust_projection: Literal["body_axis", "magnitude"] = Field(
        "body_axis",
        description="thrust magnitude: the commanded specific force projected on the current body +z, or its full "
                    "magnitude (the idealised law)",
    )

    @field_validator("law")
    @classmethod
    def _law_resolves(cls, law: str) -> str:
        controller_class(law)  # one-line ValueError: unknown name, bad import path, missing class, interface
        return law

    @field_validator("options")
    @classmethod
    def _options_valid(cls, options: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        law = info.data.get("law")
        if law is not None:
            _controller_options(controller_class(law), law, options)
        return options

    def g_L(self) -> np.ndarray:
        """Gravity in L, (3,) [m/s^2]."""
        return np.array([0.0, 0.0, -self.gravity_mps2])


def controller_class(law: str) -> type["Controller"]:
    """The class of a ``control.law`` value: ``quaternion_pd`` or a plug-in ``package.module:ClassName``.

    Raises:
        ValueError: One line naming the value and what is wrong.
    """
    if law == CONTROLLER_DEFAULT:
        return Controller
    if ":" not in law:
        raise ValueError(f"control.law = {law!r}: unknown controller; allowed: {CONTROLLER_DEFAULT}, "
                         "or a plug-in 'package.module:ClassName'")
    from gnc.plugins import load_law_class

    return load_law_class(law, Controller, field="control.law", what="controller")


def _controller_options(cls: type, law: str, options: Mapping[str, Any] | None) -> BaseModel | None:
    """Validate ``[control.options]`` with the controller's ``Options`` model (one-line ValueError)."""
    return validate_options(cls, law, options, "control.options", "controller")


def guidance_limits(vehicle: VehicleParams, cfg: ControlConfig) -> GuidanceLimits:
    """The limits guidance must plan within: the vehicle's thrust range, the controller's tilt schedule and the
    angular acceleration the RCS gives the thrust axis (its torque over the larger lateral inertia of the dry
    vehicle; the propellant sphere adds ``0.4 m_p r^2``, about 4 % on the default lander)."""
    inertia = vehicle.dry_inertia_B_kgm2
    return GuidanceLimits(thrust_min_N=vehicle.thrust_min_N, thrust_max_N=vehicle.thrust_max_N, tilt=cfg.tilt,
                          slew_accel_max_radps2=vehicle.rcs_torque_max_Nm / max(inertia[0], inertia[1]))


# --------------------------------------------------------------------------- stages
def thrust_vector_command(
    a_cmd_L: np.ndarray,
    g_L: np.ndarray,
    mass_kg: float,
    altitude_m: float,
    vehicle: VehicleParams,
    tilt: TiltLimitConfig,
    z_B_L: np.ndarray | None = None,
) -> tuple[float, np.ndarray]:
    """Thrust magnitude and direction for a commanded total acceleration.

    Args:
        a_cmd_L: Commanded total acceleration, (3,) [m/s^2], finite.
        g_L: Gravity, (3,) [m/s^2].
        mass_kg: Vehicle mass [kg], > 0.
        altitude_m: Height above the target, for the tilt limit [m].
        vehicle: Thrust limits.
        tilt: Tilt-limit schedule.
        z_B_L: The current body +z in L, (3,) unit, to project the (tilt-limited)
            specific force on; None: its full magnitude.

    Returns:
        ``(thrust_N, z_cmd_L)``: the thrust command ``m |f| / thrust_scale`` (or
        ``m f . z_B / thrust_scale``) clamped to ``[thrust_min_N, thrust_max_N]``
        [N] and the unit thrust direction in L, (3,), within the tilt limit.
    """
    f = np.asarray(a_cmd_L, float) - g_L
    if not f[2] > _F_Z_MIN_MPS2:
        return float(vehicle.thrust_min_N), _EZ.copy()
    scale = max_abs3(*f.tolist())  # work on f / scale: no overflow for absurd commands
    u = f / scale
    tan_max = np.tan(tilt.tilt_max_rad(altitude_m))
    uh_norm = float(np.hypot(u[0], u[1]))
    if uh_norm > tan_max * u[2]:
        u[:2] *= tan_max * u[2] / uh_norm
    u_norm = norm(u)
    along = u_norm if z_B_L is None else max(float(u @ z_B_L), 0.0)
    thrust = clip_float(float(mass_kg * scale * along / vehicle.thrust_scale), vehicle.thrust_min_N, vehicle.thrust_max_N)
    return thrust, u / u_norm


def attitude_command_LB(z_cmd_L: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Attitude with body +z along a thrust direction and a held heading.

    Body +x is chosen perpendicular to ``z_cmd_L`` with its horizontal
    projection along ``[cos yaw, sin yaw, 0]`` (the yaw of a z-y-x Euler
    sequence).

    Args:
        z_cmd_L: Unit thrust direction in L, (3,), with a positive up component.
        yaw_rad: Heading [rad], from L +x counter-clockwise about +z.

    Returns:
        ``q_LB`` command, (4,) scalar-first.
    """
    z = np.asarray(z_cmd_L, float)
    z = z / norm(z)
    z_x, z_y, z_z = z.tolist()
    assert z_z > 0.0, "thrust direction must point upward"
    h = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    along = (h @ z) / z_z
    h_x, h_y, _ = h.tolist()
    # x = h - along * e_z, per axis as the array expression: x . z = 0 and x's horizontal part is h
    x = np.array([h_x - along * 0.0, h_y - along * 0.0, 0.0 - along * 1.0])
    x /= norm(x)
    x_x, x_y, x_z = x.tolist()
    y_x, y_y, y_z = cross3(z_x, z_y, z_z, x_x, x_y, x_z)
    # The matrix of columns x, y, z.
    return quat_from_elements(x_x, y_x, z_x, x_y, y_y, z_y, x_z, y_z, z_z)


def attitude_torque_B(
    q_LB: np.ndarray,
    omega_B: np.ndarray,
    q_LB_cmd: np.ndarray,
    inertia_B_kgm2: np.ndarray,
    cfg: ControlConfig,
    torque_max_Nm: float,
) -> np.ndarray:
    """Quaternion PD attitude control with a slew-rate limit and RCS saturation.

    With the error quaternion ``q_e = q_cmd^-1 q`` (shortest way round) and
    ``e = 2 vec(q_e)`` (about the rotation vector for small errors), the law is
    ``tau = I kd (sat(-kp/kd e) - omega) + omega x I omega`` with
    ``kp = wn^2``, ``kd = 2 zeta wn`` and ``sat`` limiting the rate reference's
    norm to the slew limit; unsaturated it is the PD ``-I wn^2 e - 2 zeta wn I omega``.

    Args:
        q_LB: Attitude, (4,) scalar-first.
        omega_B: Body rate, (3,) [rad/s].
        q_LB_cmd: Commanded attitude, (4,) scalar-first (zero commanded rate).
        inertia_B_kgm2: Principal inertia, (3,) [kg m^2].
        cfg: Gains and slew limit.
        torque_max_Nm: Per-axis saturation [N m].

    Returns:
        Torque in B, (3,) [N m], each axis within ``+-torque_max_Nm``.
    """
    # Per axis on floats, each operation as the (3,)-array expression in the comment above it.
    e_w, e_x, e_y, e_z = quat_error(q_LB_cmd, q_LB).tolist()
    # e = 2 sign(q_e[0]) q_e[1:]
    e_gain = 2.0 * math.copysign(1.0, e_w)
    wn, zeta = cfg.attitude_bandwidth_radps, cfg.attitude_damping_ratio
    # omega_ref = -(wn / (2 zeta)) e   [rad/s]
    ref_gain = -(wn / (2.0 * zeta))
    omega_ref = np.array([ref_gain * (e_gain * e_x), ref_gain * (e_gain * e_y), ref_gain * (e_gain * e_z)])
    slew_max = np.deg2rad(cfg.slew_rate_max_degps)
    ref_norm = norm(omega_ref)
    if ref_norm > slew_max:
        omega_ref *= slew_max / ref_norm
    r_x, r_y, r_z = omega_ref.tolist()
    w_x, w_y, w_z = np.asarray(omega_B, float).tolist()
    i_x, i_y, i_z = np.asarray(inertia_B_kgm2, float).tolist()
    # tau = I (2 zeta wn) (omega_ref - omega) + omega x (I omega)   [N m]
    kd = 2.0 * zeta * wn
    g_x, g_y, g_z = cross3(w_x, w_y, w_z, i_x * w_x, i_y * w_y, i_z * w_z)
    t_x = i_x * kd * (r_x - w_x) + g_x
    t_y = i_y * kd * (r_y - w_y) + g_y
    t_z = i_z * kd * (r_z - w_z) + g_z
    peak = max_abs3(t_x, t_y, t_z)
    if peak > torque_max_Nm:
        shrink = torque_max_Nm / peak
        t_x, t_y, t_z = t_x * shrink, t_y * shrink, t_z * shrink
    # the scaling may round a hair above the limit
    return np.array([clip_float(t_x, -torque_max_Nm, torque_max_Nm), clip_float(t_y, -torque_max_Nm, torque_max_Nm),
                     clip_float(t_z, -torque_max_Nm, torque_max_Nm)])


# --------------------------------------------------------------------------- the controller
class Controller:
    """Thrust-vector and attitude controller with touchdown cut-off.

    Also the controller plug-in interface (``control.law =
    "package.module:ClassName"``): a subclass that overrides :meth:`update`
    (or :meth:`reset`), with an optional ``Options`` pydantic model of its
    ``[control.options]`` (validated options in ``self.options``).

    Ports:
        Inputs: NavState, GuidanceCommand, optional ContactMessage.
        Output: ActuatorCommand (thrust [N], torque_B (3,) [N m], engine_on).
        Rate: control rate (default 50 Hz). Stateful: last good command,
            engine-cut latch.
    """

    Options: ClassVar[type[BaseModel] | None] = None  # a plug-in's [control.options] model

    def __init__(self, cfg: ControlConfig | Mapping[str, Any] | None = None, vehicle: VehicleParams | None = None):
        self.cfg: ControlConfig = validated_config(ControlConfig, cfg, "control")
        self.options: BaseModel | None = _controller_options(type(self), self.cfg.law, self.cfg.options)
        if vehicle is None:
            vehicle = VehicleParams()
        if not isinstance(vehicle, VehicleParams):
            raise ValueError(f"vehicle = {vehicle!r}; allowed: a VehicleParams")
        self.vehicle = vehicle
        self.g_L = self.cfg.g_L()
        self.yaw_rad = float(np.deg2rad(self.cfg.yaw_hold_deg))
        self.reset()

    def reset(self) -> None:
        """Clear the engine-cut latch and the held command (new descent)."""
        self.engine_cut = False
        self._thrust_hold_N = float(self.vehicle.thrust_min_N)
        self._q_cmd_hold = attitude_command_LB(_EZ, self.yaw_rad)

    def guidance_limits(self) -> GuidanceLimits:
        """Limits for :func:`gnc.guidance.make_guidance` matching this controller."""
        return guidance_limits(self.vehicle, self.cfg)

    def update(self, nav: NavState, cmd: GuidanceCommand, contact: ContactMessage | None = None) -> ActuatorCommand:
        """One control step.

        Args:
            nav: Navigation state.
            cmd: Guidance command for this period.
            contact: Latest footpad contacts, or None when not available.

        Returns:
            The actuator command, within every actuator limit.
        """
        t_ns = int(nav.t_ns)
        if contact is not None and sum(map(bool, contact.legs)) >= self.cfg.legs_for_engine_cut:
            self.engine_cut = True
        if self.engine_cut:
            return ActuatorCommand(0.0, np.zeros(3), False, t_ns, self._q_cmd_hold.copy())

        # The finiteness checks on floats (math.isfinite of each element: np.all(np.isfinite(...))).
        mass = float(nav.mass_kg)
        if not (math.isfinite(mass) and mass > 0.0):
            mass = math.nan
        altitude = float(np.asarray(nav.r_BL_L, float)[2])
        a_cmd = np.asarray(cmd.a_cmd_L, float)
        z_B_L = None
        q = unit_quaternion(nav.q_LB)  # normalised once: the thrust projection and the attitude loop use it
        if self.cfg.thrust_projection == "body_axis" and q is not None:
            z_B_L = body_z_L(q)
        if cmd.valid and finite_small(a_cmd) and math.isfinite(mass) and math.isfinite(altitude):
            self._thrust_hold_N, z_cmd_L = thrust_vector_command(
                a_cmd, self.g_L, mass, altitude, self.vehicle, self.cfg.tilt, z_B_L
            )
            self._q_cmd_hold = attitude_command_LB(z_cmd_L, self.yaw_rad)

        omega = np.asarray(nav.omega_B, float)
        torque_max = self.vehicle.rcs_torque_max_Nm
        torque = (0.0, 0.0, 0.0)
        if q is not None and finite_small(omega):
            inertia = self.vehicle.inertia_B_kgm2(mass if math.isfinite(mass) else self.vehicle.dry_mass_kg)
            tau = attitude_torque_B(q, omega, self._q_cmd_hold, inertia, self.cfg, torque_max)
            if finite_small(tau):  # cannot fail with finite inputs; never emit NaN
                torque = tau.tolist()
        torque = np.array([clip_float(t, -torque_max, torque_max) for t in torque])
        thrust = clip_float(float(self._thrust_hold_N), self.vehicle.thrust_min_N, self.vehicle.thrust_max_N)
        return ActuatorCommand(thrust, torque, True, t_ns, self._q_cmd_hold.copy())


def make_controller(
    cfg: ControlConfig | Mapping[str, Any] | None = None, vehicle: VehicleParams | None = None
) -> Controller:
    """Build the configured controller (``control.law``: the built-in one or a plug-in).

    A bad parameter raises ValueError naming the field, value and what is allowed.
    """
    cfg = validated_config(ControlConfig, cfg, "control")
    return build_law(controller_class(cfg.law), cfg.law, "control.law", cfg, vehicle)
