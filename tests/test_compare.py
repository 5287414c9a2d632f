"""``landbench compare``: paired A/B statistics of two campaigns, gates, and refused inputs.

The statistics are checked against independent computations (textbook Wilson
interval, a binomial test for McNemar, scipy's Wilcoxon, an explicit Holm
step-down loop) on synthetic campaign folders written with the campaign's own
writers; one small real end-to-end run compares two tiny campaigns.
"""

from __future__ import annotations

import json
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest, wilcoxon

from bench.campaign import mc
from bench.cli import build_parser, main
from bench.evaluation import compare as cmp
from bench.report.io import atomic_write_text
from bench.report.mc_report import wilson_interval
from bench.scenario import case_seeds, load_scenario

N = 20
CAMPAIGN_SEED = 7
LANDED_BASE = [i != 3 for i in range(N)]  # case 3 fails in BASE only
LANDED_CAND = [i not in (5, 8) for i in range(N)]  # cases 5 and 8 fail in CAND only
MISS_SHIFT = 0.3  # CAND's miss distance: BASE's + 0.3 m + noise
V_NAN_CASE = 4  # CAND's vertical speed is missing in this case


# ============================================================= synthetic campaigns
def write_campaign(path: Path, rows: list[dict], campaign_seed: int = CAMPAIGN_SEED) -> Path:
    """The files ``landbench mc`` writes, with its own writers (rows as given)."""
    (path / mc.CASES).mkdir(parents=True)
    atomic_write_text(path / mc.BASE_SCENARIO, "")  # the base scenario is not read by compare
    atomic_write_text(path / mc.CAMPAIGN, json.dumps({"campaign_seed": campaign_seed, "runs": len(rows),
                                                      "retention": "summary"}, indent=2) + "\n")
    for r in rows:
        mc._write_row(path / mc.CASES, r)
    mc.write_cases_parquet(mc.read_rows(path, len(rows)), path / mc.CASES_PARQUET)
    return path


def _rows(landed, miss, v_vert, fuel, tilt, seeds, disp, wall):
    rows = []
    for i in range(len(seeds)):
        rows.append({
            "case": i, "seed": seeds[i], "disp_lander.dry_mass_kg": float(disp[i]),
            "disp_initial.r_BL_L_m_0": float(disp[i] / 100.0),
            "outcome": "landed" if landed[i] else "hard_landing", "landed": bool(landed[i]),
            "touchdown_miss_distance_m": float(miss[i]),
            "touchdown_v_vertical_mps": None if np.isnan(v_vert[i]) else float(v_vert[i]),
            "touchdown_tilt_deg": float(tilt[i]), "fuel_used_kg": float(fuel[i]),
            "vision_frames": 100 + i, "guidance_law": "apollo", "camera_enabled": False,
            "case_wall_time_s": float(wall[i]), "wall_time_s": float(wall[i]) * 0.9,
        })
    return rows


@pytest.fixture(scope="module")
def synth():
    """BASE and CAND arrays with known paired differences."""
    rng = np.random.default_rng(12345)
    seeds = case_seeds(CAMPAIGN_SEED, N)
    disp = rng.normal(600.0, 20.0, N)
    miss_b = rng.uniform(0.0, 5.0, N)
    miss_c = miss_b + MISS_SHIFT + rng.normal(0.0, 0.05, N)
    v_b = rng.uniform(0.5, 1.5, N)
    v_c = v_b + rng.normal(0.0, 0.1, N)
    v_c[V_NAN_CASE] = np.nan
    tilt_b = rng.uniform(0.0, 2.0, N)
    tilt_c = tilt_b - 0.05 + rng.normal(0.0, 0.2, N)
    fuel = rng.uniform(80.0, 90.0, N)
    base = _rows(LANDED_BASE, miss_b, v_b, fuel, tilt_b, seeds, disp, rng.uniform(5, 10, N))
    cand = _rows(LANDED_CAND, miss_c, v_c, fuel, tilt_c, seeds, disp, rng.uniform(5, 10, N))  # other wall times
    return {"base": base, "cand": cand, "miss": (miss_b, miss_c), "v": (v_b, v_c), "tilt": (tilt_b, tilt_c),
            "fuel": (fuel, fuel)}


