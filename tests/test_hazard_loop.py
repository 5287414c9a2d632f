"""Hazard detection and avoidance in the loop (issue 14): fine truth DEM, footprint scoring, flash lidar, retarget."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.evaluation.footprint import FootprintCriteria, score_footprint
from bench.scenario import ScenarioError, load_scenario
from gnc.hda import HazardAvoidance, HdaConfig, grid_dem, scan_points_L
from gnc.hazard import HazardConfig
from models.flash_lidar import FlashLidar, FlashLidarConfig, ray_ranges
from models.lander import LanderConfig, footpad_positions_B
from models.site_dem import SiteDem, SiteGround
from models.terrain import BOULDER_HEIGHT_RATIO, TerrainConfig, generate_surface

SMALL = dict(size_m=256.0, texture_px=1024, geometry_px=33, patch_size_m=0.0, target_clear_radius_m=0.0,
             boulder_density_per_km2=30000.0)


def _dem(h: np.ndarray, spacing: float, origin: tuple[float, float], boulders=None) -> SiteDem:
    return SiteDem(height_m=h.astype(np.float32), spacing_m=spacing, origin_xy_m=origin,
                   boulders=np.zeros((0, 3)) if boulders is None else np.asarray(boulders, float),
                   craters=np.zeros((0, 3)))


def _grid(half: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    xs = -half + spacing * np.arange(int(round(2 * half / spacing)) + 1)
    return np.meshgrid(xs, xs)


def _gaussian_boulder(X, Y, x, y, d):
    """The terrain's boulder shape, written out: a Gaussian of peak 0.5 D and sigma D / 4, cut at 3 sigma."""
    sigma = d / 4
    cut = math.exp(-4.5)
    g = (np.exp(-((X - x) ** 2 + (Y - y) ** 2) / (2 * sigma**2)) - cut) * (BOULDER_HEIGHT_RATIO * d / (1 - cut))
    return np.maximum(g, 0.0)


# ----------------------------------------------------------------- the fine truth DEM
def test_site_dem_is_the_terrains_own_surface_at_the_texels():
    """At texel centres the locally stamped DEM equals generate_surface's globally stamped one."""
    cfg = TerrainConfig(**SMALL)
    surface = generate_surface(cfg, np.random.default_rng(5))
    ground = SiteGround(cfg, np.random.default_rng(5))
    tex = surface.texel_m
    centre = (0.125 + 3.0, 0.125 - 2.0)  # posts on texel centres
    dem = ground.dem(centre, 10.0, tex)
    j0 = int(round((dem.origin_xy_m[0] + cfg.size_m / 2) / tex - 0.5))
    i0 = int(round((dem.origin_xy_m[1] + cfg.size_m / 2) / tex - 0.5))
    n = dem.height_m.shape[0]
    ref = surface.height_m[i0:i0 + n, j0:j0 + n]
    assert np.ptp(ref) > 0.5 and len(dem.boulders) > 0  # not a trivial patch
    np.testing.assert_allclose(dem.height_m, ref, atol=1e-5)
    # The catalogs are the terrain's.
    assert {tuple(b) for b in dem.boulders} <= {tuple(b) for b in surface.boulders}


def test_site_dem_resolves_a_boulder_the_texels_cannot():
    """At 0.05 m a lone boulder's peak is its own 0.5 D above the ground around it, as the catalog says."""
    cfg = TerrainConfig(**SMALL)
    ground = SiteGround(cfg, np.random.default_rng(5))
    bs = ground.boulders
    near = np.hypot(bs[:, None, 0] - bs[None, :, 0], bs[:, None, 1] - bs[None, :, 1])
    np.fill_diagonal(near, np.inf)
    lone = [k for k in range(len(bs)) if 0.6 <= bs[k, 2] <= 1.0 and max(abs(bs[k, 0]), abs(bs[k, 1])) < 100
            and near[k].min() > 3 * bs[k, 2] + 2]
    assert lone
    b = bs[lone[0]]
    dem = ground.dem((float(b[0]), float(b[1])), 2.0 * b[2], 0.05)
    peak = float(dem.height_at(b[0], b[1]))
    ring = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    r = 0.8 * b[2]  # beyond the boulder's support (0.75 D)
    base = float(np.mean(dem.height_at(b[0] + r * np.cos(ring), b[1] + r * np.sin(ring))))
    assert peak - base == pytest.approx(0.5 * b[2], abs=0.03)


def test_site_dem_refuses_a_user_dem_and_a_square_off_the_tile(tmp_path):
    np.save(tmp_path / "d.npy", np.zeros((64, 64)))
    with pytest.raises(ValueError, match="procedural"):
        SiteGround(TerrainConfig(kind="dem", dem_path=tmp_path / "d.npy", dem_spacing_m=2.0,
                                 target_clear_radius_m=0.0), np.random.default_rng(0))
    ground = SiteGround(TerrainConfig(**SMALL), np.random.default_rng(0))
    with pytest.raises(ValueError, match="leaves the terrain"):
        ground.dem((120.0, 0.0), 20.0)


