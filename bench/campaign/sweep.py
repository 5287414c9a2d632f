"""Design sweeps: ``landbench sweep``, a campaign per design point, on the Monte Carlo machinery.

Inputs: a base scenario (file or default, ``--set`` overrides), a design and
the campaign settings (``--runs``, ``--seed``, workers, backend, per-case
timeout). Designs:

* ``grid``: full factorial of ``--grid KEY=V1,V2,...`` (values as TOML values;
  ``range(start, stop[, step])`` as in Hydra's sweep grammar, stop excluded);
* ``lhs``: ``--lhs N`` Latin-hypercube points over ``--range KEY=LO:HI``
  (:class:`scipy.stats.qmc.LatinHypercube`);
* ``sobol``: ``--sobol N`` Saltelli/Sobol' points over the ranges (SALib,
  ``N (D + 2)`` points, first-order and total indices, no second order), and
  the indices with their 95 % bootstrap intervals for the point metrics.

A range whose two ends are integers gives integer values. The same design can
be a ``[sweep]`` table in the scenario file (:func:`split_sweep_table`).

Common random numbers: every point is a campaign with the same ``--runs``
and the same campaign seed, so case ``i`` has the same seed, the same
dispersion draws and the same sensor noise at every point; the points differ
only by the design. Every point's scenario is built and validated before
anything runs; an invalid one is refused naming the point and the field.

Execution: :func:`bench.campaign.mc.run_campaign` per point, in
``DIR/points/PPPP/`` (local workers or Ray, per-case timeout, resume: a
resumed sweep finishes the unfinished points and skips the finished cases).

Outputs in ``DIR``: ``sweep.json`` (design, settings, per-point statistics,
Pareto front, Sobol indices), ``scenario.toml`` (the base), ``points.parquet``
(one row per point), ``cases.parquet`` (one row per point and case) and
``report.html`` (:mod:`bench.report.sweep_html`).
"""

from __future__ import annotations

import itertools
import json
import math
import operator
import re
import time
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.report.io import atomic_write_text, json_safe
from bench.scenario import Scenario, ScenarioError, scenario_to_toml
from bench.scenario.schema import _toml_value, scenario_from_data  # noqa: F401 (scenario_from_data: the CLI)

SWEEP_JSON = "sweep.json"
MAX_GRID_VALUES = 10_000  # values one --grid range() may give
BASE_SCENARIO = "scenario.toml"
POINTS_DIR = "points"
POINTS_PARQUET = "points.parquet"
CASES_PARQUET = "cases.parquet"
POINT_JSON = "point.json"
KINDS = ("grid", "lhs", "sobol")
SOBOL_MIN_N = 8  # fewest base points of a Sobol design [-]
GFOLD = "gfold"
CONFIDENCE = 0.95
# Point metrics the Sobol indices are computed for, and the Pareto objectives (all minimised).
SOBOL_OUTPUTS = ("success_rate", "fuel_mean_kg", "td_speed_p95_mps", "miss_p95_m")
PARETO_OBJECTIVES = ("fuel_mean_kg", "td_speed_p95_mps", "miss_p95_m")
DEFAULT_REQUIRE = ("success_rate>=0.95",)
_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt, "==": operator.eq}


# --------------------------------------------------------------------------- the design
@dataclass
class Design:
    """A sweep design: its kind, factors and points.

    Attributes:
        kind: "grid", "lhs" or "sobol".
        factors: Field paths that vary, in order.
        points: One {field path: value} per design point.
        ranges: Field path -> (low, high), for lhs and sobol.
        samples: N of ``--lhs N`` / ``--sobol N``.
        seed: Seed of the lhs/sobol sample.
    """

    kind: str
    factors: list[str]
    points: list[dict[str, Any]]
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    samples: int | None = None
    seed: int = 0

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "factors": self.factors, "points": self.points,
                "ranges": {k: list(v) for k, v in self.ranges.items()}, "samples": self.samples, "seed": self.seed}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Design":
        return cls(d["kind"], list(d["factors"]), [dict(p) for p in d["points"]],
                   {k: (v[0], v[1]) for k, v in d["ranges"].items()}, d["samples"], d["seed"])

    def sobol_problem(self) -> dict[str, Any]:
        """The SALib problem of the ranges."""
        return {"num_vars": len(self.factors), "names": list(self.factors),
                "bounds": [[float(self.ranges[k][0]), float(self.ranges[k][1])] for k in self.factors]}


