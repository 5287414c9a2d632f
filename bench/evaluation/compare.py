"""Paired A/B comparison of two Monte Carlo campaigns: ``landbench compare``.

Inputs:
    * ``base_dir``, ``cand_dir``: two campaign folders written by
      ``landbench mc`` (``campaign.json``, ``cases/NNNNN.json``). Their rows
      are read with :func:`bench.campaign.mc.read_rows` (the rows
      ``cases.parquet`` holds). The campaigns must pair case by case: the
      same number of cases, every case finished on both sides, the same seed
      and the same drawn dispersions (``disp_*``) for every case. Anything
      else is refused with :class:`CompareInputError` (a ``ValueError``: the
      command line prints it as one ``landbench: error:`` line, exit 2) naming
      the first mismatch and its fix.
    * ``gates``: gate specs (``--gate``), parsed by :func:`parse_gate`:
      ``success_rate:-2pp``, ``METRIC[:STAT]:+TOL`` or ``-TOL`` with ``STAT``
      one of ``mean`` (default), ``median``, ``p95``, ``max`` and ``TOL`` an
      absolute number in the metric's unit or a relative ``N%``. A ``+``
      tolerance bounds how far CAND's statistic may rise above BASE's
      (lower is better: miss distance, speeds, fuel), a ``-`` tolerance how
      far it may fall below (higher is better).

Output: :func:`compare_campaigns` returns one JSON-ready dict (schema
``SCHEMA``, ``version`` ``VERSION``):
    * ``success``: each side's success rate (``landed``) with its Wilson 95 %
      interval, the exact McNemar test on the landed/not-landed pairs, and a
      plain verdict (``resolved``: whether the exact McNemar test rejects
      equal rates at ``ALPHA``; False means the campaign is too small to
      tell, whether or not the two intervals overlap);
    * ``flipped``: the cases that landed on one side only, each with the
      ``landbench mc --replay`` command of both sides;
    * ``metrics``: for every numeric per-case metric present on both sides
      (not the identifiers ``case``/``seed``, the dispersions ``disp_*`` or
      the machine-dependent entries, ``mc.is_run_dependent``), over the cases with a
      finite value on both sides (``n_used``; the others are dropped,
      ``n_dropped``): each side's mean, median, p95 and max, the paired
      difference CAND - BASE (mean, median, a paired BCa bootstrap 95 %
      interval of the mean, seeded so that the output is deterministic), the
      Wilcoxon signed-rank p-value (1 and ``identical`` when every difference
      is 0), and the Holm-corrected p-value over all metrics with a p-value;
    * ``gates`` and ``passed``: each gate's numbers and outcome;
    * ``platform_notes``: one line for each platform entry of the rows that
      differs between the sides and moves results (:data:`PLATFORM_NOTES`:
      the GL renderer, which draws other pixels, so every vision figure moves
      with it; the MuJoCo version). Reported, never refused: a note says the
      comparison mixes a platform change into the change under test.

:func:`write_compare` writes it as ``DIR/compare.json`` atomically;
:func:`format_compare` is the terminal table; the HTML report is drawn from the
same dict by :func:`bench.report.compare_html.write_compare_report`.

Replay folders (``landbench replay --out DIR``: ``metrics.json`` +
``frames.parquet``) are the second input kind (:func:`read_input`): one row
per replayed sequence, the metrics being every numeric per-sequence figure of
``metrics.json`` (navigation, vision and the tracker's endpoint error, flattened
to their leaf names, e.g. ``epe_median_px``, ``vel_err_rms_mps``,
``vision_gate_rejections``; the wall-clock timings are left out as
machine-dependent). Two replays pair when they replayed the same recordings:
the same seeds in the same order and the same recording manifests (their
sha256, which ``landbench replay`` writes per sequence). The success rate,
McNemar and flipped cases do not apply to open-loop replays (``success`` is
null, a ``success_rate`` gate is refused). A replay is never paired with a
campaign. Per frame, ``frames.parquet`` is compared too (``frames``: paired on
(seed, frame index), checked to be at the same ``t_ns``): every numeric column
with the same statistics, every boolean column (measurement formed / accepted /
rejected, vision active) with each side's rate, its Wilson interval and the
exact McNemar test, Holm over the frame family; reported, not gated.

``values`` (and ``frames.values``) hold the paired per-case (per-frame)
values themselves, which the HTML report (:mod:`bench.report.compare_html`,
``DIR/report.html``) plots against each other.
"""

from __future__ import annotations

import json
import math
import re
import shlex
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.campaign import mc
from bench.campaign.rows import column, row_float
from bench.report.io import atomic_write_text, json_safe
from bench.report.mc_report import wilson_interval  # one Wilson interval for every report

SCHEMA = "landbench.compare"
VERSION = 1
COMPARE_JSON = "compare.json"
CONFIDENCE = 0.95
ALPHA = 1.0 - CONFIDENCE
BOOTSTRAP_RESAMPLES = 9999
BOOTSTRAP_SEED = 20240610  # fixed: the same inputs give the same compare.json
BOOTSTRAP_METHOD = "BCa"
STATISTICS = ("mean", "median", "p95", "max")
SUCCESS_GATE = "success_rate"
IDENTIFIER_KEYS = ("case", "seed")
DISPERSION_PREFIX = "disp_"
# Metrics always shown in the terminal table (when present); the rest are shown
# when gated or significant after Holm, and are all in compare.json.
HEADLINE_METRICS = ("touchdown_miss_distance_m", "touchdown_v_vertical_mps", "touchdown_v_horizontal_mps",
                    "touchdown_tilt_deg", "fuel_used_kg", "nav_pos_err_touchdown_m")
