"""The map fix (issue 14, item 2): orthorectify, coarse NCC with a sidelobe test, fine patches, covariance.

Synthetic frames are rendered here independently of the flight code: each frame pixel's ray is
intersected with the map's DEM (fixed-point iteration) and the ground image sampled there with
SciPy (not OpenCV's remap), so the test checks the fix's geometry, not a copy of it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.maps import onboard_map_from_product
from bench.maps.synthetic import render_map_frame
from bench.scenario.seeding import component_rng
from gnc.map_nav import MapFixConfig, MapMatcher, OnboardMap, coarse_weight, peak_to_sidelobe
from models.orbital_map import OrbitalMapConfig, render_orbital_map
from models.terrain import TerrainConfig, generate_surface

TERRAIN = TerrainConfig(size_m=320.0, texture_px=1280, geometry_px=81, patch_size_m=0.0, target_clear_radius_m=20.0)
MAPCFG = OrbitalMapConfig(size_m=300.0, image_noise_dn=1.0, dem_noise_m=0.0)
W = H = 256
F_PX = 0.5 * H / math.tan(math.radians(30.0))
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def onboard() -> OnboardMap:
    surface = generate_surface(TERRAIN, component_rng(21, "terrain"))
    prod = render_orbital_map(surface, MAPCFG, (0.0, 0.0), np.random.default_rng(1))
    return onboard_map_from_product(prod, MAPCFG)


def render_frame(m: OnboardMap, r_C: np.ndarray, R_LC: np.ndarray, rng: np.random.Generator,
                 ground: np.ndarray | None = None, noise_dn: float = 2.0) -> np.ndarray:
    return render_map_frame(m, K, r_C, R_LC, rng, (H, W), ground, noise_dn)


def attitude(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    R_LB = Rotation.from_euler("xyz", [roll_deg, pitch_deg, yaw_deg], degrees=True).as_matrix()
    return R_LB @ R_BC


@pytest.mark.parametrize(
    "truth_xy, altitude, offset, att",
    [((10.0, -20.0), 120.0, (6.3, -4.1, 0.0), (0.0, 0.0, 0.0)),
     ((-30.0, 15.0), 150.0, (-8.7, 5.2, 4.0), (6.0, -4.0, 30.0)),  # tilted, yawed, altitude error
     ((0.0, 0.0), 90.0, (2.2, 11.4, -3.0), (-3.0, 2.0, -70.0)),
     ((60.0, -60.0), 150.0, (20.0, -15.0, 0.0), (2.0, 2.0, 10.0))],  # the 3-sigma window is clipped by the map
)
def test_map_fix_recovers_a_known_offset_to_a_third_of_a_pixel(onboard, truth_xy, altitude, offset, att):
    R_LC = attitude(*att)
    ground = float(onboard.dem_height(*truth_xy))
    r_true = np.array([truth_xy[0], truth_xy[1], ground + altitude])
    frame = render_frame(onboard, r_true, R_LC, np.random.default_rng(3))
    r_est = r_true + np.array(offset)
    fix = MapMatcher(onboard).fix(frame, K, R_LC, r_est, sigma_xy_m=max(5.0, np.hypot(*offset[:2]) / 2), sigma_att_rad=0.0)
    assert fix.ok, fix.reason
    err_px = (fix.r_CM_xy_m - r_true[:2]) / fix.work_res_m
    assert np.all(np.abs(err_px) < 0.3), (err_px, fix)
    assert np.allclose(fix.offset_xy_m, -np.array(offset[:2]), atol=0.3 * fix.work_res_m)
    assert 30 <= fix.n_inliers <= fix.n_patches <= 49
    # The fitted scale about the nadir point reads the altitude error: the ortho image of a camera believed
    # dz higher is magnified by (h + dz) / h about the nadir point, so matched offsets shrink by -dz / (h + dz).
    assert abs(fix.scale - (-offset[2] / (altitude + offset[2]))) < 0.01


@pytest.fixture(scope="module")
def random_poses(onboard) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """12 (true camera position, R_LC, frame, estimated position) at 100-160 m: tilt up to 5 deg, any yaw, a 4 m
    horizontal prior error."""
    rng = np.random.default_rng(7)
    out = []
    for _ in range(12):
        xy = rng.uniform(-40.0, 40.0, 2)
        r_true = np.array([xy[0], xy[1], float(onboard.dem_height(*xy)) + rng.uniform(100.0, 160.0)])
        R_LC = attitude(*rng.uniform(-5.0, 5.0, 2), rng.uniform(0.0, 360.0))
        frame = render_frame(onboard, r_true, R_LC, rng)
        out.append((r_true, R_LC, frame, r_true + np.r_[rng.normal(0.0, 4.0, 2), 0.0]))
    return out


def test_map_fix_covariance_matches_its_errors(onboard, random_poses):
    nees, errs = [], []
    for r_true, R_LC, frame, r_est in random_poses:
        fix = MapMatcher(onboard).fix(frame, K, R_LC, r_est, 5.0)
        assert fix.ok, fix.reason
        e = fix.r_CM_xy_m - r_true[:2]
        errs.append(e)
        # The whole error model: the part independent from fix to fix and the common part.
        nees.append(float(e @ np.linalg.solve(fix.total_cov_xy_m2, e)))
    # 2 degrees of freedom: mean NEES 2 when the covariance is right; not wildly optimistic nor useless.
    assert 0.3 < np.mean(nees) < 6.0, (np.mean(nees), np.sqrt(np.mean(np.square(errs), axis=0)))


def test_a_second_pass_through_the_measured_pose_removes_the_offsets_sub_pixel_bias(onboard, random_poses):
    # From a 4 m prior the first pass measures a large offset whose fraction of a pixel biases the sub-pixel
    # peaks (0.063 / 0.046 m RMS per axis on these 12 poses); a second pass through the position it measured
    # sees a near-zero offset (0.017 / 0.015 m) and reports its total from the caller's pose.
    one, two = MapMatcher(onboard, MapFixConfig(refine_passes=1)), MapMatcher(onboard, MapFixConfig(refine_passes=2))
    e1, e2 = [], []
    for r_true, R_LC, frame, r_est in random_poses:
        a, b = one.fix(frame, K, R_LC, r_est, 5.0), two.fix(frame, K, R_LC, r_est, 5.0)
        assert a.ok and b.ok, (a.reason, b.reason)
        np.testing.assert_allclose(b.offset_xy_m, b.r_CM_xy_m - r_est[:2], rtol=0, atol=1e-12)
        e1.append(a.r_CM_xy_m - r_true[:2])
        e2.append(b.r_CM_xy_m - r_true[:2])
    rms1, rms2 = float(np.sqrt(np.mean(np.square(e1)))), float(np.sqrt(np.mean(np.square(e2))))
    assert rms2 < 0.03 and rms2 < 0.5 * rms1, (rms1, rms2)


def test_featureless_map_is_refused(onboard):
    rng = np.random.default_rng(5)
    flat = OnboardMap(image=np.clip(np.rint(120 + 2.0 * rng.standard_normal(onboard.image.shape)), 0, 255)
                      .astype(np.uint8), image_res_m=1.0, image_origin_xy_m=onboard.image_origin_xy_m,
                      dem_m=np.zeros_like(onboard.dem_m), dem_spacing_m=onboard.dem_spacing_m,
                      dem_origin_xy_m=onboard.dem_origin_xy_m, target_xy_m=(0.0, 0.0), georef_sigma_m=2.0,
                      dem_sigma_m=0.2)
    r_true = np.array([5.0, 5.0, 120.0])
    frame = render_frame(flat, r_true, attitude(), rng, ground=np.full(flat.image.shape, 120.0))
    fix = MapMatcher(flat).fix(frame, K, attitude(), r_true + [4.0, -3.0, 0.0], 5.0)
    assert not fix.ok and "sidelobe" in fix.reason and np.all(np.isnan(fix.r_CM_xy_m))


def test_repetitive_map_is_refused(onboard):
    # A periodic ground (period 6 m, inside the 3-sigma window): many equal peaks, no lock even at the truth.
    n = onboard.image.shape[0]
    y, x = np.mgrid[0:n, 0:n]
    ground = 120 + 40 * np.sin(2 * np.pi * x / 6.0) * np.sin(2 * np.pi * y / 6.0)
    periodic = OnboardMap(image=np.rint(ground).astype(np.uint8), image_res_m=1.0,
                          image_origin_xy_m=onboard.image_origin_xy_m, dem_m=np.zeros_like(onboard.dem_m),
                          dem_spacing_m=onboard.dem_spacing_m, dem_origin_xy_m=onboard.dem_origin_xy_m,
                          target_xy_m=(0.0, 0.0), georef_sigma_m=2.0, dem_sigma_m=0.2)
    r_true = np.array([0.0, 0.0, 120.0])
    frame = render_frame(periodic, r_true, attitude(), np.random.default_rng(2))
    fix = MapMatcher(periodic).fix(frame, K, attitude(), r_true + [1.0, 1.0, 0.0], 5.0)
    assert not fix.ok and "sidelobe" in fix.reason and fix.sidelobe_ratio > 0.75


def test_frame_of_other_ground_is_refused(onboard):
    # The frame shows ground that is not in the map (another terrain seed): no false lock.
    other_surface = generate_surface(TERRAIN, component_rng(99, "terrain"))
    other = render_orbital_map(other_surface, MAPCFG, (0.0, 0.0), np.random.default_rng(4)).image
    refused = 0
    for k, xy in enumerate([(0.0, 0.0), (30.0, -30.0), (-40.0, 20.0), (20.0, 40.0)]):
        r_true = np.array([xy[0], xy[1], float(onboard.dem_height(*xy)) + 130.0])
        frame = render_frame(onboard, r_true, attitude(), np.random.default_rng(k), ground=other)
        fix = MapMatcher(onboard).fix(frame, K, attitude(), r_true, 8.0)
        refused += not fix.ok
    assert refused == 4


def test_peak_to_sidelobe_against_an_explicit_computation():
    rng = np.random.default_rng(0)
    c = (0.05 * rng.standard_normal((41, 41))).astype(np.float32)
    c[20, 25] = 0.9
    c[19, 25] = c[21, 25] = c[20, 24] = c[20, 26] = 0.5  # the main lobe's shoulders (above half the peak? no: 0.5 > 0.45)
    c[5, 5] = 0.3  # the highest sidelobe
    row, col, peak, psr, ratio = peak_to_sidelobe(c)
    assert (row, col) == (20, 25) and peak == pytest.approx(0.9)
    mask = np.ones_like(c, bool)
    for i in range(41):
        for j in range(41):
            # lobe = the peak and its 4 shoulders; excluded = within 2 px (Chebyshev) of any lobe pixel
            for (a, b) in ((20, 25), (19, 25), (21, 25), (20, 24), (20, 26)):
                if abs(i - a) <= 2 and abs(j - b) <= 2:
                    mask[i, j] = False
    side = c[mask].astype(np.float64)
    assert psr == pytest.approx((0.9 - side.mean()) / side.std(), rel=1e-4)
    assert ratio == pytest.approx(0.3 / 0.9, rel=1e-5)


@pytest.mark.parametrize("sun, min_accepted", [((30.0, 120.0), 8), ((15.0, 290.0), 0)])
def test_descent_sun_unlike_the_maps_gives_fixes_within_a_metre_or_refusals(sun, min_accepted):
    # The frame shows the same ground under the descent's sun (here 80 deg and 170 deg of azimuth away from the
    # map's 50/200): shading differs, so the correlation drops; accepted fixes stay near the truth (no false lock).
    surface = generate_surface(TERRAIN, component_rng(21, "terrain"))
    onboard = onboard_map_from_product(render_orbital_map(surface, MAPCFG, (0.0, 0.0), np.random.default_rng(1)),
                                       MAPCFG)
    ground_cfg = MAPCFG.model_copy(update=dict(sun_elevation_deg=sun[0], sun_azimuth_deg=sun[1], image_noise_dn=0.0,
                                               image_psf_sigma_px=0.0, image_res_m=0.5))
    ground = OnboardMap(image=render_orbital_map(surface, ground_cfg, (0.0, 0.0), np.random.default_rng(1)).image,
                        image_res_m=0.5, image_origin_xy_m=onboard.image_origin_xy_m, dem_m=onboard.dem_m,
                        dem_spacing_m=onboard.dem_spacing_m, dem_origin_xy_m=onboard.dem_origin_xy_m,
                        target_xy_m=(0.0, 0.0), georef_sigma_m=2.0, dem_sigma_m=0.2)
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(12):
        xy = rng.uniform(-40.0, 40.0, 2)
        r_true = np.array([xy[0], xy[1], float(onboard.dem_height(*xy)) + rng.uniform(60.0, 200.0)])
        R_LC = attitude(*rng.uniform(-6.0, 6.0, 2), rng.uniform(0.0, 360.0))
        frame = render_frame(ground, r_true, R_LC, rng)
        sigma = rng.uniform(3.0, 10.0)
        fix = MapMatcher(onboard).fix(frame, K, R_LC, r_true + np.r_[rng.normal(0.0, sigma, 2), 0.0], sigma)
        if fix.ok:
            errors.append(float(np.hypot(*(fix.r_CM_xy_m - r_true[:2]))))
    assert len(errors) >= min_accepted
    assert max(errors, default=0.0) < 1.5, errors


def _nadir_template_side_px(m: OnboardMap, r_est: np.ndarray, res_m: float) -> int:
    """The coarse template's side [work px] of a nadir frame taken from the estimated position ``r_est``:
    0.7 of the orthorectified footprint, 0.9 of the frame at the frame's ground-sample distance (the
    estimated height above the map's DEM under it over the focal length)."""
    height_m = float(r_est[2]) - float(m.dem_height(float(r_est[0]), float(r_est[1])))
    footprint = int(min(MapFixConfig().max_ortho_px, 0.9 * H * (height_m / F_PX) / res_m))
    return int(MapFixConfig().template_frac * footprint)


