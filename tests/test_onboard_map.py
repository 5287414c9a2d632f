"""The onboard map product (issue 14, item 1): the region regenerated, shaded under the orbital sun, shifted."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import scipy.optimize

from bench.maps import MapTruth, build_onboard_map, draw_map_shift
from bench.scenario.seeding import COMPONENTS, component_rng
from gnc.map_nav import OnboardMap
from models.orbital_map import OrbitalMapConfig, orbital_radiance, render_orbital_map
from models.terrain import TerrainConfig, generate_surface, generate_terrain

SMALL = TerrainConfig(size_m=256.0, texture_px=1024, geometry_px=65, patch_size_m=0.0, target_clear_radius_m=20.0)
MAP = OrbitalMapConfig(size_m=192.0, georef_sigma_m=4.0)


@pytest.fixture(scope="module")
def surface():
    return generate_surface(SMALL, component_rng(3, "terrain"))


def test_surface_is_the_terrains_own(surface):
    # The terrain's geometry is the tent average of its fine DEM: recompute it with an explicit loop over vertices.
    terrain = generate_terrain(SMALL, component_rng(3, "terrain"), 30.0, 120.0)
    assert np.array_equal(terrain.craters, surface.craters) and np.array_equal(terrain.boulders, surface.boulders)
    texel, m = surface.texel_m, surface.height_m.shape[0]
    centres = -SMALL.size_m / 2 + (np.arange(m) + 0.5) * texel
    n = SMALL.geometry_px
    spacing = SMALL.size_m / (n - 1)
    for i, j in [(32, 32), (10, 50), (40, 3), (64, 64)]:
        xv, yv = -SMALL.size_m / 2 + j * spacing, -SMALL.size_m / 2 + i * spacing
        wx = np.maximum(0.0, 1.0 - np.abs(centres - xv) / spacing)
        wy = np.maximum(0.0, 1.0 - np.abs(centres - yv) / spacing)
        expect = (wy @ surface.height_m.astype(np.float64) @ wx) / (wy.sum() * wx.sum())
        assert abs(expect - float(terrain.height_m[i, j])) < 2e-3


def _register(dem_map: np.ndarray, truth_lp: np.ndarray, texel: float, size_terrain: float, size_map: float,
              spacing: float) -> np.ndarray:
    """The shift d minimising sum (map(p) - truth(p - d))^2, truth sampled with scipy (cubic), not OpenCV."""
    posts = -size_map / 2 + np.arange(dem_map.shape[0]) * spacing
    inner = slice(4, -4)  # away from the map's edge

    def cost(d, order=3):
        u = (posts - d[0] + size_terrain / 2) / texel - 0.5
        v = (posts - d[1] + size_terrain / 2) / texel - 0.5
        vv, uu = np.meshgrid(v, u, indexing="ij")
        t = scipy.ndimage.map_coordinates(truth_lp, [vv, uu], order=order, mode="nearest")
        return float(np.sum((dem_map[inner, inner] - t[inner, inner]) ** 2))

    grid = np.arange(-8.0, 8.5, 1.0)
    best = min((cost((dx, dy), order=1), (dx, dy)) for dx in grid for dy in grid)[1]
    return scipy.optimize.minimize(cost, best, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9}).x


def test_map_georeferencing_error_equals_the_drawn_shift(surface):
    onboard, truth = build_onboard_map(SMALL, 3, MAP, seed=1, surface=surface)
    shift, _ = draw_map_shift(MAP, 1)
    assert truth.shift_xy_m == shift and np.hypot(*shift) > 2.0  # a real shift is being tested
    # Stated georeferencing: the map claims to be centred on the nominal site.
    assert onboard.image_origin_xy_m == (-96.0, -96.0) and onboard.dem_origin_xy_m == (-96.0, -96.0)
    assert truth.target_xy_L_m == (-shift[0], -shift[1]) and onboard.target_xy_m == (0.0, 0.0)
    # Register the map DEM to the truth fine DEM: the best shift is the drawn one.
    texel = surface.texel_m
    truth_lp = scipy.ndimage.gaussian_filter(surface.height_m.astype(np.float64), 0.5 * 2.0 / texel, mode="reflect")
    d = _register(onboard.dem_m.astype(np.float64), truth_lp, texel, SMALL.size_m, MAP.size_m, 2.0)
    assert np.allclose(d, shift, atol=0.05), (d, shift)
    print("drawn shift", shift, "registered", d)
    # The DEM's own noise is there, and of the stated size.
    posts = -96.0 + np.arange(onboard.dem_m.shape[0]) * 2.0
    u = (posts - shift[0] + 128.0) / texel - 0.5
    v = (posts - shift[1] + 128.0) / texel - 0.5
    vv, uu = np.meshgrid(v, u, indexing="ij")
    resid = onboard.dem_m - scipy.ndimage.map_coordinates(truth_lp, [vv, uu], order=1)
    assert 0.15 < float(resid[4:-4, 4:-4].std()) < 0.25


def test_orthoimage_is_shaded_under_the_orbital_sun_and_shifted(surface):
    cfg = MAP.model_copy(update={"image_noise_dn": 0.0, "image_psf_sigma_px": 0.0})
    shift = (3.25, -1.5)
    prod = render_orbital_map(surface, cfg, shift, np.random.default_rng(0))
    assert prod.image.dtype == np.uint8 and prod.image.shape == (192, 192)
    # Independent: the radiance averaged over each 1 m pixel (4 x 4 texels) at the shifted position. With a
    # whole-texel shift the box average is exact; compare through a correlation (the Gaussian is not a box).
    rad = orbital_radiance(surface, cfg.sun_elevation_deg, cfg.sun_azimuth_deg, cfg.image_mean_dn).astype(np.float64)
    k = 4
    di, dj = int(round(-shift[1] / surface.texel_m)), int(round(-shift[0] / surface.texel_m))
    r0 = (1024 - 192 * k) // 2
    box = rad[r0 + di:r0 + di + 192 * k, r0 + dj:r0 + dj + 192 * k].reshape(192, k, 192, k).mean(axis=(1, 3))
    a = prod.image.astype(np.float64)[2:-2, 2:-2].ravel()
    b = box[2:-2, 2:-2].ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.97
    assert abs(a.mean() - b.mean()) < 1.0
    # Without the shift the agreement is clearly worse: the test sees the shift.
    box0 = rad[r0:r0 + 192 * k, r0:r0 + 192 * k].reshape(192, k, 192, k).mean(axis=(1, 3))
    assert np.corrcoef(a, box0[2:-2, 2:-2].ravel())[0, 1] < np.corrcoef(a, b)[0, 1] - 0.1
    # A different sun gives a different image of the same ground (not the renderer's baked texture).
    other = orbital_radiance(surface, 30.0, 120.0, cfg.image_mean_dn)
    assert np.corrcoef(rad.ravel()[::7], other.ravel()[::7])[0, 1] < 0.8


def test_map_stream_is_its_own():
    # Appended after the streams before it (the faults' came next), so every existing stream keeps its index.
    assert COMPONENTS.index("map") == 8 and COMPONENTS.index("vision") == 7 and COMPONENTS.index("faults") == 9
    cfg = OrbitalMapConfig(georef_sigma_m=3.0)
    shift, _ = draw_map_shift(cfg, 5)
    expect = np.random.default_rng(np.random.SeedSequence(5, spawn_key=(8,))).spawn(2)[0].normal(0.0, 1.0, 2) * 3.0
    assert np.allclose(shift, expect)
    zero, _ = draw_map_shift(cfg.model_copy(update={"georef_sigma_m": 0.0}), 5)
    assert zero == (0.0, 0.0)


def test_map_is_plain_data_for_the_flight_software(surface):
    onboard, truth = build_onboard_map(SMALL, 3, MAP, seed=2, surface=surface)
    assert isinstance(onboard, OnboardMap) and isinstance(truth, MapTruth)
    fields = set(vars(onboard))
    assert not {"shift_xy_m", "target_xy_L_m"} & fields
    for v in vars(onboard).values():
        assert isinstance(v, (np.ndarray, float, tuple)), type(v)
    # The DEM lookup agrees with an explicit bilinear interpolation.
    x, y = 13.7, -42.3
    u, v = (x + 96.0) / 2.0, (y + 96.0) / 2.0
    j, i = int(u), int(v)
    fu, fv = u - j, v - i
    h = onboard.dem_m.astype(np.float64)
    expect = (1 - fv) * ((1 - fu) * h[i, j] + fu * h[i, j + 1]) + fv * ((1 - fu) * h[i + 1, j] + fu * h[i + 1, j + 1])
    assert abs(float(onboard.dem_height(x, y)) - expect) < 1e-9


def test_map_larger_than_the_terrain_is_refused(surface):
    with pytest.raises(ValueError, match="onboard_map.size_m=300"):
        render_orbital_map(surface, MAP.model_copy(update={"size_m": 300.0}), (0.0, 0.0), np.random.default_rng(0))
    with pytest.raises(ValueError, match="whole number"):
        render_orbital_map(surface, MAP.model_copy(update={"size_m": 191.0}), (0.0, 0.0), np.random.default_rng(0))


def test_map_settings_are_dispersible_in_the_scenario():
    from bench.scenario import apply_dispersions, load_scenario

    s = load_scenario(None, ['dispersions."onboard_map.sun_azimuth_deg" = {dist = "uniform", low = 150.0, high = 250.0}',
                             'dispersions."onboard_map.georef_sigma_m" = {dist = "uniform", low = 1.0, high = 3.0}'])
    case, drawn = apply_dispersions(s, np.random.default_rng(4))
    assert case.onboard_map.sun_azimuth_deg == drawn["onboard_map.sun_azimuth_deg"]
    assert 150.0 <= case.onboard_map.sun_azimuth_deg <= 250.0 and 1.0 <= case.onboard_map.georef_sigma_m <= 3.0