# ----------------------------------------------------------------- footprint scoring
LANDER = LanderConfig()
PADS_B = footpad_positions_B(LANDER)[:, :2]


def test_footprint_on_flat_ground_is_hazard_free_and_a_rock_under_the_body_is_not():
    X, Y = _grid(6.0, 0.05)
    flat = score_footprint(_dem(np.zeros_like(X), 0.05, (-6.0, -6.0)), PADS_B, np.zeros(2), LANDER.footpad_radius_m)
    assert flat["hazard_free"] and flat["tilt_deg"] == pytest.approx(0.0, abs=1e-9)
    for d, safe in ((0.8, False), (0.4, True)):  # 0.4 m and 0.2 m high
        h = _gaussian_boulder(X, Y, 1.0, -0.5, d)
        s = score_footprint(_dem(h, 0.05, (-6.0, -6.0), [[1.0, -0.5, d]]), PADS_B, np.zeros(2), LANDER.footpad_radius_m)
        assert s["hazard_free"] is safe and s["hazard_free_strict"] is safe
        assert s["rock_list_m"] == pytest.approx(0.5 * d, rel=1e-6)
        # Above the least-squares plane of the footprint (which the rock lifts a little).
        assert s["rock_dem_m"] == pytest.approx(0.5 * d, abs=0.01)
        assert ("rock" in s["hazards"]) is not safe


def test_footprint_tilt_of_a_raised_pad_and_of_a_slope_equal_the_closed_form():
    X, Y = _grid(6.0, 0.05)
    # One pad on a 0.3 m plateau (a flat-topped rock as wide as the footpad). The plane through it and its two
    # neighbours has the opposite pad above it (the lander cannot rest on it); it rests on the raised pad, the
    # opposite one and either neighbour: a rise of h over the side of the pads' square, tilt = atan(h / (sqrt2 R)).
    h = np.where(np.hypot(X - PADS_B[0, 0], Y - PADS_B[0, 1]) <= 0.35, 0.3, 0.0)
    s = score_footprint(_dem(h, 0.05, (-6.0, -6.0)), PADS_B, np.zeros(2), LANDER.footpad_radius_m)
    side = math.sqrt(2.0) * LANDER.leg_radius_m
    assert s["tilt_deg"] == pytest.approx(math.degrees(math.atan(0.3 / side)), abs=1e-6)
    assert s["pad_heights_m"][0] == pytest.approx(0.3) and max(s["pad_heights_m"][1:]) == 0.0
    for deg, safe in ((5.0, True), (12.0, False)):
        g = math.tan(math.radians(deg))
        plane = g * (X * math.cos(0.4) + Y * math.sin(0.4))
        s = score_footprint(_dem(plane, 0.05, (-6.0, -6.0)), PADS_B, np.zeros(2), LANDER.footpad_radius_m)
        assert s["slope_deg"] == pytest.approx(deg, abs=1e-6)
        # Pad heights are the highest point under each footpad: on a plane, the plane r_pad uphill.
        assert s["tilt_deg"] == pytest.approx(deg, abs=0.05)
        assert s["hazard_free"] is safe


def test_footprint_outside_the_dem_is_not_judged():
    X, Y = _grid(2.0, 0.1)  # the footprint reaches 2.4 m
    s = score_footprint(_dem(np.zeros_like(X), 0.1, (-2.0, -2.0)), PADS_B, np.zeros(2), LANDER.footpad_radius_m)
    assert s["hazard_free"] is None and s["hazards"] == ["outside_site_dem"]


# ----------------------------------------------------------------- flash lidar
def test_lidar_ranges_on_a_tilted_plane_equal_the_closed_form_and_noise_has_its_sigma():
    X, Y = _grid(40.0, 0.1)
    a, b, c = 0.1, -0.05, 1.0
    dem = _dem(c + a * X + b * Y, 0.1, (-40.0, -40.0))
    R_LS = Rotation.from_euler("xyz", [183.0, 2.0, 30.0], degrees=True).as_matrix()
    o = np.array([1.0, 2.0, 100.0])
    cfg = FlashLidarConfig(pixels=64)
    exact = FlashLidar(cfg.model_copy(update={"range_sigma_m": 0.0}), np.random.default_rng(0)).scan(0, o, R_LS,
                                                                                                   np.eye(3), dem)
    d = FlashLidar(cfg, np.random.default_rng(0)).dirs_S.reshape(-1, 3) @ R_LS.T
    t = (c + a * o[0] + b * o[1] - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])  # ray-plane intersection
    np.testing.assert_allclose(exact.ranges_m.ravel(), t, atol=1e-5)
    noisy = FlashLidar(cfg, np.random.default_rng(1)).scan(0, o, R_LS, np.eye(3), dem)
    resid = noisy.ranges_m.ravel() - t
    assert np.std(resid) == pytest.approx(cfg.range_sigma_m, rel=0.05) and abs(np.mean(resid)) < 0.003


