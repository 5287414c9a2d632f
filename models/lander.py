"""Lander configuration and its MJCF description.

The lander is a 6-DOF rigid body (MuJoCo free joint) with:

* a main body (dry mass, box inertia) whose +z axis is the thrust axis;
* a propellant tank, a massless-geometry child body welded at the main
  body's centre of mass, whose mass and inertia the engine model lowers as
  propellant flows (a sphere of uniformly distributed propellant);
* four legs (capsules) ending in spherical footpads that contact the terrain;
* sites for the engine (thrust along body +z), the RCS (torques about the
  body axes), the IMU, the laser altimeter and the nadir camera.

Frames: B is the body frame (origin at the centre of the main box, +z up
when upright, +x forward). The nadir camera looks along body -z and its
image x axis is body +x (see :mod:`models.camera`).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

# Geometry groups: mj_ray against terrain alone needs the lander in another group.
TERRAIN_GEOM_GROUP = 0
LANDER_GEOM_GROUP = 1
PATCH_GEOM_GROUP = 2  # the visual landing-site texture patch (coplanar with the terrain)
# The camera's drawing of a texture-shaded terrain (models.world.terrain_tiles): visual-only mesh tiles,
# in a group of their own (default renderers and mj_ray never see them); a tile out of the camera's view
# is moved to the hidden group for that frame.
TERRAIN_TILE_GEOM_GROUP = 4
HIDDEN_TILE_GEOM_GROUP = 5

FOOTPAD_NAMES = ("foot_fl", "foot_fr", "foot_rl", "foot_rr")

# Contact softness (MuJoCo solref): time constant [s] and damping ratio. MuJoCo
# needs the time constant to be at least twice the physics step for stable
# contacts; the scenario checks the step against it at load time.
CONTACT_TIMECONST_S = 0.02
CONTACT_DAMPING_RATIO = 1.0
CONTACT_SOLREF = f"{CONTACT_TIMECONST_S} {CONTACT_DAMPING_RATIO}"


COM_OFFSET_MAX_M = 10.0  # largest dry centre-of-mass offset per body axis a lander config may give [m]


class EngineConfig(BaseModel):
    """Throttleable main engine, thrust along body +z."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    thrust_max_N: float = Field(7500.0, gt=0, description="maximum thrust [N]")
    thrust_min_N: float = Field(1500.0, ge=0, description="minimum thrust when lit [N] (deep-throttle limit)")
    isp_s: float = Field(310.0, gt=0, description="specific impulse [s]")
    thrust_error_frac: float = Field(
        0.0, gt=-0.5, lt=0.5, description="fractional thrust error (delivered = commanded * (1 + e)) [-]"
    )
    time_constant_s: float = Field(
        0.1, ge=0.0, le=5.0,
        description="first-order throttle response time constant [s] (0: the thrust follows the command at once)",
    )
    slew_rate_Nps: float = Field(
        20000.0, gt=0.0, allow_inf_nan=True,  # inf means no limit; NaN fails gt
        description="largest rate of change of the delivered thrust [N/s] (inf: no limit)"
    )
    misalignment_deg: float = Field(
        0.0, ge=0.0, le=5.0, description="angle of the thrust line from body +z [deg]"
    )
    misalignment_azimuth_deg: float = Field(
        0.0, ge=-360.0, le=360.0,
        description="direction of the thrust line's tilt, from body +x towards +y about +z [deg]",
    )

    @model_validator(mode="after")
    def _min_below_max(self) -> "EngineConfig":
        if self.thrust_min_N >= self.thrust_max_N:
            raise ValueError(
                f"engine.thrust_min_N = {self.thrust_min_N} must be below engine.thrust_max_N = "
                f"{self.thrust_max_N}; allowed: 0 <= thrust_min_N < thrust_max_N"
            )
        return self

    def thrust_direction_B(self) -> np.ndarray:
        """Unit direction of the delivered thrust in B (3,): body +z tilted by the misalignment."""
        if self.misalignment_deg == 0.0:
            return np.array([0.0, 0.0, 1.0])
        a, az = math.radians(self.misalignment_deg), math.radians(self.misalignment_azimuth_deg)
        return np.array([math.sin(a) * math.cos(az), math.sin(a) * math.sin(az), math.cos(a)])


