"""``terrain.relief_shading = "texture"``: the whole relief shaded in the texture, the terrain drawn unlit.

MuJoCo shades a heightfield flat per triangle; with the relief's shading baked into the texture
instead, the frames have no facets, so one sample per pixel (``camera.multisampling = 0``) renders
them about as well as four. Each check is against an independent computation or the other mode.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim import terrain_cache
from bench.sim.world_builder import build_terrain, build_world, generate_scenario_terrain
from tests.conftest import SMALL_SET

TEXTURE = 'terrain.relief_shading="texture"'
RENDERER = 'terrain.relief_shading="renderer"'
HIGH_SUN = ["sun.elevation_deg=60.0", "sun.azimuth_deg=90.0"]  # few cast shadows: the shading alone


def _lommel_seeliger_of_the_geometry(terrain, el_deg: float, az_deg: float, texture_px: int) -> np.ndarray:
    """Relative brightness (flat ground = 1) of the coarse vertex heights under the sun, for a nadir view,
    at the texels: numpy's gradients, mu0 / (mu0 + mu) with the normal's length cancelling."""
    import cv2

    h = terrain.height_m.astype(float)
    spacing = terrain.size_m / (h.shape[0] - 1)
    dz_dy, dz_dx = np.gradient(h, spacing)  # rows run south to north (+y), columns west to east (+x)
    el, az = np.radians(el_deg), np.radians(az_deg)
    sx, sy, sz = np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)
    cos_i = np.clip(sz - dz_dx * sx - dz_dy * sy, 0.0, None)
    ls = cos_i / (cos_i + 1.0) * (sz + 1.0) / sz
    return cv2.resize(ls.astype(np.float32), (texture_px, texture_px), interpolation=cv2.INTER_LINEAR)


def test_the_texture_carries_the_shading_of_the_relief_the_geometry_carries():
    sets = [*SMALL_SET, *HIGH_SUN, "terrain.patch_size_m=0.0"]
    lit = generate_scenario_terrain(load_scenario(None, [*sets, RENDERER]))
    baked = generate_scenario_terrain(load_scenario(None, sets))  # the default shading
    assert not lit.relief_shaded and baked.relief_shaded
    np.testing.assert_array_equal(lit.height_m, baked.height_m)  # the same ground, only its texture differs
    # The same albedo and fine shading in both: their ratio is the coarse relief's shading.
    ok = lit.albedo > 20
    ratio = baked.albedo.astype(float) / lit.albedo.astype(float).clip(1.0)
    coarse = _lommel_seeliger_of_the_geometry(lit, 60.0, 90.0, lit.albedo.shape[0])
    assert np.corrcoef(ratio[ok], coarse[ok])[0, 1] > 0.75
    assert abs(ratio[ok].mean() - 1.0) < 0.03  # flat ground keeps its brightness
    # The renderer mode's texture leaves that relief to the renderer.
    assert abs(np.corrcoef(lit.albedo[ok].astype(float), coarse[ok])[0, 1]) < 0.15


@pytest.fixture(scope="module")
def frames():
    """Frames of both modes, 4 and 1 samples per pixel, at 400 m and 150 m over the small terrain."""
    out = {}
    for mode in ("renderer", "texture"):
        for samples in (4, 0):
            sc = load_scenario(None, [*SMALL_SET, f'terrain.relief_shading="{mode}"',
                                      f"camera.multisampling={samples}"])
            with build_world(sc, build_terrain(sc)) as world:
                shots = []
                for h in (400.0, 150.0):
                    world.reset(np.array([5.0, -3.0, h]), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
                    shots.append(world.render_signal().astype(float))
                # Dim the sun: a lit terrain darkens, an unlit one does not.
                world.model.light_diffuse[:] *= 0.5
                world.model.light_ambient[:] *= 0.5
                shots.append(world.render_signal().astype(float))
            out[mode, samples] = shots
    return out


def test_a_relief_shaded_terrain_is_drawn_unlit(frames):
    for samples in (4, 0):
        high, low, dimmed = frames["texture", samples]
        np.testing.assert_array_equal(dimmed, low)
        high, low, dimmed = frames["renderer", samples]
        assert dimmed.mean() < 0.7 * low.mean()


def test_without_facets_one_sample_per_pixel_draws_nearly_the_same_frame(frames):
    def rms(mode: str, i: int) -> float:
        return float(np.sqrt(np.mean((frames[mode, 4][i] - frames[mode, 0][i]) ** 2)))

    # At 400 m a triangle of the heightfield is a few pixels across: the lit terrain's facet edges alias
    # without multisampling (about 3 DN RMS), the unlit one's texture barely changes (well under the
    # detector's noise of about 2 DN).
    assert rms("renderer", 0) > 2.0
    assert rms("texture", 0) < 1.0 and rms("texture", 1) < 1.0
    # Both modes show flat ground about as bright.
    for i in (0, 1):
        assert frames["texture", 0][i].mean() == pytest.approx(frames["renderer", 4][i].mean(), rel=0.05)


def test_the_terrain_cache_keeps_the_mode(tmp_path):
    sc = load_scenario(None, [*SMALL_SET, TEXTURE, "terrain.patch_size_m=0.0"])
    terrain = generate_scenario_terrain(sc)
    path = tmp_path / "t.npz"
    terrain_cache.store(path, "key", terrain)
    back = terrain_cache.load(path, "key")
    assert back.relief_shaded and back.albedo.tobytes() == terrain.albedo.tobytes()


def test_the_default_camera_samples_once_over_a_texture_shaded_terrain_and_four_times_otherwise():
    """camera.multisampling = "auto" (the default) follows the terrain; a number given is kept."""
    import dataclasses
    import re

    from models.world import world_mjcf
    from tests.conftest import make_terrain

    def offsamples(*sets: str) -> int:
        sc = load_scenario(None, [*SMALL_SET, "terrain.patch_size_m=0.0", *sets])
        xml = world_mjcf(dataclasses.replace(make_terrain(np.zeros((9, 9)), 64.0, texture_px=16),
                                           relief_shaded=sc.terrain.relief_shading == "texture"),
                         sc.lander, sc.camera, sc.sun, sc.sim.physics_dt_ns / 1e9, sc.sim.gravity_mps2)
        return int(re.search(r'offsamples="(\d+)"', xml).group(1))

    assert load_scenario(None).terrain.relief_shading == "texture"
    assert offsamples() == 0
    assert offsamples(RENDERER) == 4
    assert offsamples(RENDERER, "camera.multisampling=0") == 0
    assert offsamples("camera.multisampling=4") == 4
