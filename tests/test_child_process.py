"""The helper processes' protocol (``bench.report.child_process``): batched messages arrive whole and in order."""

from __future__ import annotations

import time

import pytest

from bench.report.child_process import BATCH_MESSAGES, ChildProcess, unbatched


def _collect(messages, results) -> None:
    """A helper that reads until ("close",) and answers with every message it read and the reads it took."""
    got, reads = [], 0
    while True:
        reads += 1
        for msg in unbatched(messages.recv()):
            if msg == ("close",):
                results.send(("ok", (got, reads)))
                return
            got.append(msg)


def test_batched_and_single_messages_arrive_in_the_order_posted():
    proc = ChildProcess(_collect, (), role="test", label="protocol")
    posted = []
    for i in range(2 * BATCH_MESSAGES + 3):  # two full batches and three held
        posted.append(("frame", i, bytes(1000 * i)))
        proc.post_batched(posted[-1])
    posted.append(("digest", b"x"))
    proc.post(posted[-1])  # sends the three held first
    for i in range(5):
        posted.append(("render", i))
        proc.post_batched(posted[-1])
    proc.post(("close",))
    got, reads = proc.finish()
    assert got == posted
    assert reads == 2 + 1 + 1 + 1 + 1  # two batches, the held three, the digest, the last five, the close


def test_finish_sends_what_is_held():
    proc = ChildProcess(_collect, (), role="test", label="protocol")
    proc.post_batched(("frame", 1))
    proc.post_batched(("close",))  # held, then sent by finish
    assert proc.finish() == ([("frame", 1)], 1)


def _gc_state(messages, results) -> None:
    """A helper that answers with its garbage collector's state as it starts."""
    import gc
    import sys

    results.send(("ok", (gc.get_freeze_count(), gc.isenabled(), "bench.sim.run" in sys.modules)))


def test_a_helper_inherits_the_servers_imports_frozen_out_of_the_collector():
    """The fork server's preload (bench.campaign.server_preload) freezes what its imports made, so that no
    collection in a process forked from it walks (and writes to) the inherited objects."""
    frozen, enabled, preloaded = ChildProcess(_gc_state, (), role="test", label="gc").finish()
    assert preloaded
    assert enabled  # frozen, not switched off
    assert frozen > 20_000  # what NumPy, SciPy, MuJoCo, OpenCV and landbench's modules made (about 85 000)


def _helper_process_class() -> type:
    """The process class the helpers are made from (the fork server's context)."""
    from bench.campaign.workers import worker_context

    return type(worker_context().Process(target=print))


def _slow_start(monkeypatch, delay_s: float) -> list[float]:
    """Make every helper's start take ``delay_s`` longer (a fork server still importing); returns the
    times the starts began."""
    process_class = _helper_process_class()
    real_start = process_class.start
    began: list[float] = []

    def slow_start(self):
        began.append(time.perf_counter())
        time.sleep(delay_s)
        real_start(self)

    monkeypatch.setattr(process_class, "start", slow_start)
    return began


def test_the_run_goes_on_while_its_helper_starts(monkeypatch):
    """The constructor returns before the process is started: in `landbench run` the fork server forks
    the helpers only when its imports are done, and the run builds its world meanwhile. What is posted
    before the start arrives, in order."""
    began = _slow_start(monkeypatch, 1.0)
    t0 = time.perf_counter()
    proc = ChildProcess(_collect, (), role="test", label="protocol")
    assert time.perf_counter() - t0 < 0.5  # not the second the start takes
    proc.post_batched(("frame", 1))
    proc.post(("digest", b"x"))  # waits for the start, then sends both
    proc.post(("close",))
    assert proc.finish() == ([("frame", 1), ("digest", b"x")], 3)  # the held frame, the digest, the close
    assert len(began) == 1 and not proc._proc.is_alive()


def test_a_helper_that_cannot_start_is_reported_by_its_first_use(monkeypatch):
    process_class = _helper_process_class()

    def failing_start(self):
        raise OSError("no fork server")

    monkeypatch.setattr(process_class, "start", failing_start)
    proc = ChildProcess(_collect, (), role="test", label="protocol")
    with pytest.raises(RuntimeError, match="protocol: the test process did not start: no fork server"):
        proc.post(("close",))
    proc.abort()  # nothing to stop, and no error
    aborted = ChildProcess(_collect, (), role="test", label="protocol")
    aborted.abort()  # a helper that never started is aborted quietly
    assert not aborted._proc.is_alive()


def _busy_then_collect(messages, results, marker) -> None:
    """A helper with a long start-up (as the plot process's warm-up) before it reads; on ("abort",) it
    writes ``marker`` (its clean-up), as the video process deletes its temporary file."""
    import pathlib

    time.sleep(3.0)
    while True:
        for msg in unbatched(messages.recv()):
            if msg == ("abort",):
                pathlib.Path(marker).write_text("cleaned up")
                return


def test_a_helper_sent_nothing_is_stopped_without_waiting_for_its_start_up(tmp_path):
    """It has made nothing (a helper makes its output only from what it is sent): a run refused at
    set-up does not wait for the plot process's warm-up before its error line."""
    proc = ChildProcess(_busy_then_collect, (str(tmp_path / "marker"),), role="test", label="protocol")
    proc._started()  # the fork server has forked it: only its start-up is left to wait for
    t0 = time.perf_counter()
    proc.abort()
    assert time.perf_counter() - t0 < 1.5  # not the 3 s of its start-up
    assert not proc._proc.is_alive() and not (tmp_path / "marker").exists()


def test_a_helper_that_was_sent_work_reads_the_abort_and_cleans_up(tmp_path):
    proc = ChildProcess(_busy_then_collect, (str(tmp_path / "marker"),), role="test", label="protocol")
    proc.post(("frame", 1))
    proc.abort()
    assert not proc._proc.is_alive()
    assert (tmp_path / "marker").read_text() == "cleaned up"
