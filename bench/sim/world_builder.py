"""Build the truth world and its sensors from a scenario (bench owns truth).

Workers in a campaign call these with (scenario) alone: MuJoCo and GL objects
are built where they are used and never pickled.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from bench.scenario import Scenario, ScenarioError
from bench.scenario.seeding import component_rng, component_seed
from bench.sim.terrain_cache import cached_terrain
from models.camera import apply_detector_noise, detector_normal
from models.faults import FaultInjector, terrain_step_heights
from models.render_context import free_shared_contexts
from models.sensors import AltimeterModel, ImuModel, StarTrackerModel
from models.terrain import Terrain, generate_terrain
from models.world import World


def generate_scenario_terrain(scenario: Scenario) -> Terrain:
    """Generate (or load) the scenario's terrain from its own stream, always anew (no cache)."""
    return generate_terrain(
        scenario.terrain,
        component_rng(scenario.terrain_seed(), "terrain"),
        sun_elevation_deg=scenario.sun.elevation_deg,
        sun_azimuth_deg=scenario.sun.azimuth_deg,
    )


# Process-level cache of procedural terrains. A procedural terrain is a pure,
# deterministic function of (terrain configuration, terrain seed, sun
# direction), and a Terrain is immutable (frozen, read-only arrays), so runs
# in one process that fly over the same terrain share one generation (the
# default 4096^2 tile takes seconds). Terrains loaded from a DEM file are not
# cached: the file may change between runs. In a long process the least recently used
# terrains are dropped once the cached arrays pass TERRAIN_CACHE_MAX_BYTES
# (the default 4096^2 tile with its patch is about 21 MB). A campaign worker, which
# flies many cases in turn, clears it before each case.
TERRAIN_CACHE_MAX_BYTES = 160 * 2**20
_terrain_cache: OrderedDict[tuple, Terrain] = OrderedDict()
_terrain_cache_lock = threading.Lock()


def _terrain_key(scenario: Scenario) -> tuple | None:
    cfg = scenario.terrain
    if cfg.kind != "procedural":
        return None
    return (cfg.model_dump_json(), scenario.terrain_seed(), float(scenario.sun.elevation_deg),
            float(scenario.sun.azimuth_deg))


def _terrain_bytes(terrain: Terrain) -> int:
    arrays = [terrain.height_m, terrain.albedo, terrain.craters, terrain.boulders]
    if terrain.patch is not None:
        arrays += [terrain.patch.height_m, terrain.patch.albedo]
    return sum(a.nbytes for a in arrays)


def build_terrain(scenario: Scenario) -> Terrain:
    """The scenario's terrain: generated from its own stream, or the same one generated earlier.

    Bit-identical to :func:`generate_scenario_terrain`. Procedural terrains are
    cached in this process and on disk (:mod:`bench.sim.terrain_cache`), keyed on
    everything that generates them.
    """
    return with_terrain_steps(_build_terrain(scenario), scenario)


def with_terrain_steps(terrain: Terrain, scenario: Scenario) -> Terrain:
    """The terrain with the scenario's ``terrain_step`` faults added (the same object when there are none)."""
    steps = [f for f in scenario.faults if f.kind == "terrain_step"]
    if not steps:
        return terrain
    return dataclasses.replace(terrain, height_m=terrain_step_heights(terrain.height_m, terrain.size_m, steps))


def _build_terrain(scenario: Scenario) -> Terrain:
    key = _terrain_key(scenario)
    if key is None:
        return generate_scenario_terrain(scenario)
    with _terrain_cache_lock:
        terrain = _terrain_cache.get(key)
        if terrain is not None:
            _terrain_cache.move_to_end(key)
            return terrain

    def generate() -> Terrain:
        # A terrain to generate is one no idle render context holds: free the idle GL context (about
        # 120 MB with llvmpipe, which a reused campaign worker keeps from its last case) before the
        # generator's temporary arrays, so that the worker peaks about as a fresh process would.
        free_shared_contexts()
        return generate_scenario_terrain(scenario)

    terrain = cached_terrain(scenario.terrain, scenario.terrain_seed(), float(scenario.sun.elevation_deg),
                             float(scenario.sun.azimuth_deg), generate)
    with _terrain_cache_lock:
        _terrain_cache[key] = terrain
        _terrain_cache.move_to_end(key)
        while len(_terrain_cache) > 1 and sum(map(_terrain_bytes, _terrain_cache.values())) > TERRAIN_CACHE_MAX_BYTES:
            _terrain_cache.popitem(last=False)
    return terrain


def clear_terrain_cache() -> None:
    """Forget the cached terrains (for benchmarks and tests)."""
    with _terrain_cache_lock:
        _terrain_cache.clear()


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
        realism=scenario.realism,
    )
    init = scenario.initial
    check_initial_position(scenario, terrain)
    world.reset(np.array(init.r_BL_L_m), np.array(init.v_BL_L_mps), init.q_LB(), np.array(init.omega_B_radps))
    return world


