"""The terrain as MuJoCo sees it: triangulation and the landing-site patch."""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim.world_builder import build_terrain, build_world
from models.lander import PATCH_GEOM_GROUP, TERRAIN_GEOM_GROUP
from models.world import PATCH_LIFT_M
from tests.conftest import SMALL_SET

DOWN = np.array([0.0, 0.0, -1.0])
RAY_TOP_M = 500.0


@pytest.fixture(scope="module")
def world_and_terrain():
    scenario = load_scenario(None, SMALL_SET + ["terrain.patch_size_m=96.0", "terrain.patch_texture_px=512"])
    terrain = build_terrain(scenario)
    world = build_world(scenario, terrain)
    yield world, terrain
    world.close()


def _ray_heights(world, xy: np.ndarray, group: int) -> np.ndarray:
    return np.array([RAY_TOP_M - world.ray_cast(np.array([x, y, RAY_TOP_M]), DOWN, (group,)) for x, y in xy])


def test_surface_height_matches_mujoco_triangulation(world_and_terrain):
    world, terrain = world_and_terrain
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.45 * terrain.size_m, 0.45 * terrain.size_m, (200, 2))
    mj = _ray_heights(world, xy, TERRAIN_GEOM_GROUP)
    ours = terrain.surface_height(xy[:, 0], xy[:, 1])
    assert np.max(np.abs(mj - ours)) < 1e-3
    # The other diagonal (or bilinear interpolation) would not match: the test can fail.
    assert np.max(np.abs(mj - terrain.height_at(xy[:, 0], xy[:, 1]))) > 1e-2


def test_patch_is_coplanar_with_the_terrain_and_just_above_it(world_and_terrain):
    world, terrain = world_and_terrain
    patch = terrain.patch
    assert patch is not None and patch.size_m == pytest.approx(96.0, abs=terrain.spacing_m)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.49 * patch.size_m, 0.49 * patch.size_m, (300, 2))
    ground = _ray_heights(world, xy, TERRAIN_GEOM_GROUP)
    drawn = _ray_heights(world, xy, PATCH_GEOM_GROUP)
    assert np.allclose(drawn - ground, PATCH_LIFT_M, atol=1e-3)
    assert patch.albedo.shape == (512, 512) and patch.albedo.dtype == np.uint8


def test_textures_hold_the_albedo_north_up_in_every_channel(world_and_terrain):
    """tex_data against an explicit loop over rows: MuJoCo's row 0 is the north edge (the terrain's last row),
    and the grey value is in each of the texture's channels."""
    world, terrain = world_and_terrain
    m = world.model
    for name, albedo in (("albedo", terrain.albedo), ("patch_albedo", terrain.patch.albedo)):
        tid = m.texture(name).id
        rows, cols, nch = int(m.tex_height[tid]), int(m.tex_width[tid]), int(m.tex_nchannel[tid])
        assert (rows, cols) == albedo.shape and nch == 3
        tex = m.tex_data[m.tex_adr[tid]:m.tex_adr[tid] + rows * cols * nch]
        for r in range(0, rows, max(rows // 64, 1)):
            row = tex[r * cols * nch:(r + 1) * cols * nch].reshape(cols, nch)
            for c in range(nch):
                assert np.array_equal(row[:, c], albedo[rows - 1 - r]), (name, r, c)


def test_patch_texture_continues_the_coarse_texture(world_and_terrain):
    # Averaged back to the coarse texel size, the patch reproduces the coarse texture
    # (the detail it adds is zero-mean), so there is no seam or shift at its edge.
    _, terrain = world_and_terrain
    patch = terrain.patch
    coarse_texel = terrain.size_m / terrain.albedo.shape[0]
    k = int(round(patch.size_m / coarse_texel))
    n0 = (terrain.albedo.shape[0] - k) // 2
    coarse = terrain.albedo[n0:n0 + k, n0:n0 + k].astype(float)
    import cv2

    back = cv2.resize(patch.albedo.astype(np.float32), (k, k), interpolation=cv2.INTER_AREA)
    corr = np.corrcoef(coarse.ravel(), back.ravel())[0, 1]
    assert corr > 0.9, corr
    assert abs(back.mean() - coarse.mean()) < 3.0


def _assert_same_terrain(a, b) -> None:
    assert a.size_m == b.size_m and (a.patch is None) == (b.patch is None)
    for name in ("height_m", "albedo", "craters", "boulders"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name  # bit for bit
    if a.patch is not None:
        assert a.patch.size_m == b.patch.size_m
        for name in ("height_m", "albedo"):
            x, y = getattr(a.patch, name), getattr(b.patch, name)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f"patch.{name}"


def test_terrain_cache_returns_the_generated_terrain_bit_for_bit(tmp_path, monkeypatch):
    from bench.sim import world_builder as wb

    sets = [*SMALL_SET, "terrain.patch_size_m=96.0", "terrain.patch_texture_px=256"]
    sc = load_scenario(None, sets)
    wb.clear_terrain_cache()
    first = wb.build_terrain(sc)
    assert wb.build_terrain(load_scenario(None, sets)) is first  # an equal scenario hits the cache
    _assert_same_terrain(first, wb.generate_scenario_terrain(sc))  # cached == freshly generated
    # Everything that generates the terrain is in the key: another seed, sun or setting is another terrain.
    for other in (["terrain.seed=7"], ["sun.elevation_deg=40.0"], ["sun.azimuth_deg=200.0"],
                  ["terrain.crater_density_per_km2=50.0"]):
        osc = load_scenario(None, [*sets, *other])
        t = wb.build_terrain(osc)
        assert t is not first and t.albedo.tobytes() != first.albedo.tobytes(), other
        _assert_same_terrain(t, wb.generate_scenario_terrain(osc))
    # Bounded: the least recently used entries go first once the cache passes its byte budget.
    assert len(wb._terrain_cache) == 5
    monkeypatch.setattr(wb, "TERRAIN_CACHE_MAX_BYTES", int(2.5 * wb._terrain_bytes(first)))  # room for two
    again = wb.build_terrain(sc)  # a hit: now the most recently used
    assert again is first
    wb.build_terrain(load_scenario(None, [*sets, "terrain.seed=8"]))
    assert len(wb._terrain_cache) == 2 and wb.build_terrain(sc) is first
    # A DEM terrain is read from its file every time (the file may change): never cached.
    dem = tmp_path / "dem.npy"
    np.save(dem, np.random.default_rng(0).normal(0.0, 1.0, (65, 65)))
    dsc = load_scenario(None, [*sets, 'terrain.kind="dem"', f'terrain.dem_path="{dem}"', "terrain.dem_spacing_m=4.0",
                               "terrain.target_clear_radius_m=20.0", "terrain.patch_size_m=0.0"])
    assert wb.build_terrain(dsc) is not wb.build_terrain(dsc)
    wb.clear_terrain_cache()