REPLAY_HEADLINE_METRICS = ("epe_median_px", "epe_p95_px", "within_1px_frac", "tracks_per_frame_mean",
                           "vel_err_rms_mps", "vel_err_horizontal_at_cutoff_mps", "pos_err_end_m")
REPLAY_METRICS = "metrics.json"
REPLAY_FRAMES = "frames.parquet"
REPLAY_FORMAT = "landbench-replay"
# Wall-clock figures of a replay: they differ between two runs of the same replay, so they are not compared.
REPLAY_RUN_DEPENDENT_KEYS = ("tracker_ms_per_frame_mean", "tracker_ms_per_frame_median", "vision_ms_per_frame_mean",
                             "replay_wall_s", "replay_realtime_factor", "tracker_ms", "vision_ms")
FLIPPED_SHOWN = 20  # flipped cases listed on the terminal; all are in compare.json
GATE_FORMS = ("success_rate:-Npp (CAND's success rate at most N percentage points below BASE's); "
              "METRIC[:mean|median|p95|max]:+X or :-X (absolute, in the metric's unit) or :+X% / :-X% "
              "(relative to BASE), e.g. touchdown_miss_distance_m:p95:+0.05, fuel_used_kg:+10%")


class CompareInputError(ValueError):
    """Inputs that cannot be compared (not paired, not a campaign, a bad gate): a user error."""


# ===================================================================== inputs
@dataclass(frozen=True)
class PairedInput:
    """One side of a comparison, whatever its kind: rows in case order, and how to rerun a case.

    ``rows[i]`` is the row of case ``i`` (``case``, ``seed``, ``disp_*``,
    ``landed``, metrics), as ``landbench mc`` writes it.
    """

    kind: str
    path: Path
    rows: list[dict[str, Any]]
    info: dict[str, Any] = field(default_factory=dict)

    def replay_command(self, case: int, out: str) -> str:
        """The command that reruns ``case`` of this input with telemetry and video into ``out``."""
        if self.kind == "campaign":
            return shlex.join(["landbench", "mc", "--replay", str(self.path), "--case", str(case), "--out", out])
        raise NotImplementedError(self.kind)  # pragma: no cover - replays have no success, so no flipped case


def read_input(path: str | Path, role: str) -> PairedInput:
    """Read one side (``role``: BASE or CAND): a campaign folder or a replay folder.

    Raises:
        CompareInputError: Not a folder, neither a campaign nor a replay, an unfinished campaign, or an
            unreadable replay.
    """
    path = Path(path)
    if not path.is_dir():
        raise CompareInputError(f"{role} {path}: no such folder; give a campaign folder written by "
                                "landbench mc --out DIR or a replay folder written by landbench replay --out DIR")
    if (path / mc.CAMPAIGN).is_file():
        return _read_campaign(path, role)
    if (path / REPLAY_METRICS).is_file():
        return _read_replay(path, role)
    if (path / "summary.json").is_file():
        raise CompareInputError(f"{role} {path} is a single run (summary.json), not a campaign or a replay; "
                                "give two landbench mc folders or two landbench replay folders")
    raise CompareInputError(f"{role} {path} is not a campaign folder (no {mc.CAMPAIGN}) nor a replay folder "
                            f"(no {REPLAY_METRICS}); give a folder written by landbench mc --out DIR or "
                            "landbench replay --out DIR")


def _read_campaign(path: Path, role: str) -> PairedInput:
    try:  # whole runs >= 1 and campaign_seed >= 0, or one line
        meta = mc.read_meta(path / mc.CAMPAIGN, ("runs", "campaign_seed"), role)
    except ValueError as exc:
        raise CompareInputError(str(exc)) from None
    runs, seed = meta["runs"], meta["campaign_seed"]
    rows = mc.read_rows(path, runs)
    if any(not isinstance(r, dict) or isinstance(r.get("case"), bool) or not isinstance(r.get("case"), int)
           for r in rows):
        raise CompareInputError(f"{role} {path}: a case file in {mc.CASES}/ is not a case row (a JSON object with "
                                "an integer 'case'); give a folder written by landbench mc --out DIR, or rerun "
                                "that case with landbench mc --resume")
    have = {r["case"] for r in rows}
    missing = [i for i in range(runs) if i not in have]
    if missing:
        raise CompareInputError(
            f"{role} {path}: case {missing[0]} has no row ({mc.CASES}/{missing[0]:05d}.json; {len(missing)} of "
            f"{runs} cases missing); finish the campaign with landbench mc --resume {path}")
    return PairedInput("campaign", path, rows, {"campaign_seed": seed, "runs": runs})


def replay_row(seq: Mapping[str, Any]) -> dict[str, Any]:
    """One replayed sequence's numeric figures, flattened to leaf names (updates as ``KIND_FIELD``)."""
    row: dict[str, Any] = {}

    def put(key: str, value: Any) -> None:
        if key in row:  # pragma: no cover - the replay's names are distinct
            raise CompareInputError(f"replay metric {key!r} appears twice")
        if key not in REPLAY_RUN_DEPENDENT_KEYS and isinstance(value, (int, float, type(None))) \
                and not isinstance(value, bool):
            row[key] = math.nan if value is None else value

    for section in ("navigation", "vision"):
        for k, v in (seq.get(section) or {}).items():
            if k == "updates" and isinstance(v, dict):
                for kind, fields in v.items():
                    for fk, fv in (fields or {}).items():
                        put(f"{kind}_{fk}", fv)
            else:
                put(k, v)
    for k in ("touchdown_t_s", "control_ticks"):
        put(k, seq.get(k))
    return row


