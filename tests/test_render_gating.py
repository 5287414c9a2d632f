"""Rendering only what someone consumes: below the vision cut-off a run without a video or a recording renders
nothing, and flies exactly as a run that rendered every frame; each frame's detector noise is its own stream."""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenario import load_scenario
from bench.sim.run import run
from bench.sim.world_builder import build_sensors

# From 150 m at 6 m/s down through a vision cut-off raised to 125 m (about 4 s in); 8 s, 81 camera frames.
CUTOFF_M = 125.0
CROSSING = ["initial.r_BL_L_m=[20.0,-10.0,150.0]", "initial.v_BL_L_mps=[1.0,-1.0,-6.0]", "sim.t_max_ns=8_000_000_000",
            f"vision_nav.cutoff_altitude_m={CUTOFF_M}", "seed=3"]


@pytest.fixture(scope="module")
def runs():
    sc = load_scenario(None, CROSSING)
    frames: list[tuple[int, float]] = []
    with_sink = run(sc, frame_sink=lambda t_ns, frame, truth, tracks: frames.append((t_ns, float(truth.r_BL_L[2]))))
    lean = run(sc)
    return sc, with_sink, lean, frames


class _CountingRecorder:
    want_depth = False

    def __init__(self):
        self.images: list[int] = []

    def message(self, kind, msg):
        if kind == "image":
            self.images.append(msg.t_ns)

    def camera_truth(self, t_ns, R_LC, r_CL_L, depth):
        pass

    def control_tick(self, t_ns, contact, truth, accel_bias_B):
        pass


def test_lean_run_flies_exactly_as_one_that_rendered_every_frame(runs):
    _, with_sink, lean, _ = runs
    assert with_sink.telemetry.keys() == lean.telemetry.keys()
    for name, col in with_sink.telemetry.items():
        np.testing.assert_array_equal(lean.telemetry[name], col, err_msg=name)
    assert lean.summary["touchdown"] == with_sink.summary["touchdown"]
    assert lean.summary["vision"] == with_sink.summary["vision"]


def test_nothing_rendered_below_the_cut_off_without_a_consumer(runs):
    sc, with_sink, lean, frames = runs
    n_frames = sc.sim.t_max_ns // sc.camera.period_ns + 1
    assert with_sink.summary["time_split_s"]["frames_rendered"] == len(frames) >= n_frames - 1
    used = lean.summary["vision"]["frames"]
    assert 0 < used < 0.75 * len(frames)  # the descent crossed the cut-off
    assert lean.summary["time_split_s"]["frames_rendered"] == used  # exactly the frames the tracker took
    assert min(z for _, z in frames) < CUTOFF_M - 10.0  # well below it at the end


def test_each_frame_has_its_own_noise_stream():
    sensors = build_sensors(load_scenario(None, ["seed=5"]))
    first = [sensors.frame_rng(k).standard_normal(4) for k in range(6)]
    # Out of order, and with other frames drawn in between: the same draws per frame index.
    again = {k: sensors.frame_rng(k).standard_normal(4) for k in (5, 2, 0, 4, 1, 3)}
    for k in range(6):
        np.testing.assert_array_equal(first[k], again[k])
    assert not np.array_equal(first[0], first[1])
    other_seed = build_sensors(load_scenario(None, ["seed=6"])).frame_rng(0).standard_normal(4)
    assert not np.array_equal(first[0], other_seed)


def test_a_recording_gets_every_frame_below_the_cut_off_too(runs):
    sc, _, lean, frames = runs
    rec = _CountingRecorder()
    recorded = run(sc, recorder=rec)
    assert rec.images == [t for t, _ in frames]  # every camera frame, in order
    assert recorded.summary["time_split_s"]["frames_rendered"] == len(frames)
    for name, col in lean.telemetry.items():
        np.testing.assert_array_equal(recorded.telemetry[name], col, err_msg=name)