def test_lidar_sees_a_boulder_where_it_is():
    X, Y = _grid(20.0, 0.05)
    dem = _dem(_gaussian_boulder(X, Y, 3.0, -4.0, 2.0), 0.05, (-20.0, -20.0))
    dz = math.sqrt(1 - 0.2**2)
    ranges = ray_ranges(np.array([3.0, -4.0, 50.0]), np.array([[0.0, 0.0, -1.0], [0.0, 0.2, -dz]]), dem)
    assert ranges[0] == pytest.approx(50.0 - 1.0, abs=1e-3)  # the boulder's 1 m top
    assert ranges[1] == pytest.approx(50.0 / dz, abs=1e-3)  # the flat ground 10 m beside it


# ----------------------------------------------------------------- the flight software's DEM and retarget
def _scan_over(h: np.ndarray, half: float, spacing: float, r_true: np.ndarray, pixels: int = 128):
    dem = _dem(h, spacing, (-half, -half))
    R_LB = np.eye(3)
    R_BS = np.diag([1.0, -1.0, -1.0])  # nadir-looking, the camera's mounting
    lidar = FlashLidar(FlashLidarConfig(pixels=pixels, mount_B_m=(0.0, 0.0, 0.0)), np.random.default_rng(3))
    return lidar.scan(0, r_true, R_LB @ R_BS, R_BS, dem), R_LB


def test_the_scan_dem_is_placed_through_the_estimated_pose():
    """A navigation error e moves the flight software's DEM by e: the bump appears at truth + e."""
    X, Y = _grid(25.0, 0.05)
    h = _gaussian_boulder(X, Y, 2.0, 1.0, 2.0)
    r_true = np.array([0.0, 0.0, 60.0])
    msg, R_LB = _scan_over(h, 25.0, 0.05, r_true)
    e = np.array([4.3, -2.1, 0.0])
    dem = grid_dem(scan_points_L(msg, r_true + e, R_LB), 0.1)
    i, j = np.unravel_index(np.argmax(np.where(dem.known, dem.height_m, -np.inf)), dem.height_m.shape)
    peak_xy = np.array([dem.origin_xy_m[0] + j * 0.1, dem.origin_xy_m[1] + i * 0.1])
    np.testing.assert_allclose(peak_xy, np.array([2.0, 1.0]) + e[:2], atol=0.15)
    assert dem.height_m[i, j] == pytest.approx(1.0, abs=0.08)


def test_retarget_picks_the_only_safe_site_and_declares_none_when_there_is_none():
    half, s = 25.0, 0.1
    X, Y = _grid(half, s)
    # Rough everywhere (a 0.5 m egg-crate, period 3 m) but a flat disk of 7 m radius at (6, -5).
    rough = 0.5 * np.sin(2 * np.pi * X / 3.0) * np.sin(2 * np.pi * Y / 3.0)
    clear = np.hypot(X - 6.0, Y - 5.0 * -1) <= 7.0
    h = np.where(clear, 0.0, rough)
    r_true = np.array([0.0, 0.0, 70.0])
    msg, R_LB = _scan_over(h, half, s, r_true, pixels=192)
    e = np.array([-3.0, 2.0, 0.0])  # the navigation error: everything the flight software sees is moved by it
    hda = HazardAvoidance(HdaConfig(map=HazardConfig(max_divert_m=30.0)))
    assert hda.wants_scan(99.0, "approach") and not hda.wants_scan(101.0, "approach")
    assert not hda.wants_scan(99.0, "terminal")
    target = np.array([0.0, 0.0, 0.0]) + e
    new = hda.on_scan(msg, r_true + e, R_LB, 0.01, 0.5, target)
    assert new is not None and not hda.stats.no_safe_site
    site_true = new[:2] - e[:2]
    # Inside the clear disk, with the margin: 2.4 m of footprint plus 3 sigma of the drift.
    sigma = hda.stats.nav_sigma_m
    assert math.hypot(site_true[0] - 6.0, site_true[1] + 5.0) <= 7.0 - 2.2 - 3 * sigma + 0.2
    assert hda.stats.site.margin_m >= 3 * sigma
    assert not hda.wants_scan(50.0, "approach")  # one scan
    # The same ground with no clear disk: no safe site, declared.
    msg2, _ = _scan_over(rough, half, s, r_true, pixels=192)
    hda2 = HazardAvoidance(HdaConfig(map=HazardConfig(max_divert_m=30.0)))
    assert hda2.on_scan(msg2, r_true + e, R_LB, 0.01, 0.5, target) is None and hda2.stats.no_safe_site


