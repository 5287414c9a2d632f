"""Tests of models/terrain.py, each against an independent computation.

Small tiles (texture_px 256-1024) keep the file fast; the default config is
generated once, because the texture test is about the defaults themselves.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import scipy.integrate
import scipy.interpolate
import scipy.optimize
from pydantic import ValidationError

from models.terrain import (
    CRATER_SUPPORT_R,
    Terrain,
    TerrainConfig,
    crater_profile,
    fbm_surface,
    generate_terrain,
    load_dem,
)

SUN_EL_DEG, SUN_AZ_DEG = 30.0, 120.0
# Small, quick tile: 1024 m at 2 m/texel.
SMALL = dict(texture_px=512)
# No relief but the craters under test.
BARE = dict(roughness_rms_m=0.0, boulder_density_per_km2=0.0, albedo_contrast=0.0)
POISSON_SIGMAS = 3.0


def make(seed: int = 0, el: float = SUN_EL_DEG, az: float = SUN_AZ_DEG, **overrides) -> Terrain:
    return generate_terrain(TerrainConfig(**overrides), np.random.default_rng(seed), el, az)


@pytest.fixture(scope="module")
def default_terrain() -> Terrain:
    return make(seed=7)


# ------------------------------------------------------------------ seeding
def test_same_seed_is_bit_identical_and_other_seed_differs():
    a, b, c = make(1, **SMALL), make(1, **SMALL), make(2, **SMALL)
    for name in ("height_m", "albedo", "craters", "boulders"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        x, z = getattr(a, name), getattr(c, name)
        assert x.shape != z.shape or not np.array_equal(x, z), f"{name} did not change with the seed"


def test_parts_draw_from_independent_streams():
    base = make(3, **SMALL)
    fewer_boulders = make(3, **SMALL, boulder_density_per_km2=50.0)
    rougher = make(3, **SMALL, roughness_rms_m=5.0)
    np.testing.assert_array_equal(base.craters, fewer_boulders.craters)
    np.testing.assert_array_equal(base.craters, rougher.craters)
    np.testing.assert_array_equal(base.boulders, rougher.boulders)
    assert len(fewer_boulders.boulders) < len(base.boulders)
    more_craters = make(3, **SMALL, crater_density_per_km2=3.0e4)
    np.testing.assert_array_equal(base.boulders, more_craters.boulders)
    assert len(more_craters.craters) > len(base.craters)


# --------------------------------------------------------------- craters
def test_crater_counts_follow_the_configured_power_law():
    cfg = TerrainConfig(**SMALL)  # default mare population: ~2e4 craters on the tile
    t = generate_terrain(cfg, np.random.default_rng(11), SUN_EL_DEG, SUN_AZ_DEG)
    d = t.craters[:, 2]
    b, d_min, d_max = cfg.crater_sfd_exponent, cfg.crater_min_diameter_m, cfg.crater_max_diameter_m
    lam_per_m2 = cfg.crater_density_per_km2 / 1e6
    area_m2, clear = cfg.size_m**2, cfg.target_clear_radius_m
    assert len(d) > 10_000
    assert d.min() >= d_min and d.max() < d_max

    def expected_at_least(dd: float) -> float:
        # Untruncated law N(>=D) = lam (D/Dmin)^-b, cut at Dmax, minus craters
        # removed because their rim reaches the target circle.
        pdf = lambda x: lam_per_m2 * b * d_min**b * x ** (-b - 1)  # noqa: E731
        return scipy.integrate.quad(lambda x: pdf(x) * (area_m2 - math.pi * (clear + x / 2) ** 2), dd, d_max)[0]

    for dd in (2.0, 4.0, 8.0, 16.0, 32.0, 64.0):
        n_exp = expected_at_least(dd)
        n_obs = int(np.count_nonzero(d >= dd))
        assert abs(n_obs - n_exp) <= POISSON_SIGMAS * math.sqrt(n_exp), (dd, n_obs, n_exp)

    # Maximum-likelihood exponent of a Pareto truncated to [Dmin, Dmax).
    log_sum = np.log(d).sum()
    n = len(d)

    def score(bb: float) -> float:
        a_min, a_max = d_min**-bb, d_max**-bb
        dnorm = (-math.log(d_min) * a_min + math.log(d_max) * a_max) / (a_min - a_max)
        return n / bb - log_sum - n * dnorm

    b_hat = scipy.optimize.brentq(score, 0.5, 5.0)
    sigma_b = b / math.sqrt(n)
    assert abs(b_hat - b) < 4 * sigma_b + 0.01, (b_hat, b)


def test_crater_profile_shape():
    d, hr = 0.2, 0.04
    assert crater_profile(np.array(0.0), d, hr) == pytest.approx(-d, abs=1e-12)
    assert crater_profile(np.array(1.0), d, hr) == pytest.approx(hr, abs=1e-12)
    r = np.linspace(0.0, 4.0, 40_001)
    h = crater_profile(r, d, hr)
    assert r[np.argmax(h)] == pytest.approx(1.0, abs=1e-3)
    assert h.max() == pytest.approx(hr, abs=1e-9)
    inside, outside = h[r <= 1.0], h[(r >= 1.0) & (r <= CRATER_SUPPORT_R)]
    assert np.all(np.diff(inside) > 0) and np.all(np.diff(outside) < 0)
    assert abs(h[np.searchsorted(r, 1.0 + 1e-3)] - hr) < 1e-3  # continuous at the rim
    assert np.all(h[r >= CRATER_SUPPORT_R] == 0.0)
    assert 0.0 < crater_profile(np.array(1.5), d, hr) < hr  # ejecta blanket
    assert np.array_equal(crater_profile(-r, d, hr), h)


def _isolated_craters(t: Terrain) -> list[int]:
    """Craters whose support touches no other crater's, nor the tile edge, nor the origin (the datum)."""
    cat = t.craters
    support = CRATER_SUPPORT_R * cat[:, 2] / 2
    if np.any(np.hypot(cat[:, 0], cat[:, 1]) <= support):
        return []
    out = []
    for k, (xc, yc, _) in enumerate(cat):
        others = np.delete(np.arange(len(cat)), k)
        gap = np.hypot(cat[others, 0] - xc, cat[others, 1] - yc) - support[others] - support[k]
        if np.all(gap > 0) and max(abs(xc), abs(yc)) + support[k] < t.size_m / 2:
            out.append(k)
    return out


