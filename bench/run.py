"""One closed-loop landing: ``run(scenario) -> RunResult``, a pure function of the scenario.

Loop (integer-nanosecond scheduler):
    physics  ->  sensor models  ->  flight software  ->  actuators  ->  physics

* Every periodic component (IMU, altimeter, star tracker, camera, control)
  fires on its own period, all whole multiples of the physics step (checked
  at scenario load). Time advances from one event to the next in whole
  physics steps; between events every output is held (zero-order hold).
* Flight software (``gnc/``) receives messages only. Here navigation is
  "perfect": the truth state is handed over in the same :class:`NavState`
  the estimator will produce later. Footpad contact switches are a sensor
  message, and the controller cuts the engine on them.
* Touchdown is the first footpad contact. Its velocity and tilt are those of
  the last instant before contact forces acted (the previous event), its
  miss distance the horizontal distance from the target. The run goes on for
  ``landing.settle_s`` to see whether the lander stays upright.

Outcomes, first match wins: ``diverged`` (physics blew up), ``fuel_exhausted``
(propellant ran out before touchdown), ``timeout`` (no touchdown by
``sim.t_max_ns``), ``hard_landing`` (touchdown beyond the velocity or tilt
limits), ``tipped_over`` (not upright after settling), ``landed``.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import reduce
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bench.scenario import NS_PER_S, Scenario
from bench.world_builder import SensorSuite, build_sensors, build_terrain, build_world
from gnc.control import Controller, VehicleParams
from gnc.guidance import LandingTarget, make_guidance
from gnc.messages import ContactMessage
from gnc.navstate import NavState
from models.lander import LanderConfig, footpad_positions_B
from models.terrain import Terrain
from models.world import PhysicsDivergedError, TruthState, World

OUTCOMES = ("landed", "hard_landing", "tipped_over", "fuel_exhausted", "timeout", "diverged")
PHASE_TOUCHDOWN = "touchdown"

FrameSink = Callable[[int, np.ndarray, TruthState], None]
"""Called with (t_ns, frame (H, W) uint8, truth) for every camera frame."""


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


def vehicle_params(scenario: Scenario) -> VehicleParams:
    """The flight software's knowledge of the vehicle, from the lander configuration."""
    lander = scenario.lander
    return VehicleParams(
        thrust_min_N=lander.engine.thrust_min_N,
        thrust_max_N=lander.engine.thrust_max_N,
        rcs_torque_max_Nm=lander.rcs_torque_max_Nm,
        dry_mass_kg=lander.dry_mass_kg,
        dry_inertia_B_kgm2=tuple(float(x) for x in lander.body_inertia_kgm2()),
        tank_radius_m=lander.tank_radius_m,
    )


def tilt_deg(q_LB: np.ndarray) -> float:
    """Angle between body +z and L +z [deg]."""
    w, x, y, z = q_LB
    # R[2, 2] of the rotation body -> L, for a unit scalar-first quaternion.
    r22 = 1.0 - 2.0 * (x * x + y * y)
    return math.degrees(math.acos(max(-1.0, min(1.0, r22))))