def _split_top(text: str) -> list[str]:
    """Split on commas outside brackets and quotes (``a,[1, 2],"x,y"`` -> three items)."""
    out, depth, quote, cur = [], 0, "", ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(cur)
            cur = ""
            continue
        cur += ch
    out.append(cur)
    return [s.strip() for s in out]


def _toml_scalar(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # bare words are strings (guidance.law=zem_zev)


_RANGE = re.compile(r"^range\(([^)]*)\)$")


def parse_grid(spec: str) -> tuple[str, list[Any]]:
    """``KEY=V1,V2,...`` or ``KEY=range(start, stop[, step])`` -> (key, values).

    Raises:
        ValueError: One line naming the flag, the bad text and the allowed form.
    """
    key, sep, text = spec.partition("=")
    key, text = key.strip(), text.strip()
    if not sep or not key or not text:
        raise ValueError(f"--grid {spec!r}: expected KEY=V1,V2,... or KEY=range(start, stop, step), "
                         "e.g. --grid guidance.law=zem_zev,apollo,gfold")
    m = _RANGE.match(text)
    if m:
        try:
            args = [_toml_scalar(a) for a in _split_top(m.group(1))]
            if not (1 <= len(args) <= 3) or not all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                                    and math.isfinite(a) for a in args):
                raise ValueError
            start, stop, step = (0, args[0], 1) if len(args) == 1 else (args[0], args[1], args[2] if len(args) == 3 else 1)
            if step == 0:
                raise ValueError
        except ValueError:
            raise ValueError(f"--grid {spec!r}: range() takes 1 to 3 finite numbers (start, stop, step != 0)") from None
        span = (stop - start) / step
        if not math.isfinite(span):
            raise ValueError(f"--grid {spec!r}: range() gives too many values; allowed: at most {MAX_GRID_VALUES} "
                             "per field")
        n = max(0, math.ceil(span))
        if n > MAX_GRID_VALUES:
            raise ValueError(f"--grid {spec!r}: range() gives {n} values; allowed: at most {MAX_GRID_VALUES} per field")
        values = [start + i * step for i in range(n)]
        if all(isinstance(a, int) for a in (start, step)):
            values = [int(v) for v in values]
        else:
            values = [round(float(v), 12) for v in values]
    else:
        values = [_toml_scalar(v) for v in _split_top(text)]
    if not values or any(v == "" for v in values):
        raise ValueError(f"--grid {spec!r}: no values (or an empty one); give at least one")
    # 1 and 1.0 are one value (the scenario field gets the same number either way): compare numbers as numbers.
    same = [float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else repr(v) for v in values]
    if len(set(same)) != len(values):
        raise ValueError(f"--grid {spec!r}: a value is repeated; give each value once")
    return key, values


def parse_range(spec: str) -> tuple[str, tuple[float, float]]:
    """``KEY=LOW:HIGH`` -> (key, (low, high)), numbers, low < high."""
    key, sep, text = spec.partition("=")
    key = key.strip()
    lo_t, colon, hi_t = text.partition(":")
    lo, hi = _toml_scalar(lo_t.strip()), _toml_scalar(hi_t.strip())
    ok = sep and key and colon and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (lo, hi))
    if not ok or not lo < hi:
        raise ValueError(f"--range {spec!r}: expected KEY=LOW:HIGH with numbers LOW < HIGH, "
                         "e.g. --range control.attitude_bandwidth_radps=1:4")
    return key, (lo, hi)