def test_stamped_isolated_crater_has_its_bowl_at_the_catalog_position():
    # 1 m vertices, 0.25 m texels, ~3 fresh craters of 30-40 m, nothing else.
    cfg = dict(size_m=256.0, geometry_px=257, texture_px=1024, crater_density_per_km2=100.0,
               crater_min_diameter_m=30.0, crater_max_diameter_m=40.0, crater_freshness_min=1.0,
               target_clear_radius_m=5.0, **BARE)
    t, isolated = next((t, iso) for t in (make(s, **cfg) for s in range(20)) if (iso := _isolated_craters(t)))
    for k in isolated:
        xc, yc, dk = t.craters[k]
        assert t.height_at(xc, yc) == pytest.approx(-0.2 * dk, rel=0.02)
        # Radial cuts along +x and -y vs the analytic profile, away from the rim
        # cusp (which the 1 m vertex average rounds off).
        rho = np.linspace(0.0, 1.2 * CRATER_SUPPORT_R, 61)
        keep = np.abs(rho - 1.0) > 0.15
        expected = crater_profile(rho, 0.2, 0.04) * dk
        tol = 0.01 * 0.2 * dk
        np.testing.assert_allclose(t.height_at(xc + rho * dk / 2, yc)[keep], expected[keep], atol=tol)
        np.testing.assert_allclose(t.height_at(xc, yc - rho * dk / 2)[keep], expected[keep], atol=tol)
        # The deepest vertex nearby is at the catalog centre (row ~ y, column ~ x).
        n, w = t.height_m.shape[0], 10
        i_c, j_c = round(yc / t.spacing_m + (n - 1) / 2), round(xc / t.spacing_m + (n - 1) / 2)
        win = t.height_m[i_c - w:i_c + w + 1, j_c - w:j_c + w + 1]
        di, dj = np.unravel_index(np.argmin(win), win.shape)
        assert abs(di - w) <= 1 and abs(dj - w) <= 1


