"""landbench run: the files it writes and their contract."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from bench.cli import main
from bench.report.report import read_telemetry_parquet
from bench.scenario import load_scenario
from tests.conftest import SMALL_SET

# A short landing: from 20 m, below the 30 m gate, so only the terminal descent is flown (about 27 s).
QUICK = [*SMALL_SET, 'nav="truth"', 'vision="off"', "initial.r_BL_L_m=[5.0, -3.0, 20.0]", "initial.v_BL_L_mps=[0.0, 0.0, -1.0]",
         "camera.width_px=64", "camera.height_px=64", "landing.settle_s=2.0"]
SUMMARY_KEYS = {"outcome", "landed", "touchdown", "fuel_used_kg", "sim_time_s", "wall_time_s", "realtime_factor", "seed"}
TOUCHDOWN_KEYS = {"t_s", "v_vertical_mps", "v_horizontal_mps", "tilt_deg", "miss_distance_m"}


def _sets(extra=()):
    return [a for s in (*QUICK, *extra) for a in ("--set", s)]


def test_run_writes_the_contract_and_its_scenario_reruns_it(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), *_sets()]) == 0
    assert "LANDED" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert SUMMARY_KEYS <= summary.keys() and TOUCHDOWN_KEYS <= summary["touchdown"].keys()
    assert summary["landed"] is True and summary["outcome"] == "landed" and summary["seed"] == 1
    tel = read_telemetry_parquet(out / "telemetry.parquet")
    assert len(tel["t_s"]) == int(round(summary["sim_time_s"] * 50)) + 1  # one row per 50 Hz control tick
    assert {"r_z_m", "thrust_N", "imu_f_z_mps2", "alt_range_m", "st_q_w", "phase"} <= tel.keys()
    assert cv2.imread(str(out / "plots.png")) is not None
    cap = cv2.VideoCapture(str(out / "camera.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == int(summary["sim_time_s"] * 10) + 1
    # The written scenario reproduces the landing exactly.
    assert load_scenario(out / "scenario.toml") == load_scenario(None, QUICK)
    out2 = tmp_path / "rerun"
    assert main(["run", str(out / "scenario.toml"), "--out", str(out2), "--no-video"]) == 0
    again = json.loads((out2 / "summary.json").read_text())
    wall = ("wall_time_s", "setup_time_s", "realtime_factor", "time_split_s")
    assert {k: v for k, v in again.items() if k not in wall} == {k: v for k, v in summary.items() if k not in wall}
    tel2 = read_telemetry_parquet(out2 / "telemetry.parquet")
    for k in tel:
        np.testing.assert_array_equal(tel[k], tel2[k], err_msg=k)
    assert not (out2 / "camera.mp4").exists()


def test_failed_landing_exits_3_and_still_writes_results(tmp_path):
    out = tmp_path / "crash"
    assert main(["run", "--out", str(out), "--no-video", *_sets(['guidance.law="off"', "initial.v_BL_L_mps=[0.0, 0.0, -10.0]"])]) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcome"] == "hard_landing" and summary["landed"] is False


def test_bad_input_writes_nothing(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text("earlier result")
    assert main(["run", "--out", str(out), *_sets(['guidance.law="pdg"'])]) == 2
    assert "guidance.law" in capsys.readouterr().err
    assert (out / "summary.json").read_text() == "earlier result"
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


@pytest.mark.parametrize("error", [ValueError, OverflowError])
def test_a_defect_inside_the_loop_is_reported_as_internal_not_as_the_users_mistake(tmp_path, capsys, monkeypatch, error):
    # Before: a ValueError from inside the flight read "landbench: error: <numpy's message>" with exit 2, as if
    # the (valid) input were wrong, and without the traceback a report needs; an OverflowError was a bare
    # traceback with exit 1.
    import bench.sim.run as run_module

    def broken_row(*args, **kwargs):
        raise error("operands could not be broadcast together with shapes (3,) (4,)")

    monkeypatch.setattr(run_module, "_row", broken_row)
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text("earlier result")
    assert main(["run", "--out", str(out), *_sets()]) == 70
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback (most recent call last):" in err and "landbench: error:" not in "\n".join(err)
    assert err[-1].startswith(f"landbench: internal error: the closed loop failed at t = 0.000 s with {error.__name__}: "
                              "operands could not be broadcast"), err[-1]
    assert "not a mistake in the input" in err[-1]
    assert (out / "summary.json").read_text() == "earlier result"
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_a_flight_computer_that_cannot_be_built_stays_the_users_one_line(tmp_path, capsys, monkeypatch):
    # Built before the loop: its refusals (G-FOLD without its optional extra) are about the input, not defects.
    import bench.sim.flight_build as fb

    def no_cvxpy(*args, **kwargs):
        raise ValueError("guidance.law = 'gfold' needs cvxpy and a conic solver, the optional extra")

    monkeypatch.setattr(fb, "make_guidance", no_cvxpy)
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), *_sets()]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["landbench: error: guidance.law = 'gfold' needs cvxpy and a conic solver, the optional extra"], err
    assert not out.exists()


def test_a_camera_too_small_for_the_tracker_is_one_line_before_anything_is_built(tmp_path, capsys):
    # Before: a 64 x 64 camera flew: the tracker never placed a template (30 px, 21 px from every edge), and the
    # default landing went blind to a navigation abort at 35 m, "median 0 tracks" the only hint.
    out = tmp_path / "run"
    small = ["camera.width_px=64", "camera.height_px=64"]
    assert main(["run", "--out", str(out), *[a for s in small for a in ("--set", s)]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        "landbench: error: camera.width_px x camera.height_px = 64 x 64 is too small for the tracker") and "72 px" in err[0]
    assert not out.exists()
    camp = tmp_path / "camp"  # a campaign of such cases: refused before its folder exists, not n error rows
    assert main(["mc", "--runs", "2", "--out", str(camp), *[a for s in small for a in ("--set", s)]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is too small for the tracker" in err[0] and not camp.exists()
    from bench.sim.flight_build import check_tracker_fits_camera

    for ok in (["camera.width_px=72", "camera.height_px=72"], [*small, 'vision="off"'], [*small, 'tracks="truth"'],
               [*small, "tracker.template_size=20", "tracker.border_px=20"]):
        check_tracker_fits_camera(load_scenario(None, ok))  # the smallest frame that holds one; no tracker; a smaller one


def test_a_failure_after_the_run_leaves_no_partial_video(tmp_path, monkeypatch):
    import pytest

    import bench.report.run_outputs as ro

    def broken_plots(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(ro, "write_plots", broken_plots)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="disk full"):
        ro.run_and_write(load_scenario(None, QUICK), out)
    assert not any(p.suffix in (".mp4", ".tmp") or ".mp4." in p.name for p in out.iterdir())
    assert not (out / "summary.json").exists()



@pytest.mark.parametrize("bad, field", [
    ("initial.r_BL_L_m=[nan, 0.0, 500.0]", "initial.r_BL_L_m"),
    ("lander.propellant_kg=inf", "lander.propellant_kg"),
    ("sensors.imu.accel_noise_density=-inf", "sensors.imu.accel_noise_density"),
    ("estimator.gate_prob=nan", "estimator.gate_prob"),
    ("initial.r_BL_L_m=[0.0, 0.0, -5.0]", "initial.r_BL_L_m"),  # footpads below the ground
    ("initial.r_BL_L_m=[0.0, 0.0, 1.0]", "initial.r_BL_L_m"),  # body origin above it, footpads below
    ("initial.r_BL_L_m=[900.0, 0.0, 500.0]", "initial.r_BL_L_m"),  # off the 1024 m tile
])
def test_non_finite_values_and_impossible_starts_get_one_line_and_write_nothing(tmp_path, capsys, bad, field):
    out = tmp_path / "new" / "run"
    assert main(["run", "--out", str(out), *_sets([bad])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("landbench: error: ") and field in err[0]
    assert not out.exists()


def test_an_output_folder_that_cannot_be_made_gets_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["run", "--out", str(blocker / "run"), *_sets()]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("landbench: error: ") and "run" in err[0]
    assert blocker.read_text() == "not a folder"
