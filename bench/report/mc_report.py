"""The report of a Monte Carlo campaign (``landbench mc``): one PNG and a text table.

Pure: campaign rows in, a figure and text out; no simulator (``mujoco`` is
never imported here, and matplotlib only when a figure is drawn).

A row is one case (``bench.campaign.mc``): ``case``, ``seed``, ``outcome`` (landed,
hard_landing, tipped_over, slope_exceeded, fuel_exhausted, timeout, diverged, or ``error``
when the case raised, crashed or timed out in the runner), ``landed``,
``touchdown_t_s``, ``touchdown_v_vertical_mps``, ``touchdown_v_horizontal_mps``,
``touchdown_tilt_deg``, ``touchdown_miss_distance_m``, ``touchdown_x_m``,
``touchdown_y_m`` (body origin at touchdown in the landing frame L, x east,
y north), ``fuel_used_kg``, ``wall_time_s`` and ``error``. Any of the numbers
may be missing, None or NaN (no touchdown, or a failed case).

Outputs:
    * :func:`write_campaign_report`: ``report.png`` (``FIGURE_SIZE_IN`` at
      ``FIGURE_DPI``), written atomically (``bench.report.io``);
    * :func:`campaign_table`: the terminal summary.

Statistics: :func:`wilson_interval` (success rate) and :func:`error_ellipse`
(touchdown dispersion).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench.campaign.rows import column, row_float
from bench.evaluation.consistency import campaign_consistency
from bench.report.io import save_figure
from bench.report.report import check_criteria, draw_hillshade

if TYPE_CHECKING:  # typing only
    from matplotlib.figure import Figure

    from models.terrain import Terrain

OUTCOMES = ("landed", "hard_landing", "tipped_over", "slope_exceeded", "fuel_exhausted", "safe_abort", "off_terrain",
            "timeout", "diverged", "error")
OUTCOME_COLORS = {
    "landed": "tab:green", "hard_landing": "tab:orange", "tipped_over": "tab:red",
    "slope_exceeded": "tab:olive", "safe_abort": "tab:cyan",
    "fuel_exhausted": "tab:purple", "off_terrain": "tab:blue", "timeout": "tab:brown", "diverged": "tab:pink", "error": "black",
}
OTHER_COLOR = "tab:gray"  # outcomes not in OUTCOMES
CONFIDENCE = 0.95
ELLIPSE_SIGMA = 3.0
ELLIPSE_MIN_POINTS = 3  # fewer touchdowns: no ellipse is drawn
FIGURE_SIZE_IN = (14.0, 11.5)
# Fixed margins and gaps (figure fractions; gaps as fractions of the mean panel size), not the constrained
# layout, which laid the whole figure out once more before drawing it (about half of the report's time).
REPORT_GRID = {"left": 0.05, "right": 0.985, "bottom": 0.045, "top": 0.94, "wspace": 0.22, "hspace": 0.42}
FIGURE_DPI = 100
SUN_ELEVATION_DEG = 30.0
SUN_AZIMUTH_DEG = 120.0
MAP_MARGIN_FRAC = 0.15  # margin around the touchdowns, as a fraction of their larger spread
MAP_MIN_HALF_M = 10.0  # smallest half-width of the map [m]
HIST_MAX_BINS = 30
FAILED_LIST_MAX = 50  # failed cases listed in the table; the rest are counted
ERROR_TEXT_MAX = 100  # characters of a case's error shown in the table
MISSING = "—"

# Touchdown metrics: (row key, label, unit, criteria key or None, format).
METRICS = (
    ("touchdown_v_vertical_mps", "vertical speed", "m/s", "v_vertical_max_mps", ".2f"),
    ("touchdown_v_horizontal_mps", "horizontal speed", "m/s", "v_horizontal_max_mps", ".2f"),
    ("touchdown_tilt_deg", "tilt", "deg", "tilt_max_deg", ".1f"),
    ("touchdown_miss_distance_m", "miss distance", "m", None, ".2f"),
)


# ================================================================ statistics
def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion.

    Args:
        successes: Number of successes, 0 <= successes <= n.
        n: Number of trials, >= 0.
        confidence: Two-sided confidence level in (0, 1).

    Returns:
        (low, high) in [0, 1]; (0.0, 1.0) when n == 0. The bounds are exact
        at the edges: low == 0 when successes == 0, high == 1 when
        successes == n.

    Raises:
        ValueError: Negative or non-integer counts, successes > n, or a
            confidence outside (0, 1).
    """
    from scipy.stats import norm

    for name, value in (("successes", successes), ("n", n)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name}={value!r} must be a non-negative integer")
    if successes > n:
        raise ValueError(f"successes={successes} must be <= n={n}")
    if not 0.0 < float(confidence) < 1.0:
        raise ValueError(f"confidence={confidence!r} must be in (0, 1)")
    if n == 0:
        return 0.0, 1.0
    z = float(norm.ppf(0.5 + float(confidence) / 2.0))
    p = successes / n
    z2n = z * z / n
    centre = (p + z2n / 2.0) / (1.0 + z2n)
    half = z / (1.0 + z2n) * math.sqrt(p * (1.0 - p) / n + z2n / (4.0 * n))
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


