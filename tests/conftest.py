"""Shared fixtures: small, fast worlds built from independent, known terrains."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.terrain import Terrain

# Small terrains keep the suite fast; the physics and optics do not depend on size.
SMALL_SET = ["terrain.texture_px=1024", "terrain.geometry_px=65", "terrain.size_m=512.0"]


def make_terrain(height_m: np.ndarray, size_m: float, texture_px: int = 512, seed: int = 0) -> Terrain:
    """A Terrain from an explicit height grid (rows south to north) and a random-texture albedo."""
    rng = np.random.default_rng(seed)
    albedo = rng.integers(40, 220, (texture_px, texture_px), dtype=np.uint8)
    return Terrain(
        height_m=np.asarray(height_m, np.float32),
        size_m=float(size_m),
        albedo=albedo,
        craters=np.zeros((0, 3)),
        boulders=np.zeros((0, 3)),
    )


@pytest.fixture(autouse=True, scope="session")
def _no_progress_monitor_thread():
    """tqdm's monitor thread, started by the first progress bar (a campaign's, a run's) and alive until the
    process ends, would leave every later test a second thread; ``bench.report.split_draw`` forks only in a
    process of one thread, so its tests would then depend on which tests ran before them. No test starts
    it (the bars draw the same; only their refresh of a stalled bar is lost)."""
    from tqdm import tqdm

    interval = tqdm.monitor_interval
    tqdm.monitor_interval = 0
    yield
    tqdm.monitor_interval = interval


@pytest.fixture
def flat_terrain() -> Terrain:
    return make_terrain(np.zeros((33, 33)), 256.0)


def record_instances(monkeypatch, module, name: str) -> list:
    """Replace the class ``module.name`` (for the test's duration) by a subclass that records each
    instance it makes; returns the list they are appended to."""
    made = []
    base = getattr(module, name)

    class Recorded(base):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(module, name, Recorded)
    return made


def damage_file(path, damage: str, flip_at: float = 0.5) -> None:
    """Damage a disk-cache entry in place, as a crash or bit rot would: ``"truncate"`` (to half its
    length), ``"flip"`` (one bit at ``flip_at`` of its length), ``"garbage"`` (other bytes) or ``"empty"``."""
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "flip":
        data[int(len(data) * flip_at)] ^= 0x01
    elif damage == "garbage":
        data = bytearray(b"not a cache entry" * 10)
    elif damage == "empty":
        data = bytearray()
    else:
        raise ValueError(f"damage = {damage!r}")
    path.write_bytes(bytes(data))


def live_processes() -> dict[int, tuple[int, bytes]]:
    """Every live process on this machine (zombies, exited but not yet reaped, left out): pid -> (parent pid,
    command line)."""
    procs = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            state, ppid = (d / "stat").read_text().rsplit(")", 1)[1].split()[:2]
            cmd = (d / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if state != "Z":
            procs[int(d.name)] = (int(ppid), cmd)
    return procs


def fork_servers(procs: dict[int, tuple[int, bytes]], parent: int) -> set[int]:
    """The multiprocessing fork servers among ``procs`` (:func:`live_processes`) that ``parent`` started."""
    return {pid for pid, (ppid, cmd) in procs.items() if ppid == parent and b"forkserver" in cmd}


def pytest_addoption(parser):
    parser.addoption("--regen-snapshots", action="store_true", default=False,
                     help="rewrite the replay metric snapshots (tests/snapshots/*.json, not the tolerance files) "
                          "from this run instead of checking them; `make snapshots` runs it")