def check_initial_position(scenario: Scenario, terrain: Terrain) -> None:
    """Refuse a start outside the terrain tile, or with the footpads at or below its surface (one line)."""
    x, y, z = (float(c) for c in scenario.initial.r_BL_L_m)
    half = terrain.size_m / 2.0
    if abs(x) >= half or abs(y) >= half:
        raise ScenarioError(f"initial.r_BL_L_m = {list(scenario.initial.r_BL_L_m)}: the start is outside the "
                            f"{terrain.size_m:g} m terrain tile; give |x|, |y| < {half:g} m (or a larger "
                            f"{'terrain.dem_tile_m, or a larger DEM' if scenario.terrain.kind == 'dem' else 'terrain.size_m'})")
    ground_m = float(terrain.surface_height(x, y))
    need_m = ground_m + scenario.lander.footpad_clearance_m
    if not z > need_m:
        # A terrain_step under the start is the likelier mistake than the start itself: name it too.
        steps = [(i, f) for i, f in enumerate(scenario.faults) if f.kind == "terrain_step"
                 and math.hypot(x - f.center_xy_m[0], y - f.center_xy_m[1]) <= f.radius_m]
        why = "".join(f"; faults.{i} (a terrain_step of {f.height_m:+g} m, radius {f.radius_m:g} m about "
                      f"{list(f.center_xy_m)}) raises it there" for i, f in steps)
        fix = " or a terrain_step that leaves the start clear" if steps else ""
        raise ScenarioError(f"initial.r_BL_L_m = {list(scenario.initial.r_BL_L_m)}: the footpads would start at or "
                            f"below the terrain (ground at {ground_m:.2f} m there{why}); give z > {need_m:.2f} m{fix}")


@dataclass
class SensorSuite:
    """The sensor error models of one run, each on its own stream."""

    imu: ImuModel
    altimeter: AltimeterModel
    star_tracker: StarTrackerModel
    camera_rng: np.random.Generator
    camera_seed: np.random.SeedSequence | None = None
    faults: FaultInjector | None = None  # the scenario's faults (None: none)

    def camera_frame(self, world: World) -> np.ndarray:
        """Render and corrupt one camera frame, (H, W) uint8, with the next draws of the camera's stream."""
        return apply_detector_noise(world.render_signal(), world.camera_cfg, self.camera_rng)

    def frame_rng(self, frame_index: int) -> np.random.Generator:
        """The detector-noise stream of camera frame ``frame_index`` of the run.

        One child stream per frame (``spawn_key`` + (index,)): a frame's noise
        depends only on (seed, frame index), never on which earlier frames were
        rendered, so the closed loop may skip frames that nobody consumes and
        still fly exactly as a run that rendered them all (for a video or a
        recording).
        """
        base = self.camera_seed
        return np.random.Generator(np.random.PCG64(
            np.random.SeedSequence(base.entropy, spawn_key=(*base.spawn_key, int(frame_index)))))

    def camera_frame_at(self, world: World, frame_index: int, exposure_gain: float = 1.0) -> np.ndarray:
        """Render and corrupt camera frame ``frame_index`` of the run, (H, W) uint8 (see :meth:`frame_rng`).

        ``exposure_gain`` multiplies the scene's signal before the detector noise (an ``exposure`` fault).
        The frame's noise is drawn while the GL driver draws the frame (``World.start_frame``).
        """
        cfg = world.camera_cfg
        world.start_frame()
        normal = detector_normal((cfg.height_px, cfg.width_px), cfg, self.frame_rng(frame_index))
        signal = world.render_signal()
        if exposure_gain != 1.0:
            signal = np.clip(signal.astype(np.float32) * np.float32(exposure_gain), 0.0, 255.0)
        return apply_detector_noise(signal, cfg, None, normal)


def build_sensors(scenario: Scenario) -> SensorSuite:
    s = scenario.sensors
    return SensorSuite(
        imu=ImuModel(s.imu, component_rng(scenario.seed, "imu")),
        altimeter=AltimeterModel(s.altimeter, component_rng(scenario.seed, "altimeter")),
        star_tracker=StarTrackerModel(s.star_tracker, component_rng(scenario.seed, "star_tracker"),
                                      anisotropic=scenario.realism == "realistic"),
        camera_rng=component_rng(scenario.seed, "camera"),
        camera_seed=component_seed(scenario.seed, "camera"),
        faults=build_fault_injector(scenario),
    )


def build_fault_injector(scenario: Scenario) -> FaultInjector | None:
    """The run's fault injector, on the "faults" stream (None when the scenario has no faults)."""
    if not scenario.faults:
        return None
    s = scenario.sensors
    imu_dt = s.imu.period_ns / 1e9
    st = s.star_tracker
    st_sigma = st.noise_sigma_arcsec if scenario.realism == "ideal" else math.sqrt(
        (2 * st.cross_boresight_sigma_arcsec**2 + st.about_boresight_sigma_arcsec**2) / 3)
    alt = s.altimeter
    sigmas = {"imu.accel": s.imu.accel_noise_density / math.sqrt(imu_dt),
              "imu.gyro": s.imu.gyro_noise_density / math.sqrt(imu_dt),
              "star_tracker": st_sigma,
              "altimeter": lambda r, a=alt: math.hypot(a.noise_sigma_m, a.noise_frac * r)}
    return FaultInjector(list(scenario.faults), sigmas, component_seed(scenario.seed, "faults"))


def place_above_target(world: World, altitude_m: float) -> None:
    """Put the lander level and at rest with its camera ``altitude_m`` above the target."""
    r_BL_L = np.array([0.0, 0.0, altitude_m]) - world.camera_position_B
    world.reset(r_BL_L, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
