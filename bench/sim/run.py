"""One closed-loop landing: ``run(scenario) -> RunResult``, a pure function of the scenario.

Loop (integer-nanosecond scheduler):
    physics  ->  sensor models  ->  flight software  ->  actuators  ->  physics

* Every periodic component (IMU, altimeter, star tracker, camera, control)
  fires on its own period, all whole multiples of the physics step (checked
  at scenario load). Time advances from one event to the next in whole
  physics steps; between events every output is held (zero-order hold).
* Flight software (``gnc/``, ``vision/``) receives messages only, and is
  built from the scenario's onboard knowledge (:func:`onboard_knowledge`):
  the nominal vehicle and camera plus explicit knowledge errors, never a
  campaign case's drawn values. With ``nav = "estimator"`` (the default)
  guidance flies on the filter's estimate; ``nav = "truth"`` hands it the
  true kinematic state instead (an oracle for studies; the mass is still the
  flight software's own gauge). Footpad contact switches are a sensor
  message, and the controller cuts the engine on them.
* Sensors are sampled after ``mj_forward``, so each sample describes the
  state at its time tag.
* Touchdown is the first footpad contact, or the hull's if the body meets the
  ground first (``touchdown.first_contact``; a hull-first touchdown is a
  ``hard_landing`` whatever its speed). Its velocity and tilt are those of
  the last instant before contact forces acted (the previous event), its
  miss distance the horizontal distance from the target. The run goes on for
  ``landing.settle_s`` to see whether the lander stays upright.

Outcomes, first match wins: ``diverged`` (physics blew up), ``fuel_exhausted``
(propellant ran out before touchdown), ``off_terrain`` (the lander left the
terrain's square before touching down: there is no ground beyond it, so the
run ends there), ``timeout`` (no touchdown by ``sim.t_max_ns``), ``hard_landing`` (touchdown beyond the velocity or tilt
limits), ``tipped_over`` (after settling the lander has fallen over: its
centre of mass is outside the footpads' support polygon, or its tilt is
beyond the static tip-over angle of its leg geometry,
:func:`models.lander.static_tipover_deg`), ``slope_exceeded`` (it stands, but
tilted beyond ``landing.tilt_max_deg``), ``landed``. ``safe_abort``: the flight
software declared an abort (:mod:`gnc.fdir`) and, ``ABORT_OBSERVE_S`` later
(judged once, at that instant), the lander is still flying and not descending
faster than ``landing.v_vertical_max_mps``; an aborted lander that does not
meet this flies on to its touchdown and is classified as any other.

Faults (``scenario.faults``, :mod:`models.faults`) are applied between the
truth sensor models and the flight software's messages, in the camera's
frame delivery and in the actuator path; a ``computer_reset`` withholds
every message and commands nothing (engine and RCS off) while the computer is
down, then the flight software restarts from its own checkpoint
(:func:`bench.sim.flight_build.restart_flight_software`). The flight software's
detections (:mod:`gnc.fdir`) are in the summary, ``fdir``, and each fault's
detection and latency in ``faults``.

Flight-computer latency (``realism = "realistic"``): the command computed at
control tick k acts from tick k + ``sim.compute_latency_ticks``; before the
first command's turn the first command acts (the computer was flying it at
hand-over). ``realism = "ideal"``: it acts at once.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from collections import deque
from functools import reduce
from typing import Any, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from bench.errors import SimulationDefectError
from bench.evaluation.consistency import NEES_BLOCKS, block_nees_many, run_consistency, ticks_at_altitudes
from bench.scenario import NS_PER_S, Scenario, ScenarioError
from bench.scenario.seeding import component_rng
from bench.sim.flight_build import (build_flight_software, check_tracker_fits_camera, handover_estimate,
                                    onboard_knowledge, restart_flight_software)
from bench.sim.truth_tracker import TruthTracker
from bench.sim.world_builder import SensorSuite, build_sensors, build_terrain, build_world
from gnc.control import ActuatorCommand
from gnc.estimator import IDX_BA, IDX_R, IDX_V
from gnc.flight import FlightSoftware
from gnc.guidance import PHASE_OFF, PHASE_TERMINAL
from gnc.messages import AltimeterMessage, AttitudeMessage, ContactMessage, ImageMessage, ImuMessage
from gnc.navstate import NavState
from gnc.plugins import LawOutputError
from models.camera import R_BC
from models.render_context import free_shared_contexts
from models.sensors import ALTIMETER_BORESIGHT_B
from vision.tracks import Tracks
from models.lander import (LanderConfig, altimeter_position_B, com_position_B, footpad_positions_B,
                           static_tipover_deg, support_margin_m)
from models.terrain import Terrain
from models.world import PhysicsDivergedError, TruthState, World

OUTCOMES = ("landed", "hard_landing", "tipped_over", "slope_exceeded", "fuel_exhausted", "safe_abort", "off_terrain",
            "timeout", "diverged")
PHASE_TOUCHDOWN = "touchdown"
ABORT_OBSERVE_S = 10.0  # after a declared abort, the run goes on this long to see the lander safe

FrameSink = Callable[[int, np.ndarray, TruthState, "Tracks | None"], None]
"""Called with (t_ns, frame (H, W) uint8, truth, tracks or None) for every camera frame."""


class RenderingFrameSink(Protocol):
    """A frame sink that renders, elsewhere, the frames that only it consumes (``camera.mp4``'s video
    process, :class:`bench.report.video_process.VideoProcess`).

    The closed loop calls :meth:`start` once with its world, then, at every camera frame, either the
    sink itself with a frame it rendered for the flight software, or :meth:`render_frame` for a frame
    nobody on board consumes: the sink renders that one from the world's visual state, with camera
    frame ``frame_index``'s own noise stream and ``exposure_gain``, so it gets the pixels the loop
    would have rendered.
    """

    def __call__(self, t_ns: int, frame: np.ndarray, truth: TruthState, tracks: "Tracks | None") -> None: ...

    def start(self, world: World) -> None: ...

    def render_frame(self, t_ns: int, frame_index: int, world: World, exposure_gain: float, truth: TruthState,
                     tracks: "Tracks | None") -> None: ...


class Recorder(Protocol):
    """Receives everything the flight software is given, in the order given (``landbench record``).

    The closed loop calls it only to hand over copies-to-be; it never feeds
    anything back, so a run with a recorder flies exactly as one without.

    Attributes:
        want_depth: Also render the z-depth image at every camera frame (for
            truth correspondences later); a second render that the flight
            software never sees.
    """

    want_depth: bool

    def message(self, kind: str, msg: ImuMessage | AttitudeMessage | AltimeterMessage | ImageMessage) -> None:
        """A sensor message (``kind``: imu, attitude, altimeter, image), called just before the flight software gets it."""

    def camera_truth(self, t_ns: int, R_LC: np.ndarray, r_CL_L: np.ndarray, depth: np.ndarray | None) -> None:
        """The truth camera pose (and depth) at a camera frame, after the frame's message."""

    def control_tick(self, t_ns: int, contact: ContactMessage, truth: TruthState, accel_bias_B: np.ndarray) -> None:
        """A control tick: the contact message the flight software gets, and the truth at the tick."""
