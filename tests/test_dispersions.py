"""Dispersions reach the simulation, and per-case seeds are independent of the campaign's size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pydantic import BaseModel

from bench.scenario import apply_dispersions, case_seeds
from bench.sim.run import build_flight_software, run
from bench.scenario import ScenarioError, load_scenario
from bench.sim.world_builder import build_sensors, build_world
from tests.conftest import SMALL_SET


def test_case_seeds_do_not_depend_on_the_number_of_cases():
    a, b = case_seeds(42, 5), case_seeds(42, 50)
    assert a == b[:5] and len(set(b)) == 50
    assert case_seeds(43, 5) != a
    assert all(0 <= s < 2**63 for s in b)


def test_draws_follow_their_distributions():
    sc = load_scenario(None, ['dispersions."lander.dry_mass_kg"={dist="normal", sigma=20.0}',
                              'dispersions."sun.elevation_deg"={dist="uniform", low=20.0, high=40.0}',
                              'dispersions."lander.propellant_kg"={dist="truncnorm", sigma=10.0, low=-5.0, high=15.0}',
                              'dispersions."initial.r_BL_L_m"={dist="normal", sigma=[1.0, 2.0, 0.0]}',
                              'dispersions."terrain.seed"={dist="integers", low=5, high=9}',
                              'dispersions."guidance.law"={dist="choice", values=["apollo", "zem_zev"]}'])
    nominal = sc.model_copy()
    draws = [apply_dispersions(sc, np.random.default_rng(k))[1] for k in range(400)]
    mass = np.array([d["lander.dry_mass_kg"] for d in draws]) - nominal.lander.dry_mass_kg
    assert abs(mass.mean()) < 3.0 and abs(mass.std() - 20.0) < 2.5
    el = np.array([d["sun.elevation_deg"] for d in draws])
    assert el.min() >= 20.0 and el.max() <= 40.0 and abs(el.mean() - 30.0) < 1.0
    prop = np.array([d["lander.propellant_kg"] for d in draws]) - nominal.lander.propellant_kg
    assert prop.min() >= -5.0 and prop.max() <= 15.0
    r = np.array([d["initial.r_BL_L_m"] for d in draws]) - np.array(nominal.initial.r_BL_L_m)
    assert np.allclose(r.std(axis=0), [1.0, 2.0, 0.0], atol=0.2)
    seeds = {d["terrain.seed"] for d in draws}
    assert seeds == {5, 6, 7, 8, 9}
    assert {d["guidance.law"] for d in draws} == {"apollo", "zem_zev"}


def test_dispersed_values_are_the_live_simulated_values():
    # Not just drawn numbers: the world, sensors and engine that are built run with them.
    sc = load_scenario(None, SMALL_SET + ["seed=5"])
    case, drawn = apply_dispersions(sc)
    assert case.dispersions == {} and drawn
    world = build_world(case)
    m = world.model
    assert m.body("lander").mass[0] == pytest.approx(drawn["lander.dry_mass_kg"])
    assert m.body("tank").mass[0] == pytest.approx(drawn["lander.propellant_kg"])
    np.testing.assert_allclose(world.truth().r_BL_L, drawn["initial.r_BL_L_m"])
    np.testing.assert_allclose(world.truth().v_BL_L, drawn["initial.v_BL_L_mps"])
    el, az = math.radians(drawn["sun.elevation_deg"]), math.radians(drawn["sun.azimuth_deg"])
    sun_to = -np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
    np.testing.assert_allclose(m.light("sun").dir, sun_to, atol=1e-6)
    out = world.propulsion.apply(5000.0, np.zeros(3), 1, 0.002)
    assert out.thrust_N == pytest.approx(5000.0 * (1 + drawn["lander.engine.thrust_error_frac"]))
    sensors = build_sensors(case)
    assert sensors.imu.cfg.accel_noise_density == drawn["sensors.imu.accel_noise_density"]
    assert case.terrain_seed() == drawn["terrain.seed"]
    world.close()


def test_bad_dispersions_give_one_line_errors():
    for sets, needle in (
        (['dispersions."lander.dry_mas_kg"={dist="normal", sigma=1.0}'], "no such scenario field"),
        (['dispersions."name"={dist="normal", sigma=1.0}'], "not numeric"),
        (['dispersions."initial.r_BL_L_m"={dist="normal", sigma=[1.0, 2.0]}'], "3"),
        (['dispersions."sun.elevation_deg"={dist="uniform", low=40.0, high=20.0}'], "low"),
        (['dispersions."sun.elevation_deg"={dist="gauss", sigma=1.0}'], "dist"),
        # A table drawn whole replaced the fields other paths draw into (a KeyError traceback at draw time).
        (['dispersions."lander.engine"={dist="choice", values=[{thrust_max_N=7000.0}]}'],
         "dispersions.'lander.engine' is a table; disperse its fields one by one"),
        # The budget sets the nominal load before the draw: a drawn budget changed nothing, silently.
        (['dispersions."propellant.nominal_need_kg"={dist="uniform", low=10.0, high=20.0}'],
         "disperse the loaded propellant, 'lander.propellant_kg'"),
        (['dispersions."lander.dry_mass_kg"={dist="uniform", low=-1.7e308, high=1.7e308}'],
         "spans more than the largest float"),  # NumPy's OverflowError at draw time before
        # A field of whole numbers: 2.6-2.9 rounded to 3 every time, outside its own bounds.
        (['dispersions."sim.compute_latency_ticks"={dist="uniform", low=2.6, high=2.9}'],
         "no whole number lies between its bounds"),
        (['dispersions."sim.compute_latency_ticks"={dist="uniform", low=0.0, high=1e30}'],
         "bounds beyond the 64-bit whole numbers"),
        (['dispersions."knowledge.lander.dry_mass_kg"={dist="normal", sigma=10.0}'],
         "knowledge.lander is the nominal lander the campaign pins for the flight software"),
    ):
        with pytest.raises(ScenarioError) as exc:
            load_scenario(None, sets)
        assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_a_field_of_whole_numbers_draws_each_one_in_its_bounds_alike():
    # uniform over [0.5, 3.5] on an integer field: 1, 2 and 3 equally (rounding a continuous draw gave 0 or 4 to
    # the bounds' halves: [0.5, 0.5] drew 0, outside its own bounds); truncnorm stays inside its bounds too.
    sc = load_scenario(None, ['dispersions."sim.compute_latency_ticks"={dist="uniform", low=0.5, high=3.5}',
                              'dispersions."terrain.seed"={dist="integers", low=1, high=1}',
                              'dispersions."sim.t_max_ns"={dist="truncnorm", sigma=1.0, low=0.4, high=1.2}'])
    draws = [apply_dispersions(sc, np.random.default_rng(k))[1] for k in range(600)]
    ticks = np.array([d["sim.compute_latency_ticks"] for d in draws])
    assert set(ticks.tolist()) == {1, 2, 3}
    counts = np.bincount(ticks, minlength=4)[1:]
    from scipy.stats import chisquare
    assert chisquare(counts).pvalue > 0.01, counts  # each a third
    # Offsets 0.4-1.2 ns from the nominal: rounding took the lower part to 0, outside; 1 is the one whole number.
    t_max = np.array([d["sim.t_max_ns"] for d in draws]) - sc.sim.t_max_ns
    assert set(t_max.tolist()) == {1}


SHORT = ["sim.t_max_ns=3_000_000_000", 'vision="off"', "camera.enabled=false"]  # 3 s of flight, no frames


def test_a_single_run_flies_the_nominal_scenario():
    # The bundled default declares dispersions, but `run(scenario)` flies the values as written.
    sc = load_scenario(None, SHORT)
    assert sc.dispersions and sc.initial.r_BL_L_m == (-120.0, 80.0, 500.0)
    tel = run(sc).telemetry
    np.testing.assert_array_equal([tel[f"r_{a}_m"][0] for a in "xyz"], sc.initial.r_BL_L_m)
    np.testing.assert_array_equal([tel[f"v_{a}_mps"][0] for a in "xyz"], sc.initial.v_BL_L_mps)
    assert tel["mass_kg"][0] == sc.lander.wet_mass_kg == tel["fsw_mass_kg"][0]


def _held_values(obj, path="fsw", seen=None, out=None) -> dict[str, object]:
    """Every number, string and array an object graph holds, by attribute path (callables skipped)."""
    seen = set() if seen is None else seen
    out = {} if out is None else out
    if isinstance(obj, (bool, int, float, str, type(None), np.generic)):
        out[path] = obj
        return out
    if isinstance(obj, np.ndarray):
        out[path] = obj.tolist()
        return out
    if id(obj) in seen or callable(obj) and not hasattr(obj, "__dict__"):
        return out
    seen.add(id(obj))
    if isinstance(obj, BaseModel):
        out[path] = obj.model_dump(mode="json")
        return out
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    else:
        names = list(getattr(obj, "__dict__", {})) + [n for n in getattr(type(obj), "__slots__", ()) if hasattr(obj, n)]
        items = ((n, getattr(obj, n)) for n in names)
    for key, value in items:
        if not callable(value) or hasattr(value, "__dict__") and not isinstance(value, type):
            _held_values(value, f"{path}.{key}", seen, out)
    return out


def test_no_dispersed_truth_reaches_the_flight_software():
    # A dispersed case and its nominal scenario give flight software holding identical parameters
    # (same hand-over estimate given to both): the truth's draws stay in the world and the sensors.
    nominal = load_scenario(None, ["seed=11"])
    case, drawn = apply_dispersions(nominal)
    assert case.lander.dry_mass_kg != nominal.lander.dry_mass_kg and case.sensors != nominal.sensors
    r0, v0 = np.array([-100.0, 70.0, 490.0]), np.array([5.0, -4.0, -15.0])
    held_case = _held_values(build_flight_software(case, r0, v0))
    held_nominal = _held_values(build_flight_software(nominal, r0, v0))
    assert len(held_case) > 100  # the walk reached into guidance, control, the filter and the tracker
    assert held_case == held_nominal
    # The walk would see a leak: flight software built from the dispersed lander differs.
    leaky = case.model_copy(update={"knowledge": case.knowledge.model_copy(update={"lander": case.lander})})
    assert _held_values(build_flight_software(leaky, r0, v0)) != held_nominal


def test_dispersed_sensor_specification_stays_out_of_the_flight_software():
    # The sensors' periods and the altimeter's range are what the fault monitor expects of them: a campaign that
    # disperses them (an altimeter of 100-200 m range, a star tracker at another rate, a slower camera) flies a
    # flight software that still holds the nominal specification. It held the drawn values before.
    nominal = load_scenario(None, [
        "seed=11",
        'dispersions."sensors.altimeter.max_range_m"={dist="uniform",low=100.0,high=200.0}',
        'dispersions."sensors.star_tracker.period_ns"={dist="choice",values=[200000000]}',
        'dispersions."camera.period_ns"={dist="choice",values=[400000000]}',
    ])
    case, drawn = apply_dispersions(nominal)
    assert 100.0 <= case.sensors.altimeter.max_range_m <= 200.0 and case.camera.period_ns == 400_000_000
    assert case.sensors.star_tracker.period_ns == 200_000_000 != nominal.sensors.star_tracker.period_ns
    r0, v0 = np.array([-100.0, 70.0, 490.0]), np.array([5.0, -4.0, -15.0])
    fsw_case, fsw_nominal = build_flight_software(case, r0, v0), build_flight_software(nominal, r0, v0)
    spec = fsw_case.fdir.spec
    assert spec.altimeter_max_range_m == nominal.sensors.altimeter.max_range_m
    assert spec.star_tracker_period_ns == nominal.sensors.star_tracker.period_ns
    assert spec.camera_period_ns == nominal.camera.period_ns
    assert _held_values(fsw_case) == _held_values(fsw_nominal)
    assert case.knowledge.sensors == nominal.sensors  # pinned, and written into the case's scenario.toml


def test_mass_gauge_starts_from_the_nominal_and_drifts_with_the_thrust_error():
    # The idealised actuators deliver (1 + err) times the command at once and the RCS burns nothing, so the
    # gap is the thrust error's alone, in closed form (the realistic engine's lag and RCS add their own).
    nominal = load_scenario(None, SHORT + ["seed=3", 'realism="ideal"'])
    case, drawn = apply_dispersions(nominal)
    err = drawn["lander.engine.thrust_error_frac"]
    assert abs(err) > 1e-3
    tel = run(case).telemetry
    fsw, truth = tel["fsw_mass_kg"], tel["mass_kg"]
    # At hand-over: the flight software's mass is the nominal one, off the truth by the drawn dispersions.
    assert fsw[0] == pytest.approx(nominal.lander.wet_mass_kg, abs=1e-9)
    assert fsw[0] - truth[0] == pytest.approx(-(drawn["lander.dry_mass_kg"] - nominal.lander.dry_mass_kg)
                                               - (drawn["lander.propellant_kg"] - nominal.lander.propellant_kg),
                                               abs=1e-9)
    # Then the gauge burns the commanded thrust, the engine (1 + err) times it: the gap grows by
    # err * thrust * dt / (Isp g0), summed over the control periods flown so far.
    isp_g0 = nominal.lander.engine.isp_s * 9.80665
    dt = np.diff(tel["t_s"])
    expected = np.concatenate([[0.0], np.cumsum(err * tel["thrust_cmd_N"][:-1] * dt / isp_g0)])
    np.testing.assert_allclose((fsw - truth) - (fsw[0] - truth[0]), expected, rtol=1e-6, atol=1e-9)
    assert abs(expected[-1]) > 1e-3  # it did drift


def test_filter_noise_model_is_the_specification_the_top_of_each_dispersed_range():
    sc = load_scenario()
    est = sc.estimator
    spec = {
        "sensors.imu.accel_noise_density": est.accel_noise_density,
        "sensors.imu.accel_bias_sigma": est.init_accel_bias_sigma_mps2,
        "sensors.altimeter.noise_sigma_m": est.altimeter_noise_sigma_m,
        "sensors.star_tracker.noise_sigma_arcsec": est.attitude_sigma_arcsec,
    }
    for path, value in spec.items():
        d = sc.dispersions[path]
        assert d.dist == "uniform" and value == d.high, (path, value, d)


@pytest.mark.parametrize(
    "spec, needle",
    [
        ('{dist="normal", sigma=-5.0}', "normal sigma = -5.0 must be >= 0"),
        ('{dist="normal", sigma=[1.0, -1.0, 0.0]}', "must be >= 0"),
        ('{dist="truncnorm", sigma=0.0, low=-1.0, high=1.0}', "truncnorm sigma = 0.0 must be > 0"),
    ],
)
def test_a_negative_or_degenerate_sigma_is_refused(spec, needle):
    path = "initial.r_BL_L_m" if "[" in spec else "sun.elevation_deg"
    with pytest.raises(ScenarioError, match=needle):
        load_scenario(None, [f'dispersions."{path}"={spec}'])
