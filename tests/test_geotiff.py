"""Real sites: GeoTIFF DEMs (the optional 'geo' extra), cropped around a target in the file's coordinates."""

from __future__ import annotations

import math

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")  # the 'geo' extra
from rasterio.crs import CRS  # noqa: E402
from rasterio.transform import from_origin  # noqa: E402

from bench.cli import main  # noqa: E402
from bench.scenario import ScenarioError, load_scenario  # noqa: E402
from bench.sim.run import run  # noqa: E402
from models.terrain import TerrainConfig, generate_terrain, load_geotiff  # noqa: E402

# A local polar stereographic on the lunar sphere, as a LOLA south-pole product uses.
MOON_SPS = "+proj=stere +lat_0=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs"
X0, Y_TOP, RES = 20_000.0, -40_000.0, 5.0  # upper-left corner of the raster in the file's metres
ROWS, COLS = 121, 141


def relief(x, y):
    """Heights of the synthetic site in the file's coordinates [m] (smooth, resolved by 5 m posts)."""
    return -1800.0 + 0.02 * (x - X0) + 6.0 * np.sin(2 * np.pi * (x - X0) / 300.0) * np.cos(2 * np.pi * y / 260.0)


def post_xy(rows=ROWS, cols=COLS, res_x=RES, res_y=RES):
    c, r = np.meshgrid(np.arange(cols), np.arange(rows))
    return X0 + (c + 0.5) * res_x, Y_TOP - (r + 0.5) * res_y


def write_tif(path, heights, crs=MOON_SPS, res_x=RES, res_y=RES, nodata=-9999.0):
    with rasterio.open(path, "w", driver="GTiff", height=heights.shape[0], width=heights.shape[1], count=1,
                       dtype="float32", crs=CRS.from_string(crs) if crs else None,
                       transform=from_origin(X0, Y_TOP, res_x, res_y), nodata=nodata) as ds:
        ds.write(heights.astype(np.float32), 1)
    return path


@pytest.fixture
def site(tmp_path):
    x, y = post_xy()
    return write_tif(tmp_path / "site.tif", relief(x, y))


def test_spacing_extent_and_crop_come_from_the_file(site):
    # Target: a point between posts, snapped to the nearest post (row 47, col 83).
    target = (X0 + 83.5 * RES + 1.2, Y_TOP - 47.5 * RES - 2.0)
    heights, spacing = load_geotiff(site, target, 200.0, 1.0)
    assert spacing == RES and heights.shape == (41, 41)
    x, y = post_xy()
    expect = relief(x, y)[47 - 20:47 + 21, 83 - 20:83 + 21].astype(np.float32)  # north-up, as stored
    np.testing.assert_array_equal(heights, expect.astype(np.float64))
    # Unset tile: the largest square around the target that fits (47 rows to the north edge).
    assert load_geotiff(site, target, None)[0].shape == (95, 95)
    # The configuration takes the spacing from the file and centres the terrain on the target post.
    cfg = TerrainConfig(kind="dem", dem_path=site, dem_target_xy=target, dem_tile_m=200.0, geometry_px=41,
                        texture_px=512, crater_density_per_km2=0.0, roughness_rms_m=0.0, boulder_density_per_km2=0.0,
                        patch_size_m=0.0)
    assert cfg.dem_spacing_m == RES
    t = generate_terrain(cfg, np.random.default_rng(0), 30.0, 120.0)
    assert t.size_m == pytest.approx(200.0)
    xt, yt = X0 + 83.5 * RES, Y_TOP - 47.5 * RES
    for dx, dy in ((0.0, 0.0), (50.0, 0.0), (0.0, 50.0), (-35.0, -60.0)):
        assert t.height_at(dx, dy) == pytest.approx(relief(xt + dx, yt + dy) - relief(xt, yt), abs=0.05)


@pytest.mark.parametrize("kind, needle", [
    ("degrees", "in degrees"), ("anisotropic", "not square"), ("no_crs", "no coordinate reference system"),
])
def test_unusable_rasters_are_refused_with_how_to_reproject(tmp_path, kind, needle):
    if kind == "degrees":
        path = write_tif(tmp_path / "deg.tif", np.zeros((40, 40)), crs="EPSG:4326", res_x=0.001, res_y=0.001)
    elif kind == "anisotropic":
        path = write_tif(tmp_path / "aniso.tif", np.zeros((40, 40)), res_x=5.0, res_y=10.0)
    else:
        path = write_tif(tmp_path / "nocrs.tif", np.zeros((40, 40)), crs=None)
    with pytest.raises(ScenarioError) as err:
        load_scenario(None, ['terrain.kind="dem"', f'terrain.dem_path="{path}"'])
    msg = str(err.value)
    assert needle in msg and "gdalwarp -t_srs" in msg and "\n" not in msg


def test_target_outside_tile_too_large_and_nodata_are_refused(tmp_path, site):
    x, y = post_xy()
    h = relief(x, y)
    h[60, 70] = -9999.0  # a void near the centre
    holes = write_tif(tmp_path / "holes.tif", h)
    for path, sets, needle in (
        (site, ["terrain.dem_target_xy=[0.0, 0.0]"], "outside the raster"),
        (site, ["terrain.dem_tile_m=5000.0"], "does not fit"),
        (holes, [], "nodata"),
        (site, ["terrain.dem_spacing_m=4.0"], "differs from the GeoTIFF"),
    ):
        with pytest.raises(ScenarioError, match=needle):
            load_scenario(None, ['terrain.kind="dem"', f'terrain.dem_path="{path}"', *sets])