def test_common_error_of_a_fix_grows_as_the_frame_looks_less_like_the_map(onboard):
    # A frame coarser than the map's finest level (230 m: 1.04 m per frame pixel on the 1 m level): with the
    # step between the two calibrations (fine_blend_gsd_ratio = 1, the default), the common error is the floor plus the
    # gain times ((1 - peak) / peak)^power, in work pixels. One pass, so that the pose the error model sees
    # is the one given here.
    cfg = MapFixConfig(refine_passes=1)
    assert cfg.fine_blend_gsd_ratio == 1.0
    offset = np.array([3.0, -2.0, 0.0])
    r_high = np.array([0.0, 0.0, float(onboard.dem_height(0.0, 0.0)) + 230.0])
    high = MapMatcher(onboard, cfg).fix(render_frame(onboard, r_high, attitude(), np.random.default_rng(4)), K,
                                        attitude(), r_high + offset, 5.0)
    assert high.ok and high.work_res_m == onboard.image_res_m, high
    q = ((1.0 - high.peak) / high.peak) ** cfg.common_peak_power
    expected = cfg.coarse_common_scale * high.work_res_m * math.hypot(cfg.common_mode_sigma_px,
                                                                      cfg.common_peak_gain * q)
    assert high.common_sigma_m == pytest.approx(expected, rel=1e-12)
    assert high.coarse_weight == 1.0
    assert cfg.coarse_common_scale == 1.0  # the default: the calibration as chosen in closed loop
    rescaled = MapMatcher(onboard, cfg.model_copy(update={"coarse_common_scale": 0.8})).fix(
        render_frame(onboard, r_high, attitude(), np.random.default_rng(4)), K, attitude(), r_high + offset, 5.0)
    assert rescaled.common_sigma_m == pytest.approx(0.8 * high.common_sigma_m, rel=1e-12)
    # A frame finer than it (150 m: 0.68 m per frame pixel): its own calibration, the floor at the coarse
    # template's side (as 1 / side) and a fraction of the peak term; the independent part scaled.
    r_true = np.array([0.0, 0.0, float(onboard.dem_height(0.0, 0.0)) + 150.0])
    frame = render_frame(onboard, r_true, attitude(), np.random.default_rng(4))
    fix = MapMatcher(onboard, cfg).fix(frame, K, attitude(), r_true + offset, 5.0)
    assert fix.ok, fix.reason
    assert fix.work_res_m == onboard.image_res_m and fix.coarse_weight == 0.0  # the fine calibration whole
    q = ((1.0 - fix.peak) / fix.peak) ** cfg.common_peak_power
    side = _nadir_template_side_px(onboard, r_true + offset, fix.work_res_m)
    expected = fix.work_res_m * math.hypot(cfg.fine_common_sigma_px * cfg.fine_common_side_px / side,
                                           cfg.fine_peak_scale * cfg.common_peak_gain * q)
    assert fix.common_sigma_m == pytest.approx(expected, rel=1e-12)
    unscaled = MapMatcher(onboard, cfg.model_copy(update={"fine_independent_scale": 1.0})).fix(
        frame, K, attitude(), r_true + offset, 5.0)
    np.testing.assert_allclose(fix.cov_xy_m2, unscaled.cov_xy_m2 * cfg.fine_independent_scale**2, rtol=1e-12)
    np.testing.assert_allclose(fix.total_cov_xy_m2, fix.cov_xy_m2 + np.eye(2) * expected**2, rtol=1e-12)
    # The same ground in a noisier, lower-contrast frame correlates worse with the map: a larger common error.
    dim = np.clip(0.5 * frame.astype(float) + 60.0 + np.random.default_rng(9).normal(0.0, 6.0, frame.shape),
                  0, 255).astype(np.uint8)
    worse = MapMatcher(onboard, cfg).fix(dim, K, attitude(), r_true + offset, 5.0)
    assert worse.ok and worse.peak < fix.peak and worse.common_sigma_m > fix.common_sigma_m


