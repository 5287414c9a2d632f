"""Ensemble consistency statistics (bench/evaluation/consistency.py) against textbook values and explicit loops."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bench.evaluation.consistency import (
    MIN_SPREAD_CASES,
    NEES_ALTITUDES_M,
    NEES_BLOCKS,
    block_nees,
    campaign_consistency,
    chi2_band,
    consistency_table,
    consistent_in_band_share,
    run_consistency,
    step_correlation,
    step_phi,
)
from bench.report.io import json_safe
from bench.campaign.mc import summary_row


def test_band_matches_bar_shalom_textbook_example():
    # Bar-Shalom, Li & Kirubarajan (2001), sec. 5.4.2: 50 runs of a 2-state filter, the two-sided 95 %
    # region of the average NEES is [1.5, 2.6].
    lo, hi = chi2_band(50, 2)
    assert round(lo, 1) == 1.5 and round(hi, 1) == 2.6
    assert chi2_band(0, 2) is None


def test_block_nees_matches_an_explicit_inverse():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 20))
    P = A @ A.T + 20 * np.eye(20)
    e = rng.normal(size=9)
    got = block_nees(e, P)
    idx = {"r_h": [0, 1], "r_v": [2], "v_h": [3, 4], "v_v": [5], "b_a": [6, 7, 8]}
    for value, block in zip(got, NEES_BLOCKS):
        i = idx[block]
        want = e[i] @ np.linalg.inv(P[np.ix_(i, i)]) @ e[i]
        assert value == pytest.approx(want, rel=1e-12)


def test_block_nees_of_a_singular_block_is_nan():
    # The closed forms of the 1x1 and 2x2 blocks give NaN where a solve would fail, as the 3x3 one does.
    rng = np.random.default_rng(1)
    e = rng.normal(size=9)
    P = np.eye(9)
    P[2, 2] = 0.0           # r_v
    P[3:5, 3:5] = 1.0       # v_h: rank 1
    P[6:9, 6:9] = 0.0       # b_a
    got = dict(zip(NEES_BLOCKS, block_nees(e, P)))
    assert np.isnan(got["r_v"]) and np.isnan(got["v_h"]) and np.isnan(got["b_a"])
    assert got["r_h"] == pytest.approx(e[0] ** 2 + e[1] ** 2) and got["v_v"] == pytest.approx(e[5] ** 2)


def _telemetry(rng, z0=510.0):
    t = np.arange(0.0, 60.0, 0.02)
    z = np.maximum(z0 - 9.0 * t, 0.0)
    tel = {"t_s": t, "r_z_m": z}
    for block, dof in NEES_BLOCKS.items():
        tel[f"nees_{block}"] = rng.chisquare(dof, t.size)
    return tel


def _as_written(doc):
    """A document as it reads back from its JSON file."""
    return json.loads(json.dumps(json_safe(doc)))


def _case_row(tel, log=()):
    """A campaign row of one run's consistency (touchdown at 59 s), as written."""
    return _as_written(summary_row({"consistency": run_consistency(tel, {"t_s": 59.0}, list(log))}))


def test_a_consistent_ensemble_is_inside_its_bands_and_the_table_reads_it():
    rng = np.random.default_rng(1)
    rows = []
    for case in range(200):
        tel = _telemetry(rng)
        log = []
        for k in range(300):  # vision updates 0.1 s apart, white normalised innovations
            y = rng.normal(size=2)
            log.append(SimpleNamespace(t_ns=int(k * 1e8), kind="vision", nis=float(y @ y), accepted=True,
                                       y=y, S=np.eye(2)))
        rows.append(_case_row(tel, log))
    doc = campaign_consistency(rows)
    assert doc["n_cases"] == 200
    in_band = sum(sum(b["in_band"]) for b in doc["blocks"].values())
    cells = len(NEES_BLOCKS) * (len(NEES_ALTITUDES_M) + 1)
    assert in_band >= cells - 3  # 95 % bands: about 1.8 of 35 cells out by chance
    v = doc["nis"]["vision"]
    assert v["band"][0] <= v["mean"] <= v["band"][1]
    assert abs(doc["vision_lag1"]["x"]) < 0.02 and abs(doc["vision_lag1"]["y"]) < 0.02
    text = consistency_table(_as_written(doc))
    assert "v_h" in text and "NIS vision" in text and "NIS altimeter: no updates" in text