def error_ellipse(xy: np.ndarray, n_sigma: float = ELLIPSE_SIGMA) -> tuple[np.ndarray, float, float, float]:
    """The n-sigma ellipse of 2-D points, from their sample covariance.

    Args:
        xy: (N, 2) points [m]; rows with a non-finite value are dropped.
        n_sigma: Scale of the ellipse in standard deviations.

    Returns:
        (centre (2,), width, height, angle_deg): the mean; the full major
        and minor axes, ``2 * n_sigma * sqrt(eigenvalue)`` of the sample
        covariance (``ddof=1``), width >= height; and the angle of the major
        axis from +x toward +y [deg], in (-90, 90] (matplotlib's
        ``Ellipse(centre, width, height, angle=angle_deg)``).

    Raises:
        ValueError: ``xy`` is not (N, 2), fewer than 2 finite points, or
            ``n_sigma`` is not a positive number.
    """
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"xy has shape {pts.shape}; expected (N, 2)")
    if not (math.isfinite(n_sigma) and n_sigma > 0):
        raise ValueError(f"n_sigma={n_sigma!r} must be a positive number")
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        raise ValueError(f"error_ellipse needs at least 2 finite points, got {len(pts)}")
    centre = pts.mean(axis=0)
    cov = np.cov(pts, rowvar=False, ddof=1)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    evals = np.clip(evals, 0.0, None)
    major = evecs[:, 1]
    angle = math.degrees(math.atan2(major[1], major[0]))
    if angle <= -90.0:
        angle += 180.0
    elif angle > 90.0:
        angle -= 180.0
    width = 2.0 * n_sigma * math.sqrt(evals[1])
    height = 2.0 * n_sigma * math.sqrt(evals[0])
    return centre, width, height, angle


# ===================================================================== rows
def _check_rows(rows: Any) -> list[Mapping[str, Any]]:
    if isinstance(rows, (str, bytes, Mapping)) or not isinstance(rows, Sequence):
        raise ValueError(f"rows must be a list of dicts (one per case), got {type(rows).__name__}")
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise ValueError(f"rows[{i}] must be a dict, got {type(row).__name__}")
    return list(rows)


def _landed(row: Mapping[str, Any]) -> bool:
    """Success: the row's ``landed`` flag (its outcome is 'landed' when the flag is missing)."""
    flag = row.get("landed")
    if flag is None:
        return str(row.get("outcome")) == "landed"
    return bool(flag)


def _outcome(row: Mapping[str, Any]) -> str:
    value = row.get("outcome")
    return "unknown" if value is None else str(value)


