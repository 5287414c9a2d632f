"""A figure's PNG drawn by two processes: a fork draws part of the axes while this process draws the rest.

Ports:
    Input: a matplotlib ``Figure`` whose artists are all made (nothing drawn yet), and the dpi.
    Output: the PNG bytes ``fig.savefig(format="png", dpi=dpi)`` writes, byte for byte.
    Rate: once per figure; used by the run's plot process (:mod:`bench.report.plot_process`), which
    draws ``plots.png`` after the landing while the run's own process only waits for it.

Drawing the run's twelve panels takes Agg about a second on one core, and the second core is idle
then. Here the process forks: the child draws the axes given to it (the costlier half, by the
number of data points drawn) into a raw RGBA buffer shared with the parent, the parent draws the
other axes and the figure's own artists (its title), then takes each pixel from the one half that
drew it and encodes the PNG as matplotlib does.

The two halves make the same image as one drawing when no pixel is drawn by both: the axes of a
fixed grid with margins never share one. That is checked on every figure (a pixel that differs
from the background in both halves); where it fails, or the child fails, the figure is drawn
whole in this process, so the bytes are always those of one drawing.
"""

from __future__ import annotations

import gc
import io
import mmap
import os
import struct
import threading
from typing import Any

import numpy as np

# The axes' drawing costs, in units of an axes' fixed cost (its frame, ticks, labels and legend: about
# 40 ms), measured on the run's plots (first drawings, one core): a line's points add one unit per
# 26 000, a log-scaled axis 2.6 units (its minor ticks and exponent labels), an axes switched off
# nothing. The PNG's encoding, which the parent does after the halves, takes about 3 units, but the
# child, a fresh fork whose first writes copy pages, draws more slowly: 1.5 balanced them in the run.
POINTS_PER_UNIT = 26000.0
LOG_AXIS_UNITS = 2.6
ENCODE_UNITS = 1.5
_HEADER = struct.Struct("<q")  # the child's byte count in the shared buffer


def draw_cost(ax: Any) -> float:
    """An axes' drawing cost in the units above (a model; it only splits the work)."""
    if not ax.axison:
        return 0.0
    logs = sum(scale == "log" for scale in (ax.get_xscale(), ax.get_yscale()))
    return 1.0 + LOG_AXIS_UNITS * logs + sum(len(line.get_xdata()) for line in ax.get_lines()) / POINTS_PER_UNIT


def split_axes(axes: list) -> tuple[list, list]:
    """The visible axes in two halves of about equal cost, greedily in order of cost (ties by position),
    the parent's half counting the PNG's encoding too: (the child's, the parent's)."""
    shown = [ax for ax in axes if ax.get_visible()]
    order = sorted(range(len(shown)), key=lambda i: (-draw_cost(shown[i]), i))
    halves: tuple[list, list] = ([], [])
    cost = [0.0, ENCODE_UNITS]
    for i in order:
        side = 0 if cost[0] <= cost[1] else 1
        halves[side].append(shown[i])
        cost[side] += draw_cost(shown[i])
    return halves


def _rgba(fig: Any, dpi: float) -> bytes:
    """The figure's raw RGBA pixels, drawn as ``savefig`` draws them."""
    buf = io.BytesIO()
    fig.savefig(buf, format="rgba", dpi=dpi)
    return buf.getvalue()


def _png(rgba: np.ndarray, dpi: float) -> bytes:
    """The PNG of an (H, W, 4) uint8 image, encoded as Agg's ``print_png`` encodes a drawn figure."""
    from matplotlib.image import imsave

    buf = io.BytesIO()
    imsave(buf, rgba, format="png", origin="upper", dpi=dpi, metadata=None, pil_kwargs=None)
    return buf.getvalue()


def _shape(fig: Any, dpi: float) -> tuple[int, int]:
    """(H, W) of the figure's Agg canvas at ``dpi`` (Agg truncates the size in pixels)."""
    w_in, h_in = fig.get_size_inches()
    return int(h_in * dpi), int(w_in * dpi)