def _read_replay(path: Path, role: str) -> PairedInput:
    fix = "give a folder written by landbench replay --out DIR (re-run the replay with this landbench)"
    try:
        doc = json.loads((path / REPLAY_METRICS).read_text())
        if not isinstance(doc, dict) or doc.get("format") != REPLAY_FORMAT:
            raise ValueError(f"not a {REPLAY_FORMAT} document")
        seqs = doc["sequences"]
        rows = [{"case": i, "seed": int(m["seed"]), **replay_row(m)} for i, m in enumerate(seqs)]
        manifests = [m["recording_manifest_sha256"] for m in seqs]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CompareInputError(f"{role} {path}: {REPLAY_METRICS} is not a landbench replay's "
                                f"({type(exc).__name__}: {exc}); {fix}") from None
    if not (path / REPLAY_FRAMES).is_file() and any(m.get("vision", {}).get("frames") for m in seqs):
        raise CompareInputError(f"{role} {path}: {REPLAY_FRAMES} is missing; {fix}")
    if not rows:
        raise CompareInputError(f"{role} {path}: the replay holds no sequence; {fix}")
    return PairedInput("replay", path, rows, {"dataset": doc.get("dataset"), "overrides": doc.get("overrides"),
                                              "seeds": [r["seed"] for r in rows], "recording_manifests_sha256":
                                              manifests})


def _check_replays_paired(base: PairedInput, cand: PairedInput) -> None:
    fix = "replay the same recorded dataset on both sides (landbench replay DS ... --out DIR)"
    nb, nc = len(base.rows), len(cand.rows)
    if nb != nc:
        raise CompareInputError(f"BASE {base.path} replays {nb} sequences, CAND {cand.path} {nc}; {fix}")
    for i, (rb, rc) in enumerate(zip(base.rows, cand.rows)):
        if rb["seed"] != rc["seed"]:
            raise CompareInputError(f"sequence {i}: seed {rb['seed']} in BASE {base.path}, {rc['seed']} in "
                                    f"CAND {cand.path}; {fix}")
        mb, mc_ = base.info["recording_manifests_sha256"][i], cand.info["recording_manifests_sha256"][i]
        if mb != mc_:
            raise CompareInputError(f"sequence {i} (seed {rb['seed']}): BASE {base.path} and CAND {cand.path} "
                                    f"replayed different recordings (manifest sha256 {str(mb)[:12]}… vs "
                                    f"{str(mc_)[:12]}…); {fix}")


def _read_frames(path: Path) -> dict[str, np.ndarray] | None:
    from bench.report.report import read_telemetry_parquet

    f = path / REPLAY_FRAMES
    return read_telemetry_parquet(f) if f.is_file() else None


FRAME_KEYS = ("seed", "frame")  # a replayed frame's identity: the recording's seed, the frame's index in it
FRAME_NOT_METRICS = ("seed", "frame", "t_ns", "t_s")


def _frame_index(f: Mapping[str, np.ndarray]) -> np.ndarray:
    """Each row's frame index within its sequence: the ``frame`` column, or the row's order within its seed."""
    if "frame" in f:
        return np.asarray(f["frame"], np.int64)
    seeds = np.asarray(f["seed"], np.int64)
    out = np.zeros(seeds.size, np.int64)
    for s in np.unique(seeds):
        at = np.flatnonzero(seeds == s)
        out[at] = np.arange(at.size)
    return out


def _bool_metric(b: np.ndarray, c: np.ndarray) -> dict[str, Any]:
    """Paired booleans (one per frame on both sides): each side's count and rate with its Wilson interval,
    the exact McNemar test on the discordant pairs, and whether every pair agrees."""
    n = int(b.size)
    sides = {}
    for name, v in (("base", b), ("cand", c)):
        k = int(v.sum())
        sides[name] = {"true": k, "n": n, "rate": k / n if n else None,
                       "wilson95": list(wilson_interval(k, n, CONFIDENCE)) if n else None}
    mcn = mcnemar_exact(b, c)
    return {**sides, "mcnemar": {"true_base_only": mcn["lost"], "true_cand_only": mcn["gained"],
                                 "pvalue": mcn["pvalue"], "exact": True},
            "flipped": int(np.sum(b != c)), "identical": bool(np.array_equal(b, c)), "holm_p": None}