def test_lag1_autocorrelation_matches_an_explicit_loop_and_sees_ma1_noise():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(401, 2))
    e = d[1:] - d[:-1]  # MA(1) with rho = -1/2: a shared frame in consecutive pairs
    log = [SimpleNamespace(t_ns=int(k * 1e8), kind="vision", nis=float(v @ v), accepted=True, y=v,
                           S=2.0 * np.eye(2)) for k, v in enumerate(e)]
    tel = _telemetry(rng)
    out = run_consistency(tel, None, log)["vision_lag1"]
    for i, ax in enumerate("xy"):
        x = e[:, i] / math.sqrt(2.0)
        x = x - x.mean()
        num = sum(x[k] * x[k + 1] for k in range(len(x) - 1)) / (len(x) - 1)
        rho = num / (sum(v * v for v in x) / len(x))
        got = (out[ax]["sum_prod"] / out[ax]["n_pairs"]) / (out[ax]["sum_sq"] / out[ax]["n"])
        assert got == pytest.approx(rho, rel=1e-9)
        assert -0.6 < got < -0.4


def test_a_case_that_starts_below_an_altitude_has_no_value_there():
    rng = np.random.default_rng(3)
    out = run_consistency(_telemetry(rng, z0=495.0), {"t_s": 59.0}, [])
    assert out["nees_at"]["500"] is None and out["nees_at"]["300"] is not None


def test_block_nees_many_equals_block_nees_bit_for_bit():
    from bench.evaluation.consistency import block_nees, block_nees_many

    rng = np.random.default_rng(11)
    A = rng.normal(size=(300, 24, 24))
    P = A @ A.transpose(0, 2, 1) + 1e-3 * np.eye(24)
    e = rng.normal(size=(300, 9)) * rng.uniform(0.01, 30.0, (300, 1))
    one_by_one = np.array([block_nees(e[i], P[i]) for i in range(300)])
    assert block_nees_many(e, P).tobytes() == one_by_one.tobytes()
    P[7, 3:5, 3:5] = 0.0  # a singular v_h block: NaN there, as block_nees gives, the rest unchanged
    one_by_one = np.array([block_nees(e[i], P[i]) for i in range(300)])
    many = block_nees_many(e, P)
    assert np.isnan(many[7, 2]) and np.isnan(one_by_one[7, 2])
    assert np.array_equal(many, one_by_one, equal_nan=True)


def test_nees_profile_equals_an_explicit_loop_over_the_grid():
    from bench.evaluation.consistency import NEES_PROFILE_ALTITUDES_M, nees_profile

    rng = np.random.default_rng(21)
    t = np.arange(0.0, 80.0, 0.1)
    # A descent that climbs back twice (a divert, a hover's bobbing) and starts at 480 m: the rule
    # is the first flying tick at or below each altitude, not the last and not an interpolation.
    z = 480.0 - 6.5 * t + 25.0 * np.sin(t / 4.0) + rng.normal(0.0, 0.5, t.size)
    flying = t < 75.0
    nees = {block: rng.chisquare(dof, t.size) for block, dof in NEES_BLOCKS.items()}
    nees["v_h"][100] = np.nan
    got = nees_profile(z, flying, nees)
    for block in NEES_BLOCKS:
        assert len(got[block]) == len(NEES_PROFILE_ALTITUDES_M)
        for j, h in enumerate(NEES_PROFILE_ALTITUDES_M):
            want = None
            for k in range(t.size):
                if flying[k] and z[k] <= h:
                    if k > 0 and np.isfinite(nees[block][k]):
                        want = float(nees[block][k])
                    break
            assert got[block][j] == want, (block, h)
    assert got["r_h"][0] is None  # 500 m: the case starts at 480 m
    assert got["r_h"][-1] is not None


