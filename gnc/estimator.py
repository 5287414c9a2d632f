"""Navigation filter: an extended Kalman filter on IMU, altimeter, star tracker and vision, with stochastic cloning.

Ports (Drake-style block ``NavFilter``)::

                      +-----------------------------------+
    ImuMessage ------>| propagate_imu       (100 Hz)      |   (alias predict_imu)
    AttitudeMsg ----->| set_attitude        (10 Hz)       |   (alias update_attitude)
    AltimeterMsg ---->| update_altimeter    (20 Hz)       |----> NavState (nav_state, at the control rate)
    frame time ------>| clone_frame         (camera rate) |----> UpdateRecord (return value, and .log)
    relative z,H,R -->| update_relative     (camera rate) |
    velocity z,R ---->| update_velocity     (any rate)    |
                      +-----------------------------------+

    Inputs: :class:`gnc.messages.ImuMessage`, :class:`gnc.messages.AttitudeMessage`,
        :class:`gnc.messages.AltimeterMessage` (all through :meth:`NavFilter.process`
        or their own methods); at each camera frame a position clone
        (``clone_frame``) and a measurement relating the current position to
        the clone (``update_relative``, from :mod:`gnc.vision_nav`); optionally a
        ground-relative velocity with its covariance (``update_velocity``).
        Messages must arrive in time order (integer ns); an IMU sample not after
        the last propagation is ignored.
    Outputs: :class:`gnc.navstate.NavState` (``nav_state``) with ``P`` the 6x6
        position/velocity covariance (the full covariance is ``NavFilter.P``);
        one :class:`UpdateRecord` per measurement update (returned and appended
        to ``NavFilter.log``); counters per input (``NavFilter.counters``).

State (24), in this order: ``r_BL_L`` (3) [m], ``v_BL_L`` (3) [m/s], accelerometer
bias ``b_a_B`` (3) [m/s^2], ``h_terrain`` (1) [m], the height of the ground under
the altimeter footprint above the target's elevation (see the altimeter below),
``r_clone_L`` (3) [m], a stochastic clone of ``r_BL_L`` taken at the last camera frame
(Roumeliotis & Burdick 2002; the MSCKF and OpenVINS clone poses the same way), and
two image offsets ``d_clone`` (2) and ``d_new`` (2) [-]: the mean error of the
tracked image positions in the clone's frame and in the current frame (see the
relative update below), ``b_flow`` (2) [-], a slowly varying bias of the measured
flow (the tracker's sub-pixel bias, which follows the slowly changing image motion), a
Gauss-Markov process of time constant ``vision_bias_time_s`` whose 1-sigma is
``vision_bias_ground_m`` over the camera height (:func:`vision_bias_sigma`), and ``h_view`` (1) [m], the mean
height of the ground the camera tracks above the target's elevation: the scale of the vision measurement, a
Gauss-Markov process of 1-sigma ``view_ground_sigma_m`` that decorrelates over
``view_ground_correlation_length_m`` of travel, and ``s_terrain`` (2) [-], the slope
``(dh/dx, dh/dy)`` of the ground at the altimeter footprint, and ``s_view`` (2) [-], the
slope of the ground the camera tracks (a Gauss-Markov process over the travel, of 1-sigma
:func:`view_slope_sigma` at the camera's height). The relief's 1-sigma (terrain and viewed ground) follows
the onboard site map (:func:`relief_scale`): the landing site, cleared of craters and boulders, is about
4x smoother than the terrain around it. With map fixes (``make_estimator(map_bias_sigma_m=...)``) two more
states follow, ``b_map`` (2) [m]: the error common to consecutive map fixes (the same ground seen under slowly
changing views), a Gauss-Markov process that :class:`gnc.map_nav.MapNavigator` steps before each fix
(:meth:`NavFilter.step_map_bias`) and that each fix measures with the position; without it, fixes that share an
error would be averaged as if independent; and ``b_kz`` (1) [m], unused until a keyframe is taken below the
last map fix, when ``(b_map, b_kz)`` become the error of the pose the keyframe was laid on the ground with
(:meth:`NavFilter.map_bias_to_keyframe`). With map fixes the filter also carries the **regional relief**
(``make_estimator(regional_relief=True)``), four more states: ``u_R`` (1) [m] and its slope (2) [-], a smooth
Matern-3/2 field of 1-sigma ``regional_relief_sigma_m`` and length ``regional_relief_length_m`` under the
altimeter footprint, and ``u_R0`` (1) [m], the same field's value at the target (see the altimeter below).
L is the landing frame (origin at the target on the
surface, x east, y north, z up, gravity ``g_L = [0, 0, -g]``); B is the body frame.

Model:
    * Prediction, per IMU sample k at ``t_k`` (a filterpy ``predict``): the sample
      is taken as the mean specific force over ``(t_{k-1}, t_k]`` (what a
      delta-v IMU outputs, and what the bench's IMU sees while the thrust is held
      over the control period), so ``a = R_LB (f_B - b_a) + g_L`` is held over
      the interval and ``r += v dt + a dt^2 / 2``, ``v += a dt``. This is linear in
      the state given ``R_LB``: ``F`` carries ``-R dt`` and ``-R dt^2 / 2`` in the bias
      columns and ``B u`` the measured specific force plus gravity. ``R_LB`` is the
      attitude at mid-interval.
    * Attitude: the star tracker's ``q_LB`` is taken as truth; between fixes it
      is carried forward with the gyro (``attitude_propagation="gyro"``, the
      default) or held (``"hold"``). Gyro bias is not estimated (its effect over a
      100 ms fix interval, ~1e-6 rad, is far below the tracker's noise). The
      tracker's error ``sigma_theta`` (held for one fix period ``T``) tilts the
      measured specific force by ``sigma_theta |f|``; it is folded into ``Q`` as an
      extra acceleration white noise of density ``sigma_theta^2 |f|^2 T``.
    * Accelerometer bias: random walk (density ``accel_bias_walk``), initial
      1-sigma ``init_accel_bias_sigma_mps2`` per axis.
    * Process noise per step ``dt``: accelerometer white noise of density ``N``
      enters as ``Q_vv = N^2 dt I``, ``Q_rv = N^2 dt^2 / 2 I``, ``Q_rr = N^2 dt^3 / 4 I``
      (a sampled noise held over the step); the bias walk as ``Q_bb = W^2 dt I``.
    * Altimeter (``update_altimeter``): ASSUMPTION: the terrain is locally planar
      and horizontal, at the target's elevation (z = 0) up to a relief ``h_terrain``
      of 1-sigma ``terrain_relief_sigma_m`` (the ground under the lander is not at
      the target's elevation: craters, boulders). The slant range from the
      altimeter (at the lever arm ``l_B`` from the body origin) along the boresight
      ``b_L = R_LB b_B`` is ``rho = (r_z + (R_LB l_B)_z - h_terrain) / c`` with
      ``c = -b_L,z``; it is used only while ``c > cos(altimeter_max_incidence_deg)``.
      Its noise is the altimeter spec, 1-sigma ``hypot(floor, frac * rho)``.
      The relief is a smooth Gauss-Markov field, carried with its slope from
      one used footprint to the next (:func:`matern32_terrain_step`): an
      isotropic Matern-3/2 covariance ``sigma^2 (1 + d/l) exp(-d/l)`` of 1-sigma
      ``terrain_relief_sigma_m`` and length ``terrain_correlation_length_m``.
      With a length of 0 every sample sees independent ground, which is exactly
      the spec noise plus a white relief term ``terrain_relief_sigma_m / c`` in
      quadrature. Real relief is correlated along track; treated as white it is
      averaged away and the vertical channel becomes overconfident. A
      first-order (exponential) process is the opposite mistake near the ground:
      it makes the relief between samples a few centimetres apart far rougher
      than it is (its slope has no finite variance), so each range says little
      about the vertical velocity. The defaults, 4 m and 30 m (slope 1-sigma
      0.13), are the default terrain's statistics over dispersed terrain seeds:
      within 400 m of the target (12 terrain seeds), the height's RMS deviation
      is 3.8 m, and the RMS height change over 0.1, 1, 10, 30 and 100 m is
      0.013, 0.13, 1.21, 2.92 and 5.03 m, where the model gives 0.013, 0.13,
      1.20, 2.91 and 5.20 m. (The first-order process these replace, 3 m over
      100 m, gave 0.13 m over 0.1 m: ten times rougher.) The Jacobian of the
      step with respect to the state (through the footprint) is neglected.
    * Regional relief (with map fixes): the relief above is stationary, so two
      footprints 60 m apart are nearly independent, and inside the landing site
      its 1-sigma is the site's 0.9 m. The ground about the target's elevation is
      not: site selection clears craters and boulders, not the smooth regional
      slope, and the height above the target's elevation of ground ``d`` from the
      target grows with ``d``. Once map fixes pin the horizontal position,
      a filter that models only the stationary relief averages a persistent 1-3 m
      offset of the site as if each 30 m brought new ground (its height error 1-3 m
      under a 0.5-0.8 m sigma). So a second, smooth field ``u_R`` is added, taken
      about its value at the target: the footprint is ``h_terrain + u_R - u_R0``
      above the target's elevation. ``u_R`` and its slope step with the local
      field over the same displacement (:func:`matern32_terrain_step`, no site
      factor); ``u_R0`` is a constant of the ground, correlated with ``u_R`` as
      the field is (:func:`regional_relief_prior`). The height it adds has the
      variance ``2 (s^2 - C(d))``, none at the target. The defaults, 2.2 m and
      100 m, are a least-squares fit (in log RMS, rings from 40 m to 450 m) to the
      default terrain's fBm alone (craters and boulders off) about the target, over
      12 dispersed terrain seeds: RMS 0.71, 1.05, 1.46, 1.79, 2.23, 2.75 and
      2.98 m at 20-40, 40-70, 70-100, 100-150, 150-200, 200-300 and 300-450 m,
      where the model gives 0.61, 1.02, 1.44, 1.88, 2.28, 2.66 and 2.98 m. Its slope
      (1-sigma 0.022) is small beside the local field's (0.13) but not beside the
      cleared site's (0.03): inside the site the local field keeps the rest of the
      site's slope variance (:func:`local_site_config`: 0.61 m in place of 0.9 m), so
      that the range rate is not given more slope than the site has.
    * Stochastic cloning (``clone_frame``): at a camera frame the position is
      copied into the clone slot, with its covariance and every cross-covariance
      (``x_c = r``, ``P_cc = P_rr``, ``P_c* = P_r*``). The clone does not move in
      prediction (identity in ``F``, no process noise) but is corrected by every
      update through its correlations. A measurement between two frames
      (``update_relative``, ``h(x) = H_1 r(t) + H_0 r_clone``) therefore accounts
      exactly for the estimate at the first frame being the same one that the
      previous frame pair used: no vertical displacement is differenced out of
      two filter outputs.
    * Shared-frame image noise: a frame's pixel noise moves the tracked positions
      of that frame, and it enters the pair that ends at the frame and the pair
      that starts there with opposite signs (consecutive measurements' errors
      are correlated, -1/2 for pure per-frame noise). The filter carries it
      exactly, as a state: each pair's measurement is
      ``z = h(r, r_clone) + d_new - d_clone + w``, where ``d_new`` (the current
      frame's offset) enters with its prior covariance ``R_frame`` at the update
      and becomes ``d_clone`` (with its posterior and correlations) when the
      frame is cloned. ``w`` (covariance ``R``) is the part that is white.
    * Velocity (``update_velocity``): a ground-relative velocity in L with its
      covariance (``H = [0 I 0]``), all three components or a subset (``axes``).
    * Gyro attitude (``gyro_attitude``): besides the star-tracker-reset attitude,
      the filter integrates the gyro alone from the first fix, never reset. Its
      relative rotation between two frames is what vision uses: two independent
      star-tracker fixes would rotate every ray of one frame against the other.
    * Measurement time: a measurement stamped ``dt_m = t_meas - t_filter`` away from
      the filter time (at most ``max_update_lag_s``) is predicted to first order:
      ``r_z + v_z dt_m`` for the altimeter, ``v + a dt_m`` for the velocity.
    * Gating: every update is chi-square gated; it is rejected when its
      ``NIS = y^T S^-1 y`` exceeds ``chi2.ppf(gate_prob, dim)``; a rejected update
      leaves the state and covariance unchanged.
    * Messages with a non-finite value (or a malformed array) are rejected and
      counted, never propagated into the state.

The sensor defaults below are the **specification** of the default sensors: the
top of each range that a campaign disperses the real units over
(``models/sensors.py``: IMU, altimeter, star tracker). Flight software knows its
sensors' datasheets, never the drawn values. The altimeter's mounting is the
vehicle's calibration, passed to :func:`make_estimator` by whoever builds the
flight software from the same source as the world.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.config import validated_config
from gnc.filterpy_import import ExtendedKalmanFilter
from gnc.guidance import LUNAR_GRAVITY_MPS2
from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage
from gnc.navstate import NavState
from gnc.numeric import all_finite, chi2_ppf

NS_PER_S = 1_000_000_000
ARCSEC_TO_RAD = math.pi / (180.0 * 3600.0)

# State layout.
DIM_X = 24
IDX_R = slice(0, 3)
IDX_V = slice(3, 6)
IDX_BA = slice(6, 9)
IDX_RZ = 2
IDX_VZ = 5
IDX_H = 9  # terrain height under the altimeter footprint, relative to the target's elevation
IDX_C = slice(10, 13)  # position clone at the last camera frame
IDX_DC = slice(13, 15)  # image offset of the last camera frame (the clone's frame)
IDX_DN = slice(15, 17)  # image offset of the current camera frame
IDX_BF = slice(17, 19)  # slowly varying bias of the vision flow measurement
IDX_G = 19  # mean height of the ground the camera tracks, relative to the target's elevation
IDX_S = slice(20, 22)  # slope of the terrain at the altimeter footprint, (dh/dx, dh/dy) [-]
IDX_SV = slice(22, 24)  # slope of the ground the camera tracks, (dh/dx, dh/dy) [-]
# Only in a filter made with a map bias (``nav_map = "on"``, :func:`make_estimator`): the error common to
# consecutive map fixes, in the map frame (2) [m], appended after the 24 states above.
IDX_MB = slice(24, 26)
# And one more with it: the height error of a keyframe's pose (see :meth:`NavFilter.map_bias_to_keyframe`) [m].
IDX_KZ = 26
# Only in a filter made with the regional relief (``make_estimator(regional_relief=True)``, with map fixes):
# the smooth regional field ``u_R`` under the altimeter footprint (1) [m] with its slope (2) [-], and its value
# at the target ``u_R0`` (1) [m]; the footprint's height above the target's elevation is
# ``h_terrain + u_R - u_R0`` (see the altimeter in the module docstring).
IDX_RR = 27
IDX_RRS = slice(28, 30)
IDX_RR0 = 30
DIM_REGIONAL = 31  # the state count with the map states and the regional relief
_IDX_TERRAIN = np.array([IDX_H, *range(IDX_S.start, IDX_S.stop)])  # the terrain's height and slope, stepped together
_IX_TERRAIN = np.ix_(_IDX_TERRAIN, _IDX_TERRAIN)
# With the regional relief, its field and slope are stepped with them (u_R0 is a constant of the ground).
_IDX_TERRAIN_R = np.array([*_IDX_TERRAIN, IDX_RR, *range(IDX_RRS.start, IDX_RRS.stop)])
_IX_TERRAIN_R = np.ix_(_IDX_TERRAIN_R, _IDX_TERRAIN_R)
# Vision's consider states: the vertical channel (height, vertical velocity and accelerometer bias,
# the clone's height) and the altimeter's terrain. The flow depends on them (through the camera's
# vertical displacement and height), but they are left to the altimeter: the flow's divergence
# would read terrain slope in view as vertical velocity.
_VISION_CONSIDER = np.array([IDX_RZ, IDX_VZ, IDX_BA.start + 2, IDX_H, IDX_C.start + 2,
                             *range(IDX_S.start, IDX_S.stop)])

KIND_ALTIMETER = "altimeter"
KIND_VELOCITY = "velocity"
KIND_VISION = "vision"
KIND_MAP = "map"  # map-relative position fixes (gnc.map_nav); counted only once one is made
KIND_DIVERGENCE = "divergence"  # vision's flow divergence without an altimeter; counted only once one is made
# Why an update was not applied (UpdateRecord.reason); "" when accepted.
REASON_GATE = "gate"
REASON_NONFINITE = "nonfinite"
REASON_STALE = "stale"
REASON_INVALID_R = "invalid_covariance"
REASON_NO_CLONE = "no_clone"

# Small-angle threshold below which the rotation-vector exponential uses its series [rad].
_SMALL_ANGLE_RAD = 1e-9
# Quaternions from the star tracker whose norm is off by more than this are rejected [-].
_QUAT_NORM_TOL = 1e-3


# --------------------------------------------------------------------------- configuration
class EstimatorConfig(BaseModel):
    """Navigation-filter tuning: sensor specifications, initial uncertainty, gating.

    Defaults are the specification of the default IMU, altimeter and star
    tracker of ``models/sensors.py``: the top of the ranges the default
    campaign disperses them over.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    gravity_mps2: float = Field(LUNAR_GRAVITY_MPS2, gt=0.0, description="surface gravity magnitude [m/s^2]")
    # IMU specification (the datasheet's bounds, not the unit's drawn values).
    accel_noise_density: float = Field(
        1.4e-3, ge=0.0, description="accelerometer white noise density, specification [m/s^2/sqrt(Hz)]"
    )
    accel_bias_walk: float = Field(1e-4, ge=0.0, description="accelerometer bias random walk [m/s^2/sqrt(s)]")
    init_accel_bias_sigma_mps2: float = Field(
        7e-3, gt=0.0, description="initial accelerometer bias 1-sigma per axis (IMU turn-on bias, specification) [m/s^2]"
    )
    gyro_noise_density: float = Field(
        1e-5, ge=0.0, description="gyro white noise density, specification [rad/s/sqrt(Hz)]"
    )
    gyro_bias_sigma_radps: float = Field(
        1e-5, ge=0.0, description="gyro turn-on bias 1-sigma per axis, specification [rad/s]"
    )
    # Star tracker specification.
    attitude_sigma_arcsec: float = Field(
        14.0, ge=0.0, description="star-tracker attitude noise, 1-sigma per axis, specification [arcsec]"
    )
    attitude_period_s: float = Field(
        0.1, gt=0.0, description="star-tracker period: how long one attitude error is held [s]"
    )
    attitude_propagation: Literal["gyro", "hold"] = Field(
        "gyro", description="between star-tracker fixes: integrate the gyro, or hold the last fix"
    )
    # Altimeter specification (its mounting is the vehicle's calibration, given to make_estimator).
    altimeter_noise_sigma_m: float = Field(
        0.08, ge=0.0, description="altimeter range noise floor, 1-sigma, specification [m]"
    )
    altimeter_noise_frac: float = Field(1e-3, ge=0.0, description="altimeter range noise per metre of range [-]")
    altimeter_max_incidence_deg: float = Field(
        60.0, gt=0.0, lt=90.0, description="largest boresight angle from nadir used for updates [deg]"
    )
    terrain_relief_sigma_m: float = Field(
        4.0, ge=0.0, description="1-sigma height of the ground under the lander about the target's elevation [m]"
    )
    terrain_correlation_length_m: float = Field(
        30.0, ge=0.0,
        description="length l of that relief's Matern-3/2 covariance (slope 1-sigma: sigma / l) [m]; 0: white",
    )
    regional_relief_sigma_m: float = Field(
        2.2, gt=0.0,
        description="with map fixes: 1-sigma of the smooth regional relief that site selection does not clear, "
                    "a second Matern-3/2 field whose difference from its value at the target adds to the relief "
                    "above [m]",
    )
    regional_relief_length_m: float = Field(
        100.0, gt=0.0, description="length of that regional field's Matern-3/2 covariance [m]"
    )
    site_radius_m: float = Field(
        70.0, ge=0.0,
        description="radius of the landing site around the target that site selection cleared of craters and "
                    "boulders (the onboard site map; the default terrain's target_clear_radius_m) [m]; 0: no site map",
    )
    site_relief_sigma_m: float = Field(
        0.9, gt=0.0,
        description="1-sigma relief inside the landing site, in place of terrain_relief_sigma_m there (the site "
                    "survey's figure) [m]",
    )
    site_relief_ramp_m: float = Field(
        30.0, gt=0.0,
        description="distance beyond the site's edge over which the relief grows to terrain_relief_sigma_m [m]",
    )
    view_ground_sigma_m: float = Field(
        4.0, ge=0.0, description="1-sigma mean height of the ground the camera tracks, about the target's elevation [m]"
    )
    view_ground_samples: int = Field(
        12, ge=1,
        description="independent places at which the tracks sample the ground in view (about one per "
                    "template) for the averaging of its relief [-]",
    )
    view_ground_correlation_length_m: float = Field(
        50.0, gt=0.0, description="travel over which that mean height decorrelates [m]"
    )
    view_width_per_height: float = Field(
        1.15, gt=0.0,
        description="width of the ground patch the camera tracks per metre of height, 2 tan(fov / 2) [-] "
                    "(the default camera: 60 deg)",
    )
    vision_bias_ground_m: float = Field(
        1.7e-3, ge=0.0,
        description="1-sigma of the slowly varying error of the displacement between two frames that vision "
                    "measures, on the ground [m]; as an error of the flow (ray angle) it is this over the camera "
                    "height. Calibrated on rendered descents: the tracker's mean error over windows of 1-4 s, "
                    "less its per-frame part, is 6e-6 rad at 150-600 m and 1.4e-5 rad at 60-150 m, about "
                    "1.7 mm on the ground, with a 1 s time constant",
    )
    vision_bias_time_s: float = Field(1.0, gt=0.0, description="time constant of that error [s]")
    # Initial uncertainty (the bench draws the initial estimate with these).
    init_pos_sigma_m: float = Field(20.0, gt=0.0, description="initial position 1-sigma per axis [m]")
    init_vel_sigma_mps: float = Field(1.0, gt=0.0, description="initial velocity 1-sigma per axis [m/s]")
    # Update management.
    gate_prob: float = Field(
        0.999, gt=0.0, lt=1.0, description="chi-square gate: probability of accepting a consistent measurement [-]"
    )
    max_update_lag_s: float = Field(
        0.2, ge=0.0, description="largest |t_meas - t_filter| of a measurement that is still used [s]"
    )