@pytest.fixture
def pair(tmp_path, synth):
    return write_campaign(tmp_path / "base", synth["base"]), write_campaign(tmp_path / "cand", synth["cand"])


def _holm_stepdown(p: np.ndarray) -> np.ndarray:
    """Holm (1979), step-down: sort ascending, multiply the k-th smallest by (m - k), keep monotone, cap at 1."""
    m = len(p)
    adjusted = np.empty(m)
    running = 0.0
    for k, i in enumerate(np.argsort(p, kind="stable")):
        running = max(running, min(1.0, (m - k) * p[i]))
        adjusted[i] = running
    return adjusted


# ============================================================= statistics
def test_wilson_matches_the_textbook_example():
    from statsmodels.stats.proportion import proportion_confint

    low, high = cmp.wilson_interval(95, 100)  # the one Wilson interval compare and the campaign report use
    assert (round(low, 3), round(high, 3)) == (0.888, 0.978)
    assert np.allclose((low, high), proportion_confint(95, 100, alpha=0.05, method="wilson"), atol=1e-9)
    assert np.allclose(cmp.wilson_interval(20, 20), proportion_confint(20, 20, alpha=0.05, method="wilson"), atol=1e-9)


def test_exact_mcnemar_is_a_binomial_test_on_the_discordant_pairs():
    # 12 both landed, 1 BASE only, 6 CAND only, 1 neither.
    base = [True] * 12 + [True] + [False] * 6 + [False]
    cand = [True] * 12 + [False] + [True] * 6 + [False]
    res = cmp.mcnemar_exact(base, cand)
    assert res["table"] == [[12, 1], [6, 1]] and (res["lost"], res["gained"]) == (1, 6)
    # By hand: P(X <= 1 | n=7, 1/2) = 8/128, doubled.
    assert res["pvalue"] == pytest.approx(binomtest(1, 7, 0.5).pvalue, abs=1e-12)
    assert res["pvalue"] == pytest.approx(16 / 128, abs=1e-12)
    assert cmp.mcnemar_exact([True, False], [True, False])["pvalue"] == 1.0  # no discordant pair


def test_paired_differences_wilcoxon_and_holm_against_independent_computations(pair, synth):
    doc = cmp.compare_campaigns(*pair)
    metrics = doc["metrics"]
    # Identifiers, dispersions, wall times, booleans and strings are not metrics.
    assert set(metrics) == {"touchdown_miss_distance_m", "touchdown_v_vertical_mps", "touchdown_tilt_deg",
                            "fuel_used_kg", "vision_frames"}
    for key, name in (("touchdown_miss_distance_m", "miss"), ("touchdown_tilt_deg", "tilt")):
        b, c = synth[name]
        m = metrics[key]
        assert m["n_used"] == N and m["n_dropped"] == 0
        assert m["diff"]["mean"] == pytest.approx(np.mean(c - b), abs=1e-12)
        assert m["diff"]["median"] == pytest.approx(np.median(c - b), abs=1e-12)
        assert m["wilcoxon_p"] == pytest.approx(wilcoxon(c - b).pvalue, rel=1e-12)
        assert m["base"]["p95"] == pytest.approx(np.percentile(b, 95)) and m["cand"]["max"] == pytest.approx(c.max())
        low, high = m["diff"]["bootstrap95"]
        assert low < m["diff"]["mean"] < high
    assert metrics["touchdown_miss_distance_m"]["diff"]["mean"] == pytest.approx(MISS_SHIFT, abs=0.05)
    assert metrics["touchdown_miss_distance_m"]["diff"]["bootstrap95"][0] > 0.25  # the shift is resolved
    # A missing value on one side drops that case for that metric only.
    v = metrics["touchdown_v_vertical_mps"]
    b, c = synth["v"]
    keep = np.arange(N) != V_NAN_CASE
    assert (v["n_used"], v["n_dropped"]) == (N - 1, 1)
    assert v["diff"]["mean"] == pytest.approx(np.mean(c[keep] - b[keep]), abs=1e-12)
    assert v["wilcoxon_p"] == pytest.approx(wilcoxon(c[keep] - b[keep]).pvalue, rel=1e-12)
    # All-zero differences: p = 1, identical, a zero-width interval.
    fuel = metrics["fuel_used_kg"]
    assert fuel["identical"] and fuel["wilcoxon_p"] == 1.0 and fuel["diff"]["bootstrap95"] == [0.0, 0.0]
    # Holm over every metric with a p-value, against the step-down loop.
    names = list(metrics)
    raw = np.array([metrics[k]["wilcoxon_p"] for k in names])
    assert np.allclose([metrics[k]["holm_p"] for k in names], _holm_stepdown(raw), rtol=0, atol=1e-12)
    assert doc["settings"]["holm_family"] == len(names)
    # The bootstrap is seeded: the same inputs give the same document.
    assert cmp.compare_campaigns(*pair) == doc
    assert doc["schema"] == cmp.SCHEMA and doc["version"] == cmp.VERSION


