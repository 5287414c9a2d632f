"""The landbench command line: outputs, one-line errors, and nothing written on error."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bench.cli import main
from bench.scenario import load_scenario
from tests.conftest import SMALL_SET


def _sets(extra=()):
    return [a for s in (*SMALL_SET, *extra) for a in ("--set", s)]


def test_scenario_show_prints_resolved_toml(capsys, tmp_path):
    assert main(["scenario", "show", "--set", "seed=7"]) == 0
    text = capsys.readouterr().out
    f = tmp_path / "s.toml"
    f.write_text(text)
    sc = load_scenario(f)
    assert sc.seed == 7 and sc == load_scenario(None, ["seed=7"])


def test_render_writes_frame_and_depth(tmp_path):
    import cv2

    out, depth = tmp_path / "frame.png", tmp_path / "depth.npy"
    assert main(["render", "--altitude", "100", "--out", str(out), "--depth", str(depth), *_sets()]) == 0
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    d = np.load(depth)
    assert img.shape == (256, 256) and img.dtype == np.uint8 and img.std() > 3
    # Level camera 100 m above the target: the centre depth is ~100 m (terrain relief aside).
    assert d.shape == (256, 256) and abs(float(d[128, 128]) - 100.0) < 10.0


def test_world_map(tmp_path):
    out = tmp_path / "world.png"
    assert main(["world", "--out", str(out), *_sets()]) == 0
    assert out.stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "--altitude", "100", "--set", "lander.dry_mass_kg=-1"], "lander.dry_mass_kg"),
        (["render", "--altitude", "100", "--set", "bogus=1"], "bogus"),
        (["render", "--altitude", "-3"], "--altitude"),
        (["render", "--altitude", "100", "--set", "sensors.imu.period_ns=3000001"], "sensors.imu.period_ns"),
        (["render", "--altitude", "inf"], "--altitude inf: must be a finite height"),  # was a black frame
        (["render", "--altitude", "5000"], "--altitude 5000: the camera draws from"),  # beyond the far plane
        (["render", "--altitude", "0.01"], "--altitude 0.01: the camera draws from"),  # inside the near plane
        # the depth's folder cannot be made: refused before the frame is written (it replaced the PNG before)
        (["render", "--altitude", "100", "--depth", "{tmp}/frame.png/d.npy"], "--depth"),
    ],
)
def test_errors_are_one_line_and_write_nothing(tmp_path, capsys, argv, needle):
    out = tmp_path / "frame.png"
    out.write_bytes(b"previous result")  # an earlier result must survive a bad run
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("landbench: error:") and needle in err
    assert out.read_bytes() == b"previous result"
    assert list(tmp_path.iterdir()) == [out]


def test_console_script_entry_point():
    res = subprocess.run([sys.executable, "-m", "bench.cli", "scenario", "show", "--set", "seed=3"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "seed = 3" in res.stdout


def test_the_console_command_returns_mains_status_and_freezes_what_is_left(monkeypatch, capsys):
    """``console_main`` (the installed ``landbench``) is ``main`` on sys.argv, with the objects left frozen out
    of the collector so that the interpreter's last collection skips them."""
    import gc

    from bench.cli import console_main

    monkeypatch.setattr(sys, "argv", ["landbench", "scenario", "show", "--set", "seed=oops"])
    gc.unfreeze()
    try:
        assert console_main() == 2  # the user's mistake: main's status
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    assert capsys.readouterr().err.startswith("landbench: error: seed")


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _refused(capsys, argv, needle):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("landbench: error:") and needle in err, err


def test_an_out_folder_holding_another_commands_results_is_refused_and_kept(tmp_path, capsys):
    # A campaign folder and a run folder (made by hand: what matters is the file each is known by).
    camp, run_dir, sweep_dir = tmp_path / "camp", tmp_path / "run", tmp_path / "sweep"
    for d, name in ((camp, "campaign.json"), (run_dir, "summary.json"), (sweep_dir, "sweep.json")):
        d.mkdir()
        (d / name).write_text("{}")
        (d / "scenario.toml").write_text("# kept\n")
    before = _files(tmp_path)
    _refused(capsys, ["run", "--no-video", "--out", str(camp), "--set", "sim.t_max_ns=1000000000"], "holds a campaign")
    _refused(capsys, ["mc", "--runs", "1", "--dry-run", "--out", str(run_dir)], "holds a run's results")
    _refused(capsys, ["compare", str(camp), str(camp), "--out", str(sweep_dir)], "holds a sweep")
    _refused(capsys, ["mc", "--replay", str(camp), "--case", "0", "--out", str(sweep_dir)], "holds a sweep")
    assert _files(tmp_path) == before