def figure_png(fig: Any, dpi: float, processes: int = 1) -> bytes:
    """``fig.savefig(format="png", dpi=dpi)``'s bytes; with ``processes=2`` (POSIX, a process of one thread:
    a fork) half the axes are drawn by a child process meanwhile (see the module docstring). The figure's
    artists are unchanged afterwards (the axes hidden for a half are shown again)."""
    # A fork copies only the calling thread: another thread's locks (the allocator's, a library's) could
    # be held forever in the child. With threads about, one drawing here.
    if processes == 1 or not hasattr(os, "fork") or threading.active_count() > 1:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi)
        return buf.getvalue()
    if processes != 2:
        raise ValueError(f"processes = {processes!r}: give 1 or 2")
    child_axes, own_axes = split_axes(fig.axes)
    # The figure's own artists (its title, texts, legends), drawn by the parent; its patch by both.
    figure_artists = [a for a in fig.get_children() if a is not fig.patch and a not in fig.axes and a.get_visible()]
    height, width = _shape(fig, dpi)
    size = height * width * 4
    shared = mmap.mmap(-1, _HEADER.size + size)  # anonymous and shared with the fork
    # Collections walk every object, writing to its header: in a fork, a copy of every page. Neither
    # process collects what exists now (the child, short-lived, collects nothing at all).
    thaw = gc.get_freeze_count() == 0  # (what a caller froze stays frozen)
    gc.freeze()
    pid = os.fork()
    if pid == 0:  # the child: its axes only, into the shared buffer; never returns
        status = 1
        try:
            gc.disable()
            _hide(own_axes + figure_artists)
            pixels = _rgba(fig, dpi)
            if len(pixels) == size:
                shared[_HEADER.size:] = pixels
                shared[:_HEADER.size] = _HEADER.pack(len(pixels))
                status = 0
        finally:
            os._exit(status)
    try:
        with _hidden(child_axes):
            own = _rgba(fig, dpi)
    finally:
        _, wait_status = os.waitpid(pid, 0)
        if thaw:
            gc.unfreeze()
    whole = None
    if os.waitstatus_to_exitcode(wait_status) == 0 and _HEADER.unpack(shared[:_HEADER.size])[0] == size == len(own):
        child = np.frombuffer(shared, np.uint8, size, _HEADER.size).reshape(height, width, 4)
        mine = np.frombuffer(own, np.uint8).reshape(height, width, 4)
        whole = combine(mine, child, _background(fig))
        del child  # the shared buffer's last view: it can close
    if whole is None:  # a pixel drawn by both halves, or the child failed: one drawing, here
        whole = np.frombuffer(_rgba(fig, dpi), np.uint8).reshape(height, width, 4)
    png = _png(whole, dpi)
    shared.close()
    return png


def combine(a: np.ndarray, b: np.ndarray, background: np.ndarray) -> np.ndarray | None:
    """Two drawings of disjoint parts of one figure, each over the same ``background`` (RGBA, (4,)), as one:
    each pixel from the drawing that changed it. None when some pixel was changed by both (then the
    two cannot stand for one drawing)."""
    # A pixel's four bytes as one word: one comparison per pixel.
    a32, b32 = (np.ascontiguousarray(x).view(np.uint32)[..., 0] for x in (a, b))
    bg32 = np.ascontiguousarray(background, np.uint8).view(np.uint32)[0]
    drawn_b = b32 != bg32
    if np.logical_and(a32 != bg32, drawn_b).any():
        return None
    return np.where(drawn_b, b32, a32)[..., None].view(np.uint8)


def _background(fig: Any) -> np.ndarray:
    """The RGBA uint8 the figure's patch fills an Agg canvas with (``savefig``'s face colour 'auto')."""
    from matplotlib.colors import to_rgba

    return np.array([round(c * 255) for c in to_rgba(fig.get_facecolor())], np.uint8)


def _hide(artists: list) -> None:
    for artist in artists:
        artist.set_visible(False)


class _hidden:
    """Artists hidden for the block, shown again after it."""

    def __init__(self, artists: list) -> None:
        self.artists = artists

    def __enter__(self) -> None:
        _hide(self.artists)

    def __exit__(self, *exc: Any) -> None:
        for artist in self.artists:
            artist.set_visible(True)