def test_target_area_is_clear_of_craters_and_boulders():
    for clear in (15.0, 60.0):
        t = make(4, **SMALL, target_clear_radius_m=clear, boulder_density_per_km2=5000.0)
        for name, cat in (("craters", t.craters), ("boulders", t.boulders)):
            edge = np.hypot(cat[:, 0], cat[:, 1]) - cat[:, 2] / 2
            assert len(cat) > 100 and edge.min() >= clear, name
    # Not vacuous: without the clearing, features do overlap that circle.
    t = make(4, **SMALL, target_clear_radius_m=0.0, boulder_density_per_km2=5000.0)
    assert np.any(np.hypot(t.craters[:, 0], t.craters[:, 1]) - t.craters[:, 2] / 2 < 60.0)


# ------------------------------------------------------------------- fBm
def radial_psd_slope(z: np.ndarray, spacing_m: float, k_lo: float, k_hi: float) -> float:
    """Log-log slope of the radially averaged periodogram between k_lo and k_hi [cycles/m]."""
    n = z.shape[0]
    p = np.abs(np.fft.fft2(z - z.mean())) ** 2
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n, spacing_m), np.fft.fftfreq(n, spacing_m)))
    edges = np.geomspace(k_lo, k_hi, 16)
    idx = np.digitize(k.ravel(), edges)
    kc = [k.ravel()[idx == i].mean() for i in range(1, len(edges))]
    pc = [p.ravel()[idx == i].mean() for i in range(1, len(edges))]
    return float(np.polyfit(np.log(kc), np.log(pc), 1)[0])


@pytest.mark.parametrize("hurst", [0.4, 0.8])
def test_fbm_rms_and_spectral_slope(hurst):
    n, spacing = 512, 0.5
    z = fbm_surface(n, spacing, 2.0, hurst, np.random.default_rng(9))
    assert z.dtype == np.float32 and z.shape == (n, n)
    assert z.std() == pytest.approx(2.0, rel=1e-3)
    k_fund, k_nyq = 1.0 / (n * spacing), 0.5 / spacing
    slope = radial_psd_slope(z.astype(np.float64), spacing, 3 * k_fund, 0.7 * k_nyq)
    assert slope == pytest.approx(-(2 * hurst + 2), abs=0.1)


def test_terrain_roughness_matches_config():
    rms, hurst = 3.0, 0.8
    t = make(6, texture_px=1024, geometry_px=257, crater_density_per_km2=0.0, boulder_density_per_km2=0.0,
             roughness_rms_m=rms, roughness_hurst=hurst)
    assert len(t.craters) == 0 and len(t.boulders) == 0
    # The geometry is the fine fBm averaged over 4 m cells: the power lost at
    # those scales is < 1e-3 of the total for H = 0.8.
    assert t.height_m.std() == pytest.approx(rms, rel=0.03)
    k_fund = 1.0 / t.size_m
    slope = radial_psd_slope(t.height_m.astype(np.float64), t.spacing_m, 3 * k_fund, 0.15 / t.spacing_m)
    assert slope == pytest.approx(-(2 * hurst + 2), abs=0.2)