def _frame_metrics(base: PairedInput, cand: PairedInput) -> dict[str, Any] | None:
    """Per frame, both replays' frames.parquet paired on (seed, frame index).

    Numeric columns get the per-case treatment (:func:`_metric`), boolean
    columns (``measurement``, ``accepted``, ``rejected``, ``vision_active``)
    :func:`_bool_metric`; Holm runs over the frame family (Wilcoxon and McNemar
    p-values). A frame pairs only with the frame of the same index in the same
    sequence at the same ``t_ns``. Frames of one descent are not independent
    draws, so these p-values are a screen, not a test: reported, not gated.
    """
    fb, fc = _read_frames(base.path), _read_frames(cand.path)
    if fb is None or fc is None:
        return None

    def table(f: dict[str, np.ndarray]) -> tuple[dict[tuple[int, int], int], dict[str, np.ndarray]]:
        idx = _frame_index(f)
        keys = {(int(s), int(k)): i for i, (s, k) in enumerate(zip(f["seed"].tolist(), idx.tolist()))}
        return keys, f

    (kb, fb), (kc, fc) = table(fb), table(fc)
    if kb.keys() != kc.keys():
        first = sorted(kb.keys() ^ kc.keys())[0]
        raise CompareInputError(f"frame {first[1]} of seed {first[0]} is in {'BASE' if first in kb else 'CAND'} "
                                f"{REPLAY_FRAMES} only; replay the same recorded dataset on both sides")
    order = sorted(kb)
    ib = np.array([kb[k] for k in order], np.int64)
    ic = np.array([kc[k] for k in order], np.int64)
    tb, tc = np.asarray(fb["t_ns"], np.int64)[ib], np.asarray(fc["t_ns"], np.int64)[ic]
    if not np.array_equal(tb, tc):
        j = int(np.flatnonzero(tb != tc)[0])
        raise CompareInputError(f"frame {order[j][1]} of seed {order[j][0]} is at t_ns {tb[j]} in BASE, {tc[j]} in "
                                f"CAND; replay the same recorded dataset on both sides")

    def columns(f: dict[str, np.ndarray], kinds: str) -> list[str]:
        return [k for k, v in f.items() if k not in FRAME_NOT_METRICS and k not in REPLAY_RUN_DEPENDENT_KEYS
                and v.dtype.kind in kinds]

    numeric = [k for k in columns(fb, "iuf") if k in set(columns(fc, "iuf"))]
    numeric = [k for k in numeric if np.isfinite(fb[k][ib].astype(float)).any()
               and np.isfinite(fc[k][ic].astype(float)).any()]
    booleans = [k for k in columns(fb, "b") if k in set(columns(fc, "b"))]
    b_rows = [{k: fb[k][i].item() for k in numeric} for i in ib.tolist()]
    c_rows = [{k: fc[k][i].item() for k in numeric} for i in ic.tolist()]
    metrics = {k: _metric(b_rows, c_rows, k) for k in numeric}
    flags = {k: _bool_metric(np.asarray(fb[k], bool)[ib], np.asarray(fc[k], bool)[ic]) for k in booleans}
    family = {**{("m", k): m["wilcoxon_p"] for k, m in metrics.items()},
              **{("b", k): f["mcnemar"]["pvalue"] for k, f in flags.items()}}
    for (kind, k), p in holm(family).items():
        (metrics if kind == "m" else flags)[k]["holm_p"] = p
    return {"n_frames": len(order), "paired_on": list(FRAME_KEYS),
            "metrics": metrics, "booleans": flags,
            "holm_family": sum(p is not None for p in family.values()),
            "values": {"seed": [k[0] for k in order], "frame": [k[1] for k in order],
                       "t_s": (tb / 1e9).tolist(),
                       "metrics": {k: {"base": column(b_rows, k).tolist(), "cand": column(c_rows, k).tolist()}
                                   for k in numeric}}}


def _same(a: Any, b: Any) -> bool:
    """Equal values; two NaN/None numbers are equal."""
    fa, fb = row_float(a), row_float(b)
    if math.isnan(fa) and math.isnan(fb) and not isinstance(a, str) and not isinstance(b, str):
        return True
    return a == b


def check_paired(base: PairedInput, cand: PairedInput) -> None:
    """Refuse two inputs that do not pair case by case; the first mismatch is named.

    Raises:
        CompareInputError: Different case counts, a seed mismatch, or different drawn dispersions.
    """
    if base.kind != cand.kind:
        raise CompareInputError(f"BASE {base.path} is a {base.kind} folder, CAND {cand.path} a {cand.kind} folder; "
                                "compare two campaigns (landbench mc) or two replays (landbench replay)")
    if base.kind == "replay":
        _check_replays_paired(base, cand)
        return
    fix = "run both campaigns with the same --runs, --seed and [dispersions] table"
    nb, nc = len(base.rows), len(cand.rows)
    if nb != nc:
        raise CompareInputError(f"BASE {base.path} has {nb} cases, CAND {cand.path} has {nc}; {fix}")
    for i, (rb, rc) in enumerate(zip(base.rows, cand.rows)):
        if rb.get("seed") != rc.get("seed"):
            seeds = ""
            if base.kind == cand.kind == "campaign":
                seeds = (f" (campaign seeds {base.info['campaign_seed']} and {cand.info['campaign_seed']})")
            raise CompareInputError(f"case {i}: seed {rb.get('seed')} in BASE {base.path}, {rc.get('seed')} in "
                                    f"CAND {cand.path}{seeds}; {fix}")
        db = {k: v for k, v in rb.items() if k.startswith(DISPERSION_PREFIX)}
        dc = {k: v for k, v in rc.items() if k.startswith(DISPERSION_PREFIX)}
        if not db or not dc:
            continue  # a case that failed before its draw (timeout, dead worker) has none
        for k in sorted(db.keys() | dc.keys()):
            if k not in db or k not in dc:
                where = "BASE" if k in db else "CAND"
                raise CompareInputError(f"case {i}: {k} is drawn in {where} only; the campaigns disperse "
                                        f"different fields; {fix}")
            if not _same(db[k], dc[k]):
                raise CompareInputError(f"case {i}: {k} is {db[k]!r} in BASE, {dc[k]!r} in CAND; the campaigns "
                                        f"draw different dispersions; {fix}")


# ====================================================================== gates
@dataclass(frozen=True)
class Gate:
    """A parsed ``--gate``: CAND's ``statistic`` of ``metric`` may move by at most ``tolerance``."""

    spec: str
    metric: str  # SUCCESS_GATE for the success rate
    statistic: str  # mean | median | p95 | max; "rate" for the success rate
    tolerance: float  # signed: + bounds a rise, - a fall (pp for the success rate)
    relative: bool  # tolerance in % of BASE's value

    @property
    def bounds_fall(self) -> bool:
        """True when the spec's sign is '-' (``-0`` too: "must not fall at all", which -0.0 >= 0 would lose)."""
        return math.copysign(1.0, self.tolerance) < 0.0


