"""Local worker processes of a campaign: their start method, their fork server and their thread counts.

A light module (the standard library and :mod:`models.gl`, nothing of the
simulation), so that a command can start the fork server before it imports
anything heavy itself: see :func:`start_worker_server`.

Ports:
    in: the number of workers a campaign runs at once;
    out: the multiprocessing context its workers start from, the thread
    count each may use, the environment a worker's thread pools read at start.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
from collections.abc import Iterator
from typing import Any

# What a fork server imports before it forks any worker: every module a case needs, and nothing
# that opens a GL display or builds a MuJoCo model (the GL backend is chosen in the master and
# handed over in the environment, so importing mujoco there probes nothing). The module imports
# bench.sim.run and freezes what the imports made out of the garbage collector's reach.
WORKER_PRELOAD = ["bench.campaign.server_preload"]

# Threads a case may use are set per worker: the CPUs divided among the
# workers. Without this, llvmpipe, OpenCV and BLAS each start one thread per
# core in every worker, and K workers on K cores fight over them.
THREAD_ENV_VARS = ("LP_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def threads_per_worker(workers: int) -> int:
    """The CPUs this process may use, shared out among ``workers`` (at least 1 each)."""
    return max(1, len(os.sched_getaffinity(0)) // workers)


@contextlib.contextmanager
def thread_env(threads: int) -> Iterator[None]:
    """Set the thread-count variables a started child reads at start (the user's own win)."""
    added = [k for k in THREAD_ENV_VARS if k not in os.environ]
    os.environ.update({k: str(threads) for k in added})
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def worker_context() -> Any:
    """The multiprocessing context local workers start from.

    A fork server (where the platform has one): a process started fresh, which
    imports :data:`WORKER_PRELOAD` once and then forks a worker on request. A
    worker thus starts in milliseconds with its imports done, yet inherits no
    GL context, MuJoCo model or random state: the server never flies, renders
    or draws. The GL backend (``MUJOCO_GL``) is chosen here, in the master, and
    passed down in the environment, so that the server's ``import mujoco``
    does not initialise an EGL display that its forks would share. Its BLAS
    and OpenMP thread pools are sized once, from the environment of the first
    campaign that starts it. Elsewhere: ``spawn``, a fresh interpreter per worker.
    """
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    from models.gl import ensure_gl_backend

    ensure_gl_backend()
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(WORKER_PRELOAD)
    return ctx


def start_worker_server(workers: int | None) -> bool:
    """Start the fork server now, so that its imports run while the caller does its own.

    The server's imports (:data:`WORKER_PRELOAD`, 1.5–2 s) otherwise begin
    only when the first worker is asked for, after the master has imported
    and validated everything itself; started first, the two overlap on two
    cores. Nothing else changes: the server is the one the campaign would
    have started (same preload, same thread counts for ``workers``), and it
    stops with this process. Returns False where there is no fork server
    (``spawn``: nothing to start ahead).
    """
    ctx = worker_context()
    if ctx.get_start_method() != "forkserver":
        return False
    from multiprocessing import forkserver

    with thread_env(threads_per_worker(workers or 1)):
        forkserver.ensure_running()
    return True