def _scaled(unit: np.ndarray, ranges: Mapping[str, tuple[float, float]]) -> list[dict[str, Any]]:
    """Unit-cube samples (n, d) to points, integer where both ends of the range are integers."""
    keys = list(ranges)
    lo = np.array([ranges[k][0] for k in keys], float)
    hi = np.array([ranges[k][1] for k in keys], float)
    x = lo + unit * (hi - lo)
    return [_typed(dict(zip(keys, row)), ranges) for row in x]


def _typed(point: Mapping[str, float], ranges: Mapping[str, tuple[float, float]]) -> dict[str, Any]:
    """A sampled point in its fields' types: an integer range ``lo:hi`` gives each of its hi - lo + 1 integers an
    equal share of the range (rounding gave its two ends half a share each)."""
    out = {}
    for k, v in point.items():
        lo, hi = ranges[k]
        if isinstance(lo, int) and isinstance(hi, int):
            u = (float(v) - lo) / (hi - lo) if hi > lo else 0.0
            out[k] = min(lo + int(math.floor(u * (hi - lo + 1))), hi)
        else:
            out[k] = float(v)
    return out


def grid_design(grids: Sequence[tuple[str, list[Any]]]) -> Design:
    """Full factorial of the grids, the first factor varying slowest."""
    keys = [k for k, _ in grids]
    if len(set(keys)) != len(keys):
        raise ValueError(f"--grid: a field is given twice ({', '.join(keys)}); give each field once")
    points = [dict(zip(keys, combo)) for combo in itertools.product(*(v for _, v in grids))]
    return Design("grid", keys, points)


def lhs_design(ranges: Mapping[str, tuple[float, float]], n: int, seed: int) -> Design:
    """``n`` Latin-hypercube points over the ranges (scipy.stats.qmc, seeded)."""
    from scipy.stats import qmc

    unit = qmc.LatinHypercube(d=len(ranges), rng=np.random.default_rng(seed)).random(n)
    return Design("lhs", list(ranges), _scaled(unit, ranges), dict(ranges), n, seed)


def sobol_design(ranges: Mapping[str, tuple[float, float]], n: int, seed: int) -> Design:
    """Saltelli's scheme for first-order and total Sobol' indices: ``n (d + 2)`` points (SALib).

    Integer ranges are sampled as reals and mapped to integers (equal shares, :func:`_typed`); the
    indices are computed on the real-valued sample (the design's).
    """
    try:
        from SALib.sample import sobol as sobol_sample
    except ImportError:
        raise ValueError("--sobol needs SALib, the optional extra: pip install 'landbench[sweep]'") from None
    d = Design("sobol", list(ranges), [], dict(ranges), n, seed)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # SALib warns when n is not a power of 2 (the balance property); allowed
        x = sobol_sample.sample(d.sobol_problem(), n, calc_second_order=False, scramble=True, seed=seed)
    d.points = [_typed(dict(zip(d.factors, row)), ranges) for row in x]
    return d


def sobol_indices(design: Design, y: Sequence[float], seed: int = 0) -> dict[str, Any]:
    """First-order and total Sobol' indices of one response over a Sobol design, with 95 % intervals (SALib).

    Args:
        design: A "sobol" design.
        y: The response at every design point, in point order.
        seed: Seed of SALib's bootstrap.

    Returns:
        {factor: {"S1", "S1_conf", "ST", "ST_conf"}} (conf: half-width of the
        95 % bootstrap interval); None (undefined) where the response is not finite everywhere, or the
        same at every point (no variance to apportion: SALib would read 0 +- 0, as if no factor mattered).
    """
    from SALib.analyze import sobol as sobol_analyze

    y = np.asarray(y, float)
    if not np.all(np.isfinite(y)) or np.ptp(y) == 0.0:
        return {k: {"S1": None, "S1_conf": None, "ST": None, "ST_conf": None} for k in design.factors}
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = sobol_analyze.analyze(design.sobol_problem(), y, calc_second_order=False, conf_level=CONFIDENCE,
                                    num_resamples=200, seed=seed, print_to_console=False)
    return {k: {name: float(res[name][i]) for name in ("S1", "S1_conf", "ST", "ST_conf")}
            for i, k in enumerate(design.factors)}


