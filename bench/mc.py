"""Monte Carlo campaigns: ``landbench mc``.

A campaign is (base scenario, campaign seed, number of cases). Case ``i``
gets seed ``case_seeds(campaign_seed, n)[i]`` and its dispersions are drawn
from that seed's own stream, so a case depends only on (base, campaign seed,
i): never on the number of workers, the order of execution or a resume.

Execution (local backend), after NASA Trick's Monte Carlo master:
    * one spawned process per case (MuJoCo and GL objects are built inside
      it from the scenario; nothing is pickled but the scenario data), at
      most ``workers`` at a time;
    * a case that exceeds ``case_timeout_s`` is killed and recorded as failed;
      a case that raises is recorded with its error; a worker that dies
      without a result is retried once;
    * each finished case writes ``cases/NNNNN.json`` atomically; the parent
      rebuilds ``cases.parquet`` from them. ``--resume`` skips cases whose
      JSON exists, so a killed campaign loses and duplicates nothing.

Layout of ``DIR``: ``campaign.json`` (seed, runs, retention),
``scenario.toml`` (the base), ``cases/NNNNN.json`` (one row per case),
``cases/NNNNN/`` (telemetry, plots, video: kept per ``retention``),
``cases.parquet``, ``report.png``.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import shutil
import time
from pathlib import Path
from typing import Any


from bench.dispersions import apply_dispersions, case_seeds
from bench.io import atomic_write_bytes, atomic_write_text, json_safe
from bench.scenario import Scenario, load_scenario, scenario_from_dict, scenario_to_toml

CAMPAIGN = "campaign.json"
BASE_SCENARIO = "scenario.toml"
CASES = "cases"
CASES_PARQUET = "cases.parquet"
REPORT = "report.png"
RETENTIONS = ("summary", "failed", "all")
POLL_S = 0.05  # how often the master checks its workers
MAX_ATTEMPTS = 2  # a dead worker's case is retried once


def case_scenario(base: Scenario, campaign_seed: int, n_cases: int, index: int) -> tuple[Scenario, dict[str, Any]]:
    """The dispersed scenario of case ``index`` and the values drawn for it."""
    seed = case_seeds(campaign_seed, n_cases)[index]
    return apply_dispersions(base.model_copy(update={"seed": seed}))


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}_{k}" if prefix else k, v, out)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _flatten(f"{prefix}_{i}", v, out)
    else:
        out[prefix] = value


# Summary entries that describe the setup, not the landing (kept out of the row).
_SUMMARY_SKIP = ("criteria", "modes", "time_split_s")


def summary_row(summary: dict[str, Any]) -> dict[str, Any]:
    """A run summary flattened with ``_`` (``touchdown_miss_distance_m``, ``nav_vel_err_rms_mps``...)."""
    row: dict[str, Any] = {}
    _flatten("", {k: v for k, v in summary.items() if k not in _SUMMARY_SKIP}, row)
    return row


def _case_worker(base_data: dict, campaign_seed: int, n_cases: int, index: int, case_dir: str,
                 retention: str) -> None:
    """Child process: fly one case and write its row (and files, per retention)."""
    from bench.run_outputs import run_and_write

    case_path = Path(case_dir)
    t0 = time.perf_counter()
    row: dict[str, Any] = {"case": index}
    try:
        base = scenario_from_dict(base_data)
        scenario, drawn = case_scenario(base, campaign_seed, n_cases, index)
        row["seed"] = scenario.seed
        disp: dict[str, Any] = {}
        _flatten("", {f"disp_{k}": v for k, v in drawn.items()}, disp)
        row.update(disp)
        out = case_path / f"{index:05d}"
        summary, _ = run_and_write(scenario, out, video=retention == "all", progress=False)
        row.update(summary_row(summary))
        if retention == "summary" or (retention == "failed" and summary["landed"]):
            shutil.rmtree(out, ignore_errors=True)
    except Exception as exc:  # a case that raises is a failed case, not a failed campaign
        row.update({"outcome": "error", "landed": False, "error": f"{type(exc).__name__}: {exc}"})
    row["case_wall_time_s"] = time.perf_counter() - t0
    atomic_write_text(case_path / f"{index:05d}.json", json.dumps(json_safe(row)) + "\n")


def _failed_row(index: int, seed: int, error: str, wall_s: float) -> dict[str, Any]:
    return {"case": index, "seed": seed, "outcome": "error", "landed": False, "error": error,
            "case_wall_time_s": wall_s}


def run_campaign(base: Scenario, runs: int, out: Path, campaign_seed: int, workers: int = 1,
                 resume: bool = False, dry_run: bool = False, retention: str = "summary",
                 case_timeout_s: float | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Run (or resume, or dry-run) a campaign; returns the rows in case order."""
    if runs < 1:
        raise ValueError(f"--runs {runs}: must be >= 1")
    if workers < 1:
        raise ValueError(f"--workers {workers}: must be >= 1")
    if retention not in RETENTIONS:
        raise ValueError(f"--retention {retention!r}: allowed: {', '.join(RETENTIONS)}")
    cases_dir = out / CASES
    meta = {"campaign_seed": campaign_seed, "runs": runs, "retention": retention}
    meta_path = out / CAMPAIGN
    if resume:
        if not meta_path.exists():
            raise ValueError(f"--resume {out}: no {CAMPAIGN} there; start the campaign without --resume")
        old = json.loads(meta_path.read_text())
        if (old["campaign_seed"], old["runs"]) != (campaign_seed, runs):
            raise ValueError(f"--resume {out}: that campaign has seed {old['campaign_seed']} and "
                             f"{old['runs']} runs; allowed: the same --seed and --runs")
        base = load_scenario(out / BASE_SCENARIO)
    elif meta_path.exists():
        raise ValueError(f"--out {out} already holds a campaign; use --resume, or another folder")
    else:
        cases_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / BASE_SCENARIO, scenario_to_toml(base))
        atomic_write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    if dry_run:
        for i in range(runs):
            sc, _ = case_scenario(base, campaign_seed, runs, i)
            atomic_write_text(cases_dir / f"{i:05d}" / BASE_SCENARIO, scenario_to_toml(sc))
        return []

    seeds = case_seeds(campaign_seed, runs)
    todo = [i for i in range(runs) if not (cases_dir / f"{i:05d}.json").exists()]
    base_data = base.model_dump(mode="json")
    ctx = mp.get_context("spawn")  # a fresh interpreter per case: no inherited GL state
    running: dict[int, tuple[Any, float, int]] = {}
    attempts: dict[int, int] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=runs, initial=runs - len(todo), unit="case", desc="campaign")
    queue = list(todo)
    while queue or running:
        while queue and len(running) < workers:
            i = queue.pop(0)
            attempts[i] = attempts.get(i, 0) + 1
            p = ctx.Process(target=_case_worker, args=(base_data, campaign_seed, runs, i, str(cases_dir), retention))
            p.start()
            running[i] = (p, time.perf_counter(), attempts[i])
        time.sleep(POLL_S)
        for i, (p, t_start, attempt) in list(running.items()):
            elapsed = time.perf_counter() - t_start
            if p.is_alive():
                if case_timeout_s is not None and elapsed > case_timeout_s:
                    p.kill()
                    p.join()
                    row = _failed_row(i, seeds[i], f"timeout: exceeded the per-case limit of {case_timeout_s} s", elapsed)
                    atomic_write_text(cases_dir / f"{i:05d}.json", json.dumps(row) + "\n")
                    del running[i]
                    if bar is not None:
                        bar.update(1)
                continue
            p.join()
            del running[i]
            if (cases_dir / f"{i:05d}.json").exists():
                if bar is not None:
                    bar.update(1)
            elif attempt < MAX_ATTEMPTS:
                queue.insert(0, i)  # the worker died without a result: retry once
            else:
                row = _failed_row(i, seeds[i], f"worker died (exit code {p.exitcode}) twice", elapsed)
                atomic_write_text(cases_dir / f"{i:05d}.json", json.dumps(row) + "\n")
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    rows = read_rows(out, runs)
    write_cases_parquet(rows, out / CASES_PARQUET)
    return rows


def read_rows(out: Path, runs: int) -> list[dict[str, Any]]:
    """The rows of the finished cases, in case order."""
    rows = []
    for i in range(runs):
        f = out / CASES / f"{i:05d}.json"
        if f.exists():
            rows.append(json.loads(f.read_text()))
    return rows


def write_cases_parquet(rows: list[dict[str, Any]], path: Path) -> Path:
    """One row per case; columns are the union of the rows' keys (missing -> null)."""
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    table = pa.Table.from_pylist([{k: r.get(k) for k in keys} for r in rows])
    buf = io.BytesIO()
    pq.write_table(table, buf)
    return atomic_write_bytes(path, buf.getvalue())
