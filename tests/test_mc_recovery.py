"""Monte Carlo campaigns under failure: raising cases, timeouts, a killed campaign, a dead worker.

(Split from test_mc.py so that `make test`'s two processes share the campaign tests.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from bench.campaign import mc
from bench.cli import main
from bench.scenario import load_scenario
from tests.conftest import fork_servers, live_processes
from tests.test_mc import QUICK, _sets, _strip


def test_a_raising_case_and_a_timeout_are_recorded_and_the_campaign_goes_on(tmp_path):
    # A sun-elevation dispersion wide enough to draw elevations past 90 deg: those cases fail validation.
    # (Not a mass dispersion: the flight software flies the nominal mass, and a lander thousands of kg
    # off its nominal mass rightly does not land.)
    # Campaign seed 2 draws case 0 past 90 deg (it raises) and case 1 within range (it lands).
    base = load_scenario(None, [*QUICK, 'dispersions."sun.elevation_deg"={dist="normal", sigma=60.0}'])
    rows = mc.run_campaign(base, 2, tmp_path / "c", campaign_seed=2, workers=2, progress=False)
    assert len(rows) == 2
    errors = [r for r in rows if r["outcome"] == "error"]
    assert errors and all("sun.elevation_deg" in r["error"] for r in errors)
    assert any(r["outcome"] == "landed" for r in rows)
    # Every row names its case seed, the failed draw's too (to replay or report it).
    assert [r["seed"] for r in sorted(rows, key=lambda r: r["case"])] == list(mc.case_seeds(2, 2))
    slow = mc.run_campaign(load_scenario(None, QUICK), 2, tmp_path / "t", campaign_seed=2, workers=2,
                           case_timeout_s=0.5, progress=False)
    assert [r["outcome"] for r in slow] == ["error", "error"] and all("timeout" in r["error"] for r in slow)


def test_a_table_no_case_can_draw_is_refused_before_anything_is_written(tmp_path, capsys):
    # Gravity drawn away from the flight software's model: every case's draw is refused. The campaign flew
    # and wrote four error rows, exit 0; now it is one line naming the first case's reason, nothing written.
    out = tmp_path / "c"
    argv = ["mc", "--runs", "4", "--workers", "1", "--out", str(out), *_sets(),
            "--set", 'dispersions."sim.gravity_mps2"={dist="uniform", low=1.5, high=1.7}']
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("landbench: error: every one of the 4 cases' dispersed draws is refused (case 0: ")
    assert "sim.gravity_mps2" in err and "\n" not in err
    assert not out.exists()


def test_kill_and_resume_loses_and_duplicates_nothing(tmp_path):
    # Three cases, one worker, killed once the first has finished: the resume must run the other two.
    out = tmp_path / "camp"
    cmd = [sys.executable, "-m", "bench.cli", "mc", "--runs", "3", "--workers", "1", "--seed", "5",
           "--out", str(out), *_sets()]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((out / mc.CASES).glob("*.json"))) < 1:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the master and its worker, mid-campaign
    proc.wait()
    done_before = sorted(p.name for p in (out / mc.CASES).glob("*.json"))
    assert 1 <= len(done_before) < 3
    before = {p.name: p.read_text() for p in (out / mc.CASES).glob("*.json")}
    # Two workers for the rest and for the reference: a case does not depend on the worker count.
    assert main(["mc", "--resume", str(out), "--workers", "2"]) == 0  # its scenario is the folder's
    rows = mc.read_rows(out, 3)
    assert [r["case"] for r in rows] == [0, 1, 2]
    for name, text in before.items():  # finished cases were not redone
        assert (out / mc.CASES / name).read_text() == text
    fresh = mc.run_campaign(load_scenario(None, QUICK), 3, tmp_path / "fresh", campaign_seed=5, workers=2,
                            progress=False)
    assert _strip(rows) == _strip(fresh)


def _kill_next_worker(seen: set[int], timeout_s: float = 120.0) -> None:
    """SIGKILL the next case worker this process starts (one not in ``seen``).

    A worker is forked by this process's fork server (a child of ours whose command line names
    it), or, where there is none, spawned by this process directly.
    """
    me = os.getpid()
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        procs = live_processes()
        servers = fork_servers(procs, me)
        for pid, (ppid, cmd) in procs.items():
            is_worker = ppid in servers or (ppid == me and b"spawn_main" in cmd)
            if is_worker and pid not in seen:
                os.kill(pid, signal.SIGKILL)
                seen.add(pid)
                return
        time.sleep(0.02)
    raise AssertionError("no case worker was started")


def test_a_dead_worker_is_retried_once_then_recorded(tmp_path):
    base = load_scenario(None, QUICK)
    result = {}

    def campaign(name):
        result[name] = mc.run_campaign(base, 1, tmp_path / name, campaign_seed=3, progress=False)

    seen: set[int] = set()
    th = threading.Thread(target=campaign, args=("once",))
    th.start()
    _kill_next_worker(seen)  # killed once: rerun, and the case lands as if nothing happened
    th.join(timeout=300)
    clean = mc.run_campaign(base, 1, tmp_path / "clean", campaign_seed=3, progress=False)
    assert result["once"][0]["outcome"] == "landed" and _strip(result["once"]) == _strip(clean)
    th = threading.Thread(target=campaign, args=("twice",))
    th.start()
    _kill_next_worker(seen)
    _kill_next_worker(seen)  # killed twice: recorded as failed, and the campaign finishes
    th.join(timeout=300)
    (row,) = result["twice"]
    assert row["outcome"] == "error" and "worker died" in row["error"] and "twice" in row["error"]
