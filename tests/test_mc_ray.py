"""The Ray backend against a Ray cluster this module starts itself (``ray start --head``).

The cluster is reached the way a user reaches one: ``--address`` on the
command line, or ``RAY_ADDRESS``. Its cases must equal the local backend's
row for row, and its failure handling (a worker killed mid-case, a timeout)
must match the local backend's.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("ray", reason="the Ray extra is not installed: pip install 'landbench[ray]'")

from bench.campaign import mc  # noqa: E402
from bench.cli import main  # noqa: E402
from bench.scenario import load_scenario  # noqa: E402
from tests.test_mc import QUICK, _sets, _strip  # noqa: E402

RAY_CPUS = 2
TASK_TITLE = b"ray::_ray_case"  # Ray's process title for a worker running a case


def _ray_cli() -> str:
    exe = Path(sys.executable).with_name("ray")
    return str(exe) if exe.exists() else shutil.which("ray") or "ray"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_address():
    """A one-node Ray cluster on this machine, as `ray start --head` makes one."""
    port = _free_port()
    # No token authentication on this loopback-only test cluster: Ray reads
    # RAY_AUTH_MODE when it is imported, which pytest has already done, so a
    # token cluster could not be joined from this process (a user's shell sets
    # RAY_AUTH_MODE=token before landbench starts, and that path works).
    saved = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_ADDRESS")}
    os.environ["RAY_AUTH_MODE"] = "disabled"
    os.environ.pop("RAY_ADDRESS", None)
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    subprocess.run([_ray_cli(), "start", "--head", f"--port={port}", f"--num-cpus={RAY_CPUS}",
                    "--include-dashboard=false", "--disable-usage-stats"],
                   check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120)
    try:
        yield f"127.0.0.1:{port}"
    finally:
        import ray

        if ray.is_initialized():
            ray.shutdown()
        subprocess.run([_ray_cli(), "stop", "--force"], env=env, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, timeout=120, check=False)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _case_pids() -> list[int]:
    """Processes running a case in a Ray worker (found by their process title)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if (d / "cmdline").read_bytes().startswith(TASK_TITLE):
                    pids.append(int(d.name))
            except OSError:
                continue
    return pids


@pytest.mark.slow  # the default campaign's acceptance test (slow) checks Ray against local rows too
def test_ray_cases_equal_local_cases_row_for_row(tmp_path, ray_address, capsys):
    # Through the CLI, as a cluster user runs it; failed cases keep their files.
    assert main(["mc", "--backend", "ray", "--address", ray_address, "--runs", "3", "--workers", "2",
                 "--seed", "11", "--retention", "all", "--out", str(tmp_path / "ray"), *_sets()]) == 0
    assert "landed" in capsys.readouterr().out
    ray_rows = mc.read_rows(tmp_path / "ray", 3)
    local = mc.run_campaign(load_scenario(None, QUICK), 3, tmp_path / "local", campaign_seed=11, workers=2,
                            progress=False)
    assert [r["case"] for r in ray_rows] == [0, 1, 2]
    assert _strip(ray_rows) == _strip(local)
    import pyarrow.parquet as pq

    assert _strip(pq.read_table(tmp_path / "ray" / mc.CASES_PARQUET).to_pylist()) == _strip(
        pq.read_table(tmp_path / "local" / mc.CASES_PARQUET).to_pylist())
    # retention=all: the cases' files came back from the workers to the driver's folder.
    for i in range(3):
        kept = tmp_path / "ray" / mc.CASES / f"{i:05d}"
        assert (kept / "summary.json").is_file() and (kept / "telemetry.parquet").is_file()
    assert all(r["case_peak_rss_mb"] > 0 for r in ray_rows)


@pytest.mark.slow  # 15-22 s, the suite's slowest; the local backend's retry is in the fast suite (test_mc_recovery)
def test_ray_retries_a_killed_worker_once_then_records_the_case(tmp_path, ray_address, monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", ray_address)  # no --address: the environment names the cluster
    base = load_scenario(None, QUICK)
    result = {}

    def campaign(name):
        result[name] = mc.run_campaign(base, 1, tmp_path / name, campaign_seed=3, backend="ray", progress=False)

    def kill_next_case(seen):
        deadline = time.time() + 120
        while time.time() < deadline:
            fresh = [p for p in _case_pids() if p not in seen]
            if fresh:
                os.kill(fresh[0], signal.SIGKILL)
                seen.add(fresh[0])
                return
            time.sleep(0.05)
        raise AssertionError("no Ray worker ran the case")

    # Killed once: Ray reruns it and the case lands as if nothing happened.
    th = threading.Thread(target=campaign, args=("once",))
    th.start()
    seen: set[int] = set()
    kill_next_case(seen)
    th.join(timeout=300)
    (row,) = result["once"]
    assert row["outcome"] == "landed", row.get("error")
    clean = mc.run_campaign(base, 1, tmp_path / "clean", campaign_seed=3, progress=False)
    assert _strip([row]) == _strip(clean)

    # Killed twice: the case is recorded as failed and the campaign still finishes.
    th = threading.Thread(target=campaign, args=("twice",))
    th.start()
    kill_next_case(seen)
    kill_next_case(seen)
    th.join(timeout=300)
    (row,) = result["twice"]
    assert row["outcome"] == "error" and "worker died twice" in row["error"]


def test_ray_timeout_is_recorded(tmp_path, ray_address):
    rows = mc.run_campaign(load_scenario(None, QUICK), 2, tmp_path / "t", campaign_seed=2, workers=2,
                           backend="ray", address=ray_address, case_timeout_s=0.5, progress=False)
    assert [r["outcome"] for r in rows] == ["error", "error"] and all("timeout" in r["error"] for r in rows)


def test_ray_is_asked_for_only_with_the_ray_backend(tmp_path):
    with pytest.raises(ValueError, match="--address"):
        mc.run_campaign(load_scenario(None, QUICK), 1, tmp_path / "x", campaign_seed=1, address="127.0.0.1:1",
                        progress=False)