TRUTH_TRACK_POINTS = 80  # points the truth tracker keeps in view (about the paper tracker's count)
VEL_RMS_BELOW_M = 100.0  # vel_err_rms_mps is taken below this altitude


@dataclass
class RunResult:
    """What one landing produced.

    Attributes:
        summary: The ``summary.json`` contract (see :func:`run`).
        telemetry: One row per control tick, column name -> (N,) array.
        terrain: The terrain flown over (for plots).
    """

    summary: dict[str, Any]
    telemetry: dict[str, np.ndarray]
    terrain: Terrain = field(repr=False)


def tilt_deg(q_LB: np.ndarray) -> float:
    """Angle between body +z and L +z [deg]."""
    w, x, y, z = q_LB
    # R[2, 2] of the rotation body -> L, for a unit scalar-first quaternion.
    r22 = 1.0 - 2.0 * (x * x + y * y)
    return math.degrees(math.acos(max(-1.0, min(1.0, r22))))


class _Telemetry:
    """Row-wise recorder, turned into columns at the end."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []  # ROW_COLUMNS of each control tick
        self.nees_e: list[np.ndarray] = []  # the NEES's error (position, velocity, accelerometer bias) per tick
        self.nees_P: list[np.ndarray] = []  # and its covariance block: the NEES columns are made at the end

    COLUMNS = (
        "t_s", "r_x_m", "r_y_m", "r_z_m", "v_x_mps", "v_y_mps", "v_z_mps",
        "q_w", "q_x", "q_y", "q_z", "omega_x_radps", "omega_y_radps", "omega_z_radps",
        "mass_kg", "propellant_kg", "tilt_deg",
        "thrust_cmd_N", "thrust_N", "throttle", "torque_x_Nm", "torque_y_Nm", "torque_z_Nm",
        "q_cmd_w", "q_cmd_x", "q_cmd_y", "q_cmd_z", "a_cmd_x_mps2", "a_cmd_y_mps2", "a_cmd_z_mps2",
        "t_go_s", "engine_on", "phase", "legs_in_contact",
        "imu_f_x_mps2", "imu_f_y_mps2", "imu_f_z_mps2", "imu_w_x_radps", "imu_w_y_radps", "imu_w_z_radps",
        "alt_range_m", "alt_valid", "st_q_w", "st_q_x", "st_q_y", "st_q_z",
        "nav_r_x_m", "nav_r_y_m", "nav_r_z_m", "nav_v_x_mps", "nav_v_y_mps", "nav_v_z_mps",
        "nav_err_r_x_m", "nav_err_r_y_m", "nav_err_r_z_m", "nav_err_v_x_mps", "nav_err_v_y_mps", "nav_err_v_z_mps",
        "nav_sigma_r_x_m", "nav_sigma_r_y_m", "nav_sigma_r_z_m",
        "nav_sigma_v_x_mps", "nav_sigma_v_y_mps", "nav_sigma_v_z_mps",
        "nav_err_ba_x_mps2", "nav_err_ba_y_mps2", "nav_err_ba_z_mps2",
        *(f"nees_{block}" for block in NEES_BLOCKS), "fsw_mass_kg",
        "vision_tracks", "vision_measurements", "vision_rejected",
        "vision_v_x_mps", "vision_v_y_mps",
        "thrust_applied_cmd_N", "torque_applied_x_Nm", "torque_applied_y_Nm", "torque_applied_z_Nm",
    )

    NEES_COLUMNS = tuple(f"nees_{block}" for block in NEES_BLOCKS)
    ROW_COLUMNS = tuple(filter(lambda c, nees=NEES_COLUMNS: c not in nees, COLUMNS))  # the columns _row gives

    def columns(self, terrain: Terrain, lander: LanderConfig) -> dict[str, np.ndarray]:
        rows = {name: np.array(values) for name, values in zip(self.ROW_COLUMNS, zip(*self.rows, strict=True),
                                                                strict=True)}
        # Every tick's NEES at once (block_nees_many: the same values as block_nees row by row).
        nees = block_nees_many(np.array(self.nees_e), np.array(self.nees_P))
        rows.update({name: nees[:, j] for j, name in enumerate(self.NEES_COLUMNS)})
        cols = {name: rows[name] for name in self.COLUMNS}
        for name in ("engine_on", "alt_valid"):
            cols[name] = cols[name].astype(bool)
        for name in ("legs_in_contact", "vision_tracks", "vision_measurements", "vision_rejected"):
            cols[name] = cols[name].astype(np.int64)
        cols["phase"] = cols["phase"].astype(str)
        # Height of the lowest footpad above the terrain under it (vectorised once, after the run).
        r_L = np.column_stack([cols["r_x_m"], cols["r_y_m"], cols["r_z_m"]])
        R_LB = Rotation.from_quat(np.column_stack([cols[f"q_{c}"] for c in "wxyz"]), scalar_first=True)
        feet = np.stack([r_L + R_LB.apply(p_B) for p_B in footpad_positions_B(lander)], axis=1)  # (N, 4, 3)
        clearance = feet[..., 2] - lander.footpad_radius_m - terrain.surface_height(feet[..., 0], feet[..., 1])
        cols["height_m"] = clearance.min(axis=1)
        return cols


def run(scenario: Scenario, frame_sink: FrameSink | RenderingFrameSink | None = None, progress: bool = False,
        recorder: Recorder | None = None) -> RunResult:
    """Fly one landing.

    Args:
        scenario: The scenario (seed included); nothing else influences the result.
        frame_sink: Receives every camera frame (for ``camera.mp4``); frames are
            rendered at the camera rate when ``camera.enabled``. A
            :class:`RenderingFrameSink` renders the frames that only it consumes.
        progress: Show a progress bar over simulated time (on a terminal).
        recorder: Receives every message given to the flight software (see
            :class:`Recorder`); it does not change the run.

    Returns:
        The summary (keys: ``outcome``, ``landed``, ``touchdown`` {``t_s``,
        ``first_contact``, ``v_vertical_mps``, ``v_horizontal_mps``, ``tilt_deg``,
        ``miss_distance_m``}, ``fuel_used_kg``, ``sim_time_s``,
        ``wall_time_s``, ``realtime_factor``, ``seed``, and more), the
        telemetry and the terrain.

    Raises:
        ScenarioError: A camera too small for the vision tracker (:func:`check_tracker_fits_camera`), before
            anything is built; an input check made in flight.
        SimulationDefectError: A ``ValueError`` (other than a plug-in law's, :class:`gnc.plugins.LawOutputError`,
            or an input check's, :class:`ScenarioError`), an arithmetic, type, lookup, attribute or assertion
            error inside the closed loop.
    """
    check_tracker_fits_camera(scenario)  # before anything is built
    t_setup = time.perf_counter()
    maps = None
    if scenario.nav_map == "on":  # the onboard map (for the flight software) and its truth (for the bench)
        from bench.maps import scenario_onboard_map

        # Made first: its regenerated surface (about 300 MB while it lasts) is freed before the terrain,
        # the world and its GL context exist, so that the two do not add up in the case's peak memory.
        maps = scenario_onboard_map(scenario)
    hazard = None
    if scenario.hazard.scored:  # the fine truth ground (and the lidar that sees it)
        from bench.sim.hazard_truth import HazardTruth

        # Before the terrain and the world, for the same reason: its texel field's FFT (several hundred
        # MB while it lasts) is done before a GL context exists (a reused worker's idle one freed).
        free_shared_contexts()
        hazard = HazardTruth(scenario)
    terrain = build_terrain(scenario)
    world = build_world(scenario, terrain)
    try:
        sensors = build_sensors(scenario)
        # The flight computer, built before the loop: what it refuses (a law's missing optional extra) is the
        # user's, not the closed loop's.
        fsw = build_flight_software(scenario, *handover_estimate(scenario, world.truth()),
                                    onboard_map=maps[0] if maps is not None else None)
        setup_s = time.perf_counter() - t_setup
        try:
            return _fly(scenario, terrain, world, sensors, fsw, frame_sink, progress, setup_s, recorder, maps, hazard)
        except (LawOutputError, ScenarioError):
            raise  # the user's: a plug-in law's output, or an input check made in flight
        except (ValueError, ArithmeticError, TypeError, LookupError, AttributeError, AssertionError) as exc:
            # What no input check foresaw (an overflow included); an OSError (a full disk) and a GL error stay theirs.
            raise SimulationDefectError(
                f"the closed loop failed at t = {world.t_ns / NS_PER_S:.3f} s with {type(exc).__name__}: {exc}. "
                f"The scenario passed its checks, so this is a defect of landbench, not a mistake in the input: "
                f"please report it with the scenario (seed {scenario.seed})") from exc
    finally:
        world.close()


def _fly(scenario: Scenario, terrain: Terrain, world: World, sensors: SensorSuite, fsw: FlightSoftware,
         frame_sink: FrameSink | RenderingFrameSink | None, progress: bool, setup_s: float,
         recorder: Recorder | None = None, maps: tuple | None = None, hazard: Any = None) -> RunResult:
    sim, cam, crit = scenario.sim, scenario.camera, scenario.landing
    dt_ns = sim.physics_dt_ns
    truth_tracks = scenario.vision == "on" and scenario.tracks == "truth"
    periods = {
        "imu": scenario.sensors.imu.period_ns,
        "altimeter": scenario.sensors.altimeter.period_ns,
        "star_tracker": scenario.sensors.star_tracker.period_ns,
        "control": sim.control_period_ns,
    }
    if cam.enabled or truth_tracks:
        periods["camera"] = cam.period_ns
    tick_ns = reduce(math.gcd, periods.values())  # every event falls on a tick; a multiple of dt
    steps_per_tick = tick_ns // dt_ns
    assert tick_ns % dt_ns == 0

    map_truth_log: list[tuple[int, np.ndarray]] = []  # (t_ns, truth camera position) at each map-fix attempt
    # With map fixes the flight software navigates in the map's frame: its errors are taken against the truth
    # there (truth + the map's shift). Without them, against the truth in L.
    nav_offset_L = np.array([*maps[1].shift_xy_m, 0.0]) if maps is not None else None
    faults = sensors.faults
    down = False  # the flight computer is down (a computer_reset fault)
    abort_ns: int | None = None
    abort_judged = False  # the lander has been judged ABORT_OBSERVE_S after a declared abort
    off_terrain = False  # it left the terrain's square before touching down
    half_size_m = terrain.size_m / 2.0
    tracker_truth = (TruthTracker(terrain, world.K, (cam.width_px, cam.height_px), TRUTH_TRACK_POINTS,
                                  component_rng(scenario.seed, "vision")) if truth_tracks else None)
    thrust_max = scenario.lander.engine.thrust_max_N
    latency_ticks = scenario.sim.compute_latency_ticks if scenario.realism == "realistic" else 0
    pipeline: deque = deque()  # commands computed, not yet acting (the flight computer's latency)
    applied = None

    tel = _Telemetry()
    imu_msg = alt_msg = st_msg = None
    act = None
    truth = world.truth()
    prev_truth = truth
    propellant0 = truth.propellant_kg
    exhausted_ns: int | None = None
    touchdown: dict[str, Any] | None = None
    touchdown_ns: int | None = None
    touchdown_pose: tuple[np.ndarray, np.ndarray] | None = None  # truth (r_BL_L, q_LB) at touchdown
    outcome: str | None = None
    error: str | None = None
    settle_ns = int(round(crit.settle_s * NS_PER_S))
    bar = _progress_bar(sim.t_max_ns, progress)
    timing = {"render_s": 0.0, "vision_s": 0.0, "filter_s": 0.0}
    frames_rendered = 0
    # A sink that renders the frames only it wants (see RenderingFrameSink) is shown the world first.
    render_elsewhere = getattr(frame_sink, "render_frame", None)
    if render_elsewhere is not None and cam.enabled:
        frame_sink.start(world)

    t_ns = 0
    wall0 = time.perf_counter()
    try:
        while True:
            truth = world.truth()
            legs, hull = world.ground_contacts()
            if touchdown is None and (legs.any() or hull):
                touchdown_ns = t_ns
                touchdown = _touchdown_metrics(prev_truth, t_ns, "footpad" if legs.any() else "hull")
                touchdown_pose = (np.array(prev_truth.r_BL_L, float), np.array(prev_truth.q_LB, float))
            if faults is not None:
                faults.update(t_ns, _truth_height(terrain, truth) if faults.needs_altitude() else None,
                              fsw.last_guidance.phase if fsw.last_guidance is not None else None)
                was_down, down = down, faults.computer_down(t_ns)
                if was_down and not down:
                    fsw = restart_flight_software(scenario, fsw, t_ns)
                world.set_engine_fault(faults.thrust_gain(t_ns), faults.fault_torque_B_Nm(t_ns),
                                       faults.thrust_direction_B(t_ns))
                world.propulsion.set_rcs_fault(faults.rcs_fault(t_ns))
            camera_tick = "camera" in periods and t_ns % periods["camera"] == 0
            if camera_tick and cam.enabled and (recorder is not None or (tracker_truth is None and fsw.wants_image())):
                # A frame the tracker will want: the GL driver draws it while the other sensors are fed to the
                # flight software (World.start_frame; read below, redrawn if the world has moved since).
                t0 = time.perf_counter()
                world.start_frame()
                timing["render_s"] += time.perf_counter() - t0
            # Sensors due now (zero-order hold between samples); the filter consumes them.
            t0 = time.perf_counter()
            if t_ns % periods["imu"] == 0:
                # Realistic: an integrating IMU (delta-velocity and delta-angle over its interval, as means);
                # ideal: point samples.
                means = world.imu_mean_B() if scenario.realism == "realistic" else None
                f_B, omega_B = means if means is not None else (world.specific_force_B(), world.angular_rate_B())
                msg = _to_flight_software(sensors.imu.sample(t_ns, f_B, omega_B),
                                          None if faults is None else faults.imu, down, recorder, "imu", fsw.on_imu)
                imu_msg = msg if msg is not None else imu_msg
            if t_ns % periods["star_tracker"] == 0:
                msg = _to_flight_software(sensors.star_tracker.sample(t_ns, truth.q_LB),
                                          None if faults is None else faults.star_tracker, down, recorder, "attitude",
                                          fsw.on_attitude)
                st_msg = msg if msg is not None else st_msg
            if t_ns % periods["altimeter"] == 0:
                msg = _to_flight_software(sensors.altimeter.sample(t_ns, world.altimeter_range_truth()),
                                          None if faults is None else faults.altimeter, down, recorder, "altimeter",
                                          fsw.on_altimeter)
                alt_msg = msg if msg is not None else alt_msg
            timing["filter_s"] += time.perf_counter() - t0
            if camera_tick:
                tracks = None
                frame = None
                delivered = faults is None or (faults.frame_delivered(t_ns) and not down)
                # Render only a frame that someone consumes: the video, a recording, or the tracker
                # (above the cut-off). Each frame's noise is its own stream, so skipping changes nothing.
                on_board = (recorder is not None or (tracker_truth is None and delivered and fsw.wants_image())
                            or (delivered and fsw.wants_map_frame(t_ns)))
                video_only = frame_sink is not None and not on_board  # a frame for the video alone
                gain = 1.0 if faults is None else faults.exposure_gain(t_ns)
                if cam.enabled and (on_board or (video_only and render_elsewhere is None)):
                    t0 = time.perf_counter()
                    frame = sensors.camera_frame_at(world, t_ns // cam.period_ns, gain)
                    timing["render_s"] += time.perf_counter() - t0
                    frames_rendered += 1
                t0 = time.perf_counter()
                n_map = fsw.map_nav.stats.frames_used if fsw.map_nav is not None else 0
                if not delivered:
                    pass  # the frame never reaches the flight software (blackout, drop, computer down)
                elif tracker_truth is not None:
                    if frame is not None and fsw.map_nav is not None:
                        fsw.map_nav.on_frame(t_ns, frame, fsw.filter)
                    tracks = tracker_truth.step(*world.camera_pose())
                    fsw.on_tracks(t_ns, tracks)
                elif frame is not None:
                    image_msg = ImageMessage(t_ns, frame, world.K, R_BC)
                    if recorder is not None:
                        recorder.message("image", image_msg)
                        t0 += _record_camera_truth(recorder, t_ns, world)  # not vision time
                    tracks = fsw.on_image(image_msg)
                elif cam.enabled:
                    fsw.skip_image(t_ns)  # what on_image does with a frame it does not use
                timing["vision_s"] += time.perf_counter() - t0
                if fsw.map_nav is not None and fsw.map_nav.stats.frames_used > n_map:
                    map_truth_log.append((t_ns, world.camera_pose()[1]))
                if frame is not None and frame_sink is not None:
                    frame_sink(t_ns, frame, truth, tracks)
                elif cam.enabled and video_only:  # rendered by the sink, from the world as it is now
                    render_elsewhere(t_ns, t_ns // cam.period_ns, world, gain, truth, tracks)
            # Flight software at the control rate.
            if t_ns % periods["control"] == 0:
                truth_nav = None
                if scenario.nav == "truth":
                    truth_nav = NavState(t_ns, truth.r_BL_L, truth.v_BL_L, truth.q_LB, truth.omega_B, fsw.mass_kg)
                contact = ContactMessage(t_ns, legs)
                if recorder is not None:
                    recorder.control_tick(t_ns, contact, truth, sensors.imu.accel_bias)
                if hazard is not None and not down and fsw.wants_lidar_scan():  # a flash for hazard avoidance
                    fsw.on_lidar(hazard.flash(t_ns, truth.r_BL_L, truth.q_LB, fsw.filter.ekf.x[:3]))
                if down:  # the computer commands nothing: engine and RCS off
                    act = ActuatorCommand(0.0, np.zeros(3), False, t_ns)
                else:
                    act = fsw.control(t_ns, contact, truth_nav)
                commanded = act  # the flight software's command: telemetry thrust_cmd_N (a replay's mass gauge)
                if not down and faults is not None:
                    act = _engine_command(faults, t_ns, act)  # what the engine acts on (a stuck throttle)
                if abort_ns is None and fsw.fdir is not None and fsw.fdir.abort is not None:
                    abort_ns = t_ns
                if not pipeline:
                    pipeline.extend([act] * latency_ticks)  # at hand-over the computer was already flying it
                pipeline.append(act)
                applied = pipeline.popleft()
                guid = fsw.last_guidance  # None until guidance first runs (a computer down from the start)
                phase = PHASE_TOUCHDOWN if touchdown is not None else guid.phase if guid is not None else PHASE_OFF
                tel.rows.append(_row(t_ns, truth, commanded, guid, legs, imu_msg, alt_msg, st_msg, thrust_max,
                                     world.propulsion.delivered_thrust_N(applied.thrust_N), phase,
                                     fsw, sensors.imu.accel_bias, applied, tel, nav_offset_L))
            # End conditions.
            if touchdown_ns is not None and t_ns - touchdown_ns >= settle_ns:
                break
            if (abort_ns is not None and not abort_judged and touchdown_ns is None
                    and t_ns - abort_ns >= ABORT_OBSERVE_S * NS_PER_S):
                abort_judged = True  # judged once, at that instant: later it flies on to its touchdown
                if truth.v_BL_L[2] >= -crit.v_vertical_max_mps:
                    outcome = "safe_abort"  # declared, and seen safe: flying, not descending fast
                    break
            if touchdown_ns is None and max(abs(truth.r_BL_L[0]), abs(truth.r_BL_L[1])) > half_size_m:
                off_terrain = True  # no ground beyond it: nothing left to land on
                break
            if t_ns >= sim.t_max_ns:
                break
            prev_truth = truth
            out = world.step(steps_per_tick, applied.thrust_N, applied.torque_B_Nm)
            if out.exhausted and exhausted_ns is None:
                exhausted_ns = t_ns
            t_ns += tick_ns
            if bar is not None and t_ns % NS_PER_S == 0:
                bar.update(1)
    except PhysicsDivergedError as exc:
        outcome, error = "diverged", str(exc)
    finally:
        if bar is not None:
            bar.close()
    wall_s = time.perf_counter() - wall0

    truth = world.truth()
    final_tilt = tilt_deg(truth.q_LB)
    stability = _stability(truth, world.lander_cfg)
    if outcome is None:
        outcome = _classify(touchdown, exhausted_ns, touchdown_ns, final_tilt, scenario, stability, off_terrain)
    fdir_events = [e.to_dict() for e in fsw.fdir.events] if fsw.fdir is not None else []
    sim_time_s = world.t_ns / NS_PER_S
    telemetry = tel.columns(terrain, scenario.lander) if tel.rows else {}
    summary: dict[str, Any] = {
        "outcome": outcome,
        "landed": outcome == "landed",
        "touchdown": touchdown or {k: None for k in ("t_s", "first_contact", "v_vertical_mps", "v_horizontal_mps",
                                                      "tilt_deg", "miss_distance_m", "x_m", "y_m")},
        "final_tilt_deg": final_tilt,
        "stability": stability,
        "realism": scenario.realism,
        "fuel_used_kg": propellant0 - truth.propellant_kg,
        "fuel_exhausted_t_s": exhausted_ns / NS_PER_S if exhausted_ns is not None else None,
        "propellant_left_kg": truth.propellant_kg,
        "sim_time_s": sim_time_s,
        "wall_time_s": wall_s,
        "setup_time_s": setup_s,
        "realtime_factor": sim_time_s / wall_s if wall_s > 0 else math.inf,
        "seed": scenario.seed,
        "modes": {"nav": scenario.nav, "tracks": scenario.tracks, "vision": scenario.vision},
        "guidance_law": scenario.guidance.law,
        "camera_enabled": cam.enabled,
        "criteria": scenario.landing.model_dump(),
        "nav": _nav_summary(telemetry, touchdown),
        "guidance": {**_guidance_summary(telemetry, scenario),
                     **({"law_stats": fsw.guidance.stats()} if hasattr(fsw.guidance, "stats") else {})},
        "vision": _vision_summary(fsw),
        "consistency": run_consistency(telemetry, touchdown, fsw.filter.log),
        "fdir": _fdir_summary(fsw, fdir_events),
        "fdir_events": fdir_events,
        "faults": _fault_summary(scenario, faults, fdir_events, telemetry),
        "time_split_s": {**timing, "frames_rendered": frames_rendered},  # what was rendered depends on the outputs
        "platform": _platform(world),
        "error": error,
    }
    if maps is not None:
        summary["map_nav"] = _map_nav_summary(fsw, maps[1], map_truth_log, telemetry, touchdown)
    if hazard is not None:
        summary["hazard"] = hazard.summary(fsw, touchdown_pose)
    return RunResult(summary=summary, telemetry=telemetry, terrain=terrain)


MAP_NAV_ERR_ALTITUDE_M = 50.0  # [m] truth height of the summary's navigation error (the goal table's)
MAP_FALSE_LOCK_NIS = 25.0  # a fix the matcher accepted whose error is beyond 5 of its own sigmas (2-D NIS)


def _map_nav_summary(fsw: FlightSoftware, map_truth: Any, truth_log: list[tuple[int, np.ndarray]],
                     tel: dict[str, np.ndarray], touchdown: dict | None) -> dict[str, Any]:
    """Map-relative navigation against truth (``nav_map = "on"``).

    A fix's error is its measured camera position minus the truth camera position plus the map's
    shift (the fix measures the position in the map frame). A false lock is a fix the matcher
    accepted with an error beyond 5 of its own sigmas.
    """
    stats = fsw.map_nav.stats
    shift = np.array(map_truth.shift_xy_m)
    truth_at = dict(truth_log)
    errs, nis, used = _scored_fixes(stats.log, truth_at, lambda t_ns, fix: truth_at[t_ns][:2] + shift)
    false_locks = sum(n > MAP_FALSE_LOCK_NIS for n in nis)
    used_false = sum(n > MAP_FALSE_LOCK_NIS and u for n, u in zip(nis, used))
    kf = _keyframe_summary(stats, shift, truth_at)
    out: dict[str, Any] = {
        "shift_xy_m": [float(c) for c in shift],
        "target_xy_L_m": [float(c) for c in map_truth.target_xy_L_m],
        "attempts": stats.attempts, "refused": dict(stats.refused), "unconfirmed": stats.unconfirmed,
        "search_sigmas_max": stats.search_sigmas_max, "locked": stats.locked, "never_locked": stats.never_locked,
        "updates": stats.updates, "gate_rejected": stats.gate_rejected, "relocks": stats.relocks,
        "fixes_accepted_by_matcher": len(errs),
        **_fix_error_stats(errs, nis, ""),
        "false_locks": false_locks, "false_locks_used": used_false,
        "miss_vs_map_target_m": None, "nav_err_map_frame_touchdown_m": None,
        "nav_err_map_frame_50m_m": None, "nav_err_map_frame_50m_xy_m": None,
        **kf,
    }
    if touchdown is not None:
        out["miss_vs_map_target_m"] = float(math.hypot(touchdown["x_m"] - map_truth.target_xy_L_m[0],
                                                       touchdown["y_m"] - map_truth.target_xy_L_m[1]))
    if tel:
        t = tel["t_s"]
        flying = t < touchdown["t_s"] if touchdown is not None else np.ones(t.size, bool)
        k = int(np.flatnonzero(flying)[-1]) if flying.any() else 0
        # The telemetry's navigation errors are already against the truth in the map frame.
        out["nav_err_map_frame_touchdown_m"] = float(np.hypot(tel["nav_err_r_x_m"][k], tel["nav_err_r_y_m"][k]))
        # At 50 m (the goal table's height; the last map fixes): the first flying tick at or below it,
        # the rule of the consistency altitudes; none when the case starts below it.
        (k50,) = ticks_at_altitudes(tel["r_z_m"], flying, [MAP_NAV_ERR_ALTITUDE_M])
        if k50 >= 0:
            e50 = [float(tel["nav_err_r_x_m"][k50]), float(tel["nav_err_r_y_m"][k50])]
            out["nav_err_map_frame_50m_xy_m"] = e50
            out["nav_err_map_frame_50m_m"] = float(np.hypot(*e50))
    return out


def _keyframe_summary(stats: Any, shift: np.ndarray, truth_at: dict[int, np.ndarray]) -> dict[str, Any]:
    """The keyframe and its fixes against truth (keys always present, so campaign columns agree).

    The keyframe is the map shifted by the horizontal error of the camera position it was laid down
    with (``keyframe_err_xy_m``: estimate minus truth, in the map frame) and magnified about its nadir
    by the height error (``keyframe_err_z_m``), so a keyframe fix's error is its measured position
    minus (truth + map shift + e_xy + g e_z), ``g`` the estimated camera's displacement from the
    keyframe's over the keyframe's height (the flight software's own model, fed here with the
    truth's errors). A false lock is one accepted with an error beyond 5 of its own sigmas, as for
    map fixes. When the lander flew off a keyframe and another was taken (``keyframes`` counts them; the
    ``keyframe_*`` fields above are the first's), each fix is scored against the one it was matched to.
    """
    # Every keyframe (the first, and those taken again when the lander flew off the one before), with its errors;
    # a fix is scored against the last one taken at or before it.
    kfs = [(t, r, h, r[:2] - (truth_at[t][:2] + shift), float(r[2] - truth_at[t][2]))
           for t, r, h in stats.keyframes if t in truth_at]
    t_k, _, h_k = stats.keyframes[0] if stats.keyframes else (None, None, None)
    e_k, dz_k = kfs[0][3:] if kfs and kfs[0][0] == t_k else (None, None)
    errs: list[float] = []
    nis: list[float] = []
    if e_k is not None:

        def expected(t_ns: int, fix: Any) -> np.ndarray:
            _, r, h, e, dz = [k for k in kfs if k[0] <= t_ns][-1]
            g = (fix.r_CM_xy_m - fix.offset_xy_m - r[:2]) / h
            return truth_at[t_ns][:2] + shift + e + g * dz

        errs, nis, _ = _scored_fixes(stats.keyframe_log, truth_at, expected)
    return {
        "keyframe_t_s": None if t_k is None else t_k / NS_PER_S,
        "keyframe_height_m": None if t_k is None else float(h_k),
        "keyframe_err_xy_m": None if e_k is None else [float(c) for c in e_k],
        "keyframe_err_z_m": dz_k,
        "keyframes": len(stats.keyframes),
        "keyframe_attempts": stats.keyframe_attempts, "keyframe_refused": stats.keyframe_refused,
        "keyframe_updates": stats.keyframe_updates, "keyframe_gate_rejected": stats.keyframe_gate_rejected,
        **_fix_error_stats(errs, nis, "keyframe_"),
        "keyframe_false_locks": sum(n > MAP_FALSE_LOCK_NIS for n in nis),
    }


def _scored_fixes(log: list[tuple], truth_at: dict[int, np.ndarray],
                  expected_xy_m: Any) -> tuple[list[float], list[float], list[bool]]:
    """The fixes of a map or keyframe log that the matcher accepted, scored against truth.

    ``expected_xy_m(t_ns, fix)`` is where a perfect fix would put the camera (map frame) [m]. Returns
    each scored fix's error norm [m], its NIS under its own covariance ``total_cov_xy_m2`` [-], and
    whether the filter took it (used and through the gate).
    """
    errs, nis, taken = [], [], []
    for t_ns, fix, used, gate_ok in log:
        if not fix.ok or t_ns not in truth_at:
            continue
        e = fix.r_CM_xy_m - expected_xy_m(t_ns, fix)
        errs.append(float(np.hypot(*e)))
        nis.append(float(e @ np.linalg.solve(fix.total_cov_xy_m2, e)))
        taken.append(bool(used and gate_ok))
    return errs, nis, taken


def _fix_error_stats(errs: list[float], nis: list[float], prefix: str) -> dict[str, float | None]:
    """RMS and largest error [m] and mean NIS [-] of scored fixes, under ``prefix``; None without fixes."""
    return {
        f"{prefix}fix_err_rms_m": float(np.sqrt(np.mean(np.square(errs)))) if errs else None,
        f"{prefix}fix_err_max_m": max(errs) if errs else None,
        f"{prefix}fix_nis_mean": float(np.mean(nis)) if nis else None,
    }


def _delivered(msg: Any, down: bool) -> Any:
    """A message after the fault injector, or None while the flight computer is down."""
    return None if down else msg


def _to_flight_software(msg: Any, inject: Any, down: bool, recorder: Any, kind: str, handler: Any) -> Any:
    """One sensor message through the fault injector (``inject``; None: no faults) to the flight software.

    Returns the message delivered (recorded, then handed to ``handler``), or None when none was.
    """
    if inject is not None:
        msg = _delivered(inject(msg), down)
    if msg is not None:
        if recorder is not None:
            recorder.message(kind, msg)
        handler(msg)
    return msg


def _engine_command(faults: Any, t_ns: int, act: ActuatorCommand) -> ActuatorCommand:
    """The command the engine acts on under a stuck throttle (the flight software's own is unchanged)."""
    thrust = faults.thrust_command(t_ns, act.thrust_N)
    if thrust == act.thrust_N:
        return act
    return ActuatorCommand(thrust, act.torque_B_Nm, act.engine_on, act.t_ns, act.q_LB_cmd)


def _truth_height(terrain: Terrain, truth: TruthState) -> float:
    """Truth height of the body origin above the terrain under it [m] (altitude triggers)."""
    x, y, z = truth.r_BL_L
    return float(z - terrain.surface_height(x, y))


# Which detections count for a fault on each target (gnc.fdir subsystems).
DETECTS = {"imu": ("imu", "accel_thrust"), "altimeter": ("altimeter",), "star_tracker": ("star_tracker",),
           "camera": ("camera",), "engine": ("engine", "accel_thrust", "rcs"), "computer": ("computer",),
           "terrain": ("altimeter",), "rcs": ("rcs",)}


def _beam_on_disc_ns(tel: dict[str, np.ndarray], step: Any, lander: LanderConfig) -> int | None:
    """The first control tick at which the altimeter's beam lands on a terrain step's disc [ns]; None: never.

    The footprint is the truth: the altimeter's mount and boresight carried into L by the true attitude and
    position, out to the range it reported (a valid sample). A lander whose body starts over the disc while
    its tilted beam reaches the ground beyond the edge (seed 7's case 6 of the Hakuto-R preset: 35 m inside a
    60 m disc at 496 m, the beam 100 m out) never ranges the step, which then never acts on a sensor.
    """
    if not tel:
        return None
    q = np.column_stack([tel[f"q_{c}"] for c in "wxyz"])
    valid = np.asarray(tel["alt_valid"], bool) & np.isfinite(tel["alt_range_m"])
    if not valid.any():
        return None
    idx = np.flatnonzero(valid)
    R_LB = Rotation.from_quat(q[idx], scalar_first=True)
    ray_B = altimeter_position_B(lander)[None, :] + tel["alt_range_m"][idx, None] * ALTIMETER_BORESIGHT_B[None, :]
    hit_L = np.column_stack([tel["r_x_m"][idx], tel["r_y_m"][idx], tel["r_z_m"][idx]]) + R_LB.apply(ray_B)
    inside = np.hypot(hit_L[:, 0] - step.center_xy_m[0], hit_L[:, 1] - step.center_xy_m[1]) <= step.radius_m
    return int(round(float(tel["t_s"][idx[np.argmax(inside)]]) * NS_PER_S)) if inside.any() else None


def _fault_summary(scenario: Scenario, faults: Any, events: list[dict],
                   tel: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Per fault: its window and whether (and how late) the flight software detected it.

    Detected: a detection of a subsystem the fault's target maps to (``DETECTS``)
    at or after the fault's start and before its end plus 5 s. A terrain step
    starts when the altimeter's beam first lands on it (never: not triggered;
    :func:`_beam_on_disc_ns`).
    """
    if faults is None:
        return []
    out = []
    for f, (start, end) in zip(scenario.faults, faults.windows()):
        if f.kind == "terrain_step":  # it acts from when the altimeter first ranges it
            start, end = _beam_on_disc_ns(tel, f, scenario.lander), None
        subs = DETECTS[f.subsystem]
        hit = None
        if start is not None:
            limit = math.inf if end is None else end / NS_PER_S + 5.0
            hit = next((e for e in events if e["subsystem"] in subs and start / NS_PER_S <= e["t_s"] <= limit), None)
        out.append({"kind": f.kind, "target": f.subsystem if f.kind != "terrain_step" else "terrain",
                    "start_t_s": None if start is None else start / NS_PER_S,
                    "end_t_s": None if end is None else end / NS_PER_S,
                    "triggered": start is not None, "detected": hit is not None,
                    "detection_t_s": None if hit is None else hit["t_s"],
                    "latency_s": None if hit is None else hit["t_s"] - start / NS_PER_S,
                    "detection": None if hit is None else hit["reason"]})
    return out


def _fdir_summary(fsw: FlightSoftware, events: list[dict]) -> dict[str, Any]:
    abort = fsw.fdir.abort if fsw.fdir is not None else None
    return {"n_events": len(events), "first_event_t_s": events[0]["t_s"] if events else None,
            "subsystems": ",".join(sorted({e["subsystem"] for e in events})),
            "abort_declared": abort is not None, "abort_t_s": None if abort is None else abort.t_ns / NS_PER_S,
            "abort_reason": None if abort is None else abort.reason}


def _record_camera_truth(recorder: Recorder, t_ns: int, world: World) -> float:
    """Hand the truth camera pose (and depth) of this frame to the recorder; returns the seconds it took."""
    t0 = time.perf_counter()
    depth = world.render_depth() if recorder.want_depth else None
    recorder.camera_truth(t_ns, *world.camera_pose(), depth)
    return time.perf_counter() - t0


def _nav_summary(tel: dict[str, np.ndarray], touchdown: dict | None) -> dict[str, Any]:
    """Navigation-error figures from the telemetry (estimate vs truth).

    Consistency is reported per block as the mean of ``NEES / dof`` over the
    flight (the per-block mean ``(e / sigma)^2``); the ensemble statistics that
    can show consistency are a campaign's (``consistency.json``).
    """
    if not tel:
        return {"pos_err_touchdown_m": None, "vel_err_touchdown_mps": None, "vel_err_rms_mps": None,
                "vel_err_horizontal_touchdown_mps": None, "nees_per_dof_mean": None}
    t = tel["t_s"]
    flying = t < touchdown["t_s"] if touchdown is not None else np.ones(t.size, bool)
    k = int(np.flatnonzero(flying)[-1]) if flying.any() else 0  # last tick before touchdown
    e_r = np.column_stack([tel[f"nav_err_r_{a}_m"] for a in "xyz"])
    e_v = np.column_stack([tel[f"nav_err_v_{a}_mps"] for a in "xyz"])
    low = flying & (tel["r_z_m"] < VEL_RMS_BELOW_M)
    return {
        "pos_err_touchdown_m": float(np.linalg.norm(e_r[k])),
        "vel_err_touchdown_mps": float(np.linalg.norm(e_v[k])),
        "vel_err_horizontal_touchdown_mps": float(np.hypot(e_v[k, 0], e_v[k, 1])),
        "vel_err_rms_mps": float(np.sqrt(np.mean(np.sum(e_v[low] ** 2, axis=1)))) if low.any() else None,
        "nees_per_dof_mean": ({block: float(np.mean(tel[f"nees_{block}"][flying])) / dof
                               for block, dof in NEES_BLOCKS.items()} if flying.any() else None),
    }


def _guidance_summary(tel: dict[str, np.ndarray], scenario: Scenario) -> dict[str, Any]:
    """The hand-over to the terminal phase: truth altitude and vertical speed at its first tick."""
    out: dict[str, Any] = {"handover_t_s": None, "handover_altitude_m": None, "handover_v_z_mps": None,
                           "handover_v_z_error_mps": None}
    if not tel:
        return out
    terminal = np.flatnonzero(tel["phase"] == PHASE_TERMINAL)
    if terminal.size:
        k = int(terminal[0])
        v_z = float(tel["v_z_mps"][k])
        out.update(handover_t_s=float(tel["t_s"][k]), handover_altitude_m=float(tel["r_z_m"][k]),
                   handover_v_z_mps=v_z,
                   handover_v_z_error_mps=abs(v_z) - scenario.guidance.terminal_descent_rate_mps)
    return out


def _cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``), else what ``platform`` knows."""
    import platform

    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _platform(world: World) -> dict[str, Any]:
    """Where the run ran: results are bit-identical on one machine and one GL build, not across them."""
    import mujoco

    # With the camera on, the GL build even when no frame was consumed (then none was rendered).
    return {"cpu": _cpu_model(), "gl": world.gl_info(probe=world.camera_cfg.enabled), "mujoco": mujoco.__version__}


def _vision_summary(fsw: FlightSoftware) -> dict[str, float | int | None]:
    v = fsw.vision
    return {
        "frames": v.frames,
        "tracks_median": float(np.median(v.track_counts)) if v.track_counts else None,
        "measurements": v.measurements,
        "rejected_frac": v.rejected / v.measurements if v.measurements else None,
        "unusable_pairs": v.unusable,
    }


def _touchdown_metrics(before: TruthState, t_ns: int, first_contact: str) -> dict[str, Any]:
    """The touchdown's figures from the truth just before contact; ``first_contact``: "footpad", or "hull"
    (the lander met the ground with its body first: a crash, however slow)."""
    v = before.v_BL_L
    return {
        "t_s": t_ns / NS_PER_S,
        "first_contact": first_contact,
        "v_vertical_mps": float(abs(v[2])),
        "v_horizontal_mps": float(math.hypot(v[0], v[1])),
        "tilt_deg": tilt_deg(before.q_LB),
        "miss_distance_m": float(math.hypot(before.r_BL_L[0], before.r_BL_L[1])),
        "x_m": float(before.r_BL_L[0]),
        "y_m": float(before.r_BL_L[1]),
    }


def _stability(truth: TruthState, lander: LanderConfig) -> dict[str, float]:
    """Whether the lander stands, at the end of the run.

    ``static_tipover_deg``: the static tip-over angle of its legs (with its centre of mass now);
    ``support_margin_m``: how far the centre of mass's ground projection lies inside the convex
    hull of the footpads' (negative: outside).
    """
    R_LB = Rotation.from_quat(truth.q_LB, scalar_first=True)
    feet_L = truth.r_BL_L + R_LB.apply(footpad_positions_B(lander))
    com_L = truth.r_BL_L + R_LB.apply(com_position_B(lander, truth.propellant_kg))
    return {"static_tipover_deg": static_tipover_deg(lander, truth.propellant_kg),
            "support_margin_m": support_margin_m(feet_L[:, :2], com_L[:2])}


def _classify(touchdown: dict | None, exhausted_ns: int | None, touchdown_ns: int | None, final_tilt: float,
              scenario: Scenario, stability: dict[str, float], off_terrain: bool = False) -> str:
    crit = scenario.landing
    if exhausted_ns is not None and (touchdown_ns is None or exhausted_ns < touchdown_ns):
        return "fuel_exhausted"
    if touchdown is None:
        return "off_terrain" if off_terrain else "timeout"
    if (touchdown["v_vertical_mps"] > crit.v_vertical_max_mps or touchdown["v_horizontal_mps"] > crit.v_horizontal_max_mps
            or touchdown["tilt_deg"] > crit.tilt_max_deg or touchdown["first_contact"] == "hull"):
        return "hard_landing"
    if final_tilt > stability["static_tipover_deg"] or stability["support_margin_m"] < 0.0:
        return "tipped_over"
    if final_tilt > crit.tilt_max_deg:
        return "slope_exceeded"
    return "landed"


def _row(t_ns, truth, act, cmd, legs, imu, alt, st, thrust_max, thrust_delivered, phase, fsw, accel_bias_B,
         applied, tel: _Telemetry, nav_offset_L: np.ndarray | None = None) -> tuple:
    """One tick's ``_Telemetry.ROW_COLUMNS``; its NEES error and covariance block go to ``tel``.

    ``nav_offset_L``: where the flight software's navigation frame puts the truth, minus the truth (the
    map's shift with map fixes); None: its frame is L. ``cmd`` None (guidance has not run yet: the
    computer down from the start): its columns are NaN.
    """
    nan3 = (math.nan,) * 3
    x, P = fsw.filter.ekf.x, fsw.filter.ekf.P
    r_ref = truth.r_BL_L if nav_offset_L is None else truth.r_BL_L + nav_offset_L
    e = np.concatenate([x[IDX_R] - r_ref, x[IDX_V] - truth.v_BL_L, x[IDX_BA] - accel_bias_B])
    sig = np.sqrt(np.diag(P)[:6])  # position then velocity
    tel.nees_e.append(e)
    tel.nees_P.append(P[:9, :9].copy())
    vm = fsw.vision.last
    # Arrays go in as lists of Python floats: unpacking an array makes a NumPy scalar of each element,
    # several times slower; the columns (np.array of each) hold the same float64 values.
    return (
        t_ns / NS_PER_S, *truth.r_BL_L.tolist(), *truth.v_BL_L.tolist(), *truth.q_LB.tolist(),
        *truth.omega_B.tolist(), truth.mass_kg, truth.propellant_kg, tilt_deg(truth.q_LB),
        act.thrust_N, thrust_delivered, thrust_delivered / thrust_max, *act.torque_B_Nm.tolist(),
        *act.q_LB_cmd.tolist(), *(np.asarray(cmd.a_cmd_L, float).tolist() if cmd is not None else nan3),
        cmd.t_go_s if cmd is not None else math.nan, act.engine_on, phase,
        int(legs.sum()),
        *(imu.f_B if imu is not None else nan3), *(imu.omega_B if imu is not None else nan3),
        alt.range_m if alt is not None else math.nan, bool(alt.valid) if alt is not None else False,
        *(st.q_LB if st is not None else (math.nan,) * 4),
        *x[IDX_R].tolist(), *x[IDX_V].tolist(), *e[:6].tolist(), *sig.tolist(), *e[6:9].tolist(), fsw.mass_kg,
        len(fsw.vision.last_tracks) if fsw.vision.last_tracks is not None else 0,
        fsw.vision.measurements, fsw.vision.rejected,
        *(vm.v_L if vm is not None else (math.nan,) * 2),
        applied.thrust_N, *np.asarray(applied.torque_B_Nm, float).tolist(),
    )


def _progress_bar(t_max_ns: int, enabled: bool):
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=t_max_ns // NS_PER_S, unit="sim s", desc="landing", leave=False)
