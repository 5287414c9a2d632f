"""The ALHAT-style hazard map and safe-site choice (issue 14, item 3), against explicit loops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gnc.hazard import HazardConfig, choose_site, hazard_map

SPACING = 0.1
HALF = 30.0
N = int(round(2 * HALF / SPACING)) + 1
XS = -HALF + np.arange(N) * SPACING
BIG = [(-5.0, 0.0, 0.35), (4.0, 8.0, 0.5), (0.0, -12.0, 0.8), (-22.0, 10.0, 0.4)]  # (x, y, height): hazards
SMALL = [(6.0, -4.0, 0.15), (-8.0, -18.0, 0.12)]  # rocks below the threshold
STEEP_DEG, GENTLE_DEG = 15.0, 5.0


def synthetic_dem() -> np.ndarray:
    """Flat in |x| < 15 m, a 5 deg slope west of it, a 15 deg slope east of it, Gaussian boulders (terrain's shape)."""
    X, Y = np.meshgrid(XS, XS)
    h = np.where(X > 15.0, math.tan(math.radians(STEEP_DEG)) * (X - 15.0), 0.0)
    h = h + np.where(X < -15.0, math.tan(math.radians(GENTLE_DEG)) * (-15.0 - X), 0.0)
    for x, y, height in BIG + SMALL:
        sigma = 0.25 * (2.0 * height)  # models.terrain: height 0.5 D, sigma 0.25 D
        h = h + height * np.exp(-((X - x) ** 2 + (Y - y) ** 2) / (2 * sigma**2))
    return h


@pytest.fixture(scope="module")
def dem():
    return synthetic_dem()


@pytest.fixture(scope="module")
def hmap(dem):
    return hazard_map(dem, SPACING, (-HALF, -HALF))


def post(x: float, y: float) -> tuple[int, int]:
    return int(round((y + HALF) / SPACING)), int(round((x + HALF) / SPACING))


def explicit_tilt(dem: np.ndarray, i: int, j: int, cfg: HazardConfig, yaws_deg) -> float:
    """Worst tilt over yaws of every plane through three pads with the fourth on or below it (explicit loops)."""
    r_pad = cfg.footpad_radius_m / SPACING
    worst = 0.0
    for yaw in yaws_deg:
        pads = []
        for q in range(4):
            ang = math.radians(yaw + 45.0 + 90.0 * q)
            pi = i + int(round(cfg.leg_radius_m * math.sin(ang) / SPACING))
            pj = j + int(round(cfg.leg_radius_m * math.cos(ang) / SPACING))
            top = -np.inf
            for di in range(-3, 4):
                for dj in range(-3, 4):
                    if di * di + dj * dj <= r_pad * r_pad + 1e-9:
                        top = max(top, dem[pi + di, pj + dj])
            pads.append(np.array([(pj - j) * SPACING, (pi - i) * SPACING, top]))
        for skip in range(4):
            p = [pads[q] for q in range(4) if q != skip]
            n = np.cross(p[1] - p[0], p[2] - p[0])
            n = n if n[2] > 0 else -n
            # The skipped pad must not be above the plane (the lander rests on these three).
            if np.dot(n, pads[skip] - p[0]) > 1e-6:
                continue
            worst = max(worst, math.degrees(math.acos(n[2] / np.linalg.norm(n))))
    return worst


def explicit_roughness(dem: np.ndarray, i: int, j: int, cfg: HazardConfig) -> float:
    r = int(round(cfg.body_radius_m / SPACING))
    best = -np.inf
    rb = cfg.body_radius_m / SPACING
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            if di * di + dj * dj <= rb * rb + 1e-9:
                a, b = i + di, j + dj
                mean = dem[a - r:a + r + 1, b - r:b + r + 1].mean()
                best = max(best, dem[a, b] - mean)
    return best


def test_every_hazard_above_the_thresholds_is_found(hmap):
    cfg = HazardConfig()
    # Every boulder above 0.3 m: the lander centred on it, or with it anywhere well under its body, is unsafe.
    for x, y, height in BIG:
        for dx, dy in [(0.0, 0.0), (1.5, 0.0), (0.0, -1.5), (-1.0, 1.0), (1.4, 1.4)]:
            i, j = post(x + dx, y + dy)
            assert hmap.unsafe[i, j], (x, y, height, dx, dy, hmap.roughness_m[i, j])
        i, j = post(x, y)
        assert hmap.roughness_m[i, j] > cfg.roughness_max_m
    # The 15 deg slope (footprint wholly on it) is unsafe, and its tilt is the slope's.
    for x in (18.0, 22.0, 26.0):
        for y in (-20.0, 0.0, 20.0):
            i, j = post(x, y)
            assert hmap.unsafe[i, j] and abs(hmap.tilt_deg[i, j] - STEEP_DEG) < 0.3


def test_flat_ground_gentle_slope_and_small_rocks_are_safe(hmap):
    rocks = np.array([(x, y) for x, y, _ in BIG])
    for x in np.arange(-12.0, 12.1, 3.0):
        for y in np.arange(-25.0, 25.1, 5.0):
            if np.min(np.hypot(rocks[:, 0] - x, rocks[:, 1] - y)) > 3.0:
                assert not hmap.unsafe[post(x, y)], (x, y)
    for x, y, _ in SMALL:
        assert not hmap.unsafe[post(x, y)]
    for y in (-20.0, 0.0, 24.0):  # 5 deg slope, no rocks near
        i, j = post(-24.0, y)
        assert not hmap.unsafe[i, j] and abs(hmap.tilt_deg[i, j] - GENTLE_DEG) < 0.3


def test_tilt_and_roughness_equal_explicit_loops(dem, hmap):
    cfg = HazardConfig()
    yaws = [90.0 * k / cfg.yaw_count for k in range(cfg.yaw_count)]
    points = [(-5.0, 0.0), (-3.2, 0.4), (4.0, 6.1), (2.5, -12.0), (14.0, 3.0), (16.5, -3.0), (-16.0, 8.0),
              (-21.0, 10.0), (6.0, -4.0), (-13.9, -18.0), (5.2, -2.3)]
    for x, y in points:
        i, j = post(x, y)
        assert hmap.tilt_deg[i, j] == pytest.approx(explicit_tilt(dem, i, j, cfg, yaws), abs=1e-3), (x, y)
        assert hmap.roughness_m[i, j] == pytest.approx(explicit_roughness(dem, i, j, cfg), abs=1e-4), (x, y)
        # The sampled yaws miss at most a little of the worst over all yaws (1 deg steps).
        fine = explicit_tilt(dem, i, j, cfg, np.arange(0.0, 90.0, 1.0))
        assert hmap.tilt_deg[i, j] <= fine + 1e-3 and hmap.tilt_deg[i, j] >= fine - 2.0, (x, y)


def test_the_footprint_leaving_the_dem_is_unsafe(hmap):
    assert hmap.unsafe[0, :].all() and hmap.unsafe[:, -1].all()
    assert np.isnan(hmap.tilt_deg[5, N // 2])


def test_safe_site_keeps_three_sigma_from_hazards_and_is_the_cheapest(hmap):
    cfg = HazardConfig()
    target = np.array([-5.0, 0.0])  # on a 0.35 m boulder
    sigma = 1.2
    site = choose_site(hmap, target, sigma, cfg)
    assert site is not None and not hmap.unsafe[post(*site.xy_m)]
    assert site.divert_m <= cfg.max_divert_m and site.divert_m == pytest.approx(np.hypot(*(site.xy_m - target)))
    # Brute force: the distance to every unsafe post, and every post's cost.
    ui, uj = np.nonzero(hmap.unsafe)
    ux, uy = -HALF + uj * SPACING, -HALF + ui * SPACING
    margin = float(np.min(np.hypot(ux - site.xy_m[0], uy - site.xy_m[1])))
    assert margin >= 3 * sigma - 1e-6 and margin == pytest.approx(site.margin_m, abs=0.02)
    sub = slice(0, N, 7)  # every 7th post, for speed
    best = np.inf
    for i in range(N)[sub]:
        for j in range(N)[sub]:
            x, y = -HALF + j * SPACING, -HALF + i * SPACING
            d = math.hypot(x - target[0], y - target[1])
            m = hmap.hazard_distance_m[i, j]
            if hmap.unsafe[i, j] or m < 3 * sigma or d > cfg.max_divert_m:
                continue
            c = (d / cfg.max_divert_m + 0.5 * hmap.tilt_deg[i, j] / cfg.slope_max_deg
                 + (1.0 - min(m, cfg.margin_cap_m) / cfg.margin_cap_m))
            best = min(best, c)
    assert site.cost <= best + 1e-9
    # A target on open flat ground is kept as it is.
    i0, j0 = post(-8.0, 17.0)
    if hmap.hazard_distance_m[i0, j0] >= cfg.margin_cap_m:
        kept = choose_site(hmap, np.array([-8.0, 17.0]), sigma, cfg)
        assert kept is not None and kept.divert_m == pytest.approx(0.0, abs=1e-9)
    else:  # the test must test something
        pytest.fail("the open-ground point is too near a hazard; move it")


def test_no_safe_site_is_reported_as_none():
    X, _ = np.meshgrid(XS[:301], XS[:301])
    steep = math.tan(math.radians(20.0)) * X
    hm = hazard_map(steep, SPACING)
    assert hm.unsafe.all() and choose_site(hm, np.array([15.0, 15.0]), 1.0) is None


def test_hda_post_spacings_that_turn_the_rock_threshold_negative_are_refused():
    # 0.3 m posts made a 0.3 m rock count from -0.10 m: every post a rock, a false 'no safe site' and a safe abort.
    from gnc.hda import HdaConfig, sampling_margin_m

    with pytest.raises(ValueError, match=r"dem_spacing_m = 0.3 makes a rock of roughness_max_m = 0.3 m count from "
                                         r"-0.100 m"):
        HdaConfig(dem_spacing_m=0.3)
    widest = 0.3 * (3.0 / 8.0) ** 0.5  # margin(s) = 4 s^2 / (3 h) = h / 2
    assert sampling_margin_m(widest, 0.3) == pytest.approx(0.15)
    HdaConfig(dem_spacing_m=0.95 * widest)
    HdaConfig(dem_spacing_m=0.3, sampling_margin="off")