# --------------------------------------------------------------------------- records
@dataclass(frozen=True, slots=True)
class UpdateRecord:
    """One measurement update, accepted or not (arrays are read-only copies).

    Attributes:
        t_ns: Measurement time of validity [ns].
        kind: ``"altimeter"``, ``"velocity"`` or ``"vision"``.
        z: Measurement, (m,) [m] or [m/s].
        y: Innovation ``z - h(x_prior)``, (m,); NaN when not computed.
        S: Innovation covariance, (m, m); NaN when not computed.
        nis: Normalised innovation squared ``y^T S^-1 y`` [-]; NaN when not computed.
        accepted: Whether the update was applied.
        reason: Why it was not applied (``"gate"``, ``"nonfinite"``, ``"stale"``,
            ``"invalid_covariance"``); ``""`` when accepted.
        x_prior: State before the update, (24,) (for the altimeter, before the terrain
            state is carried to the new footprint).
        P_prior: Covariance before the update, (24, 24).
        x_post: State after the update (``x_prior`` when rejected), (24,).
        P_post: Covariance after the update (``P_prior`` when rejected), (24, 24).
    """

    t_ns: int
    kind: str
    z: np.ndarray
    y: np.ndarray
    S: np.ndarray
    nis: float
    accepted: bool
    reason: str
    x_prior: np.ndarray
    P_prior: np.ndarray
    x_post: np.ndarray
    P_post: np.ndarray


def _frozen(a: np.ndarray) -> np.ndarray:
    """A read-only float copy (records must not change after the fact)."""
    out = a.astype(float)  # always a copy
    out.flags.writeable = False
    return out


def _new_counters() -> dict[str, dict[str, int]]:
    return {
        "imu": {"used": 0, "stale": 0, "invalid": 0, "no_attitude": 0},
        "attitude": {"used": 0, "invalid": 0},
        KIND_ALTIMETER: {"accepted": 0, "rejected": 0, "invalid": 0, "skipped": 0},
        KIND_VELOCITY: {"accepted": 0, "rejected": 0, "invalid": 0},
        KIND_VISION: {"accepted": 0, "rejected": 0, "invalid": 0},
    }


