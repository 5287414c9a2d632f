"""The flight computer: messages in, actuator commands out.

Ports:
    Inputs: :class:`ImuMessage` (IMU rate), :class:`AttitudeMessage` (star
        tracker rate), :class:`AltimeterMessage` (altimeter rate), camera
        frames as :class:`ImageMessage` or ready-made tracks (camera rate),
        :class:`ContactMessage` (control rate).
    Output: :class:`ActuatorCommand` (control rate), plus the navigation
        state and vision bookkeeping for telemetry.
    Rate: event driven; the bench calls the ``on_*`` methods in time order.

Knowledge: everything the flight computer knows of its vehicle is in one
:class:`OnboardKnowledge`: the nominal vehicle (mass, inertia, engine), its
calibration (camera and altimeter mounts, intrinsics) and, in the filter's
configuration, its sensors' specifications. It never sees the truth: the bench
builds it from the nominal scenario plus explicit knowledge errors.

Navigation: the filter (:mod:`gnc.estimator`) is propagated with the IMU and
the star-tracker attitude and updated with the altimeter. Above the vision
cut-off altitude each camera frame clones the position into the filter
(stochastic cloning), and the tracks of a frame pair are a measurement of the
current position relative to that clone (:mod:`gnc.vision_nav`), with the
rotation between the frames from the integrated gyro. Below the cut-off, IMU
and altimeter carry navigation to touchdown.

Health (:mod:`gnc.fdir`): every message passes the health monitor before
the filter; it may substitute (a synthetic IMU sample, the star tracker's rate
for a failed gyro), withhold (an excluded sensor) or average (a noisy
altimeter) it, re-initialise the filter's terrain height (the Hakuto-R
guard), recalibrate the thrust, and declare a safe abort, after which
guidance is replaced by a climb. Monitoring ends at the first leg contact.
The state, covariance, mass and attitude are checkpointed at hand-over and at
every control tick (non-volatile memory, for a restart after a computer reset).

Mass is the flight computer's own propellant gauging: the mass estimate at
hand-over minus the integral of the thrust it believes it commanded,
``thrust_cmd * thrust_scale``, over the nominal ``Isp g0``. A real engine that
delivers a different thrust makes the gauge drift from the truth.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from gnc.control import ActuatorCommand, Controller, VehicleParams
from gnc.estimator import IDX_BA, IDX_C, IDX_G, IDX_H, IDX_R, IDX_SV, IDX_V, NavFilter, UpdateRecord, quat_to_matrix
from gnc.fdir import ABORT_ACCEL_MAX_MPS2, NAVIGATION, PROPELLANT, HealthMonitor, line_fit
from gnc.guidance import PHASE_APPROACH, PHASE_TERMINAL, GuidanceCommand, GuidanceLaw, LandingTarget
from gnc.hda import HazardAvoidance
from gnc.map_nav import MapNavigator
from gnc.messages import AltimeterMessage, AttitudeMessage, ContactMessage, ImageMessage, ImuMessage, LidarScanMessage
from gnc.navstate import NavState
from gnc.plugins import LawOutputError, call_law, check_law_vector
from gnc.vision_nav import VisionMeasurement, VisionNavConfig, vision_measurement
from vision.tracker import Tracker
from vision.tracks import Tracks

NS_PER_S = 1_000_000_000
HAZARD = "hazard"  # the subsystem of a "no safe site" event
RESCAN_DEADLINE_FRAC = 0.5  # a second hazard scan still due below this fraction of its height is given up [-]
RESCAN_LAST_CALL_M = 5.0  # ... or below this height above the target, where no divert is left to fly [m]
RAW_GROUND_SAMPLES = 5  # valid altimeter returns whose median ground the approach's clearance check reads [-]
RAW_GROUND_MAX_AGE_NS = 500_000_000  # ... the oldest of them at most this old [ns]
G0_MPS2 = 9.80665  # defines Isp


@dataclass(frozen=True)
class OnboardKnowledge:
    """What the flight software knows of its vehicle: nominal values and calibration, never truth.

    Attributes:
        vehicle: Thrust range, RCS limit, dry mass, dry inertia, tank radius and
            engine calibration, for guidance and control.
        wet_mass_kg: Mass estimate at hand-over [kg].
        isp_s: Engine specific impulse [s] (propellant gauging).
        K: Camera intrinsics, (3, 3) [px].
        R_BC: Camera-to-body rotation (mounting calibration), (3, 3).
        r_cam_B_m: Camera position in B, (3,) [m].
        r_alt_B_m: Altimeter position in B, (3,) [m].
    """

    vehicle: VehicleParams
    wet_mass_kg: float
    isp_s: float
    K: np.ndarray
    R_BC: np.ndarray
    r_cam_B_m: np.ndarray
    r_alt_B_m: np.ndarray

    def __post_init__(self) -> None:
        for name in ("K", "R_BC", "r_cam_B_m", "r_alt_B_m"):
            arr = np.array(getattr(self, name), dtype=float)
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        if not (math.isfinite(self.wet_mass_kg) and self.wet_mass_kg > 0.0):
            raise ValueError(f"knowledge wet_mass_kg = {self.wet_mass_kg!r}; allowed: a finite value > 0")
        if not (math.isfinite(self.isp_s) and self.isp_s > 0.0):
            raise ValueError(f"knowledge isp_s = {self.isp_s!r}; allowed: a finite value > 0")


@dataclass
class VisionStats:
    """Vision bookkeeping for telemetry and the summary."""

    frames: int = 0  # frames given to the tracker
    track_counts: list[int] = field(default_factory=list)
    measurements: int = 0  # measurements formed
    rejected: int = 0  # ... of which the filter's gate rejected
    unusable: int = 0  # frame pairs that gave no measurement (too few tracks, or in too few image cells)
    last: VisionMeasurement | None = None
    last_record: UpdateRecord | None = None
    last_tracks: Tracks | None = None


@dataclass(frozen=True)
class _Fit:
    """A noisy altimeter's straight-line fit over n samples (:meth:`FlightSoftware._averaged`)."""

    msg: AltimeterMessage  # the fitted range now, as one sample
    slope: float  # the navigation's vertical-velocity error over the span [m/s]
    var_slope: float  # its variance from the residuals [(m/s)^2]
    span_s: float  # the samples' span [s]
    consistent: bool  # the samples scatter about the line as the measured noise does


@dataclass(frozen=True)
class _Frame:
    t_ns: int
    q_gyro: tuple[float, float, float, float]  # gyro-only attitude at the frame