def design_from_args(grids: Sequence[str], lhs: int | None, sobol: int | None, ranges: Sequence[str],
                     seed: int, table: Mapping[str, Any] | None = None) -> Design:
    """Build the design from the flags, or from the scenario file's ``[sweep]`` table when no flag is given.

    ``[sweep]`` keys: ``grid`` (table: field -> list of values), ``lhs`` or
    ``sobol`` (N), ``ranges`` (table: field -> [low, high]); the flags win.
    """
    if not grids and lhs is None and sobol is None and table:
        grids = [f"{k}={','.join(_toml_value(v) for v in vals)}" if isinstance(vals, list) else f"{k}={vals}"
                 for k, vals in (table.get("grid") or {}).items()]
        lhs, sobol = table.get("lhs"), table.get("sobol")
        ranges = [f"{k}={v[0]}:{v[1]}" if isinstance(v, list) and len(v) == 2 else f"{k}={v}"
                  for k, v in (table.get("ranges") or {}).items()]
    chosen = [name for name, on in (("--grid", bool(grids)), ("--lhs", lhs is not None), ("--sobol", sobol is not None))
              if on]
    if len(chosen) != 1:
        raise ValueError("give one design: --grid KEY=V1,V2 (repeatable), --lhs N or --sobol N with --range "
                         f"KEY=LOW:HIGH (or a [sweep] table in the scenario file); got {', '.join(chosen) or 'none'}")
    if grids:
        if ranges:
            raise ValueError("--range is for --lhs and --sobol; a grid lists its values: --grid KEY=V1,V2")
        return grid_design([parse_grid(g) for g in grids])
    n = lhs if lhs is not None else sobol
    flag = "--lhs" if lhs is not None else "--sobol"
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"{flag} {n!r}: must be an integer >= 1")
    parsed = [parse_range(r) for r in ranges]
    if not parsed:
        raise ValueError(f"{flag} {n} needs ranges: --range KEY=LOW:HIGH (repeatable)")
    keys = [k for k, _ in parsed]
    if len(set(keys)) != len(keys):
        raise ValueError(f"--range: a field is given twice ({', '.join(keys)}); give each field once")
    if sobol is not None and len(parsed) < 2:
        raise ValueError("--sobol needs at least two --range factors (indices of one factor are trivial)")
    if sobol is not None and n < SOBOL_MIN_N:
        raise ValueError(f"--sobol {n}: Saltelli's estimates and their bootstrap intervals need at least "
                         f"{SOBOL_MIN_N} base points (N = 1 gave indices of 2 +- 0); allowed: {SOBOL_MIN_N} or more, "
                         "a power of 2")
    return (lhs_design if lhs is not None else sobol_design)(dict(parsed), n, seed)


def split_sweep_table(path: str | Path | None) -> tuple[dict[str, Any], Path, dict[str, Any] | None]:
    """Read a scenario file and take its ``[sweep]`` table out: (scenario data, its folder, sweep table or None)."""
    from bench.scenario.schema import read_scenario_data

    data, base = read_scenario_data(path)
    table = data.pop("sweep", None)
    if table is not None and not isinstance(table, dict):
        raise ScenarioError(f"sweep = {table!r}: expected a [sweep] table")
    if table is not None:
        unknown = set(table) - {"grid", "lhs", "sobol", "ranges", "runs", "require"}
        if unknown:
            raise ScenarioError(f"unknown field 'sweep.{sorted(unknown)[0]}'; allowed here: grid, lhs, sobol, ranges, "
                                "runs, require")
        _check_sweep_types(table)
    return data, base, table