def test_an_abandoned_second_scan_declares_no_safe_site():
    hda = HazardAvoidance(HdaConfig())
    hda.scanned, hda.awaiting_rescan = True, True  # the first scan found no site
    hda.abandon_rescan()
    assert hda.no_safe_site and not hda.awaiting_rescan and not hda.wants_scan(10.0, "terminal")
    fresh = HazardAvoidance(HdaConfig())
    fresh.abandon_rescan()  # nothing was due: nothing declared
    assert not fresh.no_safe_site


def test_an_approach_that_ends_above_the_scan_height_is_noted_once_and_the_landing_goes_on():
    """The first scan is taken on the approach at or below its height; an approach that ended before it (the
    guidance already terminal, nothing scanned) is noted once as a hazard event, asks for no flash, and lands at
    the target it has (no abort: the map was never made, which is not a site found unsafe)."""
    from bench.sim.flight_build import build_flight_software
    from gnc.guidance import GuidanceCommand

    sc = load_scenario(None, ["hazard.avoidance=on"], "hazardous")

    def flight_software():
        return build_flight_software(sc, np.array([0.0, 0.0, 150.0]), np.zeros(3), q0_LB=np.array([1.0, 0, 0, 0]))

    def at(fsw, height_m: float, phase: str, t_ns: int) -> bool:
        fsw.filter.ekf.x[2] = float(fsw.target.r_L[2]) + height_m
        fsw.last_guidance = GuidanceCommand(t_ns, np.zeros(3), phase, 10.0, saturated=False, valid=True)
        return fsw.wants_lidar_scan()

    def hazard_events(fsw):
        return [e for e in fsw.fdir.events if e.subsystem == "hazard"]

    fsw = flight_software()
    assert fsw.hda is not None and not fsw.hda.scanned
    assert not at(fsw, 150.0, "approach", 1) and not hazard_events(fsw)  # above the scan's height: nothing yet
    assert not at(fsw, 120.0, "terminal", 2) and not at(fsw, 90.0, "terminal", 3)  # ended above it: no flash, ever
    events = hazard_events(fsw)
    assert len(events) == 1 and fsw.fdir.abort is None, events
    assert events[0].reason == (f"no hazard scan: the approach ended above its height "
                                f"(hazard.hda.scan_altitude_m = {sc.hazard.hda.scan_altitude_m:g} m)")
    assert events[0].action.startswith("landing at the current target") and events[0].t_ns == 2
    # The same flight software on an approach at the scan's height would have scanned.
    fresh = flight_software()
    assert at(fresh, 90.0, "approach", 4) and not hazard_events(fresh)


@pytest.mark.slow
@pytest.mark.parametrize("sets, reason, outcome", [
    # No site, and the user chose to land anyway: declared, not silent. (A second scan 0.5 m up and a scan 1 m up
    # flew here too, until the load checks refused them: test_cli's settings that could never act.)
    (["hazard.hda.map.nav_sigmas=30.0", "hazard.hda.rescan=off", "hazard.hda.no_site_action=land"],
     "no safe site within the divert limit", "landed"),
])
def test_hazard_avoidance_that_cannot_act_is_declared(sets, reason, outcome):
    from bench.sim.run import run

    small = [f"terrain.{k}={v}" for k, v in dict(size_m=512.0, texture_px=2048, geometry_px=65).items()]
    summary = run(load_scenario(None, ["hazard.avoidance=on", *small, *sets], "hazardous")).summary
    events = [e for e in summary["fdir_events"] if e["subsystem"] == "hazard"]
    assert events and reason in events[0]["reason"], summary["fdir_events"]
    assert summary["outcome"] == outcome


def test_a_lidar_off_the_vehicle_or_a_footprint_off_the_terrain_is_one_line_naming_the_fields(tmp_path, capsys):
    from bench.cli import main

    with pytest.raises(ScenarioError, match=r"hazard.lidar.mount_B_m = \[0.0, 0.0, -150.0\]: .* off the vehicle"):
        load_scenario(None, ["hazard.avoidance=on", "hazard.lidar.mount_B_m=[0.0, 0.0, -150.0]"], "hazardous")
    # Found only in flight (the footprint at the scan's height): it named no field before.
    small = [f"terrain.{k}={v}" for k, v in dict(size_m=256.0, texture_px=1024, geometry_px=33, patch_size_m=0.0).items()]
    out = tmp_path / "r"
    argv = ["run", "--no-video", "--preset", "hazardous", "--out", str(out)]
    for a in ["hazard.avoidance=on", *small, "hazard.hda.scan_altitude_m=1000.0"]:
        argv += ["--set", a]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: hazard.hda.scan_altitude_m = 1000") and \
        "larger terrain.size_m" in err, err
    assert not out.exists()