# -------------------------------------------------------------- height_at
def test_height_at_is_bilinear_and_zero_at_the_origin():
    t = make(8, **SMALL, geometry_px=65)
    n, half = t.height_m.shape[0], t.size_m / 2
    assert t.height_at(0.0, 0.0) == 0.0
    axis = np.linspace(-half, half, n)
    # Vertices: height_m[i, j] sits at (x_j, y_i), row index along +y.
    jj, ii = np.meshgrid(np.arange(n), np.arange(n))
    np.testing.assert_array_equal(t.height_at(axis[jj], axis[ii]), t.height_m.astype(np.float64))
    # Mid-cells: mean of the four corners.
    mid = (axis[:-1] + axis[1:]) / 2
    xm, ym = np.meshgrid(mid, mid)
    h = t.height_m.astype(np.float64)
    corners = (h[:-1, :-1] + h[:-1, 1:] + h[1:, :-1] + h[1:, 1:]) / 4
    np.testing.assert_allclose(t.height_at(xm, ym), corners, rtol=0, atol=1e-9)
    # Random points vs SciPy's linear interpolator (grid axes are (y, x)).
    ref = scipy.interpolate.RegularGridInterpolator((axis, axis), h, method="linear")
    rng = np.random.default_rng(0)
    pts = rng.uniform(-half, half, size=(1000, 2))
    np.testing.assert_allclose(t.height_at(pts[:, 0], pts[:, 1]), ref(pts[:, ::-1]), atol=1e-9)
    # Broadcasting.
    assert t.height_at(np.zeros((3, 1)), np.zeros((1, 4))).shape == (3, 4)


