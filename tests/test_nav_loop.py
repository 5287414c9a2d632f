"""Navigation in the loop: estimator + the paper's vision tracker (issue 5)."""

from __future__ import annotations

import numpy as np
import pytest

import bench.run as bench_run
from bench.run import run
from bench.scenario import load_scenario
from vision.tracker import Tracker
from vision.tracks import Tracks

SEEDS = range(1, 6)


def _meets_criteria(s: dict) -> None:
    crit, td = s["criteria"], s["touchdown"]
    assert s["outcome"] == "landed", s
    assert td["v_vertical_mps"] <= crit["v_vertical_max_mps"] and td["v_horizontal_mps"] <= crit["v_horizontal_max_mps"]
    assert td["tilt_deg"] <= crit["tilt_max_deg"] and s["final_tilt_deg"] <= crit["tilt_max_deg"]


@pytest.fixture(scope="module")
def default_nav_run():
    sc = load_scenario()
    assert (sc.nav, sc.tracks, sc.vision) == ("estimator", "vision", "on")  # the defaults
    return run(sc)


def test_default_scenario_lands_on_vision_navigation(default_nav_run):
    s = default_nav_run.summary
    _meets_criteria(s)
    assert s["nav"]["vel_err_touchdown_mps"] <= 0.2, s["nav"]
    assert s["nav"]["nees_in_bounds_frac"] >= 0.9, s["nav"]  # consistent, not just accurate
    v = s["vision"]
    assert v["frames"] > 300 and v["tracks_median"] >= 40 and v["measurements"] > 300


def test_nav_telemetry_errors_match_an_independent_recomputation(default_nav_run):
    tel = default_nav_run.telemetry
    for a in "xyz":
        np.testing.assert_allclose(tel[f"nav_err_v_{a}_mps"], tel[f"nav_v_{a}_mps"] - tel[f"v_{a}_mps"], atol=1e-12)
        assert np.all(tel[f"nav_sigma_v_{a}_mps"] > 0)
    # Below the vision cut-off no new vision measurements are made.
    below = tel["nav_r_z_m"] < 29.0
    assert np.ptp(tel["vision_measurements"][below]) == 0


def _horizontal_error(sets: list[str]) -> float:
    return run(load_scenario(None, sets)).summary["nav"]["vel_err_horizontal_touchdown_mps"]


def test_vision_cuts_the_horizontal_velocity_error_at_least_fivefold():
    with_vision = [_horizontal_error([f"seed={s}"]) for s in SEEDS]
    without = [_horizontal_error([f"seed={s}", 'vision="off"', "camera.enabled=false"]) for s in SEEDS]
    ratio = np.mean(without) / np.mean(with_vision)
    assert ratio >= 5.0, (with_vision, without)


class _FaultyTracker(Tracker):
    """The paper's tracker with injected faults: a burst of consistently wrong tracks and blank frames."""

    BURST = range(150, 160)  # frames whose tracks are all shifted (a false, consistent motion)
    BLANK = range(200, 203)  # frames with no texture at all

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frame = 0

    def step(self, image):
        k, self.frame = self.frame, self.frame + 1
        if k in self.BLANK:
            image = np.full_like(image, 90)
        tracks = super().step(image)
        if k in self.BLANK:
            assert len(tracks) == 0  # a featureless frame gives zero tracks, no crash
        if k in self.BURST and len(tracks):
            tracks = Tracks(ids=tracks.ids, xy=tracks.xy + np.array([6.0, -4.0]), prev_xy=tracks.prev_xy, age=tracks.age)
        return tracks


def test_gating_rejects_wrong_and_missing_vision_and_the_run_still_lands(monkeypatch):
    monkeypatch.setattr(bench_run, "Tracker", _FaultyTracker)
    s = run(load_scenario()).summary
    _meets_criteria(s)
    assert s["vision"]["rejected_frac"] > 0  # the burst was caught by the chi-square gate
    assert s["nav"]["vel_err_touchdown_mps"] <= 0.2


def test_truth_tracks_separate_vision_error_from_filter_error():
    s = run(load_scenario(None, ['tracks="truth"', "camera.enabled=false"])).summary
    _meets_criteria(s)
    assert s["nav"]["vel_err_touchdown_mps"] <= 0.2 and s["vision"]["tracks_median"] >= 60


def test_modes_are_validated():
    from bench.scenario import ScenarioError

    with pytest.raises(ScenarioError, match="nav"):
        load_scenario(None, ['nav="psychic"'])
    with pytest.raises(ScenarioError, match="camera.enabled"):
        load_scenario(None, ["camera.enabled=false"])  # vision on needs frames
