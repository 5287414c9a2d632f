"""Building the flight software of a landing, free of the simulator.

Inputs: a :class:`~bench.scenario.Scenario` (its onboard knowledge and the
``estimator``, ``tracker``, ``vision_nav``, ``guidance`` and ``control``
sections) and, for the hand-over, the truth position and velocity at t = 0.
Outputs: the :class:`~gnc.flight.FlightSoftware` of the run, exactly as the
closed loop (:mod:`bench.sim.run`) builds it.

Nothing here builds, steps or renders a world, so an open-loop replay of a
recorded descent (:mod:`bench.evaluation.replay`) builds the very same flight
software without the simulator. :mod:`bench.sim.run` re-exports these names.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bench.scenario import Scenario, ScenarioError
from bench.scenario.seeding import component_rng
from gnc.control import VehicleParams, make_controller
from gnc.estimator import DIM_REGIONAL, IDX_H, IDX_RR, make_estimator
from gnc.fdir import COMPUTER, EngineResponse, FdirEvent, HealthMonitor, SensorSpec, restart_estimate
from gnc.flight import FlightSoftware, OnboardKnowledge
from gnc.guidance import make_guidance
from gnc.hda import HazardAvoidance
from gnc.map_nav import MapNavigator, OnboardMap
from models.camera import R_BC, intrinsics
from models.lander import altimeter_position_B, camera_position_B
from vision.tracker import Tracker


def onboard_knowledge(scenario: Scenario) -> OnboardKnowledge:
    """The flight software's knowledge of its vehicle: the nominal lander and camera plus the knowledge errors.

    Never the truth of a campaign case: the nominal lander and camera are
    ``scenario.knowledge.lander`` / ``.camera`` (pinned by the campaign before
    it draws), else the scenario's own. The mounts come from the same geometry
    functions the world's MJCF is built with (one calibration source).
    """
    k = scenario.knowledge
    lander = scenario.nominal_lander()
    vehicle = VehicleParams(
        thrust_min_N=lander.engine.thrust_min_N,
        thrust_max_N=lander.engine.thrust_max_N,
        rcs_torque_max_Nm=lander.rcs_torque_max_Nm,
        dry_mass_kg=lander.dry_mass_kg + k.dry_mass_error_kg,
        dry_inertia_B_kgm2=tuple(float(x) * (1.0 + k.inertia_error_frac) for x in lander.body_inertia_kgm2()),
        tank_radius_m=lander.tank_radius_m,
        thrust_scale=1.0 + k.thrust_calibration_error_frac,
    )
    return OnboardKnowledge(
        vehicle=vehicle,
        wet_mass_kg=lander.wet_mass_kg + k.dry_mass_error_kg + k.propellant_error_kg,
        isp_s=lander.engine.isp_s,
        K=intrinsics(scenario.nominal_camera()),
        R_BC=R_BC,
        r_cam_B_m=camera_position_B(lander),
        r_alt_B_m=altimeter_position_B(lander),
    )


def handover_estimate(scenario: Scenario, truth: Any) -> tuple[np.ndarray, np.ndarray]:
    """The navigation state handed over at t = 0: the truth plus a draw of the hand-over error.

    The error is drawn with ``estimator.init_*_sigma`` (the filter's own initial
    covariance, so the hand-over is consistent) from the run's "estimator" stream.

    Args:
        scenario: The scenario (seed and estimator section).
        truth: The truth at t = 0: anything with ``r_BL_L`` and ``v_BL_L`` (3,)
            (a :class:`models.world.TruthState`, or a recorded one).

    Returns:
        (r_BL_L estimate (3,) [m], v_BL_L estimate (3,) [m/s]).
    """
    est = scenario.estimator
    rng = component_rng(scenario.seed, "estimator")
    r0 = truth.r_BL_L + rng.normal(0.0, est.init_pos_sigma_m, 3)
    v0 = truth.v_BL_L + rng.normal(0.0, est.init_vel_sigma_mps, 3)
    return r0, v0


def sensor_spec(scenario: Scenario) -> SensorSpec:
    """The sensors' periods and the altimeter's range, as their specification gives them to the flight software:
    the nominal sensors and camera (``knowledge.sensors`` / ``.camera``, pinned by a campaign), never a case's
    drawn values."""
    s, camera = scenario.nominal_sensors(), scenario.nominal_camera()
    return SensorSpec(imu_period_ns=s.imu.period_ns, altimeter_period_ns=s.altimeter.period_ns,
                      star_tracker_period_ns=s.star_tracker.period_ns,
                      camera_period_ns=camera.period_ns if camera.enabled else None,
                      altimeter_max_range_m=s.altimeter.max_range_m)


def engine_response(scenario: Scenario) -> EngineResponse:
    """The nominal engine's throttle response, as the flight software knows it (the idealised vehicle's
    engine follows its command at once)."""
    if scenario.realism == "ideal":
        return EngineResponse()
    engine = scenario.nominal_lander().engine
    return EngineResponse(time_constant_s=engine.time_constant_s, slew_rate_Nps=engine.slew_rate_Nps)


def check_tracker_fits_camera(scenario: Scenario) -> None:
    """Refuse a flight whose vision tracker could never track in its camera's frames.

    The tracker places a template only ``border_px`` away from every edge of the frame
    (:class:`vision.tracker.Tracker`), so in a frame smaller than ``template_size + 2 border_px`` (of
    the configuration it scales to that frame) it holds no track at all, and the flight software
    would fly blind without a word. Checked before a flight is set up; other commands (rendering a
    world, the vision figures) may use such a camera.

    Raises:
        ScenarioError: Naming the camera's size, the size needed and the ways out.
    """
    if scenario.vision != "on" or scenario.tracks != "vision" or not scenario.camera.enabled:
        return
    cam = scenario.camera
    side = min(cam.width_px, cam.height_px)
    cfg = scenario.tracker.for_side(side)
    need = cfg.template_size + 2 * cfg.border_px
    if side < need:
        raise ScenarioError(
            f"camera.width_px x camera.height_px = {cam.width_px} x {cam.height_px} is too small for the tracker: a "
            f"template (tracker.template_size = {cfg.template_size} px) kept tracker.border_px = {cfg.border_px} px "
            f"from every edge needs {need} px a side, so vision would never track; allowed: a camera of at least "
            f"{need} px a side, a smaller tracker.template_size or tracker.border_px, or vision = 'off' or "
            "tracks = 'truth'")


def build_flight_software(scenario: Scenario, x0_r_L: np.ndarray, x0_v_L: np.ndarray, t0_ns: int = 0,
                          q0_LB: np.ndarray | None = None, onboard_map: OnboardMap | None = None) -> FlightSoftware:
    """The flight computer of the run: onboard knowledge, configuration and the hand-over estimate.

    Nothing of the truth reaches it but the hand-over estimate passed in (at ``t0_ns``; ``q0_LB``: an initial
    attitude the flight software holds itself, after a reset; None: from the first star-tracker fix). With
    ``nav_map = "on"`` it carries the onboard map (``onboard_map``, else made here from the scenario: plain data).
    """
    check_tracker_fits_camera(scenario)
    knowledge = onboard_knowledge(scenario)
    control = scenario.control
    if scenario.realism == "ideal":  # the idealised flight computer commands the full magnitude m |f|
        control = control.model_copy(update={"thrust_projection": "magnitude"})
    controller = make_controller(control, knowledge.vehicle)
    limits = dataclasses.replace(controller.guidance_limits(), isp_s=knowledge.isp_s)  # G-FOLD models the mass flow
    guidance = make_guidance(scenario.guidance, limits)
    # The realistic vehicle's IMU integrates (delta-velocity and delta-angle); the ideal one point-samples.
    # With map fixes the filter carries their common error b_map (its 1-sigma is set at the first fix) and the
    # regional relief under the altimeter.
    map_on = scenario.nav_map == "on"
    nav_filter = make_estimator(scenario.estimator, x0_r_L, x0_v_L, int(t0_ns), q0_LB,
                                altimeter_mount_B_m=knowledge.r_alt_B_m,
                                gyro_delta_angle=scenario.realism == "realistic",
                                map_bias_sigma_m=1.0 if map_on else None, regional_relief=map_on)
    # The tracker's own stream, drawn from only by its random feature search (tracker.fp_search = "random").
    tracker = (Tracker(scenario.tracker, rng=component_rng(scenario.seed, "tracker"))
               if scenario.tracks == "vision" and scenario.vision == "on" else None)
    map_nav = None
    if scenario.nav_map == "on":
        if onboard_map is None:
            from bench.maps import scenario_onboard_map

            onboard_map = scenario_onboard_map(scenario)[0]
        map_nav = MapNavigator(onboard_map, scenario.map_nav, knowledge.K, knowledge.R_BC, knowledge.r_cam_B_m)
    hda = HazardAvoidance(scenario.hazard.hda) if scenario.hazard.avoidance == "on" else None
    health = HealthMonitor(scenario.fdir, sensor_spec(scenario), engine_response(scenario))
    return FlightSoftware(guidance, controller, nav_filter, tracker, scenario.vision_nav, scenario.vision == "on",
                          knowledge, map_nav, health, hda)


def restart_flight_software(scenario: Scenario, old: FlightSoftware, t_ns: int) -> FlightSoftware:
    """The flight software after a computer reset at ``t_ns``: everything volatile is lost.

    It restarts from its own non-volatile checkpoint (the last control tick's
    filter state, covariance, mass and attitude, carried ballistically over the
    outage: the engine was off; :func:`gnc.fdir.restart_estimate`), never from the truth;
    the detections of its earlier life are kept, and the restart is one more.
    """
    t0, x0, P0, mass, q0 = old.checkpoint  # the hand-over's data when it went down before its first control tick
    x, P = restart_estimate(x0, P0, (t_ns - t0) / 1e9, scenario.estimator.gravity_mps2)
    onboard_map = old.map_nav.matcher.map if old.map_nav is not None else None  # the map survives in storage
    new = build_flight_software(scenario, x[:3], x[3:6], t0_ns=t_ns, q0_LB=q0, onboard_map=onboard_map)
    # Warm restart: the checkpointed kinematic, accelerometer-bias and terrain states with their covariance;
    # the vision states (clone, image offsets, flow bias, viewed ground) start afresh, as the tracker does.
    # The regional relief, where carried, is terrain too: kept.
    keep = np.arange(IDX_H + 1)
    if x.size == DIM_REGIONAL:
        keep = np.concatenate([keep, np.arange(IDX_RR, DIM_REGIONAL)])
    new.filter.ekf.x[keep] = x[keep]
    new.filter.ekf.P[keep, :] = 0.0
    new.filter.ekf.P[:, keep] = 0.0
    new.filter.ekf.P[np.ix_(keep, keep)] = P[np.ix_(keep, keep)]
    new.mass_kg = mass
    if old.map_nav is not None and new.map_nav is not None:
        # Its bookkeeping and its lock survive: the checkpointed position is the locked, map-relative one (a
        # fresh record dropped every earlier fix from the summary, and an unlocked one would re-confirm, or
        # declare a lock missing below the fixes' window). The keyframe image is volatile: made again if due.
        new.map_nav.stats = old.map_nav.stats
    if old.hda is not None:  # the scan's result (the retargeted site) is kept in non-volatile memory
        new.hda = old.hda
        new.target = old.target
    new.fdir.carry_events([*old.fdir.events, FdirEvent(
        t_ns, COMPUTER, f"computer restarted after {(t_ns - t0) / 1e9:.2f} s down",
        "state restored from the non-volatile checkpoint, carried ballistically")])
    return new
