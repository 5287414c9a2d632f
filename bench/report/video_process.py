"""A run's ``camera.mp4``, written by a second process that also renders the frames only the video needs.

Ports:
    Input (from the closed loop, at the camera rate): each frame the run rendered for the flight
    software, with its overlays; or, for a frame nobody on board consumes (below the vision
    cut-off), the world's visual state (the poses MuJoCo draws the scene from), the frame's index
    and its exposure gain.
    Output: ``camera.mp4``, the same bytes as :class:`~bench.report.report.CameraVideo` writes in
    the run's own process, renamed into place whole by :meth:`VideoProcess.close`.
    Rate: one message per camera frame, sent eight at a time (``ChildProcess.post_batched``) and read
    as they come (the second process queues them), so the closed loop never waits for an encoder or
    for a frame that only the video shows.

``landbench run`` spent about a third of its time on frames that no one on board looks at and on
encoding the video. Here a second process (forked from the campaign workers' fork server, so its
imports are done) builds the same world from the scenario, renders those frames through its own
GL context with the same detector noise (each frame's noise is its own stream: see
``SensorSuite.frame_rng``) and encodes every frame, on the second core, while the run flies on (and,
after the landing, while the run draws its plots).

The frames are the pixels the run would have rendered: the second world is checked against the
run's (the digest of everything the renderer uploads, ``World.render_digest``)
before a frame is written, and its scene is drawn from the run's own body, geom, site, camera and
light poses, copied at the frame's time (``World.visual_state``).
"""

from __future__ import annotations

import queue
import threading
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from bench.report.child_process import ChildProcess, picklable, unbatched
from bench.report.report import CameraVideo, frame_caption, track_overlay


class VideoProcess(ChildProcess):
    """The run's frame sink for ``camera.mp4``, in a second process (see the module docstring).

    The closed loop calls :meth:`start` once with its world, then at every camera frame either
    the sink itself with a frame it rendered for the flight software, or :meth:`render_frame`
    for a frame that only the video wants; :meth:`close` waits for the file.

    Args:
        scenario: The run's scenario: the second process builds the same terrain and world from it.
        path: The final video path (``.mp4``).
        fps: The camera rate [1/s].
        size: Frame (width, height) [px].
    """

    def __init__(self, scenario: Any, path: Path, fps: float, size: tuple[int, int]) -> None:
        super().__init__(_serve, (scenario, str(path), fps, size), role="video", label="camera video")

    # --------------------------------------------------------------- the closed loop's side
    def start(self, world: Any) -> None:
        """The run's world: its renderer's digest, which the second world must match."""
        self.post(("digest", world.render_digest()))

    def __call__(self, t_ns: int, frame: np.ndarray, truth: Any, tracks: Any) -> None:
        """A frame the run rendered (for the flight software), to encode."""
        self.post_batched(("frame", t_ns, frame, float(truth.r_BL_L[2]), *track_overlay(tracks)))

    def render_frame(self, t_ns: int, frame_index: int, world: Any, exposure_gain: float, truth: Any,
                     tracks: Any) -> None:
        """A frame for the video alone: rendered and corrupted in the second process from ``world``'s
        visual state now (camera frame ``frame_index``, its exposure gain), then encoded."""
        self.post_batched(("render", t_ns, frame_index, exposure_gain, world.visual_state(),
                           float(truth.r_BL_L[2]), *track_overlay(tracks)))

    # --------------------------------------------------------------------- the end
    def close(self) -> Path | None:
        """Wait for every frame to be encoded; the final path (None: no frame was written).

        Raises:
            The second process's own exception (its traceback in a note), or RuntimeError when it
            stopped without one or sent nothing in time.
        """
        if not self._ended:
            self.post(("close",))
        value = self.finish()
        return None if value is None else Path(value)

    # abort() (ChildProcess): its temporary file is deleted, the final path not touched.


def _read_into(conn: Any, inbox: queue.SimpleQueue) -> None:
    """The second process's reader thread: every message into ``inbox`` as it arrives, a batch's one by one
    (EOF: None)."""
    try:
        while True:
            for msg in unbatched(conn.recv()):
                inbox.put(msg)
    except (EOFError, OSError):
        inbox.put(None)


def _serve(messages: Any, results: Any, scenario: Any, path: str, fps: float, size: tuple[int, int]) -> None:
    """The second process: build the world, then render, caption and encode each frame in order."""
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    threading.Thread(target=_read_into, args=(messages, inbox), daemon=True).start()
    video = world = None
    try:
        from bench.scenario import NS_PER_S
        from bench.sim.world_builder import build_sensors, build_terrain, build_world

        # Built now, while the run flies its first frames: frames rendered here come below the vision cut-off.
        world = build_world(scenario, build_terrain(scenario))
        sensors = build_sensors(scenario)
        own = world.render_digest()
        while True:
            msg = inbox.get()
            if msg is None or msg[0] == "abort":  # stopped, with or without a word: leave nothing behind
                raise EOFError
            kind = msg[0]
            if kind == "digest":
                if msg[1] != own:  # an internal invariant: the two worlds must draw the same scene
                    raise RuntimeError("the video process built a world whose renderer differs from the run's")
                continue
            if kind == "close":
                written = None if video is None else video.close()
                results.send(("ok", None if written is None else str(written)))
                return
            if kind == "frame":
                t_ns, frame, height_m, xy, prev = msg[1:]
            else:  # "render"
                t_ns, index, gain, state, height_m, xy, prev = msg[1:]
                world.set_visual_state(state)
                frame = sensors.camera_frame_at(world, index, gain)
            if video is None:  # opened at the first frame, as the run's own writer is
                video = CameraVideo(path, fps=fps, size=size)
            video.add(frame, tracks_xy=xy, prev_xy=prev, text=frame_caption(t_ns / NS_PER_S, height_m))
    except EOFError:
        if video is not None:
            video.abort()
    except BaseException as exc:  # noqa: BLE001 - reported to the run, which raises it
        if video is not None:
            video.abort()
        results.send(("error", (exc if picklable(exc) else None, traceback.format_exc())))
    finally:
        if world is not None:
            world.close()