@pytest.mark.parametrize(
    "argv, needle",
    [
        # a dispersion that draws outside the field's limits: refused before the campaign's folder exists
        (["mc", "--runs", "2", "--dry-run", "--set",
          'dispersions."sun.elevation_deg"={dist="uniform", low=-100.0, high=-90.0}'], "sun.elevation_deg"),
        (["mc", "--runs", "1", "--dry-run", "--seed", "-1"], "--seed -1"),
        (["faults", "--presets", "im1", "--runs", "1", "--workers", "0"], "--workers 0"),
        (["faults", "--presets", "im1", "--runs", "1", "--seed", "-2"], "--seed -2"),
        (["sweep", "--grid", "seed=1,2", "--runs", "1", "--case-timeout", "0"], "--case-timeout"),
        (["sweep", "--grid", "seed=range(0, inf)", "--runs", "1", "--dry-run"], "finite"),
        (["sweep", "--grid", "seed=range(0, 1e9)", "--runs", "1", "--dry-run"], "at most"),
    ],
)
def test_campaign_mistakes_are_refused_before_anything_is_written(tmp_path, capsys, argv, needle):
    out = tmp_path / "out"
    _refused(capsys, [*argv, "--out", str(out)], needle)
    assert not out.exists()


def test_a_results_folder_without_its_keys_is_refused_in_one_line(tmp_path, capsys):
    camp = tmp_path / "camp"
    camp.mkdir()
    (camp / "campaign.json").write_text("{}")
    _refused(capsys, ["mc", "--resume", str(camp)], "lacks campaign_seed, runs")
    _refused(capsys, ["mc", "--replay", str(camp), "--case", "0", "--out", str(tmp_path / "r")], "lacks")
    (camp / "campaign.json").write_text("{not json")
    _refused(capsys, ["mc", "--resume", str(camp)], "cannot be read")
    for name, keys in (("faults", "presets"), ("sweep", "design")):
        d = tmp_path / name
        d.mkdir()
        (d / f"{name}.json").write_text("{}")
        _refused(capsys, [name, "--resume", str(d)], f"lacks {keys}")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "table, needle",
    [
        ("grid = [1, 2]\nruns = 1", "sweep.grid"),
        ('grid = {seed = [1, 2]}\nrequire = "success_rate>=0.5"\nruns = 1', "sweep.require"),
        ("grid = {seed = [1, 2]}\nruns = 1.7", "sweep.runs"),
        ("ranges = [1]\nlhs = 2\nruns = 1", "sweep.ranges"),
    ],
)
def test_a_sweep_table_of_the_wrong_types_is_refused_in_one_line(tmp_path, capsys, table, needle):
    f = tmp_path / "s.toml"
    f.write_text(f"[sweep]\n{table}\n")
    _refused(capsys, ["sweep", str(f), "--dry-run", "--out", str(tmp_path / "out")], needle)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("field", ["propellant.nominal_need_kg", "lander.rcs.isp_s", "lander.rcs.moment_arm_m"])
def test_non_finite_values_of_every_table_are_refused(capsys, field):
    _refused(capsys, ["scenario", "show", "--set", f"{field}=inf"], field)


def test_resume_refuses_settings_it_would_ignore(tmp_path, capsys):
    camp = tmp_path / "camp"
    assert main(["mc", "--runs", "1", "--dry-run", "--out", str(camp)]) == 0
    before = _files(tmp_path)
    _refused(capsys, ["mc", "--resume", str(camp), "--set", "seed=99"], "drop --set")
    _refused(capsys, ["mc", "--resume", str(camp), "--preset", "im1"], "drop --preset")
    _refused(capsys, ["sweep", "--resume", str(camp), "--grid", "seed=1,2"], "drop --grid")
    _refused(capsys, ["faults", "--resume", str(camp), "--runs", "3"], "drop --runs")
    assert _files(tmp_path) == before