# --------------------------------------------------------------------------- attitude helpers (plain floats: cheap at 100 Hz)
Quat = tuple[float, float, float, float]


def _quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a (x) b`` of scalar-first quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _quat_exp(wx: float, wy: float, wz: float, dt: float) -> Quat:
    """Quaternion of the rotation vector ``omega * dt`` (scalar-first)."""
    rate = math.sqrt(wx * wx + wy * wy + wz * wz)
    half = 0.5 * rate * dt
    if half < _SMALL_ANGLE_RAD:
        k = 0.5 * dt  # sin(x)/x -> 1
        return (1.0, k * wx, k * wy, k * wz)
    k = math.sin(half) / rate
    return (math.cos(half), k * wx, k * wy, k * wz)


def _quat_normalized(q: Quat) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _quat_rows(q: Quat) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The nine elements of :func:`quat_to_matrix`, row by row, as floats."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy))


def quat_to_matrix(q: Quat) -> np.ndarray:
    """Rotation matrix ``R_LB`` (3, 3) of a unit scalar-first quaternion ``q_LB``.

    Same convention as ``scipy.spatial.transform.Rotation.from_quat(q, scalar_first=True)``
    (tested against it), without building a Rotation per IMU step.
    """
    return np.array(_quat_rows(q)).reshape(3, 3)


def _const(_x: np.ndarray, value: np.ndarray) -> np.ndarray:
    """filterpy callback returning a precomputed H or h(x) (both are evaluated at the prior)."""
    return value


def _vec3(a: Any, name: str) -> np.ndarray:
    """A finite (3,) float array, or a one-line ValueError naming ``name``."""
    arr = np.asarray(a, dtype=float)
    if arr.shape != (3,):
        raise ValueError(f"{name} has shape {arr.shape}; expected (3,)")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} = {arr.tolist()}: must be finite")
    return arr


