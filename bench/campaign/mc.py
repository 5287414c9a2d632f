"""Monte Carlo campaigns: ``landbench mc``.

A campaign is (base scenario, campaign seed, number of cases). Case ``i``
gets seed ``case_seeds(campaign_seed, n)[i]`` and its dispersions are drawn
from that seed's own stream, so a case depends only on (base, campaign seed,
i): never on the number of workers, the order of execution or a resume.

Execution, after NASA Trick's Monte Carlo master, on either backend:
    * ``local`` (default): at most ``workers`` worker processes, each
      flying cases one after another (``cases_per_worker`` at most, then a
      fresh process takes its place). Workers are forked from a fork server
      that has imported what a case needs and nothing more (no GL context, no
      MuJoCo model: see :func:`bench.campaign.workers.worker_context`), so a new worker costs a fork,
      not a second of imports; ``ray``: one Ray task per case on a Ray
      cluster (given by ``--address`` or ``RAY_ADDRESS``, else a local Ray
      instance started here), a Ray worker process running at most
      ``cases_per_worker`` of them (``max_calls``). A worker receives only
      plain data (the scenario as a dict, the campaign seed, the case index)
      and builds each case's MuJoCo model and renderer anew, freeing them
      after the case: no MuJoCo or GL object is ever pickled or shared
      between cases, and nothing a case computes depends on the cases its
      worker flew before (tested: rows equal a fresh process's, in any order);
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
import importlib
import json
import multiprocessing.connection as mp_connection
import numbers
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.campaign.workers import thread_env, threads_per_worker, worker_context
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
# A worker process flies at most this many cases, then a fresh one takes its place (as
# multiprocessing's maxtasksperchild): it pays the imports once for many cases, and
# whatever memory the allocator keeps between cases cannot grow without bound. 1 gives
# every case a fresh process.
CASES_PER_WORKER = 20
# Row entries that measure the machine, not the landing: they differ between
# two runs of the same case, so comparisons (workers, backends, replay) skip them.
RUN_DEPENDENT_KEYS = ("wall_time_s", "setup_time_s", "realtime_factor", "case_wall_time_s", "case_peak_rss_mb",
                      "case_worker_pid")
# ... and every entry of a flattened ``compute_s`` block (the hazard scans' wall-clock timings).
RUN_DEPENDENT_INFIX = "_compute_s_"


def is_run_dependent(key: str) -> bool:
    """True for a row entry that measures the machine, not the landing (:data:`RUN_DEPENDENT_KEYS`, timings)."""
    return key in RUN_DEPENDENT_KEYS or RUN_DEPENDENT_INFIX in key


def case_scenario(base: Scenario, campaign_seed: int, n_cases: int, index: int) -> tuple[Scenario, dict[str, Any]]:
    """The dispersed scenario of case ``index`` and the values drawn for it."""
    return seeded_case(base, case_seeds(campaign_seed, n_cases)[index])


def seeded_case(base: Scenario, seed: int) -> tuple[Scenario, dict[str, Any]]:
    """The dispersed scenario of the case of seed ``seed`` and the values drawn for it."""
    return apply_dispersions(base.model_copy(update={"seed": seed}))


def read_meta(path: Path, keys: tuple[str, ...], flag: str) -> dict[str, Any]:
    """A results folder's metadata file (``campaign.json``, ``faults.json``, ``sweep.json``), refused in one
    line naming ``flag`` and the folder when it is missing, not JSON, or lacks one of ``keys``."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{flag} {path.parent}: its {path.name} cannot be read ({exc}); give a folder that "
                         "landbench wrote") from None
    missing = [k for k in keys if not isinstance(meta, dict) or k not in meta]
    if missing:
        raise ValueError(f"{flag} {path.parent}: its {path.name} lacks {', '.join(missing)}; give a folder that "
                         "landbench wrote")
    for key, least in (("runs", 1), ("campaign_seed", 0)):  # whole numbers: a case index and a SeedSequence seed
        value = meta.get(key, least)
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{flag} {path.parent}: its {path.name} says {key} = {value!r}; allowed: an integer >= "
                             f"{least} (give a folder that landbench wrote)")
    return meta


def check_seed(campaign_seed: object) -> None:
    """Refuse a campaign seed that is not a non-negative integer (``--seed``)."""
    if isinstance(campaign_seed, bool) or not isinstance(campaign_seed, numbers.Integral) or campaign_seed < 0:
        raise ValueError(f"--seed {campaign_seed!r}: a campaign seed is a non-negative integer")


