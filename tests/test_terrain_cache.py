"""The on-disk terrain cache: a hit is the generated terrain bit for bit, a damaged entry is rebuilt, concurrent
writers leave a valid entry, and every field that shapes the terrain is in the key."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim import terrain_cache
from bench.sim.world_builder import build_terrain, clear_terrain_cache, generate_scenario_terrain
from tests.conftest import damage_file

SMALL = ["terrain.texture_px=256", "terrain.geometry_px=33", "terrain.size_m=256.0", "terrain.patch_size_m=64.0",
         "terrain.patch_texture_px=128"]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(terrain_cache.CACHE_ENV, str(tmp_path))
    clear_terrain_cache()  # the process cache would hide the disk
    yield tmp_path / "terrain"
    clear_terrain_cache()


def _scenario(*extra):
    return load_scenario(None, [*SMALL, *extra])


def _assert_same(a, b):
    assert a.size_m == b.size_m
    for name in ("height_m", "albedo", "craters", "boulders"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert (a.patch is None) == (b.patch is None)
    if a.patch is not None:
        assert a.patch.size_m == b.patch.size_m
        assert np.array_equal(a.patch.height_m, b.patch.height_m) and np.array_equal(a.patch.albedo, b.patch.albedo)


def _get(sc, calls):
    def generate():
        calls.append(1)
        return generate_scenario_terrain(sc)
    return terrain_cache.cached_terrain(sc.terrain, sc.terrain_seed(), sc.sun.elevation_deg, sc.sun.azimuth_deg,
                                        generate)


def test_hit_returns_the_generated_terrain(cache):
    sc = _scenario("seed=3")
    calls: list = []
    first = _get(sc, calls)
    second = _get(sc, calls)
    assert len(calls) == 1 and len(list(cache.glob("*.npz"))) == 1
    fresh = generate_scenario_terrain(sc)
    _assert_same(first, fresh)
    _assert_same(second, fresh)
    assert first.patch is not None and not second.albedo.flags.writeable
    # build_terrain goes through the disk cache too.
    clear_terrain_cache()
    _assert_same(build_terrain(sc), fresh)


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty"])
def test_damaged_entry_is_rebuilt_not_trusted(cache, damage):
    sc = _scenario("seed=4")
    calls: list = []
    _get(sc, calls)
    (path,) = cache.glob("*.npz")
    damage_file(path, damage)  # a flip lands inside the albedo: only the checksum sees it
    again = _get(sc, calls)
    assert len(calls) == 2
    _assert_same(again, generate_scenario_terrain(sc))
    # ... and the rebuilt entry is valid again.
    assert terrain_cache.load(path, terrain_cache.terrain_key(sc.terrain, sc.terrain_seed(), sc.sun.elevation_deg,
                                                              sc.sun.azimuth_deg)) is not None


def test_entry_under_another_key_is_not_trusted(cache):
    a, b = _scenario("seed=5"), _scenario("seed=6")
    _get(a, [])
    key_a = terrain_cache.terrain_key(a.terrain, 5, a.sun.elevation_deg, a.sun.azimuth_deg)
    key_b = terrain_cache.terrain_key(b.terrain, 6, b.sun.elevation_deg, b.sun.azimuth_deg)
    (cache / f"{key_a}.npz").rename(cache / f"{key_b}.npz")  # a valid entry, in the wrong place
    calls: list = []
    _assert_same(_get(b, calls), generate_scenario_terrain(b))
    assert calls == [1]


def test_every_shaping_field_changes_the_key():
    sc = _scenario()
    base = terrain_cache.terrain_key(sc.terrain, 1, 30.0, 100.0)
    assert terrain_cache.terrain_key(sc.terrain, 1, 30.0, 100.0) == base
    assert terrain_cache.terrain_key(sc.terrain, 2, 30.0, 100.0) != base
    assert terrain_cache.terrain_key(sc.terrain, 1, 30.000001, 100.0) != base
    assert terrain_cache.terrain_key(sc.terrain, 1, 30.0, 100.5) != base
    for field, value in sc.terrain.model_dump().items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        changed = sc.terrain.model_copy(update={field: value + 1 if isinstance(value, int) else value * 1.01 + 0.01})
        assert terrain_cache.terrain_key(changed, 1, 30.0, 100.0) != base, field


def test_cache_off(tmp_path, monkeypatch):
    monkeypatch.setenv(terrain_cache.CACHE_ENV, "off")
    assert terrain_cache.cache_dir() is None
    monkeypatch.setenv(terrain_cache.CACHE_ENV, str(tmp_path / "c"))
    assert terrain_cache.cache_dir() == tmp_path / "c" / "terrain"
    monkeypatch.delenv(terrain_cache.CACHE_ENV)
    assert str(terrain_cache.cache_dir()).endswith(".cache/landbench/terrain")


def _writer(path: str, key: str, start, n: int) -> None:
    from pathlib import Path

    sc = load_scenario(None, [*SMALL, "seed=8"])
    terrain = generate_scenario_terrain(sc)
    start.wait()
    for _ in range(n):
        terrain_cache.store(Path(path), key, terrain)


def test_two_processes_writing_concurrently_leave_a_valid_entry(cache):
    sc = _scenario("seed=8")
    key = terrain_cache.terrain_key(sc.terrain, 8, sc.sun.elevation_deg, sc.sun.azimuth_deg)
    path = cache / f"{key}.npz"
    ctx = mp.get_context("spawn")
    start = ctx.Barrier(3)
    procs = [ctx.Process(target=_writer, args=(str(path), key, start, 10)) for _ in range(2)]
    for p in procs:
        p.start()
    start.wait()
    reads = 0
    while any(p.is_alive() for p in procs):  # meanwhile, a reader sees no entry or a complete one, never a partial one
        if path.exists():
            assert terrain_cache.load(path, key) is not None
            reads += 1
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    got = terrain_cache.load(path, key)
    assert got is not None
    _assert_same(got, generate_scenario_terrain(sc))
    assert [p.name for p in cache.iterdir()] == [path.name]  # no temporary file left behind