# --------------------------------------------------------------------------- the filter
class NavFilter:
    """Extended Kalman filter (filterpy) on position, velocity, accelerometer bias, terrain height and a position clone.

    Build it with :func:`make_estimator`. See the module docstring for the model.

    Attributes:
        cfg: The validated configuration.
        ekf: The filterpy :class:`~filterpy.kalman.ExtendedKalmanFilter` holding
            ``x`` (n,) and ``P`` (n, n): n = 24, 27 with the map fixes' common error and a
            keyframe's height error, or 31 with the regional relief besides (``dim_x``).
        log: One :class:`UpdateRecord` per measurement update, in call order.
        counters: Per input (``imu``, ``attitude``, ``altimeter``, ``velocity``),
            counts of used / accepted / rejected / invalid / skipped / stale messages.
        consecutive_rejections: Per update kind, how many updates in a row were
            rejected by the gate (a fault-detection hook; reset on acceptance).
    """

    def __init__(self, cfg: EstimatorConfig, x0: np.ndarray, P0: np.ndarray, t0_ns: int,
                 q0_LB: Quat | None, altimeter_mount_B_m: np.ndarray, gyro_delta_angle: bool = False) -> None:
        """Use :func:`make_estimator`; this constructor does not validate its inputs."""
        self.cfg = cfg
        n = self.dim_x = int(x0.shape[0])  # DIM_X, DIM_X + 3 with the map bias and the keyframe height,
        # or DIM_REGIONAL with the regional relief besides
        self._regional = n == DIM_REGIONAL
        # The site map of the local relief under the altimeter (the regional field takes its share of the site's).
        self._cfg_terrain = local_site_config(cfg) if self._regional else cfg
        ekf = ExtendedKalmanFilter(dim_x=n, dim_z=1, dim_u=3)
        ekf.x = x0.copy()
        ekf.P = P0.copy()
        self.ekf = ekf
        self.log: list[UpdateRecord] = []
        self.counters = _new_counters()
        self.consecutive_rejections = {KIND_ALTIMETER: 0, KIND_VELOCITY: 0, KIND_VISION: 0}

        self._t_ns = int(t0_ns)
        self._g_L_tuple = (0.0, 0.0, -cfg.gravity_mps2)  # gravity in L [m/s^2]
        self._q_LB: Quat | None = q0_LB  # attitude at the filter time
        self._q_gyro: Quat | None = q0_LB  # gyro-only attitude, never reset by a fix (relative rotations)
        self._clone_t_ns: int | None = None  # time of the position clone; None: no clone held
        self._offset_clone_known = False  # d_clone holds the clone frame's offset (it was introduced by an update)
        self._offset_new_known = False  # d_new holds the current frame's offset
        self._omega_B = (0.0, 0.0, 0.0)  # latest gyro sample [rad/s]
        self._have_rate = False  # a gyro sample has been received
        self._a_L = np.zeros(3)  # latest estimated total acceleration [m/s^2] (for measurement-time shifts)
        self._gyro = cfg.attitude_propagation == "gyro"
        self._lever_B = np.array(altimeter_mount_B_m, dtype=float)
        self._gyro_delta_angle = bool(gyro_delta_angle)  # rate samples are interval means (an integrating gyro)
        self._footprint_L: np.ndarray | None = None  # (2,) horizontal footprint of the last applied range [m]
        # Relief amplitude (the site map's factor on the relief 1-sigma) the terrain and view states were last
        # carried at; the initial covariance is built at the initial position's (make_estimator).
        P_xy0 = P0[:2, :2]
        self._k_terrain = relief_scale(self._cfg_terrain, x0[:2], P_xy0)
        self._k_view = relief_scale(cfg, x0[:2], P_xy0 + view_spread(cfg, float(x0[IDX_RZ] - x0[IDX_G])))
        self._sigma_bf = vision_bias_sigma(cfg, float(x0[IDX_RZ] - x0[IDX_G]))  # flow error's 1-sigma [rad]
        self._sigma_g = view_ground_sigma(cfg, float(x0[IDX_RZ] - x0[IDX_G]), self._k_view)  # h_view's [m]
        self._cos_max_incidence = math.cos(math.radians(cfg.altimeter_max_incidence_deg))
        self._accel_psd = cfg.accel_noise_density**2  # [(m/s^2)^2 / Hz]
        self._att_var_time = (cfg.attitude_sigma_arcsec * ARCSEC_TO_RAD) ** 2 * cfg.attitude_period_s  # [rad^2 s]
        self._gate = {n: float(chi2_ppf(cfg.gate_prob, n)) for n in (1, 2, 3)}
        self._max_lag_ns = int(round(cfg.max_update_lag_s * NS_PER_S))

        # Per-step matrices, rebuilt only when the IMU period changes.
        self._dt_ns = -1
        self._F = np.eye(n)
        self._Q = np.zeros((n, n))
        self._Q_shape = np.zeros((6, 6))
        self._H_vel = np.zeros((3, n))
        self._H_vel[:, IDX_V] = np.eye(3)
        self._T_terrain = np.eye(n)  # the terrain step's transition (_linear_step writes its block)
        self._ix_terrain = _IX_TERRAIN_R if self._regional else _IX_TERRAIN  # the states the step moves

    # ------------------------------------------------------------------ properties
    @property
    def time_ns(self) -> int:
        """Time of the state: the last propagation (or t0) [ns]."""
        return self._t_ns

    @property
    def x(self) -> np.ndarray:
        """State copy, (dim_x,), in the order of the module docstring (``IDX_*``)."""
        return self.ekf.x.copy()

    @property
    def P(self) -> np.ndarray:
        """Covariance copy, (24, 24)."""
        return self.ekf.P.copy()

    @property
    def clone_time_ns(self) -> int | None:
        """Time of the position clone [ns]; None when no clone is held."""
        return self._clone_t_ns

    def gyro_attitude(self) -> np.ndarray | None:
        """The gyro-only attitude at the filter time, (4,) scalar-first; None before the first fix.

        It starts at the first star-tracker fix and is then integrated from the
        gyro alone, never reset. Its absolute value drifts; the rotation between
        two of its values is the gyro's relative rotation, accurate to the gyro
        noise, which is what vision needs between two frames.
        """
        return None if self._q_gyro is None else np.array(self._q_gyro)

    @property
    def q_LB(self) -> np.ndarray | None:
        """Attitude used at the filter time, (4,) scalar-first; None before the first fix."""
        return None if self._q_LB is None else np.array(self._q_LB)

    # ------------------------------------------------------------------ dispatch
    def process(self, msg: ImuMessage | AttitudeMessage | AltimeterMessage) -> UpdateRecord | None:
        """Route one sensor message to its handler.

        Returns:
            The altimeter's :class:`UpdateRecord` when one was made, else None.
        """
        if isinstance(msg, ImuMessage):
            self.propagate_imu(msg)
            return None
        if isinstance(msg, AttitudeMessage):
            self.set_attitude(msg)
            return None
        if isinstance(msg, AltimeterMessage):
            return self.update_altimeter(msg)
        raise TypeError(f"NavFilter.process: unsupported message type {type(msg).__name__}")

    # ------------------------------------------------------------------ attitude
    def set_attitude(self, msg: AttitudeMessage) -> bool:
        """Take a star-tracker fix (carried to the filter time with the latest gyro sample).

        Args:
            msg: Attitude message; ``q_LB`` (4,) scalar-first.

        Returns:
            True when used; False (counted as invalid) for a non-finite, malformed
            or non-unit quaternion.
        """
        try:
            w, x, y, z = (float(c) for c in np.asarray(msg.q_LB, dtype=float).reshape(4))
        except (TypeError, ValueError):
            self.counters["attitude"]["invalid"] += 1
            return False
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if not math.isfinite(norm) or abs(norm - 1.0) > _QUAT_NORM_TOL:
            self.counters["attitude"]["invalid"] += 1
            return False
        q: Quat = (w / norm, x / norm, y / norm, z / norm)
        if self._gyro and msg.t_ns != self._t_ns:
            # The fix is valid at msg.t_ns; the state is at self._t_ns.
            dt = (self._t_ns - msg.t_ns) / NS_PER_S
            q = _quat_normalized(_quat_mul(q, _quat_exp(*self._omega_B, dt)))
        self._q_LB = q
        if self._q_gyro is None:
            self._q_gyro = q
        self.counters["attitude"]["used"] += 1
        return True

    # ------------------------------------------------------------------ prediction
    def _set_step_matrices(self, dt_ns: int) -> None:
        """Rebuild the dt-dependent parts of F, B and Q (once per distinct IMU period)."""
        dt = dt_ns / NS_PER_S
        eye3 = np.eye(3)
        self._F[IDX_R, IDX_V] = dt * eye3
        self._bias_coupling = np.repeat([-0.5 * dt * dt, -dt], 3)[:, None]  # (6, 1): rows (r, v) of d/d(b_a), per R_LB
        self.ekf.B = np.vstack([0.5 * dt * dt * eye3, dt * eye3, np.zeros((self.dim_x - 6, 3))])
        # Acceleration noise held over one step, per unit PSD: dv = n dt, dr = n dt^2/2, var(n) = PSD/dt.
        shape = np.zeros((self.dim_x, self.dim_x))
        shape[IDX_R, IDX_R] = 0.25 * dt**3 * eye3
        shape[IDX_R, IDX_V] = shape[IDX_V, IDX_R] = 0.5 * dt**2 * eye3
        shape[IDX_V, IDX_V] = dt * eye3
        self._Q_shape = shape[:6, :6].copy()  # it is zero outside the position / velocity block
        q = np.zeros((self.dim_x, self.dim_x))
        q[IDX_BA, IDX_BA] = self.cfg.accel_bias_walk**2 * dt * eye3
        self._Q = q  # the step's Q; its position / velocity block is set per sample (propagate_imu)
        self._dt_ns = dt_ns

    def propagate_imu(self, msg: ImuMessage) -> bool:
        """Propagate the state and covariance to ``msg.t_ns`` with one IMU sample.

        Args:
            msg: IMU sample; ``f_B`` (3,) [m/s^2] is the mean specific force over the
                interval since the previous sample, ``omega_B`` (3,) [rad/s].

        Returns:
            True when the filter was propagated; False when the sample was ignored:
            not after the filter time (``stale``), non-finite or malformed
            (``invalid``), or no attitude known yet (``no_attitude``; the filter
            time does not advance).
        """
        counts = self.counters["imu"]
        t_ns = msg.t_ns
        if t_ns <= self._t_ns:
            counts["stale"] += 1
            return False
        try:
            fx, fy, fz = msg.f_B.tolist()
            wx, wy, wz = msg.omega_B.tolist()
        except (AttributeError, TypeError, ValueError):
            counts["invalid"] += 1
            return False
        # One sum is non-finite iff some term is (barring overflow of absurd values, also rejected).
        if not math.isfinite(fx + fy + fz + wx + wy + wz):
            counts["invalid"] += 1
            return False
        # A point-sampling gyro gives the rate at t_k; over (t_{k-1}, t_k] the rate is integrated with the
        # trapezoid of the last two samples (exact for a rate that changes linearly, as under a held RCS
        # torque; holding the end sample would rotate by alpha dt^2 / 2 too much per step during a slew).
        # An integrating gyro gives the interval's delta-angle as a mean rate: the rotation itself.
        w0x, w0y, w0z = self._omega_B if self._have_rate and not self._gyro_delta_angle else (wx, wy, wz)
        self._omega_B = (wx, wy, wz)
        self._have_rate = True
        if self._q_LB is None:
            counts["no_attitude"] += 1
            return False

        dt_ns = t_ns - self._t_ns
        if dt_ns != self._dt_ns:
            self._set_step_matrices(dt_ns)
        dt = dt_ns / NS_PER_S
        half = _quat_exp(0.5 * (w0x + wx), 0.5 * (w0y + wy), 0.5 * (w0z + wz), 0.5 * dt)
        if self._gyro:
            q_mid = _quat_mul(self._q_LB, half)
            self._q_LB = _quat_normalized(_quat_mul(q_mid, half))
        else:
            q_mid = self._q_LB
        self._q_gyro = _quat_normalized(_quat_mul(self._q_gyro, _quat_mul(half, half)))
        # Mid-interval attitude, in plain floats: at the IMU rate, NumPy's per-call cost on 3-vectors
        # outweighs the arithmetic.
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rows = _quat_rows(q_mid)
        ekf = self.ekf
        F = self._F
        # d(r, v)/d(b_a) = -R_LB (dt^2 / 2, dt): one block, rows (r, v).
        np.multiply(np.array(rows + rows).reshape(6, 3), self._bias_coupling, out=F[IDX_R.start:IDX_V.stop, IDX_BA])
        ekf.F = F
        # Measured specific force in L plus gravity (the bias enters through F).
        g_x, g_y, g_z = self._g_L_tuple
        u_L = np.array((r00 * fx + r01 * fy + r02 * fz + g_x,
                        r10 * fx + r11 * fy + r12 * fz + g_y,
                        r20 * fx + r21 * fy + r22 * fz + g_z))
        # Star-tracker error tilts the specific force: extra acceleration PSD sigma^2 |f|^2 T.
        psd = self._accel_psd + self._att_var_time * (fx * fx + fy * fy + fz * fz)
        np.multiply(self._Q_shape, psd, out=self._Q[:6, :6])
        ekf.Q = self._Q
        ekf.predict(u_L)
        bx, by, bz = ekf.x[IDX_BA].tolist()
        self._a_L = u_L - np.array((r00 * bx + r01 * by + r02 * bz,
                                    r10 * bx + r11 * by + r12 * bz,
                                    r20 * bx + r21 * by + r22 * bz))
        self._t_ns = t_ns
        counts["used"] += 1
        return True

    # ------------------------------------------------------------------ updates
    def _lag_ns(self, t_ns: int) -> int:
        return int(t_ns) - self._t_ns

    def _gated_update(self, t_ns: int, kind: str, z: np.ndarray, hx: np.ndarray, H: np.ndarray,
                      R: np.ndarray, prior: tuple[np.ndarray, np.ndarray] | None = None,
                      consider: np.ndarray | None = None) -> UpdateRecord:
        """Chi-square gate, then (if it passes) filterpy's EKF update; log and count.

        ``prior`` is an (x, P) to gate and update from instead of the filter's (the
        terrain state carried to the new footprint); it is committed only on acceptance.
        ``consider``: indices of states the measurement depends on (through ``H``) but must
        not correct (a Schmidt-Kalman consider update): their uncertainty is in ``S`` and in
        the gain of the others, their rows of the gain are zero, and ``P`` takes the Joseph
        form, which is exact for any gain.
        """
        ekf = self.ekf
        x_prior = _frozen(ekf.x)
        P_prior = _frozen(ekf.P)
        P_gate = ekf.P if prior is None else prior[1]
        y = z - hx
        S = H @ P_gate @ H.T + R
        if len(z) == 1:  # the altimeter: a scalar, no solve
            s00 = float(S[0, 0])
            nis = float(y[0]) ** 2 / s00 if s00 != 0.0 else math.nan
        else:
            try:
                nis = float(y @ np.linalg.solve(S, y))
            except np.linalg.LinAlgError:
                nis = math.nan
        counts = self.counters[kind]
        if not (nis <= self._gate[len(z)]):  # NaN NIS (singular S) is rejected too
            counts["rejected"] += 1
            self.consecutive_rejections[kind] += 1
            rec = UpdateRecord(t_ns, kind, _frozen(z), _frozen(y), _frozen(S), nis, False, REASON_GATE,
                               x_prior, P_prior, x_prior, P_prior)
        else:
            if prior is not None:
                ekf.x, ekf.P = prior
            if consider is None:
                ekf.update(z, _const, _const, R=R, args=(H,), hx_args=(hx,))
            else:
                P0 = ekf.P
                K = np.linalg.solve(S, H @ P0).T  # P H^T S^-1 (S and P symmetric)
                K[consider, :] = 0.0
                ikh = np.eye(self.dim_x) - K @ H
                ekf.x = ekf.x + K @ y
                ekf.P = ikh @ P0 @ ikh.T + K @ R @ K.T
            P = ekf.P
            ekf.P = 0.5 * (P + P.T)  # keep P symmetric against round-off
            counts["accepted"] += 1
            self.consecutive_rejections[kind] = 0
            rec = UpdateRecord(t_ns, kind, _frozen(z), _frozen(y), _frozen(S), nis, True, "",
                               x_prior, P_prior, _frozen(ekf.x), _frozen(ekf.P))
        self.log.append(rec)
        return rec

    def _not_applied(self, t_ns: int, kind: str, z: np.ndarray, reason: str, counter: str) -> UpdateRecord:
        """Log and count a measurement that never reached the gate."""
        self.counters[kind][counter] += 1
        m = z.shape[0]
        x = _frozen(self.ekf.x)
        P = _frozen(self.ekf.P)
        nan_y = np.full(m, math.nan)
        nan_S = np.full((m, m), math.nan)
        nan_y.flags.writeable = nan_S.flags.writeable = False
        rec = UpdateRecord(int(t_ns), kind, _frozen(z), nan_y, nan_S, math.nan, False, reason, x, P, x, P)
        self.log.append(rec)
        return rec

    def _checked_noise_and_lag(self, t_ns: int, kind: str, z: np.ndarray,
                               R: np.ndarray) -> UpdateRecord | tuple[np.ndarray, int]:
        """The symmetrised ``R`` and the lag to the filter time, or the record of why the update is not made
        (a non-finite ``z`` or ``R``, an ``R`` not positive definite, or a time too far from the filter's)."""
        if not all_finite(z, R):
            return self._not_applied(t_ns, kind, z, REASON_NONFINITE, "invalid")
        R = 0.5 * (R + R.T)
        try:
            np.linalg.cholesky(R)
        except np.linalg.LinAlgError:
            return self._not_applied(t_ns, kind, z, REASON_INVALID_R, "invalid")
        lag_ns = self._lag_ns(t_ns)
        if abs(lag_ns) > self._max_lag_ns:
            return self._not_applied(t_ns, kind, z, REASON_STALE, "rejected")
        return R, lag_ns

    def update_altimeter(self, msg: AltimeterMessage) -> UpdateRecord | None:
        """Slant-range update against a horizontal plane at the target's elevation.

        Args:
            msg: Altimeter sample: ``range_m`` [m], ``valid``, ``boresight_B`` (3,).

        Returns:
            The update's record; None when there is nothing to use (``valid`` is
            False, no attitude yet, or the boresight is more than
            ``altimeter_max_incidence_deg`` from nadir), counted as ``skipped``.
        """
        counts = self.counters[KIND_ALTIMETER]
        if not msg.valid:
            counts["skipped"] += 1
            return None
        rho = float(msg.range_m)
        z = np.array([rho])
        try:
            bx, by, bz = np.asarray(msg.boresight_B, dtype=float).reshape(3).tolist()
        except (TypeError, ValueError):
            return self._not_applied(msg.t_ns, KIND_ALTIMETER, z, REASON_NONFINITE, "invalid")
        if not math.isfinite(rho + bx + by + bz):
            return self._not_applied(msg.t_ns, KIND_ALTIMETER, z, REASON_NONFINITE, "invalid")
        lag_ns = self._lag_ns(msg.t_ns)
        if abs(lag_ns) > self._max_lag_ns:
            return self._not_applied(msg.t_ns, KIND_ALTIMETER, z, REASON_STALE, "rejected")
        if self._q_LB is None:
            counts["skipped"] += 1
            return None
        R_LB = quat_to_matrix(self._q_LB)
        b_L = R_LB @ np.array((bx, by, bz))
        cos_nadir = -b_L[2] / math.sqrt(bx * bx + by * by + bz * bz)  # -b_L,z of the unit boresight
        if cos_nadir <= self._cos_max_incidence:
            counts["skipped"] += 1
            return None
        lag_s = lag_ns / NS_PER_S
        # Carry the terrain state from the last used footprint to this one (applied on acceptance).
        x, P = self.ekf.x, self.ekf.P
        p_alt_L = x[IDX_R] + R_LB @ self._lever_B
        footprint_L = p_alt_L[:2] + (rho / math.sqrt(bx * bx + by * by + bz * bz)) * b_L[:2]
        prior = None
        k_new = relief_scale(self._cfg_terrain, footprint_L, P[:2, :2])
        step = self._terrain_step(footprint_L, k_new)
        if step is not None:
            x, P = _linear_step(self._T_terrain, self._ix_terrain, x, P, *step)
            prior = (x, P)
        height = p_alt_L[2] + x[IDX_VZ] * lag_s - x[IDX_H]  # altimeter height above the ground [m]
        H = np.zeros((1, self.dim_x))
        if self._regional:  # the ground is u_R - u_R0 higher besides
            height -= x[IDX_RR] - x[IDX_RR0]
            H[0, IDX_RR] = -1.0 / cos_nadir
            H[0, IDX_RR0] = 1.0 / cos_nadir
        rho_hat = height / cos_nadir
        H[0, IDX_RZ] = 1.0 / cos_nadir
        H[0, IDX_VZ] = lag_s / cos_nadir
        H[0, IDX_H] = -1.0 / cos_nadir
        var = self.altimeter_sigma_m(rho_hat, include_relief=False) ** 2
        rec = self._gated_update(msg.t_ns, KIND_ALTIMETER, z, np.array([rho_hat]), H, np.array([[var]]), prior)
        if rec.accepted:
            self._footprint_L = footprint_L
            if step is not None:
                self._k_terrain = k_new
        return rec

    def _terrain_step(self, footprint_L: np.ndarray, k_new: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Transition ``(F, Q)`` of the terrain's height and slope from the last used footprint to this one.

        The relief is ``k(p) u(p)``: a unit Matern-3/2 field ``u`` times the site map's
        amplitude ``k`` (:func:`relief_scale`, ``k_new`` at this footprint). So the
        step of ``u`` is scaled by ``k_new / k_old`` and its noise by ``k_new^2``.
        None when nothing changes (the first sample, whose prior applies as it is, or the same spot).
        With a correlation length of 0 the relief is white: every sample sees independent ground.
        With the regional relief the step is (6, 6): the regional field and its slope follow the
        local ones, stepped over the same displacement as a Matern-3/2 field of their own (no site
        factor: site selection clears craters and boulders, not the regional slope).
        """
        cfg = self.cfg
        sigma_new = cfg.terrain_relief_sigma_m * k_new
        d = None if self._footprint_L is None else footprint_L - self._footprint_L
        moved = d is not None and bool(d[0] or d[1])
        if cfg.terrain_correlation_length_m == 0.0:
            local: tuple[np.ndarray, np.ndarray] | None = (np.zeros((3, 3)), np.diag([sigma_new**2, 0.0, 0.0]))
        elif moved:
            F, Q = matern32_terrain_step(d, sigma_new, cfg.terrain_correlation_length_m)
            local = (F * (k_new / self._k_terrain), Q)
        else:
            local = None
        if not self._regional or (local is None and not moved):
            return local
        still = (np.eye(3), np.zeros((3, 3)))  # a field that does not move
        F_l, Q_l = still if local is None else local
        F_r, Q_r = (matern32_terrain_step(d, cfg.regional_relief_sigma_m, cfg.regional_relief_length_m)
                    if moved else still)
        z3 = np.zeros((3, 3))
        return np.block([[F_l, z3], [z3, F_r]]), np.block([[Q_l, z3], [z3, Q_r]])

    def update_velocity(self, t_ns: int, z_v_L: np.ndarray, R: np.ndarray,
                        axes: tuple[int, ...] = (0, 1, 2)) -> UpdateRecord:
        """Ground-relative velocity update (``H = [0 I 0]``), e.g. from vision.

        Args:
            t_ns: Time of validity of the measurement [ns].
            z_v_L: Measured velocity components of B relative to the ground, in
                L, (len(axes),) [m/s].
            R: Their covariance, (len(axes), len(axes)) [(m/s)^2], symmetric positive definite.
            axes: Which velocity components of L are measured (default all
                three; ``(0, 1)`` for a horizontal-only measurement).

        Returns:
            The update's record (``accepted`` False for a gated, stale, non-finite
            or non-positive-definite measurement; the state is then unchanged).

        Raises:
            ValueError: ``z_v_L`` or ``R`` has the wrong shape (a caller bug).
        """
        z = np.asarray(z_v_L, dtype=float)
        R = np.asarray(R, dtype=float)
        idx = list(axes)
        n = len(idx)
        if not (1 <= n <= 3 and len(set(idx)) == n and all(a in (0, 1, 2) for a in idx)):
            raise ValueError(f"update_velocity: axes = {axes!r}; expected distinct indices among 0, 1, 2")
        if z.shape != (n,):
            raise ValueError(f"update_velocity: z_v_L has shape {z.shape}; expected ({n},) [m/s]")
        if R.shape != (n, n):
            raise ValueError(f"update_velocity: R has shape {R.shape}; expected ({n}, {n}) [(m/s)^2]")
        checked = self._checked_noise_and_lag(t_ns, KIND_VELOCITY, z, R)
        if isinstance(checked, UpdateRecord):
            return checked
        R, lag_ns = checked
        hx = (self.ekf.x[IDX_V] + self._a_L * (lag_ns / NS_PER_S))[idx]
        return self._gated_update(int(t_ns), KIND_VELOCITY, z, hx, self._H_vel[idx], R)

    def inflate_horizontal_position(self, factor: float) -> None:
        """Scale the horizontal position's sigmas by ``factor``, keeping every correlation.

        The covariance's rows and columns of ``r_x`` and ``r_y``, and of the position clone's
        ``x`` and ``y`` (the position at the last camera frame, which shares the prior's error),
        are multiplied by ``factor`` (``P <- D P D``, ``D`` diagonal), so ``P`` stays positive
        definite and the displacement since the last frame, ``r - r_clone``, keeps its small
        variance (times ``factor^2``). For a map acquisition that found the position only in a
        search window ``factor`` times wider than the prior's: the prior was off by more than it
        knew. (Scaling the position alone made ``r - r_clone`` as uncertain as the position
        itself; the update that followed moved the clone by half the position's jump, the next
        vision pair saw the rest as motion, and later fixes were gated out: in a 20-case stress
        campaign with a 100 m 3-sigma hand-over error, one case gated out 12 of its 21 fixes and
        reached 50 m with a 2.6 m error.)
        """
        if not factor >= 1.0:
            raise ValueError(f"inflate_horizontal_position: factor = {factor}; allowed: >= 1")
        d = np.ones(self.ekf.P.shape[0])
        d[0:2] = factor
        d[IDX_C.start:IDX_C.start + 2] = factor  # the clone is the position of the last frame: the same prior
        self.ekf.P = self.ekf.P * np.outer(d, d)

    def update_map_position(self, t_ns: int, z_xy_m: np.ndarray, R: np.ndarray,
                            lever_xy_m: np.ndarray, keyframe_gain: np.ndarray | None = None) -> UpdateRecord:
        """Horizontal position update from a map fix (kind ``"map"``, chi-square gated like every update).

        Args:
            t_ns: Time of validity [ns].
            z_xy_m: Measured horizontal position of a point on the body (the camera) in the map frame, (2,) [m].
            R: Its covariance, (2, 2) [m^2].
            lever_xy_m: Horizontal offset of that point from the body origin, in L, (2,) [m].
            keyframe_gain: For a fix against a keyframe: ``(r_C - r_C,k) / h_k`` (2,) [-], the camera's
                horizontal displacement from the keyframe's over the keyframe's height (both estimated),
                the fix's sensitivity to the keyframe's height error (``IDX_KZ``); None for a map fix.

        Returns:
            The update's record (the state is unchanged unless accepted).
        """
        self.counters.setdefault(KIND_MAP, {"accepted": 0, "rejected": 0, "invalid": 0})
        self.consecutive_rejections.setdefault(KIND_MAP, 0)
        z = np.asarray(z_xy_m, dtype=float)
        R = np.asarray(R, dtype=float)
        if z.shape != (2,) or R.shape != (2, 2):
            raise ValueError(f"update_map_position: z {z.shape}, R {R.shape}; expected (2,) and (2, 2)")
        checked = self._checked_noise_and_lag(t_ns, KIND_MAP, z, R)
        if isinstance(checked, UpdateRecord):
            return checked
        R, lag_ns = checked
        hx, H = self._map_fix_model(lag_ns / NS_PER_S, np.asarray(lever_xy_m, dtype=float), keyframe_gain)
        return self._gated_update(int(t_ns), KIND_MAP, z, hx, H, R)

    def _map_fix_model(self, lag_s: float, lever_xy_m: np.ndarray,
                       keyframe_gain: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """A map fix's prediction ``z = r + v lag + lever + b_map (+ g b_kz against a keyframe)``, (2,) [m], and
        its Jacobian (2, dim_x) (the model is linear): ``b_map`` and ``b_kz`` where the filter carries them,
        ``g`` = ``keyframe_gain`` [-], ``lag`` [s] from the filter time to the fix's time of validity,
        ``lever`` (2,) [m] the camera's horizontal offset from the body origin."""
        x = self.ekf.x
        hx = x[0:2] + x[3:5] * lag_s + lever_xy_m
        H = np.zeros((2, self.dim_x))
        H[0, 0] = H[1, 1] = 1.0
        H[0, 3] = H[1, 4] = lag_s
        if self.has_map_bias:
            hx = hx + x[IDX_MB]
            H[:, IDX_MB] = np.eye(2)
            if keyframe_gain is not None:
                g = np.asarray(keyframe_gain, dtype=float).reshape(2)
                hx = hx + g * x[IDX_KZ]
                H[:, IDX_KZ] = g
        return hx, H

    @property
    def has_map_bias(self) -> bool:
        """Whether the filter carries the map fixes' common error ``b_map`` (states ``IDX_MB``)."""
        return self.dim_x > DIM_X

    def step_map_bias(self, phi: float, sigma_m: float, scale: float = 1.0) -> None:
        """Carry ``b_map`` to the next map fix: a first-order Gauss-Markov step, in place.

        ``b <- scale phi b`` with process noise ``sigma_m^2 (1 - phi^2)`` per axis (see :func:`_decay`):
        ``phi`` the correlation between consecutive fixes' common errors, ``sigma_m`` its stationary
        1-sigma now [m], ``scale`` the ratio of that 1-sigma to the one it was last carried at.
        """
        if not self.has_map_bias:
            raise ValueError("step_map_bias: this filter has no map bias (make_estimator(map_bias_sigma_m=...))")
        _decay(self.ekf.x, self.ekf.P, IDX_MB, phi, sigma_m, scale)

    def map_bias_to_keyframe(self, t_ns: int, extra_sigma_m: float = 0.0) -> None:
        """Make ``b_map`` and ``b_kz`` a keyframe's pose error: the error of the camera position estimate now.

        A keyframe ortho image laid on the ground through the estimate ``r + v lag`` (``lag`` from the
        filter time to ``t_ns``) is a map shifted by that estimate's horizontal error
        ``e_k = (r + v lag)_est - (r + v lag)`` and magnified about the keyframe camera's nadir by its
        height error ``dz_k`` (the same, vertically): a ground point ``q`` from the nadir lands at
        ``q (1 + dz_k / h_k)``. A later frame matched against it measures
        ``r + v lag' + lever + e_k + g dz_k``, ``g = (r_C - r_C,k) / h_k`` (:meth:`update_map_position`'s
        ``keyframe_gain``). So ``(b_map, b_kz)`` become ``(e_k, dz_k)``, constant from now on: estimate 0,
        covariance ``T P T^T + extra_sigma_m^2 I`` and cross-covariance ``-T P`` with
        ``T = [I, lag I]`` on the position and velocity (the error is minus the position's: truth
        minus estimate), replacing what they held. ``extra_sigma_m`` [m] is the keyframe's own
        horizontal error (its attitude's, seen from its height), independent of the state.
        """
        if not self.has_map_bias:
            raise ValueError("map_bias_to_keyframe: this filter has no map bias (make_estimator(map_bias_sigma_m=...))")
        lag_s = self._lag_ns(t_ns) / NS_PER_S
        x, P = self.ekf.x, self.ekf.P
        TP = P[IDX_R, :] + lag_s * P[IDX_V, :]
        cov = TP[:, IDX_R] + lag_s * TP[:, IDX_V]
        cov[0:2, 0:2] += np.eye(2) * float(extra_sigma_m) ** 2
        idx = [IDX_MB.start, IDX_MB.start + 1, IDX_KZ]
        x[idx] = 0.0
        P[idx, :] = -TP
        P[:, idx] = -TP.T
        P[np.ix_(idx, idx)] = cov
        self.ekf.P = 0.5 * (P + P.T)

    def map_prior_cov_xy(self, t_ns: int, keyframe_gain: np.ndarray | None = None) -> np.ndarray:
        """Covariance (2, 2) [m^2] of the map-fix model's prediction ``r + v lag + b_map (+ g b_kz)``
        (``b_map`` when carried; ``g`` = ``keyframe_gain`` as in :meth:`update_map_position`)."""
        _, H = self._map_fix_model(self._lag_ns(t_ns) / NS_PER_S, np.zeros(2), keyframe_gain)
        return H @ self.ekf.P @ H.T

    def clone_frame(self, t_ns: int) -> bool:
        """Clone the state of a camera frame at ``t_ns``: its position and its image offset.

        The position clone is ``r + v (t_ns - t_filter)`` (first order, for a frame
        stamped off the filter time), with its covariance and every
        cross-covariance: the augmentation ``x_c = T x``, ``P_cc = T P T^T``,
        ``P_c* = T P``. The frame's image offset ``d_new`` (introduced by this
        frame's :meth:`update_relative`, if any) moves to ``d_clone`` the same way,
        and ``d_new`` is cleared for the next frame. Before that, the Gauss-Markov
        states that vision uses step from the last frame to this one: ``h_view``
        over the distance travelled, ``b_flow`` over the time.

        Args:
            t_ns: Time of the frame [ns].

        Returns:
            True when cloned; False when ``t_ns`` is further than ``max_update_lag_s``
            from the filter time (no clone is then held).
        """
        lag_ns = self._lag_ns(t_ns)
        if abs(lag_ns) > self._max_lag_ns:
            self.drop_clone()
            return False
        ekf = self.ekf
        x, P = ekf.x, ekf.P
        cfg = self.cfg
        if self._clone_t_ns is not None:
            # The view moved: its mean ground height decorrelates with the travel, and the flow
            # bias with time (Gauss-Markov). The viewed ground's height and slope carry the site
            # map's relief amplitude over the viewed patch (``k_view``).
            height_m = float(x[IDX_RZ]) - float(x[IDX_G])
            travel_m = float(np.linalg.norm(x[IDX_R] - x[IDX_C]))
            k_view = relief_scale(cfg, x[:2], P[:2, :2] + view_spread(cfg, height_m))
            ratio = k_view / self._k_view
            self._k_view = k_view
            phi_g = math.exp(-travel_m / cfg.view_ground_correlation_length_m)
            sigma_g = view_ground_sigma(cfg, height_m, k_view)
            _decay(x, P, IDX_G, phi_g, sigma_g, sigma_g / self._sigma_g)
            self._sigma_g = sigma_g
            phi_b = math.exp(-(int(t_ns) - self._clone_t_ns) / NS_PER_S / cfg.vision_bias_time_s)
            sigma_bf = vision_bias_sigma(cfg, height_m)
            _decay(x, P, IDX_BF, phi_b, sigma_bf, sigma_bf / self._sigma_bf)
            self._sigma_bf = sigma_bf
            # The viewed ground's slope: a new patch after a patch width of travel, whose slope
            # 1-sigma is that of a patch of its width at the present height.
            width_m = max(cfg.view_width_per_height * height_m, 1.0)
            _decay(x, P, IDX_SV, math.exp(-travel_m / width_m), view_slope_sigma(cfg, width_m) * k_view, ratio)
        # The frame's offset: d_clone <- d_new, with its correlations.
        row = P[IDX_DN, :].copy()
        x[IDX_DC] = x[IDX_DN]
        P[IDX_DC, :] = row
        P[:, IDX_DC] = row.T
        P[IDX_DC, IDX_DC] = row[:, IDX_DN]
        self._offset_clone_known = self._offset_new_known
        # The position: r_clone <- r + v lag, with its correlations (the offset's included).
        # T = [I, lag I] on (r, v), zero elsewhere, written out.
        lag_s = lag_ns / NS_PER_S
        x[IDX_C] = x[IDX_R] + lag_s * x[IDX_V]
        TP = P[IDX_R, :] + lag_s * P[IDX_V, :]
        P[IDX_C, :] = TP
        P[:, IDX_C] = TP.T
        P[IDX_C, IDX_C] = TP[:, IDX_R] + lag_s * TP[:, IDX_V]
        self._clear_new_offset(x, P)
        self._clone_t_ns = int(t_ns)
        return True

    def _clear_new_offset(self, x: np.ndarray, P: np.ndarray) -> None:
        _enter_independent(x, P, IDX_DN, 0.0)
        self._offset_new_known = False

    def drop_clone(self) -> None:
        """Forget the clone (a break in the image sequence); the next frame starts anew."""
        self._clone_t_ns = None
        self._offset_clone_known = False
        self._clear_new_offset(self.ekf.x, self.ekf.P)

    def update_relative(self, t_ns: int, z: np.ndarray, hx: np.ndarray, H_r: np.ndarray, H_c: np.ndarray,
                        R: np.ndarray, R_frame: np.ndarray | None = None, H_g: np.ndarray | None = None,
                        H_s: np.ndarray | None = None, kind: str = KIND_VISION,
                        frame_overlap: float = 1.0) -> UpdateRecord:
        """Update with a measurement of the current position relative to the clone.

        The measurement model is linearised by the caller at the filter's prior:
        ``z ~ hx + H_r (r(t_ns) - r_hat(t_ns)) + H_c (r_clone - r_clone_hat)
        + H_g (h_view - h_view_hat) + H_s (s_view - s_view_hat) + b_flow + d_new - d_clone + w``, where ``r(t_ns) = r + v (t_ns - t_filter)``, ``w`` is
        white with covariance ``R`` and ``d_new`` is the current frame's image
        offset, entered here with covariance ``R_frame``. ``d_clone`` is the clone
        frame's offset as this filter knows it; a clone frame that had no update of
        its own gets a fresh offset with ``R_frame`` too. Only for ``m = 2``.
        It is a consider update (Schmidt-Kalman): the vertical channel (height,
        vertical velocity, vertical accelerometer bias, the clone's height) and the
        altimeter's terrain enter ``S`` through ``H`` but are not corrected.

        Args:
            t_ns: Time of validity (the second frame) [ns].
            z: Measurement, (m,).
            hx: Its prediction at the prior, (m,).
            H_r: Jacobian with respect to the position at ``t_ns``, (m, 3).
            H_c: Jacobian with respect to the clone, (m, 3).
            R: Covariance of the white part ``w``, (m, m), symmetric positive definite.
            R_frame: Covariance of one frame's image offset, (2, 2), symmetric
                positive semi-definite; None: no shared-frame noise (zero).
            H_g: Jacobian with respect to the viewed ground's height ``h_view``, (2,);
                None: the measurement does not depend on it.
            kind: Record and counter name (default ``"vision"``).
            frame_overlap: Correlation in [0, 1] between the clone frame's offset as this pair
                sees it and as the pair before saw it. The offset is the mean error of the
                tracked positions in that frame, over each pair's own tracks: with ``n1`` and
                ``n2`` tracks, ``n12`` of them in both, it is ``n12 / sqrt(n1 n2)`` (1 when the
                tracks are the same; less when templates were dropped or refilled). The known
                offset is carried over with that factor, the rest is new (``R_frame``).

        Returns:
            The update's record (``accepted`` False when gated, stale, non-finite,
            with a non-positive-definite ``R``, or with no clone held).

        Raises:
            ValueError: Arrays of inconsistent shapes (a caller bug).
        """
        z = np.asarray(z, dtype=float)
        m = z.shape[0] if z.ndim == 1 else -1
        hx = np.asarray(hx, dtype=float)
        H_r = np.asarray(H_r, dtype=float)
        H_c = np.asarray(H_c, dtype=float)
        R = np.asarray(R, dtype=float)
        R_f = np.zeros((2, 2)) if R_frame is None else np.asarray(R_frame, dtype=float)
        H_g = np.zeros(2) if H_g is None else np.asarray(H_g, dtype=float)
        H_s = np.zeros((2, 2)) if H_s is None else np.asarray(H_s, dtype=float)
        if not (m == 2 and hx.shape == (m,) and H_r.shape == (m, 3) and H_c.shape == (m, 3) and R.shape == (m, m)
                and R_f.shape == (2, 2) and H_g.shape == (2,) and H_s.shape == (2, 2)):
            raise ValueError(
                f"update_relative: shapes z {z.shape}, hx {hx.shape}, H_r {H_r.shape}, H_c {H_c.shape}, R {R.shape}, "
                f"R_frame {R_f.shape}; expected (2,), (2,), (2, 3), (2, 3), (2, 2), (2, 2)"
            )
        if not all_finite(z, hx, H_r, H_c, R, R_f, H_g, H_s):
            return self._not_applied(t_ns, kind, z, REASON_NONFINITE, "invalid")
        if self._clone_t_ns is None:
            return self._not_applied(t_ns, kind, z, REASON_NO_CLONE, "invalid")
        checked = self._checked_noise_and_lag(t_ns, kind, z, R)
        if isinstance(checked, UpdateRecord):
            return checked
        R, lag_ns = checked
        H = np.zeros((m, self.dim_x))
        H[:, IDX_R] = H_r
        H[:, IDX_V] = H_r * (lag_ns / NS_PER_S)
        H[:, IDX_C] = H_c
        H[:, IDX_BF] = np.eye(2)
        H[:, IDX_G] = H_g
        H[:, IDX_SV] = H_s
        H[:, IDX_DN] = np.eye(2)
        H[:, IDX_DC] = -np.eye(2)
        # Enter this frame's offset (and the clone frame's, if no update introduced it) into the prior.
        x, P = self.ekf.x.copy(), self.ekf.P.copy()
        R_f = 0.5 * (R_f + R_f.T)
        for idx in [IDX_DN] if self._offset_clone_known else [IDX_DN, IDX_DC]:
            _enter_independent(x, P, idx, R_f)
        if self._offset_clone_known and frame_overlap < 1.0:
            a = min(max(float(frame_overlap), 0.0), 1.0)
            x[IDX_DC] *= a
            P[IDX_DC, :] *= a
            P[:, IDX_DC] *= a
            P[IDX_DC, IDX_DC] += (1.0 - a * a) * R_f
        hx = hx + x[IDX_BF] + x[IDX_DN] - x[IDX_DC]
        rec = self._gated_update(int(t_ns), kind, z, hx, H, R, prior=(x, P), consider=_VISION_CONSIDER)
        if rec.accepted:
            self._offset_new_known = True
        return rec

    def update_divergence(self, t_ns: int, z: float, hx: float, H_r: np.ndarray, H_c: np.ndarray, H_g: float,
                          H_s: np.ndarray, R: float) -> UpdateRecord:
        """Update with the flow's divergence of a frame pair (:class:`gnc.vision_nav.DivergenceMeasurement`):
        the camera's vertical displacement over its height, ``w = dz / h0``.

        Linearised by the caller at the prior like :meth:`update_relative`, on the current position (at
        ``t_ns``), the clone, the viewed ground's height and slope; unlike the horizontal flow it corrects the
        vertical channel (the flight software uses it when no altimeter is left: the ratio of the vertical
        velocity to the height, whose scale the IMU's accelerations make observable). The frames' common
        offsets do not enter: a shift of all tracks does not change their spread. Kind ``"divergence"``.

        Args:
            t_ns: Time of validity (the second frame) [ns].
            z: Measured divergence [-].
            hx: Its prediction at the prior [-].
            H_r: Jacobian on the position at ``t_ns``, (3,) [1/m].
            H_c: Jacobian on the clone, (3,) [1/m].
            H_g: Jacobian on the viewed ground's height [1/m].
            H_s: Jacobian on the viewed ground's slope, (2,) [-].
            R: Variance of ``z`` [-].

        Returns:
            The update's record (not applied without a clone, or when gated, stale or non-finite).
        """
        self.counters.setdefault(KIND_DIVERGENCE, {"accepted": 0, "rejected": 0, "invalid": 0})
        self.consecutive_rejections.setdefault(KIND_DIVERGENCE, 0)
        zv = np.array([float(z)])
        H_r = np.asarray(H_r, dtype=float)
        H_c = np.asarray(H_c, dtype=float)
        H_s = np.asarray(H_s, dtype=float)
        if H_r.shape != (3,) or H_c.shape != (3,) or H_s.shape != (2,):
            raise ValueError(f"update_divergence: shapes H_r {H_r.shape}, H_c {H_c.shape}, H_s {H_s.shape}; "
                             "expected (3,), (3,), (2,)")
        if not all_finite(H_r, H_c, H_s, np.array([hx, H_g])):
            return self._not_applied(t_ns, KIND_DIVERGENCE, zv, REASON_NONFINITE, "invalid")
        if self._clone_t_ns is None:
            return self._not_applied(t_ns, KIND_DIVERGENCE, zv, REASON_NO_CLONE, "invalid")
        checked = self._checked_noise_and_lag(t_ns, KIND_DIVERGENCE, zv, np.array([[float(R)]]))
        if isinstance(checked, UpdateRecord):
            return checked
        Rm, lag_ns = checked
        H = np.zeros((1, self.dim_x))
        H[0, IDX_R] = H_r
        H[0, IDX_V] = H_r * (lag_ns / NS_PER_S)
        H[0, IDX_C] = H_c
        H[0, IDX_G] = H_g
        H[0, IDX_SV] = H_s
        return self._gated_update(int(t_ns), KIND_DIVERGENCE, zv, np.array([float(hx)]), H, Rm)

    def altimeter_sigma_m(self, range_m: float, cos_nadir: float = 1.0, include_relief: bool = True) -> float:
        """1-sigma of a slant range [m]: the altimeter spec, plus the relief by default.

        Args:
            range_m: Slant range [m].
            cos_nadir: Cosine of the boresight's angle from nadir, ``-b_L,z`` (0, 1].
            include_relief: True (default): the spec plus ``terrain_relief_sigma_m /
                cos_nadir`` in quadrature, the error of the range read as the height
                above a ground other than the spot the beam hits (the target's
                elevation, or the mean ground in a camera's view). False: the sensor
                spec ``hypot(floor, frac * range)`` alone, the error of the range to
                the spot under the beam (the noise of the filter's own update).
        """
        if not 0.0 < cos_nadir <= 1.0:
            raise ValueError(f"altimeter_sigma_m: cos_nadir = {cos_nadir!r}; allowed: (0, 1]")
        cfg = self.cfg
        var = cfg.altimeter_noise_sigma_m**2 + (cfg.altimeter_noise_frac * max(float(range_m), 0.0)) ** 2
        if include_relief:
            var += (cfg.terrain_relief_sigma_m / cos_nadir) ** 2
        return math.sqrt(var)

    # Names used by the flight computer (gnc/flight.py).
    predict_imu = propagate_imu
    update_attitude = set_attitude

    # ------------------------------------------------------------------ output
    def nav_state(self, mass_kg: float) -> NavState:
        """The navigated state for guidance and control.

        Args:
            mass_kg: Current vehicle mass [kg] (not estimated here).

        Returns:
            NavState at the filter time: position and velocity from the state,
            ``q_LB`` the attitude at the filter time (NaN before the first fix),
            ``omega_B`` the latest gyro sample (zeros before the first), and ``P``
            the 6x6 position/velocity covariance.
        """
        x = self.ekf.x
        q = np.full(4, math.nan) if self._q_LB is None else np.array(self._q_LB)
        return NavState(
            t_ns=self._t_ns,
            r_BL_L=x[IDX_R].copy(),
            v_BL_L=x[IDX_V].copy(),
            q_LB=q,
            omega_B=np.array(self._omega_B),
            mass_kg=float(mass_kg),
            P=self.ekf.P[:6, :6].copy(),
        )


def _decay(x: np.ndarray, P: np.ndarray, idx: int | slice, phi: float, sigma: float, scale: float = 1.0) -> None:
    """One step of a first-order Gauss-Markov process of stationary 1-sigma ``sigma`` on states ``idx``, in place.

    ``x_i <- a x_i`` with ``a = scale phi``, so ``P_i* <- a P_i*`` and ``P_ii <- a^2 P_ii + sigma^2 (1 - phi^2)``
    (each state its own process). ``scale`` is the change of the process's amplitude (``sigma`` is the new one):
    the state is ``amplitude * u`` with ``u`` a unit Gauss-Markov process.
    """
    a = scale * phi
    x[idx] *= a
    P[idx, :] *= a
    P[:, idx] *= a
    q = sigma**2 * (1.0 - phi * phi)
    P[idx, idx] += q * np.eye(idx.stop - idx.start) if isinstance(idx, slice) else q


def _enter_independent(x: np.ndarray, P: np.ndarray, idx: slice, cov: np.ndarray | float) -> None:
    """Set states ``idx`` to zero mean with covariance ``cov``, uncorrelated with every other state, in place."""
    x[idx] = 0.0
    P[idx, :] = 0.0
    P[:, idx] = 0.0
    P[idx, idx] = cov


def matern32_terrain_step(d_xy: np.ndarray, sigma_m: float, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition of the terrain's ``(h, dh/dx, dh/dy)`` over a horizontal displacement ``d_xy`` [m].

    The relief is an isotropic Gauss-Markov field of Matern-3/2 covariance
    ``C(d) = sigma^2 (1 + d / l) exp(-d / l)`` (``sigma = sigma_m``, ``l = length_m``):
    smooth (its slope has the finite 1-sigma ``sigma / l`` per axis), unlike a
    first-order process, whose relief between samples a few centimetres apart is
    far rougher than real ground. Along a straight line the height and its
    along-track slope ``(h, g_u)`` form the Markov pair of state matrix
    ``[[0, 1], [-1/l^2, -2/l]]``; the across-track slope ``g_p`` is independent
    of both and decays as ``exp(-s / l)`` (the transverse derivative covariance
    ``-C'(s) / s``). With ``s = |d|``, ``e = exp(-s / l)``:
    ``Phi = e [[1 + s/l, s], [-s/l^2, 1 - s/l]]`` on ``(h, g_u)``, ``e`` on ``g_p``,
    and ``Q = P_inf - Phi P_inf Phi^T`` with the stationary ``P_inf = diag(sigma^2,
    sigma^2/l^2, sigma^2/l^2)``, so the process stays stationary. Both are
    rotated back to the (x, y) slope axes.

    Returns:
        ``(F, Q)``, each (3, 3), for ``x <- F x``, ``P <- F P F^T + Q``.
    """
    dx, dy = float(d_xy[0]), float(d_xy[1])
    s = math.hypot(dx, dy)
    lam = 1.0 / length_m
    e = math.exp(-s * lam)
    # Phi on (h, g_u): [[p00, p01], [p10, p11]]; e on g_p.
    p00, p01 = e * (1.0 + s * lam), e * s
    p10, p11 = -e * s * lam * lam, e * (1.0 - s * lam)
    v_h, v_g = sigma_m * sigma_m, (sigma_m * lam) ** 2  # P_inf = diag(v_h, v_g, v_g)
    q00 = v_h - (p00 * p00 * v_h + p01 * p01 * v_g)
    q01 = -(p00 * p10 * v_h + p01 * p11 * v_g)
    q11 = v_g - (p10 * p10 * v_h + p11 * p11 * v_g)
    qpp = v_g - e * e * v_g
    ux, uy = (dx / s, dy / s) if s > 0.0 else (1.0, 0.0)
    # Back to (h, g_x, g_y): g_x = ux g_u - uy g_p, g_y = uy g_u + ux g_p.
    F = np.array([[p00, p01 * ux, p01 * uy],
                  [ux * p10, ux * ux * p11 + uy * uy * e, ux * uy * (p11 - e)],
                  [uy * p10, ux * uy * (p11 - e), uy * uy * p11 + ux * ux * e]])
    Q = np.array([[q00, ux * q01, uy * q01],
                  [ux * q01, ux * ux * q11 + uy * uy * qpp, ux * uy * (q11 - qpp)],
                  [uy * q01, ux * uy * (q11 - qpp), uy * uy * q11 + ux * ux * qpp]])
    return F, Q


def _linear_step(T: np.ndarray, ix: tuple[np.ndarray, np.ndarray], x: np.ndarray, P: np.ndarray, F: np.ndarray,
                 Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The terrain states ``(h, dh/dx, dh/dy)`` (and the regional ones, where carried) stepped by
    ``x_i <- F x_i``, ``P <- F P F^T + Q``; new arrays.

    ``T`` is the filter's identity buffer (n, n); its terrain block ``ix`` (an ``np.ix_`` pair) becomes
    ``F``, so ``T x`` and ``T P T^T`` leave every other state as it was (two whole products cost
    less than the fancy-indexed block updates on a matrix this small; the same numbers).
    """
    T[ix] = F
    P = T @ P @ T.T
    P[ix] += Q
    return T @ x, P


# --------------------------------------------------------------------------- factory
def terrain_slope_sigma(cfg: EstimatorConfig) -> float:
    """1-sigma of the terrain's slope per axis, ``terrain_relief_sigma_m / terrain_correlation_length_m`` (0 for white relief) [-]."""
    length = cfg.terrain_correlation_length_m
    return cfg.terrain_relief_sigma_m / length if length > 0.0 else 0.0


def view_slope_sigma(cfg: EstimatorConfig, width_m: float) -> float:
    """1-sigma per axis of the mean slope of a ground patch ``width_m`` wide [-].

    The relief's height change over the patch's width, divided by it:
    ``sqrt(2 sigma^2 (1 - (1 + w/l) exp(-w/l))) / w`` for the Matern-3/2 relief of
    ``terrain_relief_sigma_m`` and ``terrain_correlation_length_m`` (white relief: its
    change over one metre). On the default terrain the best-fit plane of a square
    patch 30, 60 and 120 m wide has RMS slopes 0.091, 0.062 and 0.041 per axis, where
    this gives 0.097, 0.073 and 0.045; wider patches are flatter than it says (0.014
    and 0.006 at 250 and 500 m, against 0.023 and 0.011).
    """
    sigma, length = cfg.terrain_relief_sigma_m, cfg.terrain_correlation_length_m
    w = max(float(width_m), 1e-3)
    if length <= 0.0:
        return math.sqrt(2.0) * sigma / max(w, 1.0)
    u = w / length
    return math.sqrt(max(2.0 * sigma * sigma * (1.0 - (1.0 + u) * math.exp(-u)), 0.0)) / w


def _gauss_hermite_2d(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n*n, 2) and weights (n*n,) of the n-point Gauss-Hermite rule for a 2-D unit normal."""
    x, w = np.polynomial.hermite_e.hermegauss(n)
    w = w / w.sum()
    gx, gy = np.meshgrid(x, x, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel()]), np.outer(w, w).ravel()


_GH_NODES, _GH_WEIGHTS = _gauss_hermite_2d(7)
_GH_NODES_T = np.ascontiguousarray(_GH_NODES.T)  # (2, n*n)
_GH_REACH = float(np.max(np.hypot(_GH_NODES[:, 0], _GH_NODES[:, 1])))  # the farthest node, in 1-sigmas


def site_relief_factor(cfg: EstimatorConfig, rho_m: np.ndarray | float) -> np.ndarray:
    """The site map: relief 1-sigma at horizontal distance ``rho_m`` from the target, per ``terrain_relief_sigma_m`` [-].

    ``site_relief_sigma_m / terrain_relief_sigma_m`` inside ``site_radius_m`` (the cleared landing site),
    rising linearly to 1 over ``site_relief_ramp_m`` beyond its edge; 1 everywhere without a site map.
    On the default terrain (8 terrain seeds) the RMS height change over 1 m is 0.025 / 0.026 / 0.029 m
    0-30 / 30-50 / 50-70 m from the target, 0.077 / 0.104 / 0.116 m at 70-85 / 85-100 / 100-130 m
    and 0.13-0.145 m beyond 130 m; the map gives 0.030, 0.030, 0.030, 0.047, 0.10, 0.133 and 0.133.
    """
    rho = np.asarray(rho_m, dtype=float)
    if cfg.site_radius_m <= 0.0 or cfg.terrain_relief_sigma_m <= 0.0:
        return np.ones_like(rho)
    k_site = _k_site(cfg)
    # np.minimum / np.maximum: np.clip's dispatch costs more than the work on arrays this small.
    ramp = np.minimum(np.maximum((rho - cfg.site_radius_m) / cfg.site_relief_ramp_m, 0.0), 1.0)
    return k_site + (1.0 - k_site) * ramp


def _k_site(cfg: EstimatorConfig) -> float:
    """The site map's relief factor inside the cleared site [-]."""
    return min(cfg.site_relief_sigma_m / cfg.terrain_relief_sigma_m, 1.0)


def _site_relief_factor_at(cfg: EstimatorConfig, rho_m: float) -> float:
    """:func:`site_relief_factor` at one distance, in plain floats (the same arithmetic)."""
    if cfg.site_radius_m <= 0.0 or cfg.terrain_relief_sigma_m <= 0.0:
        return 1.0
    k_site = _k_site(cfg)
    return k_site + (1.0 - k_site) * min(max((rho_m - cfg.site_radius_m) / cfg.site_relief_ramp_m, 0.0), 1.0)


def relief_scale(cfg: EstimatorConfig, r_xy_m: np.ndarray, cov_xy_m2: np.ndarray) -> float:
    """RMS of the site map's relief factor over a horizontal position known to ``N(r_xy_m, cov_xy_m2)`` [-].

    ``sqrt(E[k(|p|)^2])``, by the 7x7 Gauss-Hermite rule on the covariance's principal
    axes: the relief of a spot the filter cannot place exactly is the mix of the
    relief where it may be.
    """
    if cfg.site_radius_m <= 0.0:
        return 1.0
    # Principal axes of the symmetric part [[a, b], [b, c]], in closed form (a 2x2 eigh).
    a, c = float(cov_xy_m2[0, 0]), float(cov_xy_m2[1, 1])
    b = 0.5 * (float(cov_xy_m2[0, 1]) + float(cov_xy_m2[1, 0]))
    mid, half_gap = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    s1, s2 = math.sqrt(max(mid + half_gap, 0.0)), math.sqrt(max(mid - half_gap, 0.0))  # 1-sigma along the axes [m]
    rx, ry = float(r_xy_m[0]), float(r_xy_m[1])
    # Every node beyond the ramp, or every node inside the site: the factor is the same at all of them.
    reach_m, dist_m = _GH_REACH * s1, math.hypot(rx, ry)
    if dist_m - reach_m >= cfg.site_radius_m + cfg.site_relief_ramp_m or dist_m + reach_m <= cfg.site_radius_m:
        return _site_relief_factor_at(cfg, dist_m)
    theta = 0.5 * math.atan2(2.0 * b, a - c)  # the major axis's direction
    ct, st = math.cos(theta), math.sin(theta)
    # The nodes in L: r + [[s1 ct, -s2 st], [s1 st, s2 ct]] n, as rows (x, y).
    p = np.array(((s1 * ct, -s2 * st), (s1 * st, s2 * ct))) @ _GH_NODES_T
    k = site_relief_factor(cfg, np.hypot(p[0] + rx, p[1] + ry))
    return math.sqrt(float(_GH_WEIGHTS @ (k * k)))


def vision_bias_sigma(cfg: EstimatorConfig, camera_height_m: float) -> float:
    """1-sigma of the slowly varying flow error at a camera height, ``vision_bias_ground_m / height`` [rad]."""
    return cfg.vision_bias_ground_m / max(float(camera_height_m), 1.0)


def view_ground_sigma(cfg: EstimatorConfig, camera_height_m: float, k_view: float) -> float:
    """1-sigma of the mean height of the ground patch the camera sees, at a camera height [m].

    ``view_ground_sigma_m * k_view * A``, with ``k_view`` the site map's factor over the patch
    (:func:`relief_scale`) and ``A^2 = rho + (1 - rho) / n`` the averaging over the patch of a
    Matern-3/2 relief of length ``l``, sampled by the tracks at ``n = view_ground_samples``
    independent places (one per template): ``rho = 1 / (1 + w^2 / (6 pi l^2))`` is the relief's mean
    correlation over a patch ``w`` wide (its correlation integrates to ``6 pi l^2`` over the plane;
    within 12 % of the exact square-patch average, above it). On the default terrain the RMS mean
    height of a patch 350 m wide, centred 60 / 120 / 200 m from the target, is 0.9 / 1.2 / 1.6 m
    (uniform average); this gives 1.4-1.7 m there (``rho`` alone: 1.0-1.3 m), where 4 m was used before.
    """
    length = cfg.terrain_correlation_length_m
    w = cfg.view_width_per_height * max(float(camera_height_m), 1.0)
    rho_area = 1.0 / (1.0 + w * w / (6.0 * math.pi * length * length)) if length > 0.0 else 1.0
    # The tracks sample the patch at a few places (one per template), not uniformly.
    n = float(cfg.view_ground_samples)
    return cfg.view_ground_sigma_m * k_view * math.sqrt(rho_area + (1.0 - rho_area) / n)


def view_spread(cfg: EstimatorConfig, camera_height_m: float) -> np.ndarray:
    """Covariance (2, 2) of a point spread uniformly over the ground patch the camera sees, about its centre [m^2]."""
    width_m = cfg.view_width_per_height * max(float(camera_height_m), 1.0)
    return np.eye(2) * (width_m * width_m / 12.0)


def local_site_config(cfg: EstimatorConfig) -> EstimatorConfig:
    """The config whose site map the local relief under the altimeter follows when the regional relief is carried.

    Inside the cleared site the survey's relief (``site_relief_sigma_m`` over ``terrain_correlation_length_m``:
    a slope of 1-sigma 0.03 with the defaults, the site's measured 0.025-0.029 per metre) is the whole
    ground's. The regional field carries a slope of ``regional_relief_sigma_m / regional_relief_length_m``
    everywhere, so the local field keeps the rest of the slope's variance:
    ``site_relief_sigma_m' = l sqrt((s_site / l)^2 - (s_R / l_R)^2)`` (0.61 m with the defaults, from 0.9 m);
    otherwise the altimeter's range rate would be given a third more slope than the site has, and the
    vertical velocity read through it would be conservative. Outside the site (0.13 against 0.022) the
    regional share is left in: it changes the slope by 1.4 %. Vision's viewed ground keeps the survey's site
    map (the regional field is not part of its model).

    Raises:
        ValueError: The regional slope is not below the site's (one line naming both fields).
    """
    if cfg.site_radius_m <= 0.0 or cfg.terrain_correlation_length_m <= 0.0:
        return cfg
    length = cfg.terrain_correlation_length_m
    site_slope = cfg.site_relief_sigma_m / length
    regional_slope = cfg.regional_relief_sigma_m / cfg.regional_relief_length_m
    if regional_slope >= site_slope:
        raise ValueError(
            f"estimator.regional_relief_sigma_m / regional_relief_length_m = {regional_slope:.4g} is not below the "
            f"site's slope estimator.site_relief_sigma_m / terrain_correlation_length_m = {site_slope:.4g}: the regional "
            "field would be rougher than the cleared site; lower regional_relief_sigma_m or raise its length")
    share = length * math.sqrt(site_slope**2 - regional_slope**2)
    return cfg.model_copy(update={"site_relief_sigma_m": share})


def regional_relief_prior(cfg: EstimatorConfig, r_xy_m: np.ndarray) -> np.ndarray:
    """Prior covariance (4, 4) of ``(u_R, du_R/dx, du_R/dy, u_R0)``: the regional field and its slope at
    ``r_xy_m`` and its value at the target (the origin) [m, -, -, m].

    The field is stationary, of Matern-3/2 covariance ``C(d) = s^2 (1 + d/l) exp(-d/l)``: so
    ``var u = s^2``, the slope's ``s^2 / l^2`` per axis, independent of ``u`` at the same place;
    ``cov(u(p), u(0)) = C(|p|)`` and ``cov(grad u(p), u(0)) = grad C = -s^2 exp(-|p|/l) p / l^2``.
    The height it adds above the target's elevation, ``u_R(p) - u_R0``, has the variance
    ``2 (s^2 - C(|p|))``: none at the target, growing with the distance from it.
    """
    s2 = cfg.regional_relief_sigma_m**2
    length = cfg.regional_relief_length_m
    px, py = float(r_xy_m[0]), float(r_xy_m[1])
    d = math.hypot(px, py)
    e = math.exp(-d / length)
    c_u = s2 * (1.0 + d / length) * e
    c_sx, c_sy = -s2 * e * px / length**2, -s2 * e * py / length**2
    g = s2 / length**2
    return np.array([[s2, 0.0, 0.0, c_u],
                     [0.0, g, 0.0, c_sx],
                     [0.0, 0.0, g, c_sy],
                     [c_u, c_sx, c_sy, s2]])


def initial_covariance(cfg: EstimatorConfig, camera_height_m: float = 500.0,
                       r_xy_m: np.ndarray | None = None, terrain_cfg: EstimatorConfig | None = None) -> np.ndarray:
    """Initial covariance (24, 24) from the config's 1-sigma values.

    Diagonal in position, velocity, bias and terrain; the position clone starts
    as an exact copy of the position (fully correlated with it), as if cloned at
    t0; the image offsets start at zero, unknown until an update enters them.
    ``terrain_cfg``: the config whose site map the terrain under the altimeter
    follows (:func:`local_site_config` with the regional relief); ``cfg`` by default.
    """
    r_xy = np.zeros(2) if r_xy_m is None else np.asarray(r_xy_m, dtype=float)[:2]
    cov_xy = np.eye(2) * cfg.init_pos_sigma_m**2
    k_terrain = relief_scale(cfg if terrain_cfg is None else terrain_cfg, r_xy, cov_xy)
    k_view = relief_scale(cfg, r_xy, cov_xy + view_spread(cfg, camera_height_m))
    sig = np.concatenate([
        np.repeat([cfg.init_pos_sigma_m, cfg.init_vel_sigma_mps, cfg.init_accel_bias_sigma_mps2], 3),
        [cfg.terrain_relief_sigma_m * k_terrain],
        np.repeat(cfg.init_pos_sigma_m, 3),
        np.zeros(4),
        np.repeat(vision_bias_sigma(cfg, camera_height_m), 2),
        [view_ground_sigma(cfg, camera_height_m, k_view)],
        np.repeat(terrain_slope_sigma(cfg) * k_terrain, 2),
        np.repeat(view_slope_sigma(cfg, cfg.view_width_per_height * max(camera_height_m, 1.0)) * k_view, 2),
    ])
    P = np.diag(sig**2)
    P[IDX_R, IDX_C] = P[IDX_C, IDX_R] = np.diag(np.repeat(cfg.init_pos_sigma_m**2, 3))
    return P


def make_estimator(
    cfg: EstimatorConfig | Mapping[str, Any] | None,
    x0_r_L: Any,
    x0_v_L: Any,
    t0_ns: int,
    q0_LB: Any = None,
    *,
    altimeter_mount_B_m: Any,
    gyro_delta_angle: bool = False,
    map_bias_sigma_m: float | None = None,
    regional_relief: bool = False,
) -> NavFilter:
    """Validate the config and the initial state, and build the filter.

    Args:
        cfg: An :class:`EstimatorConfig`, a mapping of its fields, or None (defaults).
        x0_r_L: Initial position estimate r_BL_L, (3,) [m].
        x0_v_L: Initial velocity estimate v_BL_L, (3,) [m/s].
        t0_ns: Time of the initial estimate [ns] (integer).
        q0_LB: Optional initial attitude, (4,) scalar-first; without it, IMU samples
            are ignored until the first star-tracker fix.
        altimeter_mount_B_m: Altimeter position relative to the body origin, in B,
            (3,) [m]: the vehicle's calibration, from the same source as the world's.
        gyro_delta_angle: The IMU is an integrating one: each gyro sample is the delta-angle
            over its interval divided by the interval (the rotation is that mean rate held),
            not the rate at the sample time (integrated with the trapezoid of two samples).
        map_bias_sigma_m: With map fixes (``nav_map = "on"``): the initial 1-sigma per axis [m] of their
            common error ``b_map``, two more states (``IDX_MB``) that :meth:`NavFilter.update_map_position`
            measures with the position, and a keyframe's height error (``IDX_KZ``, the same initial
            1-sigma; used once :meth:`NavFilter.map_bias_to_keyframe` sets it); None (the default): the
            24 states alone.
        regional_relief: With map fixes: carry the regional relief as well, four more states (``IDX_RR``,
            ``IDX_RRS``, ``IDX_RR0``; :func:`regional_relief_prior`). It needs ``map_bias_sigma_m``.

    Returns:
        The filter, with zero bias and terrain estimates and the config's initial covariance.

    Raises:
        ValueError: One line naming the bad field (``estimator.<field>``, ``x0_r_L``,
            ``x0_v_L``, ``t0_ns``, ``q0_LB`` or ``altimeter_mount_B_m``) and what is allowed.
    """
    c: EstimatorConfig = validated_config(EstimatorConfig, cfg, "estimator")
    r0 = _vec3(x0_r_L, "x0_r_L")
    v0 = _vec3(x0_v_L, "x0_v_L")
    if isinstance(t0_ns, bool) or not isinstance(t0_ns, (int, np.integer)):
        raise ValueError(f"t0_ns = {t0_ns!r}: expected an integer number of nanoseconds")
    q0: Quat | None = None
    if q0_LB is not None:
        q = np.asarray(q0_LB, dtype=float)
        if q.shape != (4,):
            raise ValueError(f"q0_LB has shape {q.shape}; expected (4,) scalar-first")
        norm = float(np.linalg.norm(q))
        if not (math.isfinite(norm) and abs(norm - 1.0) <= _QUAT_NORM_TOL):
            raise ValueError(f"q0_LB = {q.tolist()}: expected a finite unit quaternion")
        q0 = tuple(float(v) for v in q / norm)  # type: ignore[assignment]
    mount = _vec3(altimeter_mount_B_m, "altimeter_mount_B_m")
    x0 = np.concatenate([r0, v0, np.zeros(4), r0, np.zeros(11)])
    if regional_relief and map_bias_sigma_m is None:
        raise ValueError("regional_relief = True: the regional relief is carried with map fixes; "
                         "give map_bias_sigma_m as well")
    # With the regional relief the terrain under the altimeter takes its share of the site map.
    P0 = initial_covariance(c, float(r0[2]), r0[:2], local_site_config(c) if regional_relief else None)
    if map_bias_sigma_m is not None:
        # The map fixes' common error (two states) and a keyframe's height error (one, measured by nothing
        # until a keyframe is taken): zero mean, independent of the rest.
        if not (math.isfinite(map_bias_sigma_m) and map_bias_sigma_m > 0.0):
            raise ValueError(f"map_bias_sigma_m = {map_bias_sigma_m!r}: expected a finite 1-sigma > 0 [m]")
        x0 = np.concatenate([x0, np.zeros(3)])
        P0 = np.block([[P0, np.zeros((DIM_X, 3))], [np.zeros((3, DIM_X)), np.eye(3) * map_bias_sigma_m**2]])
    if regional_relief:
        n = x0.size
        x0 = np.concatenate([x0, np.zeros(4)])
        P0 = np.block([[P0, np.zeros((n, 4))], [np.zeros((4, n)), regional_relief_prior(c, r0[:2])]])
    return NavFilter(c, x0, P0, int(t0_ns), q0, mount, gyro_delta_angle=gyro_delta_angle)