@pytest.mark.parametrize(
    "setting, needle",
    [
        ("onboard_map.size_m=230.4", "whole number of image pixels"),  # checked at load, not 9 s into the run
        ("terrain.size_m=100000.0", "lower the density"),  # 2e8 craters: hours of generation
        # An RCS whose shortest pulse outlasts its period never fired: the lander drifted off the terrain.
        ("lander.rcs.min_on_ns=40000000", "no pulse could ever fire; allowed: min_on_ns <= pwm_period_ns"),
        # MuJoCo's "zero norm quaternions" (two lines, no field) or a drift off the terrain before.
        ("lander.com_offset_B_m=[1e300, 0.0, 0.0]", "lander.com_offset_B_m = [1e+300, 0.0, 0.0]"),
        ("lander.dry_mass_kg=1e308", "lander.dry_mass_kg = 1e+308"),  # named an internal inertia before
        # Noise that overflowed inside the flight software (tracebacks, or "math domain error" naming nothing).
        ("sensors.imu.gyro_noise_density=1e200", "sensors.imu.gyro_noise_density = 1e+200"),
        ("sensors.imu.accel_noise_density=1e200", "sensors.imu.accel_noise_density = 1e+200"),
        ("sensors.altimeter.noise_sigma_m=1e200", "sensors.altimeter.noise_sigma_m = 1e+200"),
        ("sensors.altimeter.noise_frac=1e308", "sensors.altimeter.noise_frac = 1e+308"),
        # Criteria without an upper bound counted a 17 m/s impact as landed (exit 0).
        ("landing.v_vertical_max_mps=1e9", "landing.v_vertical_max_mps = 1000000000.0"),
        ("landing.v_horizontal_max_mps=11", "landing.v_horizontal_max_mps = 11"),
    ],
)
def test_settings_that_would_fail_or_stall_the_run_are_refused_at_load(capsys, setting, needle):
    _refused(capsys, ["scenario", "show", "--set", setting], needle)


@pytest.mark.parametrize("argv, needle", [
    # A march step of 1e-9 m marched for ever; 1 mm pixels, 10 um map posts and 1 um truth posts ran out of memory
    # (a raw MemoryError traceback).
    (["--set", "hazard.avoidance=on", "--set", "hazard.lidar.march_step_m=1e-9"],
     "hazard.lidar.march_step_m = 1e-09: Input should be greater than or equal to 0.005"),
    (["--set", "onboard_map.image_res_m=0.001"], "onboard_map.image_res_m = 0.001 makes 768000 pixels a side"),
    (["--set", "onboard_map.dem_spacing_m=0.00001"], "onboard_map.dem_spacing_m = 1e-05 makes 76800000 posts a side"),
    (["--set", "hazard.avoidance=on", "--set", "hazard.hda.dem_spacing_m=0.00001"],
     "hazard.hda.dem_spacing_m = 1e-05 over the scan's footprint at hazard.hda.scan_altitude_m = 100 m"),
    (["--set", "hazard.scoring=on", "--set", "hazard.site_spacing_m=0.000001"],
     "hazard.site_spacing_m = 1e-06: Input should be greater than or equal to 0.005"),
    # Scans that could never be taken, or would see nothing: the run flew (and landed) without a word.
    (["--set", "hazard.avoidance=on", "--set", "hazard.hda.scan_altitude_m=25"],
     "hazard.hda.scan_altitude_m = 25 is at or below guidance.gate_altitude_m = 30"),
    (["--set", "hazard.avoidance=on", "--set", "hazard.hda.rescan_altitude_m=150"],
     "hazard.hda.rescan_altitude_m = 150 is not below hazard.hda.scan_altitude_m = 100"),
    (["--set", "hazard.avoidance=on", "--set", "initial.r_BL_L_m=[5.0, -3.0, 20.0]"],
     "initial.r_BL_L_m = [5.0, -3.0, 20.0] starts 20 m above the target, at or below guidance.gate_altitude_m = 30"),
    (["--set", "hazard.avoidance=on", "--set", "hazard.lidar.max_range_m=50"],
     "hazard.lidar.max_range_m = 50 is shorter than the slant range of the scan (103 m"),
    (["--set", "hazard.avoidance=on", "--set", "hazard.lidar.fov_deg=1"],
     "hazard.lidar.fov_deg = 1: at hazard.hda.scan_altitude_m = 100 m the footprint is 1.75 m across"),
    # These two flew in the slow hazard test, to show the flight declaring that its scan was never taken.
    (["--set", "hazard.avoidance=on", "--set", "hazard.hda.rescan_altitude_m=0.5"],
     "hazard.lidar.fov_deg = 20: at hazard.hda.rescan_altitude_m = 0.5 m the footprint is 0.18 m across"),
    (["--set", "hazard.avoidance=on", "--set", "hazard.hda.scan_altitude_m=1.0"],
     "hazard.hda.scan_altitude_m = 1 is at or below guidance.gate_altitude_m = 30"),
    # The hazardous preset on a 128 m terrain flew to 100 m before its footprint left the terrain; the second
    # scan's (over a site up to 50 m away) needs more, and the size named is the one that holds both.
    (["--preset", "hazardous", "--set", "hazard.avoidance=on", "--set", "terrain.size_m=128"],
     "hazard.hda.rescan_altitude_m = 50: the lidar's footprint (+-24 m, nadir about 50 m from the target) reaches "
     "74 m from the target, beyond the terrain (terrain.size_m = 128, half 64 m less 1 m); allowed: a larger "
     "terrain.size_m (at least 152)"),
    # Periods and run lengths past int64 overflowed the clock.
    (["--set", "nav_map=on", "--set", "map_nav.period_ns=10000000000000000000"],
     "map_nav.period_ns = 10000000000000000000 is longer than any run"),
    (["--set", "sim.t_max_ns=10000000000000000000"], "sim.t_max_ns = 10000000000000000000"),
    # A fault at 0.5 m never triggered (the body origin stands 2.1 m up): only triggered = false told.
    (["--set", 'faults=[{kind = "dropout", target = "altimeter", altitude_m = 0.5}]'],
     "faults.0.altitude_m = 0.5 is under half the body origin's height standing on level ground (2.1 m"),
])
def test_hazard_map_and_timing_settings_that_could_never_act_are_refused_at_load(capsys, argv, needle):
    _refused(capsys, ["scenario", "show", *argv], needle)


