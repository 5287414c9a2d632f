"""landbench sweep: designs, common random numbers, statistics, Pareto front, Sobol wiring, refusals, report."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.campaign import sweep
from bench.cli import main
from bench.scenario.schema import read_scenario_data
from tests.conftest import SMALL_SET

QUICK = [*SMALL_SET, 'nav="truth"', 'vision="off"', "camera.enabled=false", "landing.settle_s=1.0",
         "initial.r_BL_L_m=[5.0, -3.0, 20.0]", "initial.v_BL_L_mps=[0.0, 0.0, -1.0]",
         'dispersions={"initial.r_BL_L_m"={dist="normal", sigma=[3.0, 3.0, 2.0]}, '
         '"lander.dry_mass_kg"={dist="normal", sigma=10.0}}']


def _sets(extra=()):
    return [a for s in (*QUICK, *extra) for a in ("--set", s)]


def test_every_point_gets_the_same_cases_differing_only_by_the_design(tmp_path, capsys):
    from bench.scenario import load_scenario

    out = tmp_path / "dry"
    assert main(["sweep", "--grid", "control.attitude_bandwidth_radps=1.5,3", "--grid", "guidance.law=zem_zev,apollo",
                 "--runs", "3", "--seed", "4", "--out", str(out), "--dry-run"]) == 0
    sc = {(p, c): load_scenario(out / "points" / f"{p:04d}" / "cases" / f"{c:05d}" / "scenario.toml").model_dump()
          for p in range(4) for c in range(3)}
    design = [(1.5, "zem_zev"), (1.5, "apollo"), (3, "zem_zev"), (3, "apollo")]
    for p, (bw, law) in enumerate(design):
        for c in range(3):
            s = sc[(p, c)]
            assert s["control"]["attitude_bandwidth_radps"] == bw and s["guidance"]["law"] == law
            # Everything else, seed and every dispersed draw included, is the same at every point.
            ref = sc[(0, c)]
            strip = lambda d: {**d, "control": {**d["control"], "attitude_bandwidth_radps": 0},  # noqa: E731
                               "guidance": {**d["guidance"], "law": ""}}
            assert strip(s) == strip(ref)
    assert sc[(0, 0)]["seed"] != sc[(0, 1)]["seed"] and sc[(0, 0)]["initial"] != sc[(0, 1)]["initial"]


@pytest.mark.slow  # about 40 s: two points of two cases flown, and a resume
def test_every_point_flies_the_same_cases_and_a_resume_reruns_only_what_is_missing(tmp_path, capsys):
    out = tmp_path / "sw"
    argv = ["sweep", *_sets(), "--grid", "control.attitude_bandwidth_radps=1.5,3", "--runs", "2", "--workers", "2",
            "--seed", "4", "--out", str(out)]
    assert main(argv) == 0
    cases = pq.read_table(out / sweep.CASES_PARQUET).to_pylist()
    points = pq.read_table(out / sweep.POINTS_PARQUET).to_pylist()
    assert len(points) == 2 and len(cases) == 4
    by_point = {p: [c for c in cases if c["point"] == p] for p in (0, 1)}
    disp = [k for k in cases[0] if k.startswith("disp_")]
    assert len(disp) >= 4
    for a, b in zip(by_point[0], by_point[1]):  # common random numbers: same seed and draws, case by case
        assert a["case"] == b["case"] and a["seed"] == b["seed"]
        assert all(a[k] == b[k] for k in disp)
        assert a["design_control.attitude_bandwidth_radps"] != b["design_control.attitude_bandwidth_radps"]
    assert by_point[0][0]["seed"] != by_point[0][1]["seed"]  # ... and different cases differ
    assert by_point[0][0]["disp_lander.dry_mass_kg"] != by_point[0][1]["disp_lander.dry_mass_kg"]
    assert [p["success_rate"] for p in points] == [1.0, 1.0]
    # The statistics against the case rows, recomputed here.
    fuel0 = [c["fuel_used_kg"] for c in by_point[0]]
    assert points[0]["fuel_mean_kg"] == pytest.approx(np.mean(fuel0))
    assert points[0]["miss_p95_m"] == pytest.approx(np.percentile([c["touchdown_miss_distance_m"] for c in by_point[0]], 95))
    html = (out / "report.html").read_text()
    assert "Pareto front" in html and "<script src" not in html
    # Resume: a lost case is flown again, the others are kept.
    first = json.loads((out / "points" / "0001" / "cases" / "00001.json").read_text())
    kept = (out / "points" / "0000" / "cases" / "00000.json").stat().st_mtime_ns
    (out / "points" / "0001" / "cases" / "00001.json").unlink()
    capsys.readouterr()
    assert main(["sweep", "--resume", str(out), "--workers", "1"]) == 0
    again = json.loads((out / "points" / "0001" / "cases" / "00001.json").read_text())
    assert (out / "points" / "0000" / "cases" / "00000.json").stat().st_mtime_ns == kept
    assert again["fuel_used_kg"] == first["fuel_used_kg"] and again["seed"] == first["seed"]


@pytest.mark.parametrize("grid, needle", [
    ("control.attitude_bandwidth_radps=1,-2",
     "sweep point 1 (control.attitude_bandwidth_radps=-2): control.attitude_bandwidth_radps = -2"),
    ("control.attitude_bandwith_radps=1,2", "sweep point 0 (control.attitude_bandwith_radps=1): unknown field "
                                            "'control.attitude_bandwith_radps'"),
    ("guidance.law=zem_zev,pdg", "sweep point 1 (guidance.law='pdg'): guidance.law = 'pdg': unknown law"),
])
def test_an_invalid_point_is_refused_before_anything_runs(grid, needle, tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", "--grid", grid, "--runs", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: ") and needle in err, err
    assert not out.exists()


@pytest.mark.parametrize("argv, needle", [
    (["--runs", "2"], "give one design"),
    (["--grid", "a=1", "--lhs", "3", "--runs", "2"], "give one design"),
    (["--lhs", "3", "--runs", "2"], "needs ranges"),
    (["--sobol", "4", "--range", "guidance.gate_altitude_m=20:40", "--runs", "2"], "at least two --range"),
    (["--sobol", "1", "--range", "guidance.gate_altitude_m=20:40", "--range", "control.attitude_bandwidth_radps=1:4",
      "--runs", "2"], "need at least 8 base points"),  # N = 1 gave indices of 2 +- 0
    (["--lhs", "3", "--range", "guidance.gate_altitude_m=40:20", "--runs", "2"], "LOW < HIGH"),
    (["--grid", "guidance.law=zem_zev", "--runs", "2", "--require", "fuel<3"], "unknown metric 'fuel'"),
    (["--grid", "guidance.law=zem_zev,zem_zev", "--runs", "2"], "repeated"),
    (["--grid", "guidance.gate_altitude_m=30,30.0", "--runs", "2"], "repeated"),  # the same number twice
    (["--grid", "guidance.law=zem_zev"], "--runs N is required"),
])
def test_bad_sweep_flags_get_one_error_line(argv, needle, tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err, err
    assert not out.exists()


def test_grid_grammar():
    assert sweep.parse_grid("a.b=range(0, 1, 0.25)") == ("a.b", [0.0, 0.25, 0.5, 0.75])
    assert sweep.parse_grid("a=range(3)") == ("a", [0, 1, 2])
    assert sweep.parse_grid('guidance.law=zem_zev,"x:Y",apollo') == ("guidance.law", ["zem_zev", "x:Y", "apollo"])
    assert sweep.parse_grid("initial.r_BL_L_m=[1, 2, 3],[4, 5, 6]") == ("initial.r_BL_L_m", [[1, 2, 3], [4, 5, 6]])
    assert sweep.parse_grid('a=1,"1",true') == ("a", [1, "1", True])  # a number, a text, a boolean: three values
    d = sweep.grid_design([("a", [1, 2]), ("b", ["x", "y", "z"])])
    assert len(d.points) == 6 and d.points[0] == {"a": 1, "b": "x"} and d.points[-1] == {"a": 2, "b": "z"}


def test_latin_hypercube_puts_one_point_in_every_stratum():
    n = 12
    d = sweep.lhs_design({"x": (2.0, 5.0), "k": (1, 13)}, n, seed=3)
    x = np.array([p["x"] for p in d.points])
    bins = np.floor((x - 2.0) / 3.0 * n).astype(int)
    assert sorted(bins) == list(range(n))  # stratified: each of the n equal slices once
    assert all(isinstance(p["k"], int) and 1 <= p["k"] <= 13 for p in d.points)
    assert d.points == sweep.lhs_design({"x": (2.0, 5.0), "k": (1, 13)}, n, seed=3).points  # seeded


def test_sobol_wiring_recovers_the_ishigami_indices():
    pytest.importorskip("SALib")
    a, b = 7.0, 0.1
    d = sweep.sobol_design({"x1": (-math.pi, math.pi), "x2": (-math.pi, math.pi), "x3": (-math.pi, math.pi)},
                           2048, seed=1)
    assert len(d.points) == 2048 * (3 + 2)
    x = np.array([[p["x1"], p["x2"], p["x3"]] for p in d.points])
    y = np.sin(x[:, 0]) + a * np.sin(x[:, 1]) ** 2 + b * x[:, 2] ** 4 * np.sin(x[:, 0])
    # Analytic indices (Ishigami & Homma 1990; Saltelli et al. 2008).
    v = a**2 / 8 + b * math.pi**4 / 5 + b**2 * math.pi**8 / 18 + 0.5
    v1 = 0.5 * (1 + b * math.pi**4 / 5) ** 2
    v2 = a**2 / 8
    v13 = b**2 * math.pi**8 * (1 / 18 - 1 / 50)
    exact = {"x1": (v1 / v, (v1 + v13) / v), "x2": (v2 / v, v2 / v), "x3": (0.0, v13 / v)}
    got = sweep.sobol_indices(d, y)
    for k, (s1, st) in exact.items():
        assert abs(got[k]["S1"] - s1) < 0.03 + 2 * got[k]["S1_conf"], (k, got[k], s1)
        assert abs(got[k]["ST"] - st) < 0.03 + 2 * got[k]["ST_conf"], (k, got[k], st)
        assert 0.0 < got[k]["S1_conf"] < 0.1 and 0.0 < got[k]["ST_conf"] < 0.1


def test_an_integer_range_gives_each_integer_an_equal_share():
    # Rounding lo + u (hi - lo) gave 1:4's ends half a share each (P(1) = P(4) = 1/6).
    d = sweep.lhs_design({"k": (1, 4), "x": (0.0, 1.0)}, 400, seed=2)
    counts = np.bincount([p["k"] for p in d.points], minlength=5)[1:]
    assert counts.tolist() == [100, 100, 100, 100]  # stratified: each quarter of the unit interval 100 times
    assert sweep._typed({"k": 4.0}, {"k": (1, 4)}) == {"k": 4} and sweep._typed({"k": 1.0}, {"k": (1, 4)}) == {"k": 1}
    assert sweep._typed({"k": 3.0}, {"k": (3, 3)}) == {"k": 3}


def test_sobol_indices_of_a_constant_response_are_undefined_not_zero():
    pytest.importorskip("SALib")
    d = sweep.sobol_design({"x1": (0.0, 1.0), "x2": (0.0, 1.0)}, 64, seed=1)
    # Every case landed with the same figure (a response that no factor moves): no variance to apportion.
    for y in (np.full(len(d.points), 3.5), np.zeros(len(d.points))):
        got = sweep.sobol_indices(d, y)
        assert all(v is None for per in got.values() for v in per.values()), got  # SALib: 0 +- 0 for both
    # A response that varies, however little, still gets its indices.
    x = np.array([[p["x1"], p["x2"]] for p in d.points])
    got = sweep.sobol_indices(d, 1e-9 * x[:, 0])
    assert got["x1"]["ST"] > 0.9 and abs(got["x2"]["ST"]) < 0.05, got


def test_pareto_front_and_requirements():
    pts = [{"f": 1.0, "s": 5.0, "m": 1.0, "ok": True},   # front
           {"f": 2.0, "s": 1.0, "m": 1.0, "ok": True},   # front
           {"f": 2.0, "s": 5.0, "m": 1.0, "ok": True},   # dominated by 0
           {"f": 0.5, "s": 0.5, "m": 0.5, "ok": False},  # dominates all, but fails the requirement
           {"f": 1.0, "s": 5.0, "m": 1.0, "ok": True},   # ties with 0: neither dominates
           {"f": None, "s": 1.0, "m": 1.0, "ok": True}]  # no value: not eligible
    assert sweep.pareto_front(pts, ("f", "s", "m"), [p["ok"] for p in pts]) == [0, 1, 4]
    assert sweep.pareto_front(pts, ("f", "s", "m")) == [3]
    r = sweep.parse_require("success_rate>=0.95")
    assert r.holds({"success_rate": 0.95}) and not r.holds({"success_rate": 0.9}) and not r.holds({"success_rate": None})


def _row(case, fuel, landed=True, vv=0.8, vh=0.1, miss=0.2):
    return {"case": case, "seed": 100 + case, "landed": landed, "fuel_used_kg": fuel, "touchdown_v_vertical_mps": vv,
            "touchdown_v_horizontal_mps": vh, "touchdown_miss_distance_m": miss, "case_wall_time_s": 1.0}


def test_fuel_ratio_to_gfold_is_case_by_case_at_the_same_other_design_values(tmp_path):
    d = sweep.grid_design([("guidance.law", ["zem_zev", "gfold"]), ("control.attitude_bandwidth_radps", [1, 2])])
    rows = {("zem_zev", 1): [_row(0, 90.0), _row(1, 120.0)], ("zem_zev", 2): [_row(0, 88.0), _row(1, 100.0)],
            ("gfold", 1): [_row(0, 80.0), _row(1, 100.0)], ("gfold", 2): [_row(0, 80.0), _row(1, 80.0, landed=False)]}
    all_rows = [rows[(p["guidance.law"], p["control.attitude_bandwidth_radps"])] for p in d.points]
    doc = sweep.summarise(d, all_rows, [1.0] * 4, [sweep.parse_require("success_rate>=0.95")], 2, 1)
    p = {(q["guidance.law"], q["control.attitude_bandwidth_radps"]): q for q in doc["points"]}
    assert p[("zem_zev", 1)]["fuel_ratio_gfold_mean"] == pytest.approx((90 / 80 + 120 / 100) / 2)
    assert p[("zem_zev", 2)]["fuel_ratio_gfold_mean"] == pytest.approx((88 / 80 + 100 / 80) / 2)
    assert p[("gfold", 1)]["fuel_ratio_gfold_mean"] == 1.0
    assert p[("gfold", 2)]["success_rate"] == 0.5 and not p[("gfold", 2)]["meets_require"]
    lo, hi = p[("gfold", 2)]["success_wilson_low"], p[("gfold", 2)]["success_wilson_high"]
    assert lo < 0.5 < hi
    sweep.write_tables(doc, all_rows, tmp_path)
    cases = pq.read_table(tmp_path / sweep.CASES_PARQUET).to_pylist()
    assert [c["fuel_ratio_gfold"] for c in cases[:2]] == pytest.approx([90 / 80, 120 / 100])
    from bench.report.sweep_html import render_sweep_html

    html = render_sweep_html(doc)
    assert "scatter-matrix" in html and "pareto-0" in html
    # Points that meet the requirements but lack an objective (no touchdown in their cases): the front is empty
    # for that reason, not because "no point meets the requirements" (which the page had said beside "3 of 4").
    blind = {**doc, "points": [{**q, "pareto": False, "miss_p95_m": None} for q in doc["points"]]}
    html = render_sweep_html(blind)
    assert "no point meets the requirements" not in html and "3 points meeting the requirements lack a value" in html


def test_the_design_can_be_a_sweep_table_in_the_scenario_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('seed = 3\n[sweep]\nruns = 4\nrequire = ["success_rate>=0.9"]\n'
                 '[sweep.grid]\n"guidance.law" = ["zem_zev", "apollo"]\n"control.attitude_bandwidth_radps" = [1.0, 2.0]\n')
    data, base, table = sweep.split_sweep_table(f)
    assert "sweep" not in data and table["runs"] == 4
    d = sweep.design_from_args([], None, None, [], 0, table)
    assert d.kind == "grid" and len(d.points) == 4 and d.points[1] == {"guidance.law": "zem_zev",
                                                                       "control.attitude_bandwidth_radps": 2.0}
    f.write_text('[sweep]\nrunz = 4\n')
    with pytest.raises(ValueError, match="unknown field 'sweep.runz'"):
        sweep.split_sweep_table(f)
    assert read_scenario_data(None)[0]["seed"] == 1


def test_a_gfold_partner_case_that_used_no_fuel_gives_no_ratio_instead_of_a_crash():
    # A case whose G-FOLD partner burned nothing (its computer down for the whole short run) made the
    # summary divide by zero after every case had flown, and no statistics or report were written.
    d = sweep.design_from_args(['guidance.law="zem_zev","gfold"'], None, None, [], 0)
    assert [p["guidance.law"] for p in d.points] == ["zem_zev", "gfold"]
    rows = [[{"case": 0, "fuel_used_kg": 10.0}, {"case": 1, "fuel_used_kg": 12.0}],
            [{"case": 0, "fuel_used_kg": 0.0}, {"case": 1, "fuel_used_kg": 6.0}]]
    ratios = sweep.case_fuel_ratios(d, rows)
    assert np.isnan(ratios[0][0]) and ratios[0][1] == pytest.approx(2.0)
    np.testing.assert_array_equal(ratios[1], [math.nan, 1.0])  # 0 / 0: no ratio either


def test_a_grid_range_with_an_infinite_count_is_refused_in_one_line():
    with pytest.raises(ValueError, match="too many values"):
        sweep.design_from_args(["guidance.gate_altitude_m=range(0, 1e308, 1e-308)"], None, None, [], 0)
