"""The scenario: one typed, validated description of a landing, seed included.

A scenario is loaded from TOML (or the bundled default), patched by
``--set a.b=value`` overrides, and validated by pydantic models with
``extra="forbid"``. Every field carries its unit in its name or description.

Time is an integer number of nanoseconds. Every periodic component (IMU,
altimeter, star tracker, camera, control) must run at a whole multiple of the
physics step, checked here at load time, as dm_control's ``compute_n_steps``
does: a rate that does not divide evenly would otherwise be silently rounded.

Any user mistake surfaces as :class:`ScenarioError`, whose message is one line
naming the field, the bad value and what is allowed.
"""

from __future__ import annotations

import math
import re
import tomllib
from typing import Literal
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from bench.scenario.dispersions import Dispersion, check_dispersion_paths, draw_dispersions
from bench.scenario.hazard import HazardSettings, check_scan_plan
from gnc.config import bool_for_number, format_validation_error
from gnc.control import ControlConfig
from gnc.estimator import EstimatorConfig, local_site_config
from gnc.fdir import FdirConfig
from gnc.guidance import GuidanceConfig
from gnc.map_nav import MapNavConfig
from gnc.vision_nav import VisionNavConfig
from vision.tracker import TrackerConfig
from models.camera import CameraConfig
from models.lander import CONTACT_TIMECONST_S, LanderConfig
from models.sensors import SensorsConfig
from models.orbital_map import OrbitalMapConfig
from models.terrain import TerrainConfig
from models.sun import SunConfig  # not models.world: a scenario loads without MuJoCo
from models.faults import FaultConfig, check_fault

NS_PER_S = 1_000_000_000
DEFAULT_SCENARIO = "default.toml"


class ScenarioError(ValueError):
    """A scenario file, override or value is invalid (one-line message)."""


T_MAX_NS_MAX = 10**15  # longest run, and longest period of any component [ns] (1e6 s; int64 holds 9.2e18)


class SimConfig(BaseModel):
    """Simulation clock and world constants."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    physics_dt_ns: int = Field(2_000_000, gt=0, description="physics step [ns] (default 500 Hz)")
    control_period_ns: int = Field(20_000_000, gt=0, description="flight-software control period [ns] (default 50 Hz)")
    t_max_ns: int = Field(240 * NS_PER_S, gt=0, le=T_MAX_NS_MAX,
                          description="time limit of a run [ns] (at most 1e6 s)")
    gravity_mps2: float = Field(1.62, gt=0, description="surface gravity [m/s^2]")
    compute_latency_ticks: int = Field(
        1, ge=0, le=10,
        description="flight-computer latency in control periods: commands computed at tick k act from tick k + "
                    "latency (realism = 'realistic'; 'ideal' acts at once) [-]",
    )


class PropellantBudget(BaseModel):
    """The default propellant load (realism = 'realistic', when ``lander.propellant_kg`` is not set).

    load = ``nominal_need_kg`` + the reserve: ``reserve_hover_s`` of hover at landing mass,
    ``R = t g m_dry / (Isp g0 - t g)`` (the hover flow ``g (m_dry + R) / (Isp g0)`` for ``t``).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    nominal_need_kg: float = Field(
        72.0, ge=0, description="propellant a nominal descent from the default 500 m start uses [kg]"
    )
    reserve_hover_s: float = Field(60.0, ge=0, description="reserve, as seconds of hover at landing mass [s]")

    def reserve_kg(self, lander: LanderConfig, gravity_mps2: float) -> float:
        """The reserve [kg] for a lander (its dry mass and Isp) at a surface gravity."""
        t, g, isp_g0 = self.reserve_hover_s, gravity_mps2, lander.engine.isp_s * 9.80665
        if t * g >= isp_g0:
            raise ValueError(f"propellant.reserve_hover_s = {t} is beyond what any load can hover at a gravity of {g:g} "
                             f"m/s^2 with an Isp of {lander.engine.isp_s:g} s (sim.gravity_mps2, lander.engine.isp_s); "
                             f"allowed: < {isp_g0 / g:.3g} s")
        return t * g * lander.dry_mass_kg / (isp_g0 - t * g)

    def load_kg(self, lander: LanderConfig, gravity_mps2: float) -> float:
        """The default load [kg]: nominal need plus reserve."""
        return self.nominal_need_kg + self.reserve_kg(lander, gravity_mps2)


