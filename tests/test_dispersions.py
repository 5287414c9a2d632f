"""Dispersions reach the simulation, and per-case seeds are independent of the campaign's size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.dispersions import apply_dispersions, case_seeds
from bench.scenario import ScenarioError, load_scenario
from bench.world_builder import build_sensors, build_world
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
    ):
        with pytest.raises(ScenarioError) as exc:
            load_scenario(None, sets)
        assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_a_single_run_flies_the_nominal_scenario():
    # The bundled default declares dispersions, but `run(scenario)` uses the values as written.
    sc = load_scenario()
    assert sc.dispersions and sc.initial.r_BL_L_m == (-120.0, 80.0, 500.0)