class RcsConfig(BaseModel):
    """Reaction-control thrusters: torque delivery and propellant.

    ``mode = "pwm"``: each axis's commanded torque is delivered as on/off pulses of the
    full torque ``rcs_torque_max_Nm``, at most one pulse per ``pwm_period_ns`` whose width is
    ``|tau_cmd| / tau_max * period`` plus the impulse carried from earlier windows; a pulse
    shorter than ``min_on_ns`` is not fired and its impulse is carried (the minimum impulse
    bit is ``tau_max * min_on_ns``; see :mod:`models.actuators`).
    ``mode = "continuous"``: the commanded torque is delivered exactly (saturated), as an
    idealised controller study wants. Either way, the thrusters burn propellant from the main
    tanks at ``|tau| / moment_arm_m`` of thrust per axis (a couple of two thrusters) at ``isp_s``.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    mode: Literal["pwm", "continuous"] = Field("pwm", description="pulse-width modulated or continuous torque")
    pwm_period_ns: int = Field(20_000_000, gt=0, description="pulse-width modulation period [ns] (default 50 Hz)")
    min_on_ns: int = Field(4_000_000, ge=0, description="shortest pulse a thruster fires [ns]")
    moment_arm_m: float = Field(1.0, gt=0.0, description="moment arm of each thruster couple [m]")
    isp_s: float = Field(220.0, gt=0.0, description="RCS specific impulse [s] (hydrazine monopropellant class)")
    draws_propellant: bool = Field(True, description="the thrusters burn propellant from the main tanks")

    @model_validator(mode="after")
    def _a_pulse_fits_its_period(self) -> "RcsConfig":
        if self.mode == "pwm" and self.min_on_ns > self.pwm_period_ns:
            raise ValueError(f"rcs.min_on_ns = {self.min_on_ns} is longer than rcs.pwm_period_ns = "
                             f"{self.pwm_period_ns}: no pulse could ever fire; allowed: min_on_ns <= pwm_period_ns")
        return self


class LanderConfig(BaseModel):
    """Mass properties, geometry and actuator limits of the lander."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    dry_mass_kg: float = Field(1500.0, gt=0, le=1e6, description="dry mass [kg]")
    propellant_kg: float = Field(600.0, ge=0, le=1e6, description="initial propellant mass [kg]")
    body_half_extents_m: tuple[float, float, float] = Field(
        (1.0, 1.0, 0.75), description="half sizes of the main body box along body x, y, z [m]"
    )
    tank_radius_m: float = Field(0.6, gt=0, description="radius of the spherical propellant tank [m]")
    leg_radius_m: float = Field(2.2, gt=0, description="horizontal distance of each footpad from the body axis [m]")
    leg_drop_m: float = Field(1.9, gt=0, description="depth of the footpad centres below the body origin [m]")
    footpad_radius_m: float = Field(0.2, gt=0, description="footpad sphere radius [m]")
    friction: float = Field(0.8, gt=0, description="footpad-regolith Coulomb friction coefficient [-]")
    rcs_torque_max_Nm: float = Field(200.0, gt=0, description="RCS torque saturation per body axis [N m]")
    com_offset_B_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="dry body's centre of mass relative to the body origin, in B [m] (each "
                                     "component within COM_OFFSET_MAX_M)"
    )
    engine: EngineConfig = EngineConfig()
    rcs: RcsConfig = RcsConfig()

    @model_validator(mode="after")
    def _com_near_the_body(self) -> "LanderConfig":
        if max(abs(c) for c in self.com_offset_B_m) > COM_OFFSET_MAX_M:
            raise ValueError(f"lander.com_offset_B_m = {list(self.com_offset_B_m)} puts the dry centre of mass beyond "
                             f"{COM_OFFSET_MAX_M:g} m of the body origin; allowed: each component within "
                             f"+-{COM_OFFSET_MAX_M:g} m")
        return self

    def ideal(self) -> "LanderConfig":
        """This lander with idealised actuators (``realism = "ideal"``).

        The engine follows its command at once (no lag or slew limit) along body +z, the dry
        centre of mass is at the body origin, and the RCS delivers the commanded torque
        continuously without burning propellant: today's vehicle before issue 17.
        """
        engine = self.engine.model_copy(update={"time_constant_s": 0.0, "slew_rate_Nps": math.inf,
                                                "misalignment_deg": 0.0, "misalignment_azimuth_deg": 0.0})
        rcs = self.rcs.model_copy(update={"mode": "continuous", "draws_propellant": False})
        return self.model_copy(update={"engine": engine, "rcs": rcs, "com_offset_B_m": (0.0, 0.0, 0.0)})

    @property
    def wet_mass_kg(self) -> float:
        return self.dry_mass_kg + self.propellant_kg

    @property
    def footpad_clearance_m(self) -> float:
        """Height of the body origin above flat ground when standing on it [m]."""
        return self.leg_drop_m + self.footpad_radius_m

    def body_inertia_kgm2(self) -> np.ndarray:
        """Principal inertia of the dry main body, a solid box (3,) [kg m^2]."""
        a, b, c = (2.0 * h for h in self.body_half_extents_m)
        m = self.dry_mass_kg
        return np.array([m * (b * b + c * c), m * (a * a + c * c), m * (a * a + b * b)]) / 12.0

    def tank_inertia_kgm2(self, propellant_kg: float) -> np.ndarray:
        """Principal inertia of a uniform propellant sphere (3,) [kg m^2]."""
        return np.full(3, 0.4 * propellant_kg * self.tank_radius_m**2)