def test_per_step_ensemble_nees_is_in_band_for_a_consistent_filter_and_not_for_a_wrong_one():
    rng = np.random.default_rng(22)

    t = np.arange(0.0, 60.0, 0.1)  # 1 m per tick: finer than the 2 m grid
    rows_by_scale = {1.0: [], 2.0: [], 0.4: []}
    for _ in range(120):
        z = np.maximum(rng.uniform(505.0, 560.0) - 10.0 * t, 0.0)  # on the ground before t = 59 s
        nees = {block: rng.chisquare(dof, t.size) for block, dof in NEES_BLOCKS.items()}
        for scale, rows in rows_by_scale.items():
            tel = {"t_s": t, "r_z_m": z, **{f"nees_{b}": v * scale for b, v in nees.items()}}
            rows.append(_case_row(tel))

    def campaign(scale):
        return campaign_consistency(rows_by_scale[scale])

    ok = campaign(1.0)["steps"]
    assert ok["n_cases"] == 120
    for block, b in ok["blocks"].items():
        assert b["steps"] == 250 and b["n"][0] == 120
        # 95 % bands, steps independent here: ~237.5 of 250 inside, sd ~3.4.
        assert b["in_band_frac"] >= 0.9, (block, b["in_band_frac"])
        j = 37  # one step's ANEES and band by hand
        by_hand = sum(row["nees_profile"][block][j] for row in rows_by_scale[1.0]) / 120
        assert b["anees"][j] == pytest.approx(by_hand, rel=1e-12)
        assert b["band"][j] == pytest.approx(chi2_band(120, b["dof"]))
    over = campaign(2.0)["steps"]["blocks"]
    under = campaign(0.4)["steps"]["blocks"]
    for block in NEES_BLOCKS:
        assert over[block]["above"] >= 245 and over[block]["in_band_frac"] < 0.05
        assert under[block]["below"] >= 245
    doc = campaign(1.0)
    text = consistency_table(_as_written(doc))
    assert "per step (2 m grid, 500-2 m" in text and "r_h" in text
    assert "spread of the cases' NEES" in text
    # Steps independent here: a consistent filter's share of them in band is about 0.95, and this one's is
    # typical of it; the wrong ones' are not.
    assert "a consistent filter, steps correlated as these (phi 0.0" in text
    for block in NEES_BLOCKS:
        ref = ok["blocks"][block]["consistent_share"]
        assert ref["phi"] < 0.2 and 0.93 < ref["mean"] < 0.97 and ref["p"] > 0.02, (block, ref)
        assert over[block]["consistent_share"]["p"] == 0.0 and under[block]["consistent_share"]["p"] == 0.0