def test_coarse_weight_is_zero_below_the_work_level_linear_to_the_blend_ratio_and_one_beyond():
    for ratio in (1.25, 1.5, 2.0):
        assert coarse_weight(0.6, ratio) == 0.0 and coarse_weight(0.999, ratio) == 0.0
        assert coarse_weight(1.0, ratio) == 0.0
        for q in np.linspace(1.0, ratio, 7):
            assert coarse_weight(float(q), ratio) == pytest.approx((q - 1.0) / (ratio - 1.0), abs=1e-12)
        assert coarse_weight(ratio, ratio) == pytest.approx(1.0)
        assert coarse_weight(ratio + 0.3, ratio) == 1.0
    # A ratio of 1: the step at gsd = res.
    assert coarse_weight(0.99, 1.0) == 0.0 and coarse_weight(1.0, 1.0) == 1.0 and coarse_weight(1.3, 1.0) == 1.0


def test_a_frame_just_coarser_than_the_map_blends_the_fine_and_coarse_calibrations(onboard):
    # 230 m over the 1 m level: 1.04 m per frame pixel, so with a blend from 1 to 1.5 frame px per work px
    # the coarse calibration weighs (gsd / res - 1) / 0.5, and the common error is the geometric blend of
    # the fine one (floor at the template's side, a fraction of the peak term) and the coarse one; the
    # independent part takes that fraction of the fine scale. Recomputed here from the fix's peak, its
    # ground-sample distance (checked against the nadir geometry) and the template's side.
    cfg = MapFixConfig(refine_passes=1, fine_blend_gsd_ratio=1.5)
    offset = np.array([3.0, -2.0, 0.0])
    r_true = np.array([0.0, 0.0, float(onboard.dem_height(0.0, 0.0)) + 230.0])
    frame = render_frame(onboard, r_true, attitude(), np.random.default_rng(4))
    r_est = r_true + offset
    fix = MapMatcher(onboard, cfg).fix(frame, K, attitude(), r_est, 5.0)
    assert fix.ok and fix.work_res_m == onboard.image_res_m, fix
    height_est = float(r_est[2]) - float(onboard.dem_height(float(r_est[0]), float(r_est[1])))
    assert fix.gsd_m == pytest.approx(height_est / F_PX, rel=1e-6)
    w = (fix.gsd_m / fix.work_res_m - 1.0) / (cfg.fine_blend_gsd_ratio - 1.0)
    assert 0.0 < w < 1.0
    q = ((1.0 - fix.peak) / fix.peak) ** cfg.common_peak_power
    coarse = cfg.coarse_common_scale * fix.work_res_m * math.hypot(cfg.common_mode_sigma_px, cfg.common_peak_gain * q)
    side = _nadir_template_side_px(onboard, r_est, fix.work_res_m)
    fine = fix.work_res_m * math.hypot(cfg.fine_common_sigma_px * cfg.fine_common_side_px / side,
                                       cfg.fine_peak_scale * cfg.common_peak_gain * q)
    assert fine < coarse
    assert fix.common_sigma_m == pytest.approx(fine ** (1.0 - w) * coarse**w, rel=1e-9)
    assert fix.coarse_weight == pytest.approx(w, rel=1e-12)
    assert fine < fix.common_sigma_m < coarse
    # The step's fix of the same frame: the coarse calibration whole, the independent part unscaled.
    step = MapMatcher(onboard, cfg.model_copy(update={"fine_blend_gsd_ratio": 1.0})).fix(frame, K, attitude(), r_est,
                                                                                        5.0)
    assert step.common_sigma_m == pytest.approx(coarse, rel=1e-12)
    np.testing.assert_allclose(fix.cov_xy_m2, step.cov_xy_m2 * cfg.fine_independent_scale ** (2.0 * (1.0 - w)),
                               rtol=1e-9)
    np.testing.assert_allclose(fix.r_CM_xy_m, step.r_CM_xy_m, rtol=0, atol=0)  # the measurement is the same
