"""The HTML report of ``landbench sweep``: ``DIR/report.html``, beside ``sweep.json``.

Input: the document :func:`bench.campaign.sweep.summarise` returns (per-point
statistics, the Pareto front, Sobol indices). Nothing is computed here that
changes a figure of ``sweep.json``; this module only lays it out, with the
machinery of the compare report (:mod:`bench.report.compare_html`: jinja2,
plotly.js inline, SVG figures that render without a GPU or a network). It holds:

* the points table (design values, success rate with its Wilson interval,
  fuel mean/p95 and ratio to G-FOLD, p95 touchdown speeds and miss, wall time),
  Pareto points highlighted, points failing ``--require`` greyed;
* the Pareto front (fuel, p95 touchdown speed, p95 miss) as the three 2-D
  projections;
* a scatter matrix of every factor against every outcome;
* the Sobol indices with their intervals, for a Sobol design.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from bench.campaign.sweep import PARETO_OBJECTIVES, format_point_cell
from bench.report.compare_html import _environment
from bench.report.io import atomic_write_text

REPORT_HTML = "report.html"
TEMPLATE = "sweep.html.j2"
OUTCOMES = (("success_rate", "success rate"), ("fuel_mean_kg", "mean fuel [kg]"),
            ("td_speed_p95_mps", "p95 touchdown speed [m/s]"), ("miss_p95_m", "p95 miss [m]"))
COLUMNS = ("success_rate", "success_wilson", "fuel_mean_kg", "fuel_p95_kg", "fuel_ratio_gfold_mean",
           "fuel_ratio_gfold_p95", "td_v_vertical_p95_mps", "td_v_horizontal_p95_mps", "td_speed_p95_mps",
           "miss_p95_m", "wall_time_s", "case_wall_time_mean_s", "pareto")


def _cell(p: Mapping[str, Any], c: str) -> str:
    return format_point_cell(p, c, markdown=False)


def _label(p: Mapping[str, Any], factors: list[str]) -> str:
    return f"point {p['point']}: " + ", ".join(f"{f}={p[f]}" for f in factors)


def _fig_html(fig, div_id: str) -> str:
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id,
                       config={"displaylogo": False, "displayModeBar": False, "responsive": False})


def pareto_plots(doc: Mapping[str, Any]) -> list[str]:
    """The front's three 2-D projections: front points, other points meeting the requirements, the rest."""
    import plotly.graph_objects as go

    factors = doc["design"]["factors"]
    objs = doc["pareto_objectives"]
    names = dict(OUTCOMES)
    groups = (("Pareto front", "#1b7a1b", lambda p: p["pareto"]),
              ("meets require", "#1f5fa8", lambda p: p["meets_require"] and not p["pareto"]),
              ("fails require", "#bbbbbb", lambda p: not p["meets_require"]))
    out = []
    for n, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        fig = go.Figure()
        for name, color, pick in groups:
            pts = [p for p in doc["points"] if pick(p) and p[objs[a]] is not None and p[objs[b]] is not None]
            fig.add_trace(go.Scatter(x=[p[objs[a]] for p in pts], y=[p[objs[b]] for p in pts], mode="markers",
                                     name=name, text=[_label(p, factors) for p in pts],
                                     marker={"size": 9, "color": color},
                                     hovertemplate="%{text}<br>%{x:.4g}, %{y:.4g}<extra></extra>"))
        fig.update_layout(xaxis={"title": {"text": names.get(objs[a], objs[a])}},
                          yaxis={"title": {"text": names.get(objs[b], objs[b])}},
                          width=430, height=380, margin={"l": 60, "r": 10, "t": 30, "b": 50},
                          template="plotly_white", legend={"font": {"size": 10}}, showlegend=n == 0)
        out.append(_fig_html(fig, f"pareto-{n}"))
    return out


