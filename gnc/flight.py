"""The flight computer: messages in, actuator commands out.

Ports:
    Inputs: :class:`ImuMessage` (IMU rate), :class:`AttitudeMessage` (star
        tracker rate), :class:`AltimeterMessage` (altimeter rate), camera
        frames as :class:`ImageMessage` or ready-made tracks (camera rate),
        :class:`ContactMessage` (control rate).
    Output: :class:`ActuatorCommand` (control rate), plus the navigation
        state and vision bookkeeping for telemetry.
    Rate: event driven; the bench calls the ``on_*`` methods in time order.

Navigation: the filter (:mod:`gnc.estimator`) is propagated with the IMU and
the star-tracker attitude, and updated with the altimeter and, above the
vision cut-off altitude, with the velocity that :mod:`gnc.vision_nav` derives
from the paper's tracks between consecutive frames. Below the cut-off, IMU and
altimeter carry navigation to touchdown.

Mass is the flight computer's own propellant gauging: the wet mass at
hand-over minus the integral of commanded thrust over ``Isp g0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from gnc.control import ActuatorCommand, Controller
from gnc.estimator import NavFilter
from gnc.guidance import GuidanceCommand, GuidanceLaw, LandingTarget
from gnc.messages import AltimeterMessage, AttitudeMessage, ContactMessage, ImageMessage, ImuMessage
from gnc.navstate import NavState
from gnc.vision_nav import VelocityMeasurement, VisionNavConfig, velocity_from_tracks
from vision.tracker import Tracker
from vision.tracks import Tracks

NS_PER_S = 1_000_000_000
G0_MPS2 = 9.80665  # defines Isp
HORIZONTAL = (0, 1)  # vision measures the east and north velocity
MIN_ALTIMETER_COS_NADIR = 0.5  # the altimeter gives the camera height only within 60 deg of nadir
FALLBACK_HEIGHT_SIGMA_M = 10.0


@dataclass
class VisionStats:
    """Vision bookkeeping for telemetry and the summary."""

    frames: int = 0  # frames given to the tracker
    track_counts: list[int] = field(default_factory=list)
    measurements: int = 0  # velocity measurements formed
    rejected: int = 0  # ... of which the filter's gate rejected
    unusable: int = 0  # frame pairs that gave no measurement (too few tracks)
    last: VelocityMeasurement | None = None
    last_tracks: Tracks | None = None


@dataclass
class _Frame:
    t_ns: int
    q_LB: np.ndarray
    v_L: np.ndarray  # filter velocity at the frame [m/s]
    z_m: float  # filter altitude at the frame [m]
    h_cam_m: float  # camera height above the local ground at the frame [m]
    sigma_h_m: float


class FlightSoftware:
    """Navigation + vision + guidance + control, fed by messages.

    Args:
        guidance: The guidance law.
        controller: The controller.
        nav_filter: The navigation filter.
        tracker: The paper's tracker, or None when frames are not processed
            (vision off, or tracks supplied by :meth:`on_tracks`).
        vision_cfg: Velocity-from-tracks settings.
        vision_enabled: Use vision measurements at all.
        K, R_BC, r_cam_B: Camera calibration: intrinsics (3, 3), mounting
            rotation (3, 3), camera position in B (3,) [m].
        r_alt_B: Altimeter position in B (3,) [m].
        wet_mass_kg: Mass at hand-over [kg].
        isp_s: Engine specific impulse [s] (for propellant gauging).
    """

    def __init__(self, guidance: GuidanceLaw, controller: Controller, nav_filter: NavFilter,
                 tracker: Tracker | None, vision_cfg: VisionNavConfig, vision_enabled: bool,
                 K: np.ndarray, R_BC: np.ndarray, r_cam_B: np.ndarray, r_alt_B: np.ndarray,
                 wet_mass_kg: float, isp_s: float):
        self.guidance = guidance
        self.controller = controller
        self.filter = nav_filter
        self.tracker = tracker
        self.vision_cfg = vision_cfg
        self.vision_enabled = vision_enabled
        self.K, self.R_BC, self.r_cam_B = np.asarray(K, float), np.asarray(R_BC, float), np.asarray(r_cam_B, float)
        self.r_alt_B = np.asarray(r_alt_B, float)
        self.mass_kg = wet_mass_kg
        self._isp_g0 = isp_s * G0_MPS2
        self.target = LandingTarget()
        self.vision = VisionStats()
        self._q_LB: np.ndarray | None = None
        self._alt: AltimeterMessage | None = None
        self._prev_frame: _Frame | None = None
        self._last_cmd_t_ns: int | None = None
        self._last_thrust_N = 0.0
        self.last_guidance: GuidanceCommand | None = None

    # ------------------------------------------------------------------ sensors
    def on_imu(self, msg: ImuMessage) -> None:
        self.filter.propagate_imu(msg)

    def on_attitude(self, msg: AttitudeMessage) -> None:
        self._q_LB = np.asarray(msg.q_LB, float)
        self.filter.set_attitude(msg)

    def on_altimeter(self, msg: AltimeterMessage) -> None:
        if msg.valid:
            self._alt = msg
        self.filter.update_altimeter(msg)

    def on_image(self, msg: ImageMessage) -> Tracks | None:
        """Run the paper's tracker on a frame (above the cut-off) and use its tracks."""
        if self.tracker is None or not self._vision_active():
            return None
        tracks = self.tracker.step(msg.image)
        self.vision.frames += 1
        self.on_tracks(msg.t_ns, tracks)
        return tracks

    def on_tracks(self, t_ns: int, tracks: Tracks) -> None:
        """Form a velocity measurement from the tracks of this frame and the previous one."""
        if not self._vision_active() or self._q_LB is None:
            self._prev_frame = None
            return
        self.vision.track_counts.append(len(tracks))
        self.vision.last_tracks = tracks
        nav = self.filter.nav_state(self.mass_kg)
        h_cam, sigma_h = self._camera_height(self._q_LB)
        frame = _Frame(t_ns, self._q_LB.copy(), nav.v_BL_L.copy(), float(nav.r_BL_L[2]), h_cam, sigma_h)
        prev, self._prev_frame = self._prev_frame, frame
        if prev is None:
            return
        # The vertical displacement comes from the filter (IMU + altimeter), not from the image.
        dz = frame.z_m - prev.z_m
        sigma_dz = self.vision_cfg.vertical_rate_sigma_mps * (t_ns - prev.t_ns) / NS_PER_S
        m = velocity_from_tracks(tracks, prev.t_ns, t_ns, self.K, self.R_BC, self.r_cam_B, prev.q_LB, frame.q_LB,
                                 prev.h_cam_m, prev.sigma_h_m, frame.v_L - prev.v_L, dz, sigma_dz, self.vision_cfg)
        if m is None:
            self.vision.unusable += 1
            return
        self.vision.measurements += 1
        self.vision.last = m
        record = self.filter.update_velocity(m.t_ns, m.v_L, m.R, axes=HORIZONTAL)
        if not record.accepted:
            self.vision.rejected += 1

    def _vision_active(self) -> bool:
        if not self.vision_enabled:
            return False
        return float(self.filter.nav_state(self.mass_kg).r_BL_L[2]) > self.vision_cfg.cutoff_altitude_m

    def _camera_height(self, q_LB: np.ndarray) -> tuple[float, float]:
        """Camera height above the local ground now: the altimeter's, else the filter's [m], with 1-sigma.

        The altimeter measures from its own mount; the camera's height differs
        by the vertical component of the mounting offset between the two.
        """
        R_LB = Rotation.from_quat(q_LB, scalar_first=True).as_matrix()
        cam_above_alt = float((R_LB @ (self.r_cam_B - self.r_alt_B))[2])
        if self._alt is not None:
            cos_nadir = -float((R_LB @ np.asarray(self._alt.boresight_B, float))[2])
            if cos_nadir > MIN_ALTIMETER_COS_NADIR:
                height = self._alt.range_m * cos_nadir + cam_above_alt
                return height, self.filter.altimeter_sigma_m(self._alt.range_m, cos_nadir)
        nav = self.filter.nav_state(self.mass_kg)
        cam_above_body = float((R_LB @ self.r_cam_B)[2])
        sigma = math.sqrt(max(float(nav.P[2, 2]), 0.0)) if nav.P is not None else FALLBACK_HEIGHT_SIGMA_M
        return float(nav.r_BL_L[2]) + cam_above_body, sigma

    # ------------------------------------------------------------------ control
    def control(self, t_ns: int, contact: ContactMessage, nav: NavState | None = None) -> ActuatorCommand:
        """One control step; ``nav`` overrides the filter (perfect navigation)."""
        if self._last_cmd_t_ns is not None:
            dt = (t_ns - self._last_cmd_t_ns) / NS_PER_S
            self.mass_kg -= self._last_thrust_N / self._isp_g0 * dt
        nav = nav if nav is not None else self.filter.nav_state(self.mass_kg)
        cmd = self.guidance.update(nav, self.target)
        act = self.controller.update(nav, cmd, contact)
        self.last_guidance = cmd
        self._last_cmd_t_ns = t_ns
        self._last_thrust_N = act.thrust_N if act.engine_on else 0.0
        return act
