"""Fault detection, isolation and recovery (FDIR) of the flight software: sensor health from messages only.

Ports:
    Inputs (called by :class:`gnc.flight.FlightSoftware`, in time order): every
        sensor message before the filter sees it (:meth:`HealthMonitor.imu`,
        :meth:`~HealthMonitor.attitude`, :meth:`~HealthMonitor.altimeter`), the
        filter's altimeter update records, each camera frame's arrival and mean
        level, and at every control tick the navigation estimate, the thrust
        command and the footpad contacts (:meth:`~HealthMonitor.control_tick`).
    Outputs: :class:`FdirEvent` (time, subsystem, reason, action) in
        ``events``; per sensor a health flag the flight software acts on
        (exclude, substitute); ``abort`` once a safe abort is declared.
    Rate: event driven, as the messages arrive; the checks that need a clock
        run at the control rate.

It never sees truth: every check compares a sensor with its own specification
(period, range), with itself (stuck, jumps) or with another sensor or the
flight software's own commands.

Checks (thresholds in :class:`FdirConfig`):

* loss of data: no message for ``gap_periods`` periods (IMU, star tracker,
  altimeter; the camera while vision is active), or ``invalid_streak``
  messages in a row flagged invalid (the altimeter: no valid return while the
  estimated range is well inside its maximum); flagged-invalid altimeter
  ranges that are plausible and consistent with one another for
  ``invalid_streak`` samples are used anyway (through the filter's gate);
* stuck or frozen: ``stuck_samples`` messages in a row with a bit-identical
  value on an axis (a live sensor's noise never repeats a float exactly);
* plausibility: a negative or beyond-maximum range, a range change between
  consecutive samples that neither the estimated vertical speed nor the
  terrain's relief can explain (``jump_m``), an estimated height below the
  ground by more than ``negative_altitude_m`` without leg contact;
* innovations: ``rejection_streak`` altimeter updates in a row refused by the
  filter's gate, or a running mean of the altimeter's normalised innovation
  squared above ``nis_mean_max``;
* consistency between sensors: the gyro's mean rate over a star-tracker
  interval against the rate between two star-tracker fixes (a persistent
  difference: the gyro; an isolated jump: the star tracker), the
  accelerometer against the thrust the flight software commands, as the
  nominal engine delivers it (:class:`EngineResponse`; a lateral specific
  force, or an axial one that is not that thrust's: reported as
  ``accel_thrust``, the accelerometer or the engine);
* the filter's own consistency: its lateral accelerometer bias estimate beyond
  ``bias_plausible_sigmas`` of the specification and not read by the
  accelerometer (:meth:`HealthMonitor.bias_check`: re-initialised to the mean
  lateral specific force); a noisy altimeter's self-consistent line fit that the
  gate refuses (the flight software re-initialises the vertical channel,
  :meth:`gnc.flight.FlightSoftware._fitted_update`);
* the attitude actuators: the body's angular acceleration (the slope of the
  gyro's rates over ``torque_window_s``, times the nominal inertia, plus the
  gyroscopic term) against the RCS torque commanded over the same window
  (saturated at the RCS limit); a residual about an axis beyond what the
  engine may give nominally (``torque_lever_m`` times the thrust, from the
  centre-of-mass and alignment tolerances) plus ``torque_margin_Nm``, held for
  ``torque_persist_s``: an RCS thruster failed or stuck on, or a torque the
  vehicle should not have (:meth:`HealthMonitor.torque_check`; reported as
  ``rcs``, detection only: the attitude loop's feedback carries on with what
  the RCS still gives);
* the camera: a frame's mean level out of ``[image_mean_min, image_mean_max]``
  (exposure);
* the Hakuto-R guard: the altimeter rejected for ``guard_s`` while its ranges
  are consistent with themselves (smooth at the estimated vertical speed) is a
  gate that rejects a true measurement: detected as a fault of its own, and the
  filter's terrain height is re-initialised to the measured ground.

Recovery: vision whose measurements the gate mostly rejects is excluded for
``vision_retry_s``, then tried again once (excluded for good the second
time); a failed altimeter (stuck, noisy, out of range, rejected and not
consistent with itself) and a failed star tracker (stuck, invalid) are no
longer fed to the filter; a failed gyro is replaced by the star tracker's
rate, a failed accelerometer by the commanded thrust over the estimated mass
(``synthetic IMU``), and with no IMU message at all the filter is propagated
with that synthetic sample at the control rate. An engine that delivers less
than commanded updates the flight software's thrust calibration (the mass
gauge and the controller re-plan within the lower thrust).

Safe abort (:meth:`HealthMonitor.abort_reason`; not judged when guidance flies on
a navigation state given from outside, and the horizontal-velocity knowledge
only when vision is configured on): declared when the
navigation cannot support a landing within the criteria: the altitude is no
longer observed (altimeter failed or lost, and vision inactive) and the
filter's vertical 1-sigma is above ``abort_sigma_z_frac`` of the estimated
height (and above ``abort_sigma_z_min_m``); below ``abort_check_height_m``
(just above the vision cut-off) the horizontal velocity's 1-sigma is above
``abort_sigma_vh_mps``; the estimated descent cannot be stopped above the
ground at full thrust, down to the touchdown rate it lands at by design
(``(v^2 - touchdown_vz_max_mps^2) / (2 a_max) > stop_margin h``); below
``touchdown_check_height_m`` it descends with a horizontal speed above
``touchdown_vh_max_mps``; in the approach, the ground under the altimeter's footprint (the higher
of the filter's terrain height, while the altimeter is observed, and the median of its last valid
returns, whatever the monitor made of them) stands within ``abort_ground_clearance_m``
of the approach's floor or above it (the gate, 30 m above the target: ground the approach was not
planned to stop above, a plateau or a crater rim the onboard terrain lacks) and braking now at the
safe abort's deceleration (``ABORT_ACCEL_MAX_MPS2``) would stop less than that clearance above it;
or the estimated height is implausibly negative. The flight software then nulls its horizontal
velocity and climbs at ``abort_climb_mps`` instead of descending blind.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage
from gnc.numeric import clip_float

NS_PER_S = 1_000_000_000
ARCSEC = math.pi / (180.0 * 3600.0)

IMU = "imu"
ALTIMETER = "altimeter"
STAR_TRACKER = "star_tracker"
CAMERA = "camera"
RCS = "rcs"
INERTIAL_SUBSYSTEMS = frozenset({"imu", "star_tracker", "computer", "accel_thrust"})
TORQUE_EVAL_S = 0.1  # the RCS torque check's judgement period [s]
ABORT_ACCEL_MAX_MPS2 = 2.0  # the safe abort's largest commanded acceleration per axis, gravity included [m/s^2]
ACCEL_THRUST = "accel_thrust"
ENGINE = "engine"
COMPUTER = "computer"
NAVIGATION = "navigation"
PROPELLANT = "propellant"  # the terminal phase's propellant bingo (gnc.flight.FlightSoftware)


def _stop_distance_m(v_z_mps: float, decel_max_mps2: float) -> float:
    """The height [m] a descent at ``v_z_mps`` (< 0) takes to stop at the safe abort's net deceleration: the
    smaller of ``ABORT_ACCEL_MAX_MPS2`` and what the engine gives, ``decel_max_mps2`` (inf when that is none)."""
    brake = min(decel_max_mps2, ABORT_ACCEL_MAX_MPS2)
    return v_z_mps * v_z_mps / (2.0 * brake) if brake > 0.0 else math.inf


class TimeWindow:
    """Rows of floats in time order (the time first), the oldest dropped from the front.

    Held in one NumPy buffer whose live rows are a contiguous slice (moved to the front when the end
    is reached, the buffer doubled when they fill half of it), so that :meth:`rows` is the window as
    an (n, width) array without building one from Python tuples at every judgement: the same values,
    in the same C-contiguous layout, as ``np.array`` of the rows.
    """

    def __init__(self, width: int, capacity: int = 128) -> None:
        # Zeros, not np.empty: what the buffer holds beyond the live rows is state too, and two monitors
        # fed the same samples must hold the same (tests/test_dispersions.py walks everything they hold).
        self._buf = np.zeros((capacity, width))
        self._lo = self._hi = 0

    def __len__(self) -> int:
        return self._hi - self._lo

    def append(self, row: tuple[float, ...]) -> None:
        if self._hi == len(self._buf):
            n = self._hi - self._lo
            if 2 * n > len(self._buf):
                grown = np.zeros((2 * len(self._buf), self._buf.shape[1]))
                grown[:n] = self._buf[self._lo:self._hi]
                self._buf = grown
            else:
                self._buf[:n] = self._buf[self._lo:self._hi]
            self._lo, self._hi = 0, n
        self._buf[self._hi] = row
        self._hi += 1

    def drop_before(self, t0: float) -> None:
        """Drop the rows whose time is before ``t0``."""
        buf, lo, hi = self._buf, self._lo, self._hi
        while lo < hi and buf.item(lo, 0) < t0:
            lo += 1
        self._lo = lo

    def clear(self) -> None:
        self._lo = self._hi = 0

    def span(self) -> float:
        """Last time less first (the window must hold a row)."""
        return self._buf.item(self._hi - 1, 0) - self._buf.item(self._lo, 0)

    def rows(self) -> np.ndarray:
        """The rows, (n, width), a view: valid until the next append."""
        return self._buf[self._lo:self._hi]


class FdirConfig(BaseModel):
    """Fault detection thresholds and recovery switches of the flight software."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    recovery: bool = Field(True, description="act on detections (exclude, substitute, re-initialise, abort); "
                                             "false: detect and report only")
    gap_periods: float = Field(3.0, gt=1.0, description="loss of data after this many sensor periods without a message")
    invalid_streak: int = Field(10, ge=1, description="messages in a row flagged invalid before a loss is declared")
    stuck_samples: int = Field(5, ge=2, description="bit-identical values in a row on an axis: stuck [-]")
    jump_m: float = Field(15.0, gt=0.0, description="altimeter range change between samples beyond the expected [m]")
    jump_frac: float = Field(0.05, ge=0.0, description="... plus this fraction of the range [-]")
    rejection_streak: int = Field(5, ge=1, description="altimeter updates in a row rejected by the gate [-]")
    nis_window: int = Field(40, ge=5, description="altimeter updates in the NIS running mean [-]")
    nis_mean_max: float = Field(6.0, gt=1.0, description="largest running mean NIS of the altimeter (1-dof) [-]")
    noisy_fraction: float = Field(0.2, gt=0.0, lt=1.0,
                                  description="... with more than this fraction of sample pairs not self-consistent: noisy")
    guard_s: float = Field(2.0, gt=0.0, description="Hakuto-R guard: rejected this long while self-consistent [s]")
    consistency_sigmas: float = Field(
        4.0, gt=0.0, description="self-consistent: range change between samples (less the estimated descent) "
                                 "within this many sigmas of two samples' specified noise [-]"
    )
    consistency_relief_m: float = Field(0.3, ge=0.0, description="... plus this for the relief and speed error [m]")
    gyro_residual_radps: float = Field(
        5e-3, gt=0.0, description="gyro mean rate minus the star tracker's rate over one fix interval [rad/s]"
    )
    gyro_persist: int = Field(3, ge=2, description="fix intervals in a row beyond it: the gyro [-]")
    accel_window_s: float = Field(1.0, gt=0.0, description="window of the accelerometer-thrust check [s]")
    accel_lateral_max_mps2: float = Field(0.25, gt=0.0, description="largest mean lateral specific force [m/s^2]")
    accel_axial_frac: float = Field(0.15, gt=0.0, lt=1.0, description="largest relative axial specific-force error [-]")
    accel_axial_min_mps2: float = Field(
        0.3, ge=0.0,
        description="the axial check judges a window only when the thrust expected over it gives at least this "
                    "mean axial specific force [m/s^2]: below it the accelerometer's bias within its specification "
                    "(7e-3 m/s^2 1-sigma) is a large share of the reading (at 3 sigma, half the 15 % tolerance at "
                    "0.3 m/s^2; an engine coasting at 13 N on 1650 kg expects 0.008 m/s^2)",
    )
    thrust_efficiency_min: float = Field(0.85, gt=0.0, lt=1.0, description="re-plan below this delivered/commanded [-]")
    bias_plausible_sigmas: float = Field(
        3.0, gt=0.0, description="lateral bias check: the filter's accelerometer bias estimate beyond this many "
                                 "sigma of the bias's specification on an axis ... [-]")
    bias_check_sigmas: float = Field(
        3.0, gt=0.0, description="... and that far from what the accelerometer reads (its mean lateral specific "
                                 "force) by more than this many sigma of the difference [-]")
    bias_check_model_mps2: float = Field(
        3e-3, gt=0.0, description="... 1-sigma per axis of the lateral specific force that is neither the bias "
                                  "nor the thrust's misalignment (RCS, rotation about an IMU off the centre of "
                                  "mass) [m/s^2]")
    engine_alignment_deg: float = Field(
        0.25, ge=0.0, description="... the engine's alignment tolerance (largest misalignment of the thrust line; "
                                  "the lateral share of the axial specific force) [deg]")
    engine_out_frac: float = Field(0.2, ge=0.0, lt=1.0,
                                   description="at or below this delivered/commanded the engine is out: reported, "
                                               "no recalibration [-]")
    torque_window_s: float = Field(1.0, gt=0.0, description="window of the RCS torque check [s]")
    torque_lever_m: float = Field(
        0.035, ge=0.0, description="RCS torque check: the largest torque the engine may give about a lateral axis "
                                   "per unit thrust (centre-of-mass tolerance 0.03 m per axis, alignment 0.25 deg "
                                   "over about 1.2 m) [m]")
    torque_margin_Nm: float = Field(
        40.0, gt=0.0, description="... plus this, on every axis (PWM impulse granularity and gyro noise over the "
                                  "window, inertia error, RCS plume and slosh torques) [N m]")
    torque_persist_s: float = Field(0.5, gt=0.0, description="... held this long: an RCS fault [s]")
    image_mean_min: float = Field(15.0, ge=0.0, description="darkest plausible mean frame level [DN]")
    image_mean_max: float = Field(235.0, le=255.0, description="brightest plausible mean frame level [DN]")
    negative_altitude_m: float = Field(5.0, gt=0.0, description="estimated height below ground, no contact [m]")
    abort_sigma_z_frac: float = Field(0.2, gt=0.0, description="abort: vertical 1-sigma over the estimated height [-]")
    abort_sigma_z_min_m: float = Field(3.0, gt=0.0, description="abort: smallest vertical 1-sigma that aborts [m]")
    vision_window: int = Field(20, ge=5, description="vision measurements in the rejection-rate window [-]")
    vision_rejected_max: float = Field(0.5, gt=0.0, le=1.0,
                                       description="largest fraction of them the filter's gate may reject [-]")
    vision_unusable_max: float = Field(
        0.5, ge=0.0, le=1.0,
        description="at vision's altitude cut-off, beyond this share of the descent's frame pairs that gave no "
                    "measurement (a featureless ground) the lateral accelerometer bias is taken as unobserved: its "
                    "variance is raised to its specification for the terminal descent on the IMU alone [-]")
    vision_attribution_s: float = Field(
        20.0, gt=0.0, description="vision excluded for good within this of an inertial fault's detection (IMU, "
                                  "star tracker, computer) is that fault's doing: the lateral bias vision gave is "
                                  "kept [s]")
    vision_retry_s: float = Field(5.0, gt=0.0, description="an excluded vision is tried again once, after this [s] "
                                                           "(its cause may have passed: a gyro or IMU outage)")
    abort_check_height_m: float = Field(
        35.0, gt=0.0, description="below this estimated height (just above the vision cut-off, where vision stops "
                                  "improving it), the horizontal velocity must be known well enough to land [m]")
    abort_sigma_vh_mps: float = Field(0.3, gt=0.0, description="abort: horizontal velocity 1-sigma beyond this [m/s]")
    synthetic_accel_sigma_mps2: float = Field(
        0.15, gt=0.0, description="1-sigma error of the synthetic accelerometer (thrust command over mass), added to "
                                  "the filter's velocity covariance while it is used [m/s^2]")
    average_max: int = Field(400, ge=4, description="noisy altimeter: most samples fitted into one update [-]")
    touchdown_check_height_m: float = Field(
        10.0, gt=0.0, description="below this estimated height, the horizontal speed must be within the touchdown "
                                  "limit [m]")
    touchdown_vh_max_mps: float = Field(0.4, gt=0.0, description="... of this (the 0.5 m/s criterion less a margin) "
                                                                   "[m/s]")
    stop_margin: float = Field(1.0, gt=0.0, description="abort when the distance to slow to touchdown_vz_max_mps at "
                                                           "full thrust exceeds this fraction of the height [-]")
    touchdown_vz_max_mps: float = Field(
        0.9, ge=0.0, description="the descent rate the stopping check allows at the ground: the lander touches down "
                                 "at its terminal descent rate by design (the 1 m/s criterion less a margin) [m/s]")
    abort_ground_clearance_m: float = Field(
        10.0, ge=0.0,
        description="abort in the approach over ground that stands within this of the approach's floor (the "
                    "gate, gate_altitude_m above the target) or above it, when braking now at the safe abort's "
                    "deceleration would stop less than this above that ground [m] (0: off). On the default "
                    "campaign's descents (20 cases, campaign seed 3) the ground under the approach lay 8 m below "
                    "to 5 m above the target's elevation, so the check never judges them; G-FOLD's fuel-optimal "
                    "approach brakes late enough (16 m/s at 76 m) that a clearance check without the floor's "
                    "condition would abort its nominal landings")
    abort_hover_gain_per_s: float = Field(0.5, gt=0.0, description="safe abort: velocity feedback gain [1/s]")
    abort_climb_mps: float = Field(3.0, ge=0.0, le=20.0, description="safe abort: climb rate commanded [m/s]")