def test_nan_voids_declared_as_nodata_are_counted_once(tmp_path):
    x, y = post_xy()
    h = relief(x, y)
    h[59:62, 69:72] = np.nan  # a 3 x 3 void of NaN, NaN declared as nodata: 9 posts, not 18
    path = write_tif(tmp_path / "nan.tif", h, nodata=np.nan)
    with pytest.raises(ScenarioError, match=r": 9 nodata or non-finite posts"):
        load_scenario(None, ['terrain.kind="dem"', f'terrain.dem_path="{path}"'])


def test_the_onboard_map_size_suggestion_fits_both_grids():
    # image 0.7 m and posts 2 m: 768 fits neither; the suggestion was 768 (posts only), refused again.
    with pytest.raises(ScenarioError, match=r"e\.g\. 770$"):
        load_scenario(None, ["onboard_map.image_res_m=0.7"])
    load_scenario(None, ["onboard_map.image_res_m=0.7", "onboard_map.size_m=770.0"])


def test_a_degree_raster_gives_one_error_line_and_writes_nothing(tmp_path, capsys):
    path = write_tif(tmp_path / "deg.tif", np.zeros((40, 40)), crs="EPSG:4326", res_x=0.001, res_y=0.001)
    out = tmp_path / "out"
    assert main(["run", "--out", str(out), "--set", 'terrain.kind="dem"', "--set", f'terrain.dem_path="{path}"']) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("landbench: error:") and "gdalwarp -t_srs" in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["deg.tif"]


def test_a_geotiff_site_flies_and_lands(site):
    target = (X0 + 70.5 * RES, Y_TOP - 60.5 * RES)
    sc = load_scenario(None, ['nav="truth"', 'vision="off"', "camera.enabled=false", 'terrain.kind="dem"',
                              f'terrain.dem_path="{site}"', f"terrain.dem_target_xy=[{target[0]}, {target[1]}]",
                              "terrain.dem_tile_m=400.0", "terrain.geometry_px=81", "terrain.texture_px=1024",
                              "terrain.patch_size_m=0.0",
                              "initial.r_BL_L_m=[4.0, -3.0, 12.0]", "initial.v_BL_L_mps=[0.0, 0.0, -1.0]"])
    s = run(sc).summary
    assert s["outcome"] == "landed", s["outcome"]
    assert s["touchdown"]["miss_distance_m"] < 1.0


def test_block_averaging_the_terrain_back_to_the_dem_spacing_gives_the_dem(tmp_path):
    # Synthetic detail is added only below the DEM's resolution: averaging the flown surface over each
    # DEM post's cell (trapezoidal, the geometry 4x finer than the DEM) gives the DEM back, after its
    # mean offset (the unresolved crater bowls' volume). Measured: RMS 0.032 m with 2 m RMS of fBm,
    # 0.155 m with the default craters (up to 2 spacings across, 3 m deep) and boulders on top; the
    # stated tolerances are 0.05 m and 0.3 m.
    spacing, n, k = 8.0, 65, 4
    yy, xx = np.mgrid[0:n, 0:n] * spacing
    dem = 10.0 * np.sin(xx / 90.0) + 6.0 * np.cos(yy / 70.0)
    np.save(tmp_path / "d.npy", dem)
    ref = np.flipud(dem) - dem[(n - 1) // 2, (n - 1) // 2]  # south-up, zero at the target
    w = np.array([0.5, 1.0, 1.0, 1.0, 0.5]) / k  # the cell [-s/2, s/2] by the trapezoidal rule
    kernel = np.outer(w, w)
    bare = dict(kind="dem", dem_path=tmp_path / "d.npy", dem_spacing_m=spacing, geometry_px=k * (n - 1) + 1,
                texture_px=2048, patch_size_m=0.0)
    h0 = generate_terrain(TerrainConfig(**bare, roughness_rms_m=0.0, crater_density_per_km2=0.0,
                                        boulder_density_per_km2=0.0), np.random.default_rng(0), 30.0, 120.0).height_m
    for extra, bound in (({"crater_density_per_km2": 0.0, "boulder_density_per_km2": 0.0}, 0.05), ({}, 0.3)):
        cfg = TerrainConfig(**bare, roughness_rms_m=2.0, **extra)
        h = generate_terrain(cfg, np.random.default_rng(0), 30.0, 120.0).height_m.astype(np.float64)
        inner = range(2, n - 2)
        avg = np.array([[np.sum(kernel * h[i * k - 2:i * k + 3, j * k - 2:j * k + 3]) for j in inner] for i in inner])
        diff = avg - ref[2:-2, 2:-2]
        rms = math.sqrt(np.mean((diff - diff.mean()) ** 2))
        assert rms < bound, (extra, rms)
        assert abs(diff.mean()) < 0.3, diff.mean()
        assert np.std(h - h0) > 0.05  # there is detail at the geometry scale (measured 0.08 m and 0.26 m)