@pytest.mark.parametrize("n", [4, 5, 6, 8])
def test_success_verdict_follows_the_paired_exact_test(n):
    """Every case lands on one side and fails on the other: the two Wilson intervals part already at four
    cases, but four or five discordant pairs cannot reject equal rates at 5 % (p = 2 / 2^n); the verdict is
    the paired test's, recomputed here with scipy's binomial test."""
    base, cand = np.ones(n, bool), np.zeros(n, bool)
    s = cmp._success(base, cand)
    (bl, _), (_, ch) = wilson_interval(n, n), wilson_interval(0, n)
    assert ch < bl and not s["intervals_overlap"]  # the intervals part at every n here
    p = binomtest(0, n, 0.5).pvalue
    assert s["mcnemar"]["pvalue"] == pytest.approx(p, abs=1e-12)
    assert s["resolved"] is bool(p < 0.05) and s["resolved"] is (n >= 6)
    assert s["verdict"].startswith(f"{n} cases cannot resolve") is (n < 6)


def test_success_rates_flips_and_replay_commands(pair):
    doc = cmp.compare_campaigns(*pair, replay_root="out/replay")
    s = doc["success"]
    assert (s["base"]["landed"], s["cand"]["landed"]) == (19, 18)
    assert np.allclose(s["base"]["wilson95"], wilson_interval(19, 20)) and s["difference_pp"] == pytest.approx(-5.0)
    assert s["mcnemar"]["pvalue"] == pytest.approx(binomtest(1, 3, 0.5).pvalue)
    assert not s["resolved"] and s["verdict"].startswith("20 cases cannot resolve")
    flips = {f["case"]: f for f in doc["flipped"]}
    assert sorted(flips) == [3, 5, 8]
    assert flips[3]["direction"] == "gained" and flips[5]["direction"] == "lost"
    assert (flips[5]["base_outcome"], flips[5]["cand_outcome"]) == ("landed", "hard_landing")
    # Each command is a valid `landbench mc --replay` of that side's folder and case.
    for case, f in flips.items():
        for side, folder in zip(("base", "cand"), pair):
            argv = shlex.split(f["replay"][side])
            assert argv[0] == "landbench"
            args = build_parser().parse_args(argv[1:])
            assert (args.command, args.replay, args.case) == ("mc", str(folder), case)
            assert args.out == f"out/replay/{side}-{case:05d}"


# ============================================================= command line and gates
def _stdout_lines(capsys) -> list[str]:
    return capsys.readouterr().out.strip().splitlines()


