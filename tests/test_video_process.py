"""camera.mp4 from a second process (bench/report/video_process.py): the same file, nothing left behind.

plots.png from its own second process (bench/report/plot_process.py) is checked here too, on the same
two runs; its failures in tests/test_plot_process.py."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import bench.report.run_outputs as ro
from bench.report.child_process import BATCH, BATCH_MESSAGES, ChildProcess
from bench.report.video_process import VideoProcess
from bench.scenario import load_scenario
from bench.sim.world_builder import build_terrain, build_world
from tests.conftest import SMALL_SET, record_instances

# Vision on from 36 m: the frames above the 30 m cut-off are rendered by the run for its tracker,
# those below only for the video (by the second process); a 128² camera keeps it short (61 s to touchdown).
ACROSS_CUTOFF = [*SMALL_SET, "initial.r_BL_L_m=[0.0, 0.0, 36.0]", "initial.v_BL_L_mps=[0.0, 0.0, -2.0]",
                 "camera.width_px=128", "camera.height_px=128", "landing.settle_s=1.0"]
WALL = ("wall_time_s", "setup_time_s", "realtime_factor", "time_split_s")


@pytest.mark.parametrize("flown", [
    pytest.param(["sim.t_max_ns=15_000_000_000"], id="first-15-s"),  # 36 m down to about 25 m
    pytest.param([], id="to-touchdown", marks=pytest.mark.slow),  # 61 s flown: make test-slow
])
def test_the_video_and_plot_processes_write_the_same_files_as_the_run_itself(tmp_path, flown):
    sc = load_scenario(None, [*ACROSS_CUTOFF, *flown])
    here, there = tmp_path / "here", tmp_path / "there"
    s_here, _ = ro.run_and_write(sc, here, video_process=False, plot_process=False)
    s_there, _ = ro.run_and_write(sc, there, video_process=True, plot_process=True)
    # The second process rendered the frames below the cut-off (the run rendered only its tracker's) ...
    n_here, n_there = s_here["time_split_s"]["frames_rendered"], s_there["time_split_s"]["frames_rendered"]
    assert 0 < n_there < n_here
    # ... and the video is the same bytes, the landing the same.
    assert (there / "camera.mp4").read_bytes() == (here / "camera.mp4").read_bytes()
    assert (there / "plots.png").read_bytes() == (here / "plots.png").read_bytes()  # drawn by the plot process
    assert {k: v for k, v in s_there.items() if k not in WALL} == {k: v for k, v in s_here.items() if k not in WALL}
    assert json.loads((there / "summary.json").read_text())["outcome"] == s_here["outcome"]
    assert not [p.name for p in there.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_failure_after_the_run_leaves_no_video_and_stops_the_process(tmp_path, monkeypatch):
    made = record_instances(monkeypatch, ro, "VideoProcess")

    def broken_plots(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(ro, "write_plots", broken_plots)
    out = tmp_path / "run"
    # The first 5 s are enough (36 m down to 29 m: frames from the run and from the second process).
    with pytest.raises(RuntimeError, match="disk full"):
        ro.run_and_write(load_scenario(None, [*ACROSS_CUTOFF, "sim.t_max_ns=5_000_000_000"]), out, video_process=True)
    assert len(made) == 1 and not made[0]._proc.is_alive()
    assert not any(p.suffix in (".mp4", ".tmp") or ".mp4." in p.name for p in out.iterdir())
    assert not (out / "summary.json").exists()


def test_a_second_world_that_would_draw_another_scene_is_refused(tmp_path):
    """The process builds its world from the scenario; if that ever differed from the run's, it must
    say so instead of writing a video of another terrain."""
    sc = load_scenario(None, ACROSS_CUTOFF)
    other = load_scenario(None, [*ACROSS_CUTOFF, "terrain.seed=2"])
    video = VideoProcess(sc, tmp_path / "camera.mp4", fps=10.0, size=(128, 128))
    with build_world(other, build_terrain(other)) as world:
        video.start(world)
        with pytest.raises(RuntimeError, match="differs from the run's"):
            for _ in range(50):  # it may stop while frames are still being handed over
                video.render_frame(0, 0, world, 1.0, world.truth(), None)
            video.close()
    assert not list(tmp_path.iterdir())


def test_frames_reach_the_process_eight_at_a_time(tmp_path, monkeypatch):
    """Each write that wakes the second process costs the run about as much as pickling a frame: the
    frames go in batches, the digest and the close on their own, and every frame is encoded."""
    written = []
    real = ChildProcess._write

    def counted(self, msg):
        written.append(msg[0])
        real(self, msg)

    monkeypatch.setattr(ChildProcess, "_write", counted)
    sc = load_scenario(None, ACROSS_CUTOFF)
    video = VideoProcess(sc, tmp_path / "camera.mp4", fps=10.0, size=(128, 128))
    n = 2 * BATCH_MESSAGES + 3
    with build_world(sc, build_terrain(sc)) as world:
        video.start(world)
        for i in range(n):
            video.render_frame(i * 100_000_000, i, world, 1.0, world.truth(), None)
        path = video.close()
    assert written == ["digest", BATCH, BATCH, BATCH, "close"]  # two full batches, then the three held
    capture = cv2.VideoCapture(str(path))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == n
    capture.release()


def test_visual_state_carries_a_frame_to_another_world():
    sc = load_scenario(None, ACROSS_CUTOFF)
    terrain = build_terrain(sc)
    with build_world(sc, terrain) as a, build_world(sc, terrain) as b:
        a.reset(np.array([3.0, -2.0, 25.0]), np.zeros(3), np.array([0.99, 0.05, -0.08, 0.02]) / 1.0046, np.zeros(3))
        frame_a = a.render_signal()
        assert not np.array_equal(b.render_signal(), frame_a)  # b is elsewhere
        b.set_visual_state(a.visual_state())
        np.testing.assert_array_equal(b.render_signal(), frame_a)