def _check_sweep_types(table: dict[str, Any]) -> None:
    """The ``[sweep]`` table's entries have the types they are read as (one line naming the first that has not)."""
    expected = {"grid": (dict, "a table: field = [values]"), "ranges": (dict, "a table: field = [low, high]"),
                "require": (list, "a list of strings: [\"success_rate>=0.95\"]")}
    for key, (kind, what) in expected.items():
        value = table.get(key)
        if value is not None and (not isinstance(value, kind)
                                  or (key == "require" and not all(isinstance(r, str) for r in value))):
            raise ScenarioError(f"sweep.{key} = {value!r}: expected {what}")
    for key in ("runs", "lhs", "sobol"):
        value = table.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ScenarioError(f"sweep.{key} = {value!r}: expected a whole number >= 1")


def point_overrides(point: Mapping[str, Any]) -> list[str]:
    """A design point as ``--set`` assignments."""
    return [f"{k}={_toml_value(v)}" for k, v in point.items()]


def point_label(index: int, point: Mapping[str, Any]) -> str:
    return f"point {index} ({', '.join(f'{k}={v!r}' for k, v in point.items())})"


def point_scenarios(data: dict[str, Any], base_dir: Path, overrides: Sequence[str], design: Design) -> list[Scenario]:
    """Every point's scenario, validated before anything runs.

    Raises:
        ScenarioError: ``sweep point P (field=value, ...): <the field's error>`` for the first invalid point.
    """
    out = []
    for i, point in enumerate(design.points):
        try:
            out.append(scenario_from_data(data, base_dir, [*overrides, *point_overrides(point)]))
        except ScenarioError as exc:
            raise ScenarioError(f"sweep {point_label(i, point)}: {exc}") from None
    return out


# --------------------------------------------------------------------------- requirements
@dataclass(frozen=True)
class Requirement:
    metric: str
    op: str
    value: float

    def __str__(self) -> str:
        return f"{self.metric}{self.op}{self.value:g}"

    def holds(self, row: Mapping[str, Any]) -> bool:
        v = row.get(self.metric)
        return v is not None and isinstance(v, (int, float)) and math.isfinite(v) and _OPS[self.op](v, self.value)


_REQ = re.compile(r"^\s*([A-Za-z_]\w*)\s*(>=|<=|==|>|<)\s*([-+0-9.eE]+)\s*$")


def parse_require(spec: str) -> Requirement:
    """``METRIC>=VALUE`` (also <=, >, <, ==) on a point metric."""
    m = _REQ.match(spec)
    allowed = ", ".join(POINT_METRICS)
    if not m:
        raise ValueError(f"--require {spec!r}: expected METRIC>=VALUE, e.g. --require success_rate>=0.95; "
                         f"metrics: {allowed}")
    if m.group(1) not in POINT_METRICS:
        raise ValueError(f"--require {spec!r}: unknown metric {m.group(1)!r}; allowed: {allowed}")
    try:
        value = float(m.group(3))
    except ValueError:
        raise ValueError(f"--require {spec!r}: {m.group(3)!r} is not a number") from None
    return Requirement(m.group(1), m.group(2), value)


# --------------------------------------------------------------------------- statistics
POINT_METRICS = ("n_cases", "landed", "success_rate", "success_wilson_low", "success_wilson_high", "fuel_mean_kg",
                 "fuel_p95_kg", "fuel_ratio_gfold_mean", "fuel_ratio_gfold_p95", "td_v_vertical_p95_mps",
                 "td_v_horizontal_p95_mps", "td_speed_p95_mps", "miss_p95_m", "wall_time_s", "case_wall_time_mean_s")


def _p95(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, 95)) if x.size else None