# MuJoCo needs a strictly positive body mass for a body with an <inertial>; an
# empty tank keeps this negligible remainder (1 g), far below any tolerance.
TANK_MASS_FLOOR_KG = 1e-3


def footpad_positions_B(cfg: LanderConfig) -> np.ndarray:
    """Footpad centres in the body frame (4, 3) [m], order FOOTPAD_NAMES."""
    r = cfg.leg_radius_m / np.sqrt(2.0)
    z = -cfg.leg_drop_m
    return np.array([[r, r, z], [r, -r, z], [-r, r, z], [-r, -r, z]])


def com_position_B(cfg: LanderConfig, propellant_kg: float) -> np.ndarray:
    """Centre of mass of the whole lander in B (3,) [m]: the dry body's (offset) and the tank's (at the origin)."""
    dry = cfg.dry_mass_kg
    return np.asarray(cfg.com_offset_B_m, float) * dry / (dry + max(float(propellant_kg), 0.0))


def static_tipover_deg(cfg: LanderConfig, propellant_kg: float) -> float:
    """Static tip-over angle of the lander standing on level ground [deg].

    The smallest tilt, about any edge of the footpad square, that brings the centre of mass
    over that edge: ``atan(d / h)`` with ``d`` the horizontal distance from the centre of mass
    to the edge and ``h`` its height above the footpads' ground contacts. About 36.5 deg for the
    default legs (``d = 2.2 / sqrt 2`` m, ``h = 1.9 + 0.2`` m).

    ``d`` is signed, negative for a centre of mass outside the footpad square: the angle is then
    negative, the tilt away from that edge the lander needs to balance (it cannot stand level).
    """
    feet = footpad_positions_B(cfg)[[0, 1, 3, 2]]  # around the square
    com = com_position_B(cfg, propellant_kg)
    h = com[2] + cfg.leg_drop_m + cfg.footpad_radius_m
    centre = feet[:, :2].mean(axis=0)
    d = min(_signed_distance_to_line(com[:2], feet[i, :2], feet[(i + 1) % 4, :2], centre) for i in range(4))
    return math.degrees(math.atan2(d, h))


def _signed_distance_to_line(p: np.ndarray, a: np.ndarray, b: np.ndarray, inside: np.ndarray) -> float:
    """Distance of ``p`` from the line through ``a`` and ``b`` [m], positive on the side of ``inside``."""
    ab = b - a

    def cross(q: np.ndarray) -> float:
        return float(ab[0] * (q[1] - a[1]) - ab[1] * (q[0] - a[0]))

    return math.copysign(1.0, cross(inside)) * cross(p) / float(np.hypot(*ab))


def support_margin_m(footpads_xy_L: np.ndarray, com_xy_L: np.ndarray) -> float:
    """Signed horizontal distance of the centre of mass inside the footpads' convex hull [m] (< 0: outside).

    Args:
        footpads_xy_L: Horizontal footpad positions (4, 2) [m].
        com_xy_L: Horizontal centre-of-mass position (2,) [m].
    """
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(footpads_xy_L, float)
    try:
        hull = ConvexHull(pts)
    except QhullError:  # degenerate (collinear pads, e.g. lying on its side): no area to stand on
        return -max(float(np.min(np.linalg.norm(pts - np.asarray(com_xy_L, float), axis=1))), 1e-9)
    # Each facet: n . x + c <= 0 inside, n unit; the margin is the smallest distance to a facet.
    return float(-np.max(hull.equations[:, :2] @ np.asarray(com_xy_L, float) + hull.equations[:, 2]))


# Sensor mounts: the altimeter sits this far forward of the axis; both sit this far below the body box
# so that rays and the view clear it [m].
ALTIMETER_OFFSET_X_M = 0.3
SENSOR_STANDOFF_M = 0.02


def altimeter_position_B(cfg: LanderConfig) -> np.ndarray:
    """Altimeter mount in the body frame (3,) [m]: the one calibration source for the world and the flight software."""
    return np.array([ALTIMETER_OFFSET_X_M, 0.0, -cfg.body_half_extents_m[2] - SENSOR_STANDOFF_M])


def camera_position_B(cfg: LanderConfig) -> np.ndarray:
    """Nadir-camera mount in the body frame (3,) [m]: the one calibration source for the world and the flight software."""
    return np.array([0.0, 0.0, -cfg.body_half_extents_m[2] - SENSOR_STANDOFF_M])


