"""Output files of one run (bench/report/report.py): Parquet telemetry, plots, camera video, terminal summary."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.report.report import (
    CHECK_FAIL,
    CHECK_OK,
    DRAW_SHIFT_BITS,
    MOTION_COLOR_BGR,
    PLOT_COLUMNS_NAV,
    PLOT_COLUMNS_PLAIN,
    TRACK_COLOR_BGR,
    TRACK_RADIUS_PX,
    CameraVideo,
    draw_tracks,
    frame_caption,
    plot_canvas,
    read_telemetry_parquet,
    summary_table,
    write_plots,
    write_telemetry_parquet,
    write_video,
)
from models.terrain import Terrain

CRITERIA = {"v_vertical_max_mps": 1.0, "v_horizontal_max_mps": 0.5, "tilt_max_deg": 10.0, "settle_s": 5.0}


@pytest.fixture
def terrain() -> Terrain:
    return Terrain(height_m=np.zeros((33, 33), np.float32), size_m=256.0, albedo=np.full((64, 64), 120, np.uint8),
                   craters=np.zeros((0, 3)), boulders=np.zeros((0, 3)))


def descent_telemetry(n: int = 501, nav: bool = False) -> dict[str, np.ndarray]:
    """A synthetic 10 s descent at 50 Hz from (60, -40, 300) m to touchdown near the target."""
    t = np.arange(n) * 0.02
    s = t / t[-1]
    shape = (1 - s) ** 2  # eases into touchdown
    r = np.stack([60 * shape + 1.0 * s, -40 * shape + 0.5 * s, 300 * shape + 1.5], axis=1)
    v = np.gradient(r, t, axis=0)
    tilt = 12 * (1 - s)
    half = np.radians(tilt) / 2
    phase = np.where(s < 0.7, "approach", np.where(s < 0.98, "terminal", "touchdown"))
    thrust_max = 16_000.0
    throttle = np.clip(0.3 + 0.6 * s, 0, 1)
    cols = {
        "t_s": t,
        "r_x_m": r[:, 0], "r_y_m": r[:, 1], "r_z_m": r[:, 2],
        "v_x_mps": v[:, 0], "v_y_mps": v[:, 1], "v_z_mps": v[:, 2],
        "q_w": np.cos(half), "q_x": np.sin(half), "q_y": np.zeros(n), "q_z": np.zeros(n),
        "omega_x_radps": np.zeros(n), "omega_y_radps": np.zeros(n), "omega_z_radps": np.zeros(n),
        "mass_kg": 1800 - 20 * t, "propellant_kg": 600 - 20 * t,
        "height_m": r[:, 2] - 1.5,
        "tilt_deg": tilt,
        "thrust_cmd_N": throttle * thrust_max, "thrust_N": throttle * thrust_max, "throttle": throttle,
        "torque_x_Nm": np.zeros(n), "torque_y_Nm": np.zeros(n), "torque_z_Nm": np.zeros(n),
        "a_cmd_x_mps2": np.zeros(n), "a_cmd_y_mps2": np.zeros(n), "a_cmd_z_mps2": np.full(n, -0.5),
        "engine_on": s < 0.98,
        "phase": phase,
        "legs_in_contact": np.where(s >= 0.98, 4, 0).astype(np.int64),
    }
    if nav:
        rng = np.random.default_rng(0)
        for kind, unit, scale in (("r", "m", 2.0), ("v", "mps", 0.1)):
            for ax in "xyz":
                sigma = scale * (1 + 2 * (1 - s))
                cols[f"nav_err_{kind}_{ax}_{unit}"] = sigma * rng.standard_normal(n)
                cols[f"nav_sigma_{kind}_{ax}_{unit}"] = sigma
    return cols


def summary(**over) -> dict:
    base = {
        "outcome": "landed", "landed": True,
        "touchdown": {"t_s": 9.8, "v_vertical_mps": 0.6, "v_horizontal_mps": 0.2, "tilt_deg": 1.5,
                      "miss_distance_m": 1.1},
        "fuel_used_kg": 200.0, "sim_time_s": 14.8, "wall_time_s": 7.4, "realtime_factor": 2.0, "seed": 7,
        "criteria": CRITERIA, "guidance_law": "zem_zev",
    }
    base.update(over)
    return base


# ------------------------------------------------------------------ parquet
def test_parquet_round_trip_exact(tmp_path):
    tel = descent_telemetry()
    n = len(tel["t_s"])
    tel["tilt_deg"] = tel["tilt_deg"].astype(np.float32)
    tel["legs_i8"] = np.arange(n, dtype=np.int8)
    tel["count_u16"] = np.arange(n, dtype=np.uint16)
    tel["with_nan"] = np.where(np.arange(n) % 7 == 0, np.nan, 1.0)
    path = write_telemetry_parquet(tel, tmp_path / "run" / "telemetry.parquet")
    assert path.is_file()
    assert pq.ParquetFile(path).metadata.row_group(0).column(0).compression in ("ZSTD", "SNAPPY")
    back = read_telemetry_parquet(path)
    assert list(back) == list(tel)  # column order kept
    for name, arr in tel.items():
        assert back[name].dtype == arr.dtype, name
        np.testing.assert_array_equal(back[name], arr, err_msg=name)
    assert back["phase"].dtype.kind == "U" and back["engine_on"].dtype == np.bool_
    assert [p.name for p in tmp_path.joinpath("run").iterdir()] == ["telemetry.parquet"]  # no temp left


@pytest.mark.parametrize("bad, match", [
    ({"t_s": np.arange(5.0), "r_x_m": np.arange(4.0)}, "r_x_m"),
    ({"t_s": np.zeros(0), "r_x_m": np.zeros(0)}, "t_s"),
    ({}, "no columns"),
    ({"t_s": np.zeros((3, 2))}, "t_s"),
    ({"r_x_m": np.arange(3.0)}, "t_s"),  # missing required column
    ({"t_s": np.arange(3.0), "z": np.ones(3, complex)}, "'z'"),
])
def test_parquet_bad_telemetry_raises_and_writes_nothing(tmp_path, bad, match):
    path = tmp_path / "telemetry.parquet"
    with pytest.raises(ValueError, match=match):
        write_telemetry_parquet(bad, path)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_existing_file(tmp_path):
    path = write_telemetry_parquet(descent_telemetry(n=10), tmp_path / "telemetry.parquet")
    before = path.read_bytes()
    with pytest.raises(ValueError):
        write_telemetry_parquet({"t_s": np.arange(3.0), "x": np.arange(2.0)}, path)
    assert path.read_bytes() == before


# -------------------------------------------------------------------- plots
@pytest.mark.parametrize("nav", [False, True])
def test_plots_written(tmp_path, terrain, nav):
    path = write_plots(descent_telemetry(nav=nav), terrain, tmp_path / "plots.png", title="synthetic descent",
                       criteria=CRITERIA, touchdown={"t_s": 9.8})
    img = cv2.imread(str(path))
    assert img is not None
    h, w = img.shape[:2]
    assert 900 <= h <= 1100 and 1300 <= w <= 1500
    assert img.std() > 10  # not blank
    assert [p.name for p in tmp_path.iterdir()] == ["plots.png"]


@pytest.mark.parametrize("nav", [False, True])
def test_plots_on_a_canvas_made_ahead_are_the_same_file(tmp_path, terrain, nav):
    """The plot process makes the empty panels and their ticks before the telemetry arrives: the same
    PNG, byte for byte; a canvas of the other layout is not used (its panels would not fit)."""
    kwargs = dict(title="synthetic descent", criteria=CRITERIA, touchdown={"t_s": 9.8})
    tel = descent_telemetry(n=201, nav=nav)
    fresh = write_plots(tel, terrain, tmp_path / "fresh.png", **kwargs).read_bytes()
    ticked = plot_canvas(nav, ticks=10)
    assert all(len(ax.xaxis.majorTicks) >= 10 and len(ax.yaxis.majorTicks) >= 10 for ax in ticked.axes)
    assert write_plots(tel, terrain, tmp_path / "ticks.png", canvas=ticked, **kwargs).read_bytes() == fresh
    assert len(ticked.axes) == 3 * (PLOT_COLUMNS_NAV if nav else PLOT_COLUMNS_PLAIN)
    if nav:  # a canvas of the other layout: left as it was, and the same file
        other = plot_canvas(False)
        assert write_plots(tel, terrain, tmp_path / "other.png", canvas=other, **kwargs).read_bytes() == fresh
        assert not any(ax.has_data() for ax in other.axes)


def test_plots_tolerate_no_touchdown_and_nan(tmp_path, terrain):
    tel = descent_telemetry(n=101)
    del tel["phase"]
    tel["r_x_m"][50:] = np.nan  # diverged run
    path = write_plots(tel, terrain, tmp_path / "plots.png", touchdown={"t_s": None})
    assert cv2.imread(str(path)) is not None


def test_plots_missing_column_raises(tmp_path, terrain):
    tel = descent_telemetry(n=20)
    del tel["tilt_deg"]
    with pytest.raises(ValueError, match="tilt_deg"):
        write_plots(tel, terrain, tmp_path / "plots.png")
    with pytest.raises(ValueError, match="tilt_max_deg"):
        write_plots(descent_telemetry(n=20), terrain, tmp_path / "plots.png", criteria={"tilt_max_deg": "steep"})
    assert list(tmp_path.iterdir()) == []


# -------------------------------------------------------------------- video
def synthetic_frames(n: int = 20, h: int = 48, w: int = 64):
    yy, xx = np.mgrid[0:h, 0:w]
    for i in range(n):
        yield ((60 + 4 * i + 40 * np.sin((xx + 3 * i) / 6.0) * np.cos(yy / 5.0)).clip(0, 255)).astype(np.uint8)


def read_video(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames


def test_video_round_trip(tmp_path):
    src = list(synthetic_frames())
    path = tmp_path / "camera.mp4"
    with CameraVideo(path, fps=10.0, size=(64, 48)) as video:
        for frame in src:
            video.add(frame)
    assert video.path == path and video.fourcc == "mp4v"
    back = read_video(path)
    assert len(back) == len(src)
    assert back[0].shape == (48, 64, 3)
    for a, b in zip(src, back):
        assert abs(float(a.mean()) - float(cv2.cvtColor(b, cv2.COLOR_BGR2GRAY).mean())) < 4.0
    assert [p.name for p in tmp_path.iterdir()] == ["camera.mp4"]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # an ordinary file, not mkstemp's 0600


def test_video_overlays_odd_size_and_write_video(tmp_path):
    tracks = np.array([[10.2, 12.7], [30.0, 20.0], [np.nan, 5.0]])
    prev = tracks - 2.0

    def overlay(i):
        return {"tracks_xy": tracks, "prev_xy": prev, "text": frame_caption(i / 10, 100 - i)}

    path = write_video(synthetic_frames(n=5, h=49, w=65), tmp_path / "camera.mp4", 10.0, overlay=overlay)
    back = read_video(path)
    assert len(back) == 5 and back[0].shape == (50, 66, 3)  # padded to even
    assert (back[0][:, :, 1].astype(int) - back[0][:, :, 2].astype(int)).max() > 100  # green circles drawn
    assert write_video([], tmp_path / "empty.mp4", 10.0) is None
    assert not (tmp_path / "empty.mp4").exists()


def _tracks_one_call_each(bgr, tracks, prev):
    """The overlay drawn point by point: one cv2.line per motion segment, one cv2.circle per track,
    each coordinate rounded to the 1/16 px grid on its own (Python's round: half to even)."""
    scale = 1 << DRAW_SHIFT_BITS

    def fixed(p):
        return round(float(p[0]) * scale), round(float(p[1]) * scale)

    ok = [bool(np.isfinite(t).all()) for t in tracks]
    if prev is not None:
        for t, p, good in zip(tracks, prev, ok):
            if good and np.isfinite(p).all():
                cv2.line(bgr, fixed(p), fixed(t), MOTION_COLOR_BGR, 1, cv2.LINE_AA, DRAW_SHIFT_BITS)
    for t, good in zip(tracks, ok):
        if good:
            cv2.circle(bgr, fixed(t), round(TRACK_RADIUS_PX * scale), TRACK_COLOR_BGR, 1, cv2.LINE_AA, DRAW_SHIFT_BITS)


def test_track_overlay_is_the_same_as_one_call_per_track():
    rng = np.random.default_rng(7)
    for trial in range(60):
        n = int(rng.integers(0, 120))
        tracks = rng.uniform(-6.0, 70.0, (n, 2))
        if trial % 3 == 0:
            tracks = np.round(tracks * 32.0) / 32.0  # exact halves of the drawing grid: rounding ties
        prev = tracks + rng.normal(0.0, 3.0, (n, 2))
        tracks[rng.random(n) < 0.05] = np.nan
        prev[rng.random(n) < 0.1, int(rng.integers(0, 2))] = np.inf
        frame = cv2.cvtColor(rng.integers(0, 256, (48, 64), dtype=np.uint8), cv2.COLOR_GRAY2BGR)
        for p in (prev, None):
            want, got = frame.copy(), frame.copy()
            _tracks_one_call_each(want, tracks, p)
            draw_tracks(got, tracks, p)
            np.testing.assert_array_equal(got, want)
            assert n < 3 or not np.array_equal(got, frame)  # something was drawn


def test_video_bad_frame_raises(tmp_path):
    with CameraVideo(tmp_path / "camera.mp4", fps=10.0) as video:
        video.add(np.zeros((48, 64), np.uint8))
        with pytest.raises(ValueError, match="wide"):
            video.add(np.zeros((64, 48), np.uint8))
        with pytest.raises(ValueError, match="uint8"):
            video.add(np.zeros((48, 64), np.float32))
        with pytest.raises(ValueError, match="prev_xy"):
            video.add(np.zeros((48, 64), np.uint8), prev_xy=np.zeros((2, 2)))
    assert len(read_video(tmp_path / "camera.mp4")) == 1
    with pytest.raises(ValueError, match="fps"):
        CameraVideo(tmp_path / "x.mp4", fps=0.0)


def test_video_exception_leaves_nothing(tmp_path):
    path = tmp_path / "camera.mp4"
    with pytest.raises(RuntimeError, match="boom"):
        with CameraVideo(path, fps=10.0) as video:
            for i, frame in enumerate(synthetic_frames()):
                video.add(frame)
                if i == 5:
                    raise RuntimeError("boom")
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_video_exception_keeps_existing_file(tmp_path):
    path = tmp_path / "camera.mp4"
    path.write_bytes(b"previous result")
    with pytest.raises(RuntimeError):
        with CameraVideo(path, fps=10.0, size=(64, 48)) as video:
            video.add(next(synthetic_frames()))
            raise RuntimeError("boom")
    assert path.read_bytes() == b"previous result"
    assert list(tmp_path.iterdir()) == [path]


# ------------------------------------------------------------------ summary
def test_summary_landed():
    text = summary_table(summary(), outputs={"telemetry": "out/telemetry.parquet"})
    assert "LANDED" in text and CHECK_FAIL not in text and text.count(CHECK_OK) >= 4
    assert "zem_zev" in text and "seed 7" in text and "out/telemetry.parquet" in text
    assert len(text.splitlines()) <= 24 and max(map(len, text.splitlines())) <= 100


def test_summary_violated_limit_marked():
    td = {"t_s": 9.8, "v_vertical_mps": 2.4, "v_horizontal_mps": 0.2, "tilt_deg": 1.5, "miss_distance_m": 1.1}
    text = summary_table(summary(outcome="hard_landing", landed=False, touchdown=td))
    assert "HARD LANDING" in text
    line = next(ln for ln in text.splitlines() if "vertical speed" in ln)
    assert CHECK_FAIL in line and "2.40" in line
    assert CHECK_OK in next(ln for ln in text.splitlines() if "horizontal speed" in ln)


def test_summary_no_touchdown_and_missing_key():
    td = dict.fromkeys(("t_s", "v_vertical_mps", "v_horizontal_mps", "tilt_deg", "miss_distance_m"))
    text = summary_table(summary(outcome="fuel_exhausted", landed=False, touchdown=td, error="propellant ran out",
                                 realtime_factor=float("inf")))
    assert "FUEL EXHAUSTED" in text and "touchdown: none" in text and "propellant ran out" in text
    bad = summary()
    del bad["criteria"]
    with pytest.raises(ValueError, match="criteria"):
        summary_table(bad)


# ------------------------------------------------------------------- import
def test_import_is_cheap():
    code = ("import sys, bench.report.report; bad = [m for m in ('mujoco', 'matplotlib', 'models.terrain') "
            "if m in sys.modules]; sys.exit(f'imported {bad}' if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_summary_table_shows_navigation_and_vision_when_present():
    from bench.report.report import summary_table

    summary = {
        "outcome": "landed", "landed": True, "fuel_used_kg": 90.0, "sim_time_s": 80.0, "wall_time_s": 12.0,
        "realtime_factor": 6.7, "seed": 3,
        "touchdown": {"t_s": 75.0, "v_vertical_mps": 0.8, "v_horizontal_mps": 0.05, "tilt_deg": 0.3, "miss_distance_m": 30.0},
        "criteria": {"v_vertical_max_mps": 1.0, "v_horizontal_max_mps": 0.5, "tilt_max_deg": 10.0, "settle_s": 5.0},
        "nav": {"vel_err_touchdown_mps": 0.0642, "pos_err_touchdown_m": 30.2, "nees_per_dof_mean": {"v_h": 1.1}},
        "vision": {"frames": 392, "tracks_median": 78.0, "rejected_frac": 0.046},
    }
    text = summary_table(summary)
    assert "0.064 m/s" in text and "30.2 m" in text and "v_h 1.10" in text
    assert "392 frames" in text and "4.6%" in text


def test_summary_table_says_what_the_flight_software_did_and_did_not_do():
    # The console listed no faults, map fixes or hazard scan at all: a fault whose trigger never came, a map that
    # never locked and a hazardous touchdown all read as a plain "LANDED".
    base = summary()
    text = summary_table({**base, "faults": [
        {"kind": "dropout", "target": "altimeter", "triggered": False, "detected": False},
        {"kind": "bias", "target": "imu.gyro", "triggered": True, "start_t_s": 12.5, "detected": True,
         "latency_s": 0.31, "detection": "gyro disagrees with the star tracker"},
        {"kind": "stuck", "target": "star_tracker", "triggered": True, "start_t_s": 40.0, "detected": False}],
        "fdir": {"n_events": 2, "subsystems": "imu", "first_event_t_s": 12.81, "abort_declared": False},
        "map_nav": {"attempts": 9, "updates": 0, "locked": False, "refused": {"coarse peak not clear": 7, "x": 0}},
        "hazard": {"avoidance": "on", "scan": {"scanned": True, "height_m": 99.6, "no_safe_site": False,
                                               "first_no_site": False, "divert_m": 12.34, "margin_m": 1.5},
                   "hazard_free": False, "footprint": {"hazards": "rock"}}})
    lines = text.splitlines()
    assert "fault dropout on altimeter: never triggered (its trigger was not met in flight)" in lines
    assert ("fault bias on imu.gyro: from t = 12.50 s, detected after 0.31 s (gyro disagrees with the star "
            "tracker)") in lines
    assert "fault stuck on star_tracker: from t = 40.00 s, not detected" in lines
    assert "fault detection: 2 event(s) (imu), first at t = 12.81 s" in lines
    assert ("map fixes: 0 used of 9 attempts, NEVER LOCKED (navigation stayed on the hand-over estimate); most "
            "refused: coarse peak not clear (7)") in lines
    assert "hazard scan at 100 m: site 12.3 m away, margin 1.50 m" in lines
    # With the site's truth position and the touchdown point, how far from the site it landed.
    at_site = summary_table({**base, "touchdown": {**base["touchdown"], "x_m": 3.0, "y_m": 4.0},
                             "hazard": {"avoidance": "on", "scan": {"scanned": True, "height_m": 100.0,
                                                                     "divert_m": 5.0, "margin_m": 2.0,
                                                                     "site_truth_xy_m": [0.0, 0.0]},
                                        "hazard_free": True}})
    assert "hazard scan at 100 m: site 5.0 m away, margin 2.00 m; touchdown 5.00 m from it" in at_site
    assert "touchdown footprint: hazard-free" in at_site
    assert "touchdown footprint: HAZARDOUS (rock)" in lines
    # Without faults, map navigation or hazard avoidance, none of these lines.
    assert not any(w in summary_table(base) for w in ("fault", "map fixes", "hazard", "footprint"))
    abort = summary_table({**base, "fdir": {"n_events": 1, "abort_declared": True, "abort_t_s": 30.0,
                                            "abort_reason": "navigation lost"},
                           "hazard": {"avoidance": "on", "scan": {"scanned": True, "height_m": 100.0,
                                                                   "no_safe_site": True, "rescanned": True},
                                      "hazard_free": None}})
    assert "fault detection: abort declared at t = 30.00 s (navigation lost)" in abort
    assert "hazard scan at 100 m: no safe site (after a second scan)" in abort and "footprint: unscored" in abort