@dataclass(frozen=True)
class FdirEvent:
    """One detection (or recovery action) of the flight software.

    Attributes:
        t_ns: When it was detected [ns] (flight-software time: the message's or the tick's).
        subsystem: ``imu``, ``altimeter``, ``star_tracker``, ``camera``, ``accel_thrust``,
            ``engine``, ``computer`` or ``navigation``.
        reason: What was seen.
        action: What the flight software did about it (``""``: nothing).
    """

    t_ns: int
    subsystem: str
    reason: str
    action: str = ""

    def to_dict(self) -> dict:
        return {"t_s": self.t_ns / NS_PER_S, "subsystem": self.subsystem, "reason": self.reason, "action": self.action}


@dataclass
class SensorSpec:
    """What the flight software knows of its sensors' timing and range (their specification)."""

    imu_period_ns: int
    altimeter_period_ns: int
    star_tracker_period_ns: int
    camera_period_ns: int | None
    altimeter_max_range_m: float


@dataclass(frozen=True)
class EngineResponse:
    """The nominal engine's throttle response, as its specification gives it to the flight software.

    The accelerometer check compares the measured axial specific force with the thrust the
    nominal engine delivers for the commands given (first-order lag, then the slew limit, as the
    engine is specified), not with the command itself: a fuel-optimal profile's step from the
    deep-throttle limit to full thrust takes the engine 0.3 s of slewing, and over a 1 s window
    the command would run 15-25 % ahead of the thrust of a healthy engine.

    Attributes:
        time_constant_s: First-order response time constant [s] (0: none).
        slew_rate_Nps: Largest rate of change of the thrust [N/s] (inf: none).
    """

    time_constant_s: float = 0.0
    slew_rate_Nps: float = math.inf


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def body_rate_between(q0: np.ndarray, q1: np.ndarray, dt_s: float) -> np.ndarray:
    """Mean body rate [rad/s] (3,) that takes attitude ``q0`` to ``q1`` (scalar-first, body to L) in ``dt_s``."""
    dq = _quat_mul(np.array([q0[0], -q0[1], -q0[2], -q0[3]]), np.asarray(q1, float))
    if dq[0] < 0.0:
        dq = -dq
    s = math.sqrt(float(dq[1] ** 2 + dq[2] ** 2 + dq[3] ** 2))
    angle = 2.0 * math.atan2(s, float(dq[0]))
    axis = dq[1:] / s if s > 0.0 else np.zeros(3)
    return axis * angle / dt_s


