"""The files of one run (``landbench run --out DIR``).

``DIR/summary.json`` (the stable contract), ``DIR/telemetry.parquet`` (one row
per control tick), ``DIR/scenario.toml`` (the resolved scenario: rerunning it
reproduces the landing), ``DIR/plots.png`` and ``DIR/camera.mp4``.

Nothing is written until the run has finished, and every file is written
atomically, so a crash or a bad input never leaves a half-written result or
clobbers an earlier one; the video streams into a temporary file that is
renamed into place only at the end.
"""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

from bench.report.io import atomic_write_text, json_safe
from bench.report.report import (CameraVideo, frame_caption, summary_table, track_overlay, write_plots,
                                 write_telemetry_parquet)
from bench.report.plot_process import PlotProcess
from bench.report.video_process import VideoProcess
from bench.sim.run import RunResult, run
from bench.scenario import NS_PER_S, Scenario, scenario_to_toml

SUMMARY = "summary.json"
TELEMETRY = "telemetry.parquet"
SCENARIO = "scenario.toml"
PLOTS = "plots.png"
VIDEO = "camera.mp4"


def run_and_write(scenario: Scenario, out: Path, video: bool = True, progress: bool = False,
                  video_process: bool = False, plot_process: bool = False) -> tuple[dict, str]:
    """Fly the scenario and write its files into ``out``.

    Args:
        video_process: Encode ``camera.mp4`` in a second process, which also renders the frames
            only the video needs (:class:`~bench.report.video_process.VideoProcess`): the same
            file, while the run flies on. Ignored in a daemon process (a campaign worker), which
            may not start one.
        plot_process: Draw ``plots.png`` in a second process made ready while the run flies
            (:class:`~bench.report.plot_process.PlotProcess`): the same file. Ignored in a daemon
            process, as ``video_process``.

    Returns:
        (summary dict as written to summary.json, the terminal summary table).
    """
    cam = scenario.camera
    writer: CameraVideo | VideoProcess | None = None  # opened at the first frame: a run refused at set-up writes nothing
    created = not out.exists()

    def sink(t_ns, frame, truth, tracks) -> None:
        nonlocal writer
        if writer is None:
            writer = CameraVideo(out / VIDEO, fps=NS_PER_S / cam.period_ns, size=(cam.width_px, cam.height_px))
        xy, prev = track_overlay(tracks)
        writer.add(frame, tracks_xy=xy, prev_xy=prev, text=frame_caption(t_ns / NS_PER_S, float(truth.r_BL_L[2])))

    frame_sink = sink if video and cam.enabled else None
    helpers = not multiprocessing.current_process().daemon
    plotter = PlotProcess() if plot_process and helpers else None
    try:
        if frame_sink is not None and video_process and helpers:
            writer = frame_sink = VideoProcess(scenario, out / VIDEO, fps=NS_PER_S / cam.period_ns,
                                                size=(cam.width_px, cam.height_px))
        result = run(scenario, frame_sink=frame_sink, progress=progress)
        summary, outputs = write_run_outputs(scenario, result, out, writer, plotter)
    except BaseException:
        if plotter is not None:
            plotter.abort()
        if writer is not None:
            writer.abort()  # no half-written video left behind, whatever failed
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # nor an empty folder this run made
        raise
    return summary, summary_table(summary, {k: str(v) for k, v in outputs.items()})


def write_run_outputs(scenario: Scenario, result: RunResult, out: Path,
                      video: CameraVideo | VideoProcess | None = None,
                      plotter: PlotProcess | None = None) -> tuple[dict, dict[str, Path]]:
    """Write the files of a finished run (``video``: its open writer, closed here; ``plotter``: the
    process that draws ``plots.png``, else it is drawn here).

    Also used by a campaign worker that decides only after the run whether a
    case's files are kept (``--retention failed``).

    Returns:
        (summary dict as written to summary.json, {name: path} of the files written).
    """
    summary = json_safe(result.summary)
    outputs = {"scenario": out / SCENARIO, "summary": out / SUMMARY, "telemetry": out / TELEMETRY, "plots": out / PLOTS}
    touchdown = summary["touchdown"] if summary["touchdown"]["t_s"] is not None else None
    plot_args = dict(title=f"{scenario.name}: seed {scenario.seed}, {scenario.guidance.law} guidance -> "
                           f"{summary['outcome']}",
                     criteria=summary["criteria"], touchdown=touchdown,
                     sun_elevation_deg=scenario.sun.elevation_deg, sun_azimuth_deg=scenario.sun.azimuth_deg)
    if plotter is not None:  # first: it draws while the files below are written
        plotter.draw(result.telemetry, result.terrain, outputs["plots"], **plot_args)
    atomic_write_text(outputs["scenario"], scenario_to_toml(scenario))
    write_telemetry_parquet(result.telemetry, outputs["telemetry"])
    if plotter is None:
        write_plots(result.telemetry, result.terrain, outputs["plots"], **plot_args)
    else:
        plotter.result()  # before the video is closed: a failed plot leaves no video behind either
    if video is not None:
        path = video.close()  # a video process has encoded while the plots were drawn
        if path is not None:
            outputs["video"] = path
    # Last: a summary.json present means the run's files are complete.
    atomic_write_text(outputs["summary"], json.dumps(summary, indent=2) + "\n")
    return summary, outputs