def frame_overlap(prev_ids: np.ndarray | None, ids: np.ndarray) -> float:
    """Correlation of a frame's mean tracking error as two consecutive pairs see it: ``n12 / sqrt(n1 n2)``.

    Args:
        prev_ids: Track ids of the previous pair (None: no previous pair, 1 is returned).
        ids: Track ids of this pair.

    Returns:
        The shared tracks' count over the geometric mean of the two counts, in [0, 1]
        (each pair averages the frame's per-track errors over its own tracks).
    """
    if prev_ids is None:
        return 1.0
    if len(prev_ids) == 0 or len(ids) == 0:
        return 0.0
    shared = np.intersect1d(prev_ids, ids, assume_unique=True).size
    return float(shared / math.sqrt(len(prev_ids) * len(ids)))


def _any_leg(contact: ContactMessage) -> bool:
    """Whether a footpad touches: ``bool(np.any(contact.legs))``, by the array's own method when it is one
    (three times a control tick; NumPy's function wrapper costs more than the test)."""
    legs = contact.legs
    return bool(legs.any()) if type(legs) is np.ndarray else bool(np.any(legs))


class FlightSoftware:
    """Navigation + vision + guidance + control, fed by messages.

    Args:
        guidance: The guidance law.
        controller: The controller (built with ``knowledge.vehicle``).
        nav_filter: The navigation filter (built with ``knowledge.r_alt_B_m``).
        tracker: The paper's tracker, or None when frames are not processed
            (vision off, or tracks supplied by :meth:`on_tracks`).
        vision_cfg: Vision-measurement settings.
        vision_enabled: Use vision measurements at all.
        knowledge: The onboard knowledge of the vehicle. (The gyro's specification,
            for the relative rotation's uncertainty, is the filter's configuration.)
        map_nav: Map-relative position fixes (``nav_map = "on"``), or None.
        fdir: Sensor health monitoring and recovery (:mod:`gnc.fdir`); None: none
            (every message goes to the filter as it comes).
        hda: Hazard detection and avoidance (``hazard.avoidance = "on"``, :mod:`gnc.hda`), or None.
    """

    def __init__(self, guidance: GuidanceLaw, controller: Controller, nav_filter: NavFilter,
                 tracker: Tracker | None, vision_cfg: VisionNavConfig, vision_enabled: bool,
                 knowledge: OnboardKnowledge, map_nav: MapNavigator | None = None,
                 fdir: HealthMonitor | None = None, hda: HazardAvoidance | None = None):
        self.guidance = guidance
        self.controller = controller
        self.filter = nav_filter
        self.tracker = tracker
        self.vision_cfg = vision_cfg
        self.vision_enabled = vision_enabled
        self.knowledge = knowledge
        self.mass_kg = knowledge.wet_mass_kg
        self._thrust_scale = knowledge.vehicle.thrust_scale
        self._isp_g0 = knowledge.isp_s * G0_MPS2
        self.target = LandingTarget()
        self.vision = VisionStats()
        self._prev_frame: _Frame | None = None
        self._prev_pair_ids: np.ndarray | None = None  # track ids of the last measured pair
        self._last_cmd_t_ns: int | None = None
        self._last_thrust_N = 0.0
        self.last_guidance: GuidanceCommand | None = None
        self.map_nav = map_nav
        self.fdir = fdir
        self.hda = hda
        self._on_ground = False  # footpad contact seen: health monitoring ends (the descent is over)
        self._alt_buffer: list[tuple[int, float, float]] = []  # (t, height less expected, sigma)
        # The ground elevation each of the last valid altimeter returns implies (t, z - range cos(nadir)) [ns, m],
        # whatever the monitor made of the sensor: the approach's ground-clearance check reads their median.
        self._raw_ground: deque[tuple[int, float]] = deque(maxlen=RAW_GROUND_SAMPLES)
        self._discounted = False  # the vertical covariance was re-inflated on a noisy-altimeter detection
        self._altimeter_lost = False  # no usable altimeter (health monitoring): vision's divergence is used
        self._vision_cut_off = False  # vision has reached its altitude cut-off (:meth:`_at_vision_cutoff`)
        # Non-volatile memory: (t_ns, filter state (24,), covariance (24, 24), mass [kg], attitude q_LB (4,) or
        # None). The hand-over's data until the first control tick writes it (a reset before that restarts there).
        self.checkpoint: tuple[int, np.ndarray, np.ndarray, float, np.ndarray | None] = self._checkpoint(
            nav_filter.time_ns)

    # ------------------------------------------------------------------ sensors
    def on_imu(self, msg: ImuMessage) -> None:
        if self._monitoring():
            t_prev = self.filter.time_ns
            msg = self.fdir.imu(msg)
            if msg is None:
                return
            if self.filter.propagate_imu(msg) and self.fdir.last_imu_synthetic:
                self._inflate_velocity(msg.t_ns - t_prev)
            return
        self.filter.propagate_imu(msg)

    def on_attitude(self, msg: AttitudeMessage) -> None:
        if self._monitoring():
            msg = self.fdir.attitude(msg)
            if msg is None:
                return
        self.filter.set_attitude(msg)

    def on_altimeter(self, msg: AltimeterMessage) -> None:
        if not self._monitoring():
            self.filter.update_altimeter(msg)
            return
        x = self.filter.ekf.x
        if msg.valid and math.isfinite(msg.range_m):
            self._raw_ground.append((msg.t_ns, float(x[2]) - float(msg.range_m) * self._cos_nadir(msg)))
        est_range = float(x[2] - x[IDX_H])  # the altimeter's height above the filter's ground (nadir)
        sigma = self.filter.altimeter_sigma_m(max(est_range, 0.0), include_relief=False)
        used = self.fdir.altimeter(msg, est_range, float(x[5]), sigma)
        if used is None:
            return
        if self.fdir.alt_average_n is not None:  # a noisy altimeter: one update from n samples' fit
            if not self._discounted:  # the noisy ranges it took as precise before the detection
                self._discounted = True
                k2 = self.fdir.alt_noise_factor ** 2
                window_s = self.fdir.cfg.nis_window * self.fdir.spec.altimeter_period_ns / NS_PER_S
                P = self.filter.ekf.P
                P[2, 2] += k2 * sigma**2  # one noisy range's error, and its slope over the detection window
                P[5, 5] += k2 * sigma**2 / window_s**2
            fit = self._averaged(used, est_range, sigma)
            if fit is None:
                return
            self._fitted_update(fit, est_range)
            return
        record = self.filter.update_altimeter(used)
        if record is not None and record.reason in ("", "gate"):
            var = self.filter.altimeter_sigma_m(float(used.range_m), include_relief=False) ** 2
            self.fdir.altimeter_record(used.t_ns, record.accepted, float(record.nis), float(used.range_m), est_range, var)
            if self.fdir.terrain_reinit is not None:
                self._reinit_terrain(used)

    def _cos_nadir(self, msg: AltimeterMessage) -> float:
        """Cosine of the altimeter boresight's angle from nadir, from the filter's attitude (1 without one)."""
        q = self.filter.q_LB
        if q is None:
            return 1.0
        b = np.asarray(msg.boresight_B, float)
        c = -float((quat_to_matrix(q) @ b)[2]) / float(np.linalg.norm(b))
        return c if c > 0.1 else 1.0

    def _averaged(self, msg: AltimeterMessage, est_range_m: float, sigma_m: float) -> _Fit | None:
        """Collect each sample's height (range times the boresight's cosine) less the height the navigation
        expects at its time; every n-th sample, the straight-line fit of those differences (else None).

        The motion between the samples is the IMU's, so the line's intercept now is the navigation's height
        error and its slope the navigation's vertical-velocity error (less the rate at which the ground
        under the footprint rises). The endpoint has about 4/n of one sample's variance; :mod:`gnc.fdir`
        chooses n = 2 k^2 for a noise k times the specification.
        """
        buf = self._alt_buffer
        c = self._cos_nadir(msg)
        buf.append((msg.t_ns, float(msg.range_m) * c - est_range_m, sigma_m))
        if len(buf) < self.fdir.alt_average_n:
            return None
        t = np.array([b[0] - msg.t_ns for b in buf], float) / NS_PER_S
        d = np.array([b[1] for b in buf])
        sig = max(b[2] for b in buf)
        buf.clear()
        slope, intercept, var_slope, s2 = line_fit(t, d)
        # Self-consistent: the samples scatter about the line by no more than twice the noise measured at the
        # detection (a line, not a step or a frozen stretch, explains them).
        consistent = math.sqrt(s2) <= 2.0 * self.fdir.alt_noise_factor * sig
        return _Fit(AltimeterMessage(msg.t_ns, (est_range_m + float(intercept)) / c, True, msg.boresight_B),
                    float(slope), var_slope, float(-t[0]), consistent)

    def _fitted_update(self, fit: _Fit, est_range_m: float) -> None:
        """A noisy altimeter's fitted height and vertical velocity, with the vertical channel re-initialised
        when the gate refuses a self-consistent fit (the filter, not the sensor, is then wrong)."""
        used, fd, flt = fit.msg, self.fdir, self.filter
        # The slope is the vertical-velocity error of the navigation the samples were compared with, i.e. of
        # the state before this update: the height update below moves the velocity too (through their
        # correlation), so the velocity measurement is fixed now, not taken from the updated state.
        z = np.array([float(flt.ekf.x[5]) + fit.slope])
        record = flt.update_altimeter(used)
        if record is None or record.reason not in ("", "gate"):
            return
        reinit = not record.accepted and fit.consistent and fd.cfg.recovery
        if reinit:
            y = float(record.y[0]) * self._cos_nadir(used)  # the height error [m]
            P = flt.ekf.P
            P[2, 2] += y * y
            P[5, 5] += (y / fit.span_s) ** 2
            fd.note(used.t_ns, "altimeter", f"gate refused a self-consistent altimeter fit ({y:+.1f} m of height, "
                                            f"NIS {record.nis:.0f}): the navigation's vertical channel is wrong",
                    "vertical covariance re-initialised, fit applied", once_key="fit_reinit")
            record = flt.update_altimeter(used)
            if record is None:
                return
        var = flt.altimeter_sigma_m(float(used.range_m), include_relief=False) ** 2
        fd.altimeter_record(used.t_ns, record.accepted, float(record.nis), float(used.range_m), est_range_m, var)
        if fd.terrain_reinit is not None:
            self._reinit_terrain(used)
        if not (record.accepted and fit.consistent and math.isfinite(fit.var_slope)):
            return
        # The slope: the mean vertical-velocity error over the fit's span, less the ground's rise under the
        # moving footprint (the relief's slope 1-sigma, relief over correlation length, times the horizontal
        # speed) and the change of the error over half the span (the vertical bias's uncertainty).
        x, P = flt.ekf.x, flt.ekf.P
        cfg = flt.cfg
        relief_slope = cfg.terrain_relief_sigma_m / max(cfg.terrain_correlation_length_m, 1e-9)
        ib = IDX_BA.start + 2
        var_v = fit.var_slope + (relief_slope * math.hypot(x[3], x[4])) ** 2 + (0.5 * fit.span_s) ** 2 * P[ib, ib]
        rec = flt.update_velocity(used.t_ns, z, np.array([[var_v]]), axes=(2,))
        if not rec.accepted and rec.reason == "gate" and fd.cfg.recovery:
            yv = float(rec.y[0])
            P[5, 5] += yv * yv
            P[ib, ib] += (yv / fit.span_s) ** 2
            fd.note(used.t_ns, "altimeter", f"gate refused a self-consistent altimeter fit's vertical velocity "
                                            f"({yv:+.2f} m/s, NIS {rec.nis:.0f}): the navigation's vertical "
                                            "velocity is wrong", "vertical velocity covariance re-initialised, fit "
                                                                  "applied", once_key="fit_reinit_v")
            flt.update_velocity(used.t_ns, z, np.array([[var_v]]), axes=(2,))

    def _reinit_terrain(self, msg: AltimeterMessage) -> None:
        """The Hakuto-R recovery: the filter's ground height re-initialised to the one this range measures."""
        rho, var = self.fdir.terrain_reinit
        self.fdir.terrain_reinit = None
        q = self.filter.q_LB
        if q is None:
            return
        R_LB = quat_to_matrix(q)
        b_L = R_LB @ np.asarray(msg.boresight_B, float)
        b_L = b_L / np.linalg.norm(b_L)
        x, P = self.filter.ekf.x, self.filter.ekf.P
        p_alt_z = float(x[2] + (R_LB @ self.knowledge.r_alt_B_m)[2])
        x[IDX_H] = p_alt_z + rho * float(b_L[2])  # the ground the beam hits, relative to the target's elevation
        P[IDX_H, :] = 0.0
        P[:, IDX_H] = 0.0
        P[IDX_H, IDX_H] = P[2, 2] + var

    def wants_image(self) -> bool:
        """Would :meth:`on_image` use a frame now (a tracker, vision enabled, above the cut-off)?

        A caller that has no other use for the frame may then skip rendering
        it and call :meth:`skip_image` instead: the same as ``on_image`` of a
        frame it would not use.
        """
        return self.tracker is not None and self.vision_active()

    def wants_map_frame(self, t_ns: int) -> bool:
        """Would :meth:`on_image` take a map fix from a frame now (``map_nav`` set, due, in its height window)?"""
        return self.map_nav is not None and self.map_nav.wants_frame(t_ns, float(self.filter.ekf.x[2]))

    def skip_image(self, t_ns: int | None = None) -> None:
        """A camera frame went by that :meth:`wants_image` said would not be used (``t_ns``: its time)."""
        if self._monitoring() and t_ns is not None:
            self.fdir.image(t_ns, None)
            self._at_vision_cutoff(t_ns)
        self._end_vision()

    def on_image(self, msg: ImageMessage) -> Tracks | None:
        """A map fix when one is due (``map_nav``), then the paper's tracker (above the cut-off) and its tracks."""
        if self._monitoring():
            self.fdir.image(msg.t_ns, float(msg.image.mean()))
        if self.map_nav is not None:
            self.map_nav.on_frame(msg.t_ns, msg.image, self.filter)
            self._check_map_lock(msg.t_ns)
        if not self.wants_image():
            self._at_vision_cutoff(msg.t_ns)
            self._end_vision()
            return None
        tracks = self.tracker.step(msg.image)
        self.vision.frames += 1
        self.on_tracks(msg.t_ns, tracks)
        return tracks

    def on_tracks(self, t_ns: int, tracks: Tracks) -> None:
        """Use the tracks of this frame against the previous one, then clone the position here."""
        q_gyro = self.filter.gyro_attitude()
        q_LB = self.filter.q_LB
        if not self.vision_active() or q_gyro is None or q_LB is None:
            self._end_vision()
            return
        self.vision.track_counts.append(len(tracks))
        self.vision.last_tracks = tracks
        prev = self._prev_frame
        if prev is not None and self.filter.clone_time_ns == prev.t_ns:
            self._measure(prev, t_ns, tracks, q_LB, q_gyro)
        cloned = self.filter.clone_frame(t_ns)
        self._prev_frame = _Frame(t_ns, tuple(float(c) for c in q_gyro)) if cloned else None

    def _measure(self, prev: _Frame, t_ns: int, tracks: Tracks, q_LB: np.ndarray, q_gyro: np.ndarray) -> None:
        """Form the frame pair's measurement and update the filter with it."""
        R_LB1 = quat_to_matrix(q_LB)
        # The first frame's attitude: the current one carried back by the gyro's relative rotation.
        R_LB0 = R_LB1 @ quat_to_matrix(q_gyro).T @ quat_to_matrix(prev.q_gyro)
        x = self.filter.ekf.x
        lag_s = (t_ns - self.filter.time_ns) / NS_PER_S
        r1 = x[IDX_R] + x[IDX_V] * lag_s
        dt_s = (t_ns - prev.t_ns) / NS_PER_S
        cfg = self.filter.cfg
        sigma_rot = math.sqrt(cfg.gyro_noise_density**2 * dt_s + (cfg.gyro_bias_sigma_radps * dt_s) ** 2)
        k = self.knowledge
        ids = tracks.ids[np.all(np.isfinite(tracks.prev_xy), axis=1)]
        overlap = frame_overlap(self._prev_pair_ids, ids)
        self._prev_pair_ids = ids
        divergence = self._altimeter_lost
        m = vision_measurement(tracks, prev.t_ns, t_ns, k.K, k.R_BC, k.r_cam_B_m, R_LB0, R_LB1,
                               x[IDX_C].copy(), r1, float(x[IDX_G]), sigma_rot, self.vision_cfg,
                               s_view=x[IDX_SV].copy(), with_divergence=divergence)
        if m is None:
            self.vision.unusable += 1
            return
        if divergence and m.divergence is not None:
            # No altimeter: the divergence measures the vertical velocity over the height (made at the same
            # prior as the horizontal flow, so applied first; the horizontal flow's consider update leaves
            # the vertical channel alone). Below the usual cut-off only the divergence is used.
            d = m.divergence
            self.filter.update_divergence(d.t_ns, d.z, d.hx, d.H_r, d.H_c, d.H_g, d.H_s, d.R)
            x = self.filter.ekf.x  # the update made a new state vector
            if float(x[2]) <= self.vision_cfg.cutoff_altitude_m:
                return
            m = vision_measurement(tracks, prev.t_ns, t_ns, k.K, k.R_BC, k.r_cam_B_m, R_LB0, R_LB1,
                                   x[IDX_C].copy(), x[IDX_R] + x[IDX_V] * lag_s, float(x[IDX_G]), sigma_rot,
                                   self.vision_cfg, s_view=x[IDX_SV].copy())
            if m is None:
                self.vision.unusable += 1
                return
        self.vision.measurements += 1
        self.vision.last = m
        record = self.filter.update_relative(m.t_ns, m.z, m.hx, m.H_r, m.H_c, m.R, m.R_frame, m.H_g, m.H_s,
                                             frame_overlap=overlap)
        self.vision.last_record = record
        if not record.accepted:
            self.vision.rejected += 1
        if self._monitoring() and self.fdir.vision_record(m.t_ns, record.accepted):
            self._vision_excluded(t_ns, self.fdir.cfg.vision_window * (t_ns - prev.t_ns) / NS_PER_S)

    def _vision_excluded(self, t_ns: int, window_s: float) -> None:
        """Vision was excluded for good (a majority of rejections again after its retry) over the last
        ``window_s`` [s].

        The measurements of that window that passed the gate are suspect as well, and the lateral
        accelerometer bias, which only vision observes (the altimeter sees the vertical), may have been pulled
        by them; below the vision cut-off such a bias error grows into a horizontal-velocity error nothing
        sees. The bias goes back to its specification (mean 0, the datasheet's 1-sigma per axis), and the
        velocity covariance takes the change over the window (:meth:`_reset_lateral_bias`).
        """
        sig_b = self.filter.cfg.init_accel_bias_sigma_mps2
        self._reset_lateral_bias(t_ns, (0.0, 0.0, sig_b**2), since_s=window_s)

    def _at_vision_cutoff(self, t_ns: int) -> None:
        """Once, at the first frame vision does not use because the estimated altitude is at its cut-off: when
        most of the descent's frame pairs gave no measurement (``fdir.vision_unusable_max``: a featureless
        ground, whose few tracks sat in too few image cells), the lateral accelerometer bias, which only vision
        observes, is taken as unobserved from here on. Its estimate is kept and its variance raised to at least
        its specification's (``init_accel_bias_sigma_mps2`` squared, per axis; adding to a diagonal keeps the
        covariance positive semi-definite), so that the horizontal velocity's variance grows as the bias's over
        the terminal descent on the IMU alone, where the safe-abort criterion judges it
        (``fdir.abort_sigma_vh_mps``).

        Why: the few measurements such a descent keeps are over-trusted as a group (their cluster-robust
        covariance rests on a handful of cells), and a velocity error they leave is, after a gap, read by the
        filter as a bias (the velocity-bias correlation the gap builds): a bias error of 0.01 m/s^2 that the
        filter is sure of, and 0.5 m/s of horizontal speed after 50 s on the IMU, unseen.
        """
        if self._vision_cut_off or not self._monitoring() or not self.fdir.cfg.recovery:
            return
        if not self.vision_enabled or self.tracker is None or "vision" in self.fdir.failed or self.vision_active():
            return
        self._vision_cut_off = True
        share = self._vision_unusable_share()
        if not share > self.fdir.cfg.vision_unusable_max:
            return
        var = self.filter.cfg.init_accel_bias_sigma_mps2 ** 2
        P = self.filter.ekf.P
        ib = IDX_BA.start
        for i in (ib, ib + 1):
            P[i, i] += max(var - float(P[i, i]), 0.0)
        self.fdir.note(t_ns, "vision", f"{100 * share:.0f} % of vision's frame pairs gave no measurement",
                       "lateral accelerometer bias taken as unobserved: its variance raised to its specification")

    def _end_vision(self) -> None:
        """No vision at this frame: the next frame starts a new pair."""
        self._prev_frame = None
        self._prev_pair_ids = None
        self.filter.drop_clone()

    def vision_active(self) -> bool:
        """Vision is enabled and the estimated altitude is above the cut-off (without an altimeter, above
        the divergence's lower cut-off; in a terminal fly-out, above ``flyout_cutoff_m``)."""
        if not self.vision_enabled or (self.fdir is not None and "vision" in self.fdir.failed):
            return False
        cfg = self.vision_cfg
        cutoff = min(cfg.cutoff_altitude_m, cfg.divergence_cutoff_m) if self._altimeter_lost else cfg.cutoff_altitude_m
        z = float(self.filter.ekf.x[2])
        if z > cutoff:
            return True
        return z > cfg.flyout_cutoff_m and self._flying_out() and not self._vision_mostly_unusable()

    def _vision_unusable_share(self) -> float:
        """The share of the descent's frame pairs that gave no measurement (0 before any pair)."""
        pairs = self.vision.measurements + self.vision.unusable
        return self.vision.unusable / pairs if pairs else 0.0

    def _vision_mostly_unusable(self) -> bool:
        """More than ``fdir.vision_unusable_max`` of the descent's frame pairs gave no measurement (a featureless
        ground; without health monitoring: never). Vision is then not used in a terminal fly-out below its
        cut-off: the few measurements such a ground gives are over-trusted as a group, and the fly-out would
        bring back the over-confident lateral bias that :meth:`_at_vision_cutoff` takes as unobserved."""
        return self.fdir is not None and self._vision_unusable_share() > self.fdir.cfg.vision_unusable_max

    def _flying_out(self) -> bool:
        """A built-in law's terminal phase is flying out a missed gate at the filter's position
        (:meth:`_fly_out_m`)."""
        return not math.isnan(self._fly_out_m(self.filter.ekf.x))

    def _fly_out_m(self, r_L: np.ndarray) -> float:
        """How far [m] from the target a built-in law's terminal phase is flying out a missed gate at ``r_L``:
        more than twice ``terminal_hold_radius_m``, so guidance hovers and translates
        (:meth:`GuidanceLaw.terminal_accel_L`); NaN when it is not (another phase, nearer, a plug-in without the
        terminal phase, or after a bingo, which lands where it is)."""
        g = self.guidance
        if not isinstance(g, GuidanceLaw) or g.phase != PHASE_TERMINAL or getattr(g, "bingo", False):
            return math.nan
        target = self.target.r_L
        away_m = math.hypot(float(r_L[0]) - float(target[0]), float(r_L[1]) - float(target[1]))
        return away_m if away_m > 2.0 * g.cfg.terminal_hold_radius_m else math.nan

    # ------------------------------------------------------------------ hazard avoidance
    def wants_lidar_scan(self) -> bool:
        """Hazard avoidance asks for a flash now (its estimated height above the target, on the approach)."""
        if self.hda is None or self.last_guidance is None or self.filter.q_LB is None:
            return False
        if self.fdir is not None and self.fdir.abort is not None:
            return False
        target = np.asarray(self.target.r_L, float)
        height = float(self.filter.ekf.x[2]) - float(target[2])
        self._hda_deadlines(int(self.last_guidance.t_ns), height, self.last_guidance.phase)
        if self.fdir is not None and self.fdir.abort is not None:
            return False
        return self.hda.wants_scan(height, self.last_guidance.phase, self.filter.ekf.x[:3],
                                   quat_to_matrix(self.filter.q_LB), target)

    def _hda_deadlines(self, t_ns: int, height_m: float, phase: str) -> None:
        """Hazard avoidance that cannot happen is declared, not left to a blind landing: a second scan still due
        below ``RESCAN_DEADLINE_FRAC`` of its height, or below ``RESCAN_LAST_CALL_M`` (the target never came into
        its view) gives no safe site; an approach that ended before the first scan's height is noted."""
        hda = self.hda
        deadline_m = max(RESCAN_DEADLINE_FRAC * hda.cfg.rescan_altitude_m, RESCAN_LAST_CALL_M)
        if hda.awaiting_rescan and height_m < deadline_m:
            hda.abandon_rescan()
            self._declare_no_site(t_ns, f"no safe site: the second scan was not made above {deadline_m:g} m "
                                        "(the target never in its view, or its height too low)")
        if not hda.scanned and phase == "terminal" and self.fdir is not None:
            self.fdir.note(t_ns, HAZARD, f"no hazard scan: the approach ended above its height "
                                         f"(hazard.hda.scan_altitude_m = {hda.cfg.scan_altitude_m:g} m)",
                           "landing at the current target without a hazard map", once_key="no_scan")

    def _declare_no_site(self, t_ns: int, reason: str = "no safe site within the divert limit") -> None:
        """No safe site: the safe abort (``no_site_action = 'abort'``), or a declared landing at the current target."""
        if self.fdir is None:
            return
        if self.hda.cfg.no_site_action == "abort":
            self.fdir.declare_abort(t_ns, HAZARD, reason)
        else:
            self.fdir.note(t_ns, HAZARD, reason, "landing at the current target (no_site_action = 'land')",
                           once_key="no_site")

    def on_lidar(self, msg: LidarScanMessage) -> None:
        """A hazard flash: kept until its scan is complete; then map the hazards through the estimate, retarget
        to a safe site (or to the best-margin area for a second scan), or declare none."""
        x, P = self.filter.ekf.x, self.filter.ekf.P
        R_LB = quat_to_matrix(self.filter.q_LB)
        q_gyro = self.filter.gyro_attitude()
        R_gyro = None if q_gyro is None else quat_to_matrix(q_gyro)
        if self.hda.flashes_wanted() > 1:
            self.hda.add_flash(msg, x[:3].copy(), R_LB, R_gyro)
            return
        sigma_vh = math.sqrt(max(float(P[3, 3] + P[4, 4]) / 2.0, 0.0))
        sigma_z = math.sqrt(max(float(P[2, 2]), 0.0))
        new = self.hda.on_scan(msg, x[:3].copy(), R_LB, sigma_vh, sigma_z, np.asarray(self.target.r_L, float),
                               self._t_go_plan_s(), R_gyro, x[3:6].copy())
        if new is not None:
            self.target = LandingTarget(r_L=new)
            return
        if not self.hda.no_safe_site:  # the first scan's no-site: a second scan follows
            return
        self._declare_no_site(msg.t_ns)

    def _ground_under_m(self, t_ns: int, observed: bool) -> float:
        """The elevation of the ground under the altimeter's footprint in L [m], for the approach's
        ground-clearance check and the terminal phase's propellant bingo: the higher of the filter's terrain height (while the altimeter is observed) and
        the median of the last ``RAW_GROUND_SAMPLES`` valid returns' (the oldest at most
        ``RAW_GROUND_MAX_AGE_NS`` old), whatever the monitor made of the sensor. A ground that the altimeter
        shows nearer than planned is taken as possibly there: crossing a plateau's edge, the returns were
        excluded as inconsistent (they moved faster than the descent) and the lander flew into the plateau
        believing the ground 150 m lower; a faulty altimeter that reads short can at worst declare a safe abort.
        NaN: neither is known."""
        ground = float(self.filter.ekf.x[IDX_H]) if observed else math.nan
        raw = self._raw_ground
        if len(raw) == raw.maxlen and t_ns - raw[0][0] <= RAW_GROUND_MAX_AGE_NS:
            median = sorted(g for _, g in raw)[len(raw) // 2]
            ground = median if math.isnan(ground) else max(ground, median)
        return ground

    def _approach_floor_m(self) -> float:
        """The lowest point of guidance's approach in L [m]: its gate, ``gate_altitude_m`` above the landing
        target (NaN for a law without a gate)."""
        gate = getattr(getattr(self.guidance, "cfg", None), "gate_altitude_m", None)
        return float(self.target.r_L[2]) + float(gate) if isinstance(gate, (int, float)) else math.nan

    def _t_go_plan_s(self) -> float | None:
        """The guidance plan's time left to touchdown [s]: to the gate plus the terminal descent (None: unknown)."""
        cmd, gcfg = self.last_guidance, getattr(self.guidance, "cfg", None)
        if cmd is None or gcfg is None or not math.isfinite(cmd.t_go_s):
            return None
        if cmd.phase == "terminal":
            return float(cmd.t_go_s)
        if cmd.phase == "approach":
            return float(cmd.t_go_s) + gcfg.gate_altitude_m / gcfg.terminal_descent_rate_mps
        return None

    # ------------------------------------------------------------------ control
    def control(self, t_ns: int, contact: ContactMessage, nav: NavState | None = None) -> ActuatorCommand:
        """One control step; ``nav`` overrides the filter (perfect navigation)."""
        self._advance_mass_gauge(t_ns)
        self._monitor_before_command(t_ns, contact, oracle=nav is not None)
        nav = nav if nav is not None else self.filter.nav_state(self.mass_kg)
        if self.fdir is not None and self.fdir.abort is not None:
            cmd = self._abort_command(nav)
        else:
            self._bingo_check(t_ns, nav)
            cmd = self._law_call(self.guidance, "guidance.law", t_ns, nav, self.target)
            # GuidanceLaw.update checks its formulas' output itself; a law that overrides it is checked here.
            if type(self.guidance).update is not GuidanceLaw.update:
                self._check_guidance_output(cmd, t_ns)
        act = self._law_call(self.controller, "control.law", t_ns, nav, cmd, contact)
        act = self._checked_controller_output(act, t_ns)
        self.last_guidance = cmd
        self._command_issued(t_ns, act.thrust_N if act.engine_on else 0.0, act.torque_B_Nm, contact)
        return act

    def _bingo_check(self, t_ns: int, nav: NavState) -> None:
        """The propellant bingo of a built-in law's terminal phase (``guidance.terminal_bingo``).

        While the terminal phase flies out a missed gate (the vehicle more than twice ``terminal_hold_radius_m``
        from the target: guidance hovers and translates), the propellant the gauge says is left (the mass
        estimate less the vehicle's dry mass), less ``terminal_reserve_kg``, must cover the terminal phase's own
        descent from the height above the filter's ground at ``terminal_descent_rate_mps``, at the hover's flow
        ``m g / (Isp g0)``. Once it does not, guidance lands where the vehicle is (:meth:`GuidanceLaw.land_here`),
        by a faster descent (:meth:`GuidanceLaw.bingo_rate_mps`) that needs less than that, and an event is
        recorded: a touchdown away from the target instead of a tank run dry above the ground. The ground is
        :meth:`_ground_under_m`'s, given to guidance again every tick of the bingo's descent.
        """
        g = self.guidance
        # The ground as the approach's clearance check reads it: the higher of the filter's terrain height and the
        # altimeter's fresh returns (a filter whose terrain state went wrong must not set a fast descent's floor).
        if isinstance(g, GuidanceLaw) and g.phase == PHASE_TERMINAL and getattr(g, "bingo", False):
            g.bingo_ground_z_L = self._ground_under_m(t_ns, observed=True)  # the ground under the vehicle as it goes
            return
        r = nav.r_BL_L
        away_m = self._fly_out_m(r)
        if math.isnan(away_m) or not g.cfg.terminal_bingo:  # not NaN: a built-in law (GuidanceLaw)
            return
        cfg = g.cfg
        ground_z = self._ground_under_m(t_ns, observed=True)
        height_m = max(float(r[2]) - ground_z, 0.0)
        need_kg = nav.mass_kg * cfg.gravity_mps2 / self._isp_g0 * height_m / cfg.terminal_descent_rate_mps
        left_kg = nav.mass_kg - self.controller.vehicle.dry_mass_kg
        if left_kg - cfg.terminal_reserve_kg >= need_kg:
            return
        g.land_here(ground_z)
        if self.fdir is not None:
            self.fdir.note(t_ns, PROPELLANT,
                           f"propellant bingo: {left_kg:.1f} kg left by the gauge, {need_kg:.1f} kg to descend "
                           f"{height_m:.1f} m at {cfg.terminal_descent_rate_mps:g} m/s and {cfg.terminal_reserve_kg:g} "
                           f"kg of reserve; the target is {away_m:.1f} m away",
                           f"landing where it is, down at up to {cfg.bingo_descent_rate_mps:g} m/s", once_key="bingo")

    def _monitor_before_command(self, t_ns: int, contact: ContactMessage, oracle: bool) -> None:
        """A control tick's health monitoring before the command is made (:meth:`control`, and a replay's
        :meth:`on_flown_command`): the first leg contact ends it; the clocked checks and recoveries."""
        if self.fdir is not None and _any_leg(contact):
            self._on_ground = True
        if self._monitoring():
            self._fdir_tick(t_ns, contact, oracle=oracle)

    def _command_issued(self, t_ns: int, thrust_N: float, torque_B_Nm: np.ndarray, contact: ContactMessage) -> None:
        """The command of a control tick was issued (``thrust_N``: 0 with the engine off): the mass gauge holds
        its thrust; the accelerometer and torque checks take it; the checkpoint is written."""
        self._hold_thrust(t_ns, thrust_N)
        if self._monitoring():
            self.fdir.control_tick(t_ns, thrust_N, self._thrust_scale, self.mass_kg, _any_leg(contact))
            veh = self.controller.vehicle
            self.fdir.torque_check(t_ns, torque_B_Nm, thrust_N, veh.inertia_B_kgm2(self.mass_kg),
                                   veh.rcs_torque_max_Nm)
            self.checkpoint = self._checkpoint(t_ns)

    @staticmethod
    def _law(component: object) -> str:
        """The ``guidance.law`` / ``control.law`` value a guidance law or controller was built from."""
        return getattr(getattr(component, "cfg", None), "law", type(component).__name__)

    def _law_call(self, component: object, field: str, t_ns: int, *args: object) -> object:
        """``component.update(*args)``; a plug-in's exception becomes one line (:func:`gnc.plugins.plugin_raised`).
        A built-in's exception propagates as it is, with its traceback (a defect of this software)."""
        # A LawOutputError passes: it names the law already (GuidanceLaw.update's check of accel_L and its kin).
        return call_law(self._law(component), field, "update", t_ns, LawOutputError, component.update, *args)

    def _check_map_lock(self, t_ns: int) -> None:
        """Below the map fixes' height window without a lock, declare it (once): the landing is then flown on
        the hand-over position, and the map's target is reached only within the hand-over error."""
        st, cfg = self.map_nav.stats, self.map_nav.cfg
        if st.locked or float(self.filter.ekf.x[2]) >= cfg.min_altitude_m:
            return
        st.never_locked = True
        if self._monitoring():
            refused = sum(st.refused.values())
            self.fdir.note(t_ns, NAVIGATION, f"map-relative navigation never locked ({st.attempts} fixes tried, "
                                             f"{refused} refused by the matcher, {st.unconfirmed} unconfirmed)",
                           "no keyframe; the landing is flown on the hand-over position", once_key="map_no_lock")

    def _check_guidance_output(self, cmd: object, t_ns: int) -> None:
        """Raise :class:`gnc.plugins.LawOutputError` when the command of a law that overrides ``update`` cannot
        be flown (:meth:`GuidanceLaw.update` checks its formulas' output itself)."""
        law = self._law(self.guidance)
        head = f"guidance.law = {law!r}: update returned"
        if not isinstance(cmd, GuidanceCommand):
            raise LawOutputError(f"{head} {type(cmd).__name__} at t = {t_ns / 1e9:.3f} s; allowed: a "
                                 "gnc.guidance.GuidanceCommand (README: Controller design studies)")
        if not isinstance(cmd.phase, str):
            raise LawOutputError(f"{head} phase = {cmd.phase!r} at t = {t_ns / 1e9:.3f} s; allowed: a str "
                                 "('approach', 'terminal', ...)")
        if isinstance(cmd.t_go_s, bool) or not isinstance(cmd.t_go_s, (int, float, np.integer, np.floating)):
            raise LawOutputError(f"{head} t_go_s = {cmd.t_go_s!r} at t = {t_ns / 1e9:.3f} s; allowed: a number of "
                                 "seconds (NaN when unknown)")
        if cmd.valid:
            check_law_vector(cmd.a_cmd_L, 3, "guidance.law", law, "update (GuidanceCommand.a_cmd_L)", t_ns, "m/s^2")

    def _checked_controller_output(self, act: object, t_ns: int) -> ActuatorCommand:
        """The controller's command, checked (finite thrust and torque of the right shape; else
        :class:`gnc.plugins.LawOutputError`) and with a torque given as a sequence made an array."""
        law = self._law(self.controller)
        if not isinstance(act, ActuatorCommand):
            raise LawOutputError(f"control.law = {law!r}: update returned {type(act).__name__} at t = "
                                 f"{t_ns / 1e9:.3f} s; allowed: a gnc.control.ActuatorCommand "
                                 "(README: Controller design studies)")
        check_law_vector(act.thrust_N, 0, "control.law", law, "update (ActuatorCommand.thrust_N)", t_ns, "N")
        check_law_vector(act.torque_B_Nm, 3, "control.law", law, "update (ActuatorCommand.torque_B_Nm)", t_ns, "N m")
        if type(act.thrust_N) is not float or type(act.torque_B_Nm) is not np.ndarray:
            act = dataclasses.replace(act, thrust_N=float(act.thrust_N), torque_B_Nm=np.asarray(act.torque_B_Nm, float))
        return act

    def _checkpoint(self, t_ns: int) -> tuple[int, np.ndarray, np.ndarray, float, np.ndarray | None]:
        """The state, covariance, mass and attitude as they are now, tagged ``t_ns`` (:attr:`checkpoint`)."""
        return t_ns, self.filter.ekf.x.copy(), self.filter.ekf.P.copy(), self.mass_kg, self.filter.q_LB

    # ------------------------------------------------------------------ fault detection and recovery
    def _monitoring(self) -> bool:
        """Health monitoring runs (there is a monitor, and no footpad has touched the ground yet)."""
        return self.fdir is not None and not self._on_ground

    def _fdir_tick(self, t_ns: int, contact: ContactMessage, oracle: bool = False) -> None:
        """The clocked checks and recoveries of :mod:`gnc.fdir` at a control tick.

        ``oracle``: guidance flies on a navigation state given from outside (the bench's truth), so the
        abort criteria, which judge the filter's estimate, are not applied.
        """
        fd = self.fdir
        fd.start(t_ns)
        if fd.cfg.recovery and fd.imu_missing(t_ns) and t_ns > self.filter.time_ns:
            t_prev = self.filter.time_ns
            if self.filter.propagate_imu(fd.synthetic_imu(t_ns)):  # dead reckoning on the thrust command
                self._inflate_velocity(t_ns - t_prev)
        fd.camera_check(t_ns, self.vision_active())
        if fd.thrust_efficiency is not None:  # the engine delivers less: re-plan within what it gives
            eff, fd.thrust_efficiency = fd.thrust_efficiency, None
            self._thrust_scale *= eff
            self.controller.vehicle = dataclasses.replace(
                self.controller.vehicle, thrust_scale=self.controller.vehicle.thrust_scale * eff)
            # ... and guidance plans again within the thrust the engine now delivers.
            veh, lim = self.controller.vehicle, self.guidance.limits
            self.guidance.set_limits(dataclasses.replace(lim, thrust_min_N=veh.thrust_min_N * veh.thrust_scale,
                                                         thrust_max_N=veh.thrust_max_N * veh.thrust_scale))
        x, P = self.filter.ekf.x, self.filter.ekf.P
        ib = IDX_BA.start
        reset = fd.bias_check(t_ns, (float(x[ib]), float(x[ib + 1])), (float(P[ib, ib]), float(P[ib + 1, ib + 1])),
                              self.filter.cfg.accel_noise_density, self.filter.cfg.init_accel_bias_sigma_mps2)
        if reset is not None:
            self._reset_lateral_bias(t_ns, reset)
        observed = not fd.altitude_lost(t_ns, float(x[2] - x[IDX_H]))
        # Without an altimeter (and with recovery on), vision's divergence carries the vertical channel.
        self._altimeter_lost = not observed and fd.cfg.recovery
        if oracle:
            return
        veh = self.controller.vehicle
        decel = veh.thrust_max_N * self._thrust_scale / self.mass_kg - float(-self.controller.g_L[2]) \
            if self.mass_kg > 0.0 else -math.inf
        cmd = self.last_guidance
        approach = cmd is not None and cmd.phase == PHASE_APPROACH
        fd.abort_reason(t_ns, float(x[2]), math.sqrt(max(float(P[2, 2]), 0.0)), observed, _any_leg(contact),
                        # the horizontal-velocity knowledge is judged when vision is meant to provide it
                        math.sqrt(max(float(P[3, 3] + P[4, 4]), 0.0)) if self.vision_enabled else 0.0,
                        float(x[5]), decel, math.hypot(x[3], x[4]),
                        # the ground under the altimeter's footprint and the approach's floor, its gate (a law
                        # without one: unknown); read only in the approach, the one phase the check judges
                        self._ground_under_m(t_ns, observed) if approach else math.nan,
                        self._approach_floor_m() if approach else math.nan, approach)

    def _reset_lateral_bias(self, t_ns: int, reset: tuple[float, float, float], since_s: float | None = None) -> None:
        """Re-initialise the filter's lateral accelerometer bias (to the measured mean lateral specific force,
        or to its specification when vision is excluded).

        The bias's x and y are set to ``reset[:2]`` with variance ``reset[2]`` and no correlation (a principal
        block of a positive semi-definite matrix stays so). The horizontal velocity (and position) has
        integrated the bias error since the filter last saw an accepted vision measurement (at least over the
        check's window; ``since_s`` when given), so its variance grows by that error times that time, squared
        (the position's by the time squared over two).
        """
        fx, fy, var = reset
        x, P = self.filter.ekf.x, self.filter.ekf.P
        ib = IDX_BA.start
        db = math.hypot(fx - float(x[ib]), fy - float(x[ib + 1]))
        x[ib], x[ib + 1] = fx, fy
        for i in (ib, ib + 1):
            P[i, :] = 0.0
            P[:, i] = 0.0
            P[i, i] = var
        last = self.vision.last_record
        window_s = self.fdir.cfg.accel_window_s
        tau = max((t_ns - last.t_ns) / NS_PER_S, window_s) if last is not None and last.accepted else window_s
        if since_s is not None:
            tau = since_s
        for i in (0, 1):
            P[3 + i, 3 + i] += (db * tau) ** 2
            P[i, i] += (0.5 * db * tau**2) ** 2

    def _inflate_velocity(self, dt_ns: int) -> None:
        """Add the synthetic accelerometer's error over ``dt_ns`` to the filter's velocity (and position) covariance."""
        dt = max(dt_ns, 0) / NS_PER_S
        q = self.fdir.cfg.synthetic_accel_sigma_mps2 ** 2
        P = self.filter.ekf.P
        P[IDX_V, IDX_V] += np.eye(3) * q * dt
        P[IDX_R, IDX_R] += np.eye(3) * q * dt**3 / 3.0

    def _abort_command(self, nav: NavState) -> GuidanceCommand:
        """Safe abort: null the horizontal velocity and climb at ``abort_climb_mps`` (never descend blind)."""
        c = self.fdir.cfg
        v = np.asarray(nav.v_BL_L, float)
        a = c.abort_hover_gain_per_s * (np.array([0.0, 0.0, c.abort_climb_mps]) - v)
        a = np.clip(a, -ABORT_ACCEL_MAX_MPS2, ABORT_ACCEL_MAX_MPS2)
        return GuidanceCommand(int(nav.t_ns), a, "abort", math.nan)

    def on_flown_command(self, t_ns: int, thrust_cmd_N: float, engine_on: bool, contact: ContactMessage | None = None,
                         torque_B_Nm: np.ndarray | None = None, oracle: bool = False) -> None:
        """Open-loop replay's control tick: the mass gauge takes the command that was flown, and the health
        monitoring runs on it as in flight.

        In an open-loop replay the vehicle does not respond, so a recomputed
        command flies nothing; the mass gauge integrates the recorded one
        (telemetry ``thrust_cmd_N``, ``engine_on``), exactly as :meth:`control`
        integrated it in flight. Guidance and control are not run. Given the
        footpad contacts and the flown torque, the fault detection's clocked checks
        and recoveries run as :meth:`control` ran them (the synthetic IMU while the
        IMU is missing, the bias reset, the thrust calibration, the accelerometer
        and torque checks), so that a replay of a descent whose monitoring acted
        reproduces its navigation.

        Args:
            t_ns: the control tick [ns].
            thrust_cmd_N: the thrust command issued at this tick [N].
            engine_on: whether the engine was commanded on.
            contact: the footpad contacts at this tick (None: no monitoring, the mass gauge only).
            torque_B_Nm: the torque command issued at this tick, (3,) [N m] (with ``contact``).
            oracle: guidance flew on the bench's truth (``nav = "truth"``), as :meth:`control`'s ``nav``.
        """
        self._advance_mass_gauge(t_ns)
        thrust_N = thrust_cmd_N if engine_on else 0.0
        if contact is None:
            self._hold_thrust(t_ns, thrust_N)
            return
        self._monitor_before_command(t_ns, contact, oracle)
        self._command_issued(t_ns, thrust_N, np.asarray(torque_B_Nm, float), contact)

    def _advance_mass_gauge(self, t_ns: int) -> None:
        """Burn the held thrust command's propellant up to ``t_ns`` (rocket equation, nominal Isp)."""
        if self._last_cmd_t_ns is not None:
            dt = (t_ns - self._last_cmd_t_ns) / NS_PER_S
            self.mass_kg -= self._last_thrust_N * self._thrust_scale / self._isp_g0 * dt

    def _hold_thrust(self, t_ns: int, thrust_N: float) -> None:
        self._last_cmd_t_ns = t_ns
        self._last_thrust_N = thrust_N
