"""Monte Carlo campaigns: ``landbench mc``.

A campaign is (base scenario, campaign seed, number of cases). Case ``i``
gets seed ``case_seeds(campaign_seed, n)[i]`` and its dispersions are drawn
from that seed's own stream, so a case depends only on (base, campaign seed,
i): never on the number of workers, the order of execution or a resume.

Execution, after NASA Trick's Monte Carlo master, on either backend:
    * ``local`` (default): one spawned process per case, at most ``workers``
      at a time; ``ray``: one Ray task per case on a Ray cluster (given by
      ``--address`` or ``RAY_ADDRESS``, else a local Ray instance started
      here), each in a fresh worker process (``max_calls=1``). A worker
      receives only plain data (the scenario as a dict, the campaign seed,
      the case index) and builds its own MuJoCo model and renderer: no
      MuJoCo or GL object is ever pickled;
    * a case that exceeds ``case_timeout_s`` is killed and recorded as failed;
      a case that raises is recorded with its error; a worker that dies
      without a result is retried once;
    * each finished case's row is written to ``cases/NNNNN.json`` atomically
      (by the local worker itself, or by the Ray driver, which also receives
      the case's kept files as bytes: cluster nodes need not share a file
      system); ``cases.parquet`` is rebuilt from them. ``--resume`` skips
      cases whose JSON exists, so a killed campaign loses and duplicates
      nothing, whichever backend ran or resumes it.

Layout of ``DIR``: ``campaign.json`` (seed, runs, retention),
``scenario.toml`` (the base), ``cases/NNNNN.json`` (one row per case),
``cases/NNNNN/`` (telemetry, plots, video: kept per ``retention``),
``cases.parquet``, ``report.png``.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.evaluation.consistency import CONSISTENCY_FILE, campaign_consistency
from bench.report.io import atomic_write_bytes, atomic_write_text, json_safe
from bench.scenario import Scenario, apply_dispersions, case_seeds, load_scenario, scenario_from_dict, scenario_to_toml

CAMPAIGN = "campaign.json"
BASE_SCENARIO = "scenario.toml"
CASES = "cases"
CASES_PARQUET = "cases.parquet"
REPORT = "report.png"
RETENTIONS = ("summary", "failed", "all")
BACKENDS = ("local", "ray")
POLL_S = 0.05  # how often the master checks its workers
MAX_ATTEMPTS = 2  # a dead worker's case is retried once
# Row entries that measure the machine, not the landing: they differ between
# two runs of the same case, so comparisons (workers, backends, replay) skip them.
RUN_DEPENDENT_KEYS = ("wall_time_s", "setup_time_s", "realtime_factor", "case_wall_time_s", "case_peak_rss_mb")


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
_SUMMARY_SKIP = ("criteria", "modes", "time_split_s", "fdir_events")


def summary_row(summary: dict[str, Any]) -> dict[str, Any]:
    """A run summary flattened with ``_`` (``touchdown_miss_distance_m``, ``nav_vel_err_rms_mps``...).

    The consistency block's per-step NEES (``consistency.nees_profile``, 250 values
    per error block) is not flattened into columns: it stays one entry,
    ``nees_profile`` (block -> list), which no metric reads as a number.
    """
    row: dict[str, Any] = {}
    kept = {k: v for k, v in summary.items() if k not in _SUMMARY_SKIP}
    consistency = kept.get("consistency")
    profile = None
    if isinstance(consistency, dict) and "nees_profile" in consistency:
        kept["consistency"] = {k: v for k, v in consistency.items() if k != "nees_profile"}
        profile = consistency["nees_profile"]
    _flatten("", kept, row)
    if profile is not None:
        row["nees_profile"] = profile
    return row


# Threads a case may use are set per worker: the CPUs divided among the
# workers. Without this, llvmpipe, OpenCV and BLAS each start one thread per
# core in every worker, and K workers on K cores fight over them.
THREAD_ENV_VARS = ("LP_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def threads_per_worker(workers: int) -> int:
    """The CPUs this process may use, shared out among ``workers`` (at least 1 each)."""
    return max(1, len(os.sched_getaffinity(0)) // workers)


@contextlib.contextmanager
def _thread_env(threads: int) -> Iterator[None]:
    """Set the thread-count variables a spawned child reads at start (the user's own win)."""
    added = [k for k in THREAD_ENV_VARS if k not in os.environ]
    os.environ.update({k: str(threads) for k in added})
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _limit_threads(threads: int) -> None:
    """In a worker, before any rendering: llvmpipe reads its variable when GL starts."""
    import cv2

    os.environ.setdefault("LP_NUM_THREADS", str(threads))
    cv2.setNumThreads(threads)


def _peak_rss_mb() -> float:
    """This process's peak resident memory [MB] (Linux reports ru_maxrss in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _case_row(base_data: dict, campaign_seed: int, n_cases: int, index: int, case_dir: Path,
              retention: str, threads: int) -> dict[str, Any]:
    """Fly one case in this process and return its row.

    Telemetry, plots and video go to ``case_dir/NNNNN/`` and are kept per
    ``retention``. Called inside a fresh worker process (either backend), so
    ``case_peak_rss_mb`` is the worker's peak memory for this one case.
    """
    _limit_threads(threads)
    t0 = time.perf_counter()
    row: dict[str, Any] = {"case": index}
    try:
        base = scenario_from_dict(base_data)
        scenario, drawn = case_scenario(base, campaign_seed, n_cases, index)
        row["seed"] = scenario.seed
        disp: dict[str, Any] = {}
        _flatten("", {f"disp_{k}": v for k, v in drawn.items()}, disp)
        row.update(disp)
        out = case_dir / f"{index:05d}"
        if retention == "all":
            from bench.report.run_outputs import run_and_write

            summary, _ = run_and_write(scenario, out, video=True, progress=False)
        else:
            # Files only for a case that failed, and only if asked: plots and
            # Parquet would cost every case time and ~60 MB of imports.
            from bench.sim.run import run

            result = run(scenario)
            summary = json_safe(result.summary)
            if retention == "failed" and not summary["landed"]:
                from bench.report.run_outputs import write_run_outputs

                write_run_outputs(scenario, result, out)
            del result
        row.update(summary_row(summary))
    except Exception as exc:  # noqa: BLE001 - a case that raises is a failed case, not a failed campaign
        row.update({"outcome": "error", "landed": False, "error": f"{type(exc).__name__}: {exc}"})
    row["case_wall_time_s"] = time.perf_counter() - t0
    row["case_peak_rss_mb"] = _peak_rss_mb()
    return json_safe(row)


def _write_row(cases_dir: Path, row: dict[str, Any]) -> None:
    atomic_write_text(cases_dir / f"{row['case']:05d}.json", json.dumps(json_safe(row)) + "\n")


def _case_worker(base_data: dict, campaign_seed: int, n_cases: int, index: int, case_dir: str,
                 retention: str, threads: int) -> None:
    """Local backend, child process: fly one case and write its row itself.

    The child writes the row (not the master), so a case that finished is
    kept even if the master is killed the next instant.
    """
    cases_dir = Path(case_dir)
    _write_row(cases_dir, _case_row(base_data, campaign_seed, n_cases, index, cases_dir, retention, threads))


def _ray_case(base_data: dict, campaign_seed: int, n_cases: int, index: int,
              retention: str) -> tuple[dict[str, Any], dict[str, bytes]]:
    """Ray backend, task body: fly one case on whichever node Ray chose.

    Cluster nodes need not share a file system with the driver, so the case
    runs in a scratch folder and the files it keeps come back as bytes.

    Returns:
        (row, files): files maps paths relative to ``cases/`` to contents.
    """
    import tempfile

    with tempfile.TemporaryDirectory(prefix="landbench-case-") as tmp:
        scratch = Path(tmp)
        row = _case_row(base_data, campaign_seed, n_cases, index, scratch, retention, threads=1)  # 1 CPU per task
        kept = scratch / f"{index:05d}"
        files = {p.relative_to(scratch).as_posix(): p.read_bytes()
                 for p in sorted(kept.rglob("*")) if p.is_file()} if kept.exists() else {}
    return row, files


def _failed_row(index: int, seed: int, error: str, wall_s: float) -> dict[str, Any]:
    return {"case": index, "seed": seed, "outcome": "error", "landed": False, "error": error,
            "case_wall_time_s": wall_s}


def run_campaign(base: Scenario, runs: int, out: Path, campaign_seed: int, workers: int | None = 1,
                 resume: bool = False, dry_run: bool = False, retention: str = "summary",
                 case_timeout_s: float | None = None, progress: bool = True, backend: str = "local",
                 address: str | None = None) -> list[dict[str, Any]]:
    """Run (or resume, or dry-run) a campaign; returns the rows in case order.

    Args:
        base: The base scenario; its ``dispersions`` are drawn per case.
        runs: Number of cases.
        out: Campaign folder.
        campaign_seed: Seed of the campaign; case ``i`` gets the ``i``-th spawned seed.
        workers: Cases run at once. ``None``: 1 for ``local``, every CPU of
            the cluster for ``ray``.
        resume: Finish the campaign in ``out``; cases with a row are not rerun.
        dry_run: Only write the dispersed scenarios.
        retention: Whose telemetry and video are kept: summary, failed or all.
        case_timeout_s: Per-case wall-clock limit [s]; None: no limit.
        progress: Show a progress bar.
        backend: ``local`` (worker processes) or ``ray`` (a Ray cluster).
        address: Ray cluster address; None: ``RAY_ADDRESS`` if set, else a
            local Ray instance started (and stopped) here.
    """
    if runs < 1:
        raise ValueError(f"--runs {runs}: must be >= 1")
    if workers is not None and workers < 1:
        raise ValueError(f"--workers {workers}: must be >= 1")
    if retention not in RETENTIONS:
        raise ValueError(f"--retention {retention!r}: allowed: {', '.join(RETENTIONS)}")
    if backend not in BACKENDS:
        raise ValueError(f"--backend {backend!r}: allowed: {', '.join(BACKENDS)}")
    if address is not None and backend != "ray":
        raise ValueError(f"--address {address!r} is for the ray backend; add --backend ray")
    if case_timeout_s is not None and not case_timeout_s > 0:
        raise ValueError(f"--case-timeout {case_timeout_s}: must be > 0 [s]")
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

    todo = [i for i in range(runs) if not (cases_dir / f"{i:05d}.json").exists()]
    job = _Job(base.model_dump(mode="json"), campaign_seed, runs, cases_dir, retention, case_timeout_s,
               case_seeds(campaign_seed, runs))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=runs, initial=runs - len(todo), unit="case", desc=f"campaign ({backend})")
    try:
        if todo:
            done = bar.update if bar is not None else (lambda n: None)
            if backend == "local":
                _run_local(job, todo, workers or 1, done)
            else:
                _run_ray(job, todo, workers, address, done)
    finally:
        if bar is not None:
            bar.close()
    rows = read_rows(out, runs)
    write_cases_parquet(rows, out / CASES_PARQUET)
    atomic_write_text(out / CONSISTENCY_FILE, json.dumps(json_safe(campaign_consistency(rows)), indent=1) + "\n")
    return rows


@dataclass(frozen=True)
class _Job:
    """What every case of a campaign shares (plain data: this is all a worker receives)."""

    base_data: dict
    campaign_seed: int
    runs: int
    cases_dir: Path
    retention: str
    case_timeout_s: float | None
    seeds: list[int]

    def timeout_row(self, i: int, elapsed_s: float) -> dict[str, Any]:
        return _failed_row(i, self.seeds[i], f"timeout: exceeded the per-case limit of {self.case_timeout_s} s",
                           elapsed_s)


def _run_local(job: _Job, todo: list[int], workers: int, done: Callable[[int], Any]) -> None:
    """Local backend: one spawned process per case, at most ``workers`` at a time."""
    ctx = mp.get_context("spawn")  # a fresh interpreter per case: no inherited GL state
    threads = threads_per_worker(workers)
    running: dict[int, tuple[Any, float, int]] = {}
    attempts: dict[int, int] = {}
    queue = list(todo)
    while queue or running:
        while queue and len(running) < workers:
            i = queue.pop(0)
            attempts[i] = attempts.get(i, 0) + 1
            p = ctx.Process(target=_case_worker, args=(job.base_data, job.campaign_seed, job.runs, i,
                                                       str(job.cases_dir), job.retention, threads))
            with _thread_env(threads):
                p.start()
            running[i] = (p, time.perf_counter(), attempts[i])
        time.sleep(POLL_S)
        for i, (p, t_start, attempt) in list(running.items()):
            elapsed = time.perf_counter() - t_start
            if p.is_alive():
                if job.case_timeout_s is not None and elapsed > job.case_timeout_s:
                    p.kill()
                    p.join()
                    _write_row(job.cases_dir, job.timeout_row(i, elapsed))
                    del running[i]
                    done(1)
                continue
            p.join()
            del running[i]
            if (job.cases_dir / f"{i:05d}.json").exists():
                done(1)
            elif attempt < MAX_ATTEMPTS:
                queue.insert(0, i)  # the worker died without a result: retry once
            else:
                _write_row(job.cases_dir, _failed_row(i, job.seeds[i], f"worker died (exit code {p.exitcode}) twice",
                                                      elapsed))
                done(1)


def _run_ray(job: _Job, todo: list[int], workers: int | None, address: str | None,
             done: Callable[[int], Any]) -> None:
    """Ray backend: one Ray task per case, each in a fresh worker process.

    ``max_calls=1`` gives every case a new process, as the local backend
    does (no GL context or memory growth carried between cases), and
    ``max_retries=1`` lets Ray rerun a case once if its worker dies. The
    driver writes the rows, so the campaign folder lives on the driver only.
    """
    try:
        import ray
    except ImportError:
        raise ValueError("--backend ray: Ray is not installed; install the extra: "
                         "pip install 'landbench[ray]'") from None
    started_here = False
    if not ray.is_initialized():
        if address or os.environ.get("RAY_ADDRESS"):
            where = address or os.environ["RAY_ADDRESS"]
            try:
                ray.init(address=address, log_to_driver=False)  # address=None: Ray reads RAY_ADDRESS
            except (ConnectionError, RuntimeError, ray.exceptions.RayError) as exc:
                raise ValueError(
                    f"--address {where}: cannot connect to a Ray cluster there ({type(exc).__name__}: {exc}). "
                    "Check the address (ray status on the head node prints it); for a cluster with token "
                    "authentication (Ray's default) set RAY_AUTH_MODE=token and the token "
                    "(RAY_AUTH_TOKEN or ~/.ray/auth_token)") from None
        else:
            ray.init(num_cpus=workers or os.cpu_count() or 1, include_dashboard=False, log_to_driver=False)
        started_here = True
    try:
        capacity = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        task = ray.remote(num_cpus=1, max_calls=1, max_retries=MAX_ATTEMPTS - 1)(_ray_case)
        queue = list(todo)
        in_flight: dict[Any, tuple[int, float]] = {}
        while queue or in_flight:
            while queue and len(in_flight) < capacity:
                i = queue.pop(0)
                ref = task.remote(job.base_data, job.campaign_seed, job.runs, i, job.retention)
                in_flight[ref] = (i, time.perf_counter())
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=POLL_S * 10)
            for ref in ready:
                i, t_start = in_flight.pop(ref)
                try:
                    row, files = ray.get(ref)
                except ray.exceptions.RayError as exc:  # the worker died twice, or the node was lost
                    row, files = _failed_row(i, job.seeds[i], f"worker died twice ({type(exc).__name__})",
                                             time.perf_counter() - t_start), {}
                for rel, data in files.items():
                    atomic_write_bytes(job.cases_dir / rel, data)
                _write_row(job.cases_dir, row)
                done(1)
            if job.case_timeout_s is not None:
                # Measured from submission: with at most `capacity` tasks in
                # flight, each starts as soon as it is submitted.
                for ref, (i, t_start) in list(in_flight.items()):
                    elapsed = time.perf_counter() - t_start
                    if elapsed > job.case_timeout_s:
                        ray.cancel(ref, force=True)  # kills the worker; a cancelled task is not retried
                        del in_flight[ref]
                        _write_row(job.cases_dir, job.timeout_row(i, elapsed))
                        done(1)
    finally:
        if started_here:
            ray.shutdown()


def landing_values(row: dict[str, Any]) -> dict[str, Any]:
    """A case row without its machine-dependent entries (wall time, memory).

    Two runs of the same case, whatever the backend, the number of workers or
    a replay, must agree on everything this returns.
    """
    return {k: v for k, v in row.items() if k not in RUN_DEPENDENT_KEYS}


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
