"""Filter consistency measured the way the field measures it (bench side: it needs truth).

One run cannot show that a filter is consistent: its horizontal position error
is one frozen draw, its samples are autocorrelated, and channels offset each
other in a pooled figure. So a run records, per error block, its NEES at fixed
altitudes and at touchdown, and per sensor the sums of its NIS; a campaign
averages them over its cases into the **ensemble NEES** (ANEES, Bar-Shalom,
Li & Kirubarajan 2001, sec. 5.4) and the mean NIS, each against its two-sided
chi-square band.

Blocks of the error ``e = x_hat - x_true`` (filter state minus truth):
    ``r_h`` horizontal position (2), ``r_v`` vertical position (1),
    ``v_h`` horizontal velocity (2), ``v_v`` vertical velocity (1),
    ``b_a`` accelerometer bias (3).

Bands: for ``N`` cases of a block with ``n`` degrees of freedom, ``N`` times the
ANEES is chi-square with ``N n`` degrees of freedom when the filter is
consistent, so the ANEES lies in ``chi2.ppf([a/2, 1 - a/2], N n) / N`` with
probability ``1 - a``. For ``k`` NIS samples of ``m`` degrees of freedom, the
mean NIS lies in ``chi2.ppf(..., k m) / k`` (independent samples).

Altitudes are the truth height of the body origin above the target's ground
elevation (``r_z`` in L); a block's NEES at altitude ``h`` is taken at the first
control tick at or below ``h``. A case that starts below ``h`` has no value there.

**Per step.** Besides those few altitudes, every run records each block's NEES on
a dense grid, every :data:`NEES_STEP_M` from :data:`NEES_STEP_TOP_M` down
(:data:`NEES_PROFILE_ALTITUDES_M`, the "steps" of the descent, aligned across
cases by altitude because the cases' trajectories differ in time). A campaign's
ANEES at each step against that step's band gives the share of steps inside
it: the filter is consistent throughout the descent, not only at a few heights.
Neighbouring steps are correlated (the same errors a second apart), so that share
is a description of where the filter is off, not a count of independent trials; it
is judged against the shares a consistent filter would give with that correlation
(:func:`consistent_in_band_share`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from bench.campaign.rows import column
from gnc.numeric import chi2_ppf

# Error blocks: name -> degrees of freedom; their indices in e = [r (3), v (3), b_a (3)].
NEES_BLOCKS: dict[str, int] = {"r_h": 2, "r_v": 1, "v_h": 2, "v_v": 1, "b_a": 3}
_BLOCK_INDEX: dict[str, list[int]] = {"r_h": [0, 1], "r_v": [2], "v_h": [3, 4], "v_v": [5], "b_a": [6, 7, 8]}
NEES_ALTITUDES_M = (500, 300, 150, 80, 30, 10)
NEES_STEP_TOP_M = 500  # [m] the dense grid's first altitude
NEES_STEP_M = 2  # [m] its spacing
NEES_PROFILE_ALTITUDES_M = tuple(range(NEES_STEP_TOP_M, 0, -NEES_STEP_M))  # 500, 498, ..., 2
TOUCHDOWN = "touchdown"
# NIS altitude bands [m], (low, high].
NIS_BANDS_M = ((400, 600), (120, 250), (30, 120))
NIS_SENSORS: dict[str, int] = {"altimeter": 1, "vision": 2}
BAND_PROB = 0.95
BAND_PROB_WIDE = 0.999
CONSISTENCY_FILE = "consistency.json"
SCHEMA_VERSION = 1
# Fewest cases for which the table prints the spread of the cases' NEES, the cases that drive the ANEES out
# of its band and what share of steps a consistent filter would have in band: one step's spread, for a
# consistent filter, scatters about 1 with a relative standard deviation of about sqrt((2 + 12 / dof) / N)
# (0.6 at 20 cases and 2 dof, 0.28 at 100), and leaving one case out of a few moves every step; under 20
# cases they say little. consistency.json carries them at any count.
MIN_SPREAD_CASES = 20


def block_nees(e: np.ndarray, P: np.ndarray) -> tuple[float, ...]:
    """NEES of each block, in :data:`NEES_BLOCKS` order.

    Args:
        e: Error ``[r (3), v (3), b_a (3)]``, (9,), in the filter's state order.
        P: The filter's covariance; its leading (9, 9) block is used.

    Returns:
        ``e_b^T P_bb^-1 e_b`` per block (NaN where the block is singular).
    """
    # Closed forms for the 1x1 and 2x2 blocks (every control tick calls this); a solve for the 3x3 one.
    out = []
    for block in NEES_BLOCKS:
        idx = _BLOCK_INDEX[block]
        if len(idx) == 1:
            i = idx[0]
            p, ei = float(P[i, i]), float(e[i])
            out.append(ei * ei / p if p != 0.0 else math.nan)
        elif len(idx) == 2:
            i, j = idx
            a, b, c, d = float(P[i, i]), float(P[i, j]), float(P[j, i]), float(P[j, j])
            det = a * d - b * c
            ei, ej = float(e[i]), float(e[j])
            out.append((d * ei * ei - (b + c) * ei * ej + a * ej * ej) / det if det != 0.0 else math.nan)
        else:
            eb = e[idx]
            try:
                out.append(float(eb @ np.linalg.solve(P[np.ix_(idx, idx)], eb)))
            except np.linalg.LinAlgError:
                out.append(math.nan)
    return tuple(out)


def block_nees_many(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """:func:`block_nees` of many samples at once, bit for bit the same values.

    Args:
        e: Errors, (N, 9), in the filter's state order.
        P: Covariances, (N, >=9, >=9); the leading (9, 9) blocks are used.

    Returns:
        (N, len(NEES_BLOCKS)) NEES values, NaN where a block is singular.
        One stacked ``np.linalg.solve`` per block (the same LAPACK solve per
        matrix as :func:`block_nees`), then the same 1-D dot product per sample.
    """
    e = np.asarray(e, float)
    P = np.asarray(P, float)
    out = np.empty((e.shape[0], len(NEES_BLOCKS)))
    for j, block in enumerate(NEES_BLOCKS):
        idx = _BLOCK_INDEX[block]
        if len(idx) == 1:  # block_nees's closed form, elementwise (the same IEEE operations in the same order)
            i = idx[0]
            p = P[:, i, i]
            with np.errstate(divide="ignore", invalid="ignore"):
                out[:, j] = np.where(p != 0.0, e[:, i] * e[:, i] / p, math.nan)
            continue
        if len(idx) == 2:
            i, k = idx
            a, b, c, d = P[:, i, i], P[:, i, k], P[:, k, i], P[:, k, k]
            det = a * d - b * c
            ei, ek = e[:, i], e[:, k]
            with np.errstate(divide="ignore", invalid="ignore"):
                out[:, j] = np.where(det != 0.0, (d * ei * ei - (b + c) * ei * ek + a * ek * ek) / det, math.nan)
            continue
        eb = e[:, idx]
        Pb = P[:, idx][:, :, idx]
        try:
            x = np.linalg.solve(Pb, eb[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # a singular block somewhere: one sample at a time, as block_nees does
            out[:, j] = [block_nees(e[i], P[i])[j] for i in range(e.shape[0])]
            continue
        out[:, j] = [float(a @ b) for a, b in zip(eb, x)]
    return out


def chi2_band(n_samples: int, dof: int, prob: float = BAND_PROB) -> list[float] | None:
    """Two-sided ``prob`` band of the mean of ``n_samples`` chi-square(``dof``) variables.

    A new list on every call, from a cache: a campaign's profile asks for the same few
    (count, dof) pairs at every altitude, and each quantile costs about 0.1 ms.
    """
    band = _chi2_band(n_samples, dof, prob)
    return None if band is None else list(band)


@functools.lru_cache(maxsize=4096)
def _chi2_band(n_samples: int, dof: int, prob: float) -> tuple[float, float] | None:
    if n_samples <= 0:
        return None
    k = n_samples * dof
    a = 0.5 * (1.0 - prob)
    return float(chi2_ppf(a, k) / n_samples), float(chi2_ppf(1.0 - a, k) / n_samples)


def _band_key(lo: float, hi: float) -> str:
    return f"{lo:g}_{hi:g}"


def run_consistency(tel: Mapping[str, np.ndarray], touchdown: Mapping[str, Any] | None,
                    log: Sequence[Any]) -> dict[str, Any]:
    """One run's contribution to the ensemble statistics.

    Args:
        tel: The run's telemetry columns (``t_s``, ``r_z_m``, ``nees_<block>``).
        touchdown: The touchdown metrics (``t_s``), or None.
        log: The filter's update records (``t_ns``, ``kind``, ``y``, ``S``, ``nis``, ``accepted``).

    Returns:
        ``{"nees_at": {"500": {block: NEES} | None, ..., "touchdown": ...},
        "nis": {sensor: {"dof", "n", "sum", "rejected", "bands": {"400_600": {"n", "sum"}, ...}}},
        "vision_lag1": {"x"|"y": {"n", "sum_sq", "n_pairs", "sum_prod"}},
        "nees_profile": {block: [NEES or None per NEES_PROFILE_ALTITUDES_M]}}``: sums
        and samples, so that a campaign can pool them.
    """
    out: dict[str, Any] = {"nees_at": {}, "nis": {}, "vision_lag1": {}, "nees_profile": {}}
    if not tel:
        return out
    t = np.asarray(tel["t_s"], float)
    z = np.asarray(tel["r_z_m"], float)
    flying = t < touchdown["t_s"] if touchdown is not None else np.ones(t.size, bool)
    idx_flying = np.flatnonzero(flying)

    def nees_row(k: int) -> dict[str, float]:
        return {block: float(tel[f"nees_{block}"][k]) for block in NEES_BLOCKS}

    for alt, k in zip(NEES_ALTITUDES_M, ticks_at_altitudes(z, flying, NEES_ALTITUDES_M)):
        out["nees_at"][str(alt)] = nees_row(int(k)) if k >= 0 else None
    out["nees_at"][TOUCHDOWN] = nees_row(int(idx_flying[-1])) if touchdown is not None and idx_flying.size else None
    out["nees_profile"] = nees_profile(z, flying, {b: np.asarray(tel[f"nees_{b}"], float) for b in NEES_BLOCKS})

    for sensor, dof in NIS_SENSORS.items():
        recs = [r for r in log if r.kind == sensor and math.isfinite(r.nis)]
        used = [r for r in recs if r.accepted]
        nis = np.array([r.nis for r in used])
        alt = np.interp([r.t_ns / 1e9 for r in used], t, z) if used else np.zeros(0)
        bands = {}
        for lo, hi in NIS_BANDS_M:
            sel = (alt > lo) & (alt <= hi)
            bands[_band_key(lo, hi)] = {"n": int(sel.sum()), "sum": float(nis[sel].sum())}
        out["nis"][sensor] = {"dof": dof, "n": int(nis.size), "sum": float(nis.sum()),
                              "rejected": len(recs) - len(used), "bands": bands}

    out["vision_lag1"] = _lag1_sums([r for r in log if r.kind == "vision" and r.accepted])
    return out


def ticks_at_altitudes(z_m: np.ndarray, flying: np.ndarray, altitudes_m: Sequence[float]) -> np.ndarray:
    """The first flying tick at or below each altitude, -1 where there is none.

    Args:
        z_m: Truth height of the body origin above the target's ground [m], (N,).
        flying: Ticks before touchdown, (N,) bool.
        altitudes_m: The altitudes [m].

    Returns:
        (len(altitudes_m),) tick indices; -1 where the case never gets that low in
        flight, or starts below it (its first tick is already there: no value).
    """
    idx_flying = np.flatnonzero(flying)
    grid = np.asarray(altitudes_m, float)
    k = np.full(grid.size, -1)
    if idx_flying.size:
        # The running minimum of the height is monotone, so a search on it finds the first
        # tick whose height is <= h.
        zf = np.minimum.accumulate(np.asarray(z_m, float)[idx_flying])
        pos = np.searchsorted(-zf, -grid, side="left")
        ok = pos < idx_flying.size
        k[ok] = idx_flying[pos[ok]]
        k[k == 0] = -1
    return k


def nees_profile(z_m: np.ndarray, flying: np.ndarray, nees: Mapping[str, np.ndarray]) -> dict[str, list[float | None]]:
    """Each block's NEES at every altitude of :data:`NEES_PROFILE_ALTITUDES_M`.

    Args:
        z_m: Truth height of the body origin above the target's ground [m], (N,).
        flying: Ticks before touchdown, (N,) bool.
        nees: Block name -> NEES per tick, (N,).

    Returns:
        Block -> one value per grid altitude: the NEES at :func:`ticks_at_altitudes`'s
        tick, None where there is none or the value is not finite (the fixed
        altitudes' rule).
    """
    k = ticks_at_altitudes(z_m, flying, NEES_PROFILE_ALTITUDES_M)
    out: dict[str, list[float | None]] = {}
    for block in NEES_BLOCKS:
        v = nees[block]
        out[block] = [float(v[i]) if i >= 0 and math.isfinite(v[i]) else None for i in k]
    return out


def _lag1_sums(records: Sequence[Any]) -> dict[str, dict[str, float]]:
    """Sums for the lag-1 autocorrelation of the normalised vision residuals, per axis.

    Residual ``y_i / sqrt(S_ii)``, the run's mean removed; pairs are consecutive
    accepted measurements that share a frame (the second's first frame is the
    first's second), i.e. are one frame period apart.
    """
    out = {}
    if not records:
        return {ax: {"n": 0, "sum_sq": 0.0, "n_pairs": 0, "sum_prod": 0.0} for ax in "xy"}
    t = np.array([r.t_ns for r in records], dtype=np.int64)
    steps = np.diff(t)
    period = int(np.min(steps)) if steps.size else 0
    consecutive = steps == period
    for i, ax in enumerate("xy"):
        e = np.array([r.y[i] / math.sqrt(r.S[i, i]) for r in records])
        e = e - e.mean()
        prod = e[:-1] * e[1:]
        out[ax] = {"n": int(e.size), "sum_sq": float(np.sum(e * e)),
                   "n_pairs": int(consecutive.sum()), "sum_prod": float(np.sum(prod[consecutive]))}
    return out


# --------------------------------------------------------------------------- campaign
def campaign_consistency(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The ensemble statistics of a campaign from its flattened case rows.

    Args:
        rows: ``cases.parquet`` rows (summary flattened with ``_``); failed cases
            (no consistency columns) are skipped.

    Returns:
        The ``consistency.json`` document::

            {"schema": 1, "n_cases": N, "altitudes_m": [...],
             "blocks": {block: {"dof", "anees": [.. per altitude, then touchdown],
                                "n": [...], "band": [[lo, hi], ...], "band_999": [...],
                                "in_band": [...]}},
             "nis": {sensor: {"dof", "mean", "n", "band", "rejected",
                              "bands": [{"alt_m": [lo, hi], "mean", "n", "band"}]}},
             "vision_lag1": {"x": rho, "y": rho, "n_pairs": k}}

        ``altitudes_m`` lists the fixed altitudes and ``"touchdown"`` last; every
        per-altitude list follows it. ANEES values are NaN (JSON null after
        ``json_safe``) where no case has a value.
    """
    cases = [r for r in rows if any(k.startswith("consistency_nees_at_") for k in r)]
    levels = [str(a) for a in NEES_ALTITUDES_M] + [TOUCHDOWN]
    blocks: dict[str, Any] = {}
    for block, dof in NEES_BLOCKS.items():
        anees, ns, band, band_999, in_band = [], [], [], [], []
        for level in levels:
            vals = column(cases, f"consistency_nees_at_{level}_{block}")
            vals = vals[np.isfinite(vals)]
            n = int(vals.size)
            a = float(vals.mean()) if n else math.nan
            b95, b999 = chi2_band(n, dof), chi2_band(n, dof, BAND_PROB_WIDE)
            anees.append(a)
            ns.append(n)
            band.append(b95)
            band_999.append(b999)
            in_band.append(bool(b95 is not None and b95[0] <= a <= b95[1]))
        blocks[block] = {"dof": dof, "anees": anees, "n": ns, "band": band, "band_999": band_999,
                         "in_band": in_band}
    nis: dict[str, Any] = {}
    for sensor, dof in NIS_SENSORS.items():
        pre = f"consistency_nis_{sensor}"
        n = int(np.nansum(column(cases, f"{pre}_n")))
        total = float(np.nansum(column(cases, f"{pre}_sum")))
        rejected = int(np.nansum(column(cases, f"{pre}_rejected")))
        per_band = []
        for lo, hi in NIS_BANDS_M:
            key = f"{pre}_bands_{_band_key(lo, hi)}"
            bn = int(np.nansum(column(cases, f"{key}_n")))
            bs = float(np.nansum(column(cases, f"{key}_sum")))
            per_band.append({"alt_m": [lo, hi], "mean": bs / bn if bn else math.nan, "n": bn,
                             "band": chi2_band(bn, dof)})
        nis[sensor] = {"dof": dof, "mean": total / n if n else math.nan, "n": n, "band": chi2_band(n, dof),
                       "rejected": rejected, "bands": per_band}
    lag1: dict[str, Any] = {}
    for ax in "xy":
        pre = f"consistency_vision_lag1_{ax}"
        n, n_pairs, sum_sq, sum_prod = (np.nansum(column(cases, f"{pre}_{k}"))
                                        for k in ("n", "n_pairs", "sum_sq", "sum_prod"))
        lag1[ax] = float((sum_prod / n_pairs) / (sum_sq / n)) if n_pairs and sum_sq else math.nan
        lag1["n_pairs"] = int(n_pairs)
    return {"schema": SCHEMA_VERSION, "n_cases": len(cases), "altitudes_m": [*NEES_ALTITUDES_M, TOUCHDOWN],
            "blocks": blocks, "nis": nis, "vision_lag1": lag1, "steps": campaign_nees_steps(cases)}


def campaign_nees_steps(rows: Sequence[Mapping[str, Any]], prob: float = BAND_PROB,
                        rng: np.random.Generator | None = None) -> dict[str, Any]:
    """The ensemble NEES at every step of the dense altitude grid, against each step's band.

    Args:
        rows: Case rows carrying ``nees_profile`` (block -> list over
            :data:`NEES_PROFILE_ALTITUDES_M`); rows without it are skipped.
        prob: The band's probability.
        rng: The draws of :func:`consistent_in_band_share` (default: a generator seeded with
            :data:`NULL_SEED`, so that the document is a function of the cases alone).

    Returns:
        ``{"altitudes_m": [...], "n_cases": N, "blocks": {block: {"dof", "anees": [...],
        "n": [...], "band": [[lo, hi] | None, ...], "steps": k, "in_band": i,
        "below": b, "above": a, "in_band_frac": i / k, "spread": [...], "spread_median": m}}}``.
        A step counts when at least half of the cases have a value there (so the top of the
        grid, which only the cases handed over highest reach, does not decide the share).

        ``spread`` is, at each step, the squared coefficient of variation of the cases' NEES
        (unbiased variance over the cases that have one, over the ANEES squared; NaN under two
        cases) over a chi-square's, ``2 / dof``; ``spread_median`` its median over the counted
        steps. A consistent filter's cases give 1, and so does one whose covariance is off by
        the same factor in every case (that shows in the ANEES). A spread well above 1 is a
        mixture: some cases' errors larger than their covariance says and others' smaller, or
        a heavy tail. Such a filter leaves its band at more steps than a consistent one even
        where its ANEES is right, because the ANEES scatters from step to step more than the
        band allows for.

        ``drivers`` names the cases that most keep the ANEES out of its band: for each case,
        the steps in band with that case left out (each step's ANEES and band over the other
        cases, the same steps counted) minus the steps in band with all; the
        :data:`DRIVERS_SHOWN` largest positive gains, as ``[{"case": id, "gain": steps}]``
        (``id``: the row's ``case``, else its position). A single case that moves many steps
        is a heavy tail worth flying again.

        ``consistent_share`` says what share of steps in band a consistent filter would give
        with these cases and this step-to-step correlation (:func:`consistent_in_band_share`):
        neighbouring steps share their errors, so even a consistent filter's share scatters
        well below ``prob`` from campaign to campaign, and a share is judged against that.
    """
    rng = np.random.default_rng(NULL_SEED) if rng is None else rng
    kept = [(r.get("case", i), r["nees_profile"]) for i, r in enumerate(rows)
            if isinstance(r.get("nees_profile"), Mapping)]
    ids = [k for k, _ in kept]
    profiles = [p for _, p in kept]
    n_cases = len(profiles)
    out: dict[str, Any] = {"altitudes_m": list(NEES_PROFILE_ALTITUDES_M), "n_cases": n_cases, "blocks": {}}
    for block, dof in NEES_BLOCKS.items():
        vals = np.array([[math.nan if v is None else float(v) for v in p.get(block, [])] for p in profiles], float)
        if vals.size == 0:
            vals = np.full((0, len(NEES_PROFILE_ALTITUDES_M)), math.nan)
        finite = np.isfinite(vals)
        n = finite.sum(axis=0)
        total = np.where(finite, vals, 0.0).sum(axis=0)
        with np.errstate(invalid="ignore"):
            anees = np.where(n > 0, total / np.maximum(n, 1), math.nan)
        band, lo, hi = _step_bands(n, dof, prob)
        counted = n >= max(1, math.ceil(0.5 * n_cases))
        below = counted & (anees < lo)
        above = counted & (anees > hi)
        steps = int(counted.sum())
        inside = steps - int(below.sum()) - int(above.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            dev = np.where(finite, vals - anees, 0.0)
            spread = np.where(n >= 2, (dev**2).sum(axis=0) / np.maximum(n - 1, 1) / anees**2 * (dof / 2.0), math.nan)
        spread_counted = spread[counted & np.isfinite(spread)]
        out["blocks"][block] = {"dof": dof, "anees": anees.tolist(), "n": n.tolist(), "band": band, "steps": steps,
                                "in_band": inside, "below": int(below.sum()), "above": int(above.sum()),
                                "in_band_frac": inside / steps if steps else math.nan,
                                "spread": spread.tolist(),
                                "spread_median": float(np.median(spread_counted)) if spread_counted.size else math.nan,
                                "drivers": _band_drivers(vals, finite, total, n, lo, hi, counted, inside, dof, prob,
                                                         ids),
                                "consistent_share": consistent_in_band_share(vals, finite, lo, hi, counted, dof,
                                                                             inside / steps if steps else math.nan,
                                                                             rng)}
    return out


def _step_bands(n: np.ndarray, dof: int, prob: float) -> tuple[list[list[float] | None], np.ndarray, np.ndarray]:
    """Each step's :func:`chi2_band` for its count of cases ``n``: the bands, and their lower and upper
    ends as arrays (NaN where a step has no case)."""
    band = [chi2_band(int(k), dof, prob) for k in n]
    return band, np.array([b[0] if b else math.nan for b in band]), np.array([b[1] if b else math.nan for b in band])


DRIVERS_SHOWN = 3  # cases named per block by campaign_nees_steps's "drivers"
NULL_DRAWS = 400  # campaigns a consistent filter flies per block in consistent_in_band_share
NULL_SEED = 14  # its default generator's seed


def step_correlation(vals: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """The correlation of the cases' NEES between steps ``k`` apart, for every lag ``k`` (lag 0: 1).

    Each case's NEES less the step's mean over the cases; at lag ``k`` the sum of the products of
    a case's values ``k`` steps apart over the root of the products of their sums of squares,
    over every case and pair of steps where both are finite. NaN at a lag with no such pair. The
    sums over pairs are cross-correlations along the steps, taken by FFT.
    """
    T = vals.shape[1]
    n = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.where(finite, vals, 0.0).sum(axis=0) / np.maximum(n, 1), 0.0)
    z = np.where(finite, vals - mean, 0.0)
    f = finite.astype(float)
    size = 2 * T

    def xcorr(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # sum over cases and t of a[t] b[t + k], k = 0..T-1
        spec = np.conj(np.fft.rfft(a, size, axis=1)) * np.fft.rfft(b, size, axis=1)
        return np.fft.irfft(spec.sum(axis=0), size)[:T]

    num, sa, sb = xcorr(z, z), xcorr(z * z, f), xcorr(f, z * z)
    den = np.sqrt(np.clip(sa, 0.0, None) * np.clip(sb, 0.0, None))
    scale = max(float(den[0]), 1e-300)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-12 * scale, num / den, math.nan)


def step_phi(corr: np.ndarray, floor: float = 0.05) -> float:
    """The per-step correlation ``phi`` of a first-order Gauss-Markov (AR(1)) error whose squares have the NEES
    correlation ``corr`` (:func:`step_correlation`): such an error's NEES correlates as ``phi^(2k)`` at lag ``k``,
    so ``log phi`` is the least-squares slope of ``log corr`` against ``2k`` through the origin, over the lags
    from 1 to the last before ``corr`` first falls to ``floor`` (below it, the estimate is mostly noise). 0 when
    lag 1 is already at or below ``floor``."""
    c = np.asarray(corr, float)
    low = np.flatnonzero(~(c[1:] > floor))
    last = int(low[0]) if low.size else c.size - 1  # lags 1..last are above the floor
    if last < 1:
        return 0.0
    k = np.arange(1, last + 1, dtype=float)
    return float(math.exp(float((k * np.log(c[1:last + 1])).sum()) / (2.0 * float((k * k).sum()))))


def consistent_in_band_share(vals: np.ndarray, finite: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                             counted: np.ndarray, dof: int, observed: float, rng: np.random.Generator,
                             draws: int = NULL_DRAWS) -> dict[str, float] | None:
    """The share of steps in band that a consistent filter would give, with these cases' step-to-step correlation.

    A consistent filter's error at each step is Gaussian with its covariance, so a case's NEES is
    the sum of ``dof`` squared standard normals; taken as first-order Gauss-Markov sequences over
    the steps (``x_k = phi x_{k-1} + sqrt(1 - phi^2) w_k``), their NEES correlate as ``phi^(2k)``, and
    ``phi`` is fitted to the cases' NEES correlation between steps (:func:`step_phi`; on the campaigns
    of issue 14 that correlation at lags 1 to 80 follows ``phi^(2k)`` to within a few hundredths). The
    ANEES at a step of ``n`` cases is then chi-square with ``n dof`` degrees of freedom over ``n``, and
    from step to step it correlates as ``phi^2``: each of ``draws`` campaigns draws it as a Gaussian
    AR(1) sequence of correlation ``phi^2`` carried through that chi-square's quantile function (a
    Gaussian copula: exact in the marginals, and in the correlation as ``n dof`` grows), judged against
    the same bands (``lo``, ``hi``) over the same counted steps.

    The cases' NEES correlation includes whatever makes this filter inconsistent (a mixture of cases
    reads as more correlation), so the reference is, if anything, wider than a consistent filter's.

    Returns:
        ``{"phi", "mean", "median", "q05", "p"}``: the fitted ``phi``; the mean, median and 5 % quantile of the
        drawn shares; and ``p``, the fraction of draws whose share is at most ``observed`` (one-sided: a
        share this low or lower from a consistent filter). None with under 3 cases or no counted step.
    """
    from scipy.special import ndtr  # scipy.special is imported already (gnc.numeric); ndtr only here

    n_cases, T = vals.shape
    if n_cases < 3 or not counted.any() or not math.isfinite(observed):
        return None
    phi = step_phi(step_correlation(vals, finite))
    rho = phi * phi
    u = rng.standard_normal((draws, T))
    innov = math.sqrt(1.0 - rho * rho)
    for k in range(1, T):
        u[:, k] = rho * u[:, k - 1] + innov * u[:, k]
    n = finite.sum(axis=0)
    cols = np.flatnonzero(counted)  # counted steps have n >= 1
    q = np.clip(ndtr(u[:, cols]), 1e-15, 1.0 - 1e-15)
    anees = chi2_ppf(q, n[cols] * dof) / n[cols]
    shares = ((anees >= lo[cols]) & (anees <= hi[cols])).sum(axis=1) / float(cols.size)
    return {"phi": phi, "mean": float(shares.mean()), "median": float(np.median(shares)),
            "q05": float(np.quantile(shares, 0.05)), "p": float((shares <= observed).mean())}


def _band_drivers(vals: np.ndarray, finite: np.ndarray, total: np.ndarray, n: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray, counted: np.ndarray, inside: int, dof: int, prob: float,
                  ids: Sequence[Any]) -> list[dict[str, Any]]:
    """The cases whose removal puts the most counted steps back in band (see :func:`campaign_nees_steps`).

    ``total``, ``n``, ``lo`` and ``hi``: each step's sum of the cases' NEES, their count and band, over all
    cases. Without one case a step keeps its count and band where that case has no value there, and takes
    the band of one case fewer where it has."""
    if vals.shape[0] < 3 or not counted.any():
        return []
    _, lo_less, hi_less = _step_bands(n - 1, dof, prob)
    gains = []
    for i in range(vals.shape[0]):
        m = n - finite[i]
        with np.errstate(invalid="ignore", divide="ignore"):
            a = np.where(m > 0, (total - np.where(finite[i], vals[i], 0.0)) / np.maximum(m, 1), math.nan)
        lo_i, hi_i = np.where(finite[i], lo_less, lo), np.where(finite[i], hi_less, hi)
        gains.append(int((counted & (a >= lo_i) & (a <= hi_i)).sum()) - inside)
    order = sorted(range(len(gains)), key=lambda i: (-gains[i], i))
    return [{"case": ids[i], "gain": gains[i]} for i in order[:DRIVERS_SHOWN] if gains[i] > 0]


def consistency_table(doc: Mapping[str, Any]) -> str:
    """A plain-text table of a ``consistency.json`` document (ANEES per block and altitude, NIS per sensor)."""
    levels = [str(a) for a in doc["altitudes_m"]]
    lines = [f"filter consistency over {doc['n_cases']} cases (ANEES, 95 % band; * outside it)"]
    lines.append("block dof " + " ".join(f"{lv + (' m' if lv != TOUCHDOWN else ''):>17}" for lv in levels))
    for block, b in doc["blocks"].items():
        cells = []
        for a, band in zip(b["anees"], b["band"]):
            if band is None or a is None or not math.isfinite(a):
                cells.append(f"{'-':>17}")
                continue
            mark = " " if band[0] <= a <= band[1] else "*"
            cells.append(f"{a:6.2f}{mark}[{band[0]:.2f},{band[1]:.2f}]".rjust(17))
        lines.append(f"{block:<5} {b['dof']:>3} " + " ".join(cells))
    for sensor, s in doc["nis"].items():
        if not s["n"]:
            lines.append(f"NIS {sensor}: no updates")
            continue
        band = s["band"]
        parts = [f"NIS {sensor} (dof {s['dof']}): mean {s['mean']:.2f} over {s['n']}"
                 + (f" [{band[0]:.2f},{band[1]:.2f}]" if band else "") + f", {s['rejected']} gated out"]
        for b in s["bands"]:
            if b["n"]:
                parts.append(f"{b['alt_m'][0]}-{b['alt_m'][1]} m: {b['mean'] / s['dof']:.2f}/dof (n {b['n']})")
        lines.append("; ".join(parts))
    steps = doc.get("steps")
    if steps and steps.get("n_cases"):
        alt = steps["altitudes_m"]
        lines.append(f"per step ({alt[0] - alt[1]} m grid, {alt[0]}-{alt[-1]} m; ANEES inside its 95 % band "
                     f"at k of K steps, below / above):")
        enough = steps["n_cases"] >= MIN_SPREAD_CASES
        for block, b in steps["blocks"].items():
            if b["steps"]:
                spread = b.get("spread_median")  # absent (as "drivers") from a consistency.json written before it
                lines.append(f"  {block:<5} {b['in_band']}/{b['steps']} ({100 * b['in_band_frac']:.0f} %), "
                             f"below {b['below']}, above {b['above']}"
                             + (f"; spread of the cases' NEES {spread:.2f} (chi-square: 1)"
                                if enough and spread is not None and math.isfinite(spread) else ""))
                ref = b.get("consistent_share")  # absent from a consistency.json written before it
                if enough and ref:
                    lines.append(f"        a consistent filter, steps correlated as these (phi {ref['phi']:.3f}): "
                                 f"median {100 * ref['median']:.0f} %, 5 % quantile {100 * ref['q05']:.0f} %; "
                                 f"this share or less: p = {ref['p']:.2f}")
                if enough and b.get("drivers"):
                    lines.append("        cases that most keep it out of its band: " + ", ".join(
                        f"{d['case']} (+{d['gain']} step{'s' if d['gain'] > 1 else ''} without it)"
                        for d in b["drivers"]))
    lag = doc["vision_lag1"]
    if lag.get("n_pairs"):
        lines.append(f"vision residual lag-1 autocorrelation: x {lag['x']:+.3f}, y {lag['y']:+.3f} "
                     f"({lag['n_pairs']} pairs)")
    return "\n".join(lines)
