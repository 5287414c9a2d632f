"""A run's ``camera.mp4``, written by a second process that also renders the frames only the video needs.

Ports:
    Input (from the closed loop, at the camera rate): each frame the run rendered for the flight
    software, with its overlays; or, for a frame nobody on board consumes (below the vision
    cut-off), the world's visual state (the poses MuJoCo draws the scene from), the frame's index
    and its exposure gain.
    Output: ``camera.mp4``, the same bytes as :class:`~bench.report.report.CameraVideo` writes in
    the run's own process, renamed into place whole by :meth:`VideoProcess.close`.
    Rate: one message per camera frame, read as it comes (the second process queues them), so the
    closed loop never waits for an encoder or for a frame that only the video shows.

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

import fcntl
import pickle
import queue
import threading
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from bench.report.report import CameraVideo, frame_caption, track_overlay

PIPE_BYTES = 1 << 20  # the run-to-process pipe's kernel buffer, where the platform allows it
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)  # Linux's fcntl that sizes a pipe
RESULT_TIMEOUT_S = 600.0  # the most the run waits for the process to finish its queue
STOP_TIMEOUT_S = 10.0  # for an aborted process to delete its temporary file and stop


def _widen_pipe(conn: Any) -> None:
    """Make a pipe's kernel buffer ``PIPE_BYTES`` where the platform allows (else keep its default)."""
    try:
        fcntl.fcntl(conn.fileno(), F_SETPIPE_SZ, PIPE_BYTES)
    except OSError:
        pass


class VideoProcess:
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
        from bench.campaign.workers import worker_context

        ctx = worker_context()
        self._results, result_end = ctx.Pipe(duplex=False)
        message_end, self._send = ctx.Pipe(duplex=False)
        _widen_pipe(self._send)
        self._proc = ctx.Process(target=_serve, args=(message_end, result_end, scenario, str(path), fps, size),
                                 name="landbench-video", daemon=True)
        self._proc.start()
        message_end.close()
        result_end.close()
        self._path: Path | None = None
        self._ended = False

    def _post(self, msg: tuple) -> None:
        try:
            self._send.send(msg)
        except OSError:  # it has stopped (a broken pipe): raise its reason
            self._finish()
            raise RuntimeError("camera video: the video process stopped early") from None

    # --------------------------------------------------------------- the closed loop's side
    def start(self, world: Any) -> None:
        """The run's world: its renderer's digest, which the second world must match."""
        self._post(("digest", world.render_digest()))

    def __call__(self, t_ns: int, frame: np.ndarray, truth: Any, tracks: Any) -> None:
        """A frame the run rendered (for the flight software), to encode."""
        self._post(("frame", t_ns, frame, float(truth.r_BL_L[2]), *track_overlay(tracks)))

    def render_frame(self, t_ns: int, frame_index: int, world: Any, exposure_gain: float, truth: Any,
                     tracks: Any) -> None:
        """A frame for the video alone: rendered and corrupted in the second process from ``world``'s
        visual state now (camera frame ``frame_index``, its exposure gain), then encoded."""
        self._post(("render", t_ns, frame_index, exposure_gain, world.visual_state(),
                    float(truth.r_BL_L[2]), *track_overlay(tracks)))

    # --------------------------------------------------------------------- the end
    def close(self) -> Path | None:
        """Wait for every frame to be encoded; the final path (None: no frame was written).

        Raises:
            The second process's own exception (its traceback in a note), or RuntimeError when it
            stopped without one or sent nothing in ``RESULT_TIMEOUT_S``.
        """
        if not self._ended:
            self._post(("close",))
            self._finish()
        return self._path

    def _finish(self) -> None:
        """Stop sending, collect the process's result, and raise its error if it failed."""
        if self._ended:
            return
        self._ended = True
        self._send.close()
        try:
            if not self._results.poll(RESULT_TIMEOUT_S):
                raise RuntimeError(f"camera video: the video process sent no result in {RESULT_TIMEOUT_S:.0f} s")
            status, value = self._results.recv()
        except EOFError:
            status, value = "error", (None, f"it ended (exit code {self._proc.exitcode}) with no result")
        finally:
            self._stop()
        if status != "ok":
            exc, text = value
            if exc is None:
                raise RuntimeError(f"camera video: the video process failed: {text}")
            exc.add_note(f"(raised in the video process)\n{text}")
            raise exc  # its own type: the command reports an unwritable folder as it always did
        self._path = None if value is None else Path(value)

    def abort(self) -> None:
        """Stop the second process; its temporary file is deleted, the final path not touched."""
        if self._ended:
            return
        self._ended = True
        try:
            self._send.send(("abort",))
        except OSError:
            pass
        self._send.close()
        self._stop()

    def _stop(self) -> None:
        self._proc.join(timeout=STOP_TIMEOUT_S)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join()
        self._results.close()


def _picklable(exc: BaseException) -> bool:
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any failure means: send its text only
        return False
    return True


def _read_into(conn: Any, inbox: queue.SimpleQueue) -> None:
    """The second process's reader thread: every message into ``inbox`` as it arrives (EOF: None)."""
    try:
        while True:
            inbox.put(conn.recv())
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
        results.send(("error", (exc if _picklable(exc) else None, traceback.format_exc())))
    finally:
        if world is not None:
            world.close()