# ----------------------------------------------------------------- scenario
def test_hazard_switches_default_off_and_a_bad_combination_is_one_line(tmp_path):
    sc = load_scenario(None)
    assert sc.hazard.avoidance == "off" and sc.hazard.scoring == "off" and not sc.hazard.scored
    hz = load_scenario(None, preset="hazardous")
    assert hz.terrain.target_clear_radius_m == 0.0 and hz.hazard.scored and hz.hazard.avoidance == "off"
    np.save(tmp_path / "d.npy", np.zeros((64, 64)))
    with pytest.raises(ScenarioError) as err:
        load_scenario(None, ["hazard.avoidance=on", "terrain.kind=dem", f"terrain.dem_path={tmp_path / 'd.npy'}",
                             "terrain.dem_spacing_m=2.0", "terrain.target_clear_radius_m=0"])
    assert "procedural" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ScenarioError, match="nav = 'estimator'"):
        load_scenario(None, ["hazard.avoidance=on", "nav=truth"])


# ----------------------------------------------------------------- closed loop
@pytest.mark.slow
def test_a_hazardous_landing_with_avoidance_retargets_and_lands_on_safe_ground():
    """Seed 1 of the hazardous preset, vision on (about 40 s): one scan near 100 m, a divert, a hazard-free touchdown."""
    from bench.sim.run import run

    sc = load_scenario(None, ["hazard.avoidance=on"], "hazardous")
    summary = run(sc).summary
    hz = summary["hazard"]
    assert summary["outcome"] == "landed"
    assert hz["scan"]["scanned"] and 90.0 <= hz["scan"]["height_m"] <= 110.0 and not hz["scan"]["no_safe_site"]
    assert hz["hazard_free"] is True and hz["scan"]["site_truth_hazard_free"] is True
    # It landed where it meant to: the site's truth position, within the drift it allowed for.
    fp = hz["footprint"]
    miss = math.hypot(fp["x_m"] - hz["scan"]["site_truth_xy_m"][0], fp["y_m"] - hz["scan"]["site_truth_xy_m"][1])
    assert miss <= 3 * hz["scan"]["nav_sigma_m"] + 0.5
    det = hz["scan"]["detection"]
    assert det["detection_rate"] > 0.8 and det["false_alarm_rate"] < 0.1


def test_campaign_table_counts_hazard_free_touchdowns():
    from bench.report.mc_report import campaign_table

    rows = [{"case": i, "outcome": "landed", "landed": True, "hazard_hazard_free": i % 4 != 0,
             "hazard_scan_scanned": True, "hazard_scan_no_safe_site": False} for i in range(8)]
    rows.append({"case": 8, "outcome": "safe_abort", "landed": False, "hazard_hazard_free": None,
                 "hazard_scan_scanned": True, "hazard_scan_no_safe_site": True})
    text = campaign_table(rows)
    assert "hazard-free touchdowns: 6/8 = 75.0%" in text and "no safe site: 1/9" in text
    assert "hazard-free" not in campaign_table([{"case": 0, "outcome": "landed", "landed": True}])


# ----------------------------------------------------------------- the mosaic, the sampling margin, the second scan
def test_sampling_margin_bounds_a_gaussian_rocks_worst_read():
    """The margin 4 s^2 / (3 h) bounds (and is close to) what a cell-mean post at the worst offset loses on the
    terrain's rock shape, integrated numerically: the cell [0, s]^2 from the top, h (1 - mean of the Gaussian)."""
    from gnc.hda import sampling_margin_m

    h = 0.3
    sigma = h / BOULDER_HEIGHT_RATIO / 4  # D / 4, with h = 0.5 D
    assert sigma == pytest.approx(0.15)
    for s in (0.05, 0.07, 0.1, 0.14):
        u = np.linspace(0.0, s, 2001)
        mean_1d = np.trapezoid(np.exp(-u**2 / (2 * sigma**2)), u) / s
        loss = h * (1.0 - mean_1d**2)
        margin = sampling_margin_m(s, h)
        assert 0.8 * margin <= loss <= margin, (s, loss, margin)  # the parabola bounds the Gaussian top
    assert sampling_margin_m(0.1, 0.3) == pytest.approx(0.0444, abs=1e-4)


def _rock_field(half: float = 11.0, s: float = 0.025, seed: int = 11):
    rng = np.random.default_rng(seed)
    X, Y = _grid(half, s)
    xy = (np.array([(x, y) for x in np.arange(-10, 11, 4.0) for y in np.arange(-10, 11, 4.0)])
          + rng.uniform(-0.05, 0.05, (36, 2)))
    h = sum(_gaussian_boulder(X, Y, x, y, 0.6) for x, y in xy)  # 36 rocks of 0.3 m, 4 m apart
    return _dem(h, s, (-half, -half)), xy


