"""The fault matrix: ``landbench faults``, every preset x N seeds on the Monte Carlo machinery.

Inputs: a base scenario (file or default, ``--set`` overrides), the presets
(``all``: every preset of :mod:`bench.scenario.presets`, plus the no-fault
reference ``nominal``), ``--runs N`` and the campaign settings (seed,
workers, backend, per-case timeout).

Execution: for each preset, :func:`bench.campaign.mc.run_campaign` of the
base with the preset laid over it, in ``DIR/presets/NAME/`` (local workers or
Ray, resumable: ``--resume DIR`` finishes the unfinished presets and skips the
finished cases). Every preset uses the same campaign seed, so case ``i`` has
the same seed and dispersions under every preset (common random numbers).

The matrix (one row per preset): outcome counts; the success rate (landed)
and the landed-or-safe-abort rate, each with its Wilson interval; the
injected faults that triggered, the fraction the flight software detected and
the detection latency (median, max); the cases whose failure the flight
software did not see coming (neither landed nor safely aborted, and no abort
declared before the end: ``unseen``; a declared abort that still ends on the
ground too hard counts as seen, not as safe); the cases with a detection
although nothing was injected (``false_alarm``, on the ``nominal`` row only:
a stress preset without faults has true detections); touchdown figures (p95
vertical and horizontal speed, median miss) and fuel.

Outputs in ``DIR``: ``faults.json`` (settings and matrix), ``matrix.parquet``,
``cases.parquet`` (every preset's cases), ``matrix.md`` (the README table),
``report.png`` (outcomes per preset) and each preset's campaign report.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.report.io import atomic_write_text, json_safe
from bench.scenario import scenario_to_toml
from bench.scenario.presets import REFERENCE, TERRAIN_PRESETS, get_preset, preset_names
from bench.scenario.schema import read_scenario_data, scenario_from_data

FAULTS_JSON = "faults.json"
BASE_SCENARIO = "scenario.toml"
PRESETS_DIR = "presets"
MATRIX_PARQUET = "matrix.parquet"
CASES_PARQUET = "cases.parquet"
MATRIX_MD = "matrix.md"
PRESET_JSON = "preset.json"  # per preset: its wall time so far (a resume adds to it)
REPORT = "report.png"
CONFIDENCE = 0.95
MAX_FAULTS_PER_CASE = 8  # fault columns read from a case row (faults_0_... to faults_7_...)


def parse_presets(text: str) -> list[str]:
    """``all`` (every preset and the ``nominal`` reference) or ``NAME,NAME`` -> the names, validated."""
    names = [*preset_names(), REFERENCE.name] if text.strip() == "all" else [t.strip() for t in text.split(",")]
    if not names or any(not n for n in names):
        raise ValueError(f"--presets {text!r}: expected all or NAME,NAME (landbench faults list)")
    if len(set(names)) != len(names):
        raise ValueError(f"--presets {text!r}: a preset is given twice; give each once")
    for n in names:
        try:
            get_preset(n)
        except ValueError:
            raise ValueError(f"--presets {text!r}: no preset {n!r}; allowed: all, or names among "
                             f"{', '.join([*preset_names(), REFERENCE.name])} (landbench faults list), or the terrain "
                             f"preset{'s' if len(TERRAIN_PRESETS) > 1 else ''} {', '.join(TERRAIN_PRESETS)}") from None
    return names


def list_presets() -> str:
    """One line per preset: its name and its provenance."""
    width = max(len(n) for n in [*preset_names(), REFERENCE.name])
    return "\n".join(f"{n:<{width}}  {get_preset(n).provenance}" for n in [*preset_names(), REFERENCE.name])


# --------------------------------------------------------------------------- statistics
def _case_faults(row: Mapping[str, Any]) -> list[dict[str, Any]]:
    out = []
    for i in range(MAX_FAULTS_PER_CASE):
        if f"faults_{i}_kind" not in row:
            break
        out.append({k: row.get(f"faults_{i}_{k}") for k in ("kind", "target", "triggered", "detected", "latency_s")})
    return out


def _p(x: np.ndarray, q: float) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else None


def preset_stats(rows: Sequence[Mapping[str, Any]], reference: bool = False) -> dict[str, Any]:
    """One matrix row from a preset's case rows.

    ``reference``: the no-fault preset, whose detections are false alarms (``false_alarm`` is None for the
    others: a stress preset without ``[[faults]]`` has true detections, of the vision it degrades).
    """
    from bench.campaign.rows import column
    from bench.report.mc_report import outcome_counts, wilson_interval

    n = len(rows)
    counts = outcome_counts(rows)
    landed = counts.get("landed", 0)
    safe = landed + counts.get("safe_abort", 0)
    lo, hi = wilson_interval(landed, n, CONFIDENCE) if n else (None, None)
    slo, shi = wilson_interval(safe, n, CONFIDENCE) if n else (None, None)
    injected = detected = 0
    latencies = []
    for r in rows:
        for f in _case_faults(r):
            if f["triggered"]:
                injected += 1
                if f["detected"]:
                    detected += 1
                    if f["latency_s"] is not None:
                        latencies.append(float(f["latency_s"]))
    lat = np.array(latencies, float)
    failed = [r for r in rows if r.get("outcome") not in ("landed", "safe_abort")]
    unseen = sum(1 for r in failed if not r.get("fdir_abort_declared"))
    false_alarm = sum(1 for r in rows if (r.get("fdir_n_events") or 0)) if reference else None
    vv, vh = column(rows, "touchdown_v_vertical_mps"), column(rows, "touchdown_v_horizontal_mps")
    return {
        "n_cases": n, "outcomes": counts, "landed": landed, "safe_abort": counts.get("safe_abort", 0),
        "success_rate": landed / n if n else None, "success_wilson_low": lo, "success_wilson_high": hi,
        "land_or_abort_rate": safe / n if n else None, "land_or_abort_wilson_low": slo,
        "land_or_abort_wilson_high": shi,
        "faults_injected": injected, "faults_detected": detected,
        "detection_rate": detected / injected if injected else None,
        "latency_median_s": _p(lat, 50), "latency_max_s": float(lat.max()) if lat.size else None,
        "failed": len(failed), "unseen": unseen, "false_alarm": false_alarm,
        "td_v_vertical_p95_mps": _p(vv, 95), "td_v_horizontal_p95_mps": _p(vh, 95),
        "miss_median_m": _p(column(rows, "touchdown_miss_distance_m"), 50),
        "fuel_mean_kg": _mean(column(rows, "fuel_used_kg")),
    }


def _mean(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if x.size else None


# --------------------------------------------------------------------------- running
def run_faults(presets: Sequence[str], runs: int, out: Path, campaign_seed: int | None, scenario: str | None = None,
               overrides: Sequence[str] = (), workers: int | None = 1, resume: bool = False,
               retention: str = "summary", case_timeout_s: float | None = None, progress: bool = True,
               backend: str = "local", address: str | None = None) -> dict[str, Any]:
    """Run (or resume) the fault matrix; returns the ``faults.json`` document.

    Every preset's scenario is built and validated before anything runs or is written.
    """
    from bench.campaign import mc

    meta_path = out / FAULTS_JSON
    if resume:
        if not meta_path.exists():
            raise ValueError(f"--resume {out}: no {FAULTS_JSON} there; start the matrix with --out")
        old = mc.read_meta(meta_path, ("presets", "runs", "campaign_seed"), "--resume")
        presets, runs, campaign_seed = old["presets"], old["runs"], old["campaign_seed"]
        data, base_dir = read_scenario_data(out / BASE_SCENARIO)
        overrides = []
    else:
        if meta_path.exists():
            raise ValueError(f"--out {out} already holds a fault matrix; use --resume, or another folder")
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {str(out)!r} is a file; give a folder")
        if out.exists() and any(out.iterdir()):
            raise ValueError(f"--out {out} is a folder that is not empty and holds no fault matrix; give a new folder")
        data, base_dir = read_scenario_data(scenario)
    base = scenario_from_data(data, base_dir, overrides)
    campaign_seed = base.seed if campaign_seed is None else campaign_seed
    scenarios = {}
    for name in presets:
        try:
            scenarios[name] = scenario_from_data(data, base_dir, overrides, name)
        except ValueError as exc:
            raise ValueError(f"preset {name}: {exc}") from None
    mc.check_campaign_args(runs, campaign_seed, workers, retention, case_timeout_s, backend, address)
    if not resume:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / BASE_SCENARIO, scenario_to_toml(base))
        atomic_write_text(meta_path, json.dumps({"presets": list(presets), "runs": runs,
                                                 "campaign_seed": campaign_seed}, indent=1) + "\n")
    all_rows: dict[str, list[dict[str, Any]]] = {}
    walls: dict[str, float] = {}
    for k, (name, sc) in enumerate(scenarios.items()):
        pdir = out / PRESETS_DIR / name
        if progress:
            print(f"faults: preset {name} [{k + 1}/{len(scenarios)}]", flush=True)
        t0 = time.perf_counter()
        rows = mc.run_campaign(sc, runs, pdir, campaign_seed, workers=workers,
                               resume=(pdir / mc.CAMPAIGN).exists(), retention=retention,
                               case_timeout_s=case_timeout_s, progress=progress, backend=backend, address=address)
        walls[name] = time.perf_counter() - t0
        done_path = pdir / PRESET_JSON
        if done_path.exists():  # a resumed preset: its wall time is the earlier runs' plus this one's
            walls[name] += json.loads(done_path.read_text()).get("wall_time_s") or 0.0
        atomic_write_text(done_path, json.dumps({"preset": name, "wall_time_s": walls[name]}) + "\n")
        all_rows[name] = rows
        _preset_report(sc, rows, pdir, name, campaign_seed)
    matrix = [{"preset": name, "provenance": get_preset(name).provenance,
               **preset_stats(rows, reference=name == REFERENCE.name),
               "wall_time_s": walls[name]} for name, rows in all_rows.items()]
    doc = {"presets": list(presets), "runs": runs, "campaign_seed": campaign_seed, "matrix": matrix}
    _write_tables(doc, all_rows, out)
    atomic_write_text(meta_path, json.dumps(json_safe(doc), indent=1) + "\n")
    atomic_write_text(out / MATRIX_MD, format_matrix(doc) + "\n")
    write_matrix_figure(doc, out / REPORT)
    return doc


def _preset_report(sc, rows, pdir: Path, name: str, seed: int) -> None:
    """The preset's campaign report (the figure of ``landbench mc``)."""
    from bench.report.mc_report import write_campaign_report

    terrain = None
    if "terrain.seed" not in sc.dispersions:
        from bench.sim.world_builder import build_terrain

        terrain = build_terrain(sc)
    write_campaign_report(rows, sc.landing.model_dump(), pdir / "report.png", terrain=terrain,
                          title=f"preset {name}: {len(rows)} cases, campaign seed {seed}",
                          sun_elevation_deg=sc.sun.elevation_deg, sun_azimuth_deg=sc.sun.azimuth_deg)


