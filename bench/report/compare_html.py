"""The HTML report of ``landbench compare``: ``DIR/report.html``, beside ``compare.json``.

Input: the document :func:`bench.evaluation.compare.compare_inputs` returns
(or ``compare.json`` read back): it holds the statistics and, under
``values`` (and ``frames.values`` for replays), the paired values themselves.
Nothing is computed here that changes a figure of ``compare.json``; this
module only lays it out.

Output: one self-contained HTML file (:func:`render_compare_html`, written
atomically by :func:`write_compare_report`) that opens in a browser with no
network at all: plotly.js is embedded inline (no ``<script src>``, no CDN,
no web font). It holds:

* the verdict line (gates passed or failed), the inputs and the platform notes
  (``platform_notes``: a renderer or MuJoCo version that differs between the sides);
* campaigns: each side's success rate with its Wilson 95 % interval, the
  exact McNemar test, and the plain statement of whether the campaign is large
  enough to resolve the difference (e.g. 95/100 landed: Wilson 88.8-97.8 %);
* the gates and their outcome;
* the flipped cases (landed on one side only) with both replay commands;
* every compared metric: each side's mean, the paired difference (mean,
  median, bootstrap 95 % interval of the mean), Wilcoxon and Holm p-values;
* paired scatter plots, BASE on x and CAND on y per case (per sequence for
  replays), with the y = x line: a point off the line is a case that changed;
* replays: the per-frame comparison (numeric columns, and boolean columns
  with each side's rate, Wilson interval and exact McNemar), with per-frame
  scatter plots.

jinja2 lays out the page (``templates/compare.html.j2``, autoescaped), plotly
draws the figures (SVG scatter, not WebGL: it renders in a headless browser
without a GPU).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from bench.report.io import atomic_write_text

REPORT_HTML = "report.html"
TEMPLATE = "compare.html.j2"
TEMPLATES = Path(__file__).with_name("templates")
MAX_CASE_SCATTERS = 24  # scatter plots of per-case metrics; every metric is in the table
MAX_FRAME_SCATTERS = 12
ALPHA = 0.05  # as compare.ALPHA (a significance highlight only)


# ------------------------------------------------------------------ formatting
def fmt_num(value: Any, spec: str = ".4g") -> str:
    """A number for a table cell; None (no value) as an em dash."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, bool):
        return str(value)
    return format(value, spec)


def fmt_p(value: Any) -> str:
    """A p-value: three decimals, '<0.001' below that, an em dash when there is none."""
    if value is None:
        return "—"
    return "<0.001" if value < 0.001 else f"{value:.3f}"


def fmt_pct(value: Any, digits: int = 1) -> str:
    """A fraction in [0, 1] as a percentage."""
    return "—" if value is None else f"{100.0 * value:.{digits}f} %"


def fmt_interval(pair: Sequence[float] | None, spec: str = ".3g", pct: bool = False) -> str:
    """A (low, high) interval as '[low, high]' (as percentages with ``pct``)."""
    if pair is None:
        return "—"
    lo, hi = pair
    if pct:
        return f"{100.0 * lo:.1f}–{100.0 * hi:.1f} %"
    return f"[{fmt_num(lo, spec)}, {fmt_num(hi, spec)}]"


# ------------------------------------------------------------------ statements
def success_statement(success: Mapping[str, Any], n_cases: int) -> str:
    """The plain sentence on the success rates: resolved, or too few cases to tell (with both intervals)."""
    b, c = success["base"], success["cand"]

    def side(name: str, s: Mapping[str, Any]) -> str:
        return (f"{name} landed {s['landed']}/{s['n']} ({fmt_pct(s['rate'])}, Wilson 95 % interval "
                f"{fmt_interval(s['wilson95'], pct=True)})")

    p = success["mcnemar"]["pvalue"]
    both = f"{side('BASE', b)}; {side('CAND', c)}."
    if success["resolved"]:
        return (f"{both} The difference, {success['difference_pp']:+.1f} percentage points, is resolved: "
                f"the exact McNemar test on the paired cases gives p = {p:.3g} < {ALPHA:g}.")
    apart = "the intervals overlap and " if success["intervals_overlap"] else \
        "the intervals do not overlap, but the cases are paired and "
    return (f"{both} {n_cases} cases are too few to resolve a difference in success rate: {apart}"
            f"the exact McNemar test gives p = {p:.3g} ≥ {ALPHA:g} (observed difference "
            f"{success['difference_pp']:+.1f} percentage points). Run more cases to tell.")


# ------------------------------------------------------------------ figures
def _finite_pairs(base: Sequence[Any], cand: Sequence[Any], labels: Sequence[str]) -> tuple[list, list, list]:
    xs, ys, ts = [], [], []
    for x, y, t in zip(base, cand, labels):
        if x is None or y is None:
            continue
        x, y = float(x), float(y)
        if math.isfinite(x) and math.isfinite(y):
            xs.append(x)
            ys.append(y)
            ts.append(t)
    return xs, ys, ts


