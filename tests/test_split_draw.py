"""A figure drawn by two processes (bench/report/split_draw.py): the bytes of one drawing, whatever happens."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest
from matplotlib.figure import Figure

import bench.report.split_draw as sd
from bench.report.report import write_plots
from tests.test_report import descent_telemetry, terrain  # noqa: F401 - the fixture


@pytest.fixture
def combined(monkeypatch):
    """What each call of ``combine`` returned (None: the halves overlapped).

    ``figure_png`` forks only in a process of one thread, so these tests need this one to have no other
    (a thread another test left running would send every drawing down the one-process path)."""
    others = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
    assert not others, f"threads left running by earlier tests: {others}"
    out = []
    real = sd.combine

    def spy(*args):
        out.append(real(*args))
        return out[-1]

    monkeypatch.setattr(sd, "combine", spy)
    return out


def _figure(overlap: bool = False) -> Figure:
    """Four panels of lines, a log axis, an image, legends and a title (two panels on top of each other)."""
    fig = Figure(figsize=(6.0, 4.0))
    fig.subplots_adjust(hspace=0.5, wspace=0.4)  # room for each panel's labels and title
    axes = list(fig.subplots(2, 2).ravel())
    if overlap:
        axes[3].set_position([0.3, 0.3, 0.5, 0.5])  # over its neighbours
    t = np.linspace(0.0, 10.0, 3000)
    axes[0].plot(t, np.sin(t), label="sin")
    axes[0].legend(loc="best")
    axes[1].semilogy(t, np.exp(t / 3), label="exp")
    axes[2].imshow(np.arange(64.0).reshape(8, 8))
    axes[3].plot(t, np.cos(3 * t), ls="--")
    axes[3].set_title("cos")
    fig.suptitle("two halves")
    return fig


def test_the_run_plots_from_two_processes_are_the_bytes_of_one(tmp_path, terrain, combined):  # noqa: F811
    for nav in (False, True):
        tel = descent_telemetry(nav=nav)
        kwargs = {"title": "synthetic descent", "criteria": {"tilt_max_deg": 10.0}, "touchdown": {"t_s": 9.9}}
        one = write_plots(tel, terrain, tmp_path / "one.png", **kwargs).read_bytes()
        two = write_plots(tel, terrain, tmp_path / "two.png", processes=2, **kwargs).read_bytes()
        assert two == one
    assert len(combined) == 2 and all(c is not None for c in combined)  # both were drawn in halves


def test_a_figure_is_the_same_and_unchanged_after_two_processes_drew_it(combined):
    fig = _figure()
    one = sd.figure_png(fig, 80)
    visible = [a.get_visible() for a in fig.get_children()]
    assert sd.figure_png(fig, 80, processes=2) == one
    assert combined[-1] is not None
    assert [a.get_visible() for a in fig.get_children()] == visible  # every axes and the title shown again
    assert sd.figure_png(fig, 80) == one


def test_overlapping_axes_are_drawn_as_one(combined):
    fig = _figure(overlap=True)
    assert sd.figure_png(fig, 80, processes=2) == sd.figure_png(fig, 80)
    assert combined == [None]  # the halves shared pixels: drawn again whole


def test_a_child_that_fails_leaves_the_drawing_to_the_parent(monkeypatch, combined):
    parent = os.getpid()
    real = sd._rgba

    def fails_in_the_child(fig, dpi):
        if os.getpid() != parent:
            raise MemoryError("the child could not draw")
        return real(fig, dpi)

    fig = _figure()
    one = sd.figure_png(fig, 80)
    monkeypatch.setattr(sd, "_rgba", fails_in_the_child)
    assert sd.figure_png(fig, 80, processes=2) == one
    assert combined == []  # nothing to combine


def test_with_other_threads_about_it_does_not_fork(monkeypatch, combined):
    monkeypatch.setattr(threading, "active_count", lambda: 2)
    fig = _figure()
    assert sd.figure_png(fig, 80, processes=2) == sd.figure_png(fig, 80)
    assert combined == []


def test_combine_against_an_explicit_loop():
    rng = np.random.default_rng(7)
    bg = np.array([255, 255, 255, 255], np.uint8)
    a = np.broadcast_to(bg, (6, 9, 4)).copy()
    b = a.copy()
    owner = rng.integers(0, 3, (6, 9))  # 0: neither half drew the pixel, 1: a, 2: b
    a[owner == 1] = rng.integers(0, 255, ((owner == 1).sum(), 4))
    b[owner == 2] = rng.integers(0, 255, ((owner == 2).sum(), 4))
    want = np.empty_like(a)
    for i in range(6):
        for j in range(9):
            want[i, j] = b[i, j] if (b[i, j] != bg).any() else a[i, j]
    np.testing.assert_array_equal(sd.combine(a, b, bg), want)
    b[owner == 1] = 0  # b now also draws where a did
    assert sd.combine(a, b, bg) is None


def test_the_halves_split_the_cost_and_cover_every_axes():
    fig = Figure()
    axes = list(fig.subplots(3, 3).ravel())
    t = np.arange(26000.0)
    axes[0].semilogy(t, t + 1)  # 1 + 2.6 + 1 units
    for ax in axes[1:4]:
        ax.plot(t, t)  # 2 units each
    axes[8].set_axis_off()  # nothing drawn: no cost
    axes[7].set_visible(False)  # not drawn at all
    assert sd.draw_cost(axes[0]) == pytest.approx(1 + sd.LOG_AXIS_UNITS + 1)
    assert sd.draw_cost(axes[1]) == pytest.approx(2.0)
    assert sd.draw_cost(axes[4]) == 1.0 and sd.draw_cost(axes[8]) == 0.0
    child, parent = sd.split_axes(axes)
    assert sorted(map(id, child + parent)) == sorted(id(ax) for ax in axes if ax is not axes[7])
    cost = [sum(map(sd.draw_cost, half)) for half in (child, parent)]
    # Greedy by cost: the halves (the parent's with the encoding) differ by at most the cheapest axes'.
    assert abs(cost[0] - (cost[1] + sd.ENCODE_UNITS)) <= 1.0