_NUMBER = r"[+-](?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"


def parse_gate(spec: str) -> Gate:
    """Parse one gate spec; see ``GATE_FORMS``.

    Raises:
        CompareInputError: A malformed spec (the metric name is checked later, against the inputs).
    """
    bad = f"--gate {spec!r}: allowed forms: {GATE_FORMS}"
    text = spec.strip()
    if text.startswith(SUCCESS_GATE + ":"):
        m = re.fullmatch(r"(-(?:\d+(?:\.\d*)?|\.\d+)|\+?0+(?:\.0*)?)pp", text[len(SUCCESS_GATE) + 1:].strip())
        if not m:
            raise CompareInputError(bad)
        return Gate(spec, SUCCESS_GATE, "rate", float(m.group(1)), False)
    parts = text.rsplit(":", 2)
    if len(parts) == 3 and parts[1] in STATISTICS:
        metric, stat, tol = parts
    elif len(parts) >= 2:
        metric, tol = text.rsplit(":", 1)
        stat = "mean"
    else:
        raise CompareInputError(bad)
    m = re.fullmatch(f"({_NUMBER})(%?)", tol.strip())
    if not metric or not m or not math.isfinite(float(m.group(1))):
        raise CompareInputError(bad)
    return Gate(spec, metric, stat, float(m.group(1)), bool(m.group(2)))


def _evaluate_gate(gate: Gate, success: Mapping[str, Any], metrics: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"spec": gate.spec, "metric": gate.metric, "statistic": gate.statistic,
                           "tolerance": gate.tolerance, "relative": gate.relative}
    if gate.metric == SUCCESS_GATE:
        b, c = success["base"]["rate"], success["cand"]["rate"]
        change_pp = 100.0 * (c - b)
        passed = change_pp >= gate.tolerance - 1e-9
        out.update(base=b, cand=c, change=change_pp, limit=gate.tolerance, unit="pp", passed=passed,
                   reason=f"success rate {100 * c:.1f} % vs {100 * b:.1f} %: {change_pp:+.1f} pp "
                          f"{'>=' if passed else '<'} {gate.tolerance:+g} pp")
        return out
    if gate.metric not in metrics:  # BASE has it, CAND has no finite value in any case
        out.update(base=None, cand=None, change=None, limit=None, passed=False,
                   reason=f"CAND has no value of {gate.metric} in any case (BASE has): cannot check, failed")
        return out
    m = metrics[gate.metric]
    b, c = m["base"].get(gate.statistic), m["cand"].get(gate.statistic)
    if b is None or c is None:
        out.update(base=b, cand=c, change=None, limit=None, passed=False,
                   reason=f"no case has a value of {gate.metric} on both sides: cannot check")
        return out
    limit = abs(b) * gate.tolerance / 100.0 if gate.relative else gate.tolerance
    change = c - b
    passed = change >= limit - 1e-12 if gate.bounds_fall else change <= limit + 1e-12
    tol_text = f"{gate.tolerance:+g} %" if gate.relative else f"{gate.tolerance:+g}"
    out.update(base=b, cand=c, change=change, limit=limit, passed=passed,
               reason=f"{gate.statistic} {c:.4g} vs {b:.4g}: change {change:+.4g}, allowed {tol_text}"
                      + (f" ({limit:+.4g})" if gate.relative else ""))
    return out


# ================================================================= statistics
def mcnemar_exact(base_ok: Sequence[bool], cand_ok: Sequence[bool]) -> dict[str, Any]:
    """Exact McNemar test on paired successes: a binomial test on the discordant pairs.

    Returns:
        table [[both, BASE only], [CAND only, neither]], ``lost`` (landed in
        BASE only), ``gained`` (CAND only), ``statistic`` (min of the two) and
        the two-sided ``pvalue`` (1 when no pair is discordant).
    """
    from statsmodels.stats.contingency_tables import mcnemar

    b, c = np.asarray(base_ok, bool), np.asarray(cand_ok, bool)
    table = [[int(np.sum(b & c)), int(np.sum(b & ~c))], [int(np.sum(~b & c)), int(np.sum(~b & ~c))]]
    res = mcnemar(np.array(table), exact=True)
    return {"table": table, "lost": table[0][1], "gained": table[1][0], "statistic": float(res.statistic),
            "pvalue": float(min(1.0, res.pvalue)), "exact": True}


def _landed(row: Mapping[str, Any]) -> bool:
    from bench.report.mc_report import _landed as landed  # one definition of success for every report

    return landed(row)


def _side_stats(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {s: None for s in STATISTICS}
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "p95": float(np.percentile(values, 95)), "max": float(np.max(values))}


