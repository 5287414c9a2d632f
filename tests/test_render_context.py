"""The camera renderer's shared render context against MuJoCo's own renderer, frame for frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim.world_builder import build_terrain, build_world, place_above_target
from models import render_context as rc
from tests.conftest import SMALL_SET

mujoco = rc.mujoco  # imported after the GL backend is chosen (models.gl)

SMALL_CAMERA = ["camera.width_px=96", "camera.height_px=96"]


def _scenario(*extra: str):
    return load_scenario(None, SMALL_SET + SMALL_CAMERA + list(extra))


def _reference_frame(world) -> np.ndarray:
    """The frame through a fresh ``mujoco.Renderer`` (its own GL and render contexts), of the same
    scene: a texture-shaded terrain's tiles, all of them (tests/test_terrain_tiles.py holds the
    camera's culling to the same pixels, and the tiles to the heightfield's)."""
    cfg = world.camera_cfg
    r = mujoco.Renderer(world.model, cfg.height_px, cfg.width_px)
    option = mujoco.MjvOption()
    tiles = world._camera_tiles
    if tiles is not None:
        world.model.geom_group[tiles.geom_ids] = tiles.group
        tiles.show_in(option)
    try:
        r.update_scene(world.data, camera=world._cam, scene_option=option)
        return r.render()[:, :, 1].copy()
    finally:
        r.close()


def _pose(world, altitude_m: float, dx_m: float) -> None:
    place_above_target(world, altitude_m)
    world.data.qpos[0] += dx_m
    mujoco.mj_forward(world.model, world.data)


@pytest.fixture(autouse=True)
def _no_idle_contexts():
    rc.free_shared_contexts()
    yield
    rc.free_shared_contexts()


def test_worlds_over_one_terrain_share_a_context_and_render_what_mujoco_renders():
    sc = _scenario()
    heavier = _scenario("lander.dry_mass_kg=700", "lander.com_offset_B_m=[0.05, 0.02, 0.1]")
    terrain = build_terrain(sc)
    with build_world(sc, terrain) as a, build_world(heavier, terrain) as b:
        for altitude_m, dx_m in ((300.0, 0.0), (60.0, 7.5), (20.0, -3.0)):
            _pose(a, altitude_m, dx_m)
            _pose(b, altitude_m, -dx_m)
            fa, fb = a.render_signal(), b.render_signal()
            assert fa.dtype == np.uint8 and fa.shape == (96, 96) and fa.flags.c_contiguous
            np.testing.assert_array_equal(fa, _reference_frame(a))
            np.testing.assert_array_equal(fb, _reference_frame(b))
            if dx_m:
                assert not np.array_equal(fa, fb)  # the two poses differ, and so do their frames
        assert a._renderer._ctx is b._renderer._ctx
        assert len(rc._CONTEXTS) == 1 and rc._CONTEXTS[0].users == 2
    # Both closed: the context is kept, idle, for the next world over this terrain.
    assert [c.users for c in rc._CONTEXTS] == [0]
    kept = rc._CONTEXTS[0]
    with build_world(sc, terrain) as c:
        _pose(c, 60.0, 7.5)
        np.testing.assert_array_equal(c.render_signal(), _reference_frame(c))
        assert c._renderer._ctx is kept


def test_another_terrain_takes_over_the_idle_gl_context_with_its_own_assets():
    """Terrain A, B, A again (a campaign's cases): the one GL context is rebuilt with each
    world's assets, and every frame is what a fresh MuJoCo renderer draws."""
    scenarios = [_scenario(), _scenario("terrain.seed=12345"), _scenario()]
    # The terrains first: one generated between two worlds (a cold terrain cache) frees the idle
    # context instead (test_a_terrain_cache_miss_frees_the_idle_context_first).
    terrains = [build_terrain(sc) for sc in scenarios]
    seen = []
    for sc, terrain in zip(scenarios, terrains):
        with build_world(sc, terrain) as w:
            for altitude_m, dx_m in ((300.0, 0.0), (40.0, 5.0)):
                _pose(w, altitude_m, dx_m)
                np.testing.assert_array_equal(w.render_signal(), _reference_frame(w))
            seen.append((w._renderer._ctx, w._renderer._ctx.key))
        assert len(rc._CONTEXTS) == 1
    (c0, k0), (c1, k1), (c2, k2) = seen
    assert c0 is c1 is c2  # one GL context throughout
    assert k0 != k1 and k2 == k0  # rebuilt for B, and for A again


def test_a_terrain_cache_miss_frees_the_idle_context_first(monkeypatch, tmp_path):
    """A reused campaign worker keeps its last case's GL context idle (about 120 MB with llvmpipe);
    build_terrain frees it when it must generate a terrain, not on a cache hit."""
    from bench.sim import world_builder

    calls = []
    monkeypatch.setattr(world_builder, "free_shared_contexts", lambda: calls.append(1) or 0)
    monkeypatch.setenv("LANDBENCH_CACHE_DIR", str(tmp_path))
    world_builder.clear_terrain_cache()
    sc = _scenario("terrain.seed=4242")
    build_terrain(sc)  # generated
    assert calls == [1]
    world_builder.clear_terrain_cache()
    build_terrain(sc)  # from the disk cache
    assert calls == [1]
    world_builder.clear_terrain_cache()


def test_the_key_covers_heights_texture_pixels_and_frame_size():
    sc = _scenario()
    with build_world(sc) as world:
        base = rc.visual_digest(world.model, 96, 96)
        assert rc.visual_digest(world.model, 96, 64) != base
        world.model.hfield_data[17] += 1e-6
        assert rc.visual_digest(world.model, 96, 96) != base
        world.model.hfield_data[17] -= 1e-6
        assert rc.visual_digest(world.model, 96, 96) == base
        world.model.tex_data[12345] ^= 1
        assert rc.visual_digest(world.model, 96, 96) != base


def test_a_different_albedo_gives_another_context():
    """The world's texture key comes from its terrain's albedo: equal heights, other pixels."""
    sc = _scenario()
    terrain = build_terrain(sc)
    albedo = terrain.albedo.copy()
    albedo[100, 200] ^= 0x10
    repainted = dataclasses.replace(terrain, albedo=albedo)
    with build_world(sc, terrain) as a, build_world(sc, repainted) as b:
        _pose(a, 100.0, 0.0)
        _pose(b, 100.0, 0.0)
        a.render_signal()
        b.render_signal()
        assert a._renderer._ctx is not b._renderer._ctx
        assert len(rc._CONTEXTS) == 2


def test_a_context_inherited_through_a_fork_is_not_used(monkeypatch):
    sc = _scenario()
    terrain = build_terrain(sc)
    with build_world(sc, terrain) as a:
        _pose(a, 100.0, 0.0)
        a.render_signal()
    inherited = rc._CONTEXTS[0]
    monkeypatch.setattr(inherited, "pid", -1)  # as if made by the parent before a fork
    with build_world(sc, terrain) as b:
        _pose(b, 100.0, 0.0)
        np.testing.assert_array_equal(b.render_signal(), _reference_frame(b))
        assert b._renderer._ctx is not inherited
    monkeypatch.setattr(inherited, "pid", rc.os.getpid())
    inherited.free()  # this process made it after all: free its GL objects


def test_a_world_in_another_thread_takes_over_the_idle_context_and_never_shares_a_live_one():
    """A Gymnasium episode flies in a thread of its own: the context a finished episode left idle
    serves the next one, while two threads with live worlds each get their own."""
    import threading

    sc = _scenario()
    terrain = build_terrain(sc)
    frames, contexts, errors = [], [], []

    def episode(dx_m: float) -> None:
        try:
            with build_world(sc, terrain) as w:
                _pose(w, 80.0, dx_m)
                frames.append((w.render_signal(), _reference_frame(w)))
                contexts.append(w._renderer._ctx)
        except Exception as exc:  # noqa: BLE001 - reported below, in the test's thread
            errors.append(exc)

    for dx_m in (0.0, 4.0):  # one after the other, each in a new thread
        t = threading.Thread(target=episode, args=(dx_m,))
        t.start()
        t.join()
    assert not errors, errors
    assert contexts[0] is contexts[1]
    for got, want in frames:
        np.testing.assert_array_equal(got, want)
    # A live world here, and one in another thread at the same time: two contexts.
    with build_world(sc, terrain) as mine:
        _pose(mine, 80.0, 0.0)
        mine.render_signal()
        t = threading.Thread(target=episode, args=(2.0,))
        t.start()
        t.join()
        assert not errors, errors
        assert contexts[2] is not mine._renderer._ctx
        np.testing.assert_array_equal(mine.render_signal(), _reference_frame(mine))


def test_a_world_dropped_without_close_gives_its_context_back():
    import gc

    sc = _scenario()
    w = build_world(sc)
    _pose(w, 100.0, 0.0)
    w.render_signal()
    ctx = w._renderer._ctx
    assert ctx.users == 1
    del w
    gc.collect()
    assert ctx.users == 0 and ctx in rc._CONTEXTS  # idle, kept for the next world


def test_a_scored_run_makes_its_fine_ground_before_the_terrain_with_no_idle_context(monkeypatch):
    """The hazard truth's texel field (an FFT of several hundred MB while it lasts) is made first, after
    freeing an idle render context, so that it never adds to a live GL context in a reused worker."""
    import bench.sim.hazard_truth as hazard_truth
    import bench.sim.run as run_module

    order = []

    class Stop(Exception):
        pass

    class FakeHazardTruth:
        def __init__(self, scenario):
            order.append("hazard truth")

    def fake_build_terrain(scenario):
        order.append("terrain")
        raise Stop

    monkeypatch.setattr(run_module, "free_shared_contexts", lambda: order.append("free idle context") or 0)
    monkeypatch.setattr(hazard_truth, "HazardTruth", FakeHazardTruth)
    monkeypatch.setattr(run_module, "build_terrain", fake_build_terrain)
    with pytest.raises(Stop):
        run_module.run(_scenario('hazard.scoring="on"'))
    assert order == ["free idle context", "hazard truth", "terrain"]
    order.clear()
    with pytest.raises(Stop):
        run_module.run(_scenario())  # unscored: nothing of the kind
    assert order == ["terrain"]


def test_gl_info_reads_the_strings_of_the_cameras_context():
    """Against PyOpenGL's own glGetString in the same context (World.gl_info calls the GL library directly)."""
    from OpenGL import GL

    with build_world(_scenario()) as world:
        assert world.gl_info() is None  # nothing rendered, no probe
        probed = world.gl_info(probe=True)
        world.render_signal()
        info = world.gl_info()
        with world._renderer.current():
            expected = {name: GL.glGetString(code).decode() for name, code in (
                ("vendor", GL.GL_VENDOR), ("renderer", GL.GL_RENDERER), ("version", GL.GL_VERSION))}
    assert info == expected == probed
    assert all(expected.values())


def test_a_frame_started_ahead_is_the_frame_and_a_stale_one_is_never_read():
    """World.start_frame hands the frame to the GL driver, render_signal reads it: the pixels of
    MuJoCo's own renderer. When the world moves in between, the frame is drawn again at the new pose
    (reading the started one would return the old view)."""
    sc = _scenario()
    with build_world(sc) as world:
        _pose(world, 300.0, 0.0)
        at_a = _reference_frame(world)
        world.start_frame()
        world.start_frame()  # the same pose: drawn once
        assert np.array_equal(world.render_signal(), at_a)
        world.start_frame()
        _pose(world, 60.0, 7.5)  # the world moves before the frame is read
        at_b = _reference_frame(world)
        assert not np.array_equal(at_a, at_b)
        assert np.array_equal(world.render_signal(), at_b)
        world.start_frame()  # a frame started and never read is dropped by the next pose's frame
        _pose(world, 20.0, -3.0)
        assert np.array_equal(world.render_signal(), _reference_frame(world))
        assert np.array_equal(world.render_signal(), _reference_frame(world))  # read twice: drawn again


def test_a_frame_started_is_drawn_again_when_another_world_drew_in_the_shared_context():
    """Two worlds over one terrain share a GL context, and so its frame buffer: a frame started by one
    is not read after the other has drawn there (it would be the other's view)."""
    sc = _scenario()
    terrain = build_terrain(sc)
    with build_world(sc, terrain) as a, build_world(sc, terrain) as b:
        _pose(a, 300.0, 0.0)
        _pose(b, 60.0, 7.5)
        want_a, want_b = _reference_frame(a), _reference_frame(b)
        a.start_frame()
        assert np.array_equal(b.render_signal(), want_b)
        assert a._renderer._ctx is b._renderer._ctx  # shared
        assert np.array_equal(a.render_signal(), want_a)


def test_camera_frame_at_draws_its_noise_while_the_frame_is_drawn_and_gives_the_same_frame():
    """SensorSuite.camera_frame_at takes the frame's normal draws ahead: the same frame as the noise
    drawn after the render, with and without an exposure gain, and without any noise."""
    from bench.sim.world_builder import build_sensors
    from models.camera import apply_detector_noise

    for extra in ([], ["camera.shot_noise=false", "camera.read_noise_dn=0"]):
        sc = _scenario(*extra)
        sensors = build_sensors(sc)
        with build_world(sc) as world:
            _pose(world, 120.0, 4.0)
            for index, gain in ((3, 1.0), (7, 0.6), (8, 1.7)):
                signal = world.render_signal()
                if gain != 1.0:
                    signal = np.clip(signal.astype(np.float32) * np.float32(gain), 0.0, 255.0)
                want = apply_detector_noise(signal, world.camera_cfg, sensors.frame_rng(index))
                assert np.array_equal(sensors.camera_frame_at(world, index, gain), want)
