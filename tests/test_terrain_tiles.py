"""The camera draws a texture-shaded terrain from mesh tiles culled to its view (``models.world.TerrainTiles``).

Two independent references: MuJoCo's own drawing of the heightfield (a renderer with no tiles, the
heightfield's group shown), and the tiles all drawn (nothing culled). The first may differ by
rasterisation rounding; the second must not differ at all.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim.world_builder import build_terrain, build_world
from models.lander import HIDDEN_TILE_GEOM_GROUP, TERRAIN_TILE_GEOM_GROUP
from models import render_context as rc
from models.render_context import CameraRenderer, CulledGeoms
from tests.conftest import SMALL_SET

mujoco = rc.mujoco  # the GL backend chosen by models first

# (x, y, height above the ground [m], tilt of the camera from nadir about the body x axis [deg])
POSES = [(-60.0, 40.0, 400.0, 0.0), (-60.0, 40.0, 120.0, 0.0), (10.0, -5.0, 30.0, 0.0),
         (200.0, -180.0, 60.0, 0.0),  # over a corner tile, the terrain's edge in view
         (-60.0, 40.0, 80.0, 35.0), (30.0, 60.0, 200.0, -50.0)]  # looking across the ground


@pytest.fixture(scope="module", params=["square", "wide"])
def world(request):
    # Texture-shaded by default; 65 posts over 512 m: 4 x 4 tiles. "wide": a 4:1 frame and another field of
    # view, so the view pyramid's horizontal half-angle (fovy's, times the aspect) is tested too.
    wide = ["camera.width_px=192", "camera.height_px=48", "camera.fovy_deg=25.0"] if request.param == "wide" else []
    sc = load_scenario(None, [*SMALL_SET, *wide])
    w = build_world(sc, build_terrain(sc))
    yield w
    w.close()


def _pose(world, x: float, y: float, above_m: float, tilt_deg: float) -> None:
    m, d = world.model, world.data
    qa = m.jnt_qposadr[0]  # the lander's free joint: position, then the quaternion (w, x, y, z)
    ground = float(world.terrain.surface_height(np.array([x]), np.array([y]))[0])
    d.qpos[qa:qa + 3] = (x, y, ground + above_m)
    half = np.radians(tilt_deg) / 2.0
    d.qpos[qa + 3:qa + 7] = (np.cos(half), np.sin(half), 0.0, 0.0)
    mujoco.mj_forward(m, d)


def _frame_through(world, renderer: CameraRenderer) -> np.ndarray:
    """The frame of `world`'s camera drawn through another renderer (heightfield, or every tile)."""
    return renderer.render_green(world.data, world._cam).copy()


def test_a_texture_shaded_terrain_has_tiles_that_cover_its_heightfield(world):
    tiles = world._camera_tiles
    assert tiles is not None and tiles.geom_ids.size == 16
    m = world.model
    assert np.all(m.geom_type[tiles.geom_ids] == mujoco.mjtGeom.mjGEOM_MESH)
    assert np.all(m.geom_contype[tiles.geom_ids] == 0) and np.all(m.geom_conaffinity[tiles.geom_ids] == 0)
    # Their boxes tile the heightfield's square exactly, and hold its heights.
    half = world.terrain.size_m / 2.0
    lo, hi = tiles.corners.min(axis=1), tiles.corners.max(axis=1)
    assert np.isclose(lo[:, 0].min(), -half) and np.isclose(hi[:, 0].max(), half)
    assert np.isclose(lo[:, 1].min(), -half) and np.isclose(hi[:, 1].max(), half)
    area = ((hi[:, 0] - lo[:, 0]) * (hi[:, 1] - lo[:, 1])).sum()
    assert np.isclose(area, (2 * half) ** 2)
    h = world.terrain.height_m
    assert np.isclose(lo[:, 2].min(), h.min(), atol=1e-3) and np.isclose(hi[:, 2].max(), h.max(), atol=1e-3)