# ------------------------------------------------------------------ texture
def local_std(img: np.ndarray, win: int) -> np.ndarray:
    m = img.shape[0] // win * win
    blocks = img[:m, :m].astype(np.float64).reshape(m // win, win, m // win, win)
    return blocks.std(axis=(1, 3))


STD_FLOOR_DN = 3.0  # well above uint8 quantisation noise (0.29 DN)


def _check_texture(t: Terrain, cfg: TerrainConfig) -> np.ndarray:
    """Shape, dtype, brightness and clipping of a texture, and detail everywhere in the target area (the
    central 32 m x 32 m, 128 texels, seen at ~30 m altitude); returns the 8x8 blocks' DN standard deviations."""
    assert t.albedo.dtype == np.uint8 and t.albedo.shape == (cfg.texture_px, cfg.texture_px)
    assert t.height_m.dtype == np.float32 and t.height_m.shape == (cfg.geometry_px, cfg.geometry_px)
    assert 110 <= t.albedo.mean() <= 140
    assert np.mean(t.albedo == 255) < 0.005 and np.mean(t.albedo == 0) < 0.005
    c, half = cfg.texture_px // 2, 64
    s_target = local_std(t.albedo[c - half:c + half, c - half:c + half], 8)
    assert np.mean(s_target > STD_FLOOR_DN) >= 0.99
    return local_std(t.albedo, 8)


def test_default_texture_has_detail_everywhere_but_in_cast_shadows(default_terrain):
    """The default texture carries the whole relief's shading and cast shadows (relief_shading="texture"):
    it has detail wherever the sun reaches, which is told from the physical surface regenerated without
    the texture (its fine DEM's cast shadows), and everywhere around the target."""
    from models.terrain import _lit_fraction, _sun_vector, generate_surface

    t, cfg = default_terrain, TerrainConfig()
    assert cfg.relief_shading == "texture" and t.relief_shaded
    s = _check_texture(t, cfg)
    surface = generate_surface(cfg, np.random.default_rng(7))
    lit = _lit_fraction(surface.height_m, surface.size_m / cfg.texture_px, _sun_vector(SUN_EL_DEG, SUN_AZ_DEG))
    m = lit.shape[0] // 8 * 8
    sunlit = lit[:m, :m].reshape(m // 8, 8, m // 8, 8).min(axis=(1, 3)) > 0.99  # blocks wholly in the sun
    assert sunlit.mean() > 0.8  # the mask is not degenerate: most of the ground is lit at 30 deg
    assert np.mean(s[sunlit] > STD_FLOOR_DN) >= 0.99


def test_a_renderer_shaded_texture_has_detail_everywhere():
    """With relief_shading="renderer" the texture carries the fine detail's shading and shadows only (the
    renderer shades the coarse relief, without cast shadows): detail everywhere."""
    t, cfg = make(seed=7, relief_shading="renderer"), TerrainConfig(relief_shading="renderer")
    assert not t.relief_shaded
    s = _check_texture(t, cfg)
    assert np.mean(s > STD_FLOOR_DN) >= 0.99


def test_texture_has_detail_with_a_high_sun():
    # Same 0.25 m texels on a smaller tile; at noon only the albedo carries detail.
    t = make(2, el=90.0, size_m=256.0, texture_px=1024)
    s = local_std(t.albedo, 8)
    assert np.mean(s > STD_FLOOR_DN) >= 0.99
    assert 110 <= t.albedo.mean() <= 140


def test_baked_shading_follows_the_sun_direction():
    cfg = dict(size_m=128.0, geometry_px=33, texture_px=512, crater_density_per_km2=250.0,
               crater_min_diameter_m=12.0, crater_max_diameter_m=14.0, crater_freshness_min=1.0,
               crater_fresh_albedo_gain=0.0, target_clear_radius_m=5.0, bake_cast_shadows="none", **BARE)
    for az, axis_name in ((90.0, "x"), (0.0, "y")):
        t = make(1, el=40.0, az=az, **cfg)
        assert len(t.craters) >= 1
        xc, yc, dk = t.craters[0]
        texel = t.size_m / t.albedo.shape[0]
        centres = (np.arange(t.albedo.shape[0]) + 0.5) * texel - t.size_m / 2
        x, y = np.meshgrid(centres, centres)  # rows are +y
        r = np.hypot(x - xc, y - yc)
        wall = (r > 0.3 * dk / 2) & (r < 0.9 * dk / 2)
        toward_sun = (x > xc) if axis_name == "x" else (y > yc)
        # The inner wall on the sun's side faces away from it: darker.
        dark = t.albedo[wall & toward_sun].mean()
        bright = t.albedo[wall & ~toward_sun].mean()
        assert bright > dark + 20, (az, bright, dark)


def test_cast_shadows_fall_away_from_the_sun():
    cfg = dict(size_m=128.0, geometry_px=17, texture_px=512, crater_density_per_km2=0.0,
               boulder_density_per_km2=2000.0, boulder_min_diameter_m=3.0, boulder_max_diameter_m=3.1,
               target_clear_radius_m=5.0, roughness_rms_m=0.0, albedo_contrast=0.0)

    def strips(shadows: str) -> tuple[float, float]:
        t = next(t for t in (make(s, el=10.0, az=90.0, bake_cast_shadows=shadows, **cfg) for s in range(20))
                 if len(t.boulders) == 1 and np.all(np.abs(t.boulders[0, :2]) < t.size_m / 2 - 10))
        xb, yb, _ = t.boulders[0]
        texel = t.size_m / t.albedo.shape[0]
        centres = (np.arange(t.albedo.shape[0]) + 0.5) * texel - t.size_m / 2
        x, y = np.meshgrid(centres, centres)
        band = np.abs(y - yb) < 0.3
        west = t.albedo[band & (x < xb - 2.5) & (x > xb - 4.5)].mean()  # lee side, beyond the bump
        east = t.albedo[band & (x > xb + 2.5) & (x < xb + 4.5)].mean()
        return west, east

    west, east = strips("residual")
    assert west < 0.4 * east, (west, east)
    west, east = strips("none")
    assert west > 0.8 * east, (west, east)


def test_sun_elevation_is_validated():
    with pytest.raises(ValueError, match="sun_elevation_deg"):
        make(0, el=0.0, **SMALL)


# --------------------------------------------------------------------- DEM
def test_load_dem_round_trips_npy_and_16bit_png(tmp_path):
    rng = np.random.default_rng(0)
    heights = rng.normal(size=(20, 30)).astype(np.float32)
    np.save(tmp_path / "d.npy", heights)
    np.testing.assert_array_equal(load_dem(tmp_path / "d.npy", 2.0), heights.astype(np.float64))
    np.testing.assert_array_equal(load_dem(tmp_path / "d.npy", 2.0, z_scale_m=0.5), heights * 0.5)
    dn = rng.integers(0, 65536, size=(24, 17), dtype=np.uint16)
    assert cv2.imwrite(str(tmp_path / "d.png"), dn)
    np.testing.assert_array_equal(load_dem(tmp_path / "d.png", 2.0, z_scale_m=0.01), dn * 0.01)


def _write_bad(tmp_path, case: str):
    if case == "missing":
        return tmp_path / "nope.npy", "not found"
    if case == "8-bit png":
        cv2.imwrite(str(tmp_path / "b.png"), np.zeros((32, 32), np.uint8))
        return tmp_path / "b.png", "16-bit"
    if case == "rgb png":
        cv2.imwrite(str(tmp_path / "c.png"), np.zeros((32, 32, 3), np.uint16))
        return tmp_path / "c.png", "2-D"
    if case == "3-d array":
        np.save(tmp_path / "c.npy", np.zeros((32, 32, 2)))
        return tmp_path / "c.npy", "2-D"
    if case == "nan":
        a = np.zeros((32, 32))
        a[3, 4] = np.nan
        np.save(tmp_path / "n.npy", a)
        return tmp_path / "n.npy", "non-finite"
    if case == "tiny":
        np.save(tmp_path / "t.npy", np.zeros((8, 64)))
        return tmp_path / "t.npy", "too small"
    if case == "complex":
        np.save(tmp_path / "x.npy", np.zeros((32, 32), complex))
        return tmp_path / "x.npy", "dtype"
    if case in ("garbage npy", "garbage png"):
        p = tmp_path / ("g.npy" if case == "garbage npy" else "g.png")
        p.write_bytes(b"\x00not an image or array" * 10)
        return p, "cannot be"
    if case == "wrong suffix":
        p = tmp_path / "d.tif"
        p.write_bytes(b"x")
        return p, "unsupported"
    raise AssertionError(case)


BAD_CASES = ["missing", "8-bit png", "rgb png", "3-d array", "nan", "tiny", "complex", "garbage npy",
             "garbage png", "wrong suffix"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_load_dem_rejects_bad_files(tmp_path, case):
    path, problem = _write_bad(tmp_path, case)
    with pytest.raises(ValueError) as err:
        load_dem(path, 1.0)
    assert str(path) in str(err.value) and problem in str(err.value)


@pytest.mark.parametrize("case", ["missing", "nan", "garbage png"])
def test_dem_config_rejects_bad_files_at_validation(tmp_path, case):
    path, problem = _write_bad(tmp_path, case)
    with pytest.raises(ValidationError) as err:
        TerrainConfig(kind="dem", dem_path=path, dem_spacing_m=1.0)
    assert "dem_path" in str(err.value) and problem in str(err.value)


def test_dem_terrain_keeps_orientation_extent_and_shape(tmp_path):
    spacing, rows, cols = 4.0, 101, 121  # cropped to the central 101 x 101
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    # Stored north-up: row 0 is the north edge. Smooth relief the geometry resolves.
    x_m = (xx - (cols - 1) / 2) * spacing
    y_m = ((rows - 1) / 2 - yy) * spacing
    f = lambda x, y: 0.05 * y + 8.0 * np.sin(2 * np.pi * x / 200.0)  # noqa: E731
    np.save(tmp_path / "dem.npy", f(x_m, y_m))
    cfg = TerrainConfig(kind="dem", dem_path=tmp_path / "dem.npy", dem_spacing_m=spacing, geometry_px=101,
                        texture_px=512, crater_density_per_km2=0.0, **BARE)
    t = generate_terrain(cfg, np.random.default_rng(0), SUN_EL_DEG, SUN_AZ_DEG)
    assert t.size_m == pytest.approx(spacing * (rows - 1))
    assert t.height_at(0.0, 0.0) == 0.0
    axis = np.linspace(-t.size_m / 2, t.size_m / 2, t.height_m.shape[0])
    xg, yg = np.meshgrid(axis, axis)
    inner = (slice(5, -5), slice(5, -5))  # away from the edge-clamped border
    np.testing.assert_allclose(t.height_m[inner], (f(xg, yg) - f(0.0, 0.0))[inner], atol=0.05)


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(geometry_px=128), "geometry_px"),
        (dict(texture_px=128, geometry_px=129), "texture_px"),
        (dict(crater_max_diameter_m=1.0), "crater_max_diameter_m"),
        (dict(boulder_max_diameter_m=0.1), "boulder_max_diameter_m"),
        (dict(target_clear_radius_m=600.0), "target_clear_radius_m"),
        (dict(dem_spacing_m=1.0), "kind='dem'"),
        (dict(kind="dem"), "dem_path"),
        (dict(roughness_hurst=1.5), "roughness_hurst"),
        (dict(unknown_field=1), "unknown_field"),
    ],
)
def test_config_rejects_bad_values(overrides, field):
    with pytest.raises(ValidationError) as err:
        TerrainConfig(**overrides)
    assert field in str(err.value)