def line_fit(t_s: np.ndarray, d: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares straight line ``d = slope t + intercept`` with its statistics.

    Args:
        t_s: Sample times (n,) [s], at least 3 distinct.
        d: Samples (n,).

    Returns:
        (slope, intercept (the line at t = 0), the slope's variance from the residuals,
        the residuals' variance ``sum(res^2) / (n - 2)``).
    """
    t, d = np.asarray(t_s, float), np.asarray(d, float)
    tc = t - t.mean()
    stt = float(tc @ tc)
    slope = float(tc @ (d - d.mean())) / stt
    intercept = float(d.mean()) - slope * float(t.mean())
    res = d - (slope * t + intercept)
    s2 = float(res @ res) / max(t.size - 2, 1)
    return slope, intercept, s2 / stt, s2


@dataclass
class _Stuck:
    """Per-axis counter of bit-identical values in a row (plain floats: it runs on every IMU sample)."""

    last: list[float] | None = None
    count: list[int] | None = None

    def step(self, vals: list[float]) -> list[int]:
        """Take one sample's values (a fresh list); returns the per-axis counts."""
        last = self.last
        if last is not None and len(last) == len(vals):
            self.count = [c + 1 if a == b else 0 for a, b, c in zip(vals, last, self.count)]
        else:
            self.count = [0] * len(vals)
        self.last = vals
        return self.count


class HealthMonitor:
    """Per-sensor health monitoring and the recovery decisions built on it (see the module docstring).

    Args:
        cfg: Thresholds and switches.
        spec: The sensors' periods and the altimeter's maximum range.
        engine: The nominal engine's throttle response (the accelerometer check's expected thrust);
            None: the thrust follows the command at once.
    """

    def __init__(self, cfg: FdirConfig, spec: SensorSpec, engine: EngineResponse | None = None):
        self.cfg = cfg
        self.spec = spec
        self.engine = engine or EngineResponse()
        self.events: list[FdirEvent] = []
        self.failed: set[str] = set()  # "imu.accel", "imu.gyro", "altimeter", "star_tracker"
        self.abort: FdirEvent | None = None
        self._seen: set[tuple[str, str]] = set()
        self._started = False
        self._st_silent_since: int | None = None
        # IMU
        self._imu_last_t: int | None = None
        self._imu_gap_open = False
        self._imu_invalid = 0
        self._acc_stuck, self._gyro_stuck = _Stuck(), _Stuck()
        self._gyro_sum = np.zeros(3)
        self._gyro_n = 0
        self._acc_win: deque[tuple[int, float, float, float, float]] = deque()  # (t, f_B, expected f_z), thrusting
        self._acc_sum = [0.0, 0.0, 0.0, 0.0]  # running sums over the window: f_B (3), expected f_z
        self._thrusting = False
        # The command in force (while thrusting), and the nominal engine's thrust for the commands given
        # (EngineResponse), advanced to each IMU sample.
        self._cmd = (0.0, 1.0, 1.0)  # (thrust command [N], thrust scale [-], mass [kg])
        self._engine_N: float | None = None
        self._engine_t_ns = 0
        self._lateral_run = 0
        self._axial_run = 0
        self.lateral_mean_B: tuple[int, float, float, float, int] | None = None  # (t, mean f_B (3), n), a full window
        self._bias_run = 0
        self._last_tick_ns: int | None = None
        self._tick_s = 0.02  # control period, measured from the ticks [s]
        self.last_gyro_B = np.zeros(3)
        self.last_imu_synthetic = False  # the message returned by imu() carries a synthetic specific force
        # star tracker
        self._st_last: AttitudeMessage | None = None
        self._st_gap_open = False
        self._st_invalid = 0
        self._st_stuck = _Stuck()
        self._gyro_bad_run = 0
        self._last_bad_res = 0.0
        self._st_jumps = 0
        self.st_rate_B: np.ndarray | None = None
        # altimeter
        self._alt_last_t: int | None = None
        self._alt_gap_open = False
        self._alt_invalid = 0
        self._alt_stuck = _Stuck()
        self._alt_prev: tuple[int, float] | None = None
        self._alt_nis: list[float] = []
        self._alt_reject_since: int | None = None
        self._alt_consistent_since: int | None = None
        self._flag_prev: tuple[int, float] | None = None
        self._alt_consist_hist: list[bool] = []
        self._alt_changes: list[float] = []
        self._flag_ok = 0
        self._alt_override = False
        self.terrain_reinit: tuple[float, float] | None = None  # (measured height above ground, variance) to apply
        # camera
        self._cam_last_t: int | None = None
        self._cam_gap_open = False
        self.thrust_efficiency: float | None = None
        # RCS torque check: gyro rates (t [s], wx, wy, wz) and commands (t [s], tx, ty, tz, thrust [N]) in the window
        self._rate_win = TimeWindow(4)
        self._torque_win = TimeWindow(5)
        self._torque_bad_since: int | None = None
        self._torque_eval_t: float | None = None  # the last judgement [s]
        self.torque_residual_B_Nm: np.ndarray | None = None  # the last window's residual (telemetry, tests)
        self._inertial_fault_ns: int | None = None  # the last detection on the IMU, star tracker or computer
        self._vision_hist: list[bool] = []
        self._vision_excluded_ns: int | None = None
        self._vision_exclusions = 0
        self.alt_average_n: int | None = None  # noisy altimeter: samples fitted into one update (None: off)
        self.alt_noise_factor = 1.0  # its noise over the specification's

    # ------------------------------------------------------------------ events
    def _event(self, t_ns: int, subsystem: str, reason: str, action: str = "", once_key: str | None = None) -> None:
        if subsystem in INERTIAL_SUBSYSTEMS:
            self._inertial_fault_ns = t_ns
        key = (subsystem, once_key or reason)
        if key in self._seen:
            return
        self._seen.add(key)
        self.events.append(FdirEvent(int(t_ns), subsystem, reason, action if self.cfg.recovery else ""))

    def note(self, t_ns: int, subsystem: str, reason: str, action: str = "", once_key: str | None = None) -> None:
        """An event the flight software detected itself (a recovery it made), recorded once per key."""
        self._event(t_ns, subsystem, reason, action, once_key)

    def _fail(self, t_ns: int, channel: str, reason: str, action: str) -> None:
        """Declare a channel failed (recovery then acts on it) and record the event (once per channel and check)."""
        self._event(t_ns, channel.split(".")[0], reason, action, once_key=f"{channel}:{' '.join(reason.split(' ')[:2])}")
        if self.cfg.recovery:
            self.failed.add(channel)

    def carry_events(self, events: list[FdirEvent]) -> None:
        """Events of an earlier life of the flight software (before a computer reset)."""
        self.events[:0] = events

    # ------------------------------------------------------------------ IMU
    def imu(self, msg: ImuMessage) -> ImuMessage | None:
        """Check an IMU message; returns what the filter should get (None: nothing from this one)."""
        c, t = self.cfg, msg.t_ns
        if self._imu_last_t is not None and t - self._imu_last_t > c.gap_periods * self.spec.imu_period_ns:
            self._event(t, IMU, "loss of data: IMU messages missing", "synthetic IMU from the thrust command",
                        once_key="gap")
        self._imu_last_t = t
        self._imu_gap_open = False
        if not msg.valid:
            self._imu_invalid += 1
            if self._imu_invalid >= 3:
                self._fail(t, "imu.accel", "IMU flags its data invalid", "synthetic IMU")
                if self.cfg.recovery:
                    self.failed.add("imu.gyro")
            self.last_imu_synthetic = self.cfg.recovery
            return self.synthetic_imu(t) if self.cfg.recovery else None
        self._imu_invalid = 0
        self.last_imu_synthetic = False
        f_B, w_B = np.asarray(msg.f_B, float), np.asarray(msg.omega_B, float)
        if max(self._acc_stuck.step(f_B.tolist())) >= c.stuck_samples - 1:
            self._fail(t, "imu.accel", "accelerometer output frozen (bit-identical samples)",
                       "accelerometer replaced by the thrust command over the mass")
        if max(self._gyro_stuck.step(w_B.tolist())) >= c.stuck_samples - 1:
            self._fail(t, "imu.gyro", "gyro output frozen (bit-identical samples)", "gyro replaced by the star tracker's rate")
        self._gyro_sum += w_B
        self._gyro_n += 1
        self.last_gyro_B = w_B
        wx, wy, wz = w_B.tolist()
        self._rate_win.append((t / NS_PER_S, wx, wy, wz))
        if self._thrusting:
            fx, fy, fz = f_B.tolist()
            _, scale, mass_kg = self._cmd
            self._acc_push(t, fx, fy, fz, self._engine_thrust(t) * scale / mass_kg)
            self._check_accel(t)
        else:
            self._acc_clear()
        if not self.cfg.recovery or not ({"imu.accel", "imu.gyro"} & self.failed):
            return msg
        if "imu.accel" in self.failed:
            f_B = np.array([0.0, 0.0, self._command_accel_mps2()])
            self.last_imu_synthetic = True
        if "imu.gyro" in self.failed and self.st_rate_B is not None:
            w_B = self.st_rate_B
        return ImuMessage(t, f_B, w_B)

    def synthetic_imu(self, t_ns: int) -> ImuMessage:
        """An IMU sample made from the thrust command over the mass and the star tracker's rate."""
        w = self.st_rate_B if self.st_rate_B is not None else self.last_gyro_B
        return ImuMessage(t_ns, np.array([0.0, 0.0, self._command_accel_mps2()]), np.array(w, float))

    def imu_missing(self, t_ns: int) -> bool:
        """Whether the IMU has been silent beyond its gap (the caller then feeds :meth:`synthetic_imu`)."""
        if self._imu_last_t is None:
            return False
        gone = t_ns - self._imu_last_t > self.cfg.gap_periods * self.spec.imu_period_ns
        if gone and not self._imu_gap_open:
            self._imu_gap_open = True
            self._event(t_ns, IMU, "loss of data: IMU messages missing", "synthetic IMU from the thrust command",
                        once_key="gap")
        return gone

    def _command_accel_mps2(self) -> float:
        """The commanded thrust over the mass, along +z [m/s^2] (0 when not thrusting)."""
        if not self._thrusting:
            return 0.0
        thrust_cmd_N, scale, mass_kg = self._cmd
        return thrust_cmd_N * scale / mass_kg

    def _engine_thrust(self, t_ns: int) -> float:
        """The nominal engine's thrust at ``t_ns`` [N]: the command in force since the last update
        through the first-order lag, then the slew limit (the order the engine model applies)."""
        cmd = self._cmd[0]
        if self._engine_N is None:  # lit: burning at the first command
            self._engine_N, self._engine_t_ns = cmd, t_ns
            return cmd
        dt = (t_ns - self._engine_t_ns) / NS_PER_S
        if dt <= 0.0:
            return self._engine_N
        thrust = self._engine_N
        tau = self.engine.time_constant_s
        new = cmd + (thrust - cmd) * math.exp(-dt / tau) if tau > 0.0 else cmd
        max_change = self.engine.slew_rate_Nps * dt
        new = min(max(new, thrust - max_change), thrust + max_change)
        self._engine_N, self._engine_t_ns = new, t_ns
        return new

    def _acc_push(self, t: int, fx: float, fy: float, fz: float, expect: float) -> None:
        self._acc_win.append((t, fx, fy, fz, expect))
        acc = self._acc_sum
        acc[0] += fx
        acc[1] += fy
        acc[2] += fz
        acc[3] += expect

    def _acc_clear(self) -> None:
        self._acc_win.clear()
        self._acc_sum = [0.0, 0.0, 0.0, 0.0]
        self.lateral_mean_B = None
        self._bias_run = 0

    def bias_check(self, t_ns: int, b_xy: tuple[float, float], var_xy: tuple[float, float],
                   noise_density: float, bias_sigma: float) -> tuple[float, float, float] | None:
        """The filter's lateral accelerometer bias: plausible, and read by the accelerometer (a control tick)?

        Vision measurements that pass the gate but are wrong move the bias estimate through its correlation
        with the velocity; a filter so misled is confidently wrong about its horizontal velocity, and below
        the vision cut-off that error grows unseen. Two conditions, both held for half a window of ticks:

        * the estimate is beyond ``bias_plausible_sigmas`` times the bias's specification ``bias_sigma`` on
          an axis (an accelerometer within its datasheet rarely has such a bias);
        * on that axis the accelerometer itself does not read it: with the engine lit along +z its mean
          lateral specific force over the window is its bias plus the thrust's share through the engine's
          misalignment (within ``engine_alignment_deg``, uniform in size and in any direction: 1-sigma per
          axis the tolerance over sqrt(6), times the mean axial specific force), a constant
          ``bias_check_model_mps2`` (RCS, rotation) and its white noise; the difference to the estimate is
          beyond ``bias_check_sigmas`` of those and the estimate's own variance.

        Args:
            t_ns: The control tick [ns].
            b_xy: The filter's bias estimate, body x and y [m/s^2].
            var_xy: Its variances [(m/s^2)^2].
            noise_density: The accelerometer's white-noise density (specification) [m/s^2/sqrt(Hz)].
            bias_sigma: The accelerometer bias's 1-sigma per axis (specification) [m/s^2].

        Returns:
            None, or on a detection with recovery on: (mean f_x, mean f_y [m/s^2], the variance of each
            as a bias [(m/s^2)^2]), the bias the filter should take.
        """
        c, lm = self.cfg, self.lateral_mean_B
        if lm is None or not self._thrusting or "imu.accel" in self.failed or t_ns - lm[0] > 2 * self.spec.imu_period_ns:
            self._bias_run = 0
            return None
        _, fx, fy, fz, n = lm
        # Misalignment uniform in size below the tolerance, in any direction: 1-sigma per axis tolerance / sqrt(6).
        tilt = math.radians(c.engine_alignment_deg) / math.sqrt(6.0) * abs(fz)
        r = c.bias_check_model_mps2 ** 2 + tilt**2 + noise_density ** 2 / (n * self.spec.imu_period_ns / NS_PER_S)
        bad = [abs(b) > c.bias_plausible_sigmas * bias_sigma
               and abs(f - b) > c.bias_check_sigmas * math.sqrt(v + r)
               for f, b, v in ((fx, b_xy[0], var_xy[0]), (fy, b_xy[1], var_xy[1]))]
        self._bias_run = self._bias_run + 1 if any(bad) else 0
        if self._bias_run * self._tick_s < 0.5 * c.accel_window_s:
            return None
        self._event(t_ns, NAVIGATION, f"accelerometer bias estimate ({b_xy[0]:+.3f}, {b_xy[1]:+.3f}) m/s^2 beyond "
                                      f"{c.bias_plausible_sigmas:g} sigma of its specification and not read by the "
                                      f"accelerometer (mean lateral specific force ({fx:+.3f}, {fy:+.3f}) m/s^2): "
                                      "the filter's horizontal channel is wrong",
                    "bias re-initialised to the lateral specific force, horizontal velocity covariance inflated",
                    once_key="bias")
        self._bias_run = 0
        self._acc_clear()  # the next judgement needs a fresh window
        return (fx, fy, r) if c.recovery else None

    def torque_check(self, t_ns: int, torque_cmd_B_Nm: np.ndarray, thrust_N: float, inertia_B_kgm2: np.ndarray,
                     torque_max_Nm: float) -> np.ndarray | None:
        """The RCS against its command (module docstring), at a control tick.

        Args:
            t_ns: The control tick [ns].
            torque_cmd_B_Nm: The torque commanded from this tick on, (3,) [N m] (saturated here at
                ``torque_max_Nm`` per axis, as the RCS can give no more).
            thrust_N: The thrust commanded from this tick on (0: engine off) [N].
            inertia_B_kgm2: The flight software's principal inertia now, (3,) [kg m^2].
            torque_max_Nm: The RCS's torque limit per axis [N m].

        Returns:
            The window's residual torque (3,) [N m], measured less commanded, when the window is full and a
            judgement is due (every ``TORQUE_EVAL_S``; also in ``torque_residual_B_Nm``); None otherwise.
        """
        c = self.cfg
        t = t_ns / NS_PER_S
        rates, cmds = self._rate_win, self._torque_win
        if "imu.gyro" in self.failed or not (self._thrusting or thrust_N > 0.0):
            rates.clear()
            cmds.clear()
            self._torque_bad_since = None
            self._torque_eval_t = None
            return None
        tx, ty, tz = (clip_float(v, -torque_max_Nm, torque_max_Nm)
                      for v in np.asarray(torque_cmd_B_Nm, float).tolist())
        cmds.append((t, tx, ty, tz, float(thrust_N)))
        t0 = t - c.torque_window_s
        rates.drop_before(t0)
        cmds.drop_before(t0)
        if len(rates) < 5 or len(cmds) < 3 or rates.span() < 0.9 * c.torque_window_s:
            return None
        if self._torque_eval_t is not None and t - self._torque_eval_t < TORQUE_EVAL_S - 1e-9:
            return None  # judged at 10 Hz: the window is 1 s, the persistence 0.5 s
        self._torque_eval_t = t
        w = rates.rows()
        tc = w[:, 0] - w[:, 0].mean()
        alpha = tc @ (w[:, 1:] - w[:, 1:].mean(axis=0)) / float(tc @ tc)  # the rates' slope [rad/s^2]
        w_mean = w[:, 1:].mean(axis=0)
        inertia = np.asarray(inertia_B_kgm2, float)
        # The commands in force over the rates' span: each holds from its tick to the next (the last one,
        # issued now, has not acted yet).
        u = cmds.rows()
        in_span = (u[:, 0] >= w[0, 0] - self._tick_s) & (u[:, 0] < w[-1, 0])
        if not in_span.any():
            return None
        tau_cmd = u[in_span, 1:4].mean(axis=0)
        thrust = float(u[in_span, 4].mean())
        residual = inertia * alpha + np.cross(w_mean, inertia * w_mean) - tau_cmd
        self.torque_residual_B_Nm = residual
        envelope = np.array([c.torque_lever_m * thrust, c.torque_lever_m * thrust, 0.0]) + c.torque_margin_Nm
        if (np.abs(residual) > envelope).any():
            if self._torque_bad_since is None:
                self._torque_bad_since = t_ns
            elif t_ns - self._torque_bad_since >= c.torque_persist_s * NS_PER_S:
                ax = int(np.argmax(np.abs(residual) - envelope))
                self._event(t_ns, RCS, f"torque about body {'xyz'[ax]} {residual[ax]:+.0f} N m other than "
                                       f"commanded (beyond the {envelope[ax]:.0f} N m the engine may give): an RCS "
                                       "thruster failed or stuck on", "reported; attitude feedback carries on",
                            once_key="torque")
        else:
            self._torque_bad_since = None
        return residual

    def _check_accel(self, t: int) -> None:
        c = self.cfg
        win_ns = c.accel_window_s * NS_PER_S
        win, acc = self._acc_win, self._acc_sum
        while win and t - win[0][0] > win_ns:
            _, fx, fy, fz, e = win.popleft()
            acc[0] -= fx
            acc[1] -= fy
            acc[2] -= fz
            acc[3] -= e
        if not win or t - win[0][0] < 0.9 * win_ns or "imu.accel" in self.failed:
            return
        n = len(win)
        expect = acc[3] / n
        mean = (acc[0] / n, acc[1] / n, acc[2] / n)
        # A violation must hold for half a window of samples in a row (an impact's spike does not).
        persist = 0.5 * win_ns / self.spec.imu_period_ns
        self.lateral_mean_B = (t, mean[0], mean[1], mean[2], n)
        lateral = math.hypot(mean[0], mean[1]) > c.accel_lateral_max_mps2
        self._lateral_run = self._lateral_run + 1 if lateral else 0
        if self._lateral_run >= persist:
            self._event(t, ACCEL_THRUST, f"lateral specific force {math.hypot(mean[0], mean[1]):.2f} m/s^2 "
                                         "(accelerometer bias or thrust misalignment)", once_key="lateral")
        if expect > 0.0 and expect >= c.accel_axial_min_mps2:
            eff = mean[2] / expect
            self._axial_run = self._axial_run + 1 if abs(eff - 1.0) > c.accel_axial_frac else 0
            if self._axial_run >= persist:
                self._event(t, ACCEL_THRUST, f"axial specific force {eff:.2f} x the commanded thrust's "
                                             "(accelerometer or engine)",
                            "thrust calibration updated" if c.engine_out_frac < eff < c.thrust_efficiency_min else "",
                            once_key="axial")
                if eff <= c.engine_out_frac:
                    self._event(t, ENGINE, f"engine delivers {100 * eff:.0f} % of the commanded thrust (out)",
                                once_key="out")
                elif c.recovery and eff < c.thrust_efficiency_min and self.thrust_efficiency is None:
                    self.thrust_efficiency = float(eff)  # relative to the calibration in force
                    self._acc_clear()  # the next estimate starts afresh, under the new calibration
                    self._axial_run = 0

    # ------------------------------------------------------------------ star tracker
    def attitude(self, msg: AttitudeMessage) -> AttitudeMessage | None:
        """Check a star-tracker fix; returns it, or None when the tracker is excluded."""
        c, t = self.cfg, msg.t_ns
        if self._st_last is not None and t - self._st_last.t_ns > c.gap_periods * self.spec.star_tracker_period_ns:
            self._event(t, STAR_TRACKER, "loss of data: star-tracker fixes missing", once_key="gap")
        self._st_gap_open = False
        if not msg.valid:
            self._st_invalid += 1
            if self._st_invalid >= 3:
                self._fail(t, STAR_TRACKER, "star tracker flags its solution invalid", "attitude from the gyro alone")
            return None
        self._st_invalid = 0
        q = np.asarray(msg.q_LB, float)
        if min(self._st_stuck.step(q.tolist())) >= c.stuck_samples - 3:  # fixes come 10x slower than IMU samples
            self._fail(t, STAR_TRACKER, "star-tracker attitude frozen (bit-identical fixes)", "attitude from the gyro alone")
        prev = self._st_last
        self._st_last = msg
        if prev is not None and self._gyro_n > 0 and STAR_TRACKER not in self.failed:
            dt = (t - prev.t_ns) / NS_PER_S
            rate = body_rate_between(prev.q_LB, q, dt)
            gyro = self._gyro_sum / self._gyro_n
            res = float(np.linalg.norm(gyro - rate))
            bad = res > c.gyro_residual_radps
            if bad:
                self._gyro_bad_run += 1
                self._last_bad_res = res * dt
                if self._gyro_bad_run >= c.gyro_persist:  # persistent: the gyro
                    self._fail(t, "imu.gyro", f"gyro disagrees with the star tracker by {res:.4f} rad/s "
                                              f"for {self._gyro_bad_run} fixes", "gyro replaced by the star tracker's rate")
            else:
                if 0 < self._gyro_bad_run < c.gyro_persist:  # an isolated disagreement: the tracker jumped
                    self._event(t, STAR_TRACKER, f"attitude jump of {self._last_bad_res / ARCSEC:.0f} arcsec between "
                                                 "fixes that the gyro did not see", once_key="jump")
                    self._st_jumps += 1
                self._gyro_bad_run = 0
            if not bad or self._gyro_bad_run >= c.gyro_persist:
                self.st_rate_B = rate
        self._gyro_sum = np.zeros(3)
        self._gyro_n = 0
        if STAR_TRACKER in self.failed and self.cfg.recovery:
            return None
        return msg

    # ------------------------------------------------------------------ altimeter
    def _consistent(self, change_m: float, sigma_m: float) -> bool:
        """A range change between samples (less the estimated descent) within the noise of two samples and the relief."""
        return abs(change_m) <= self.cfg.consistency_sigmas * math.sqrt(2.0) * sigma_m + self.cfg.consistency_relief_m

    def altimeter(self, msg: AltimeterMessage, est_range_m: float | None, v_z_mps: float,
                  sigma_m: float) -> AltimeterMessage | None:
        """Check an altimeter sample before the filter; returns it, or None when the altimeter is excluded.

        Args:
            msg: The sample.
            est_range_m: The range the navigation expects now [m] (None: unknown).
            v_z_mps: The estimated vertical speed [m/s] (for the jump and self-consistency checks).
            sigma_m: The range noise 1-sigma of the altimeter's specification at this range [m].
        """
        c, t = self.cfg, msg.t_ns
        if self._alt_last_t is not None and t - self._alt_last_t > c.gap_periods * self.spec.altimeter_period_ns:
            self._event(t, ALTIMETER, "loss of data: altimeter samples missing", once_key="gap")
        self._alt_last_t = t
        self._alt_gap_open = False
        in_range = est_range_m is not None and est_range_m < 0.9 * self.spec.altimeter_max_range_m
        if not msg.valid:
            self._alt_invalid += 1
            if self._alt_invalid >= c.invalid_streak and in_range:
                self._event(t, ALTIMETER, "no valid range in range of the surface (flagged invalid or no return)",
                            once_key="invalid")
            # Valid-but-flagged-invalid: ranges that are plausible and consistent with one another for a
            # streak are used (the filter's gate still checks each against the navigation).
            rho = float(msg.range_m)
            if math.isfinite(rho) and 0.0 < rho <= self.spec.altimeter_max_range_m:
                prev = self._flag_prev
                smooth = prev is not None and self._consistent(rho - prev[1] - v_z_mps * (t - prev[0]) / NS_PER_S,
                                                               sigma_m)
                self._flag_ok = self._flag_ok + 1 if smooth else 0
                self._flag_prev = (t, rho)
            else:
                self._flag_ok = 0
            if not (c.recovery and self._flag_ok >= c.invalid_streak):
                self._alt_override = False
                return None
            self._event(t, ALTIMETER, "altimeter flags its ranges invalid, but they are plausible and consistent",
                        "flag overridden: ranges used through the filter's gate", once_key="override")
            self._alt_override = True
            msg = AltimeterMessage(msg.t_ns, msg.range_m, True, msg.boresight_B)
        else:
            self._alt_invalid = 0
            self._alt_override = False
        rho = float(msg.range_m)
        if not math.isfinite(rho) or rho < 0.0 or rho > self.spec.altimeter_max_range_m:
            self._fail(t, ALTIMETER, f"implausible range {rho:.1f} m", "altimeter excluded")
        if self._alt_stuck.step([float(rho)])[0] >= c.stuck_samples - 3:
            self._fail(t, ALTIMETER, "altimeter range frozen (bit-identical samples)", "altimeter excluded")
        prev = self._alt_prev
        self._alt_prev = (t, rho)
        consistent = True
        if prev is not None:
            dt = (t - prev[0]) / NS_PER_S
            change = rho - prev[1] - v_z_mps * dt
            if abs(change) > c.jump_m + c.jump_frac * rho:
                self._event(t, ALTIMETER, f"range jump of {change:+.1f} m between samples, beyond what the "
                                          "descent and the terrain explain", once_key="jump")
            consistent = self._consistent(change, sigma_m)
        self._alt_consist_hist.append(consistent)
        del self._alt_consist_hist[:-c.nis_window]
        if prev is not None:
            self._alt_changes.append(change)
            del self._alt_changes[:-c.nis_window]
        if consistent:
            self._alt_consistent_since = self._alt_consistent_since or t
        else:
            self._alt_consistent_since = None
        if ALTIMETER in self.failed and self.cfg.recovery:
            return None
        return msg

    def altimeter_record(self, t_ns: int, accepted: bool, nis: float, range_m: float,
                         est_height_m: float | None, var_m2: float) -> None:
        """The filter's verdict on an altimeter update (innovation streaks, NIS, the Hakuto-R guard).

        Args:
            t_ns: The sample's time [ns].
            accepted: Whether the gate accepted it.
            nis: Its normalised innovation squared (NaN when not computed).
            range_m: The measured range [m].
            est_height_m: The filter's altimeter height above its terrain estimate [m] (prior).
            var_m2: The range measurement variance the filter uses [m^2].
        """
        c = self.cfg
        if math.isfinite(nis):
            self._alt_nis.append(nis)
            del self._alt_nis[:-c.nis_window]
            # The cheap conditions first: this runs on every altimeter update.
            if len(self._alt_nis) == c.nis_window and self.alt_average_n is None \
                    and sum(self._alt_nis) / c.nis_window > c.nis_mean_max:
                hist = self._alt_consist_hist
                ch = np.array(self._alt_changes)
                # White range noise makes successive changes alternate (lag-1 correlation -1/2); a slope or a
                # step does not.
                alternating = ch.size >= 10 and float(np.mean(ch[1:] * ch[:-1])) < -0.25 * float(np.mean(ch * ch))
                noisy = (len(hist) >= c.nis_window // 2 and hist.count(False) / len(hist) > c.noisy_fraction
                         and alternating)
            else:
                noisy = False
            if noisy:  # a consistent sensor the gate refuses: the guard's case
                # The noise's factor over the specification, from the spread of the changes between samples.
                k2 = float(np.mean(ch * ch)) / (2.0 * var_m2) if var_m2 > 0.0 else math.inf
                # A line's endpoint over n samples has about 4/n of one sample's variance: n = 2 k^2 brings it
                # to within sqrt(2) of the specification the filter weighs it with.
                n = int(math.ceil(2.0 * k2)) if math.isfinite(k2) else c.average_max + 1
                if c.recovery and n <= c.average_max:
                    self.alt_average_n = max(n, 4)
                    self.alt_noise_factor = math.sqrt(k2)
                    nis_mean = float(np.mean(self._alt_nis))
                    self._alt_nis.clear()
                    self._event(t_ns, ALTIMETER, f"altimeter innovations too large (mean NIS {nis_mean:.1f}), "
                                                 f"its noise about {math.sqrt(k2):.1f} x the specification",
                                f"ranges fitted {self.alt_average_n} at a time", once_key="noisy")
                else:
                    self._fail(t_ns, ALTIMETER, f"altimeter innovations too large (mean NIS "
                                                f"{np.mean(self._alt_nis):.1f})", "altimeter excluded")
        if accepted:
            self._alt_reject_since = None
            return
        self._alt_reject_since = self._alt_reject_since or t_ns
        streak_s = (t_ns - self._alt_reject_since) / NS_PER_S
        n_streak = streak_s / (self.spec.altimeter_period_ns / NS_PER_S) + 1
        if n_streak >= c.rejection_streak:
            self._event(t_ns, ALTIMETER, f"{c.rejection_streak} altimeter updates in a row rejected by the gate",
                        once_key="streak")
        if streak_s >= c.guard_s:
            consistent_s = (t_ns - self._alt_consistent_since) / NS_PER_S if self._alt_consistent_since else 0.0
            if consistent_s >= c.guard_s and est_height_m is not None:
                self._event(t_ns, ALTIMETER, f"gate has rejected a self-consistent altimeter for {streak_s:.1f} s "
                                             "(Hakuto-R guard): the terrain changed, not the sensor",
                            "terrain height re-initialised to the measured ground", once_key="guard")
                if c.recovery:
                    self.terrain_reinit = (range_m, var_m2)
                    self._alt_nis.clear()  # the innovations before the re-initialisation say nothing of the sensor
                self._alt_reject_since = None
            elif consistent_s < c.guard_s and streak_s >= 2 * c.guard_s:
                self._fail(t_ns, ALTIMETER, f"altimeter rejected for {streak_s:.1f} s and not self-consistent",
                           "altimeter excluded")

    def altitude_lost(self, t_ns: int, est_range_m: float | None) -> bool:
        """No usable altimeter now: failed, silent beyond its gap, or invalid in range of the surface."""
        if ALTIMETER in self.failed:
            return True
        c = self.cfg
        if self._alt_last_t is not None and t_ns - self._alt_last_t > c.gap_periods * self.spec.altimeter_period_ns:
            if not self._alt_gap_open:
                self._alt_gap_open = True
                self._event(t_ns, ALTIMETER, "loss of data: altimeter samples missing", once_key="gap")
            return True
        in_range = est_range_m is not None and est_range_m < 0.9 * self.spec.altimeter_max_range_m
        return in_range and self._alt_invalid >= c.invalid_streak and not self._alt_override

    def vision_record(self, t_ns: int, accepted: bool) -> bool:
        """The filter's verdict on a vision measurement (the rejection rate over a window).

        Returns True when this verdict excludes vision for good (its second exclusion: the first is
        retried, its cause may have been another sensor's) and recovery is on, unless an inertial fault
        (IMU, star tracker, computer) was detected within ``vision_attribution_s`` before: vision itself is
        then the failing sensor, the measurements the gate let through while it failed are suspect too,
        and what only vision observes (the lateral accelerometer bias) is to be re-initialised
        (:meth:`gnc.flight.FlightSoftware._measure`). After an inertial fault the rejections are that
        fault's (the filter's state went wrong, vision did not), and the bias vision gave before is kept.
        """
        c = self.cfg
        self._vision_hist.append(accepted)
        del self._vision_hist[:-c.vision_window]
        if len(self._vision_hist) == c.vision_window:
            frac = self._vision_hist.count(False) / c.vision_window
            if frac > c.vision_rejected_max and "vision" not in self.failed:
                self._vision_exclusions += 1
                retry = self._vision_exclusions == 1
                self._fail(t_ns, "vision", f"vision measurements {100 * frac:.0f} % rejected by the gate",
                           f"vision excluded for {c.vision_retry_s:g} s" if retry else "vision excluded")
                self._vision_excluded_ns = t_ns if retry else None
                inertial = self._inertial_fault_ns is not None and \
                    t_ns - self._inertial_fault_ns <= c.vision_attribution_s * NS_PER_S
                if not retry and c.recovery:  # the second exclusion's event has the first's key: a note of its own
                    self._event(t_ns, "vision", "vision measurements rejected again after the retry",
                                "vision excluded" + ("" if inertial else
                                                     "; lateral accelerometer bias re-initialised to its "
                                                     "specification"), once_key="vision_final")
                return c.recovery and not retry and not inertial
        return False

    # ------------------------------------------------------------------ camera
    def image(self, t_ns: int, mean_dn: float | None) -> None:
        """A camera frame arrived (``mean_dn``: its mean level, None when not looked at)."""
        c = self.cfg
        if self._cam_last_t is not None and self.spec.camera_period_ns is not None \
                and t_ns - self._cam_last_t > c.gap_periods * self.spec.camera_period_ns:
            self._event(t_ns, CAMERA, "loss of data: camera frames missing", once_key="gap")
        if self._cam_last_t is not None and self.spec.camera_period_ns is not None \
                and t_ns - self._cam_last_t > 1.5 * self.spec.camera_period_ns:
            self._event(t_ns, CAMERA, "camera frames dropped", once_key="drop")
        self._cam_last_t = t_ns
        self._cam_gap_open = False
        if mean_dn is not None and not (c.image_mean_min <= mean_dn <= c.image_mean_max):
            self._event(t_ns, CAMERA, f"frame mean level {mean_dn:.0f} DN out of [{c.image_mean_min:g}, "
                                      f"{c.image_mean_max:g}] (exposure)", once_key="exposure")

    def camera_check(self, t_ns: int, expecting: bool) -> None:
        """At a control tick: frames overdue while vision expects them."""
        p = self.spec.camera_period_ns
        if not expecting or p is None or self._cam_last_t is None:
            return
        if t_ns - self._cam_last_t > self.cfg.gap_periods * p and not self._cam_gap_open:
            self._cam_gap_open = True
            self._event(t_ns, CAMERA, "loss of data: camera frames missing", once_key="gap")

    # ------------------------------------------------------------------ control tick
    def start(self, t_ns: int) -> None:
        """The first control tick: every sensor is expected from now on (one that never speaks is lost too)."""
        if self._started:
            return
        self._started = True
        self._imu_last_t = t_ns if self._imu_last_t is None else self._imu_last_t
        self._alt_last_t = t_ns if self._alt_last_t is None else self._alt_last_t
        if self._st_last is None:
            self._st_silent_since = t_ns

    def control_tick(self, t_ns: int, thrust_cmd_N: float, thrust_scale: float, mass_kg: float,
                     contact: bool) -> None:
        """Record the command in force (for the accelerometer check) and run the clocked checks."""
        self._thrusting = thrust_cmd_N > 0.0 and not contact and mass_kg > 0.0
        if self._last_tick_ns is not None and t_ns > self._last_tick_ns:
            self._tick_s = (t_ns - self._last_tick_ns) / NS_PER_S
        self._last_tick_ns = t_ns
        if self._vision_excluded_ns is not None and t_ns - self._vision_excluded_ns >= self.cfg.vision_retry_s * NS_PER_S:
            self.failed.discard("vision")  # tried again; a new streak of rejections excludes it again
            self._vision_excluded_ns = None
            self._vision_hist.clear()
        if self._thrusting:
            if self._engine_N is not None:
                self._engine_thrust(t_ns)  # the last command's response up to now
            self._cmd = (thrust_cmd_N, thrust_scale, mass_kg)
        else:
            self._engine_N = None  # shut down (or on the ground): lit again at the next command
        p = self.spec.star_tracker_period_ns
        last = self._st_last.t_ns if self._st_last is not None else self._st_silent_since
        if last is not None and t_ns - last > self.cfg.gap_periods * p \
                and not self._st_gap_open and STAR_TRACKER not in self.failed:
            self._st_gap_open = True
            self._event(t_ns, STAR_TRACKER, "loss of data: star-tracker fixes missing", once_key="gap")

    def abort_reason(self, t_ns: int, height_m: float, sigma_z_m: float, altitude_observed: bool,
                     contact: bool, sigma_vh_mps: float = 0.0, v_z_mps: float = 0.0,
                     decel_max_mps2: float = math.inf, v_h_mps: float = 0.0,
                     ground_m: float = math.nan, plan_floor_m: float = math.nan,
                     approach: bool = False) -> str | None:
        """The safe-abort criterion (module docstring); the first reason declares the abort.

        ``decel_max_mps2``: the largest net upward acceleration the engine can give now (thrust limit over
        the mass, less gravity) [m/s^2]; with the descent rate ``v_z_mps`` it says whether the lander can
        still stop above the ground. ``ground_m``: the elevation of the ground under the altimeter's footprint
        in the frame of ``height_m`` [m] (the filter's terrain height; NaN while the altimeter does not
        observe it); ``plan_floor_m``: the lowest point of guidance's approach in that frame, its gate [m]
        (NaN: unknown, a law without a gate); ``approach``: guidance flies its approach phase (the
        ground-clearance check).
        """
        if self.abort is not None or contact or not self.cfg.recovery:
            return None
        c = self.cfg
        reason = None
        if height_m < -c.negative_altitude_m:
            self._event(t_ns, NAVIGATION, f"estimated height {height_m:.1f} m below the ground without contact",
                        once_key="negative")
            reason = "implausible negative altitude estimate"
        elif not altitude_observed and sigma_z_m > max(c.abort_sigma_z_min_m, c.abort_sigma_z_frac * max(height_m, 0.0)):
            reason = (f"altitude not observed and its 1-sigma {sigma_z_m:.1f} m is beyond "
                      f"{100 * c.abort_sigma_z_frac:.0f} % of the height {height_m:.1f} m")
        elif v_z_mps < 0.0 and height_m > 0.0 and (
                decel_max_mps2 <= 0.0
                or (v_z_mps**2 - c.touchdown_vz_max_mps**2) / (2.0 * decel_max_mps2) > c.stop_margin * height_m):
            reason = (f"cannot stop before the ground: {-v_z_mps:.1f} m/s down at {height_m:.0f} m with "
                      f"{decel_max_mps2:.2f} m/s^2 of net deceleration")
        elif (approach and v_z_mps < 0.0 and c.abort_ground_clearance_m > 0.0
              and ground_m > plan_floor_m - c.abort_ground_clearance_m
              and (stop_above_m := height_m - ground_m - _stop_distance_m(v_z_mps, decel_max_mps2))
              < c.abort_ground_clearance_m):
            reason = (f"ground {ground_m - plan_floor_m:+.0f} m from the approach's floor, {height_m - ground_m:.0f} m "
                      f"below at {-v_z_mps:.1f} m/s: braking now stops {stop_above_m:.0f} m above it, under "
                      f"{c.abort_ground_clearance_m:g} m")
        elif height_m < c.touchdown_check_height_m and v_z_mps < 0.0 and v_h_mps > c.touchdown_vh_max_mps:
            reason = (f"descending at {height_m:.1f} m with {v_h_mps:.2f} m/s of horizontal speed, beyond "
                      f"{c.touchdown_vh_max_mps:g} m/s")
        elif height_m < c.abort_check_height_m and sigma_vh_mps > c.abort_sigma_vh_mps:
            reason = (f"horizontal velocity 1-sigma {sigma_vh_mps:.2f} m/s at {height_m:.0f} m, beyond "
                      f"{c.abort_sigma_vh_mps:g} m/s")
        if reason is not None:
            self.declare_abort(t_ns, NAVIGATION, reason)
        return reason

    def declare_abort(self, t_ns: int, subsystem: str, reason: str) -> None:
        """Declare the safe abort (hover) for ``reason``, unless one is declared already; recorded as an event."""
        if self.abort is None:
            self.abort = FdirEvent(int(t_ns), subsystem, reason, "safe abort: hover")
            self.events.append(self.abort)


def restart_estimate(x: np.ndarray, P: np.ndarray, dt_s: float, gravity_mps2: float,
                     accel_sigma_mps2: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A checkpointed filter state carried ballistically (engine off) over an outage of ``dt_s``.

    Position and velocity follow free fall; their covariance grows by the
    carried velocity uncertainty and an unknown acceleration of
    ``accel_sigma_mps2`` (engine tail-off, RCS) over the outage.

    Args:
        x: Filter state (24,): position (0:3) and velocity (3:6) first.
        P: Its covariance (24, 24).
        dt_s: Outage [s].
        gravity_mps2: Surface gravity [m/s^2].
        accel_sigma_mps2: 1-sigma of the unmodelled acceleration [m/s^2].

    Returns:
        (x (24,), P (24, 24)), new arrays.
    """
    x, P = np.array(x, float), np.array(P, float)
    g_L = np.array([0.0, 0.0, -gravity_mps2])
    x[0:3] += x[3:6] * dt_s + 0.5 * g_L * dt_s**2
    x[3:6] += g_L * dt_s
    F = np.eye(P.shape[0])
    F[0:3, 3:6] = np.eye(3) * dt_s
    P = F @ P @ F.T
    q = accel_sigma_mps2**2
    P[0:3, 0:3] += np.eye(3) * q * dt_s**4 / 4.0
    P[0:3, 3:6] += np.eye(3) * q * dt_s**3 / 2.0
    P[3:6, 0:3] += np.eye(3) * q * dt_s**3 / 2.0
    P[3:6, 3:6] += np.eye(3) * q * dt_s**2
    return x, P