def _touched_down(rows: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """(N,) bool: landed, or a finite touchdown time."""
    t = column(rows, "touchdown_t_s")
    return np.array([_landed(r) for r in rows], dtype=bool) | np.isfinite(t)


def outcome_counts(rows: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """Cases per outcome: the known outcomes that occur in ``OUTCOMES`` order, then any others by name."""
    counts: dict[str, int] = {}
    for row in rows:
        name = _outcome(row)
        counts[name] = counts.get(name, 0) + 1
    known = [o for o in OUTCOMES if o in counts]
    other = sorted(o for o in counts if o not in OUTCOMES)
    return {o: counts[o] for o in known + other}


def _wall_times(rows: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """Wall time of each case [s]: the runner's ``case_wall_time_s`` when present, else ``wall_time_s``."""
    case = column(rows, "case_wall_time_s")
    run = column(rows, "wall_time_s")
    return np.where(np.isfinite(case), case, run)


def _one_line(text: Any, limit: int = ERROR_TEXT_MAX) -> str:
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    line = lines[0] if lines else ""
    if len(lines) > 1:
        line += " …"
    if len(line) > limit:
        line = line[: limit - 1].rstrip() + "…"
    return line


# ==================================================================== table
def _fmt(value: float, spec: str, unit: str = "") -> str:
    if not math.isfinite(value):
        return MISSING
    return f"{value:{spec}}{' ' + unit if unit else ''}"


def _stats(values: np.ndarray) -> tuple[int, float, float, float]:
    """(count, mean, 95th percentile, max) of the finite values; NaN when there are none."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0, math.nan, math.nan, math.nan
    return int(v.size), float(v.mean()), float(np.percentile(v, 95)), float(v.max())


def campaign_table(rows: Sequence[Mapping[str, Any]], criteria: Mapping[str, Any] | None = None) -> str:
    """A plain-text summary of a campaign, for the terminal.

    Args:
        rows: One dict per case (see the module docstring).
        criteria: Landing limits (``v_vertical_max_mps``,
            ``v_horizontal_max_mps``, ``tilt_max_deg``), shown next to the
            statistics with the number of touchdowns over each limit.

    Returns:
        Lines joined with ``\\n`` (no trailing newline): number of cases,
        outcome counts, success rate with its Wilson 95 % interval, mean /
        p95 / max of the touchdown speeds, tilt and miss distance over the
        cases that landed or touched down, mean wall time per case, the
        workers' peak memory (``case_peak_rss_mb``) where recorded, and the
        failed cases (outcome, then the first line of their error,
        truncated; at most ``FAILED_LIST_MAX``).

    Raises:
        ValueError: ``rows`` is not a list of dicts, or a criterion is not a number.
    """
    rows = _check_rows(rows)
    limits = check_criteria(criteria)
    n = len(rows)
    ok = sum(_landed(r) for r in rows)
    lines = [f"landbench mc: {n} case{'s' if n != 1 else ''}"]
    counts = outcome_counts(rows)
    if counts:
        width = max(len(k) for k in counts)
        lines.append("outcomes:")
        lines.extend(f"  {k:<{width}}  {c:>6}  {c / n:6.1%}" for k, c in counts.items())
    low, high = wilson_interval(ok, n)
    rate = f"{ok / n:.1%}" if n else MISSING
    lines.append(f"success rate: {ok}/{n} = {rate}  (Wilson {CONFIDENCE:.0%} interval {low:.1%} – {high:.1%})")

    scored = [r for r in rows if isinstance(r.get("hazard_hazard_free"), bool)]
    if scored:  # touchdown footprints judged against the fine truth DEM (hazard scoring)
        free = sum(bool(r["hazard_hazard_free"]) for r in scored)
        h_lo, h_hi = wilson_interval(free, len(scored))
        line = (f"hazard-free touchdowns: {free}/{len(scored)} = {free / len(scored):.1%}  "
                f"(Wilson {CONFIDENCE:.0%} interval {h_lo:.1%} – {h_hi:.1%})")
        no_site = sum(bool(r.get("hazard_scan_no_safe_site")) for r in rows)
        if any("hazard_scan_scanned" in r for r in rows):
            line += f"; no safe site: {no_site}/{n}"
        lines.append(line)

    lines.extend(map_nav_lines(rows))

    td = _touched_down(rows)
    n_td = int(td.sum())
    lines.append(f"touchdown statistics over {n_td} case{'s' if n_td != 1 else ''} that landed or touched down:")
    lines.append(f"  {'':<18}{'mean':>12}{'p95':>12}{'max':>12}" + ("   limit" if limits else ""))
    for key, label, unit, crit_key, spec in METRICS:
        values = column(rows, key)[td]
        _, mean, p95, vmax = _stats(values)
        line = f"  {label:<18}{_fmt(mean, spec, unit):>12}{_fmt(p95, spec, unit):>12}{_fmt(vmax, spec, unit):>12}"
        if crit_key in limits:
            lim = limits[crit_key]
            over = int(np.sum(values[np.isfinite(values)] > lim))
            line += f"   {'≤ ' + _fmt(lim, spec, unit):<14}{over} over"
        lines.append(line.rstrip())
    walls = _wall_times(rows)
    walls = walls[np.isfinite(walls)]
    lines.append(f"wall time per case: mean {_fmt(float(walls.mean()) if walls.size else math.nan, '.2f', 's')}"
                 f" ({walls.size} timed)")
    rss = column(rows, "case_peak_rss_mb")
    rss = rss[np.isfinite(rss)]
    if rss.size:  # rows of older campaigns, and killed cases, have none
        lines.append(f"peak memory per worker: max {rss.max():.0f} MB, mean {rss.mean():.0f} MB")

    failed = [r for r in rows if not _landed(r)]
    if failed:
        lines.append(f"failed cases ({len(failed)}):")
        for r in failed[:FAILED_LIST_MAX]:
            text = f"  case {r.get('case', '?')} (seed {r.get('seed', '?')}): {_outcome(r)}"
            if r.get("error"):
                text += f": {_one_line(r['error'])}"
            lines.append(text)
        if len(failed) > FAILED_LIST_MAX:
            lines.append(f"  … and {len(failed) - FAILED_LIST_MAX} more")
    else:
        lines.append("failed cases: none")
    return "\n".join(lines)


def _three_sigma(dx: np.ndarray, dy: np.ndarray) -> tuple[float, float, int]:
    """3 × the per-axis RMS of 2-D errors (about zero: a bias counts), the largest radial one, and the count."""
    ok = np.isfinite(dx) & np.isfinite(dy)
    if not ok.any():
        return math.nan, math.nan, 0
    rms = math.sqrt(float(np.mean(np.concatenate((dx[ok], dy[ok])) ** 2)))
    return 3.0 * rms, float(np.max(np.hypot(dx[ok], dy[ok]))), int(ok.sum())


def map_nav_lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The campaign's map-relative navigation figures (cases flown with ``nav_map = "on"``).

    Per-axis "3σ" is 3 × the RMS over the cases and both axes, about zero (a bias
    counts against it); "max" the largest radial value. Lines: fixes used and false
    locks (fixes the matcher accepted with an error beyond 5 of their sigmas; Wilson
    interval of their rate per accepted fix and of the cases with one), the
    horizontal navigation error at 50 m in the map frame, the miss against the map
    target, and the absolute miss (against L's origin). No lines without map rows.
    """
    nav = [r for r in rows if row_float(r.get("map_nav_attempts")) >= 0]
    if not nav:
        return []
    attempts = int(np.nansum(column(nav, "map_nav_attempts")))
    updates = int(np.nansum(column(nav, "map_nav_updates")))
    accepted = int(np.nansum(column(nav, "map_nav_fixes_accepted_by_matcher")))
    false = column(nav, "map_nav_false_locks")
    n_false = int(np.nansum(false))
    cases_false = int(np.sum(false > 0))
    f_lo, f_hi = wilson_interval(n_false, accepted)
    c_lo, c_hi = wilson_interval(cases_false, len(nav))
    relocks = column(nav, "map_nav_relocks")  # absent from campaigns written before the re-lock
    relocked = f", {int(np.nansum(relocks))} re-locks" if np.isfinite(relocks).any() else ""
    lines = [f"map navigation over {len(nav)} cases: {updates} fixes used of {attempts} attempts "
             f"({accepted} accepted by the matcher, "
             f"{int(np.nansum(column(nav, 'map_nav_gate_rejected')))} gated out{relocked})",
             f"  false locks: {n_false}/{accepted} fixes (Wilson {CONFIDENCE:.0%} {f_lo:.2%} – {f_hi:.2%}); "
             f"cases with one: {cases_false}/{len(nav)} (Wilson {c_lo:.1%} – {c_hi:.1%}), "
             f"{int(np.nansum(column(nav, 'map_nav_false_locks_used')))} used by the filter"]
    figures = [
        ("nav error at 50 m (map frame)", column(nav, "map_nav_nav_err_map_frame_50m_xy_m_0"),
         column(nav, "map_nav_nav_err_map_frame_50m_xy_m_1")),
        ("miss vs map target", column(nav, "touchdown_x_m") - column(nav, "map_nav_target_xy_L_m_0"),
         column(nav, "touchdown_y_m") - column(nav, "map_nav_target_xy_L_m_1")),
        ("absolute miss", column(nav, "touchdown_x_m"), column(nav, "touchdown_y_m")),
    ]
    for label, dx, dy in figures:
        three, worst, k = _three_sigma(dx, dy)
        lines.append(f"  {label:<30} 3σ per axis {_fmt(three, '.2f', 'm'):>9}, max {_fmt(worst, '.2f', 'm'):>9}"
                     f" ({k} cases)")
    lines.extend(_keyframe_lines(nav))
    return lines


def _keyframe_lines(nav: Sequence[Mapping[str, Any]]) -> list[str]:
    """Keyframe registration below the last map fix: cases with a keyframe, its fixes, their error
    (RMS over the cases' own RMS, weighted by their fixes) and false locks (as for map fixes)."""
    kf_t = column(nav, "map_nav_keyframe_t_s")
    if not np.isfinite(kf_t).any() and not np.nansum(column(nav, "map_nav_keyframe_attempts")):
        return []
    attempts = int(np.nansum(column(nav, "map_nav_keyframe_attempts")))
    used = column(nav, "map_nav_keyframe_updates")
    updates = int(np.nansum(used))
    gated = int(np.nansum(column(nav, "map_nav_keyframe_gate_rejected")))
    refused = int(np.nansum(column(nav, "map_nav_keyframe_refused")))
    rms = column(nav, "map_nav_keyframe_fix_err_rms_m")
    nis = column(nav, "map_nav_keyframe_fix_nis_mean")
    ok = np.isfinite(rms) & (used > 0)
    pooled = float(np.sqrt(np.sum(used[ok] * rms[ok] ** 2) / np.sum(used[ok]))) if ok.any() else math.nan
    ok_nis = np.isfinite(nis) & (used > 0)
    nis_mean = float(np.sum(used[ok_nis] * nis[ok_nis]) / np.sum(used[ok_nis])) if ok_nis.any() else math.nan
    false = int(np.nansum(column(nav, "map_nav_keyframe_false_locks")))
    taken = column(nav, "map_nav_keyframes")  # absent from campaigns written before a keyframe could be taken again
    n_again = int(np.sum(taken > 1))
    again = (f"; {int(np.nansum(np.maximum(taken - 1, 0)))} keyframes taken again in {n_again} "
             f"case{'' if n_again == 1 else 's'}" if np.isfinite(taken).any() else "")
    return [f"  keyframe in {int(np.isfinite(kf_t).sum())}/{len(nav)} cases: {updates} fixes used of {attempts} "
            f"attempts ({refused} refused, {gated} gated out); fix error RMS {_fmt(pooled, '.3f', 'm')}, "
            f"mean NIS {_fmt(nis_mean, '.2f', '')} (2 expected), false locks {false}{again}"]


# =================================================================== figure
def _map_bounds(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Square (xmin, xmax, ymin, ymax) [m] holding the touchdowns, the target and a margin."""
    xs = np.concatenate((x, [0.0]))
    ys = np.concatenate((y, [0.0]))
    cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
    span = max(xs.max() - xs.min(), ys.max() - ys.min())
    half = max(span / 2 + MAP_MARGIN_FRAC * span, MAP_MIN_HALF_M)
    return cx - half, cx + half, cy - half, cy + half


def _draw_map(ax, rows, terrain, sun_elevation_deg: float, sun_azimuth_deg: float) -> None:
    from matplotlib.patches import Ellipse

    x, y = column(rows, "touchdown_x_m"), column(rows, "touchdown_y_m")
    ok = np.isfinite(x) & np.isfinite(y)
    ell = error_ellipse(np.column_stack((x[ok], y[ok])), ELLIPSE_SIGMA) if ok.sum() >= ELLIPSE_MIN_POINTS else None
    bx, by = x[ok], y[ok]
    if ell is not None:  # the crop holds the whole ellipse too (its bounding box)
        (cx, cy), width, height, angle = ell
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        ex, ey = math.hypot(width / 2 * c, height / 2 * s), math.hypot(width / 2 * s, height / 2 * c)
        bx, by = np.concatenate((bx, [cx - ex, cx + ex])), np.concatenate((by, [cy - ey, cy + ey]))
    bounds = _map_bounds(bx, by)
    if terrain is not None:
        draw_hillshade(ax, terrain, bounds, sun_elevation_deg, sun_azimuth_deg)
    else:
        ax.grid(alpha=0.3)
    outcomes = np.array([_outcome(r) for r in rows], dtype=object)
    for name in outcome_counts([r for r, k in zip(rows, ok) if k]):
        sel = ok & (outcomes == name)
        ax.scatter(x[sel], y[sel], s=22, color=OUTCOME_COLORS.get(name, OTHER_COLOR), edgecolors="k",
                   linewidths=0.5, label=f"{name} ({int(sel.sum())})", zorder=3)
    ax.plot(0, 0, marker="+", color="red", ms=16, mew=2.5, ls="none", label="target", zorder=4)
    if ell is not None:
        centre, width, height, angle = ell
        ellipse = Ellipse(tuple(centre), width, height, angle=angle, fill=False, color="cyan", lw=2, zorder=5,
                          label=f"{ELLIPSE_SIGMA:g}σ ellipse ({width:.1f} × {height:.1f} m)")
        ellipse.set_gid("error_ellipse")
        ax.add_patch(ellipse)
    elif not ok.any():
        ax.text(0.5, 0.6, "no touchdowns", transform=ax.transAxes, ha="center", va="center", fontsize=12,
                bbox={"facecolor": "white", "alpha": 0.8})
    ax.set_xlim(bounds[0], bounds[1])
    ax.set_ylim(bounds[2], bounds[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    shade = f"hillshade, sun el {sun_elevation_deg:.0f}° az {sun_azimuth_deg:.0f}°" if terrain is not None else "no terrain"
    ax.set_title(f"touchdown points: {int(ok.sum())} of {len(rows)} ({shade})", y=1.0)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)


def _draw_hist(ax, values: np.ndarray, label: str, unit: str, limit: float | None) -> None:
    v = values[np.isfinite(values)]
    if v.size:
        lo, hi = float(v.min()), float(v.max())
        if limit is not None:
            lo, hi = min(lo, limit), max(hi, limit)
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        bins = int(np.clip(np.ceil(np.sqrt(v.size)) + 1, 5, HIST_MAX_BINS))
        ax.hist(v, bins=np.linspace(lo, hi, bins + 1), color="tab:blue", alpha=0.8, edgecolor="k", lw=0.4)
    else:
        ax.text(0.5, 0.5, "no touchdowns", transform=ax.transAxes, ha="center", va="center")
    if limit is not None:
        ax.axvline(limit, color="red", ls="--", lw=1.5, label=f"limit {limit:g} {unit}")
        over = int(np.sum(v > limit))
        ax.legend(loc="upper right", fontsize=7, title=f"{over} over", title_fontsize=7)
    ax.set_xlabel(f"{label} [{unit}]")
    ax.set_ylabel("cases")
    ax.set_title(f"touchdown {label} ({v.size})", y=1.0)
    ax.grid(alpha=0.3)


def _draw_outcomes(ax, rows) -> None:
    counts = outcome_counts(rows)
    names = list(counts)
    if names:
        bars = ax.bar(range(len(names)), [counts[k] for k in names],
                      color=[OUTCOME_COLORS.get(k, OTHER_COLOR) for k in names], edgecolor="k", lw=0.5)
        ax.bar_label(bars, fontsize=8)
        # Smaller labels when many outcomes share the panel ("fuel\nexhausted" beside "timeout" would touch).
        ax.set_xticks(range(len(names)), [k.replace("_", "\n") for k in names], fontsize=8 if len(names) <= 5 else 6.5)
        ax.set_ylim(0, max(counts.values()) * 1.15)
    else:
        ax.text(0.5, 0.5, "no cases", transform=ax.transAxes, ha="center", va="center")
    ax.set_ylabel("cases")
    ax.set_title("outcomes", y=1.0)
    ax.grid(alpha=0.3, axis="y")


def _draw_rate(ax, rows) -> None:
    n = len(rows)
    ok = sum(_landed(r) for r in rows)
    low, high = wilson_interval(ok, n)
    if n:
        p = ok / n
        ax.errorbar([p], [0], xerr=[[p - low], [high - p]], fmt="o", color="tab:green", ms=9, capsize=8, lw=2)
        text = (f"success rate {ok}/{n} = {p:.1%}   "
                f"Wilson {CONFIDENCE:.0%} interval [{low:.1%}, {high:.1%}]")
    else:
        text = "no cases"
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(-1.0, 1.0)
    ax.set_yticks([])
    ax.xaxis.set_major_formatter(lambda v, _: f"{v:.0%}")
    ax.set_title(text, fontsize=10, y=1.0)
    ax.grid(alpha=0.3, axis="x")


def _draw_consistency(ax, doc: Mapping[str, Any]) -> None:
    """ANEES / dof per error block at each altitude, with each block's 95 % band (bars) and 1 (dotted)."""
    levels = [str(a) for a in doc["altitudes_m"]]
    x = np.arange(len(levels), dtype=float)
    blocks = list(doc["blocks"].items())
    width = 0.8 / max(len(blocks), 1)
    for i, (block, b) in enumerate(blocks):
        dof = b["dof"]
        xi = x - 0.4 + (i + 0.5) * width
        a = np.array([np.nan if v is None else v for v in b["anees"]], float) / dof
        lo = np.array([np.nan if bd is None else bd[0] for bd in b["band"]], float) / dof
        hi = np.array([np.nan if bd is None else bd[1] for bd in b["band"]], float) / dof
        ax.vlines(xi, lo, hi, color=f"C{i}", alpha=0.35, linewidth=6)
        ax.plot(xi, a, "o", color=f"C{i}", label=f"{block} ({dof} dof)")
    ax.axhline(1.0, color="k", linestyle=":", linewidth=1)
    ax.set_xticks(x, [lv if lv == "touchdown" else f"{lv} m" for lv in levels])
    ax.set_xlim(-0.5, len(levels) - 0.5)  # each level's group inside, with or without points (fixed margins)
    ax.set_yscale("log")
    ax.set_ylabel("ANEES / dof")
    nis = doc["nis"]
    text = ", ".join(f"NIS {k} {v['mean'] / v['dof']:.2f}/dof" for k, v in nis.items() if v["n"])
    ax.set_title(f"filter consistency over {doc['n_cases']} cases (bars: 95 % band)" + (f"; {text}" if text else ""), y=1.0)
    ax.legend(loc="upper left", ncol=len(blocks), fontsize="small")


def campaign_figure(
    rows: Sequence[Mapping[str, Any]],
    criteria: Mapping[str, Any] | None = None,
    terrain: Terrain | None = None,
    title: str = "",
    sun_elevation_deg: float = SUN_ELEVATION_DEG,
    sun_azimuth_deg: float = SUN_AZIMUTH_DEG,
) -> Figure:
    """The campaign report as a matplotlib ``Figure`` (no pyplot); see :func:`write_campaign_report`.

    The axes carry labels (``ax.get_label()``): ``map``, ``v_vertical``,
    ``v_horizontal``, ``tilt``, ``outcomes``, ``rate``, ``consistency``; the 3σ ellipse patch
    has the gid ``error_ellipse``.
    """
    rows = _check_rows(rows)
    limits = check_criteria(criteria)
    from matplotlib.figure import Figure

    fig = Figure(figsize=FIGURE_SIZE_IN)
    axd = fig.subplot_mosaic(
        [["map", "v_vertical", "v_horizontal"], ["map", "tilt", "outcomes"], ["map", "rate", "rate"],
         ["consistency", "consistency", "consistency"]],
        width_ratios=[1.25, 1.0, 1.0], height_ratios=[1.0, 1.0, 0.45, 0.9], gridspec_kw=REPORT_GRID,
    )
    for name, ax in axd.items():
        ax.set_label(name)
    _draw_map(axd["map"], rows, terrain, sun_elevation_deg, sun_azimuth_deg)
    td = _touched_down(rows)
    for key, label, unit, crit_key, _ in METRICS[:3]:
        panel = {"touchdown_v_vertical_mps": "v_vertical", "touchdown_v_horizontal_mps": "v_horizontal",
                 "touchdown_tilt_deg": "tilt"}[key]
        _draw_hist(axd[panel], column(rows, key)[td], label, unit, limits.get(crit_key))
    _draw_outcomes(axd["outcomes"], rows)
    _draw_rate(axd["rate"], rows)
    _draw_consistency(axd["consistency"], campaign_consistency(rows))
    n = len(rows)
    fig.suptitle(title or f"Monte Carlo campaign: {n} case{'s' if n != 1 else ''}")
    return fig


def write_campaign_report(
    rows: Sequence[Mapping[str, Any]],
    criteria: Mapping[str, Any] | None,
    path: str | Path,
    terrain: Terrain | None = None,
    title: str = "",
    sun_elevation_deg: float = SUN_ELEVATION_DEG,
    sun_azimuth_deg: float = SUN_AZIMUTH_DEG,
) -> Path:
    """Draw the campaign report into one PNG (``FIGURE_SIZE_IN`` at ``FIGURE_DPI``), atomically.

    Panels: touchdown points over the terrain hillshade (cropped to the
    points and the target plus a margin; target marked; points coloured by
    outcome) with their 3σ error ellipse (3 or more touchdowns; the crop
    holds it too); histograms
    of the touchdown vertical speed, horizontal speed and tilt over the
    cases that landed or touched down, with the limits as dashed lines;
    outcome counts; the success rate with its Wilson 95 % interval.

    Args:
        rows: One dict per case (see the module docstring); may be empty.
            Missing, None and NaN values are left out of the panels.
        criteria: Landing limits (``v_vertical_max_mps``,
            ``v_horizontal_max_mps``, ``tilt_max_deg``; others ignored), or None.
        path: Destination PNG; parent folders are created.
        terrain: ``models.terrain.Terrain`` for the hillshade, or None for plain axes.
        title: Figure title (default: the number of cases).
        sun_elevation_deg: Sun elevation for the hillshade [deg].
        sun_azimuth_deg: Sun azimuth from north toward east for it [deg].

    Returns:
        The path written.

    Raises:
        ValueError: ``rows`` is not a list of dicts, or a criterion is not a
            number. Nothing is written then.
    """
    fig = campaign_figure(rows, criteria, terrain, title, sun_elevation_deg, sun_azimuth_deg)
    return save_figure(fig, path, dpi=FIGURE_DPI)