def _mean(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if x.size else None


def gfold_partner(design: Design, index: int) -> int | None:
    """The point that differs from ``index`` only by ``guidance.law = "gfold"`` (None when there is none)."""
    if "guidance.law" not in design.factors:
        return None
    p = design.points[index]
    for j, q in enumerate(design.points):
        if q["guidance.law"] == GFOLD and all(q[k] == p[k] for k in design.factors if k != "guidance.law"):
            return j
    return None


def point_stats(rows: Sequence[Mapping[str, Any]], ratio: np.ndarray | None, wall_s: float | None) -> dict[str, Any]:
    """One point's statistics from its case rows (and the per-case fuel ratio to G-FOLD, when there is one)."""
    from bench.campaign.rows import column
    from bench.report.mc_report import wilson_interval

    n = len(rows)
    landed = int(sum(bool(r.get("landed")) for r in rows))
    lo, hi = wilson_interval(landed, n, CONFIDENCE) if n else (None, None)
    vv, vh = column(rows, "touchdown_v_vertical_mps"), column(rows, "touchdown_v_horizontal_mps")
    fuel = column(rows, "fuel_used_kg")
    return {
        "n_cases": n, "landed": landed, "success_rate": landed / n if n else None,
        "success_wilson_low": lo, "success_wilson_high": hi,
        "fuel_mean_kg": _mean(fuel), "fuel_p95_kg": _p95(fuel),
        "fuel_ratio_gfold_mean": _mean(ratio) if ratio is not None else None,
        "fuel_ratio_gfold_p95": _p95(ratio) if ratio is not None else None,
        "td_v_vertical_p95_mps": _p95(vv), "td_v_horizontal_p95_mps": _p95(vh),
        "td_speed_p95_mps": _p95(np.hypot(vv, vh)), "miss_p95_m": _p95(column(rows, "touchdown_miss_distance_m")),
        "wall_time_s": wall_s, "case_wall_time_mean_s": _mean(column(rows, "case_wall_time_s")),
    }


def pareto_front(points: Sequence[Mapping[str, Any]], objectives: Sequence[str] = PARETO_OBJECTIVES,
                 eligible: Sequence[bool] | None = None) -> list[int]:
    """Indices of the non-dominated points (every objective minimised) among the eligible ones.

    A point with a missing objective is not eligible. ``q`` dominates ``p`` when
    it is no worse in every objective and better in at least one.
    """
    cand = []
    for i, p in enumerate(points):
        vals = [p.get(k) for k in objectives]
        if (eligible is None or eligible[i]) and all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            cand.append((i, np.array(vals, float)))
    front = []
    for i, a in cand:
        if not any(np.all(b <= a) and np.any(b < a) for j, b in cand if j != i):
            front.append(i)
    return front


# --------------------------------------------------------------------------- running
def run_sweep(data: dict[str, Any], base_dir: Path, overrides: Sequence[str], design: Design, runs: int, out: Path,
              campaign_seed: int, workers: int | None = 1, resume: bool = False, retention: str = "summary",
              case_timeout_s: float | None = None, progress: bool = True, backend: str = "local",
              address: str | None = None, require: Sequence[str] = DEFAULT_REQUIRE,
              dry_run: bool = False) -> dict[str, Any]:
    """Run (or resume) a sweep; returns the ``sweep.json`` document.

    Every point's scenario and every requirement is checked first; nothing is
    written when one is invalid. ``dry_run``: only write every point's
    dispersed case scenarios (``points/PPPP/cases/NNNNN/scenario.toml``) and
    return the design document without statistics.
    """
    from bench.campaign import mc

    reqs = [parse_require(r) for r in require]
    meta_path = out / SWEEP_JSON
    if not resume and out.exists() and any(out.iterdir()) and not meta_path.exists():
        raise ValueError(f"--out {out} is a folder that is not empty and holds no sweep; give a new folder")
    if resume:
        if not meta_path.exists():
            raise ValueError(f"--resume {out}: no {SWEEP_JSON} there; start the sweep with --out")
        old = mc.read_meta(meta_path, ("design", "runs", "campaign_seed"), "--resume")
        design = Design.from_json(old["design"])
        runs, campaign_seed = old["runs"], old["campaign_seed"]
        from bench.scenario.schema import read_scenario_data

        data, base_dir = read_scenario_data(out / BASE_SCENARIO)
        overrides = []
    elif meta_path.exists():
        raise ValueError(f"--out {out} already holds a sweep; use --resume, or another folder")
    scenarios = point_scenarios(data, base_dir, overrides, design)  # every point validated before anything runs
    mc.check_campaign_args(runs, campaign_seed, workers, retention, case_timeout_s, backend, address)
    if not resume:
        if dry_run:  # a dry run's cases, before anything is written
            for i, sc in enumerate(scenarios):
                try:
                    mc.check_cases(sc, runs, campaign_seed)
                except ValueError as exc:
                    raise ValueError(f"point {i}: {exc}") from None
        base = scenario_from_data(data, base_dir, overrides)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / BASE_SCENARIO, scenario_to_toml(base))
        atomic_write_text(meta_path, json.dumps(json_safe(_doc(design, runs, campaign_seed, reqs)), indent=1) + "\n")
    all_rows: list[list[dict[str, Any]]] = []
    for i, sc in enumerate(scenarios):
        pdir = out / POINTS_DIR / f"{i:04d}"
        done_path = pdir / POINT_JSON
        if progress:
            print(f"sweep: {point_label(i, design.points[i])} [{i + 1}/{len(scenarios)}]", flush=True)
        t0 = time.perf_counter()
        rows = mc.run_campaign(sc, runs, pdir, campaign_seed, workers=workers,
                               resume=resume and (pdir / mc.CAMPAIGN).exists(), retention=retention,
                               case_timeout_s=case_timeout_s, progress=progress, backend=backend, address=address,
                               dry_run=dry_run)
        if dry_run:
            continue
        wall = time.perf_counter() - t0
        if done_path.exists():  # a resumed point: its wall time is the first run's plus this one's
            wall += json.loads(done_path.read_text()).get("wall_time_s") or 0.0
        atomic_write_text(done_path, json.dumps({"point": i, "values": design.points[i], "wall_time_s": wall}) + "\n")
        all_rows.append(rows)
    if dry_run:
        return _doc(design, runs, campaign_seed, reqs)
    doc = summarise(design, all_rows, [json.loads((out / POINTS_DIR / f"{i:04d}" / POINT_JSON).read_text())["wall_time_s"]
                                       for i in range(len(scenarios))], reqs, runs, campaign_seed)
    write_tables(doc, all_rows, out)
    atomic_write_text(meta_path, json.dumps(json_safe(doc), indent=1) + "\n")
    from bench.report.sweep_html import write_sweep_report

    write_sweep_report(doc, out)
    return doc