def test_terrain_arrays_are_read_only():
    t = make(0, **SMALL)
    with pytest.raises(ValueError):
        t.height_m[0, 0] = 1.0
    with pytest.raises(ValueError):
        t.albedo[0, 0] = 1


@pytest.mark.parametrize("sets", [
    {},  # the default terrain
    {"crater_density_per_km2": 2000.0, "crater_min_diameter_m": 20.0, "crater_sfd_exponent": 0.1},  # large craters
    {"size_m": 256.0, "texture_px": 2048, "geometry_px": 65, "boulder_density_per_km2": 20000.0},
])
def test_the_expected_stamping_work_matches_a_drawn_catalog(sets):
    # The load check's estimate of the texels stamped (its cost) against the squares _stamp_radial stamps for an
    # actual catalog, counted one by one (no cleared target: every feature is stamped).
    import models.terrain as terrain_mod

    cfg = TerrainConfig(**{"target_clear_radius_m": 0.0, **sets})
    craters, _, boulders = terrain_mod._catalogs(cfg, np.random.default_rng(1), np.random.default_rng(2), cfg.size_m,
                                                 cfg.crater_max_diameter_m)
    texel_m = cfg.size_m / cfg.texture_px
    counted = sum(float(((2 * np.ceil(support * cat[:, 2] / 2 / texel_m) + 1) ** 2).sum())
                  for cat, support in ((craters, terrain_mod.CRATER_SUPPORT_R), (boulders, terrain_mod.BOULDER_SUPPORT_R)))
    assert 0.8 < counted / terrain_mod.stamped_texels_expected(cfg) < 1.25


def test_terrain_whose_stamping_would_take_hours_is_refused_at_load():
    # 1.9 million craters of 20-200 m passed the count check (under 2e6) and ran for hours; their area is refused.
    with pytest.raises(ValidationError, match=r"stamped over about 1.56e\+12 texels.*at most 2e\+10"):
        TerrainConfig(crater_density_per_km2=9e6, crater_min_diameter_m=20.0, crater_sfd_exponent=0.1)
    with pytest.raises(ValidationError, match=r"stamped over about 3.47e\+10 texels"):  # 43 000 craters, > 330 s
        TerrainConfig(crater_density_per_km2=2e5, crater_min_diameter_m=20.0, crater_sfd_exponent=0.1)
    TerrainConfig(crater_density_per_km2=2e4, crater_min_diameter_m=20.0, crater_sfd_exponent=0.1)  # 46 s: allowed
    TerrainConfig(crater_density_per_km2=1e6)  # fifty times the default's craters of every size (3.9e9): allowed
