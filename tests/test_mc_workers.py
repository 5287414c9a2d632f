"""Reused campaign workers: a worker process flies many cases in turn, and each row is a fresh process's.

(The failure handling of the local pool, timeouts, dead workers and kill-and-resume, is in
test_mc_recovery.py; the Ray backend's in test_mc_ray.py.)
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from bench.campaign import mc
from bench.scenario import load_scenario
from tests.conftest import SMALL_SET
from tests.test_mc import QUICK, _strip

# The default descent with every default dispersion (a new terrain per case), camera, vision and filter in
# the loop, cut after 2 s of flight: each case renders its frames over its own terrain, which is what a
# worker must not carry into the next case.
RENDERING = [*SMALL_SET, "sim.t_max_ns=2000000000"]


def test_a_reused_worker_gives_the_rows_of_fresh_processes_whatever_ran_before(tmp_path):
    base = load_scenario(None, RENDERING)
    fresh = mc.run_campaign(base, 3, tmp_path / "fresh", campaign_seed=7, workers=2, cases_per_worker=1,
                            progress=False)
    assert len({r["case_worker_pid"] for r in fresh}) == 3  # one process per case
    assert all(r["vision_frames"] > 0 and r["vision_measurements"] > 0 for r in fresh), "frames were rendered"
    assert len({r["disp_terrain.seed"] for r in fresh}) == 3  # three terrains
    # One worker at a time, two cases each, in reverse order: case 1 is flown by the process that flew
    # case 2 just before (its terrain, model, renderer and streams), and a fresh process takes case 0.
    out = tmp_path / "reused"
    (out / mc.CASES).mkdir(parents=True)
    job = mc._Job(base.model_dump(mode="json"), 7, 3, out / mc.CASES, "summary", None, mc.case_seeds(7, 3))
    finished = []
    mc._run_local(job, [2, 1, 0], workers=1, done=finished.append, cases_per_worker=2)
    reused = mc.read_rows(out, 3)
    assert len(finished) == 3 and [r["case"] for r in reused] == [0, 1, 2]
    pid = {r["case"]: r["case_worker_pid"] for r in reused}
    assert pid[1] == pid[2] != pid[0]  # reused once, then replaced after its two cases
    assert _strip(reused) == _strip(fresh)
    assert all(0 < r["case_peak_rss_mb"] < 600 for r in reused)


def test_cases_per_worker_must_be_positive(tmp_path):
    import pytest

    with pytest.raises(ValueError, match="--cases-per-worker"):
        mc.run_campaign(load_scenario(None, RENDERING), 1, tmp_path / "x", campaign_seed=1, cases_per_worker=0,
                        progress=False)


def test_the_fork_server_started_first_is_the_one_the_campaign_forks_from(tmp_path):
    """``landbench mc`` starts its workers' fork server before it imports the simulation (the two then
    overlap): the master has imported nothing heavy yet, the server alone gets the workers' thread
    counts, and the campaign that follows forks its workers from that server instead of starting one."""
    code = textwrap.dedent("""
        import os, sys
        from pathlib import Path
        from bench.campaign.workers import THREAD_ENV_VARS, start_worker_server, threads_per_worker

        env_before = dict(os.environ)
        assert start_worker_server(2)
        assert dict(os.environ) == env_before, "the thread counts are the server's, not the master's"
        heavy = [m for m in sys.modules if m.split(".")[0] in ("mujoco", "scipy", "filterpy", "cv2")
                 or m.startswith(("bench.scenario", "bench.sim"))]
        assert not heavy, heavy
        from tests.conftest import fork_servers, live_processes  # (after the check: it imports the terrain)

        def servers():
            return fork_servers(live_processes(), os.getpid())

        (server,) = servers()
        env = dict(kv.split("=", 1) for kv in Path(f"/proc/{server}/environ").read_bytes().decode().split("\\0")
                   if "=" in kv)
        want = str(threads_per_worker(2))
        assert all(env.get(k) == os.environ.get(k, want) for k in THREAD_ENV_VARS), env

        from bench.campaign import mc
        from bench.scenario import load_scenario
        import threading
        sc = load_scenario(None, QUICK)
        assert "matplotlib.figure" not in sys.modules
        rows = mc.run_campaign(sc, 1, Path(OUT), campaign_seed=3, workers=2, progress=False)
        assert rows[0]["outcome"] == "landed", rows
        assert servers() == {server}, "the campaign forked its worker from the server started first"
        # Its last case handed back, the master imported what the campaign's end needs on a thread.
        for t in threading.enumerate():
            if t.name == "campaign-tail-imports":
                t.join()
        assert all(m in sys.modules for m in mc.TAIL_MODULES), [m for m in mc.TAIL_MODULES if m not in sys.modules]
    """)
    subprocess.run([sys.executable, "-c", f"QUICK = {QUICK!r}\nOUT = {str(tmp_path / 'mc')!r}\n" + code],
                   check=True, timeout=300, cwd=Path(__file__).resolve().parents[1])