def test_the_tiles_draw_what_the_heightfield_draws(world):
    """Against MuJoCo's own heightfield: the same frame up to rasterisation rounding."""
    plain = CameraRenderer(world.model, world.camera_cfg.width_px, world.camera_cfg.height_px)
    try:
        for pose in POSES:
            _pose(world, *pose)
            tiled = world.render_signal().copy()
            reference = _frame_through(world, plain)
            diff = np.abs(tiled.astype(int) - reference)
            assert reference.std() > 5.0, pose  # a textured view, not an empty one
            assert diff.max() <= 1, pose
            assert (diff > 0).mean() < 0.01, pose
    finally:
        plain.close()


def test_culling_leaves_every_frame_as_it_is_and_draws_fewer_tiles(world):
    """Against the tiles all drawn (boxes around the whole world, the camera inside: never culled): the same pixels."""
    tiles = world._camera_tiles
    everywhere = np.array([[x, y, z] for x in (-1e5, 1e5) for y in (-1e5, 1e5) for z in (-1e5, 1e5)])
    every = CulledGeoms(tiles.geom_ids, np.broadcast_to(everywhere, tiles.corners.shape), TERRAIN_TILE_GEOM_GROUP,
                        HIDDEN_TILE_GEOM_GROUP, tiles.replaces_group)
    uncull = CameraRenderer(world.model, world.camera_cfg.width_px, world.camera_cfg.height_px, culled=every)
    hidden = []
    try:
        for pose in POSES:
            _pose(world, *pose)
            culled = world.render_signal().copy()
            hidden.append(int((world.model.geom_group[tiles.geom_ids] == HIDDEN_TILE_GEOM_GROUP).sum()))
            np.testing.assert_array_equal(culled, _frame_through(world, uncull), err_msg=str(pose))
    finally:
        uncull.close()
    # The culling does something: low over the ground most tiles are left out, high up fewer.
    assert hidden[2] >= 12 and hidden[0] < hidden[2]


def test_a_renderer_shaded_terrain_is_drawn_from_its_heightfield():
    """Its material is lit: a mesh's smoothed normals would shade it unlike the heightfield's flat triangles."""
    sc = load_scenario(None, [*SMALL_SET, 'terrain.relief_shading="renderer"', "terrain.patch_size_m=0.0"])
    w = build_world(sc, build_terrain(sc))
    try:
        assert w._camera_tiles is None
        assert not any(w.model.geom(i).name.startswith("terrain_tile") for i in range(w.model.ngeom))
    finally:
        w.close()


def test_the_tiles_heights_are_the_heightfields_own_vertices():
    """Against what MuJoCo draws: each heightfield vertex at ``hfield_data * size_z`` in float32 on the geom's
    base (mjr_uploadHField), from the model's own stored data. Where the float32 heights' span rounds
    (NumPy's ptp in float32), the tiles must use that same size z (random heights, 20 in 30 such grids)."""
    import re

    from models.world import terrain_tiles
    from tests.conftest import make_terrain

    sc = load_scenario(None, SMALL_SET)
    for seed in range(4):
        terrain = make_terrain(np.random.default_rng(seed).normal(0.0, 10.0, (65, 65)), 256.0)
        world = build_world(sc, terrain)
        try:
            m = world.model
            hid = m.hfield("terrain").id
            data = m.hfield_data[m.hfield_adr[hid]:m.hfield_adr[hid] + m.hfield_nrow[hid] * m.hfield_ncol[hid]]
            drawn = (data.astype(np.float32) * np.float32(m.hfield_size[hid, 2])).astype(np.float64)
            drawn = set((drawn + m.geom_pos[m.geom("terrain").id, 2]).tolist())
        finally:
            world.close()
        tiles = {float(v) for text in re.findall(r'vertex="([^"]*)"', terrain_tiles(terrain).assets)
                 for v in text.split()[2::3]}
        assert tiles == drawn, seed