def test_gates_pass_and_fail_through_the_cli(pair, tmp_path, capsys):
    base, cand = (str(p) for p in pair)
    out = tmp_path / "cmp"
    passing = ["success_rate:-10pp", "touchdown_miss_distance_m:p95:+0.5", "fuel_used_kg:max:+0",
               "touchdown_tilt_deg:+100%", "touchdown_miss_distance_m:median:-0.1"]
    assert main(["compare", base, cand, "--out", str(out), *[a for g in passing for a in ("--gate", g)]]) == 0
    lines = _stdout_lines(capsys)
    assert lines[-1] == f"all {len(passing)} gates passed"
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert doc["passed"] and [g["spec"] for g in doc["gates"]] == passing

    # success rate -5 pp > 2 pp allowed; miss p95 up ~0.3 m > 0.05; mean miss up far more than 1 %.
    failing = ["success_rate:-2pp", "touchdown_miss_distance_m:p95:+0.05", "touchdown_miss_distance_m:+1%"]
    assert main(["compare", base, cand, "--out", str(out), "--gate", "fuel_used_kg:+0",
                 *[a for g in failing for a in ("--gate", g)]]) == 1
    lines = _stdout_lines(capsys)
    assert lines[-1].startswith("FAILED gates:") and all(g in lines[-1] for g in failing)
    assert "fuel_used_kg" not in lines[-1]
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert not doc["passed"] and [g["passed"] for g in doc["gates"]] == [True, False, False, False]
    g = doc["gates"][2]  # the p95 gate
    assert g["change"] == pytest.approx(doc["metrics"]["touchdown_miss_distance_m"]["cand"]["p95"]
                                        - doc["metrics"]["touchdown_miss_distance_m"]["base"]["p95"])


def test_identical_inputs_give_zero_differences_and_exit_0(pair, tmp_path, capsys):
    base = pair[0]
    twin = tmp_path / "twin"
    shutil.copytree(base, twin)
    out = tmp_path / "cmp"
    assert main(["compare", str(base), str(twin), "--out", str(out), "--gate", "success_rate:-0pp",
                 "--gate", "touchdown_miss_distance_m:p95:+0"]) == 0
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert doc["flipped"] == [] and doc["success"]["mcnemar"]["pvalue"] == 1.0
    for m in doc["metrics"].values():
        assert m["identical"] and m["diff"]["mean"] == 0.0 and m["wilcoxon_p"] == 1.0 and m["holm_p"] == 1.0
    assert _stdout_lines(capsys)[-1] == "all 2 gates passed"


def test_timings_are_not_metrics_and_do_not_tell_two_runs_of_a_case_apart(synth):
    # The hazard scans' wall-clock timings (summary hazard_scan.compute_s, flattened) measure the machine.
    base = [{**r, "hazard_scan_compute_s_dem_s": 0.10 + 0.001 * i} for i, r in enumerate(synth["base"])]
    cand = [{**r, "hazard_scan_compute_s_dem_s": 0.20 + 0.001 * i} for i, r in enumerate(synth["base"])]
    assert "hazard_scan_compute_s_dem_s" not in cmp.metric_names(base, cand)
    assert [mc.landing_values(r) for r in base] == [mc.landing_values(r) for r in cand]
    assert mc.is_run_dependent("case_wall_time_s") and not mc.is_run_dependent("touchdown_miss_distance_m")


LLVMPIPE = "llvmpipe (LLVM 15.0.6, 256 bits)"
H100 = "NVIDIA H100 80GB HBM3/PCIe/SSE2"


def test_a_renderer_or_mujoco_version_that_differs_between_the_sides_is_noted(synth, tmp_path, capsys):
    # The rows as a campaign writes them (summary.json's platform, flattened); the CPU is no note's business.
    def platform(rows, renderer, mujoco, cpu):
        return [{**r, "platform_gl_renderer": renderer, "platform_mujoco": mujoco, "platform_cpu": cpu} for r in rows]

    def notes(base_rows, cand_rows, name):
        b = write_campaign(tmp_path / f"{name}-base", base_rows)
        c = write_campaign(tmp_path / f"{name}-cand", cand_rows)
        return cmp.compare_campaigns(b, c)["platform_notes"], b, c

    same, _, _ = notes(platform(synth["base"], LLVMPIPE, "4.0.0", "Xeon"),
                       platform(synth["cand"], LLVMPIPE, "4.0.0", "EPYC"), "same")
    assert same == []
    no_camera, _, _ = notes(platform(synth["base"], None, "4.0.0", "Xeon"),
                            platform(synth["cand"], H100, "4.0.0", "Xeon"), "camera-less")
    assert no_camera == []  # one side has no renderer: nothing to compare
    both, b, c = notes(platform(synth["base"], LLVMPIPE, "3.3.0", "Xeon"),
                       platform(synth["cand"], H100, "4.0.0", "Xeon"), "both")
    assert len(both) == 2
    assert both[0].startswith(f"BASE rendered its camera frames with {LLVMPIPE}, CAND with {H100}: ")
    assert both[1].startswith("BASE ran MuJoCo 3.3.0, CAND MuJoCo 4.0.0: ")
    # The notes reach the terminal (under the header line) and the HTML report; the comparison still runs.
    out = tmp_path / "cmp"
    assert main(["compare", str(b), str(c), "--out", str(out)]) == 0
    lines = _stdout_lines(capsys)
    assert lines[1] == f"  note: {both[0]}" and lines[2] == f"  note: {both[1]}"
    html = (out / "report.html").read_text()
    assert html.count('class="note platform-note"') == 2 and H100 in html


