"""Tests of bench.evaluation.tracking_eval on a synthetic textured-plane descent (no MuJoCo)."""

from __future__ import annotations

import numpy as np
import pytest

import bench.evaluation.tracking_eval as tracking_eval
from bench.evaluation.tracking_eval import (
    BaselineConfig,
    OpenCVBaseline,
    compare,
    evaluate,
    synthetic_descent,
    track_metrics,
    truth_flow,
)
from vision import Tracker, TrackerConfig, Tracks


@pytest.fixture(scope="module")
def descent():
    return synthetic_descent(size=256, n_frames=24, seed=3)


def apply_h(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = h @ np.column_stack([xy, np.ones(len(xy))]).T
    return (p[:2] / p[2]).T


def test_truth_flow_matches_plane_homography(descent):
    d = descent
    rng = np.random.default_rng(0)
    for k in (0, 10, 22):
        xy = rng.uniform(0, 255, (400, 2))
        truth, valid = truth_flow(xy, d.depths[k], d.K, *d.poses[k], *d.poses[k + 1], depth_k1=d.depths[k + 1])
        # Independent route: image k -> ground plane -> image k+1 by homographies.
        expected = apply_h(d.homographies[k + 1] @ np.linalg.inv(d.homographies[k]), xy)
        inside = (expected >= 0).all(axis=1) & (expected <= 255).all(axis=1)
        np.testing.assert_array_equal(valid, inside)
        assert np.abs(truth[valid] - expected[valid]).max() < 1e-3
        assert np.isnan(truth[~valid]).all()


def test_depth_is_consistent_with_homography(descent):
    # Analytic depth of frame 0 back-projects onto the plane z = 0.
    d = descent
    R, r = d.poses[0]
    v, u = 100, 37
    ray = np.linalg.solve(d.K, [u, v, 1.0])
    p_L = R @ (ray * d.depths[0][v, u]) + r
    assert abs(p_L[2]) < 1e-3


def test_truth_flow_invalid_cases():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    r0, r1 = np.array([0, 0, 10.0]), np.array([0.5, 0, 10.0])
    depth = np.full((64, 64), 10.0, np.float32)
    depth[:, 40:] = 5.0  # a step: discontinuity between columns 39 and 40
    depth[5, 5] = np.nan
    xy = np.array([[20.0, 20.0], [39.5, 20.0], [5.2, 5.3], [-3.0, 10.0], [63.4, 10.0], [2.0, 30.0], [30.0, 30.0]])
    truth, valid = truth_flow(xy, depth, K, R, r0, R, r1)
    # In order: fine; on the depth step; NaN depth; off frame k (twice);
    # leaves frame k+1; fine.
    assert valid.tolist() == [True, False, False, False, False, False, True]
    # Moving east by 0.5 m at 10 m depth shifts the image by -5 px in x.
    np.testing.assert_allclose(truth[0], [15.0, 20.0], atol=1e-9)
    np.testing.assert_allclose(truth[-1], [25.0, 30.0], atol=1e-9)
    # Occlusion: the surface seen in frame k+1 is much nearer.
    near = np.full((64, 64), 2.0, np.float32)
    _, valid_occ = truth_flow(xy[:1], np.full((64, 64), 10.0, np.float32), K, R, r0, R, r1, depth_k1=near)
    assert not valid_occ[0]
    with pytest.raises(ValueError, match="rotation"):
        truth_flow(xy, depth, K, 2 * R, r0, R, r1)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        truth_flow(np.zeros(3), depth, K, R, r0, R, r1)


def test_baseline_contract():
    d = synthetic_descent(size=128, n_frames=30, seed=1)
    b = OpenCVBaseline()
    prev = b.step(d.frames[0])
    assert len(prev) > 20 and np.isnan(prev.prev_xy).all()
    for img in d.frames[1:5]:
        out = b.step(img)
        _, ia, ib = np.intersect1d(prev.ids, out.ids, return_indices=True)
        assert len(ia) > 0.7 * len(prev)
        np.testing.assert_allclose(out.prev_xy[ib], prev.xy[ia])
        np.testing.assert_array_equal(out.age[ib], prev.age[ia] + 1)
        prev = out
    with pytest.raises(ValueError, match="dtype"):
        b.step(np.zeros((8, 8), np.float64))
    assert len(OpenCVBaseline().step(np.zeros((64, 64), np.uint8))) == 0


def test_tracker_and_baseline_score_well_on_descent(descent):
    d = descent
    res = compare(
        {"tracker": lambda: Tracker(TrackerConfig()), "opencv_baseline": lambda: OpenCVBaseline(BaselineConfig())},
        d.frames,
        d.depths,
        d.K,
        d.poses,
        repeats=2,
    )
    for name, m in res.items():
        print(
            f"{name}: {m['tracks_per_frame_mean']:.1f} tracks/frame, median EPE {m['epe_median_px']:.3f} px, "
            f"p95 {m['epe_p95_px']:.3f} px, within 1 px {100 * m['within_1px_frac']:.2f} %, "
            f"{m['ms_per_frame_mean']:.3f} ms/frame (median {m['ms_per_frame_median']:.3f}, "
            f"min over repeats {m['ms_per_frame_min_of_repeats_mean']:.3f})"
        )
        assert m["n_errors"] > 500, name
        assert m["epe_median_px"] < 0.1, name
        assert m["within_1px_frac"] >= 0.99, name
        assert m["tracks_per_frame_mean"] > 40, name
        assert m["mean_lifetime_frames"] > 5, name
        # The timing statistics themselves are checked against a fake clock in
        # test_compare_timing_matches_an_explicit_computation.
        assert m["ms_per_frame_min_of_repeats_mean"] > 0
        assert m["ms_per_frame_median"] > 0


def test_evaluate_detects_a_bad_tracker(descent):
    """The metrics must be able to fail: a tracker that reports the previous
    positions (no motion) scores badly."""

    class Frozen:
        def __init__(self):
            self.inner = Tracker()

        def step(self, image):
            t = self.inner.step(image)
            old = ~np.isnan(t.prev_xy[:, 0])
            xy = t.xy.copy()
            xy[old] = t.prev_xy[old]
            return type(t)(ids=t.ids, xy=xy, prev_xy=t.prev_xy, age=t.age)

    d = descent
    m = evaluate(Frozen, d.frames, d.depths, d.K, d.poses)
    assert m["epe_median_px"] > 0.5
    with pytest.raises(ValueError, match="equal lengths"):
        evaluate(Tracker, d.frames, d.depths[:-1], d.K, d.poses)


def test_track_metrics_match_an_explicit_loop_on_known_tracks(descent):
    """Tracks built from the plane homographies with known injected errors:
    every metric of track_metrics must equal what an explicit loop gives."""
    d = descent
    rng = np.random.default_rng(4)
    magnitudes = np.arange(0.05, 2.0, 0.1)  # none near the 1 px limit
    next_id = 0
    xy = {}  # id -> position in the current frame
    tracks, injected = [], []
    seen = {}  # id -> number of frames reported
    for k in range(len(d.frames)):
        if k > 0:
            to_k = d.homographies[k] @ np.linalg.inv(d.homographies[k - 1])
            moved = {}
            for i, p in xy.items():
                if rng.random() < 0.15:
                    continue  # track dies
                q = to_k @ np.array([p[0], p[1], 1.0])
                q = q[:2] / q[2]
                if not ((40 < q) & (q < 215)).all():
                    continue  # leaves the well-inside area: dropped
                e = rng.choice(magnitudes)
                phi = rng.uniform(0, 2 * np.pi)
                moved[i] = q + e * np.array([np.cos(phi), np.sin(phi)])
                injected.append(e)
            xy = moved
        for _ in range(5 if k else 30):
            xy[next_id] = rng.uniform(60, 196, 2)
            next_id += 1
        ids = np.array(list(xy), np.int64)
        order = rng.permutation(len(ids))  # matching must go by id, not by index
        ids = ids[order]
        pos = np.array([xy[i] for i in ids]).reshape(-1, 2)
        tracks.append(Tracks(ids=ids, xy=pos, prev_xy=np.full_like(pos, np.nan), age=np.zeros(len(ids), np.int64)))
        for i in ids.tolist():
            seen[i] = seen.get(i, 0) + 1
    err = np.array(injected)
    assert err.size > 200 and (err > 1.0).any() and (err <= 1.0).any()
    m = track_metrics(tracks, d.depths, d.K, d.poses)
    assert m["n_errors"] == err.size
    # truth_flow agrees with the homographies to < 1e-3 px.
    assert m["epe_median_px"] == pytest.approx(np.median(err), abs=2e-3)
    assert m["epe_p95_px"] == pytest.approx(np.percentile(err, 95), abs=2e-3)
    assert m["epe_max_px"] == pytest.approx(err.max(), abs=2e-3)
    assert m["within_1px_frac"] == (err <= 1.0).mean()
    counts = [len(t) for t in tracks]
    assert m["tracks_per_frame_mean"] == pytest.approx(np.mean(counts))
    assert m["tracks_per_frame_median"] == np.median(counts)
    assert m["mean_lifetime_frames"] == pytest.approx(sum(seen.values()) / len(seen))


def test_compare_timing_matches_an_explicit_computation(monkeypatch):
    """ms_per_frame_* from a fake clock whose steps cost known times."""
    n_frames, repeats = 6, 3
    clock = [0.0]
    monkeypatch.setattr(tracking_eval, "time", type("FakeTime", (), {"perf_counter": staticmethod(lambda: clock[0])}))

    def cost_ms(name: str, rep: int, k: int) -> float:
        base = 1.0 if name == "a" else 5.0
        return base + 0.25 * k + (7.0 if (k + 2 * rep) % 4 == 0 else 0.0) + 0.5 * rep

    def factory(name: str):
        made = []  # instance 0 is the untimed warm-up, then one per repeat

        def make():
            rep = len(made) - 1
            made.append(None)

            class Fake:
                k = 0

                def step(self, image):
                    clock[0] += 1e-3 * cost_ms(name, rep, self.k)
                    self.k += 1
                    return Tracks.empty()

            return Fake()

        return make

    frames = [np.zeros((8, 8), np.uint8)] * n_frames
    poses = [(np.eye(3), np.zeros(3))] * n_frames
    res = compare({"a": factory("a"), "b": factory("b")}, frames, frames, np.eye(3), poses, repeats=repeats)
    for name in ("a", "b"):
        t = np.array([[cost_ms(name, rep, k) for k in range(n_frames)] for rep in range(repeats)])
        assert res[name]["ms_per_frame_mean"] == pytest.approx(t.mean())
        assert res[name]["ms_per_frame_median"] == pytest.approx(np.median(t))
        assert res[name]["ms_per_frame_min_of_repeats_mean"] == pytest.approx(t.min(axis=0).mean())
        assert res[name]["tracks_per_frame_mean"] == 0 and res[name]["n_errors"] == 0
    # The three statistics differ here, so a mix-up between them would show.
    t = np.array([[cost_ms("a", rep, k) for k in range(n_frames)] for rep in range(repeats)])
    assert len({round(t.mean(), 6), round(float(np.median(t)), 6), round(t.min(axis=0).mean(), 6)}) == 3


def test_compare_counts_the_page_faults_inside_each_tracker_step():
    """minor_faults_per_frame: a tracker that maps and touches fresh pages in every step shows one fault a page
    (the kernel zeroing them inside its time); one that allocates nothing shows none; neither is charged the
    other's, though they take turns on each frame."""
    import mmap

    pages = 64
    page = mmap.PAGESIZE

    class Touching:
        def step(self, image):
            buf = mmap.mmap(-1, pages * page)  # anonymous, fresh from the kernel each time
            for k in range(pages):
                buf[k * page] = 1
            buf.close()
            return Tracks.empty()

    class Idle:
        def step(self, image):
            return Tracks.empty()

    frames = [np.zeros((8, 8), np.uint8)] * 5
    poses = [(np.eye(3), np.zeros(3))] * len(frames)
    res = compare({"touching": Touching, "idle": Idle}, frames, frames, np.eye(3), poses, repeats=2)
    assert pages <= res["touching"]["minor_faults_per_frame"] <= pages + 8
    assert res["idle"]["minor_faults_per_frame"] < 1.0