def _write_tables(doc: Mapping[str, Any], all_rows: Mapping[str, Sequence[Mapping[str, Any]]], out: Path) -> None:
    from bench.campaign.mc import write_cases_parquet

    cases = [{"preset": name, **r} for name, rows in all_rows.items() for r in rows]
    write_cases_parquet(cases, out / CASES_PARQUET)
    flat = []
    for m in doc["matrix"]:
        row = {k: v for k, v in m.items() if k != "outcomes"}
        row.update({f"n_{o}": c for o, c in m["outcomes"].items()})
        flat.append(row)
    write_cases_parquet(flat, out / MATRIX_PARQUET)


# --------------------------------------------------------------------------- output
def _pct(v: float | None) -> str:
    return "—" if v is None else f"{100 * v:.0f} %"


def _wilson(lo: float | None, hi: float | None) -> str:
    return "—" if lo is None else f"{100 * lo:.0f}–{100 * hi:.0f} %"


def _num(v: float | None, spec: str = ".2f") -> str:
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def format_matrix(doc: Mapping[str, Any]) -> str:
    """The matrix as Markdown (the CLI prints it; the README quotes it)."""
    head = ["preset", "outcomes", "landed", "95 % CI", "landed or safe abort", "95 % CI", "faults detected",
            "latency median / max [s]", "failed / unseen", "false alarms", "p95 v_v / v_h [m/s]", "miss median [m]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in doc["matrix"]:
        outcomes = ", ".join(f"{o} {c}" for o, c in m["outcomes"].items())
        det = "—" if not m["faults_injected"] else f"{m['faults_detected']}/{m['faults_injected']}"
        lines.append("| " + " | ".join([
            m["preset"], outcomes, _pct(m["success_rate"]), _wilson(m["success_wilson_low"], m["success_wilson_high"]),
            _pct(m["land_or_abort_rate"]), _wilson(m["land_or_abort_wilson_low"], m["land_or_abort_wilson_high"]),
            det, f"{_num(m['latency_median_s'])} / {_num(m['latency_max_s'])}", f"{m['failed']} / {m['unseen']}",
            "—" if m["false_alarm"] is None else str(m["false_alarm"]),
            f"{_num(m['td_v_vertical_p95_mps'])} / {_num(m['td_v_horizontal_p95_mps'])}", _num(m["miss_median_m"], ".1f"),
        ]) + " |")
    return "\n".join(lines)


def write_matrix_figure(doc: Mapping[str, Any], path: Path) -> Path:
    """Stacked outcome bars per preset (the campaign report's outcome colours)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.report.mc_report import OUTCOME_COLORS, OTHER_COLOR

    names = [m["preset"] for m in doc["matrix"]]
    outcomes: list[str] = []
    for m in doc["matrix"]:
        outcomes += [o for o in m["outcomes"] if o not in outcomes]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.8 * len(names) + 2.0), 4.0), layout="constrained")
    bottom = np.zeros(len(names))
    for o in outcomes:
        counts = np.array([m["outcomes"].get(o, 0) for m in doc["matrix"]], float)
        ax.bar(names, counts, bottom=bottom, label=o, color=OUTCOME_COLORS.get(o, OTHER_COLOR))
        bottom += counts
    ax.set_ylabel("cases")
    ax.set_title(f"fault matrix: {doc['runs']} cases per preset, campaign seed {doc['campaign_seed']}", y=1.0)
    ax.tick_params(axis="x", rotation=45)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    path.parent.mkdir(parents=True, exist_ok=True)
    from bench.report.io import atomic_write_bytes
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