def check_cases(base: Scenario, runs: int, campaign_seed: int, every: bool = True) -> None:
    """Draw the cases' dispersions and validate their scenarios (and their cameras against the tracker,
    :func:`bench.sim.flight_build.check_tracker_fits_camera`), before anything is written.

    ``every`` (a dry run, which writes each case's dispersed scenario): a draw outside a field's
    limits is refused here, in one line naming the case and the field, instead of after the
    campaign's folder exists; about 3 ms per case with dispersions. Otherwise (a campaign that
    flies, which records a refused case as an error row and goes on): the campaign is refused only
    when no case can be drawn, the table itself being wrong; the draws stop at the first valid case.
    """
    from bench.sim.flight_build import check_tracker_fits_camera

    check_seed(campaign_seed)
    if not base.dispersions:
        check_tracker_fits_camera(base)  # every case is the base scenario with its own seed
        return
    first = None
    for i, seed in enumerate(case_seeds(campaign_seed, runs)):
        try:
            check_tracker_fits_camera(seeded_case(base, seed)[0])
        except ValueError as exc:
            if every:
                raise ValueError(f"case {i} of --seed {campaign_seed}: its dispersed draw is refused: {exc}; "
                                 "keep that field's [dispersions] entry to values the scenario accepts") from None
            first = first or f"case {i}: {exc}"
        else:
            if not every:
                return
    if first is not None:
        raise ValueError(f"every one of the {runs} cases' dispersed draws is refused ({first}); keep that field's "
                         "[dispersions] entry to values the scenario accepts (landbench mc --dry-run checks a table)")


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


def _limit_threads(threads: int) -> None:
    """In a worker, before any rendering: llvmpipe reads its variable when GL starts."""
    import cv2

    os.environ.setdefault("LP_NUM_THREADS", str(threads))
    cv2.setNumThreads(threads)