class _Telemetry:
    """Row-wise recorder, turned into columns at the end."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    COLUMNS = (
        "t_s", "r_x_m", "r_y_m", "r_z_m", "v_x_mps", "v_y_mps", "v_z_mps",
        "q_w", "q_x", "q_y", "q_z", "omega_x_radps", "omega_y_radps", "omega_z_radps",
        "mass_kg", "propellant_kg", "tilt_deg",
        "thrust_cmd_N", "thrust_N", "throttle", "torque_x_Nm", "torque_y_Nm", "torque_z_Nm",
        "q_cmd_w", "q_cmd_x", "q_cmd_y", "q_cmd_z", "a_cmd_x_mps2", "a_cmd_y_mps2", "a_cmd_z_mps2",
        "t_go_s", "engine_on", "phase", "legs_in_contact",
        "imu_f_x_mps2", "imu_f_y_mps2", "imu_f_z_mps2", "imu_w_x_radps", "imu_w_y_radps", "imu_w_z_radps",
        "alt_range_m", "alt_valid", "st_q_w", "st_q_x", "st_q_y", "st_q_z",
    )

    def columns(self, terrain: Terrain, lander: LanderConfig) -> dict[str, np.ndarray]:
        cols = {name: np.array(values) for name, values in zip(self.COLUMNS, zip(*self.rows))}
        for name in ("engine_on", "alt_valid"):
            cols[name] = cols[name].astype(bool)
        cols["legs_in_contact"] = cols["legs_in_contact"].astype(np.int64)
        cols["phase"] = cols["phase"].astype(str)
        # Height of the lowest footpad above the terrain under it (vectorised once, after the run).
        r_L = np.column_stack([cols["r_x_m"], cols["r_y_m"], cols["r_z_m"]])
        R_LB = Rotation.from_quat(np.column_stack([cols[f"q_{c}"] for c in "wxyz"]), scalar_first=True)
        feet = np.stack([r_L + R_LB.apply(p_B) for p_B in footpad_positions_B(lander)], axis=1)  # (N, 4, 3)
        clearance = feet[..., 2] - lander.footpad_radius_m - terrain.surface_height(feet[..., 0], feet[..., 1])
        cols["height_m"] = clearance.min(axis=1)
        return cols


def run(scenario: Scenario, frame_sink: FrameSink | None = None, progress: bool = False) -> RunResult:
    """Fly one landing.

    Args:
        scenario: The scenario (seed included); nothing else influences the result.
        frame_sink: Receives every camera frame (for ``camera.mp4``); frames are
            rendered at the camera rate when ``camera.enabled``.
        progress: Show a progress bar over simulated time (on a terminal).

    Returns:
        The summary (keys: ``outcome``, ``landed``, ``touchdown`` {``t_s``,
        ``v_vertical_mps``, ``v_horizontal_mps``, ``tilt_deg``,
        ``miss_distance_m``}, ``fuel_used_kg``, ``sim_time_s``,
        ``wall_time_s``, ``realtime_factor``, ``seed``, and more), the
        telemetry and the terrain.
    """
    t_setup = time.perf_counter()
    terrain = build_terrain(scenario)
    world = build_world(scenario, terrain)
    sensors = build_sensors(scenario)
    setup_s = time.perf_counter() - t_setup
    try:
        return _fly(scenario, terrain, world, sensors, frame_sink, progress, setup_s)
    finally:
        world.close()


def _fly(scenario: Scenario, terrain: Terrain, world: World, sensors: SensorSuite,
         frame_sink: FrameSink | None, progress: bool, setup_s: float) -> RunResult:
    sim, cam, crit = scenario.sim, scenario.camera, scenario.landing
    dt_ns = sim.physics_dt_ns
    periods = {
        "imu": scenario.sensors.imu.period_ns,
        "altimeter": scenario.sensors.altimeter.period_ns,
        "star_tracker": scenario.sensors.star_tracker.period_ns,
        "control": sim.control_period_ns,
    }
    if cam.enabled:
        periods["camera"] = cam.period_ns
    tick_ns = reduce(math.gcd, periods.values())  # every event falls on a tick; a multiple of dt
    steps_per_tick = tick_ns // dt_ns
    assert tick_ns % dt_ns == 0

    vehicle = vehicle_params(scenario)
    controller = Controller(scenario.control, vehicle)
    guidance = make_guidance(scenario.guidance, controller.guidance_limits())
    target = LandingTarget()
    thrust_max = scenario.lander.engine.thrust_max_N

    tel = _Telemetry()
    imu_msg = alt_msg = st_msg = None
    act = None
    cmd = None
    truth = world.truth()
    prev_truth = truth
    propellant0 = truth.propellant_kg
    exhausted_ns: int | None = None
    touchdown: dict[str, Any] | None = None
    touchdown_ns: int | None = None
    outcome: str | None = None
    error: str | None = None
    settle_ns = int(round(crit.settle_s * NS_PER_S))
    bar = _progress_bar(sim.t_max_ns, progress)

    t_ns = 0
    wall0 = time.perf_counter()
    try:
        while True:
            truth = world.truth()
            legs = world.footpad_contacts()
            if touchdown is None and legs.any():
                touchdown_ns = t_ns
                touchdown = _touchdown_metrics(prev_truth, t_ns)
            # Sensors due now (zero-order hold between samples).
            if t_ns % periods["imu"] == 0:
                imu_msg = sensors.imu.sample(t_ns, world.specific_force_B(), world.angular_rate_B())
            if t_ns % periods["altimeter"] == 0:
                alt_msg = sensors.altimeter.sample(t_ns, world.altimeter_range_truth())
            if t_ns % periods["star_tracker"] == 0:
                st_msg = sensors.star_tracker.sample(t_ns, truth.q_LB)
            if cam.enabled and t_ns % periods["camera"] == 0:
                frame = sensors.camera_frame(world)
                if frame_sink is not None:
                    frame_sink(t_ns, frame, truth)
            # Flight software at the control rate.
            if t_ns % periods["control"] == 0:
                nav = NavState(t_ns, truth.r_BL_L, truth.v_BL_L, truth.q_LB, truth.omega_B, truth.mass_kg)
                cmd = guidance.update(nav, target)
                act = controller.update(nav, cmd, ContactMessage(t_ns, legs))
                tel.rows.append(_row(t_ns, truth, act, cmd, legs, imu_msg, alt_msg, st_msg, thrust_max,
                                     world.propulsion.clamp_thrust(act.thrust_N) * (1 + scenario.lander.engine.thrust_error_frac),
                                     PHASE_TOUCHDOWN if touchdown is not None else cmd.phase))
            # End conditions.
            if touchdown_ns is not None and t_ns - touchdown_ns >= settle_ns:
                break
            if t_ns >= sim.t_max_ns:
                break
            prev_truth = truth
            out = world.step(steps_per_tick, act.thrust_N, act.torque_B_Nm)
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
    if outcome is None:
        outcome = _classify(touchdown, exhausted_ns, touchdown_ns, final_tilt, scenario)
    sim_time_s = world.t_ns / NS_PER_S
    summary: dict[str, Any] = {
        "outcome": outcome,
        "landed": outcome == "landed",
        "touchdown": touchdown or {k: None for k in ("t_s", "v_vertical_mps", "v_horizontal_mps", "tilt_deg", "miss_distance_m")},
        "final_tilt_deg": final_tilt,
        "fuel_used_kg": propellant0 - truth.propellant_kg,
        "propellant_left_kg": truth.propellant_kg,
        "sim_time_s": sim_time_s,
        "wall_time_s": wall_s,
        "setup_time_s": setup_s,
        "realtime_factor": sim_time_s / wall_s if wall_s > 0 else math.inf,
        "seed": scenario.seed,
        "guidance_law": scenario.guidance.law,
        "camera_enabled": cam.enabled,
        "criteria": scenario.landing.model_dump(),
        "error": error,
    }
    telemetry = tel.columns(terrain, scenario.lander) if tel.rows else {}
    return RunResult(summary=summary, telemetry=telemetry, terrain=terrain)


def _touchdown_metrics(before: TruthState, t_ns: int) -> dict[str, float]:
    v = before.v_BL_L
    return {
        "t_s": t_ns / NS_PER_S,
        "v_vertical_mps": float(abs(v[2])),
        "v_horizontal_mps": float(math.hypot(v[0], v[1])),
        "tilt_deg": tilt_deg(before.q_LB),
        "miss_distance_m": float(math.hypot(before.r_BL_L[0], before.r_BL_L[1])),
    }


def _classify(touchdown: dict | None, exhausted_ns: int | None, touchdown_ns: int | None, final_tilt: float,
              scenario: Scenario) -> str:
    crit = scenario.landing
    if exhausted_ns is not None and (touchdown_ns is None or exhausted_ns < touchdown_ns):
        return "fuel_exhausted"
    if touchdown is None:
        return "timeout"
    if (touchdown["v_vertical_mps"] > crit.v_vertical_max_mps or touchdown["v_horizontal_mps"] > crit.v_horizontal_max_mps
            or touchdown["tilt_deg"] > crit.tilt_max_deg):
        return "hard_landing"
    if final_tilt > crit.tilt_max_deg:
        return "tipped_over"
    return "landed"


def _row(t_ns, truth, act, cmd, legs, imu, alt, st, thrust_max, thrust_delivered, phase) -> tuple:
    nan3 = (math.nan,) * 3
    return (
        t_ns / NS_PER_S, *truth.r_BL_L, *truth.v_BL_L, *truth.q_LB, *truth.omega_B,
        truth.mass_kg, truth.propellant_kg, tilt_deg(truth.q_LB),
        act.thrust_N, thrust_delivered, thrust_delivered / thrust_max, *act.torque_B_Nm,
        *act.q_LB_cmd, *cmd.a_cmd_L, cmd.t_go_s, act.engine_on, phase, int(legs.sum()),
        *(imu.f_B if imu is not None else nan3), *(imu.omega_B if imu is not None else nan3),
        alt.range_m if alt is not None else math.nan, bool(alt.valid) if alt is not None else False,
        *(st.q_LB if st is not None else (math.nan,) * 4),
    )


def _progress_bar(t_max_ns: int, enabled: bool):
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=t_max_ns // NS_PER_S, unit="sim s", desc="landing", leave=False)