@pytest.mark.parametrize("setting, line", [
    # The member's tag was read as a table (faults.0.dropout.t_s); a missing kind, target or dist quoted the whole
    # table with pydantic's "Unable to extract tag" or "Field required" and listed nothing allowed; an unknown key
    # in a fault or a dispersion listed no fields.
    ('faults=[{kind = "dropout", target = "altimeter", t_s = -1}]',
     "faults.0.t_s = -1: Input should be greater than or equal to 0"),
    ('faults=[{target = "altimeter", t_s = 1}]', "faults.0.kind is missing; allowed: dropout, stuck, bias_step,"),
    ('faults=[{kind = "dropout", t_s = 1}]', "faults.0.target is missing; allowed: imu.accel, imu.gyro, altimeter, "
                                             "star_tracker"),
    ('faults=[{kind = "bias_step", target = "imu.gyro"}]', "faults.0.value is missing; give a value"),
    ('faults=[{kind = "dropout", target = "altimeter", bogus = 2}]',
     "unknown field 'faults.0.bogus'; allowed here: t_s, t_ns, altitude_m, phase, duration_s, target, axes, kind"),
    ('dispersions={"seed" = {sigma = 1}}', "dispersions.seed.dist is missing; allowed: normal, truncnorm, uniform, "
                                          "integers, choice"),
    ('dispersions={"seed" = {dist = "normal", sigma = 1, bogus = 2}}',
     "unknown field 'dispersions.seed.bogus'; allowed here: own_stream, dist, sigma"),
])
def test_a_fault_or_dispersion_mistake_names_the_path_the_user_wrote(capsys, setting, line):
    _refused(capsys, ["scenario", "show", "--set", setting], line)


def test_scenario_show_takes_a_preset(capsys):
    assert main(["scenario", "show", "--preset", "hazardous"]) == 0
    assert "boulder_density_per_km2 = 25000.0" in capsys.readouterr().out


def test_a_dispersed_map_resolution_is_named_with_a_value_that_would_do():
    from models.orbital_map import grid_counts

    # It blamed onboard_map.size_m and offered "e.g. 697498" (the common multiple of a drawn 0.9934 m and 2 m).
    with pytest.raises(ValueError) as exc:
        grid_counts(768.0, 0.993419909472726, 2.0)
    msg = str(exc.value)
    assert "onboard_map.image_res_m = 0.99342 m" in msg and "e.g. 0.993532 = 768 / 773" in msg and "697498" not in msg
    assert grid_counts(768.0, 768 / 773, 2.0) == (773, 384)


