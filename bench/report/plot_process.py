"""A run's ``plots.png``, drawn by a second process that is ready before the landing ends.

Ports:
    Input (once, when the run has finished): its telemetry, the terrain's geometry
    (:meth:`models.terrain.Terrain.geometry_only`), the figure's title, limits and sun, and the path.
    Output: ``plots.png``, the file :func:`bench.report.report.write_plots` writes (it is that
    function), atomically.
    Rate: once per run.

In ``landbench run`` the plots were drawn after the landing, in the run's own process, from a cold
start: importing matplotlib and loading its fonts and text machinery took about as long as drawing
the twelve panels (1.5–2.3 s in all, against about 1.0 s warm). Here a process forked from the
campaign workers' fork server imports matplotlib and draws a small figure of the same kinds of
artists while the run flies (on the second core, which the closed loop leaves partly idle), makes
the run figure's empty panels and their ticks (:func:`~bench.report.report.plot_canvas`), then
waits; at the end it draws the run's figure warm while the run writes its other files and the video
process finishes, its panels shared with a fork of itself (:mod:`bench.report.split_draw`: the same
bytes), since the run then only waits for it.
"""

from __future__ import annotations

import gc
import io
import traceback
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from bench.report.child_process import ChildProcess, picklable


TICKS_AHEAD = 10  # major ticks made ahead on each axis of the run's figure (its axes have 4 to 9)


class PlotProcess(ChildProcess):
    """The run's ``plots.png`` writer, in a second process (see the module docstring).

    Call :meth:`draw` once with what :func:`~bench.report.report.write_plots` takes, then
    :meth:`result` for the path written.
    """

    def __init__(self) -> None:
        super().__init__(_serve, (), role="plots", label="plots")

    def draw(self, telemetry: Mapping[str, np.ndarray], terrain: Any, path: Path, **kwargs: Any) -> None:
        """Draw the plots of a finished run (``terrain``: its geometry is all that is read)."""
        self.post(("plot", {k: np.asarray(v) for k, v in telemetry.items()}, terrain.geometry_only(), str(path),
                   kwargs))

    def result(self) -> Path:
        """Wait for the plots; the path written.

        Raises:
            The process's own exception (a bad column, an unwritable folder), or RuntimeError when
            it stopped without one.
        """
        return Path(self.finish())


def warm_up() -> None:
    """Draw, into memory, a small figure of the artists the run's plots use (lines, spans, a log axis,
    a legend with patches, an image, titles): matplotlib's imports, fonts, text layout and PNG writer
    are then loaded."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(3.0, 2.0))
    ax, log = fig.subplots(1, 2)
    ax.plot([0.0, 1.0], [0.0, 1.0], label="a")
    ax.axvspan(0.2, 0.4, alpha=0.2, lw=0)
    ax.axhline(0.5, ls="--")
    ax.legend([Patch(color="tab:blue", alpha=0.3)], ["phase"], fontsize=7)
    ax.set_title("t [s]")
    ax.set_xlabel("t [s]")
    ax.grid(alpha=0.3)
    log.semilogy([0.0, 1.0], [0.01, 10.0])
    log.imshow(np.zeros((4, 4)), extent=(0.0, 1.0, 0.1, 1.0), origin="lower", aspect="auto")
    fig.suptitle("landbench", fontsize=13)
    fig.savefig(io.BytesIO(), format="png", dpi=50)


def _serve(messages: Any, results: Any) -> None:
    """The second process: warm up, then draw the one figure it is sent."""
    try:
        from bench.report.report import plot_canvas, write_plots

        # matplotlib's imports and the artists made ahead keep almost all they create, so collections
        # while they are made (a tenth of their CPU, measured) free little: they run once, afterwards.
        gc.disable()
        try:
            warm_up()
            # The empty panels and their ticks: a run's telemetry has the navigation errors (else a new one is made).
            canvas = plot_canvas(nav=True, ticks=TICKS_AHEAD)
        finally:
            gc.enable()
        msg = messages.recv()
        if msg[0] == "abort":
            return
        _, telemetry, terrain, path, kwargs = msg
        results.send(("ok", str(write_plots(telemetry, terrain, path, canvas=canvas, processes=2, **kwargs))))
    except EOFError:  # the run stopped without a word: leave nothing behind
        pass
    except BaseException as exc:  # noqa: BLE001 - reported to the run, which raises it
        results.send(("error", (exc if picklable(exc) else None, traceback.format_exc())))