def _rock_reads(dem: SiteDem, xy: np.ndarray, flashes: int) -> np.ndarray:
    """The flight software's mosaic of ``flashes`` flashes from 100 m, dithered by half a ground sample (0.07 m)
    between flashes (:meth:`HazardAvoidance.add_flash`, then :meth:`HazardAvoidance.on_scan`); each rock's read."""
    R_BS = np.diag([1.0, -1.0, -1.0])
    lidar = FlashLidar(FlashLidarConfig(mount_B_m=(0.0, 0.0, 0.0)), np.random.default_rng(3))
    hda = HazardAvoidance(HdaConfig(flashes=flashes, rescan="off"))
    for k in range(flashes):
        r = np.array([0.3 + 0.07 * (k % 2), 0.2 + 0.07 * (k // 2), 100.0])
        msg = lidar.scan(0, r, R_BS, R_BS, dem)
        assert hda.wants_scan(100.0 if k == 0 else 1e3, "approach") and hda.flashes_wanted() == flashes - k
        if k < flashes - 1:
            hda.add_flash(msg, r, np.eye(3))
        else:
            hda.on_scan(msg, r, np.eye(3), 0.01, 0.5, np.zeros(3))
    assert not hda.wants_scan(50.0, "approach") and hda.stats.flashes == flashes
    d = hda.last_dem
    out = []
    for x, y in xy:
        j = int(round((x - d.origin_xy_m[0]) / d.spacing_m))
        i = int(round((y - d.origin_xy_m[1]) / d.spacing_m))
        out.append(float(d.height_m[i - 3:i + 4, j - 3:j + 4].max()))
    return np.array(out)


def test_a_threshold_rock_reads_within_its_sampling_error_and_the_mosaic_steadies_it():
    """36 rocks of 0.3 m from 100 m (ground sample 0.14 m, posts 0.1 m): their mean read lies within the sampling
    margin below 0.3 m (plus the noise's upward bias of a max); with 4 flashes fewer read below the margin."""
    from gnc.hda import sampling_margin_m

    dem, xy = _rock_field()
    one, four = _rock_reads(dem, xy, 1), _rock_reads(dem, xy, 4)
    margin = sampling_margin_m(0.1, 0.3)
    for reads in (one, four):
        assert 0.3 - margin <= float(np.mean(reads)) <= 0.3 + 0.02
    assert np.sum(four < 0.3 - margin) < np.sum(one < 0.3 - margin)
    assert float(np.min(four)) >= 0.3 - margin - 2 * 0.03 / math.sqrt(2)  # 2 returns a post: noise 0.021 m


def test_fused_margin_equals_brute_force_over_both_scans_hazards():
    """fuse_maps against an explicit loop: candidates are the second scan's rated safe posts; the margin is the
    least of the distance to its rated hazards and to the first scan's hazards outside them, less the shift."""
    from gnc.hazard import HazardMap
    from gnc.hda import fuse_maps

    rng = np.random.default_rng(4)
    s = 0.5

    def hmap(unsafe, origin):
        z = np.zeros(unsafe.shape, np.float32)
        return HazardMap(tilt_deg=z, roughness_m=z, unsafe=unsafe, hazard_distance_m=z, spacing_m=s, origin_xy_m=origin)

    first = hmap(rng.random((40, 40)) < 0.05, (-10.0, -10.0))
    second = hmap(rng.random((12, 12)) < 0.08, (-2.0, -1.0))
    rated = np.zeros((12, 12), bool)
    rated[2:10, 3:11] = True
    shift, pad = 0.7, 3.0
    fused = fuse_maps(second, rated, first, pad, shift)
    p = int(round(pad / s))
    assert fused.unsafe.shape == (12 + 2 * p, 12 + 2 * p) and fused.origin_xy_m == (-2.0 - pad, -1.0 - pad)
    # Hazards in L: the second's rated unsafe posts; the first's unsafe posts at the fused posts outside the rated.
    fx = fused.origin_xy_m[0] + s * np.arange(fused.unsafe.shape[1])
    fy = fused.origin_xy_m[1] + s * np.arange(fused.unsafe.shape[0])
    h2, h1 = [], []
    for i in range(len(fy)):
        for j in range(len(fx)):
            ii, jj = i - p, j - p
            if 0 <= ii < 12 and 0 <= jj < 12 and rated[ii, jj]:
                if second.unsafe[ii, jj]:
                    h2.append((fx[j], fy[i]))
            else:
                i1, j1 = int(round((fy[i] + 10.0) / s)), int(round((fx[j] + 10.0) / s))
                inside = 0 <= i1 < 40 and 0 <= j1 < 40
                if not inside or first.unsafe[i1, j1]:
                    h1.append((fx[j], fy[i]))
    h2, h1 = np.array(h2), np.array(h1)
    for i in range(len(fy)):
        for j in range(len(fx)):
            ii, jj = i - p, j - p
            cand = 0 <= ii < 12 and 0 <= jj < 12 and rated[ii, jj] and not second.unsafe[ii, jj]
            assert fused.unsafe[i, j] == (not cand)
            if cand:
                d2 = np.hypot(h2[:, 0] - fx[j], h2[:, 1] - fy[i]).min()
                d1 = np.hypot(h1[:, 0] - fx[j], h1[:, 1] - fy[i]).min()
                assert fused.hazard_distance_m[i, j] == pytest.approx(min(d2, max(d1 - shift, 0.0)), abs=1e-3)


def test_view_offset_is_where_the_boresight_meets_the_ground():
    """A lander tilted by theta about x, h above the target, the sensor on the axis: the boresight meets the
    ground h tan(theta) off, in y; the second scan waits for it to come within rescan_view_frac of the half-width."""
    hda = HazardAvoidance(HdaConfig())
    R_BS = np.diag([1.0, -1.0, -1.0])
    hda._mount = (R_BS, np.zeros(3), 20.0)  # what the first scan's message states
    hda.scanned, hda.awaiting_rescan = True, True
    h, theta = 45.0, math.radians(8.0)
    R_LB = Rotation.from_rotvec([theta, 0.0, 0.0]).as_matrix()
    target = np.array([3.0, -2.0, 1.0])
    r = target + np.array([0.0, 0.0, h])
    assert hda.view_offset_m(r, R_LB, target) == pytest.approx(h * math.tan(theta), rel=1e-9)
    half = h * math.tan(math.radians(10.0))
    assert h * math.tan(theta) > 0.5 * half and not hda.wants_scan(h, "approach", r, R_LB, target)
    assert hda.wants_scan(h, "terminal", r, np.eye(3), target)  # upright over the target
    assert not hda.wants_scan(55.0, "terminal", target + [0, 0, 55.0], np.eye(3), target)  # above rescan_altitude_m
    r_off = r + np.array([0.6 * half, 0.0, 0.0])  # upright but beside it
    assert not hda.wants_scan(h, "approach", r_off, np.eye(3), target)


def test_no_site_in_the_first_scan_gives_a_second_chance_before_declaring():
    """Egg-crate ground with a 7 m flat disk: too small for the first scan's margin (a large drift sigma), so it
    moves the target to the disk's centre (its best-margin post) without declaring; the second scan, with a
    smaller drift, finds a site in the disk. Without the disk the second scan declares; with rescan = 'off'
    the first one does."""
    half, s = 25.0, 0.1
    X, Y = _grid(half, s)
    rough = 0.5 * np.sin(2 * np.pi * X / 3.0) * np.sin(2 * np.pi * Y / 3.0)
    centre = np.array([6.0, -5.0])
    h = np.where(np.hypot(X - centre[0], Y - centre[1]) <= 7.0, 0.0, rough)
    e = np.array([-3.0, 2.0, 0.0])  # the navigation error
    target = np.zeros(3) + e
    cfg = HdaConfig(flashes=1, map=HazardConfig(max_divert_m=30.0))
    msg, R_LB = _scan_over(h, half, s, np.array([0.0, 0.0, 70.0]), pixels=192)
    hda = HazardAvoidance(cfg)
    new = hda.on_scan(msg, np.array([0.0, 0.0, 70.0]) + e, R_LB, 0.1, 0.5, target)  # sigma about 3.5 m
    assert hda.stats.no_safe_site and not hda.no_safe_site and hda.awaiting_rescan
    # The disk's best-margin post: its centre, to within the posts' rounding and the lidar's sampling.
    assert new is not None and np.hypot(*(new[:2] - e[:2] - centre)) <= 0.5
    assert hda.stats.best_margin_m == pytest.approx(7.0 - 2.4, abs=0.4)  # the disk less the footprint's reach
    # The second scan from 40 m over the new target, a smaller drift.
    r2 = np.array([*(new[:2] - e[:2]), 40.0])
    assert hda.wants_scan(39.0, "approach", r2 + e, R_LB, np.array([*new[:2], 0.0]))
    msg2, _ = _scan_over(h, half, s, r2, pixels=192)
    site = hda.on_scan(msg2, r2 + e, R_LB, 0.005, 0.2, new)
    assert site is not None and not hda.no_safe_site and hda.rescanned and not hda.wants_scan(30.0, "terminal")
    st2 = hda.rescan_stats
    assert st2.site.margin_m >= 3 * st2.nav_sigma_m
    assert np.hypot(*(site[:2] - e[:2] - centre)) <= 7.0 - 2.2 - 3 * st2.nav_sigma_m + 0.2
    # No disk: the second scan declares.
    msg_r, _ = _scan_over(rough, half, s, np.array([0.0, 0.0, 70.0]), pixels=192)
    hda2 = HazardAvoidance(cfg)
    assert hda2.on_scan(msg_r, np.array([0.0, 0.0, 70.0]) + e, R_LB, 0.1, 0.5, target) is None
    assert not hda2.no_safe_site and hda2.awaiting_rescan  # nothing safe in view: the target stays, scan again
    msg_r2, _ = _scan_over(rough, half, s, np.array([0.0, 0.0, 40.0]), pixels=192)
    assert hda2.on_scan(msg_r2, np.array([0.0, 0.0, 40.0]) + e, R_LB, 0.005, 0.2, target) is None
    assert hda2.no_safe_site
    # rescan = 'off': declared at the first scan.
    hda3 = HazardAvoidance(cfg.model_copy(update={"rescan": "off"}))
    assert hda3.on_scan(msg, np.array([0.0, 0.0, 70.0]) + e, R_LB, 0.1, 0.5, target) is None and hda3.no_safe_site


def test_the_flashes_are_registered_through_the_estimated_motion_not_the_jumping_estimate():
    """Four flashes while descending at 10 m/s; a filter update moves the estimate 0.12 m up and 0.04 m across
    between the second and third (as measured in the loop). Registered through the estimated velocity, the
    mosaic equals the one placed through the true poses (plus the last flash's error, then common to all);
    through each tick's estimate, the rocks' tops read off by centimetres."""
    dem, xy = _rock_field()
    R_BS = np.diag([1.0, -1.0, -1.0])
    lidar = FlashLidar(FlashLidarConfig(mount_B_m=(0.0, 0.0, 0.0)), np.random.default_rng(3))
    v = np.array([0.5, -0.3, -10.0])
    common = np.array([3.0, -2.0, 0.5])  # the navigation error all flashes share
    jump = np.array([0.04, 0.0, 0.12])
    poses = [np.array([0.3, 0.2, 100.0]) + v * 0.02 * k for k in range(4)]
    msgs = []
    for k, r in enumerate(poses):
        R_LS = Rotation.from_rotvec([2e-3 * k, 1e-3 * k, 0.0]).as_matrix() @ R_BS  # it turns, too
        m = lidar.scan(20_000_000 * k, r, R_LS, R_BS, dem)
        msgs.append((m, R_LS @ R_BS.T))

    def mosaic(v_est):
        hda = HazardAvoidance(HdaConfig(rescan="off"))
        for k, (m, R_LB) in enumerate(msgs):
            r_est = poses[k] + common + (jump if k >= 2 else 0.0)
            G = Rotation.from_rotvec([0.01, 0.0, 0.0]).as_matrix() @ R_LB  # a drifted gyro attitude: only its
            R_est = Rotation.from_rotvec([0.0, 0.0, 1e-5]).as_matrix() @ R_LB if k < 3 else R_LB  # relative use
            if k < 3:
                hda.add_flash(m, r_est, R_est, G)
            else:
                hda.on_scan(m, r_est, R_est, 0.01, 0.5, np.zeros(3), None, G, v_est)
        d = hda.last_dem
        return np.array([float(d.height_m[int(round((y + common[1] - d.origin_xy_m[1]) / 0.1)) - 3:
                                           int(round((y + common[1] - d.origin_xy_m[1]) / 0.1)) + 4,
                                           int(round((x + common[0] - d.origin_xy_m[0]) / 0.1)) - 3:
                                           int(round((x + common[0] - d.origin_xy_m[0]) / 0.1)) + 4].max())
                         for x, y in xy])

    # The reference: every flash through its true pose, moved by the error of the last flash's estimate.
    pts = np.concatenate([scan_points_L(m, poses[k] + common + jump, R_LB) for k, (m, R_LB) in enumerate(msgs)])
    ref_dem = grid_dem(pts, 0.1)
    ref = np.array([float(ref_dem.height_m[int(round((y + common[1] - ref_dem.origin_xy_m[1]) / 0.1)) - 3:
                                           int(round((y + common[1] - ref_dem.origin_xy_m[1]) / 0.1)) + 4,
                                           int(round((x + common[0] - ref_dem.origin_xy_m[0]) / 0.1)) - 3:
                                           int(round((x + common[0] - ref_dem.origin_xy_m[0]) / 0.1)) + 4].max())
                    for x, y in xy])
    registered, jumping = mosaic(v), mosaic(None)
    # Registered to the last flash: the reference (the jump is then common to all flashes), to 1 mm.
    np.testing.assert_allclose(registered, ref, atol=1e-3)
    assert np.max(np.abs(jumping - ref)) > 0.03