class InitialState(BaseModel):
    """Lander state at hand-over, in the landing frame L (x east, y north, z up)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    r_BL_L_m: tuple[float, float, float] = Field(
        (-120.0, 80.0, 500.0), description="body position relative to the target [m]"
    )
    v_BL_L_mps: tuple[float, float, float] = Field((6.0, -4.0, -15.0), description="body velocity [m/s]")
    euler_LB_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="attitude as extrinsic x-y-z (roll, pitch, yaw) angles, body to L [deg]"
    )
    omega_B_radps: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="body rate in B [rad/s]")

    def q_LB(self) -> np.ndarray:
        """Initial attitude quaternion, scalar-first (4,)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_euler("xyz", self.euler_LB_deg, degrees=True).as_quat(scalar_first=True)


# A landing criterion's largest speed: beyond it a touchdown is a crash whatever the table says (landing legs
# are built for a few m/s; 1e9 m/s counted a 17 m/s impact as landed) [m/s].
LANDING_SPEED_MAX_MPS = 10.0


class LandingCriteria(BaseModel):
    """What counts as a safe landing (checked at first footpad contact and after settling)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    v_vertical_max_mps: float = Field(1.0, gt=0, le=LANDING_SPEED_MAX_MPS,
                                      description="largest vertical speed at touchdown [m/s]")
    v_horizontal_max_mps: float = Field(0.5, gt=0, le=LANDING_SPEED_MAX_MPS,
                                        description="largest horizontal speed at touchdown [m/s]")
    tilt_max_deg: float = Field(10.0, gt=0, lt=90, description="largest tilt from vertical at touchdown and after settling [deg]")
    settle_s: float = Field(5.0, ge=0, description="time after touchdown the lander must stay upright [s]")


class KnowledgeConfig(BaseModel):
    """What the flight software knows of its vehicle, and how wrong that knowledge is.

    The flight software is built from the **nominal** vehicle, camera and
    sensors, never from a campaign case's drawn values: a campaign pins
    ``lander``, ``camera`` and ``sensors`` here to the nominal ones before it
    disperses the truth. A single run leaves them unset, and the flight software
    then knows the scenario's own (nominal) lander, camera and sensors. The error fields model what a real team gets
    wrong on top (mass properties measured on the ground, engine calibration);
    they can be dispersed like any other field.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    lander: LanderConfig | None = Field(
        None, description="the vehicle the flight software was built for; unset: the scenario's lander"
    )
    camera: CameraConfig | None = Field(
        None, description="the camera calibration the flight software holds; unset: the scenario's camera"
    )
    sensors: SensorsConfig | None = Field(
        None, description="the sensors' specification the flight software holds (their periods, the altimeter's "
                          "range); unset: the scenario's sensors"
    )
    dry_mass_error_kg: float = Field(0.0, description="flight software's dry-mass estimate minus the nominal [kg]")
    propellant_error_kg: float = Field(
        0.0, description="flight software's loaded-propellant estimate minus the nominal [kg]"
    )
    inertia_error_frac: float = Field(
        0.0, gt=-0.5, lt=0.5, description="fractional error of the flight software's dry inertia [-]"
    )
    thrust_calibration_error_frac: float = Field(
        0.0, gt=-0.5, lt=0.5,
        description="the flight software believes the engine delivers command * (1 + this) [-]",
    )