def _unpair(kind: str, base: Path, cand: Path, synth) -> None:
    if kind == "seed":
        shutil.rmtree(cand)
        write_campaign(cand, [{**r, "seed": s} for r, s in zip(synth["cand"], case_seeds(CAMPAIGN_SEED + 1, N))],
                       campaign_seed=CAMPAIGN_SEED + 1)
    elif kind == "missing":
        (cand / mc.CASES / "00002.json").unlink()
    elif kind == "count":
        shutil.rmtree(cand)
        write_campaign(cand, synth["cand"][: N - 1])
    elif kind == "dispersion":
        row = json.loads((cand / mc.CASES / "00006.json").read_text())
        row["disp_lander.dry_mass_kg"] += 1.0
        atomic_write_text(cand / mc.CASES / "00006.json", json.dumps(row))
    elif kind == "not-a-campaign":
        (cand / mc.CAMPAIGN).unlink()


@pytest.mark.parametrize("kind, needle", [
    ("seed", "case 0: seed"), ("missing", "case 2 has no row"), ("count", "has 20 cases"),
    ("dispersion", "case 6: disp_lander.dry_mass_kg"), ("not-a-campaign", "not a campaign folder"),
])
def test_unpaired_inputs_are_refused_with_one_line_and_nothing_written(pair, synth, tmp_path, capsys, kind, needle):
    base, cand = pair
    _unpair(kind, base, cand, synth)
    out = tmp_path / "cmp"
    assert main(["compare", str(base), str(cand), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("landbench: error:") and needle in err[0], err
    assert "--seed" in err[0] or "--resume" in err[0] or "landbench mc --out" in err[0]  # the fix is named
    assert not out.exists() and captured.out == ""


@pytest.mark.parametrize("gate", ["touchdown_miss_distance_m:p95", "touchdown_miss_distance_m:p99:+1",
                                  "touchdown_miss_distance_m:0.05", "success_rate:+2", "no_such_metric:+1",
                                  "guidance_law:+1", "disp_lander.dry_mass_kg:+1"])
def test_a_bad_gate_is_refused_before_anything_is_written(pair, tmp_path, capsys, gate):
    out = tmp_path / "cmp"
    assert main(["compare", str(pair[0]), str(pair[1]), "--out", str(out), "--gate", "success_rate:-2pp",
                 "--gate", gate]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("landbench: error: --gate") and repr(gate) in err[0]
    assert "allowed forms" in err[0] and not out.exists()


# ============================================================= a real end-to-end run
def test_two_tiny_real_campaigns_of_the_same_scenario_compare_identical(tmp_path, capsys):
    from tests.test_mc import QUICK

    base = load_scenario(None, QUICK)
    for name in ("a", "b"):
        mc.run_campaign(base, 2, tmp_path / name, campaign_seed=3, workers=2, progress=False)
    out = tmp_path / "cmp"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out),
                 "--gate", "success_rate:-2pp", "--gate", "touchdown_miss_distance_m:p95:+0"]) == 0
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert doc["n_cases"] == 2 and doc["success"]["base"]["landed"] == 2 and doc["flipped"] == []
    assert "touchdown_miss_distance_m" in doc["metrics"] and "case_wall_time_s" not in doc["metrics"]
    assert all(m["identical"] and m["diff"]["mean"] == 0.0 for m in doc["metrics"].values())
    assert _stdout_lines(capsys)[-1] == "all 2 gates passed"


