"""A helper process of one run: forked from the campaign workers' fork server, fed through a pipe.

``landbench run`` hands two jobs to such processes so that they run on the second core, off the
closed loop's path: ``camera.mp4`` (:mod:`bench.report.video_process`) and ``plots.png``
(:mod:`bench.report.plot_process`). Both follow the same protocol, kept here once:

- the run sends tuples through a one-way pipe (its kernel buffer widened where the platform allows, so
  that a message rarely waits for the reader); the many small messages of a stream (a frame each) go
  ``BATCH_MESSAGES`` at a time (:meth:`ChildProcess.post_batched`), in one message that
  :func:`unbatched` takes apart, since each write that wakes the reader costs the run about as much as
  pickling a frame;
- the process answers once, through a second pipe: ``("ok", value)`` or ``("error", (exception or
  None, traceback text))``; an ``("abort",)`` message, or the run's end of the pipe closing, stops it
  with nothing left behind. A process makes its output only from what it is sent, so one that was sent
  nothing yet is stopped at once (``terminate``) rather than after its start-up work (a run refused
  at set-up, or interrupted early, does not wait for the plot process's warm-up);
- :meth:`ChildProcess.finish` waits for that answer and raises the process's own exception (its
  traceback in a note), so the command reports a failure there as it would one in the run itself.

A process is started on a thread of the run (:class:`ChildProcess`): the fork server forks it only once
its own imports are done, and the run goes on meanwhile (building its world) instead of waiting for
that; its first message, or its end, waits for the start.
"""

from __future__ import annotations

import fcntl
import pickle
import threading
from typing import Any, Callable

PIPE_BYTES = 1 << 20  # the run-to-process pipe's kernel buffer, where the platform allows it
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)  # Linux's fcntl that sizes a pipe
RESULT_TIMEOUT_S = 600.0  # the most the run waits for the process's answer
STOP_TIMEOUT_S = 10.0  # for an aborted process to clean up and stop
BATCH_MESSAGES = 8  # messages of a stream sent in one write (8 frames of 256^2: half the widened pipe)
BATCH = "batch"  # the first item of a message that carries a list of messages


def _widen_pipe(conn: Any) -> None:
    """Make a pipe's kernel buffer ``PIPE_BYTES`` where the platform allows (else keep its default)."""
    try:
        fcntl.fcntl(conn.fileno(), F_SETPIPE_SZ, PIPE_BYTES)
    except OSError:
        pass


def unbatched(msg: tuple) -> list[tuple]:
    """The messages one received message carries, in the order posted (one, or a batch's)."""
    return list(msg[1]) if msg and msg[0] == BATCH else [msg]


def picklable(exc: BaseException) -> bool:
    """Whether ``exc`` survives the trip to the run (else only its text is sent)."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any failure means: send its text only
        return False
    return True


class ChildProcess:
    """The run's side of a helper process (see the module docstring).

    The process is started on a thread (``landbench-<role>-start``), so that the constructor returns at
    once: the fork server, started with the command, forks it only when the server's own imports are
    done (in ``landbench run`` about half a second after the run's, which meanwhile builds its world).
    Every method that talks to the process waits for that start first, and raises when it failed.

    Args:
        target: The process's body, called as ``target(messages, results, *args)`` with the two pipe
            ends it reads and answers through.
        args: Its further arguments (pickled to it when it starts: not to be changed afterwards).
        role: What it makes, in its name and messages ("video": the process ``landbench-video``,
            errors "<label>: the video process failed: ...").
        label: The output it is for, first in its error messages ("camera video").
    """

    def __init__(self, target: Callable[..., None], args: tuple, role: str, label: str) -> None:
        from bench.campaign.workers import worker_context

        ctx = worker_context()
        self._results, result_end = ctx.Pipe(duplex=False)
        message_end, self._send = ctx.Pipe(duplex=False)
        _widen_pipe(self._send)
        self._proc = ctx.Process(target=target, args=(message_end, result_end, *args), name=f"landbench-{role}",
                                 daemon=True)
        self._what = f"{label}: the {role} process"
        self._start_error: BaseException | None = None

        def start() -> None:
            try:
                self._proc.start()
            except BaseException as exc:  # noqa: BLE001 - raised in the run by _started
                self._start_error = exc
            finally:
                message_end.close()  # the process's ends: its own copies are all that is left
                result_end.close()

        self._starter: threading.Thread | None = threading.Thread(target=start, name=f"landbench-{role}-start")
        self._starter.start()
        self._role = role
        self._ended = False
        self._sent = False  # whether anything was written to the process
        self._value: Any = None
        self._batch: list[tuple] = []  # posted by post_batched, not sent yet

    def post(self, msg: tuple) -> None:
        """Send one message now (after any batched ones); a process that has stopped raises its reason here."""
        self._flush()
        self._write(msg)

    def post_batched(self, msg: tuple) -> None:
        """Send one message of a stream: held until ``BATCH_MESSAGES`` are, then sent together (:meth:`post`
        and :meth:`finish` send what is held first, so the process reads every message in the order posted)."""
        self._batch.append(msg)
        if len(self._batch) >= BATCH_MESSAGES:
            self._flush()

    def _flush(self) -> None:
        if self._batch:
            batch, self._batch = self._batch, []
            self._write((BATCH, batch))

    def _started(self) -> None:
        """Wait for the process's start (see the class docstring); raise when it could not start."""
        if self._starter is None:
            return
        self._starter.join()
        self._starter = None
        if self._start_error is not None:
            self._ended = True
            self._send.close()
            self._results.close()
            raise RuntimeError(f"{self._what} did not start: {self._start_error}") from self._start_error

    def _write(self, msg: tuple) -> None:
        self._started()
        self._sent = True
        try:
            self._send.send(msg)
        except OSError:  # it has stopped (a broken pipe): raise its reason
            self.finish()
            raise RuntimeError(f"{self._what} stopped early") from None

    def finish(self) -> Any:
        """Stop sending, wait for the process's answer and return its value.

        Raises:
            The process's own exception (its traceback in a note), or RuntimeError when it stopped
            without one or sent nothing in ``RESULT_TIMEOUT_S``.
        """
        if self._ended:
            return self._value
        self._started()
        if self._batch:
            batch, self._batch = self._batch, []
            self._sent = True
            try:
                self._send.send((BATCH, batch))
            except OSError:  # it has stopped: its answer, read below, says why
                pass
        self._ended = True
        self._send.close()
        try:
            if not self._results.poll(RESULT_TIMEOUT_S):
                raise RuntimeError(f"{self._what} sent no result in {RESULT_TIMEOUT_S:.0f} s")
            status, value = self._results.recv()
        except EOFError:
            status, value = "error", (None, f"it ended (exit code {self._proc.exitcode}) with no result")
        finally:
            self._stop()
        if status != "ok":
            exc, text = value
            if exc is None:
                raise RuntimeError(f"{self._what} failed: {text}")
            exc.add_note(f"(raised in the {self._role} process)\n{text}")
            raise exc  # its own type: the command reports an unwritable folder as it always did
        self._value = value
        return value

    def abort(self) -> None:
        """Stop the process; it leaves nothing behind (sent nothing yet, it is stopped at once)."""
        if self._ended:
            return
        try:
            self._started()
        except RuntimeError:
            return  # it never started: nothing to stop
        self._ended = True
        self._batch = []  # nothing more is written
        if not self._sent:  # it has made nothing: no need to wait for it to read the abort
            self._proc.terminate()
        else:
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