def test_vision_figures_with_too_few_frames_names_the_flag(tmp_path, capsys):
    _refused(capsys, ["vision-figures", "--frames", "2", "--out", str(tmp_path / "v")], "--frames 2")
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize("argv, needle", [
    # Frames 57..59 were shown for --start 100 without a word; a negative start showed frame 0.
    (["--frames", "60", "--start", "100"], "--start 100: the figures show frames START..START+2 of the 60 rendered; "
                                           "give --start from 0 to 57"),
    (["--start", "-1"], "give --start from 0 to 57"),
    # A camera smaller than a template failed inside the variance map, naming no field.
    (["--set", "camera.width_px=16", "--set", "camera.height_px=16"],
     "camera.width_px x camera.height_px = 16 x 16: the figures' templates are tracker.template_size = 30 px"),
])
def test_vision_figures_refuses_what_it_cannot_show_before_rendering(tmp_path, capsys, argv, needle):
    _refused(capsys, ["vision-figures", *argv, "--out", str(tmp_path / "v")], needle)
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize("argv, needle", [
    (["run", "--bogus"], "unrecognized arguments: --bogus; see 'landbench run --help'"),
    (["mc", "--runs", "x"], "argument --runs: invalid int value: 'x'; see 'landbench mc --help'"),
    (["sweep", "--lhs"], "argument --lhs: expected one argument; see 'landbench sweep --help'"),
    (["scenario"], "the following arguments are required: ACTION; see 'landbench scenario --help'"),
    (["nope"], "argument COMMAND: invalid choice: 'nope'"),
])
def test_a_flag_mistake_is_one_error_line(argv, needle, capsys):
    # argparse's own printed its usage block, then 'landbench <command>: error: ...'
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: ") and needle in err, err


def test_json_outputs_are_valid_json_and_worker_counts_are_checked_first(capsys):
    # 3 frames over the whole descent leave nothing to score: its medians are NaN, which json.dumps wrote as a
    # bare NaN (not JSON); they are null now.
    assert main(["track-eval", "--size", "256", "--frames", "3", "--repeats", "1", "--json", *_sets()]) == 0
    doc = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"{c} in --json output"))
    assert "epe_median_px" in doc["results"]["256"]["tracker"]
    # A repeated worker count failed after the cases had flown, naming a temporary folder.
    assert main(["perf", "--campaign", "1", "--campaign-workers", "1,1", *_sets()]) == 2
    assert "--campaign-workers 1,1: a worker count is repeated" in capsys.readouterr().err


def test_world_refuses_a_start_off_the_tile_as_run_does(tmp_path, capsys):
    out = tmp_path / "w.png"
    assert main(["world", "--out", str(out), "--set", "terrain.size_m=64", "--set",
                 "terrain.target_clear_radius_m=10"]) == 2
    assert "the start is outside the 64 m terrain tile" in capsys.readouterr().err and not out.exists()


def test_faults_takes_a_scenario_file_in_place_of_its_default_action(tmp_path, capsys):
    # The help says run is the default; before, `landbench faults FILE` read FILE as the action:
    # "argument action: invalid choice: 'FILE' (choose from 'list', 'run')".
    missing = tmp_path / "mine.toml"
    _refused(capsys, ["faults", str(missing), "--runs", "1", "--out", str(tmp_path / "m")],
             f"scenario file '{missing}' does not exist")
    _refused(capsys, ["faults", "a.toml", "b.toml", "--runs", "1", "--out", str(tmp_path / "m")],
             "the first word is list or run")
    assert not (tmp_path / "m").exists()


def test_a_dispersed_map_resolution_is_refused_naming_the_resolution(tmp_path, capsys):
    # Every case was refused as "onboard_map.size_m = 768.0 must be a whole number ... e.g. 697498; keep that
    # field's [dispersions] entry within the field's limits": the size named, an absurd size offered, and a
    # limit that is not one.
    table = 'dispersions={"onboard_map.image_res_m" = {dist = "uniform", low = 0.9, high = 1.1}}'
    _refused(capsys, ["mc", "--runs", "2", "--dry-run", "--out", str(tmp_path / "c"), "--set", table],
             "is not a whole number of image pixels (onboard_map.image_res_m = ")
    err_line = main(["mc", "--runs", "2", "--dry-run", "--out", str(tmp_path / "c"), "--set", table])
    err = capsys.readouterr().err
    assert err_line == 2 and "697498" not in err and "to values the scenario accepts" in err, err
    assert not (tmp_path / "c").exists()