# ============================================================= replays, per sequence and per frame
def test_replays_pair_per_sequence_and_per_frame_with_booleans(tmp_path):
    from tests.replay_synth import FRAMES_PER_SEQ, replay_pair

    base, cand, arrays = replay_pair(tmp_path)
    doc = cmp.compare_campaigns(base, cand, ["epe_median_px:+10%"])
    assert doc["kind"] == "replay" and doc["n_cases"] == 3 and not doc["passed"]
    e = doc["metrics"]["epe_median_px"]
    assert e["diff"]["mean"] == pytest.approx(np.mean([0.07 + 0.001 * s for s in (1, 2, 3)]), abs=1e-12)
    assert doc["values"]["metrics"]["epe_median_px"]["cand"] == pytest.approx([0.142, 0.144, 0.146])
    fr = doc["frames"]
    assert fr["n_frames"] == 3 * FRAMES_PER_SEQ and fr["paired_on"] == ["seed", "frame"]
    # Numeric columns, against independent computations on the arrays written.
    for key in ("tracks", "nis"):
        b, c = (np.asarray(a, float) for a in arrays[key])
        m = fr["metrics"][key]
        assert m["n_used"] == b.size and m["diff"]["mean"] == pytest.approx(np.mean(c - b), abs=1e-12)
        assert m["wilcoxon_p"] == pytest.approx(wilcoxon(c - b).pvalue, rel=1e-12)
    assert not {"seed", "frame", "t_ns", "t_s", "tracker_ms"} & set(fr["metrics"])  # identity and wall clock
    # Boolean columns: rates, Wilson intervals and an exact McNemar test (a binomial test on the discordant pairs).
    acc_b, acc_c = arrays["accepted"]
    a = fr["booleans"]["accepted"]
    only_b, only_c = int(np.sum(acc_b & ~acc_c)), int(np.sum(~acc_b & acc_c))
    assert (a["mcnemar"]["true_base_only"], a["mcnemar"]["true_cand_only"]) == (only_b, only_c)
    assert a["flipped"] == only_b + only_c == 9 and not a["identical"]
    assert a["mcnemar"]["pvalue"] == pytest.approx(binomtest(min(only_b, only_c), only_b + only_c, 0.5).pvalue)
    assert a["base"]["true"] == acc_b.sum() and np.allclose(a["base"]["wilson95"], wilson_interval(acc_b.sum(), acc_b.size))
    assert fr["booleans"]["measurement"]["identical"] and fr["booleans"]["measurement"]["mcnemar"]["pvalue"] == 1.0
    # Holm over the frame family (numeric Wilcoxon and boolean McNemar p-values), against the step-down loop.
    names = [("m", k) for k in fr["metrics"]] + [("b", k) for k in fr["booleans"]]
    raw = np.array([fr["metrics"][k]["wilcoxon_p"] if t == "m" else fr["booleans"][k]["mcnemar"]["pvalue"]
                    for t, k in names])
    got = [fr["metrics"][k]["holm_p"] if t == "m" else fr["booleans"][k]["holm_p"] for t, k in names]
    assert np.allclose(got, _holm_stepdown(raw), rtol=0, atol=1e-12) and fr["holm_family"] == len(names)
    # The per-frame values are kept, in (seed, frame) order, for the report's scatter plots.
    v = fr["values"]
    assert v["seed"][:2] == [1, 1] and v["frame"][:2] == [0, 1] and v["metrics"]["tracks"]["base"][:3] == \
        arrays["tracks"][0][:3].tolist()


def test_replay_frames_without_a_frame_column_pair_by_their_order_in_each_sequence(tmp_path):
    from tests.replay_synth import replay_pair

    with_col = cmp.compare_campaigns(*replay_pair(tmp_path / "a")[:2])["frames"]
    without = cmp.compare_campaigns(*replay_pair(tmp_path / "b", with_frame=False)[:2])["frames"]
    assert without["metrics"] == with_col["metrics"] and without["booleans"] == with_col["booleans"]