def test_the_spread_of_the_cases_nees_shows_a_mixture_that_the_ensemble_mean_hides():
    """Half the cases over-confident by 1.5, half conservative by 0.5: the ANEES is a consistent filter's,
    the spread (the NEES's squared coefficient of variation across cases over a chi-square's 2 / dof) is
    1.25 + dof / 8 instead of 1, and each step's value is the one computed by hand. Every case conservative
    by the same 0.4 leaves the spread at 1: a common scale shows in the ANEES, not here."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 60.0, 0.1)
    consistent, mixed, scaled = [], [], []
    for i in range(400):
        z = np.maximum(rng.uniform(505.0, 560.0) - 10.0 * t, 0.0)
        nees = {block: rng.chisquare(dof, t.size) for block, dof in NEES_BLOCKS.items()}
        for scale, rows in ((1.0, consistent), (0.5 if i % 2 else 1.5, mixed), (0.4, scaled)):
            tel = {"t_s": t, "r_z_m": z, **{f"nees_{b}": v * scale for b, v in nees.items()}}
            rows.append(_case_row(tel))
    ok = campaign_consistency(consistent)["steps"]["blocks"]
    mix = campaign_consistency(mixed)["steps"]["blocks"]
    low = campaign_consistency(scaled)["steps"]["blocks"]
    for block, dof in NEES_BLOCKS.items():
        assert ok[block]["spread_median"] == pytest.approx(1.0, abs=0.08), block
        assert low[block]["spread_median"] == pytest.approx(ok[block]["spread_median"], rel=1e-9), block
        assert low[block]["below"] >= 245, block
        assert mix[block]["spread_median"] == pytest.approx(1.25 + dof / 8, rel=0.1), block
        assert 0.85 < np.nanmedian(np.array(mix[block]["anees"], float)) / dof < 1.15, block  # the mean is right
        j = 37
        column = [row["nees_profile"][block][j] for row in mixed]
        by_hand = np.var(column, ddof=1) / np.mean(column) ** 2 / (2 / dof)
        assert mix[block]["spread"][j] == pytest.approx(by_hand, rel=1e-9), block
    # Under two cases at a step the spread is not defined.
    one = campaign_consistency(consistent[:1])["steps"]["blocks"]["r_h"]
    assert math.isnan(one["spread_median"]) and all(math.isnan(v) for v in one["spread"])
    # The table prints it from MIN_SPREAD_CASES cases on; consistency.json carries it at any count.
    few = campaign_consistency(mixed[:MIN_SPREAD_CASES - 1])
    assert math.isfinite(few["steps"]["blocks"]["r_h"]["spread_median"])
    assert "spread of the cases' NEES" not in consistency_table(_as_written(few))
    enough = campaign_consistency(mixed[:MIN_SPREAD_CASES])
    assert "spread of the cases' NEES" in consistency_table(_as_written(enough))


def test_the_cases_that_keep_the_ensemble_nees_out_of_its_band_are_named():
    """One case whose NEES is 40 times its mean at every step among 60 consistent ones: it is the first of
    ``drivers``, with the gain that the campaign without it gives, computed again from the other rows."""
    rng = np.random.default_rng(9)
    t = np.arange(0.0, 60.0, 0.1)
    rows = []
    for i in range(60):
        z = np.maximum(rng.uniform(505.0, 560.0) - 10.0 * t, 0.0)
        nees = {b: np.full(t.size, 40.0 * dof) if i == 17 else rng.chisquare(dof, t.size)
                for b, dof in NEES_BLOCKS.items()}
        tel = {"t_s": t, "r_z_m": z, **{f"nees_{b}": v for b, v in nees.items()}}
        row = _case_row(tel)
        row["case"] = 100 + i
        rows.append(row)
    steps = campaign_consistency(rows)["steps"]
    without = campaign_consistency(rows[:17] + rows[18:])["steps"]
    for block in NEES_BLOCKS:
        b = steps["blocks"][block]
        assert b["above"] > 200, block  # the one case takes the ANEES out of its band
        first = b["drivers"][0]
        assert first["case"] == 117, (block, b["drivers"])
        assert first["gain"] == without["blocks"][block]["in_band"] - b["in_band"] > 180, block
        assert len(b["drivers"]) <= 3 and all(d["gain"] > 0 for d in b["drivers"])
    text = consistency_table(_as_written(campaign_consistency(rows)))
    assert "cases that most keep it out of its band: 117 (+" in text
    # Too few cases to leave one out: none named; under MIN_SPREAD_CASES the table does not print them.
    assert campaign_consistency(rows[:2])["steps"]["blocks"]["r_h"]["drivers"] == []
    few = campaign_consistency(rows[10:10 + MIN_SPREAD_CASES - 1])
    assert few["steps"]["blocks"]["r_h"]["drivers"]
    assert "cases that most keep it out" not in consistency_table(_as_written(few))


def _gauss_markov_nees(rng, n_cases, dof, phi, T, start=None):
    """Cases' NEES over T steps of a consistent filter whose error is first-order Gauss-Markov from step to
    step (each of dof components x_k = phi x_(k-1) + sqrt(1 - phi^2) w_k), by explicit loops; NaN before
    each case's ``start`` step (the steps it never reached)."""
    vals = np.full((n_cases, T), np.nan)
    for i in range(n_cases):
        x = rng.normal(size=dof)
        for k in range(T):
            if k:
                x = phi * x + math.sqrt(1.0 - phi * phi) * rng.normal(size=dof)
            if start is None or k >= start[i]:
                vals[i, k] = float(x @ x)
    return vals


