"""Campaign report (bench/report/mc_report.py): Wilson interval, error ellipse, report PNG, text table."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from bench.report.mc_report import (
    FIGURE_DPI,
    FIGURE_SIZE_IN,
    campaign_figure,
    campaign_table,
    error_ellipse,
    outcome_counts,
    wilson_interval,
    write_campaign_report,
)
from bench.report.io import save_figure
from models.terrain import Terrain

CRITERIA = {"v_vertical_max_mps": 1.0, "v_horizontal_max_mps": 0.5, "tilt_max_deg": 10.0, "settle_s": 5.0}
Z95 = 1.959963984540054  # Phi^-1(0.975), written out so the reference does not use scipy
Z90 = 1.6448536269514722  # Phi^-1(0.95)


def wilson_reference(k: int, n: int, z: float) -> tuple[float, float]:
    """Closed form, written independently: (2k + z² ∓ z·sqrt(z² + 4k(n-k)/n)) / (2(n + z²))."""
    root = z * math.sqrt(z * z + 4.0 * k * (n - k) / n)
    den = 2.0 * (n + z * z)
    return (2 * k + z * z - root) / den, (2 * k + z * z + root) / den


# ===================================================================== Wilson
@pytest.mark.parametrize(("k", "n", "expected"), [
    # Hand-derived with z = 1.96, z² = 3.8415 (and the published 19/20 example):
    (19, 20, (0.7639, 0.9911)),
    (0, 10, (0.0, 3.8415 / 13.8415)),  # 0.27753
    (10, 10, (10 / 13.8415, 1.0)),  # 0.72247
    (5, 10, (0.2366, 0.7634)),
    (1, 1, (1 / 4.8415, 1.0)),  # 0.20655
])
def test_wilson_known_values(k, n, expected):
    low, high = wilson_interval(k, n)
    assert low == pytest.approx(expected[0], abs=2e-4)
    assert high == pytest.approx(expected[1], abs=2e-4)


@pytest.mark.parametrize("n", [1, 2, 7, 20, 100, 1000])
def test_wilson_matches_closed_form_everywhere(n):
    for k in range(0, n + 1, max(1, n // 13)):
        for conf, z in ((0.95, Z95), (0.90, Z90)):
            ref = wilson_reference(k, n, z)
            got = wilson_interval(k, n, confidence=conf)
            assert got == pytest.approx(ref, abs=1e-12), (k, n, conf)
            assert 0.0 <= got[0] <= k / n <= got[1] <= 1.0
        low, _ = wilson_interval(k, n)
        mirror = wilson_interval(n - k, n)
        assert low == pytest.approx(1.0 - mirror[1], abs=1e-12)


def test_wilson_edges_exact_and_errors():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    assert wilson_interval(0, 10)[0] == 0.0
    assert wilson_interval(10, 10)[1] == 1.0
    # Wider with more confidence, narrower with more data.
    assert np.diff(wilson_interval(19, 20, 0.99))[0] > np.diff(wilson_interval(19, 20, 0.95))[0]
    assert np.diff(wilson_interval(190, 200))[0] < np.diff(wilson_interval(19, 20))[0]
    for bad in [(-1, 10), (11, 10), (1.5, 10), (True, 3), (1, -1)]:
        with pytest.raises(ValueError):
            wilson_interval(*bad)
    for conf in (0.0, 1.0, 1.5):
        with pytest.raises(ValueError, match="confidence"):
            wilson_interval(1, 2, conf)


# ==================================================================== ellipse
def test_error_ellipse_exact_small_set():
    # Mean 0; ddof=1 variances x: 2/3, y: 8/3, no covariance -> major axis along y (90°).
    xy = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 2.0], [0.0, -2.0]]) + [5.0, -3.0]
    centre, width, height, angle = error_ellipse(xy)
    np.testing.assert_allclose(centre, [5.0, -3.0], atol=1e-12)
    assert width == pytest.approx(6.0 * math.sqrt(8.0 / 3.0))
    assert height == pytest.approx(6.0 * math.sqrt(2.0 / 3.0))
    assert angle == pytest.approx(90.0)
    _, w1, h1, _ = error_ellipse(xy, n_sigma=1.0)
    assert (w1, h1) == pytest.approx((width / 3.0, height / 3.0))


@pytest.mark.parametrize("theta_deg", [30.0, -60.0, 0.0, 75.0])
def test_error_ellipse_recovers_known_covariance(theta_deg):
    rng = np.random.default_rng(7)
    s_major, s_minor = 4.0, 1.0
    th = math.radians(theta_deg)
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    cov = rot @ np.diag([s_major**2, s_minor**2]) @ rot.T
    xy = rng.multivariate_normal([3.0, -2.0], cov, size=40_000)
    xy[::1000] = np.nan  # non-finite rows are dropped
    centre, width, height, angle = error_ellipse(xy, n_sigma=3.0)
    np.testing.assert_allclose(centre, [3.0, -2.0], atol=0.1)
    assert width == pytest.approx(2 * 3 * s_major, rel=0.02)
    assert height == pytest.approx(2 * 3 * s_minor, rel=0.02)
    assert -90.0 < angle <= 90.0
    # Axis direction (mod 180°).
    diff = (angle - theta_deg + 90.0) % 180.0 - 90.0
    assert abs(diff) < 1.0


def test_error_ellipse_errors():
    with pytest.raises(ValueError, match="at least 2"):
        error_ellipse(np.array([[1.0, 2.0], [np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        error_ellipse(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="n_sigma"):
        error_ellipse(np.zeros((4, 2)), n_sigma=0.0)
    # Degenerate (collinear) points: zero minor axis, angle along the line.
    _, w, h, a = error_ellipse(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]))
    assert h == pytest.approx(0.0, abs=1e-9) and a == pytest.approx(45.0) and w > 0


# ====================================================================== rows
def _row(case, outcome, landed, vv=None, vh=None, tilt=None, miss=None, x=None, y=None, t=None, wall=2.0,
         error=None):
    return {"case": case, "seed": 1000 + case, "outcome": outcome, "landed": landed, "touchdown_t_s": t,
            "touchdown_v_vertical_mps": vv, "touchdown_v_horizontal_mps": vh, "touchdown_tilt_deg": tilt,
            "touchdown_miss_distance_m": miss, "touchdown_x_m": x, "touchdown_y_m": y, "fuel_used_kg": 50.0,
            "wall_time_s": wall, "error": error}


@pytest.fixture
def rows() -> list[dict]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(40):
        x, y = rng.normal(2.0, 3.0), rng.normal(-1.0, 1.5)
        out.append(_row(i, "landed", True, vv=rng.uniform(0.2, 0.9), vh=rng.uniform(0.0, 0.4),
                        tilt=rng.uniform(0, 8), miss=math.hypot(x, y), x=x, y=y, t=30.0 + i * 0.1,
                        wall=1.0 + i * 0.05))
    out.append(_row(40, "hard_landing", False, vv=2.5, vh=0.3, tilt=4.0, miss=6.0, x=6.0, y=0.0, t=31.0))
    out.append(_row(41, "tipped_over", False, vv=0.8, vh=1.2, tilt=40.0, miss=3.0, x=0.0, y=3.0, t=29.0))
    out.append(_row(42, "fuel_exhausted", False, wall=3.0))
    out.append(_row(43, "error", False, vv=float("nan"), wall=None,
                    error="RuntimeError: MuJoCo blew up\nTraceback (most recent call last):\n  ..."))
    out.append(_row(44, "error", False, wall=None, error="TimeoutError: " + "x" * 500))
    out.append({"case": 45, "seed": 1045, "outcome": "error", "landed": False, "error": "killed",
                "case_wall_time_s": 600.0})  # runner-failed row: most keys missing
    return out


@pytest.fixture
def terrain() -> Terrain:
    n = 65
    ax = np.linspace(-64, 64, n)
    h = (0.5 * np.sin(ax[None, :] / 6.0) * np.cos(ax[:, None] / 9.0)).astype(np.float32)
    h -= h[n // 2, n // 2]
    return Terrain(height_m=h, size_m=128.0, albedo=np.full((64, 64), 120, np.uint8),
                   craters=np.zeros((0, 3)), boulders=np.zeros((0, 3)))


def _axes(fig) -> dict:
    return {ax.get_label(): ax for ax in fig.axes if ax.get_label()}


def _hist_total(ax) -> int:
    return round(sum(p.get_height() for p in ax.patches))


# ===================================================================== figure
def test_report_png_size_and_atomic(tmp_path, rows, terrain):
    path = write_campaign_report(rows, CRITERIA, tmp_path / "sub" / "report.png", terrain=terrain, title="t")
    img = cv2.imread(str(path))
    assert img is not None
    assert img.shape[:2] == (int(FIGURE_SIZE_IN[1] * FIGURE_DPI), int(FIGURE_SIZE_IN[0] * FIGURE_DPI))
    assert img.std() > 10  # not blank
    assert [p.name for p in path.parent.iterdir()] == ["report.png"]  # no temporary left behind
    # Bad input: ValueError, and the existing report is not touched.
    before = path.read_bytes()
    with pytest.raises(ValueError, match="tilt_max_deg"):
        write_campaign_report(rows, {"tilt_max_deg": "steep"}, path)
    with pytest.raises(ValueError, match="rows"):
        write_campaign_report({"case": 1}, CRITERIA, path)
    assert path.read_bytes() == before


def test_figure_content_matches_independent_computation(rows, terrain):
    fig = campaign_figure(rows, CRITERIA, terrain)
    axd = _axes(fig)
    assert set(axd) >= {"map", "v_vertical", "v_horizontal", "tilt", "outcomes", "rate"}

    # Outcome bars equal the counts.
    expected = {"landed": 40, "hard_landing": 1, "tipped_over": 1, "fuel_exhausted": 1, "error": 3}
    assert outcome_counts(rows) == expected
    heights = [int(p.get_height()) for p in axd["outcomes"].patches]
    assert heights == list(expected.values())

    # Histograms hold every finite value of the cases that touched down; the limit line is where it should be.
    for panel, key, crit in (("v_vertical", "touchdown_v_vertical_mps", "v_vertical_max_mps"),
                             ("v_horizontal", "touchdown_v_horizontal_mps", "v_horizontal_max_mps"),
                             ("tilt", "touchdown_tilt_deg", "tilt_max_deg")):
        finite = [r[key] for r in rows if r.get(key) is not None and math.isfinite(r[key])]
        assert _hist_total(axd[panel]) == len(finite) == 42
        limit_x = [ln.get_xdata()[0] for ln in axd[panel].lines if ln.get_linestyle() == "--"]
        assert limit_x == [CRITERIA[crit]]

    # The ellipse is the 3-sigma ellipse of the touchdown points, computed here with numpy directly.
    xy = np.array([[r["touchdown_x_m"], r["touchdown_y_m"]] for r in rows if r.get("touchdown_x_m") is not None])
    (ell,) = [p for p in axd["map"].patches if p.get_gid() == "error_ellipse"]
    evals = np.linalg.eigvalsh(np.cov(xy.T))
    assert ell.width == pytest.approx(6 * math.sqrt(evals[1]))
    assert ell.height == pytest.approx(6 * math.sqrt(evals[0]))
    np.testing.assert_allclose(ell.center, xy.mean(axis=0))
    # Map crop holds all touchdowns and the target; the hillshade is drawn.
    x0, x1 = axd["map"].get_xlim()
    y0, y1 = axd["map"].get_ylim()
    assert x0 < min(xy[:, 0].min(), 0) and x1 > max(xy[:, 0].max(), 0)
    assert y0 < min(xy[:, 1].min(), 0) and y1 > max(xy[:, 1].max(), 0)
    assert len(axd["map"].images) == 1
    ext = ell.get_extents().transformed(axd["map"].transData.inverted())  # whole ellipse inside the crop
    assert x0 <= ext.x0 and ext.x1 <= x1 and y0 <= ext.y0 and ext.y1 <= y1
    # Points: one scatter per outcome with touchdown positions, sizes add up.
    assert sum(len(c.get_offsets()) for c in axd["map"].collections) == len(xy)

    # Success-rate error bar: 40/46 with its Wilson interval.
    lo, hi = wilson_reference(40, 46, Z95)
    line = axd["rate"].lines[0]
    assert line.get_xdata()[0] == pytest.approx(40 / 46)
    assert "40/46" in axd["rate"].get_title()
    segs = next(c for c in axd["rate"].collections if hasattr(c, "get_segments")).get_segments()
    np.testing.assert_allclose([segs[0][0][0], segs[0][1][0]], [lo, hi], atol=1e-9)


@pytest.mark.parametrize("case", ["empty", "one", "one_failed", "all_failed", "nans", "two_points"])
def test_report_degenerate_inputs(tmp_path, case, terrain):
    rows = {
        "empty": [],
        "one": [_row(0, "landed", True, vv=0.5, vh=0.1, tilt=2.0, miss=1.0, x=1.0, y=0.0, t=30.0)],
        "one_failed": [_row(0, "error", False, error="boom")],
        "all_failed": [_row(i, "diverged", False) for i in range(5)],
        "nans": [_row(i, "timeout", False, vv=math.nan, vh=math.nan, tilt=math.nan, x=math.nan, y=1.0)
                 for i in range(3)],
        "two_points": [_row(i, "landed", True, vv=0.5, x=float(i), y=0.0, t=1.0) for i in range(2)],
    }[case]
    for ter in (terrain, None):
        # What write_campaign_report does (figure, then the atomic PNG), with the figure kept to inspect.
        fig = campaign_figure(rows, CRITERIA, ter)
        path = save_figure(fig, tmp_path / f"{case}.png", dpi=FIGURE_DPI)
        assert cv2.imread(str(path)).shape[:2] == (1150, 1400)  # 14 x 11.5 in at 100 dpi
        axd = _axes(fig)
        assert not [p for p in axd["map"].patches if p.get_gid() == "error_ellipse"]  # < 3 points
        assert len(axd["map"].images) == (1 if ter is not None else 0)
    assert _hist_total(axd["v_vertical"]) == sum(
        1 for r in rows if r["touchdown_v_vertical_mps"] is not None and math.isfinite(r["touchdown_v_vertical_mps"]))


def test_report_without_criteria_and_far_points(tmp_path):
    # Points far outside any terrain tile and no limits: still draws, crop holds the points.
    rows = [_row(i, "landed", True, vv=0.3, vh=0.1, tilt=1.0, x=500.0 + i, y=-300.0 + 2 * i, t=1.0)
            for i in range(4)]
    fig = campaign_figure(rows, None)
    axd = _axes(fig)
    assert not [ln for ln in axd["tilt"].lines if ln.get_linestyle() == "--"]
    assert axd["map"].get_xlim()[1] > 503 and axd["map"].get_ylim()[0] < -300
    assert write_campaign_report(rows, None, tmp_path / "r.png").is_file()


# ====================================================================== table
def _stat_row(text: str, label: str) -> list[str]:
    (line,) = [ln for ln in text.splitlines() if ln.strip().startswith(label)]
    return line.split()


def test_campaign_table_numbers(rows):
    text = campaign_table(rows, CRITERIA)
    lines = text.splitlines()
    assert lines[0] == "landbench mc: 46 cases"
    # Outcome counts.
    for name, count in {"landed": 40, "hard_landing": 1, "tipped_over": 1, "fuel_exhausted": 1, "error": 3}.items():
        (ln,) = [ln for ln in lines if ln.split()[:1] == [name]]
        assert int(ln.split()[1]) == count
    # Success rate and Wilson interval (independent closed form).
    lo, hi = wilson_reference(40, 46, Z95)
    assert f"40/46 = {40 / 46:.1%}" in text
    assert f"{lo:.1%} – {hi:.1%}" in text
    # Touchdown statistics over the cases that landed or touched down (finite values only).
    td = [r for r in rows if r["landed"] or (r.get("touchdown_t_s") is not None)]
    assert "over 42 cases" in text
    for key, label, spec in (("touchdown_v_vertical_mps", "vertical speed", ".2f"),
                             ("touchdown_v_horizontal_mps", "horizontal speed", ".2f"),
                             ("touchdown_tilt_deg", "tilt", ".1f"),
                             ("touchdown_miss_distance_m", "miss distance", ".2f")):
        v = np.array([r[key] for r in td], dtype=float)
        words = _stat_row(text, label)
        nums = [w for w in words if w[0].isdigit()]
        assert nums[:3] == [format(v.mean(), spec), format(np.percentile(v, 95), spec), format(v.max(), spec)]
    # Over-limit counts.
    assert _stat_row(text, "vertical speed")[-2:] == ["1", "over"]  # 2.5 m/s
    assert _stat_row(text, "tilt")[-2:] == ["1", "over"]  # 40 deg
    assert _stat_row(text, "horizontal speed")[-2:] == ["1", "over"]  # 1.2 m/s
    # Mean wall time: wall_time_s, or the runner's case_wall_time_s where present.
    walls = [r["wall_time_s"] for r in rows[:43]] + [600.0]
    assert f"wall time per case: mean {np.mean(walls):.2f} s (44 timed)" in text


def test_campaign_table_failed_list(rows):
    text = campaign_table(rows, CRITERIA)
    lines = text.splitlines()
    i = lines.index("failed cases (6):")
    failed = lines[i + 1:]
    assert len(failed) == 6
    assert failed[0] == "  case 40 (seed 1040): hard_landing"
    assert failed[3] == "  case 43 (seed 1043): error: RuntimeError: MuJoCo blew up …"
    assert "Traceback" not in text
    assert failed[4].startswith("  case 44 (seed 1044): error: TimeoutError: xxx") and failed[4].endswith("…")
    assert len(failed[4]) < 150
    assert failed[5] == "  case 45 (seed 1045): error: killed"


def test_campaign_table_edge_cases():
    empty = campaign_table([], CRITERIA)
    assert "0 cases" in empty and "0/0" in empty and "0.0% – 100.0%" in empty and "failed cases: none" in empty
    one = campaign_table([_row(0, "landed", True, vv=0.5, vh=0.1, tilt=2.0, miss=1.0, x=1.0, y=0.0, t=3.0)], None)
    assert "1 case\n" in one + "\n" and "1/1 = 100.0%" in one and "failed cases: none" in one
    assert _stat_row(one, "vertical speed")[2:5] == ["0.50", "m/s", "0.50"]
    nan = campaign_table([_row(0, "diverged", False, vv=math.nan)], CRITERIA)
    assert "—" in _stat_row(nan, "vertical speed")
    assert "over 0 cases" in nan
    with pytest.raises(ValueError):
        campaign_table("rows", CRITERIA)
    with pytest.raises(ValueError):
        campaign_table([1, 2], CRITERIA)


def test_statistics_only_over_touchdowns():
    # A case with speeds recorded but no touchdown (no t, not landed) is left out of the statistics and histograms.
    rows = [_row(0, "landed", True, vv=0.5, vh=0.1, tilt=2.0, miss=1.0, x=1.0, y=0.0, t=3.0),
            _row(1, "hard_landing", False, vv=1.5, vh=0.2, tilt=3.0, miss=2.0, x=2.0, y=0.0, t=4.0),
            _row(2, "timeout", False, vv=9.0, vh=9.0, tilt=90.0, miss=99.0)]
    text = campaign_table(rows, CRITERIA)
    assert "over 2 cases" in text
    assert _stat_row(text, "vertical speed")[2:4] == ["1.00", "m/s"]  # mean of 0.5 and 1.5
    assert _stat_row(text, "tilt")[-2:] == ["0", "over"]
    axd = _axes(campaign_figure(rows, CRITERIA))
    assert _hist_total(axd["v_vertical"]) == 2


def test_campaign_table_peak_memory():
    rows = [{"case": i, "outcome": "landed", "landed": True, "case_peak_rss_mb": m}
            for i, m in enumerate([500.0, 520.0, None])]
    assert "peak memory per worker: max 520 MB, mean 510 MB" in campaign_table(rows)
    assert "peak memory" not in campaign_table([{"case": 0, "outcome": "landed", "landed": True}])


def test_map_nav_lines_against_hand_computed_figures():
    from bench.report.mc_report import map_nav_lines

    rng = np.random.default_rng(5)
    rows = []
    for i in range(40):
        e50 = rng.normal(0.0, 0.3, 2)
        tx, ty = rng.normal(0.0, 2.0, 2)
        rows.append({"case": i, "outcome": "landed", "landed": True, "map_nav_attempts": 30, "map_nav_updates": 27,
                     "map_nav_fixes_accepted_by_matcher": 28, "map_nav_gate_rejected": 1,
                     "map_nav_false_locks": 2 if i == 7 else 0, "map_nav_false_locks_used": 1 if i == 7 else 0,
                     "map_nav_nav_err_map_frame_50m_xy_m_0": e50[0], "map_nav_nav_err_map_frame_50m_xy_m_1": e50[1],
                     "map_nav_target_xy_L_m_0": tx, "map_nav_target_xy_L_m_1": ty,
                     "touchdown_x_m": tx + rng.normal(0.0, 0.5), "touchdown_y_m": ty + rng.normal(0.0, 0.5)})
    rows.append({"case": 40, "outcome": "landed", "landed": True})  # a case flown without map navigation
    text = "\n".join(map_nav_lines(rows))
    assert "map navigation over 40 cases: 1080 fixes used of 1200 attempts (1120 accepted by the matcher, 40 gated out)" in text
    # Campaigns written since the re-lock (MapNavConfig.relock_after) count them too.
    for i, r in enumerate(rows[:40]):
        r["map_nav_relocks"] = 1 if i in (3, 17, 29) else 0
    assert "(1120 accepted by the matcher, 40 gated out, 3 re-locks)" in "\n".join(map_nav_lines(rows))
    assert "false locks: 2/1120 fixes" in text and "cases with one: 1/40" in text and "1 used by the filter" in text

    def three_sigma_and_max(dx, dy):
        sq = [v * v for v in dx] + [v * v for v in dy]
        return 3.0 * math.sqrt(sum(sq) / len(sq)), max(math.hypot(a, b) for a, b in zip(dx, dy))

    nav = rows[:40]
    checks = {
        "nav error at 50 m (map frame)": ([r["map_nav_nav_err_map_frame_50m_xy_m_0"] for r in nav],
                                          [r["map_nav_nav_err_map_frame_50m_xy_m_1"] for r in nav]),
        "miss vs map target": ([r["touchdown_x_m"] - r["map_nav_target_xy_L_m_0"] for r in nav],
                               [r["touchdown_y_m"] - r["map_nav_target_xy_L_m_1"] for r in nav]),
        "absolute miss": ([r["touchdown_x_m"] for r in nav], [r["touchdown_y_m"] for r in nav]),
    }
    for label, (dx, dy) in checks.items():
        three, worst = three_sigma_and_max(dx, dy)
        line = next(ln for ln in text.splitlines() if label in ln)
        flat = " ".join(line.split())
        assert f"3σ per axis {three:.2f} m, max {worst:.2f} m (40 cases)" in flat, line
    assert map_nav_lines([{"case": 0, "outcome": "landed"}]) == []
    assert "keyframe" not in text  # rows without keyframe columns (a campaign from before them)
    # Keyframe lines: pooled over the fixes used (RMS weighted by each case's fixes).
    kf = [dict(r, map_nav_keyframe_t_s=33.0 if i < 3 else None, map_nav_keyframe_attempts=[10, 20, 0, 0][i],
               map_nav_keyframe_updates=[8, 18, 0, 0][i], map_nav_keyframe_gate_rejected=[1, 0, 0, 0][i],
               map_nav_keyframe_refused=[1, 2, 0, 0][i], map_nav_keyframe_false_locks=[0, 1, 0, 0][i],
               map_nav_keyframe_fix_err_rms_m=[0.02, 0.05, None, None][i],
               map_nav_keyframe_fix_nis_mean=[1.0, 3.0, None, None][i]) for i, r in enumerate(rows[:4])]
    line = next(ln for ln in map_nav_lines(kf) if "keyframe" in ln)
    pooled = math.sqrt((8 * 0.02**2 + 18 * 0.05**2) / 26)
    nis = (8 * 1.0 + 18 * 3.0) / 26
    assert (f"keyframe in 3/4 cases: 26 fixes used of 30 attempts (3 refused, 1 gated out); fix error RMS "
            f"{pooled:.3f} m, mean NIS {nis:.2f} (2 expected), false locks 1") in " ".join(line.split()), line
    assert "taken again" not in line  # a campaign from before keyframes could be taken again
    for r, n in zip(kf, (1, 4, 0, 0)):
        r["map_nav_keyframes"] = n
    line = next(ln for ln in map_nav_lines(kf) if "keyframe" in ln)
    assert line.endswith("false locks 1; 3 keyframes taken again in 1 case"), line