def scatter_matrix(doc: Mapping[str, Any]) -> str:
    """Every factor (columns) against every outcome (rows), one SVG subplot each."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    factors = doc["design"]["factors"]
    rows = len(OUTCOMES)
    fig = make_subplots(rows=rows, cols=len(factors), shared_xaxes="columns", horizontal_spacing=0.06,
                        vertical_spacing=0.04)
    for j, f in enumerate(factors):
        for i, (key, name) in enumerate(OUTCOMES):
            pts = [p for p in doc["points"] if p[key] is not None]
            fig.add_trace(go.Scatter(x=[p[f] for p in pts], y=[p[key] for p in pts], mode="markers",
                                     text=[_label(p, factors) for p in pts], showlegend=False,
                                     marker={"size": 7, "color": ["#1b7a1b" if p["pareto"] else "#1f5fa8" for p in pts],
                                             "opacity": 0.8},
                                     hovertemplate="%{text}<br>" + name + " %{y:.4g}<extra></extra>"),
                          row=i + 1, col=j + 1)
            if j == 0:
                fig.update_yaxes(title_text=name, title_font={"size": 10}, row=i + 1, col=1)
            if i == rows - 1:
                fig.update_xaxes(title_text=f, title_font={"size": 10}, row=i + 1, col=j + 1)
    fig.update_layout(width=max(420, 300 * len(factors)), height=170 * rows + 80, template="plotly_white",
                      margin={"l": 70, "r": 10, "t": 20, "b": 60})
    return _fig_html(fig, "scatter-matrix")


def sobol_plots(doc: Mapping[str, Any]) -> list[str]:
    """One bar chart per metric: S1 and ST per factor with their 95 % intervals."""
    import plotly.graph_objects as go

    out = []
    for n, (metric, per) in enumerate((doc.get("sobol") or {}).items()):
        factors = list(per)
        if any(per[f]["S1"] is None for f in factors):
            continue
        fig = go.Figure()
        for key, color in (("S1", "#1f5fa8"), ("ST", "#e07b00")):
            fig.add_trace(go.Bar(x=factors, y=[per[f][key] for f in factors], name=key, marker={"color": color},
                                 error_y={"type": "data", "array": [per[f][f"{key}_conf"] for f in factors]}))
        fig.update_layout(title={"text": metric, "font": {"size": 13}}, barmode="group", width=430, height=340,
                          template="plotly_white", margin={"l": 50, "r": 10, "t": 40, "b": 80})
        out.append(_fig_html(fig, f"sobol-{n}"))
    return out


def render_sweep_html(doc: Mapping[str, Any]) -> str:
    """The sweep's report as one self-contained HTML page."""
    from plotly.offline import get_plotlyjs

    factors = doc["design"]["factors"]
    front = [p for p in doc["points"] if p["pareto"]]
    front_text = "; ".join(_label(p, factors) for p in front)
    if not front:  # say why: none meets the requirements, or those that do lack an objective (no touchdown)
        ok = [p for p in doc["points"] if p["meets_require"]]
        front_text = ("no point meets the requirements" if not ok else
                      f"none: the {len(ok)} point{'s' if len(ok) > 1 else ''} meeting the requirements lack a value "
                      f"of the objectives ({', '.join(PARETO_OBJECTIVES)}; no touchdown in their cases)")
    return _environment().get_template(TEMPLATE).render(
        doc=doc, columns=[*factors, *COLUMNS], cell=_cell, n_ok=sum(p["meets_require"] for p in doc["points"]),
        front_text=front_text, pareto_plots=pareto_plots(doc), matrix=scatter_matrix(doc),
        sobol_plots=sobol_plots(doc), plotly_js=get_plotlyjs())


def write_sweep_report(doc: Mapping[str, Any], out: str | Path) -> Path:
    """Write ``out/report.html`` atomically; returns its path."""
    return atomic_write_text(Path(out) / REPORT_HTML, render_sweep_html(doc))