def _doc(design: Design, runs: int, campaign_seed: int, reqs: Sequence[Requirement]) -> dict[str, Any]:
    return {"design": design.to_json(), "runs": runs, "campaign_seed": campaign_seed,
            "require": [str(r) for r in reqs]}


def _ratio(num: float, den: float) -> float:
    return num / den if den != 0.0 and math.isfinite(den) else math.nan


def case_fuel_ratios(design: Design, all_rows: Sequence[Sequence[Mapping[str, Any]]]) -> list[np.ndarray | None]:
    """Per point, each case's fuel over the same case's fuel at its G-FOLD partner point (None: no partner)."""
    from bench.campaign.rows import row_float

    out: list[np.ndarray | None] = []
    for i, rows in enumerate(all_rows):
        j = gfold_partner(design, i)
        if j is None:
            out.append(None)
            continue
        ref = {r["case"]: row_float(r.get("fuel_used_kg")) for r in all_rows[j]}
        # A partner case that used no fuel (or none known) gives no ratio: NaN, left out like a missing value.
        out.append(np.array([_ratio(row_float(r.get("fuel_used_kg")), ref.get(r["case"], math.nan)) for r in rows],
                            float))
    return out


def summarise(design: Design, all_rows: Sequence[Sequence[Mapping[str, Any]]], walls: Sequence[float | None],
              reqs: Sequence[Requirement], runs: int, campaign_seed: int) -> dict[str, Any]:
    """Per-point statistics, the Pareto front among the points meeting the requirements, and Sobol indices."""
    ratios = case_fuel_ratios(design, all_rows)
    points = []
    for i, rows in enumerate(all_rows):
        points.append({"point": i, **design.points[i], **point_stats(rows, ratios[i], walls[i])})
    ok = [all(r.holds(p) for r in reqs) for p in points]
    for p, good in zip(points, ok):
        p["meets_require"] = good
    front = pareto_front(points, PARETO_OBJECTIVES, ok)
    for p in points:
        p["pareto"] = p["point"] in front
    doc = {**_doc(design, runs, campaign_seed, reqs), "points": points, "pareto_front": front,
           "pareto_objectives": list(PARETO_OBJECTIVES)}
    if design.kind == "sobol":
        doc["sobol"] = {out: sobol_indices(design, [p[out] if p[out] is not None else math.nan for p in points])
                        for out in SOBOL_OUTPUTS}
    return doc