class Scenario(BaseModel):
    """A complete landing scenario. ``run(scenario) -> result`` is a pure function of it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field("default", description="free-form scenario name")
    seed: int = Field(1, ge=0, lt=2**63,
                      description="master seed; every random stream is spawned from it (below 2^63: results store "
                                  "it as a 64-bit integer)")
    nav: Literal["truth", "estimator"] = Field(
        "estimator", description="navigation given to guidance: the truth state, or the filter's estimate"
    )
    tracks: Literal["vision", "truth"] = Field(
        "vision", description="feature tracks from the paper's tracker on rendered frames, or exact truth tracks"
    )
    vision: Literal["on", "off"] = Field("on", description="use vision velocity measurements ('off': IMU + altimeter)")
    nav_map: Literal["off", "on"] = Field(
        "off",
        description="map-relative navigation: position fixes of camera frames against the onboard map "
                    "([onboard_map], [map_nav]); 'off' flies exactly as without it",
    )
    realism: Literal["realistic", "ideal"] = Field(
        "realistic",
        description="'realistic': engine lag, slew limit, misalignment and centre-of-mass offset, PWM RCS with "
                    "propellant, anisotropic star tracker, compute latency, thrust projected on the body axis and the "
                    "propellant budget; 'ideal': the idealised vehicle and flight computer (results as before issue 17; studies may select it)",
    )
    propellant: PropellantBudget = PropellantBudget()
    sim: SimConfig = SimConfig()
    terrain: TerrainConfig = TerrainConfig()
    sun: SunConfig = SunConfig()
    lander: LanderConfig = LanderConfig()
    initial: InitialState = InitialState()
    sensors: SensorsConfig = SensorsConfig()
    camera: CameraConfig = CameraConfig()
    guidance: GuidanceConfig = GuidanceConfig()
    control: ControlConfig = ControlConfig()
    landing: LandingCriteria = LandingCriteria()
    estimator: EstimatorConfig = EstimatorConfig()
    tracker: TrackerConfig = TrackerConfig()
    vision_nav: VisionNavConfig = VisionNavConfig()
    fdir: FdirConfig = FdirConfig()
    knowledge: KnowledgeConfig = KnowledgeConfig()
    onboard_map: OrbitalMapConfig = Field(
        OrbitalMapConfig(),
        description="the onboard map product for map-relative navigation (orbital sun, resolution, noise, "
                    "georeferencing error); see bench.maps",
    )
    map_nav: MapNavConfig = Field(
        MapNavConfig(), description="when the flight software takes map fixes and how it matches (nav_map = 'on')"
    )
    hazard: HazardSettings = Field(
        HazardSettings(), description="hazard detection and avoidance (flash lidar, hazard map, retarget) and "
                                      "touchdown footprint scoring against the fine truth DEM",
    )
    faults: list[FaultConfig] = Field(
        default_factory=list,
        description="truth-side faults ([[faults]] tables; models.faults): sensors, camera, engine, flight computer, "
                    "terrain; each with a kind, a trigger, a duration and its parameters",
    )
    dispersions: dict[str, Dispersion] = Field(
        default_factory=dict,
        description="field path -> distribution, drawn per case in Monte Carlo campaigns (a single run flies nominal)",
    )

    @model_validator(mode="after")
    def _propellant_budget(self) -> "Scenario":
        # Realistic: an unset propellant load is the budget (nominal need + reserve); written out, it stays.
        if self.realism == "realistic" and "propellant_kg" not in self.lander.model_fields_set:
            load = self.propellant.load_kg(self.lander, self.sim.gravity_mps2)
            self.lander = self.lander.model_copy(update={"propellant_kg": load})
            self.lander.model_fields_set.add("propellant_kg")
        return self

    @model_validator(mode="after")
    def _rates_divide(self) -> "Scenario":
        dt = self.sim.physics_dt_ns
        dt_max = int(CONTACT_TIMECONST_S * NS_PER_S) // 2
        if dt > dt_max:
            raise ValueError(
                f"sim.physics_dt_ns = {dt} is too large for stable contacts: MuJoCo needs the contact time "
                f"constant ({CONTACT_TIMECONST_S * 1e3:g} ms) to be at least twice the step; allowed: <= {dt_max}"
            )
        periods = self.periods_ns()
        if self.nav_map == "on":
            periods["map_nav.period_ns"] = self.map_nav.period_ns
        for name, period in periods.items():
            if period > T_MAX_NS_MAX:  # 1e19 overflowed the int64 clock
                raise ValueError(f"{name} = {period} is longer than any run (at most sim.t_max_ns <= {T_MAX_NS_MAX}); "
                                 f"allowed: <= {T_MAX_NS_MAX}")
            if period % dt:
                lo = max(dt, period // dt * dt)
                raise ValueError(
                    f"{name} = {period} is not a whole multiple of sim.physics_dt_ns = {dt}; "
                    f"allowed: multiples of {dt}, e.g. {lo} or {lo + dt}"
                )
        return self

    @model_validator(mode="after")
    def _one_gravity(self) -> "Scenario":
        g = self.sim.gravity_mps2
        for name, value in (("guidance.gravity_mps2", self.guidance.gravity_mps2),
                            ("control.gravity_mps2", self.control.gravity_mps2),
                            ("estimator.gravity_mps2", self.estimator.gravity_mps2)):
            if value != g:
                raise ValueError(
                    f"{name} = {value} differs from sim.gravity_mps2 = {g}; allowed: the same value "
                    "(the flight software's gravity model is the world's; set them together)"
                )
        return self

    @model_validator(mode="after")
    def _faults_consistent(self) -> "Scenario":
        standing_m = self.lander.footpad_clearance_m
        for i, f in enumerate(self.faults):
            try:
                check_fault(f)
            except ValueError as exc:
                raise ValueError(f"faults.{i}: {exc}") from None
            if f.altitude_m is not None and f.altitude_m < 0.5 * standing_m:  # 0.5 m: never triggered in a landing
                raise ValueError(f"faults.{i}.altitude_m = {f.altitude_m:g} is under half the body origin's height "
                                 f"standing on level ground ({standing_m:g} m, lander.leg_drop_m + footpad_radius_m): "
                                 f"a landing never brings it that low (a crash might); allowed: altitude_m >= "
                                 f"{0.5 * standing_m:g} (about {standing_m:g}: at touchdown), or a t_s or phase trigger")
            t0 = f.trigger_time_ns()
            if t0 is not None and t0 >= self.sim.t_max_ns:
                given = f"t_s = {f.t_s:g} s" if f.t_s is not None else f"t_ns = {f.t_ns}"
                raise ValueError(f"faults.{i}.{given} is at or after the run's end "
                                 f"(sim.t_max_ns = {self.sim.t_max_ns}), so the fault would never act; allowed: "
                                 f"a trigger before {self.sim.t_max_ns / 1e9:g} s, or a longer sim.t_max_ns")
            if f.kind in ("misalignment", "stuck_throttle") and t0 is not None:
                # One thrust line and one held command at a time: a second that overlaps acts not at all.
                end = f.end_ns(t0)
                for j, g in enumerate(self.faults[:i]):
                    g0 = g.trigger_time_ns() if g.kind == f.kind else None
                    g_end = g.end_ns(g0)
                    if g0 is not None and (end is None or g0 < end) and (g_end is None or t0 < g_end):
                        raise ValueError(
                            f"faults.{i}: a second {f.kind} while faults.{j}'s is active (from {g0 / 1e9:g} s"
                            f"{'' if g_end is None else f' to {g_end / 1e9:g} s'}): only the first listed would "
                            f"act; allowed: {f.kind} faults whose windows do not overlap (a duration_s on the first), "
                            "or one of them")
            if f.kind == "terrain_step":
                keep_m = self.terrain.patch_size_m / math.sqrt(2.0)  # the target and its texture patch stay as they are
                if math.hypot(*f.center_xy_m) - f.radius_m <= keep_m:
                    raise ValueError(
                        f"faults.{i}.center_xy_m = {list(f.center_xy_m)} with radius_m = {f.radius_m}: the step reaches "
                        f"within {keep_m:.1f} m of the target (its texture patch); allowed: "
                        f"|center_xy_m| - radius_m > {keep_m:.1f} m")
        return self

    @model_validator(mode="after")
    def _dispersions_name_fields(self) -> "Scenario":
        if self.dispersions:
            check_dispersion_paths(self.model_dump(mode="json"), self.dispersions)
        return self

    @model_validator(mode="after")
    def _vision_needs_camera(self) -> "Scenario":
        if self.vision == "on" and self.tracks == "vision" and not self.camera.enabled:
            raise ValueError(
                "vision = 'on' with tracks = 'vision' needs camera.enabled = true; allowed: enable the camera, "
                "or set tracks = 'truth' or vision = 'off'"
            )
        return self

    @model_validator(mode="after")
    def _map_nav_needs_camera_and_map(self) -> "Scenario":
        if self.nav_map == "on":
            if not self.camera.enabled:
                raise ValueError("nav_map = 'on' needs camera.enabled = true; allowed: enable the camera, or "
                                 "set nav_map = 'off'")
            if self.nav != "estimator":
                raise ValueError(f"nav_map = 'on' with nav = '{self.nav}': map fixes update the filter; allowed: "
                                 "nav = 'estimator', or nav_map = 'off'")
            size = self.terrain.size_m if self.terrain.kind == "procedural" else None
            if size is not None and self.onboard_map.size_m > size:
                raise ValueError(f"onboard_map.size_m = {self.onboard_map.size_m} is larger than the terrain "
                                 f"(terrain.size_m = {size}); allowed: at most {size}")
            if self.map_nav.period_ns % self.camera.period_ns:
                raise ValueError(f"map_nav.period_ns = {self.map_nav.period_ns} is not a whole multiple of "
                                 f"camera.period_ns = {self.camera.period_ns}; allowed: multiples of it")
            local_site_config(self.estimator)  # the regional relief the filter carries with map fixes
        return self

    @model_validator(mode="after")
    def _hazard_needs_procedural_terrain(self) -> "Scenario":
        if self.hazard.scored and self.terrain.kind != "procedural":
            raise ValueError(f"hazard.avoidance = '{self.hazard.avoidance}', hazard.scoring = "
                             f"'{self.hazard.scoring}' with terrain.kind = '{self.terrain.kind}': the fine truth DEM "
                             "needs a procedural terrain; allowed: terrain.kind = 'procedural', or both 'off'")
        if self.hazard.avoidance == "on" and self.nav != "estimator":
            raise ValueError(f"hazard.avoidance = 'on' with nav = '{self.nav}': the flight software maps hazards "
                             "through its own estimate; allowed: nav = 'estimator', or hazard.avoidance = 'off'")
        check_scan_plan(self.hazard, self.guidance.gate_altitude_m, self.terrain.size_m, self.initial.r_BL_L_m)
        return self

    def periods_ns(self) -> dict[str, int]:
        """Every periodic component's period, by field path [ns]."""
        return {
            "sim.control_period_ns": self.sim.control_period_ns,
            "sensors.imu.period_ns": self.sensors.imu.period_ns,
            "sensors.altimeter.period_ns": self.sensors.altimeter.period_ns,
            "sensors.star_tracker.period_ns": self.sensors.star_tracker.period_ns,
            "camera.period_ns": self.camera.period_ns,
            **({"lander.rcs.pwm_period_ns": self.lander.rcs.pwm_period_ns}
               if self.realism == "realistic" and self.lander.rcs.mode == "pwm" else {}),
        }

    def nominal_lander(self) -> LanderConfig:
        """The lander the flight software was built for (``knowledge.lander``, else ``lander``)."""
        return self.knowledge.lander if self.knowledge.lander is not None else self.lander

    def nominal_camera(self) -> CameraConfig:
        """The camera calibration the flight software holds (``knowledge.camera``, else ``camera``)."""
        return self.knowledge.camera if self.knowledge.camera is not None else self.camera

    def nominal_sensors(self) -> SensorsConfig:
        """The sensors' specification the flight software holds (``knowledge.sensors``, else ``sensors``)."""
        return self.knowledge.sensors if self.knowledge.sensors is not None else self.sensors

    def terrain_seed(self) -> int:
        """The terrain's seed: its own when set, else derived from the master seed."""
        return self.terrain.seed if self.terrain.seed is not None else self.seed


