"""Scenario loading, overrides and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenario import Scenario, ScenarioError, load_scenario, scenario_to_toml
from bench.scenario.schema import tomllib  # the same parser users' files go through


def test_default_loads_and_round_trips_through_toml(tmp_path):
    sc = load_scenario()
    assert sc.seed == 1 and sc.name == "default"
    text = scenario_to_toml(sc)
    f = tmp_path / "resolved.toml"
    f.write_text(text)
    assert load_scenario(f) == sc


def test_overrides_set_nested_fields_and_seed():
    sc = load_scenario(None, ["seed=7", "sun.elevation_deg=12.5", "camera.width_px=320", "sun.shadows=true",
                              "initial.r_BL_L_m=[1.0, 2.0, 300.0]", "name=trial"])
    assert sc.seed == 7 and sc.sun.elevation_deg == 12.5 and sc.camera.width_px == 320 and sc.sun.shadows
    assert sc.initial.r_BL_L_m == (1.0, 2.0, 300.0) and sc.name == "trial"


def test_terrain_seed_follows_master_seed_unless_set():
    assert load_scenario(None, ["seed=9"]).terrain_seed() == 9
    assert load_scenario(None, ["seed=9", "terrain.seed=4"]).terrain_seed() == 4


def _err(overrides=(), path=None) -> str:
    with pytest.raises(ScenarioError) as exc:
        load_scenario(path, list(overrides))
    msg = str(exc.value)
    assert "\n" not in msg, "errors must be one line"
    return msg


def test_unknown_key_names_the_field_and_what_is_allowed():
    msg = _err(["lander.dry_mas_kg=100"])
    assert "lander.dry_mas_kg" in msg and "dry_mass_kg" in msg


def test_wrong_type_names_field_value_and_expectation():
    msg = _err(["camera.width_px=wide"])
    assert "camera.width_px" in msg and "'wide'" in msg and "integer" in msg


@pytest.mark.parametrize("assignment, path, shown", [
    ("sim.t_max_ns=true", "sim.t_max_ns", "true"),  # pydantic's lax mode read this as 1 ns
    ("lander.dry_mass_kg=false", "lander.dry_mass_kg", "false"),
    ("lander.engine.thrust_max_N=true", "lander.engine.thrust_max_N", "true"),
    ("initial.r_BL_L_m=[0, true, 500]", "initial.r_BL_L_m[1]", "true"),
    ("sensors.altimeter.dropout_prob=true", "sensors.altimeter.dropout_prob", "true"),
    ('faults=[{kind="thrust_loss", fraction=true}]', "faults.0.fraction", "true"),  # named as pydantic names it
])
def test_a_boolean_for_a_number_names_the_field(assignment, path, shown):
    msg = _err([assignment])
    assert msg == (f"{path} = {shown}: a number is expected, not a boolean; allowed: a number (write 1 or 0 if "
                   "that is what you meant)"), msg


@pytest.mark.parametrize("assignment, path", [("nav_map=true", "nav_map"), ("hazard.avoidance=false", "hazard.avoidance")])
def test_a_boolean_for_a_switch_is_shown_as_written_with_the_words_allowed(assignment, path):
    msg = _err([assignment])
    shown = assignment.split("=")[1]  # TOML's true/false, not Python's True/False
    assert msg == (f"{path} = {shown}: Input should be 'off' or 'on'; allowed: 'off' or 'on', in quotes (a word, "
                   "not a boolean)"), msg
    value = load_scenario(None, [f'{path}="on"'])  # the word itself is taken
    for part in path.split("."):
        value = getattr(value, part)
    assert value == "on"


@pytest.mark.parametrize("assignment, path, shown", [
    # pydantic's lax mode read a quoted number as the number: t_s = "5" flew the fault at 5 s without a word.
    ('faults=[{kind = "dropout", target = "altimeter", t_s = "5"}]', "faults.0.t_s", "'5'"),
    ('sim.t_max_ns="1000"', "sim.t_max_ns", "'1000'"),
    ('sun.elevation_deg="20"', "sun.elevation_deg", "'20'"),
    ('initial.r_BL_L_m=[1.0, "2", 500.0]', "initial.r_BL_L_m[1]", "'2'"),
])
def test_a_string_for_a_number_names_the_field(assignment, path, shown):
    msg = _err([assignment])
    assert msg == f"{path} = {shown}: a number is expected, not a string; allowed: a number, written without quotes", msg
    load_scenario(None, ['name="a string where a string belongs"', 'guidance.law="apollo"'])


@pytest.mark.parametrize("assignment, needle", [
    ("map_nav.min_altitude_m=700.0", "map_nav.min_altitude_m = 700.0 must be below map_nav.max_altitude_m"),
    ("map_nav.keyframe_min_altitude_m=80.0", "map_nav.keyframe_min_altitude_m = 80.0 must be below"),
    ("map_nav.fix.subpixel_floor_px=1e200", "map_nav.fix.subpixel_floor_px = 1e+200"),  # overflowed in flight
    ("map_nav.fix.common_mode_sigma_px=1e200", "map_nav.fix.common_mode_sigma_px = 1e+200"),
    ("map_nav.confirm_drift_m=1e200", "map_nav.confirm_drift_m = 1e+200"),
    ("map_nav.fix.min_inliers=200", "map_nav.fix.min_inliers = 200 exceeds the 49 patches"),
])
def test_map_nav_settings_that_cannot_fly_are_refused(assignment, needle):
    msg = _err([assignment])
    assert msg.startswith(needle), msg


def test_a_seed_fits_a_64_bit_integer():
    assert load_scenario(None, [f"seed={2**63 - 1}"]).seed == 2**63 - 1
    msg = _err([f"seed={2**63}"])  # was a traceback when a replay wrote it to an int64 column
    assert msg.startswith(f"seed = {2**63}: Input should be less than"), msg


def test_booleans_stay_booleans_and_numbers_numbers():
    sc = load_scenario(None, ["camera.enabled=false", "vision=\"off\"", "sim.t_max_ns=90000000000",
                              "lander.dry_mass_kg=1000.5"])
    assert sc.camera.enabled is False and sc.sim.t_max_ns == 90_000_000_000 and sc.lander.dry_mass_kg == 1000.5


def test_negative_mass_is_rejected():
    msg = _err(["lander.dry_mass_kg=-5"])
    assert "lander.dry_mass_kg" in msg and "-5" in msg and "greater than 0" in msg


def test_rates_must_divide_the_physics_step():
    msg = _err(["sensors.imu.period_ns=3000000"])  # 3 ms against a 2 ms physics step
    assert "sensors.imu.period_ns = 3000000" in msg and "sim.physics_dt_ns = 2000000" in msg
    assert "2000000" in msg and "4000000" in msg
    msg = _err(["camera.period_ns=33333333"])
    assert "camera.period_ns" in msg


def test_engine_min_above_max_is_rejected():
    msg = _err(["lander.engine.thrust_min_N=9000"])
    assert "thrust_min_N" in msg and "thrust_max_N" in msg


@pytest.mark.parametrize("assignment, start", [
    # Before: "lander.rcs = {'min_on_ns': 40000000}: rcs.min_on_ns = ..." and "terrain = {'crater_min_diameter_m':
    # 500.0}: crater_max_diameter_m=200.0 must be > crater_min_diameter_m=500.0" (the table quoted, no path, no fix).
    ("lander.rcs.min_on_ns=40000000", "lander.rcs.min_on_ns = 40000000 is longer than rcs.pwm_period_ns = "),
    ("terrain.crater_min_diameter_m=500.0", "terrain.crater_min_diameter_m = 500 is not below crater_max_diameter_m "
                                            "= 200; allowed: crater_min_diameter_m < crater_max_diameter_m"),
    ("terrain.geometry_px=64", "terrain.geometry_px=64 is even"),
])
def test_a_tables_own_check_names_the_field_by_its_path_without_quoting_the_table(assignment, start):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(None, [assignment])
    msg = str(exc.value)
    assert msg.startswith(start) and "{" not in msg and "\n" not in msg, msg


def test_malformed_override_and_path_through_value():
    assert "KEY=VALUE" in _err(["seed"])
    assert "'seed' is a value" in _err(["seed.x=1"])


def test_missing_and_corrupt_scenario_files(tmp_path):
    assert "does not exist" in _err(path=tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("seed = = 3\n")
    assert "not valid TOML" in _err(path=bad)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    assert "UTF-8" in _err(path=binary)


def test_missing_and_corrupt_dem(tmp_path):
    msg = _err(["terrain.kind=\"dem\"", f"terrain.dem_path=\"{tmp_path / 'missing.npy'}\"", "terrain.dem_spacing_m=2.0"])
    assert "dem_path" in msg and "missing.npy" in msg
    corrupt = tmp_path / "corrupt.npy"
    corrupt.write_bytes(b"not a numpy file at all")
    msg = _err(["terrain.kind=\"dem\"", f"terrain.dem_path=\"{corrupt}\"", "terrain.dem_spacing_m=2.0"])
    assert "dem_path" in msg and "corrupt.npy" in msg


def test_dem_path_is_relative_to_the_scenario_file(tmp_path):
    dem = np.random.default_rng(0).normal(0, 2, (64, 64)).astype(np.float32)
    np.save(tmp_path / "site.npy", dem)
    f = tmp_path / "s.toml"
    f.write_text('[terrain]\nkind = "dem"\ndem_path = "site.npy"\ndem_spacing_m = 4.0\n')
    sc = load_scenario(f)
    assert sc.terrain.dem_path == tmp_path / "site.npy"


def test_a_scenario_loaded_by_a_relative_path_writes_one_that_reruns_elsewhere(tmp_path, monkeypatch):
    (tmp_path / "geo").mkdir()
    np.save(tmp_path / "geo" / "site.npy", np.random.default_rng(0).normal(0, 2, (64, 64)).astype(np.float32))
    (tmp_path / "geo" / "s.toml").write_text('[terrain]\nkind = "dem"\ndem_path = "site.npy"\ndem_spacing_m = 4.0\n')
    monkeypatch.chdir(tmp_path)
    written = scenario_to_toml(load_scenario("geo/s.toml"))  # as run writes it into --out
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "scenario.toml").write_text(written)
    monkeypatch.chdir(tmp_path / "out")  # was 'out/geo/site.npy': not found
    assert load_scenario("scenario.toml").terrain.dem_path == tmp_path / "geo" / "site.npy"


def test_every_field_declares_a_unit_or_description():
    # Units live in field names (_m, _ns, ...) or descriptions; a bare, undocumented field is a defect.
    def walk(model, prefix=""):
        for name, field in model.model_fields.items():
            ann = field.annotation
            if isinstance(ann, type) and issubclass(ann, Scenario.__mro__[1]):  # nested BaseModel
                yield from walk(ann, f"{prefix}{name}.")
            else:
                yield f"{prefix}{name}", field
    undocumented = [n for n, f in walk(Scenario) if not f.description]
    assert not undocumented, undocumented


def test_toml_parser_is_stdlib():
    assert tomllib.__name__ == "tomllib"