def lander_mjcf(cfg: LanderConfig, camera_fovy_deg: float) -> str:
    """MJCF ``<body>`` element of the lander, to be placed in ``<worldbody>``.

    Args:
        cfg: Lander configuration.
        camera_fovy_deg: Vertical field of view of the nadir camera [deg].

    Returns:
        MJCF text of the ``lander`` body with its free joint, geoms and sites.
    """
    hx, hy, hz = cfg.body_half_extents_m
    inertia = cfg.body_inertia_kgm2()
    tank_mass = max(cfg.propellant_kg, TANK_MASS_FLOOR_KG)
    tank_inertia = cfg.tank_inertia_kgm2(tank_mass)
    feet = footpad_positions_B(cfg)
    leg_top_z = -0.6 * hz
    g = LANDER_GEOM_GROUP
    contact = f'friction="{cfg.friction} 0.005 0.0001" solref="{CONTACT_SOLREF}"'
    legs = []
    for name, (x, y, z) in zip(FOOTPAD_NAMES, feet):
        x0, y0 = np.sign(x) * hx * 0.9, np.sign(y) * hy * 0.9
        legs.append(
            f'<geom name="leg_{name[5:]}" type="capsule" size="0.06" fromto="{x0} {y0} {leg_top_z} {x} {y} {z}" '
            f'group="{g}" contype="1" conaffinity="0" mass="0" rgba="0.7 0.7 0.7 1" {contact}/>'
        )
        legs.append(
            f'<geom name="{name}" type="sphere" size="{cfg.footpad_radius_m}" pos="{x} {y} {z}" '
            f'group="{g}" contype="1" conaffinity="0" mass="0" rgba="0.8 0.7 0.3 1" {contact}/>'
        )
    alt_x, alt_y, alt_z = altimeter_position_B(cfg)
    cam_x, cam_y, cam_z = camera_position_B(cfg)
    com_x, com_y, com_z = cfg.com_offset_B_m
    return f"""
    <body name="lander" pos="0 0 0">
      <freejoint name="lander_free"/>
      <inertial pos="{com_x} {com_y} {com_z}" mass="{cfg.dry_mass_kg}" diaginertia="{inertia[0]} {inertia[1]} {inertia[2]}"/>
      <geom name="hull" type="box" size="{hx} {hy} {hz}" group="{g}" contype="1" conaffinity="0"
            mass="0" rgba="0.85 0.75 0.3 1" {contact}/>
      {''.join(legs)}
      <site name="engine" pos="0 0 {-hz}" size="0.1"/>
      <site name="rcs" pos="0 0 0" size="0.05"/>
      <site name="imu" pos="0 0 0" size="0.05"/>
      <site name="altimeter" pos="{alt_x} {alt_y} {alt_z}" size="0.03"/>
      <camera name="nadir" pos="{cam_x} {cam_y} {cam_z}" xyaxes="1 0 0 0 1 0" fovy="{camera_fovy_deg}"/>
      <body name="tank" pos="0 0 0">
        <inertial pos="0 0 0" mass="{tank_mass}" diaginertia="{tank_inertia[0]} {tank_inertia[1]} {tank_inertia[2]}"/>
      </body>
    </body>"""


def actuator_mjcf(cfg: LanderConfig) -> str:
    """MJCF ``<actuator>`` children: engine thrust and three RCS torques.

    The engine actuator's control is the delivered thrust [N]; throttle
    limits, the on/off logic, the throttle response and thrust error are applied by
    :class:`models.actuators.PropulsionModel` before it writes ``data.ctrl``. The force acts
    at the engine site along :meth:`EngineConfig.thrust_direction_B` (body +z unless
    misaligned), fixed in the body; MuJoCo adds its moment about the centre of mass.
    """
    tau = cfg.rcs_torque_max_Nm
    dx, dy, dz = cfg.engine.thrust_direction_B()
    return f"""
    <motor name="engine" site="engine" gear="{dx} {dy} {dz} 0 0 0" ctrllimited="true" ctrlrange="0 {cfg.engine.thrust_max_N * 1.5}"/>
    <motor name="rcs_x" site="rcs" gear="0 0 0 1 0 0" ctrllimited="true" ctrlrange="{-tau} {tau}"/>
    <motor name="rcs_y" site="rcs" gear="0 0 0 0 1 0" ctrllimited="true" ctrlrange="{-tau} {tau}"/>
    <motor name="rcs_z" site="rcs" gear="0 0 0 0 0 1" ctrllimited="true" ctrlrange="{-tau} {tau}"/>"""


def sensor_mjcf() -> str:
    """MJCF ``<sensor>`` children: the truth IMU signals at the IMU site."""
    return """
    <accelerometer name="imu_acc" site="imu"/>
    <gyro name="imu_gyro" site="imu"/>"""
