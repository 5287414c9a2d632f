"""Build the truth world and its sensors from a scenario (bench owns truth).

Workers in a campaign call these with (scenario) alone: MuJoCo and GL objects
are built where they are used and never pickled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.scenario import Scenario
from bench.scenario.seeding import component_rng
from models.camera import apply_detector_noise
from models.sensors import AltimeterModel, ImuModel, StarTrackerModel
from models.terrain import Terrain, generate_terrain
from models.world import World


def build_terrain(scenario: Scenario) -> Terrain:
    """Generate (or load) the scenario's terrain from its own stream."""
    return generate_terrain(
        scenario.terrain,
        component_rng(scenario.terrain_seed(), "terrain"),
        sun_elevation_deg=scenario.sun.elevation_deg,
        sun_azimuth_deg=scenario.sun.azimuth_deg,
    )


def build_world(scenario: Scenario, terrain: Terrain | None = None) -> World:
    """The MuJoCo world of the scenario, with the lander at its initial state."""
    terrain = build_terrain(scenario) if terrain is None else terrain
    world = World(
        terrain,
        scenario.lander,
        scenario.camera,
        scenario.sun,
        physics_dt_ns=scenario.sim.physics_dt_ns,
        gravity_mps2=scenario.sim.gravity_mps2,
    )
    init = scenario.initial
    world.reset(np.array(init.r_BL_L_m), np.array(init.v_BL_L_mps), init.q_LB(), np.array(init.omega_B_radps))
    return world


@dataclass
class SensorSuite:
    """The sensor error models of one run, each on its own stream."""

    imu: ImuModel
    altimeter: AltimeterModel
    star_tracker: StarTrackerModel
    camera_rng: np.random.Generator

    def camera_frame(self, world: World) -> np.ndarray:
        """Render and corrupt one camera frame, (H, W) uint8."""
        return apply_detector_noise(world.render_signal(), world.camera_cfg, self.camera_rng)


def build_sensors(scenario: Scenario) -> SensorSuite:
    s = scenario.sensors
    return SensorSuite(
        imu=ImuModel(s.imu, component_rng(scenario.seed, "imu")),
        altimeter=AltimeterModel(s.altimeter, component_rng(scenario.seed, "altimeter")),
        star_tracker=StarTrackerModel(s.star_tracker, component_rng(scenario.seed, "star_tracker")),
        camera_rng=component_rng(scenario.seed, "camera"),
    )


def place_above_target(world: World, altitude_m: float) -> None:
    """Put the lander level and at rest with its camera ``altitude_m`` above the target."""
    r_BL_L = np.array([0.0, 0.0, altitude_m]) - world.camera_position_B
    world.reset(r_BL_L, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