def write_tables(doc: Mapping[str, Any], all_rows: Sequence[Sequence[Mapping[str, Any]]], out: Path) -> None:
    """``points.parquet`` (one row per point) and ``cases.parquet`` (one row per point and case)."""
    from bench.campaign.mc import write_cases_parquet

    design = Design.from_json(doc["design"])
    ratios = case_fuel_ratios(design, all_rows)
    cases = []
    for i, rows in enumerate(all_rows):
        for k, r in enumerate(rows):
            extra = {"fuel_ratio_gfold": float(ratios[i][k]) if ratios[i] is not None else None}
            cases.append({"point": i, **{f"design_{f}": design.points[i][f] for f in design.factors}, **extra, **r})
    write_cases_parquet(cases, out / CASES_PARQUET)
    write_cases_parquet([dict(p) for p in doc["points"]], out / POINTS_PARQUET)


POINT_COLUMNS = ("success_rate", "success_wilson", "fuel_mean_kg", "fuel_p95_kg", "fuel_ratio_gfold_mean",
                 "td_v_vertical_p95_mps", "td_v_horizontal_p95_mps", "miss_p95_m", "wall_time_s", "pareto")
"""The per-point figures of the points table, after the design's factors (CLI, README and HTML report)."""


def format_point_cell(p: Mapping[str, Any], c: str, markdown: bool = True) -> str:
    """One cell of the points table: point ``p``'s column ``c`` as text (Markdown bold for a Pareto point)."""
    if c == "success_wilson":
        lo, hi = p["success_wilson_low"], p["success_wilson_high"]
        return "—" if lo is None else f"{100 * lo:.0f}–{100 * hi:.0f} %"
    v = p.get(c)
    if c == "pareto":
        if v:
            return "**yes**" if markdown else "yes"
        return ("no" if markdown else "") if p["meets_require"] else "fails require"
    if v is None:
        return "—"
    if c == "success_rate":
        return f"{100 * v:.0f} %"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def format_points(doc: Mapping[str, Any]) -> str:
    """The points table as Markdown (the CLI prints it; the README quotes it)."""
    factors = doc["design"]["factors"]
    cols = [*factors, *POINT_COLUMNS]
    cell = format_point_cell

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(cell(p, c) for c in cols) + " |" for p in doc["points"]]
    if doc.get("sobol"):
        lines.append("")
        lines.append("| output | factor | S1 | ±95 % | ST | ±95 % |")
        lines.append("|---|---|---|---|---|---|")
        for outp, per in doc["sobol"].items():
            for f, s in per.items():
                lines.append(f"| {outp} | {f} | " + " | ".join("—" if s[k] is None else f"{s[k]:.3f}"
                                                               for k in ("S1", "S1_conf", "ST", "ST_conf")) + " |")
    return "\n".join(lines)