def bootstrap_mean_diff(base: np.ndarray, cand: np.ndarray, seed: int = BOOTSTRAP_SEED) -> tuple[float, float] | None:
    """Paired bootstrap CONFIDENCE interval of mean(cand - base); None with fewer than 2 pairs.

    BCa (scipy.stats.bootstrap, ``paired=True``) with a fixed ``numpy`` Generator,
    so the interval is deterministic; a constant difference d gives (d, d);
    the percentile interval is used where BCa is undefined.
    """
    from scipy.stats import bootstrap

    d = cand - base
    if d.size < 2:
        return None
    if np.all(d == d[0]):
        return float(d[0]), float(d[0])

    def stat(b: np.ndarray, c: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean(c - b, axis=axis)

    for method in (BOOTSTRAP_METHOD, "percentile"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # BCa's degenerate-data warning: handled by the fallback
            res = bootstrap((base, cand), stat, paired=True, vectorized=True, n_resamples=BOOTSTRAP_RESAMPLES,
                            confidence_level=CONFIDENCE, method=method, rng=np.random.default_rng(seed))
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
        if math.isfinite(low) and math.isfinite(high):
            return low, high
    return None


def wilcoxon_p(diff: np.ndarray) -> tuple[float | None, bool]:
    """Two-sided Wilcoxon signed-rank p-value of paired differences, and whether all are 0.

    scipy's defaults (zero differences dropped, exact for small samples); all
    differences 0: p = 1 and identical; no pairs: p = None.
    """
    from scipy.stats import wilcoxon

    if diff.size == 0:
        return None, False
    if np.all(diff == 0):
        return 1.0, True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # small-sample / ties notes
        return float(wilcoxon(diff).pvalue), False


def holm(pvalues: Mapping[Any, float | None]) -> dict[Any, float | None]:
    """Holm step-down adjusted p-values over the metrics that have a p-value (None stays None)."""
    from statsmodels.stats.multitest import multipletests

    names = [k for k, p in pvalues.items() if p is not None]
    out: dict[Any, float | None] = {k: None for k in pvalues}
    if names:
        adjusted = multipletests([pvalues[k] for k in names], alpha=ALPHA, method="holm")[1]
        out.update({k: float(p) for k, p in zip(names, adjusted)})
    return out


def metric_names(base_rows: Sequence[Mapping[str, Any]], cand_rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The numeric per-case metrics present on both sides, in BASE's column order.

    A key is numeric on a side when at least one of its rows holds a finite
    non-boolean number; identifiers, dispersions and machine-dependent keys are left out.
    """
    cand = set(numeric_keys(cand_rows))
    return [k for k in numeric_keys(base_rows) if k in cand]


def numeric_keys(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The numeric per-case metrics of one side (see :func:`metric_names`), in column order."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    return [k for k in keys if k not in IDENTIFIER_KEYS and not mc.is_run_dependent(k)
            and not k.startswith(DISPERSION_PREFIX) and np.isfinite(column(rows, k)).any()]


def _metric(base_rows: Sequence[Mapping[str, Any]], cand_rows: Sequence[Mapping[str, Any]], key: str) -> dict[str, Any]:
    b, c = column(base_rows, key), column(cand_rows, key)
    ok = np.isfinite(b) & np.isfinite(c)
    b, c = b[ok], c[ok]
    d = c - b
    p, identical = wilcoxon_p(d)
    ci = bootstrap_mean_diff(b, c)
    return {
        "n_used": int(ok.sum()), "n_dropped": int((~ok).sum()),
        "base": _side_stats(b), "cand": _side_stats(c),
        "diff": {"mean": float(np.mean(d)) if d.size else None, "median": float(np.median(d)) if d.size else None,
                 "bootstrap95": list(ci) if ci is not None else None},
        "wilcoxon_p": p, "holm_p": None, "identical": identical,
    }


def _success(base_ok: np.ndarray, cand_ok: np.ndarray) -> dict[str, Any]:
    n = int(base_ok.size)
    sides = {}
    for name, ok in (("base", base_ok), ("cand", cand_ok)):
        k = int(ok.sum())
        sides[name] = {"landed": k, "n": n, "rate": k / n, "wilson95": list(wilson_interval(k, n, CONFIDENCE))}
    mcn = mcnemar_exact(base_ok, cand_ok)
    diff_pp = 100.0 * (sides["cand"]["rate"] - sides["base"]["rate"])
    (bl, bh), (cl, ch) = sides["base"]["wilson95"], sides["cand"]["wilson95"]
    overlap = bl <= ch and cl <= bh
    # The cases are paired (the same draws on both sides), so the paired exact test decides. Two separate
    # Wilson intervals can part where it does not: 4/4 against 0/4 gives [51, 100] and [0, 49] % but
    # p = 0.125 (four discordant pairs cannot reach 0.05; five give 0.0625).
    resolved = mcn["pvalue"] < ALPHA
    if resolved:
        verdict = (f"CAND's success rate differs from BASE's by {diff_pp:+.1f} pp (McNemar p = {mcn['pvalue']:.3g}"
                   f"{'' if overlap else ', the Wilson intervals do not overlap'})")
    else:
        why = "the Wilson 95 % intervals overlap and " if overlap else ""
        verdict = (f"{n} cases cannot resolve a difference in success rate (observed {diff_pp:+.1f} pp; {why}"
                   f"McNemar p = {mcn['pvalue']:.3g} >= {ALPHA:g}): run more cases")
    return {**sides, "difference_pp": diff_pp, "mcnemar": mcn, "intervals_overlap": overlap,
            "resolved": resolved, "verdict": verdict}


# ================================================================== compare
# Row entries (``summary.json``'s ``platform``, flattened) that change results when they differ between the
# sides: what each side did, and what that moves. The CPU is not among them: the loop is deterministic on
# any processor.
PLATFORM_NOTES = {
    "platform_gl_renderer": ("BASE rendered its camera frames with {b}, CAND with {c}",
                             "a renderer draws other pixels, so the frames and every vision-dependent figure move with "
                             "the renderer as well as with the change; run both on the same renderer (one machine, or "
                             "MUJOCO_GL and the GL driver alike)"),
    "platform_mujoco": ("BASE ran MuJoCo {b}, CAND MuJoCo {c}",
                        "the physics may differ between MuJoCo versions as well as by the change; run both with the "
                        "same version"),
}


def platform_notes(base_rows: Sequence[Mapping[str, Any]], cand_rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """One line per :data:`PLATFORM_NOTES` entry whose values differ between BASE and CAND.

    Only entries present on both sides count (a campaign without a camera has no renderer).
    """
    notes = []
    for key, (what, why) in PLATFORM_NOTES.items():
        b = sorted({str(r[key]) for r in base_rows if r.get(key) is not None})
        c = sorted({str(r[key]) for r in cand_rows if r.get(key) is not None})
        if b and c and b != c:
            notes.append(f"{what.format(b=' / '.join(b), c=' / '.join(c))}: {why}")
    return notes


def compare_inputs(base: PairedInput, cand: PairedInput, gates: Sequence[str | Gate] = (),
                   replay_root: str | Path = "replay") -> dict[str, Any]:
    """Compare two paired inputs of any kind; see the module docstring for the result.

    Raises:
        CompareInputError: The inputs do not pair, or a gate is malformed or names an unknown metric.
    """
    parsed = [g if isinstance(g, Gate) else parse_gate(g) for g in gates]
    check_paired(base, cand)
    names = metric_names(base.rows, cand.rows)
    base_names = numeric_keys(base.rows)
    replay = base.kind == "replay"
    headline = REPLAY_HEADLINE_METRICS if replay else HEADLINE_METRICS
    for g in parsed:
        if g.metric == SUCCESS_GATE and replay:
            raise CompareInputError(f"--gate {g.spec!r}: open-loop replays have no success rate (the vehicle does "
                                    "not respond); gate a replay metric instead, e.g. epe_median_px:+10%")
        # A metric BASE has and CAND lost in every case is a regression the gate reports (failed), not bad input.
        if g.metric != SUCCESS_GATE and g.metric not in base_names:
            raise CompareInputError(f"--gate {g.spec!r}: BASE has no numeric metric {g.metric!r} (e.g. "
                                    f"{', '.join(n for n in headline if n in base_names) or ', '.join(base_names[:4])}"
                                    f"); allowed forms: {GATE_FORMS}")
    success = None
    base_ok = cand_ok = np.zeros(0, bool)
    if not replay:
        base_ok = np.array([_landed(r) for r in base.rows], bool)
        cand_ok = np.array([_landed(r) for r in cand.rows], bool)
        success = _success(base_ok, cand_ok)
    root = Path(replay_root)
    flipped = []
    for i in np.flatnonzero(base_ok != cand_ok):
        rb, rc = base.rows[i], cand.rows[i]
        flipped.append({
            "case": int(i), "seed": rb.get("seed"), "direction": "lost" if base_ok[i] else "gained",
            "base_outcome": rb.get("outcome"), "cand_outcome": rc.get("outcome"),
            "replay": {"base": base.replay_command(int(i), str(root / f"base-{i:05d}")),
                       "cand": cand.replay_command(int(i), str(root / f"cand-{i:05d}"))},
        })
    metrics = {k: _metric(base.rows, cand.rows, k) for k in names}
    for k, p in holm({k: m["wilcoxon_p"] for k, m in metrics.items()}).items():
        metrics[k]["holm_p"] = p
    gate_results = [_evaluate_gate(g, success, metrics) for g in parsed]
    doc = {
        "schema": SCHEMA, "version": VERSION, "kind": base.kind,
        "base": {"kind": base.kind, "path": str(base.path), **base.info},
        "cand": {"kind": cand.kind, "path": str(cand.path), **cand.info},
        "n_cases": len(base.rows),
        "settings": {"confidence": CONFIDENCE, "bootstrap_resamples": BOOTSTRAP_RESAMPLES,
                     "bootstrap_seed": BOOTSTRAP_SEED, "bootstrap_method": BOOTSTRAP_METHOD,
                     "wilcoxon": "two-sided, zero differences dropped (scipy default)",
                     "holm_family": sum(m["wilcoxon_p"] is not None for m in metrics.values()),
                     "percentile": "p95: numpy linear interpolation over the paired cases"},
        "success": success, "flipped": flipped, "metrics": metrics,
        "gates": gate_results, "passed": all(g["passed"] for g in gate_results),
        "platform_notes": platform_notes(base.rows, cand.rows),
        "values": paired_values(base.rows, cand.rows, names),
    }
    if replay:
        doc["success_applicable"] = False  # open loop: nothing lands
        doc["frames"] = _frame_metrics(base, cand)
    return json_safe(doc)


def paired_values(base_rows: Sequence[Mapping[str, Any]], cand_rows: Sequence[Mapping[str, Any]],
                  names: Sequence[str]) -> dict[str, Any]:
    """Every compared metric's value per case on both sides (what the report's scatter plots draw).

    Returns:
        ``case`` and ``seed`` (BASE's rows, in case order) and, per metric,
        ``base`` and ``cand`` lists of the same length (None where a side has no finite value).
    """
    return {"case": [int(r.get("case", i)) for i, r in enumerate(base_rows)],
            "seed": [r.get("seed") for r in base_rows],
            "metrics": {k: {"base": column(base_rows, k).tolist(), "cand": column(cand_rows, k).tolist()}
                        for k in names}}


def compare_campaigns(base_dir: str | Path, cand_dir: str | Path, gates: Sequence[str | Gate] = (),
                      replay_root: str | Path = "replay") -> dict[str, Any]:
    """Compare two ``landbench mc`` campaign folders case by case (pure: reads, writes nothing).

    Args:
        base_dir, cand_dir: Campaign folders (BASE, CAND).
        gates: Gate specs (see ``GATE_FORMS``), checked before the inputs are read.
        replay_root: Folder the printed replay commands write into (``ROOT/base-NNNNN``, ``ROOT/cand-NNNNN``).

    Raises:
        CompareInputError: see :func:`read_input`, :func:`check_paired`, :func:`parse_gate`.
    """
    parsed = [parse_gate(g) if isinstance(g, str) else g for g in gates]
    return compare_inputs(read_input(base_dir, "BASE"), read_input(cand_dir, "CAND"), parsed, replay_root)


def write_compare(doc: Mapping[str, Any], out: str | Path) -> Path:
    """Write ``out/compare.json`` atomically (the HTML report beside it: :mod:`bench.report.compare_html`)."""
    return atomic_write_text(Path(out) / COMPARE_JSON, json.dumps(json_safe(doc), indent=1) + "\n")


# ================================================================== terminal
def _f(value: Any, spec: str = ".4g") -> str:
    return "—" if value is None else format(value, spec)


def _p(value: Any) -> str:
    return "—" if value is None else ("<0.001" if value < 0.001 else f"{value:.3f}")


def format_compare(doc: Mapping[str, Any], written: str | Path | None = None) -> str:
    """The terminal summary; its last line is the gates' verdict (failing gates named).

    ``written``: the path of compare.json, listed just above that last line.
    """
    s = doc["success"]
    replay = doc.get("kind") == "replay"
    unit = "paired sequences (open-loop replays)" if replay else "paired cases"
    lines = [f"compare: BASE {doc['base']['path']} vs CAND {doc['cand']['path']}: {doc['n_cases']} {unit}"]
    lines += [f"  note: {n}" for n in doc.get("platform_notes") or ()]
    if s is None:
        lines.append("  success rate: not applicable to open-loop replays")
    for name in (("base", "cand") if s is not None else ()):
        side = s[name]
        lo, hi = side["wilson95"]
        lines.append(f"  success {name.upper():4s} {side['landed']:>5d}/{side['n']:<5d} {100 * side['rate']:5.1f} %  "
                     f"Wilson 95 % [{100 * lo:.1f}, {100 * hi:.1f}] %")
    if s is not None:
        mcn = s["mcnemar"]
        lines.append(f"  difference {s['difference_pp']:+.1f} pp; exact McNemar: {mcn['lost']} lost, "
                     f"{mcn['gained']} gained, p = {mcn['pvalue']:.3g}")
        lines.append(f"  {s['verdict']}")
    if doc["flipped"]:
        lines.append(f"flipped cases ({len(doc['flipped'])}):")
        for f in doc["flipped"][:FLIPPED_SHOWN]:
            lines.append(f"  case {f['case']} (seed {f['seed']}): {f['base_outcome']} -> {f['cand_outcome']}")
            lines.append(f"    BASE: {f['replay']['base']}")
            lines.append(f"    CAND: {f['replay']['cand']}")
        if len(doc["flipped"]) > FLIPPED_SHOWN:
            lines.append(f"  ... {len(doc['flipped']) - FLIPPED_SHOWN} more in {COMPARE_JSON}")
    metrics = doc["metrics"]
    gated = {g["metric"] for g in doc["gates"]}
    headline = REPLAY_HEADLINE_METRICS if replay else HEADLINE_METRICS
    shown = [k for k in metrics if k in headline or k in gated
             or (metrics[k]["holm_p"] is not None and metrics[k]["holm_p"] < ALPHA)]
    if shown:
        w = max(len(k) for k in shown)
        lines.append(f"{'metric (CAND - BASE)':{w}s} {'n':>5s} {'BASE mean':>10s} {'CAND mean':>10s} "
                     f"{'diff mean':>10s} {'95 % CI':>21s} {'diff med':>10s} {'Wilcoxon':>8s} {'Holm':>7s}")
        for k in shown:
            m = metrics[k]
            ci = m["diff"]["bootstrap95"]
            ci_text = "—" if ci is None else f"[{ci[0]:.3g}, {ci[1]:.3g}]"
            lines.append(f"{k:{w}s} {m['n_used']:>5d} {_f(m['base']['mean']):>10s} {_f(m['cand']['mean']):>10s} "
                         f"{_f(m['diff']['mean'], '+.3g'):>10s} {ci_text:>21s} {_f(m['diff']['median'], '+.3g'):>10s} "
                         f"{'same' if m['identical'] else _p(m['wilcoxon_p']):>8s} {_p(m['holm_p']):>7s}")
    rest = [k for k in metrics if k not in shown]
    if rest:
        same = sum(metrics[k]["identical"] for k in rest)
        lines.append(f"{len(rest)} other metric{'s' if len(rest) != 1 else ''} ({same} identical), none significant "
                     f"after Holm: see {COMPARE_JSON}")
    fr = doc.get("frames")
    if fr:
        changed = [k for k, m in fr["metrics"].items() if not m["identical"]]
        lines.append(f"per frame ({fr['n_frames']} paired frames, {COMPARE_JSON} 'frames'): "
                     + (f"{len(changed)} column(s) differ: {', '.join(changed)}" if changed else "all identical"))
    for g in doc["gates"]:
        lines.append(f"gate {'PASS' if g['passed'] else 'FAIL'} {g['spec']}: {g['reason']}")
    if written is not None:
        lines.append(f"written: {written}")
    failed = [g["spec"] for g in doc["gates"] if not g["passed"]]
    if failed:
        lines.append(f"FAILED gates: {', '.join(failed)}")
    elif doc["gates"]:
        lines.append(f"all {len(doc['gates'])} gates passed")
    else:
        lines.append("no gates given (--gate SPEC)")
    return "\n".join(lines)