# --------------------------------------------------------------------------- loading
def _parse_value(text: str) -> Any:
    """Parse an override value as a TOML value; bare words fall back to strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _split_key(key: str) -> list[str] | None:
    """Parts of a TOML dotted key (quoted parts may hold dots), or None if it is not one."""
    try:
        node: Any = tomllib.loads(f"{key} = 0")
    except tomllib.TOMLDecodeError:
        return None
    parts = []
    while isinstance(node, dict) and len(node) == 1:
        (part, node), = node.items()
        parts.append(part)
    return parts


def apply_override(data: dict[str, Any], assignment: str) -> None:
    """Apply one ``a.b.c=value`` override to a nested dict in place.

    Raises:
        ScenarioError: Malformed assignment or a path through a non-table.
    """
    key, sep, value = assignment.partition("=")
    key = key.strip()
    parts = _split_key(key) if sep and key else None
    if not parts:
        raise ScenarioError(
            f"--set {assignment!r}: expected KEY=VALUE with a dotted key, e.g. --set seed=7 or --set sun.elevation_deg=20"
        )
    node = data
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ScenarioError(
                f"--set {assignment!r}: '{'.'.join(parts[: i + 1])}' is a value, not a table; it has no field '{parts[i + 1]}'"
            )
        node = child
    node[parts[-1]] = _parse_value(value.strip())


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(f"scenario file {str(path)!r} does not exist; give an existing .toml file or none for the default") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"scenario file {str(path)!r} cannot be read as UTF-8 text: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"scenario file {str(path)!r} is not valid TOML: {exc}") from None


def default_scenario_text() -> str:
    """Text of the bundled default scenario."""
    return resources.files("bench.scenario").joinpath(DEFAULT_SCENARIO).read_text(encoding="utf-8")


def scenario_from_dict(data: dict[str, Any]) -> Scenario:
    """Validate a plain dict into a Scenario, raising a one-line ScenarioError."""
    if (line := bool_for_number(Scenario, data)) is not None:
        raise ScenarioError(line)  # pydantic's lax mode would take true for 1
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(format_validation_error(err, Scenario)) from None


def apply_dispersions(scenario: Scenario, rng: np.random.Generator | None = None) -> tuple[Scenario, dict[str, Any]]:
    """Draw every dispersion and return the dispersed, re-validated scenario.

    The draws are :func:`bench.scenario.dispersions.draw_dispersions`; the
    validation is here, so the dispersions module never imports the schema.

    Args:
        scenario: The nominal scenario (its ``dispersions`` table says what to draw).
        rng: The draws' generator; by default the scenario's own "dispersions" stream.

    Returns:
        (the dispersed scenario, {path: drawn value}). The dispersed scenario
        keeps its seed and has an empty ``dispersions`` table (it is one case).
    """
    data, drawn = draw_dispersions(scenario, rng)
    return scenario_from_dict(data), drawn


def load_scenario(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
                  preset: str | None = None) -> Scenario:
    """Load a scenario file (or the bundled default), lay a named preset over it and apply overrides.

    Relative paths inside the file (``terrain.dem_path``) are resolved against
    the file's folder, so a scenario can travel with its DEM.

    Args:
        path: TOML file, or None for the bundled default.
        overrides: ``a.b=value`` assignments, applied in order (after the preset).
        preset: A named layer of :mod:`bench.scenario.presets` (``--preset``), or None.

    Returns:
        The validated scenario.

    Raises:
        ScenarioError: One line naming the field, the bad value and what is allowed.
    """
    data, base = read_scenario_data(path)
    return scenario_from_data(data, base, overrides, preset)


def read_scenario_data(path: str | Path | None) -> tuple[dict[str, Any], Path]:
    """The raw TOML table of a scenario file (or the bundled default) and the folder its relative paths start from.

    Raises:
        ScenarioError: The file is missing, unreadable or not TOML.
    """
    if path is None:
        return tomllib.loads(default_scenario_text()), Path.cwd()
    path = Path(path)
    # Absolute: a relative dem_path resolved against it is written back into scenario.toml absolute, so that
    # the written scenario reruns from any folder (a relative base gave 'runs/g_rel/geo/good.tif': not found).
    return _read_toml(path), path.resolve().parent


def scenario_from_data(data: dict[str, Any], base: Path, overrides: list[str] | tuple[str, ...] = (),
                       preset: str | None = None) -> Scenario:
    """Lay a preset over a raw scenario table, apply overrides, resolve ``terrain.dem_path`` against ``base``, validate.

    ``data`` is copied, not changed. (``landbench sweep`` takes its ``[sweep]`` table out of the file first.)
    """
    import copy

    from bench.scenario.presets import apply_preset

    data = apply_preset(data, preset) if preset is not None else copy.deepcopy(data)
    for assignment in overrides:
        apply_override(data, assignment)
    dem = data.get("terrain", {}).get("dem_path") if isinstance(data.get("terrain"), dict) else None
    if isinstance(dem, str) and dem and not Path(dem).is_absolute():
        data["terrain"]["dem_path"] = str(base / dem)
    return scenario_from_dict(data)


# --------------------------------------------------------------------------- writing
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v) or math.isinf(v):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):  # an inline table (the entries of [[faults]]); None fields are omitted
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(key: str) -> str:
    """A TOML key, quoted unless it is a bare key (dotted field paths must be quoted)."""
    return key if _BARE_KEY.match(key) else _toml_value(key)


def _toml_lines(table: dict[str, Any], prefix: str) -> list[str]:
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in table.items() if not isinstance(v, dict) and v is not None]
    for k, v in table.items():
        if isinstance(v, dict):
            name = f"{prefix}.{_toml_key(k)}" if prefix else _toml_key(k)
            lines += ["", f"[{name}]", *_toml_lines(v, name)]
    return lines


def scenario_to_toml(scenario: Scenario) -> str:
    """Serialise the fully resolved scenario to TOML that loads back to an equal scenario.

    ``None`` fields are omitted (TOML has no null); they load back as their default, None.
    """
    data = scenario.model_dump(mode="json")
    return "\n".join(_toml_lines(data, "")).lstrip("\n") + "\n"
