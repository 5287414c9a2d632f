"""plots.png from a second process (bench/report/plot_process.py): its failures are the run's, and it stops.

That it writes the same file as the run itself: tests/test_video_process.py (the same two runs)."""

from __future__ import annotations

import numpy as np
import pytest

import bench.report.run_outputs as ro
from bench.report.plot_process import PlotProcess
from bench.report.report import PLOT_REQUIRED_COLUMNS
from tests.conftest import make_terrain, record_instances


def _telemetry(n: int = 50) -> dict[str, np.ndarray]:
    t = np.linspace(0.0, 10.0, n)
    tel = {name: np.zeros(n) for name in PLOT_REQUIRED_COLUMNS}
    tel.update(t_s=t, r_z_m=100.0 - 10.0 * t, v_z_mps=np.full(n, -10.0), height_m=100.0 - 10.0 * t,
               throttle=np.full(n, 0.5), mass_kg=1600.0 - t)
    return tel


def test_the_plot_process_draws_what_write_plots_draws(tmp_path):
    from bench.report.report import write_plots

    terrain = make_terrain(np.random.default_rng(3).normal(0.0, 2.0, (33, 33)), 256.0)
    plots = PlotProcess()
    plots.draw(_telemetry(), terrain, tmp_path / "there.png", title="t", criteria={"tilt_max_deg": 10.0})
    assert plots.result() == tmp_path / "there.png"
    write_plots(_telemetry(), terrain, tmp_path / "here.png", title="t", criteria={"tilt_max_deg": 10.0})
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()
    assert not plots._proc.is_alive()


def test_its_error_is_raised_in_the_run_and_nothing_is_written(tmp_path):
    tel = _telemetry()
    del tel["mass_kg"]
    plots = PlotProcess()
    plots.draw(tel, make_terrain(np.zeros((33, 33)), 256.0), tmp_path / "plots.png")
    with pytest.raises(ValueError, match="mass_kg") as info:
        plots.result()
    assert any("raised in the plots process" in note for note in info.value.__notes__)
    assert not plots._proc.is_alive() and not list(tmp_path.iterdir())


def test_a_run_that_fails_stops_its_plot_process(tmp_path, monkeypatch):
    made = record_instances(monkeypatch, ro, "PlotProcess")

    def failing_run(*args, **kwargs):
        raise RuntimeError("diverged")

    monkeypatch.setattr(ro, "run", failing_run)
    from bench.scenario import load_scenario

    with pytest.raises(RuntimeError, match="diverged"):
        ro.run_and_write(load_scenario(None), tmp_path / "run", plot_process=True)
    assert len(made) == 1 and not made[0]._proc.is_alive()
    assert not (tmp_path / "run").exists()


def test_the_geometry_only_terrain_keeps_what_the_plots_read():
    terrain = make_terrain(np.random.default_rng(4).normal(0.0, 3.0, (33, 33)), 256.0)
    light = terrain.geometry_only()
    assert light.albedo.size == 1 and light.patch is None
    xy = np.random.default_rng(5).uniform(-128.0, 128.0, (2, 200))
    np.testing.assert_array_equal(light.surface_height(*xy), terrain.surface_height(*xy))
    np.testing.assert_array_equal(light.hillshade(30.0, 120.0), terrain.hillshade(30.0, 120.0))
    assert light.spacing_m == terrain.spacing_m


def test_a_failed_plot_leaves_no_video_and_stops_both_processes(tmp_path, monkeypatch):
    """As when the run draws the plots itself (tests/test_video_process.py): nothing half-written stays."""
    from bench.scenario import load_scenario
    from tests.test_video_process import ACROSS_CUTOFF

    class Broken(PlotProcess):
        def draw(self, telemetry, terrain, path, **kwargs):
            super().draw({k: v for k, v in telemetry.items() if k != "mass_kg"}, terrain, path, **kwargs)

    monkeypatch.setattr(ro, "PlotProcess", Broken)
    plots, videos = record_instances(monkeypatch, ro, "PlotProcess"), record_instances(monkeypatch, ro, "VideoProcess")
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="mass_kg"):
        ro.run_and_write(load_scenario(None, [*ACROSS_CUTOFF, "sim.t_max_ns=5_000_000_000"]), out,
                         video_process=True, plot_process=True)
    assert len(plots) == len(videos) == 1 and not any(p._proc.is_alive() for p in plots + videos)
    assert not any(p.suffix in (".mp4", ".png", ".tmp") or ".mp4." in p.name for p in out.iterdir())
    assert not (out / "summary.json").exists()


def test_the_plot_process_warms_up_without_collections_and_draws_with_them(tmp_path, monkeypatch):
    """_serve, run here with pipes of its own: the warm-up and the canvas made ahead run with the collector
    off (they keep what they make), the run's figure with it on again."""
    import gc
    import multiprocessing as mp

    import bench.report.plot_process as pp
    import bench.report.report as report
    from bench.report.child_process import _widen_pipe

    seen = {}
    monkeypatch.setattr(pp, "warm_up", lambda: seen.setdefault("warm_up", gc.isenabled()))
    canvas = report.plot_canvas
    monkeypatch.setattr(report, "plot_canvas",
                        lambda *a, **kw: (seen.setdefault("canvas", gc.isenabled()), canvas(*a, **kw))[1])
    draw = report.write_plots
    monkeypatch.setattr(report, "write_plots",
                        lambda *a, **kw: (seen.setdefault("draw", gc.isenabled()), draw(*a, **kw))[1])
    terrain = make_terrain(np.random.default_rng(3).normal(0.0, 2.0, (33, 33)), 256.0)
    recv_msg, send_msg = mp.Pipe(duplex=False)
    _widen_pipe(send_msg)  # the message is sent before anything reads it
    recv_res, send_res = mp.Pipe(duplex=False)
    send_msg.send(("plot", _telemetry(), terrain, str(tmp_path / "p.png"), {"title": "t"}))
    try:
        pp._serve(recv_msg, send_res)
    finally:
        gc.enable()
    answer = recv_res.recv()
    assert answer == ("ok", str(tmp_path / "p.png")), answer[1][1] if answer[0] == "error" else answer
    assert seen == {"warm_up": False, "canvas": False, "draw": True}
    assert gc.isenabled()
