"""The onboard map products' disk cache: a hit is the product made afresh bit for bit, a damaged entry is
rebuilt, and everything that shapes the product is in its key."""

from __future__ import annotations

import numpy as np
import pytest

from bench.maps import build_onboard_map, map_key, scenario_onboard_map
from bench.scenario import load_scenario
from bench.scenario.seeding import component_rng
from bench.sim import terrain_cache
from models.terrain import generate_surface
from tests.conftest import damage_file

SMALL = ["terrain.texture_px=256", "terrain.geometry_px=33", "terrain.size_m=256.0", "terrain.patch_size_m=64.0",
         "terrain.patch_texture_px=128", "onboard_map.size_m=128.0", "nav_map=on"]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(terrain_cache.CACHE_ENV, str(tmp_path))
    return tmp_path / "map"


def _scenario(*extra):
    return load_scenario(None, [*SMALL, *extra])


def _fresh(sc):
    """The map made from a surface regenerated here: the path that never reads the cache."""
    surface = generate_surface(sc.terrain, component_rng(sc.terrain_seed(), "terrain"))
    return build_onboard_map(sc.terrain, sc.terrain_seed(), sc.onboard_map, sc.seed, surface=surface)


def _assert_same(a, b):
    (ma, ta), (mb, tb) = a, b
    assert ta == tb
    for name in ("image", "dem_m"):
        x, y = getattr(ma, name), getattr(mb, name)
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
    for name in ("image_res_m", "image_origin_xy_m", "dem_spacing_m", "dem_origin_xy_m", "target_xy_m",
                 "georef_sigma_m", "dem_sigma_m"):
        assert getattr(ma, name) == getattr(mb, name), name


def test_hit_returns_the_map_made_afresh(cache, monkeypatch):
    sc = _scenario("seed=3")
    first = scenario_onboard_map(sc)
    (entry,) = cache.glob("*.npz")
    # The second call must read the entry: generating the surface again would fail.
    import bench.maps as maps

    monkeypatch.setattr(maps, "generate_surface", lambda *a, **k: pytest.fail("generated on a hit"))
    second = scenario_onboard_map(sc)
    monkeypatch.undo()
    fresh = _fresh(sc)
    _assert_same(first, fresh)
    _assert_same(second, fresh)
    assert not second[0].image.flags.writeable and not second[0].dem_m.flags.writeable
    assert entry.exists()


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage"])
def test_damaged_entry_is_rebuilt_not_trusted(cache, damage):
    sc = _scenario("seed=4")
    scenario_onboard_map(sc)
    (path,) = cache.glob("*.npz")
    damage_file(path, damage, flip_at=1 / 3)  # a flip lands inside the image: only the checksum sees it
    _assert_same(scenario_onboard_map(sc), _fresh(sc))
    (rebuilt,) = cache.glob("*.npz")
    assert terrain_cache.load_entry(rebuilt, rebuilt.stem) is not None


def test_cache_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(terrain_cache.CACHE_ENV, "off")
    sc = _scenario("seed=5")
    _assert_same(scenario_onboard_map(sc), _fresh(sc))
    assert not any(tmp_path.iterdir())


def test_every_shaping_field_changes_the_key():
    sc = _scenario()
    shift = (0.5, -1.25)
    base = map_key(sc.terrain, 1, sc.onboard_map, 7, shift)
    assert map_key(sc.terrain, 1, sc.onboard_map, 7, shift) == base
    assert map_key(sc.terrain, 2, sc.onboard_map, 7, shift) != base
    assert map_key(sc.terrain, 1, sc.onboard_map, 8, shift) != base
    assert map_key(sc.terrain, 1, sc.onboard_map, 7, (0.5, -1.2500001)) != base
    for cfg, rebuild in ((sc.onboard_map, lambda c: map_key(sc.terrain, 1, c, 7, shift)),
                         (sc.terrain, lambda c: map_key(c, 1, sc.onboard_map, 7, shift))):
        for field, value in cfg.model_dump().items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            changed = cfg.model_copy(update={field: value + 1 if isinstance(value, int) else value * 1.01 + 0.01})
            assert rebuild(changed) != base, field
