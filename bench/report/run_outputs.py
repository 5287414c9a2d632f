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
import queue
import threading
from pathlib import Path

from bench.report.io import atomic_write_text, json_safe
from bench.report.report import CameraVideo, frame_caption, summary_table, write_plots, write_telemetry_parquet
from bench.sim.run import RunResult, run
from bench.scenario import NS_PER_S, Scenario, scenario_to_toml

SUMMARY = "summary.json"
TELEMETRY = "telemetry.parquet"
SCENARIO = "scenario.toml"
PLOTS = "plots.png"
VIDEO = "camera.mp4"


# Frames waiting for the encoder (bounded: a stalled encoder slows the run, it never fills memory).
VIDEO_QUEUE_FRAMES = 64


class _VideoThread:
    """Encodes ``camera.mp4`` on a thread of its own while the run goes on.

    The closed loop hands each frame over (copied) and continues; one
    consumer thread annotates and encodes the frames in order, so the file is
    the one a synchronous writer makes. OpenCV's drawing and encoding release
    the GIL, so on a second core the encoding no longer adds to the run's wall
    time. The writer is opened at the first frame: a run refused at set-up
    writes nothing.
    """

    def __init__(self, path: Path, fps: float, size: tuple[int, int]):
        self._path, self._fps, self._size = path, fps, size
        self.writer: CameraVideo | None = None
        self.error: BaseException | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=VIDEO_QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._work, name="camera.mp4", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self.error is not None:
                continue  # drain: the run is told at the next frame or at the end
            try:
                if self.writer is None:
                    self.writer = CameraVideo(self._path, fps=self._fps, size=self._size)
                self.writer.add(item[0], tracks_xy=item[1], prev_xy=item[2], text=item[3])
            except BaseException as exc:  # noqa: BLE001 - handed to the run's thread
                self.error = exc

    def add(self, frame, tracks_xy, prev_xy, text: str) -> None:
        if self.error is not None:
            raise self.error
        copy = (lambda a: None if a is None else a.copy())
        self._queue.put((frame.copy(), copy(tracks_xy), copy(prev_xy), text))

    def stop(self) -> None:
        """Wait for the frames queued so far to be encoded (or dropped after an error)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()

    def finish(self) -> CameraVideo | None:
        """:meth:`stop`, then the open writer (None: no frame came); raises the encoder's error, if any."""
        self.stop()
        if self.error is not None:
            raise self.error
        return self.writer


def run_and_write(scenario: Scenario, out: Path, video: bool = True, progress: bool = False) -> tuple[dict, str]:
    """Fly the scenario and write its files into ``out``.

    Returns:
        (summary dict as written to summary.json, the terminal summary table).
    """
    cam = scenario.camera
    encoder: _VideoThread | None = None
    created = not out.exists()

    def sink(t_ns, frame, truth, tracks) -> None:
        nonlocal encoder
        if encoder is None:
            encoder = _VideoThread(out / VIDEO, fps=NS_PER_S / cam.period_ns, size=(cam.width_px, cam.height_px))
        xy = prev = None
        if tracks is not None and len(tracks):
            xy, prev = tracks.xy, tracks.prev_xy
        encoder.add(frame, xy, prev, frame_caption(t_ns / NS_PER_S, float(truth.r_BL_L[2])))

    try:
        try:
            result = run(scenario, frame_sink=sink if video and cam.enabled else None, progress=progress)
        finally:
            if encoder is not None:
                encoder.stop()
        summary, outputs = write_run_outputs(scenario, result, out, encoder.finish() if encoder is not None else None)
    except BaseException:
        writer = encoder.writer if encoder is not None else None
        if writer is not None:
            writer.abort()  # no half-written video left behind, whatever failed
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # nor an empty folder this run made
        raise
    return summary, summary_table(summary, {k: str(v) for k, v in outputs.items()})


def write_run_outputs(scenario: Scenario, result: RunResult, out: Path,
                      video: CameraVideo | None = None) -> tuple[dict, dict[str, Path]]:
    """Write the files of a finished run (``video``: its open writer, closed here).

    Also used by a campaign worker that decides only after the run whether a
    case's files are kept (``--retention failed``).

    Returns:
        (summary dict as written to summary.json, {name: path} of the files written).
    """
    summary = json_safe(result.summary)
    outputs = {"scenario": out / SCENARIO, "summary": out / SUMMARY, "telemetry": out / TELEMETRY, "plots": out / PLOTS}
    atomic_write_text(outputs["scenario"], scenario_to_toml(scenario))
    write_telemetry_parquet(result.telemetry, outputs["telemetry"])
    touchdown = summary["touchdown"] if summary["touchdown"]["t_s"] is not None else None
    write_plots(result.telemetry, result.terrain, outputs["plots"],
                title=f"{scenario.name}: seed {scenario.seed}, {scenario.guidance.law} guidance -> {summary['outcome']}",
                criteria=summary["criteria"], touchdown=touchdown,
                sun_elevation_deg=scenario.sun.elevation_deg, sun_azimuth_deg=scenario.sun.azimuth_deg)
    if video is not None:
        path = video.close()
        if path is not None:
            outputs["video"] = path
    # Last: a summary.json present means the run's files are complete.
    atomic_write_text(outputs["summary"], json.dumps(summary, indent=2) + "\n")
    return summary, outputs