def _reset_peak_rss() -> bool:
    """Start this process's peak-memory count afresh (Linux: the high-water mark drops to the current RSS).

    A worker flies many cases, so each case's ``case_peak_rss_mb`` is the
    worker's peak *during that case* (what it held from earlier cases
    included): the same quantity a fresh process per case measured.
    Returns False where the kernel offers no reset (then the figure is the
    worker's peak so far).
    """
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """This process's peak resident memory [MB] since :func:`_reset_peak_rss` (else since it started)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


# glibc's malloc raises its mmap threshold each time a large block is freed (up to
# 32 MB), after which medium arrays come from the heap and are not given back: a
# worker's resident memory then creeps up case by case. A fixed threshold keeps
# every block over 1 MB in its own mapping, returned to the system when freed.
_M_MMAP_THRESHOLD = -3  # mallopt's parameter number (malloc.h)
MMAP_THRESHOLD_BYTES = 1 << 20
_malloc_tuned = False


def _release_memory() -> None:
    """Give freed heap memory back to the system (glibc; elsewhere nothing is done)."""
    global _malloc_tuned
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        if not _malloc_tuned:
            libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
            _malloc_tuned = True
        libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _between_cases() -> None:
    """What a worker does before each case: nothing carried from the cases before, memory handed back.

    A case's result depends only on its scenario: every random stream is
    spawned from its seed, and the World, its renderer and GL context are
    built for the case and freed after it. The only state a process keeps
    between runs is the terrain cache, whose terrains are immutable and
    bit-identical to a fresh generation; a worker drops it here (the next
    case loads its terrain from the disk cache, about 0.1 s), so that it holds
    no tile it may not need. Garbage from the last case is collected and the
    freed heap returned to the system now, not during the next case.
    """
    import gc

    from bench.sim.world_builder import clear_terrain_cache

    clear_terrain_cache()
    gc.collect()
    _release_memory()


def _case_row(base_data: dict, campaign_seed: int, n_cases: int, index: int, case_dir: Path,
              retention: str, threads: int) -> dict[str, Any]:
    """Fly one case in this process and return its row.

    Telemetry, plots and video go to ``case_dir/NNNNN/`` and are kept per
    ``retention``. Called inside a worker process (either backend), which may
    have flown other cases before; ``case_peak_rss_mb`` is the worker's peak
    memory during this case.
    """
    _limit_threads(threads)
    _between_cases()
    _reset_peak_rss()
    t0 = time.perf_counter()
    row: dict[str, Any] = {"case": index}
    try:
        row["seed"] = seed = case_seeds(campaign_seed, n_cases)[index]  # kept by a case whose draw fails validation
        scenario, drawn = seeded_case(scenario_from_dict(base_data), seed)
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
    row["case_worker_pid"] = os.getpid()  # which worker flew it (a worker flies several cases in turn)
    return json_safe(row)


def _write_row(cases_dir: Path, row: dict[str, Any]) -> None:
    atomic_write_text(cases_dir / f"{row['case']:05d}.json", json.dumps(json_safe(row)) + "\n")


def _case_worker(conn: Any, base_data: dict, campaign_seed: int, n_cases: int, case_dir: str,
                 retention: str, threads: int, max_cases: int, lp_threads: str | None = None) -> None:
    """Local backend, a worker process: fly the cases the master sends, one at a time.

    Receives case indices on ``conn`` (None: stop), and after each case writes
    its row itself (not the master, so a case that finished is kept even if
    the master is killed the next instant), then sends the index back. Stops
    after ``max_cases`` cases, or when the master is gone. ``lp_threads``: the
    llvmpipe thread count this campaign's worker uses (a forked worker inherits the
    fork server's environment, not the master's of the moment).
    """
    if lp_threads is not None:
        os.environ["LP_NUM_THREADS"] = lp_threads  # read when the case's GL context starts
    _limit_threads(threads)
    import bench.sim.run  # noqa: F401 - the imports every case needs (already there in a forked worker)

    cases_dir = Path(case_dir)
    for _ in range(max_cases):
        try:
            index = conn.recv()
        except (EOFError, OSError):  # the master is gone
            return
        if index is None:
            return
        _write_row(cases_dir, _case_row(base_data, campaign_seed, n_cases, index, cases_dir, retention, threads))
        try:
            conn.send(index)
        except (BrokenPipeError, OSError):
            return


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


def check_campaign_args(runs: int, campaign_seed: int, workers: int | None = 1, retention: str = "summary",
                        case_timeout_s: float | None = None, backend: str = "local", address: str | None = None,
                        cases_per_worker: int | None = None) -> None:
    """Refuse a campaign's bad arguments (as :func:`run_campaign` takes them) in one line, before anything is
    written (``landbench faults`` and ``sweep`` call it before their own files too)."""
    if runs < 1:
        raise ValueError(f"--runs {runs}: must be >= 1")
    check_seed(campaign_seed)
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
    if cases_per_worker is not None and cases_per_worker < 1:
        raise ValueError(f"--cases-per-worker {cases_per_worker}: must be >= 1 (1: a fresh process per case)")


def run_campaign(base: Scenario, runs: int, out: Path, campaign_seed: int, workers: int | None = 1,
                 resume: bool = False, dry_run: bool = False, retention: str = "summary",
                 case_timeout_s: float | None = None, progress: bool = True, backend: str = "local",
                 address: str | None = None, cases_per_worker: int | None = None) -> list[dict[str, Any]]:
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
        cases_per_worker: Cases a worker process flies before a fresh one
            takes its place; None: :data:`CASES_PER_WORKER`; 1: a fresh
            process per case. The rows do not depend on it.
    """
    check_campaign_args(runs, campaign_seed, workers, retention, case_timeout_s, backend, address, cases_per_worker)
    if cases_per_worker is None:
        cases_per_worker = CASES_PER_WORKER
    cases_dir = out / CASES
    meta = {"campaign_seed": campaign_seed, "runs": runs, "retention": retention}
    meta_path = out / CAMPAIGN
    if resume:
        if not meta_path.exists():
            raise ValueError(f"--resume {out}: no {CAMPAIGN} there; start the campaign without --resume")
        old = read_meta(meta_path, ("campaign_seed", "runs"), "--resume")
        if (old["campaign_seed"], old["runs"]) != (campaign_seed, runs):
            raise ValueError(f"--resume {out}: that campaign has seed {old['campaign_seed']} and "
                             f"{old['runs']} runs; allowed: the same --seed and --runs")
        base = load_scenario(out / BASE_SCENARIO)
    elif meta_path.exists():
        raise ValueError(f"--out {out} already holds a campaign; use --resume, or another folder")
    else:
        # A dry run's job is writing every case's scenario: a draw that cannot be one is refused first. A
        # campaign that flies is refused only when no case can be drawn.
        check_cases(base, runs, campaign_seed, every=dry_run)
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
                _run_local(job, todo, workers or 1, done, cases_per_worker)
            else:
                _run_ray(job, todo, workers, address, done, cases_per_worker)
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


@dataclass
class _Worker:
    """The master's view of one local worker process."""

    proc: Any
    conn: Any
    served: int = 0  # cases it has finished
    case: int | None = None  # the case it is flying now
    t_start: float = 0.0  # when that case was handed to it
    attempt: int = 0


# What a campaign's end needs that its start does not: the Parquet writer and the report's
# figure. Imported in a background thread once a worker has no case left (see _run_local).
TAIL_MODULES = ("pyarrow", "pyarrow.parquet", "matplotlib.figure", "matplotlib.backends.backend_agg")


def _import_tail_modules() -> None:
    for name in TAIL_MODULES:
        importlib.import_module(name)