def scatter_html(name: str, base: Sequence[Any], cand: Sequence[Any], labels: Sequence[str], div_id: str,
                 unit_label: str = "case") -> str | None:
    """One paired scatter plot (BASE on x, CAND on y, the y = x line) as an HTML fragment; None with no pair.

    The fragment is a ``<div>`` and the script that calls ``Plotly.newPlot``;
    plotly.js itself is loaded once by the page (inline).
    """
    import plotly.graph_objects as go

    xs, ys, ts = _finite_pairs(base, cand, labels)
    if not xs:
        return None
    lo, hi = min(min(xs), min(ys)), max(max(xs), max(ys))
    pad = 0.05 * (hi - lo) if hi > lo else (abs(hi) * 0.05 or 1.0)
    lo, hi = lo - pad, hi + pad
    changed = sum(x != y for x, y in zip(xs, ys))
    fig = go.Figure()
    fig.add_trace(go.Scatter(x=[lo, hi], y=[lo, hi], mode="lines", name="y = x (no change)",
                             line={"color": "#888", "dash": "dash", "width": 1}, hoverinfo="skip"))
    fig.add_trace(go.Scatter(x=xs, y=ys, mode="markers", name=f"{unit_label}s", text=ts,
                             marker={"size": 7, "color": "#1f5fa8", "opacity": 0.75},
                             hovertemplate="%{text}<br>BASE %{x:.5g}<br>CAND %{y:.5g}<extra></extra>"))
    fig.update_layout(
        title={"text": f"{name}<br><sup>{len(xs)} paired {unit_label}s, {changed} off the line</sup>",
               "font": {"size": 13}},
        xaxis={"title": {"text": "BASE"}, "range": [lo, hi]},
        yaxis={"title": {"text": "CAND"}, "range": [lo, hi], "scaleanchor": "x", "scaleratio": 1},
        width=380, height=400, margin={"l": 60, "r": 15, "t": 60, "b": 50}, showlegend=False,
        template="plotly_white")
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id,
                       config={"displaylogo": False, "displayModeBar": False, "responsive": False})


def _plotted_metrics(doc: Mapping[str, Any]) -> list[str]:
    """The per-case metrics that get a scatter plot: gated, headline, significant after Holm, then those that
    changed, at most ``MAX_CASE_SCATTERS``."""
    from bench.evaluation.compare import HEADLINE_METRICS, REPLAY_HEADLINE_METRICS

    metrics = doc["metrics"]
    headline = REPLAY_HEADLINE_METRICS if doc.get("kind") == "replay" else HEADLINE_METRICS
    order: list[str] = []
    groups = ([g["metric"] for g in doc["gates"]], [k for k in headline],
              [k for k, m in metrics.items() if m["holm_p"] is not None and m["holm_p"] < ALPHA],
              [k for k, m in metrics.items() if not m["identical"]], list(metrics))
    for group in groups:
        order += [k for k in group if k in metrics and k not in order]
    return order[:MAX_CASE_SCATTERS]


def _case_scatters(doc: Mapping[str, Any]) -> list[dict[str, str]]:
    values = doc.get("values") or {}
    per = values.get("metrics") or {}
    replay = doc.get("kind") == "replay"
    unit = "sequence" if replay else "case"
    labels = [f"{unit} {c} (seed {s})" for c, s in zip(values.get("case", []), values.get("seed", []))]
    out = []
    for i, k in enumerate(_plotted_metrics(doc)):
        if k not in per:
            continue
        html = scatter_html(k, per[k]["base"], per[k]["cand"], labels, f"scatter-case-{i}", unit)
        if html is not None:
            out.append({"name": k, "html": html})
    return out


def _frame_scatters(frames: Mapping[str, Any]) -> list[dict[str, str]]:
    values = frames.get("values") or {}
    per = values.get("metrics") or {}
    labels = [f"seed {s}, frame {k}" for s, k in zip(values.get("seed", []), values.get("frame", []))]
    names = sorted(per, key=lambda k: (frames["metrics"][k]["identical"], list(per).index(k)))
    out = []
    for i, k in enumerate(names[:MAX_FRAME_SCATTERS]):
        html = scatter_html(f"{k} (per frame)", per[k]["base"], per[k]["cand"], labels, f"scatter-frame-{i}",
                            "frame")
        if html is not None:
            out.append({"name": k, "html": html})
    return out


# ------------------------------------------------------------------ page
def _environment():
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATES)),
                             autoescape=jinja2.select_autoescape(["html", "j2"]),
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    env.filters.update(num=fmt_num, p=fmt_p, pct=fmt_pct, interval=fmt_interval)
    return env


def render_compare_html(doc: Mapping[str, Any]) -> str:
    """The report of one comparison as a self-contained HTML page (plotly.js inline; no network needed)."""
    from plotly.offline import get_plotlyjs

    metrics = doc["metrics"]
    success = doc.get("success")
    frames = doc.get("frames")
    plotted = _case_scatters(doc)
    frame_plots = _frame_scatters(frames) if frames else []
    failed = [g["spec"] for g in doc["gates"] if not g["passed"]]
    if failed:
        verdict = f"FAILED gates: {', '.join(failed)}"
    elif doc["gates"]:
        verdict = f"all {len(doc['gates'])} gates passed"
    else:
        verdict = "no gates given (--gate SPEC)"
    return _environment().get_template(TEMPLATE).render(
        doc=doc, replay=doc.get("kind") == "replay", success=success,
        success_statement=success_statement(success, doc["n_cases"]) if success else None,
        metrics=metrics, alpha=ALPHA, frames=frames, case_plots=plotted, frame_plots=frame_plots,
        n_plotted=len(plotted), verdict=verdict, failed=bool(failed), plotly_js=get_plotlyjs())


def write_compare_report(doc: Mapping[str, Any], out: str | Path, html: str | None = None) -> Path:
    """Write ``out/report.html`` atomically (``html``: already rendered, else rendered here); returns its path."""
    return atomic_write_text(Path(out) / REPORT_HTML, render_compare_html(doc) if html is None else html)