def test_step_correlation_is_the_explicit_sum_over_cases_and_pairs_of_steps():
    rng = np.random.default_rng(3)
    vals = rng.chisquare(2, (6, 14))
    vals[1, :4] = np.nan
    vals[4, 9:] = np.nan
    finite = np.isfinite(vals)
    got = step_correlation(vals, finite)
    mean = [np.mean([vals[i, t] for i in range(6) if finite[i, t]]) for t in range(14)]
    for k in range(14):
        num = sa = sb = 0.0
        for i in range(6):
            for t in range(14 - k):
                if finite[i, t] and finite[i, t + k]:
                    a, b = vals[i, t] - mean[t], vals[i, t + k] - mean[t + k]
                    num, sa, sb = num + a * b, sa + a * a, sb + b * b
        assert got[k] == pytest.approx(num / math.sqrt(sa * sb), rel=1e-9, abs=1e-12), k
    assert got[0] == pytest.approx(1.0)


def test_step_phi_recovers_the_correlation_of_a_gauss_markov_error():
    rng = np.random.default_rng(8)
    for phi, dof in ((0.97, 2), (0.99, 1), (0.9, 3)):
        start = rng.integers(0, 40, 150)
        vals = _gauss_markov_nees(rng, 150, dof, phi, 250, start)
        est = step_phi(step_correlation(vals, np.isfinite(vals)))
        assert est == pytest.approx(phi, abs=0.01), (phi, dof, est)
    white = rng.chisquare(2, (150, 250))
    assert step_phi(step_correlation(white, np.isfinite(white))) < 0.1


def test_consistent_in_band_share_agrees_with_flying_the_cases_themselves():
    """The reference's draws (the ANEES as a Gaussian AR(1) through the chi-square quantile) against the
    exact thing: each of 40 cases' two error components drawn as Gauss-Markov sequences and the ANEES of
    the campaign taken step by step, 300 campaigns each way; and, with independent steps, its 5 % quantile
    against the binomial one. The data's own campaign is drawn by explicit loops."""
    from scipy.stats import binom

    rng = np.random.default_rng(12)
    n_cases, dof, T = 40, 2, 250
    lo_hi = chi2_band(n_cases, dof)
    lo, hi = np.full(T, lo_hi[0]), np.full(T, lo_hi[1])
    counted = np.ones(T, bool)
    for phi in (0.98, 0.9):
        data = _gauss_markov_nees(rng, n_cases, dof, phi, T)
        finite = np.isfinite(data)
        anees = data.mean(axis=0)
        share = float(((anees >= lo) & (anees <= hi)).mean())
        ref = consistent_in_band_share(data, finite, lo, hi, counted, dof, share, np.random.default_rng(1), 300)
        # 300 campaigns at once: every case's components as Gauss-Markov sequences, the ANEES step by step.
        x = rng.normal(size=(300, n_cases, dof))
        inside = np.zeros(300)
        for k in range(T):
            if k:
                x = ref["phi"] * x + math.sqrt(1.0 - ref["phi"] ** 2) * rng.normal(size=x.shape)
            a = (x * x).sum(axis=2).mean(axis=1)
            inside += (a >= lo[k]) & (a <= hi[k])
        exact = inside / T
        assert ref["mean"] == pytest.approx(np.mean(exact), abs=0.02), (phi, ref, np.mean(exact))
        assert ref["q05"] == pytest.approx(np.quantile(exact, 0.05), abs=0.05), (phi, ref, np.quantile(exact, 0.05))
        assert ref["p"] > 0.02  # a consistent campaign's share is not an outlier of its own reference
    white = rng.chisquare(dof, (n_cases, T))
    ref = consistent_in_band_share(white, np.isfinite(white), lo, hi, counted, dof, 0.95, np.random.default_rng(2))
    assert ref["q05"] == pytest.approx(binom.ppf(0.05, T, 0.95) / T, abs=0.012)
    # A conservative filter (every NEES times 0.6) is far outside: p = 0.
    low = 0.6 * white
    share = float(((low.mean(axis=0) >= lo) & (low.mean(axis=0) <= hi)).mean())
    assert consistent_in_band_share(low, np.isfinite(low), lo, hi, counted, dof, share,
                                    np.random.default_rng(2))["p"] == 0.0
    # Under three cases there is nothing to correlate.
    assert consistent_in_band_share(white[:2], np.isfinite(white[:2]), lo, hi, counted, dof, 0.9,
                                    np.random.default_rng(2)) is None