def _warm_tail() -> threading.Thread:
    """Import :data:`TAIL_MODULES` in a daemon thread: a core is idle while the last cases fly
    (a worker has run out of cases), and these imports (about 0.6 s here) were otherwise paid
    after the last case, on the campaign's critical path."""
    t = threading.Thread(target=_import_tail_modules, name="campaign-tail-imports", daemon=True)
    t.start()
    return t


def _run_local(job: _Job, todo: list[int], workers: int, done: Callable[[int], Any],
               cases_per_worker: int = CASES_PER_WORKER) -> None:
    """Local backend: at most ``workers`` worker processes, each flying up to ``cases_per_worker`` cases in turn.

    A case is handed to an idle worker (a new one is spawned when none is
    idle and fewer than ``workers`` exist); its timeout runs from that
    moment. A worker that overruns is killed and the case recorded as timed
    out; a worker that dies without the case's row is replaced and the case
    retried once on a fresh process, then recorded as failed.
    """
    ctx = worker_context()
    threads = threads_per_worker(workers)
    lp_threads = os.environ.get("LP_NUM_THREADS", str(threads))  # the user's own wins
    pool: list[_Worker] = []
    attempts: dict[int, int] = {}
    queue = list(todo)
    tail: threading.Thread | None = None

    def spawn() -> _Worker:
        conn, child = ctx.Pipe()
        p = ctx.Process(target=_case_worker, args=(child, job.base_data, job.campaign_seed, job.runs,
                                                   str(job.cases_dir), job.retention, threads, cases_per_worker,
                                                   lp_threads))
        with thread_env(threads):
            p.start()
        child.close()
        return _Worker(p, conn)

    def assign(w: _Worker) -> None:
        i = queue.pop(0)
        attempts[i] = attempts.get(i, 0) + 1
        w.case, w.t_start, w.attempt = i, time.perf_counter(), attempts[i]
        w.conn.send(i)

    def retire(w: _Worker, kill: bool = False) -> None:
        pool.remove(w)
        if kill and w.proc.is_alive():
            w.proc.kill()
        w.proc.join(timeout=None if kill else 10)
        if w.proc.is_alive():  # it did not stop when asked
            w.proc.kill()
            w.proc.join()
        w.conn.close()

    try:
        while queue or any(w.case is not None for w in pool):
            for w in pool:
                if w.case is None and queue:
                    assign(w)
            while queue and len(pool) < workers:
                w = spawn()
                pool.append(w)
                assign(w)
            busy = [w for w in pool if w.case is not None]
            mp_connection.wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout=POLL_S)
            for w in busy:
                i, elapsed = w.case, time.perf_counter() - w.t_start
                finished = False
                try:
                    finished = w.conn.poll() and w.conn.recv() == i
                except (EOFError, OSError):
                    finished = False
                if finished:
                    w.case = None
                    w.served += 1
                    done(1)
                    if not queue and tail is None:  # the first worker out of work: a core to spare
                        tail = _warm_tail()
                    if w.served >= cases_per_worker:  # it stops by itself: a fresh one takes its place
                        retire(w)
                    continue
                if w.proc.is_alive():
                    if job.case_timeout_s is not None and elapsed > job.case_timeout_s:
                        retire(w, kill=True)
                        _write_row(job.cases_dir, job.timeout_row(i, elapsed))
                        done(1)
                    continue
                retire(w)  # it died without handing the case back
                if (job.cases_dir / f"{i:05d}.json").exists():  # after writing the row
                    done(1)
                elif w.attempt < MAX_ATTEMPTS:
                    queue.insert(0, i)  # retry once, on a fresh process
                else:
                    _write_row(job.cases_dir, _failed_row(i, job.seeds[i], f"worker died (exit code "
                                                          f"{w.proc.exitcode}) twice", elapsed))
                    done(1)
    finally:
        for w in list(pool):  # idle workers stop when told; one still flying (an error in the master) is killed
            if w.case is None:
                with contextlib.suppress(OSError):
                    w.conn.send(None)
            retire(w, kill=w.case is not None)


def _run_ray(job: _Job, todo: list[int], workers: int | None, address: str | None,
             done: Callable[[int], Any], cases_per_worker: int = CASES_PER_WORKER) -> None:
    """Ray backend: one Ray task per case; a Ray worker process runs at most ``cases_per_worker`` of them.

    ``max_calls=cases_per_worker`` recycles a worker as the local backend
    does (each case builds and frees its own model, renderer and GL context;
    see :func:`_between_cases`), and ``max_retries=1`` lets Ray rerun a case
    once if its worker dies. The driver writes the rows, so the campaign
    folder lives on the driver only.
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
        task = ray.remote(num_cpus=1, max_calls=cases_per_worker, max_retries=MAX_ATTEMPTS - 1)(_ray_case)
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
    return {k: v for k, v in row.items() if not is_run_dependent(k)}


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