def test_replay_frames_at_different_times_are_refused(tmp_path, capsys):
    from bench.report.report import read_telemetry_parquet, write_telemetry_parquet
    from tests.replay_synth import replay_pair

    base, cand, _ = replay_pair(tmp_path)
    f = read_telemetry_parquet(cand / "frames.parquet")
    f["t_ns"] = f["t_ns"].copy()
    f["t_ns"][33] += 1
    write_telemetry_parquet(f, cand / "frames.parquet")
    out = tmp_path / "cmp"
    assert main(["compare", str(base), str(cand), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("landbench: error: frame 3 of seed 2 is at t_ns") and "\n" not in err
    assert not out.exists()


def test_a_minus_zero_gate_bounds_a_fall(synth, tmp_path, capsys):
    # "-0": may not fall at all. The tilt falls about 0.05 deg on average (synth), the miss rises 0.3 m:
    # a -0 gate fails the tilt and passes the miss (-0.0 >= 0 once read it as a +0 bound, both ways round).
    base = write_campaign(tmp_path / "base", synth["base"])
    cand = write_campaign(tmp_path / "cand", synth["cand"])
    tilt_change = float(np.mean(synth["tilt"][1] - synth["tilt"][0]))
    assert tilt_change < 0
    for gate in ("touchdown_tilt_deg:-0", "touchdown_tilt_deg:-0%"):
        assert main(["compare", str(base), str(cand), "--out", str(tmp_path / "c"), "--gate", gate]) == 1
        assert _stdout_lines(capsys)[-1] == f"FAILED gates: {gate}"
    assert main(["compare", str(base), str(cand), "--out", str(tmp_path / "c"), "--gate",
                 "touchdown_miss_distance_m:-0"]) == 0
    assert cmp.parse_gate("x:-0").bounds_fall and not cmp.parse_gate("x:+0").bounds_fall


def test_a_metric_the_candidate_lost_in_every_case_fails_its_gate(synth, tmp_path, capsys):
    # Every CAND case without a touchdown (say, all timed out): the gate cannot check, so it fails (exit 1)
    # and the comparison is written, instead of a bad-input refusal that a CI would read as a broken job.
    cand_rows = [{**r, "touchdown_miss_distance_m": None} for r in synth["cand"]]
    base = write_campaign(tmp_path / "base", synth["base"])
    cand = write_campaign(tmp_path / "cand", cand_rows)
    out = tmp_path / "c"
    assert main(["compare", str(base), str(cand), "--out", str(out), "--gate", "touchdown_miss_distance_m:+1",
                 "--gate", "success_rate:-50pp"]) == 1
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert [g["passed"] for g in doc["gates"]] == [False, True] and "CAND has no value" in doc["gates"][0]["reason"]
    capsys.readouterr()
    # A metric BASE does not have is still a bad gate (a typo): exit 2, nothing written.
    assert main(["compare", str(base), str(cand), "--out", str(tmp_path / "d"), "--gate", "bogus_metric:+1"]) == 2
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("damage", ["runs_zero", "row_is_a_list", "case_is_null", "runs_fraction", "seed_text"])
def test_a_damaged_campaign_is_refused_in_one_line(synth, tmp_path, capsys, damage):
    base = write_campaign(tmp_path / "base", synth["base"])
    cand = write_campaign(tmp_path / "cand", synth["cand"])
    if damage in ("runs_zero", "runs_fraction", "seed_text"):  # runs 1.5 was read as 1, silently
        meta = {"campaign_seed": "x" if damage == "seed_text" else CAMPAIGN_SEED,
                "runs": {"runs_zero": 0, "runs_fraction": 1.5}.get(damage, len(synth["cand"]))}
        (cand / mc.CAMPAIGN).write_text(json.dumps(meta))
    else:
        f = cand / mc.CASES / "00000.json"
        f.write_text("[1, 2]" if damage == "row_is_a_list" else json.dumps({**synth["cand"][0], "case": None}))
    assert main(["compare", str(base), str(cand), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("landbench: error: CAND") and str(cand) in err
    assert not (tmp_path / "c").exists()
