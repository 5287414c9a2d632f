"""The output files of one landing run (``landbench run --out DIR``).

Pure: arrays and dicts in, files and text out; no simulator (``mujoco`` is
never imported here, and matplotlib only when a plot is drawn).

Outputs:
    * ``telemetry.parquet``: :func:`write_telemetry_parquet` /
      :func:`read_telemetry_parquet`, one row per control tick, exact round trip.
    * ``plots.png``: :func:`write_plots`, a grid of trajectory and time-history
      panels over the terrain.
    * ``camera.mp4``: :class:`CameraVideo` (streaming) or :func:`write_video`.
    * the terminal summary: :func:`summary_table`.

Every file appears whole or not at all: results are built in memory or in a
temporary file in the destination folder and renamed into place
(``bench.report.io``), so a failed run never leaves a truncated file or clobbers a
result that was already there.

Telemetry is a ``dict[str, np.ndarray]`` of equal-length 1-D columns (the
dict order is the column order), in the landing frame L (origin at the
landing target on the surface, x east, y north, z up). Column names carry
their units (``_m``, ``_mps``, ``_deg``, ``_kg``, ``_N``, ``_s``).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.report.io import atomic_write_bytes, save_figure

if TYPE_CHECKING:  # typing only: keeps this module cheap to import
    from models.terrain import Terrain

# ------------------------------------------------------------------ telemetry
TIME_COLUMN = "t_s"
PARQUET_COMPRESSION = "zstd"  # falls back to PARQUET_FALLBACK_COMPRESSION when this pyarrow lacks it
PARQUET_FALLBACK_COMPRESSION = "snappy"
# Schema metadata: the NumPy dtype of every column, so reading restores them exactly
# (Parquet alone would turn '<U…' strings into Python objects).
PARQUET_DTYPES_KEY = b"landbench.numpy_dtypes"
PARQUET_FORMAT_KEY = b"landbench.telemetry_format"
PARQUET_FORMAT_VERSION = b"1"
SUPPORTED_DTYPE_KINDS = "biufUSOM"  # bool, int, uint, float, str, bytes, object (str), datetime64

# ---------------------------------------------------------------------- plots
PLOT_REQUIRED_COLUMNS = (
    "t_s", "r_x_m", "r_y_m", "r_z_m", "v_x_mps", "v_y_mps", "v_z_mps",
    "height_m", "throttle", "tilt_deg", "mass_kg",
)
FIGURE_SIZE_IN = (14.0, 10.0)
FIGURE_DPI = 100
PLOT_COLUMNS_PLAIN = 3  # panels per row without navigation-error panels (3 x 3)
PLOT_COLUMNS_NAV = 4  # with them (3 x 4)
PLOT_MARGINS = dict(left=0.055, right=0.99, bottom=0.05, top=0.93, wspace=0.3, hspace=0.36)  # figure fractions
SUN_ELEVATION_DEG = 30.0  # default hillshade sun for the top view [deg]
SUN_AZIMUTH_DEG = 315.0  # from north, clockwise toward east [deg] (the cartographic north-west light)
TOP_VIEW_MARGIN_FRAC = 0.15  # margin around the flown area, as a fraction of its larger side
TOP_VIEW_MIN_HALF_M = 20.0  # smallest half-width of the top view [m]
SPEED_LOG_FLOOR_MPS = 1e-2  # speeds below this are drawn at it on the log-scale panel [m/s]
NAV_SIGMA_BOUND = 3.0  # estimation errors are drawn with +/- this many sigma
AXES = ("x", "y", "z")
AXIS_COLORS = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
PHASE_ALPHA = 0.08  # background tint of the flight phases on time panels
PHASE_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
CRITERIA_KEYS = ("v_vertical_max_mps", "v_horizontal_max_mps", "tilt_max_deg")

# ---------------------------------------------------------------------- video
VIDEO_FOURCC = "mp4v"  # MPEG-4 Part 2 in .mp4: encodes with opencv-python-headless' bundled FFmpeg
# Tried in order for a .mp4 path; MJPG is the last resort and renames the output to .avi.
VIDEO_CODECS_MP4 = (("mp4v", ".mp4"), ("avc1", ".mp4"), ("MJPG", ".avi"))
VIDEO_CODECS_AVI = (("MJPG", ".avi"),)
VIDEO_FILE_MODE = 0o666  # permissions of the finished video, before the umask (as bench.report.io gives its files)
TRACK_RADIUS_PX = 3.0  # circle drawn at each track position [px]
TRACK_COLOR_BGR = (0, 255, 0)
MOTION_COLOR_BGR = (0, 200, 255)
DRAW_SHIFT_BITS = 4  # sub-pixel precision of cv2 drawing (1/16 px)
TEXT_COLOR_BGR = (255, 255, 255)
TEXT_OUTLINE_BGR = (0, 0, 0)
TEXT_MARGIN_PX = 6
TEXT_REFERENCE_HEIGHT_PX = 512  # font scale 0.5 at this frame height, proportional otherwise
TEXT_MIN_SCALE = 0.35

# -------------------------------------------------------------------- summary
SUMMARY_REQUIRED_KEYS = (
    "outcome", "landed", "touchdown", "fuel_used_kg", "sim_time_s", "wall_time_s",
    "realtime_factor", "seed", "criteria",
)
TOUCHDOWN_KEYS = ("t_s", "v_vertical_mps", "v_horizontal_mps", "tilt_deg", "miss_distance_m")
CHECK_OK = "✓"
CHECK_FAIL = "✗"
MISSING = "—"


# =============================================================== validation
def _validate_telemetry(telemetry: Mapping[str, Any], required: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """Check that telemetry is a non-empty table of equal-length 1-D columns.

    Args:
        telemetry: Column name -> (N,) array-like.
        required: Column names that must be present.

    Returns:
        Column name -> (N,) ``np.ndarray``, in the input order (no copies).

    Raises:
        ValueError: Not a mapping, no columns, a non-string name, a column
            that is not 1-D, columns of different lengths (the message names
            the column), zero rows, or a missing required column.
    """
    if not isinstance(telemetry, Mapping):
        raise ValueError(f"telemetry must be a mapping of column name -> 1-D array, got {type(telemetry).__name__}")
    if len(telemetry) == 0:
        raise ValueError("telemetry is empty: it has no columns")
    cols: dict[str, np.ndarray] = {}
    first: str | None = None
    for name, values in telemetry.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"telemetry column names must be non-empty strings, got {name!r}")
        arr = np.asarray(values)
        if arr.ndim != 1:
            raise ValueError(f"telemetry column {name!r} has shape {arr.shape}; expected a 1-D (N,) array")
        if first is None:
            first = name
        elif len(arr) != len(cols[first]):
            raise ValueError(
                f"telemetry is ragged: column {name!r} has {len(arr)} rows but column {first!r} has {len(cols[first])}"
            )
        cols[name] = arr
    assert first is not None
    if len(cols[first]) == 0:
        raise ValueError(f"telemetry is empty: it has 0 rows (column {first!r} is empty)")
    missing = [c for c in required if c not in cols]
    if missing:
        raise ValueError(f"telemetry lacks the required column(s) {', '.join(map(repr, missing))}; it has {list(cols)}")
    return cols


# ================================================================== parquet
def _to_arrow(name: str, arr: np.ndarray) -> tuple[pa.Array, np.dtype]:
    """One telemetry column as an Arrow array, plus the NumPy dtype to restore on read."""
    if arr.dtype.kind not in SUPPORTED_DTYPE_KINDS:
        raise ValueError(
            f"telemetry column {name!r} has dtype {arr.dtype}, which Parquet cannot store; "
            "use bool, int, uint, float, str, bytes or datetime64"
        )
    if not arr.dtype.isnative:
        arr = arr.astype(arr.dtype.newbyteorder("="))  # Arrow wants native byte order
    try:
        if arr.dtype.kind in "biuf" or (arr.dtype.kind in "US" and arr.ndim == 1):
            out = _arrow_from_buffers(arr)
        elif arr.dtype.kind in "US":
            out = pa.array(arr.tolist(), type=pa.string() if arr.dtype.kind == "U" else pa.binary())
        elif arr.dtype.kind == "O":
            out = pa.array(arr.tolist())
        else:
            out = pa.array(arr)
    except (pa.ArrowException, TypeError) as exc:
        raise ValueError(f"telemetry column {name!r} (dtype {arr.dtype}) cannot be stored in Parquet: {exc}") from exc
    return out, arr.dtype


def _arrow_from_buffers(arr: np.ndarray) -> "pa.Array":
    """A 1-D bool, int, uint, float, str or bytes column as an Arrow array, built from its buffers.

    The same array as ``pa.array``, which imports pandas (about a second) to
    ask whether its input is a pandas object.
    """
    n = len(arr)
    if arr.dtype.kind in "US":
        items = [v.encode("utf-8") for v in arr.tolist()] if arr.dtype.kind == "U" else arr.tolist()
        offsets = np.zeros(n + 1, np.int32)
        np.cumsum([len(b) for b in items], out=offsets[1:])
        return pa.Array.from_buffers(pa.string() if arr.dtype.kind == "U" else pa.binary(), n,
                                     [None, pa.py_buffer(offsets), pa.py_buffer(b"".join(items))])
    if arr.dtype.kind == "b":
        data = np.packbits(arr.astype(bool, copy=False), bitorder="little")
    else:
        data = np.ascontiguousarray(arr)
    return pa.Array.from_buffers(pa.from_numpy_dtype(arr.dtype), n, [None, pa.py_buffer(data)])


def write_telemetry_parquet(telemetry: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """Write telemetry to a Parquet file, atomically.

    Column types are kept: bool, signed and unsigned integers and floats of
    every width, str (``'<U…'``), bytes and datetime64. The NumPy dtype of
    each column is stored in the schema metadata so that
    :func:`read_telemetry_parquet` restores it exactly. Compression is
    ``PARQUET_COMPRESSION`` (zstd), or snappy where this pyarrow lacks zstd.

    Args:
        telemetry: Column name -> (N,) array, N >= 1, one row per control
            tick; must hold ``t_s`` [s]. The dict order is the column order.
        path: Destination file (``telemetry.parquet``); parent folders are created.

    Returns:
        The path written.

    Raises:
        ValueError: Ragged or empty telemetry, a column that is not 1-D, a
            missing ``t_s`` column, or a column Parquet cannot store (the
            message names the column). Nothing is written then.
    """
    cols = _validate_telemetry(telemetry, required=(TIME_COLUMN,))
    arrays, dtypes = [], {}
    for name, arr in cols.items():
        out, dtype = _to_arrow(name, arr)
        arrays.append(out)
        dtypes[name] = dtype.str
    table = pa.Table.from_arrays(arrays, names=list(cols))
    table = table.replace_schema_metadata({
        PARQUET_DTYPES_KEY: json.dumps(dtypes).encode("utf-8"),
        PARQUET_FORMAT_KEY: PARQUET_FORMAT_VERSION,
    })
    compression = PARQUET_COMPRESSION if pa.Codec.is_available(PARQUET_COMPRESSION) else PARQUET_FALLBACK_COMPRESSION
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression=compression)
    return atomic_write_bytes(path, sink.getvalue().to_pybytes())


def read_telemetry_parquet(path: str | Path) -> dict[str, np.ndarray]:
    """Read telemetry written by :func:`write_telemetry_parquet`.

    Args:
        path: A Parquet file.

    Returns:
        Column name -> (N,) ``np.ndarray`` in the file's column order, with the
        dtypes that were written (exact round trip). For a Parquet file from
        elsewhere (no landbench metadata), strings come back as ``'<U…'``
        arrays and other columns with Arrow's NumPy types (nulls in numeric
        columns as NaN).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is not a readable Parquet file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"telemetry file {path} does not exist")
    try:
        table = pq.read_table(path)
    except pa.ArrowException as exc:
        raise ValueError(f"{path} is not a readable Parquet file: {exc}") from exc
    meta = table.schema.metadata or {}
    try:
        dtypes: dict[str, str] = json.loads(meta[PARQUET_DTYPES_KEY]) if PARQUET_DTYPES_KEY in meta else {}
    except (ValueError, TypeError):
        dtypes = {}
    out: dict[str, np.ndarray] = {}
    for name, column in zip(table.column_names, table.columns):
        values = column.to_numpy(zero_copy_only=False)
        stored = dtypes.get(name)
        if stored is not None:
            dtype = np.dtype(stored)
            if dtype.kind in "US":
                values = np.asarray(values.tolist(), dtype=dtype)
            else:
                values = values.astype(dtype, copy=False)
        elif pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
            values = np.asarray(values.tolist(), dtype=str)
        out[name] = values
    return out


# ==================================================================== plots
def check_criteria(criteria: Mapping[str, Any] | None) -> dict[str, float]:
    """The landing limits that are given, as floats (unknown keys such as ``settle_s`` are ignored)."""
    if criteria is None:
        return {}
    if not isinstance(criteria, Mapping):
        raise ValueError(f"criteria must be a mapping with keys {CRITERIA_KEYS}, got {type(criteria).__name__}")
    out = {}
    for key in CRITERIA_KEYS:
        value = criteria.get(key)
        if value is None:
            continue
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"criteria[{key!r}] = {value!r} is not a number") from None
    return out


def _touchdown_time(touchdown: Mapping[str, Any] | None) -> float | None:
    """Touchdown time [s] from the ``touchdown`` dict, None when there was none."""
    if touchdown is None:
        return None
    if not isinstance(touchdown, Mapping):
        raise ValueError(f"touchdown must be a mapping with key 't_s', got {type(touchdown).__name__}")
    t = touchdown.get("t_s")
    if t is None:
        return None
    try:
        t = float(t)
    except (TypeError, ValueError):
        raise ValueError(f"touchdown['t_s'] = {t!r} is not a number") from None
    return t if math.isfinite(t) else None


def _phase_segments(t: np.ndarray, phase: np.ndarray) -> list[tuple[float, float, str]]:
    """Runs of equal phase as (t_start, t_end, name); a run ends where the next begins."""
    names = phase.astype(str)
    change = np.flatnonzero(names[1:] != names[:-1]) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [len(names) - 1]))
    return [(float(t[s]), float(t[e]), str(names[s])) for s, e in zip(starts, ends)]


def _nav_components(cols: Mapping[str, np.ndarray], kind: str) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
    """(axis, error, sigma or None) for the navigation-error columns of ``kind`` 'r' [m] or 'v' [m/s] present."""
    unit = "m" if kind == "r" else "mps"
    out = []
    for ax in AXES:
        err = cols.get(f"nav_err_{kind}_{ax}_{unit}")
        if err is not None:
            out.append((ax, err.astype(np.float64), cols.get(f"nav_sigma_{kind}_{ax}_{unit}")))
    return out


def _terrain_under(terrain: Terrain, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``terrain.surface_height`` at the finite (x, y) points, NaN elsewhere [m]."""
    z = np.full(x.shape, np.nan)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.any():
        z[ok] = terrain.surface_height(x[ok], y[ok])
    return z


def _top_view_bounds(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Square (xmin, xmax, ymin, ymax) [m] holding the flown track, the target and a margin."""
    ok = np.isfinite(x) & np.isfinite(y)
    xs = np.concatenate((x[ok], [0.0]))
    ys = np.concatenate((y[ok], [0.0]))
    cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
    span = max(xs.max() - xs.min(), ys.max() - ys.min())
    half = max(span / 2 + TOP_VIEW_MARGIN_FRAC * span, TOP_VIEW_MIN_HALF_M)
    return cx - half, cx + half, cy - half, cy + half


def draw_hillshade(ax, terrain: Terrain, bounds: tuple[float, float, float, float],
                   sun_elevation_deg: float, sun_azimuth_deg: float) -> None:
    """The terrain hillshade under ``bounds`` (x0, x1, y0, y1) [m] (south-up grid, origin='lower').

    Only that window is shaded: the vertex index ranges covering it, clamped to the tile.
    """
    x0, x1, y0, y1 = bounds
    n = terrain.height_m.shape[0]
    half, s = terrain.size_m / 2, terrain.spacing_m
    j0, j1 = (int(np.clip(np.floor((v + half) / s), 0, n - 1)) for v in (x0, x1))
    i0, i1 = (int(np.clip(np.floor((v + half) / s), 0, n - 1)) for v in (y0, y1))
    j1, i1 = min(j1 + 1, n - 1), min(i1 + 1, n - 1)
    shade = terrain.hillshade(sun_elevation_deg, sun_azimuth_deg)[i0:i1 + 1, j0:j1 + 1]
    if shade.size:
        extent = (-half + (j0 - 0.5) * s, -half + (j1 + 0.5) * s, -half + (i0 - 0.5) * s, -half + (i1 + 0.5) * s)
        ax.imshow(shade, cmap="gray", origin="lower", extent=extent, vmin=0.0, vmax=1.0, interpolation="bilinear")


def _draw_top_view(ax, terrain: Terrain, x: np.ndarray, y: np.ndarray, i_td: int | None,
                   sun_elevation_deg: float, sun_azimuth_deg: float) -> None:
    """Ground track over the terrain hillshade, cropped to the flown area (south-up grid, origin='lower')."""
    x0, x1, y0, y1 = bounds = _top_view_bounds(x, y)
    draw_hillshade(ax, terrain, bounds, sun_elevation_deg, sun_azimuth_deg)
    ax.plot(x, y, color="tab:orange", lw=1.5, label="ground track")
    ax.plot(x[0], y[0], marker="^", color="cyan", ms=8, mec="k", ls="none", label="start")
    ax.plot(0, 0, marker="+", color="red", ms=14, mew=2, ls="none", label="target")
    if i_td is not None:
        ax.plot(x[i_td], y[i_td], marker="*", color="yellow", ms=12, mec="k", ls="none", label="touchdown")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(f"top view (hillshade, sun el {sun_elevation_deg:.0f}° az {sun_azimuth_deg:.0f}°)", y=1.0)
    ax.legend(loc="best", fontsize=7)


def _draw_side_view(ax, horiz: np.ndarray, z: np.ndarray, ground: np.ndarray, i_td: int | None, axis: str) -> None:
    """Trajectory in a vertical plane with the terrain under the ground track."""
    ax.plot(horiz, ground, color="saddlebrown", lw=1.2, label="terrain under track")
    ax.plot(horiz, z, color="tab:blue", lw=1.5, label="lander (body origin)")
    ax.plot(horiz[0], z[0], marker="^", color="cyan", ms=8, mec="k", ls="none", label="start")
    ax.plot(0, 0, marker="+", color="red", ms=12, mew=2, ls="none", label="target")
    if i_td is not None:
        ax.plot(horiz[i_td], z[i_td], marker="*", color="yellow", ms=12, mec="k", ls="none", label="touchdown")
    name = "east" if axis == "x" else "north"
    ax.set_xlabel(f"{axis} {name} [m]")
    ax.set_ylabel("z up [m]")
    ax.set_title(f"side view {axis}–z", y=1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=7)


class PlotCanvas(NamedTuple):
    """The run figure's empty panels (:func:`plot_canvas`)."""

    figure: Any
    axes: list
    nav: bool  # with the navigation-error panels (3 x PLOT_COLUMNS_NAV), else 3 x PLOT_COLUMNS_PLAIN


def plot_canvas(nav: bool, ticks: int = 0) -> PlotCanvas:
    """The figure of :func:`write_plots` before anything is drawn on it: its size, margins and panels
    (``nav``: with the two navigation-error panels). Nothing in it depends on the telemetry.

    ``ticks``: major ticks made ahead on each axis (matplotlib makes them when the figure is drawn, as
    many as the axis needs, copying the first one's properties; a process that waits for the telemetry
    makes them meanwhile: 0.1-0.2 s of the drawing). The PNG is the same (tested)."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no GUI backend

    # Fixed margins, not layout="constrained": the constrained layout lays the whole figure
    # out once more before drawing it (about half of the plots' time, a few per cent of a run).
    fig = Figure(figsize=FIGURE_SIZE_IN)
    fig.subplots_adjust(**PLOT_MARGINS)
    ncols = PLOT_COLUMNS_NAV if nav else PLOT_COLUMNS_PLAIN
    axes = list(fig.subplots(3, ncols).ravel())
    for ax in axes:
        ax.xaxis.get_major_ticks(ticks)
        ax.yaxis.get_major_ticks(ticks)
    return PlotCanvas(fig, axes, nav)


def write_plots(
    telemetry: Mapping[str, np.ndarray],
    terrain: Terrain,
    path: str | Path,
    *,
    title: str = "",
    criteria: Mapping[str, Any] | None = None,
    touchdown: Mapping[str, Any] | None = None,
    sun_elevation_deg: float = SUN_ELEVATION_DEG,
    sun_azimuth_deg: float = SUN_AZIMUTH_DEG,
    canvas: PlotCanvas | None = None,
    processes: int = 1,
) -> Path:
    """Draw the run's plots into one PNG (``FIGURE_SIZE_IN`` at ``FIGURE_DPI``), atomically.

    Panels: side views x–z and y–z (with the terrain profile under the ground
    track, ``terrain.surface_height`` at the flown x, y), top view over the
    terrain hillshade (cropped to the flown area plus a margin; target
    marked), footpad height vs t, velocities vx, vy, vz and horizontal speed
    vs t, |vz| and horizontal speed on a log scale, throttle, tilt and mass
    vs t. When the ``nav_err_{r,v}_{x,y,z}_{m,mps}`` columns exist, two more
    panels show the estimation errors with ±3σ bounds (from the matching
    ``nav_sigma_…`` columns when present). Flight phases (``phase`` column,
    optional) tint the time panels.

    Args:
        telemetry: Column name -> (N,) array; needs ``PLOT_REQUIRED_COLUMNS``
            (``t_s`` [s], ``r_{x,y,z}_m`` [m] in L, ``v_{x,y,z}_mps`` [m/s],
            ``height_m`` [m], ``throttle`` [0..1], ``tilt_deg`` [deg],
            ``mass_kg`` [kg]). Non-finite values are drawn as gaps.
        terrain: The terrain flown over (``models.terrain.Terrain``).
        path: Destination PNG; parent folders are created.
        title: Figure title (e.g. the scenario name and the outcome).
        criteria: Landing limits drawn as dashed lines: any of
            ``v_vertical_max_mps``, ``v_horizontal_max_mps``, ``tilt_max_deg``
            (other keys are ignored).
        touchdown: Touchdown metrics; its ``t_s`` [s] (None: no touchdown)
            is marked on every time panel and on the trajectories.
        sun_elevation_deg: Sun elevation for the top-view hillshade [deg].
        sun_azimuth_deg: Sun azimuth from north toward east for it [deg].
        canvas: An empty figure made ahead by :func:`plot_canvas` (a process that waits for the
            telemetry makes it meanwhile), drawn on once; used when its ``nav`` matches the telemetry's
            navigation-error columns, else a new one is made. The PNG is the same either way.
        processes: 2: the panels drawn by two processes (a fork draws half of them meanwhile), the
            same PNG (:func:`bench.report.split_draw.figure_png`); for a process with a second core
            to itself and no threads, such as the run's plot process.

    Returns:
        The path written.

    Raises:
        ValueError: Ragged or empty telemetry, a missing required column, or
            a criteria / touchdown value that is not a number. Nothing is
            written then.
    """
    cols = _validate_telemetry(telemetry, required=PLOT_REQUIRED_COLUMNS)
    limits = check_criteria(criteria)
    t_td = _touchdown_time(touchdown)
    f64 = {k: cols[k].astype(np.float64) for k in PLOT_REQUIRED_COLUMNS}
    t = f64["t_s"]
    x, y, z = f64["r_x_m"], f64["r_y_m"], f64["r_z_m"]
    vx, vy, vz = f64["v_x_mps"], f64["v_y_mps"], f64["v_z_mps"]
    v_h = np.hypot(vx, vy)
    i_td = None
    if t_td is not None and np.isfinite(t).any():
        i_td = int(np.nanargmin(np.abs(t - t_td)))
    ground = _terrain_under(terrain, x, y)
    segments = _phase_segments(t, cols["phase"]) if "phase" in cols else []
    phase_color = {}
    for _, _, name in segments:
        phase_color.setdefault(name, PHASE_COLORS[len(phase_color) % len(PHASE_COLORS)])
    nav_r, nav_v = _nav_components(cols, "r"), _nav_components(cols, "v")

    nav = bool(nav_r or nav_v)
    fig, axes, _ = canvas if canvas is not None and canvas.nav == nav else plot_canvas(nav)
    panels = iter(axes)

    def time_axis(ylabel: str, panel_title: str):
        ax = next(panels)
        for t0, t1, name in segments:
            ax.axvspan(t0, t1, color=phase_color[name], alpha=PHASE_ALPHA, lw=0)
        if t_td is not None:
            ax.axvline(t_td, color="k", ls=":", lw=1.2, label=f"touchdown {t_td:.2f} s")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(panel_title, y=1.0)  # a fixed place: no layout pass to dodge top decorations (there are none)
        ax.grid(alpha=0.3)
        return ax

    _draw_side_view(next(panels), x, z, ground, i_td, "x")
    _draw_side_view(next(panels), y, z, ground, i_td, "y")
    _draw_top_view(next(panels), terrain, x, y, i_td, sun_elevation_deg, sun_azimuth_deg)

    ax = time_axis("height [m]", "footpad height above terrain")
    ax.plot(t, f64["height_m"], color="tab:blue", label="height_m")
    ax.axhline(0.0, color="saddlebrown", lw=1)
    if segments:  # phase legend (tint patches)
        from matplotlib.patches import Patch

        handles, labels = ax.get_legend_handles_labels()
        handles += [Patch(color=c, alpha=0.3) for c in phase_color.values()]
        labels += list(phase_color)
        ax.legend(handles, labels, loc="best", fontsize=7)
    else:
        ax.legend(loc="best", fontsize=7)

    ax = time_axis("velocity [m/s]", "velocity in L")
    for axis, v in zip(AXES, (vx, vy, vz)):
        ax.plot(t, v, color=AXIS_COLORS[axis], lw=1.2, label=f"v{axis}")
    ax.plot(t, v_h, color="k", lw=1.2, label="horizontal speed")
    if "v_vertical_max_mps" in limits:
        ax.axhline(-limits["v_vertical_max_mps"], color=AXIS_COLORS["z"], ls="--", lw=1,
                   label=f"−v_vert max {limits['v_vertical_max_mps']:g}")
    if "v_horizontal_max_mps" in limits:
        ax.axhline(limits["v_horizontal_max_mps"], color="k", ls="--", lw=1,
                   label=f"v_horiz max {limits['v_horizontal_max_mps']:g}")
    ax.legend(loc="best", fontsize=7, ncol=2)

    ax = time_axis("speed [m/s] (log)", "touchdown speeds vs limits")
    ax.semilogy(t, np.maximum(np.abs(vz), SPEED_LOG_FLOOR_MPS), color=AXIS_COLORS["z"], lw=1.2, label="|vz|")
    ax.semilogy(t, np.maximum(v_h, SPEED_LOG_FLOOR_MPS), color="k", lw=1.2, label="horizontal speed")
    if "v_vertical_max_mps" in limits:
        ax.axhline(limits["v_vertical_max_mps"], color=AXIS_COLORS["z"], ls="--", lw=1, label="v_vert max")
    if "v_horizontal_max_mps" in limits:
        ax.axhline(limits["v_horizontal_max_mps"], color="k", ls="--", lw=1, label="v_horiz max")
    ax.legend(loc="best", fontsize=7)

    ax = time_axis("throttle [-]", "throttle (delivered thrust / max)")
    ax.plot(t, f64["throttle"], color="tab:orange", lw=1.2, label="throttle")
    ax.set_ylim(-0.05, 1.05)
    ax.legend(loc="best", fontsize=7)

    ax = time_axis("tilt [deg]", "tilt of body +z from vertical")
    ax.plot(t, f64["tilt_deg"], color="tab:purple", lw=1.2, label="tilt")
    if "tilt_max_deg" in limits:
        ax.axhline(limits["tilt_max_deg"], color="tab:purple", ls="--", lw=1,
                   label=f"limit {limits['tilt_max_deg']:g}°")
    ax.legend(loc="best", fontsize=7)

    mass = f64["mass_kg"]
    finite_mass = mass[np.isfinite(mass)]
    used = f", {finite_mass[0] - finite_mass[-1]:.1f} kg used" if finite_mass.size else ""
    ax = time_axis("mass [kg]", f"mass{used}")
    ax.plot(t, mass, color="tab:brown", lw=1.2, label="mass")
    ax.legend(loc="best", fontsize=7)

    for comps, unit, what in ((nav_r, "m", "position"), (nav_v, "m/s", "velocity")):
        if not comps:
            continue
        ax = time_axis(f"error [{unit}]", f"{what} estimation error (±{NAV_SIGMA_BOUND:g}σ dashed)")
        for axis, err, sigma in comps:
            ax.plot(t, err, color=AXIS_COLORS[axis], lw=1.0, label=f"{axis}")
            if sigma is not None:
                bound = NAV_SIGMA_BOUND * sigma.astype(np.float64)
                ax.plot(t, bound, color=AXIS_COLORS[axis], ls="--", lw=0.8)
                ax.plot(t, -bound, color=AXIS_COLORS[axis], ls="--", lw=0.8)
        ax.legend(loc="best", fontsize=7)

    for ax in panels:  # unused grid cells
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=13)
    return save_figure(fig, path, dpi=FIGURE_DPI, processes=processes)


# ==================================================================== video
def track_overlay(tracks: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A frame's track overlay for :meth:`CameraVideo.add`: (``tracks_xy``, ``prev_xy``) of a
    ``vision.tracks.Tracks``, or (None, None) when there are none."""
    if tracks is None or not len(tracks):
        return None, None
    return tracks.xy, tracks.prev_xy


def frame_caption(t_s: float, height_m: float | None = None) -> str:
    """The usual video caption, e.g. ``'t = 12.34 s  h = 56.7 m'``."""
    text = f"t = {t_s:.2f} s"
    if height_m is not None:
        text += f"  h = {height_m:.1f} m"
    return text


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _pixel_points(name: str, xy: Any) -> np.ndarray:
    """Validate an (N, 2) array of pixel coordinates (x = column, y = row)."""
    arr = np.asarray(xy, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} has shape {arr.shape}; expected (N, 2) pixel coordinates (x = column, y = row)")
    return arr


def draw_tracks(bgr: np.ndarray, tracks: np.ndarray, prev: np.ndarray | None = None) -> None:
    """Draw tracks onto a BGR frame, in place: a circle at each position and, with ``prev``, a motion
    segment from each previous position (both finite) to the current one.

    Args:
        bgr: (H, W, 3) uint8 frame, drawn on.
        tracks: (N, 2) pixel coordinates (x = column, y = row); non-finite rows are skipped.
        prev: (N, 2) the same tracks' previous positions, or None.

    Coordinates are drawn at 1/2^DRAW_SHIFT_BITS px (rounded half to even, as Python's ``round``),
    anti-aliased; the segments first, then the circles, each in track order. The segments go to
    OpenCV in one ``polylines`` call and the centres are converted at once: the same pixels as
    one ``cv2.line`` and one ``cv2.circle`` call per track (tested), about 4x faster at 90
    tracks, which matters where a campaign worker encodes its cases' videos itself.
    """
    scale = 1 << DRAW_SHIFT_BITS
    ok = np.isfinite(tracks).all(axis=1)
    if prev is not None:
        both = ok & np.isfinite(prev).all(axis=1)
        if both.any():
            seg = np.rint(np.stack([prev[both], tracks[both]], axis=1) * scale).astype(np.int32)  # (M, 2, 2)
            cv2.polylines(bgr, list(seg), False, MOTION_COLOR_BGR, 1, cv2.LINE_AA, DRAW_SHIFT_BITS)
    radius = int(round(TRACK_RADIUS_PX * scale))
    for centre in np.rint(tracks[ok] * scale).astype(np.int64).tolist():
        cv2.circle(bgr, centre, radius, TRACK_COLOR_BGR, 1, cv2.LINE_AA, DRAW_SHIFT_BITS)


class CameraVideo:
    """Streams grayscale camera frames into a video file (``camera.mp4``).

    Frames are encoded as they are added (a run may render thousands; none
    are kept in memory) into a temporary file in the destination folder,
    which :meth:`close` renames to the final name. So a crash never leaves a
    half-written video under the final name, and an exception inside a
    ``with`` block deletes the temporary file (an existing file at the final
    path is left untouched).

    Codec: ``cv2.VideoWriter`` with fourcc ``'mp4v'`` (MPEG-4 Part 2) in an
    .mp4 container, which the FFmpeg bundled with opencv-python-headless
    encodes (checked with 5.0; its 'avc1'/H.264 encoder is *not* available
    there). Should 'mp4v' fail to open, 'avc1' is tried, then MJPG, in which
    case the file is written as ``.avi`` instead (see :attr:`path` and
    :attr:`fourcc`). A ``.avi`` path is written with MJPG directly.

    MPEG-4 needs even frame sizes: an odd width or height is padded by one
    replicated column / row at the right / bottom.

    Example::

        with CameraVideo(out / "camera.mp4", fps=10.0) as video:
            for frame in frames:
                video.add(frame, text=frame_caption(t, h))

    Attributes:
        path: The final path (``.avi`` when MJPG was the fallback).
        fourcc: The codec in use ('' until the writer is opened).
        frames_written: Frames added so far.
    """

    def __init__(self, path: str | Path, fps: float, size: tuple[int, int] | None = None) -> None:
        """Prepare the writer.

        Args:
            path: Final file, ``.mp4`` (or ``.avi``); parent folders are created.
            fps: Frame rate [1/s], > 0 (the camera rate of the run).
            size: Frame size ``(width, height)`` [px] (OpenCV order; a frame
                is a (height, width) array). None: taken from the first frame.
                When given, the writer (and codec) is opened now.

        Raises:
            ValueError: Bad fps, size or file extension.
            RuntimeError: No codec could open a writer.
        """
        self._final = Path(path)
        if self._final.suffix.lower() not in (".mp4", ".avi"):
            raise ValueError(f"video path {self._final} must end in .mp4 or .avi")
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps={fps} must be a finite number > 0")
        self._fps = fps
        self._size: tuple[int, int] | None = None
        self._writer: cv2.VideoWriter | None = None
        self._tmp: Path | None = None
        self._closed = False
        self.path = self._final
        self.fourcc = ""
        self.frames_written = 0
        if size is not None:
            try:
                w, h = (int(v) for v in size)
            except (TypeError, ValueError):
                raise ValueError(f"size={size!r} must be (width, height) in pixels") from None
            if w < 1 or h < 1:
                raise ValueError(f"size={size!r} must be (width, height) with both >= 1")
            self._size = (w, h)
            self._open()

    # -------------------------------------------------------------- internals
    def _open(self) -> None:
        assert self._size is not None
        w, h = self._size
        even = (w + w % 2, h + h % 2)
        self._final.parent.mkdir(parents=True, exist_ok=True)
        codecs = VIDEO_CODECS_AVI if self._final.suffix.lower() == ".avi" else VIDEO_CODECS_MP4
        for fourcc, suffix in codecs:
            final = self._final.with_suffix(suffix)
            # The temporary name keeps the container extension: FFmpeg picks the muxer from it.
            fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".tmp{suffix}", dir=final.parent)
            os.close(fd)
            writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*fourcc), self._fps, even, True)
            if writer.isOpened():
                self._writer, self._tmp, self.path, self.fourcc = writer, Path(tmp), final, fourcc
                return
            writer.release()
            Path(tmp).unlink(missing_ok=True)
        raise RuntimeError(
            f"no video codec could be opened for {self._final} (tried {', '.join(c for c, _ in codecs)}); "
            "is this OpenCV built with FFmpeg?"
        )

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"video {self.path} is already closed")

    # -------------------------------------------------------------------- API
    def add(self, frame: np.ndarray, tracks_xy: np.ndarray | None = None, prev_xy: np.ndarray | None = None,
            text: str | None = None) -> None:
        """Encode one frame, with optional overlays.

        Args:
            frame: (H, W) uint8 grayscale image (or (H, W, 1)); H, W must match
                the size of the video.
            tracks_xy: (N, 2) float pixel coordinates (x = column, y = row,
                integer values at pixel centres) drawn as small circles.
                Non-finite rows are skipped.
            prev_xy: (N, 2) the same tracks' previous positions; a motion
                segment is drawn from each to its current position. Needs
                ``tracks_xy`` with the same shape.
            text: Caption drawn at the top left (``\\n`` separates lines),
                e.g. :func:`frame_caption`.

        Raises:
            ValueError: Wrong dtype / shape / size, mismatched track arrays,
                or the video is closed.
        """
        self._check_open()
        img = np.asarray(frame)
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if img.ndim != 2 or img.dtype != np.uint8:
            raise ValueError(f"frame has shape {img.shape} and dtype {img.dtype}; expected (H, W) uint8 grayscale")
        h, w = img.shape
        if self._size is None:
            if w < 1 or h < 1:
                raise ValueError(f"frame has shape {img.shape}; expected a non-empty (H, W) image")
            self._size = (w, h)
            self._open()
        elif (w, h) != self._size:
            raise ValueError(
                f"frame has shape (H, W) = {(h, w)}, but the video is {self._size[0]} wide and {self._size[1]} high"
            )
        tracks = _pixel_points("tracks_xy", tracks_xy) if tracks_xy is not None else None
        prev = _pixel_points("prev_xy", prev_xy) if prev_xy is not None else None
        if prev is not None and (tracks is None or prev.shape != tracks.shape):
            raise ValueError(
                f"prev_xy has shape {prev.shape}; it needs tracks_xy of the same shape, got "
                f"{None if tracks is None else tracks.shape}"
            )
        bgr = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_GRAY2BGR)
        if w % 2 or h % 2:
            bgr = cv2.copyMakeBorder(bgr, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)
        if tracks is not None:
            draw_tracks(bgr, tracks, prev)
        if text:
            self._draw_text(bgr, text, h)
        assert self._writer is not None
        self._writer.write(bgr)
        self.frames_written += 1

    @staticmethod
    def _draw_text(bgr: np.ndarray, text: str, height: int) -> None:
        scale = max(TEXT_MIN_SCALE, 0.5 * height / TEXT_REFERENCE_HEIGHT_PX)
        thickness = max(1, int(round(scale * 2)))
        font = cv2.FONT_HERSHEY_SIMPLEX
        y = TEXT_MARGIN_PX
        for line in str(text).splitlines():
            (_, th), base = cv2.getTextSize(line, font, scale, thickness)
            y += th
            org = (TEXT_MARGIN_PX, y)
            cv2.putText(bgr, line, org, font, scale, TEXT_OUTLINE_BGR, thickness + 2, cv2.LINE_AA)
            cv2.putText(bgr, line, org, font, scale, TEXT_COLOR_BGR, thickness, cv2.LINE_AA)
            y += base + TEXT_MARGIN_PX // 2

    def close(self) -> Path | None:
        """Finish the file and rename it into place.

        Returns:
            The final path, or None when no frame was added (nothing is
            written then). Calling it again returns the same.
        """
        if self._closed:
            return self.path if self.frames_written else None
        self._closed = True
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._tmp is None:
            return None
        tmp, self._tmp = self._tmp, None
        if self.frames_written == 0:
            tmp.unlink(missing_ok=True)
            return None
        try:
            os.chmod(tmp, VIDEO_FILE_MODE & ~_current_umask())  # mkstemp made it 0600; results are ordinary files
            os.replace(tmp, self.path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return self.path

    def abort(self) -> None:
        """Stop and delete the temporary file; the final path is not touched."""
        self._closed = True
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
            self._tmp = None
        self.frames_written = 0

    def __enter__(self) -> CameraVideo:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self.abort()
        else:
            self.close()
        return False


def write_video(
    frames: Iterable[np.ndarray],
    path: str | Path,
    fps: float,
    overlay: Callable[[int], Mapping[str, Any] | None] | None = None,
) -> Path | None:
    """Encode grayscale frames into a video, streaming (see :class:`CameraVideo`).

    Args:
        frames: (H, W) uint8 images, all the same size; consumed one at a time.
        path: Final ``.mp4`` (or ``.avi``) path.
        fps: Frame rate [1/s].
        overlay: Optional ``overlay(i)`` for frame index ``i`` returning the
            keyword arguments of :meth:`CameraVideo.add` (``tracks_xy``,
            ``prev_xy``, ``text``), or None for none.

    Returns:
        The path written (``.avi`` on the MJPG fallback), or None when
        ``frames`` was empty (nothing is written).
    """
    with CameraVideo(path, fps) as video:
        for i, frame in enumerate(frames):
            extra = overlay(i) if overlay is not None else None
            video.add(frame, **(dict(extra) if extra else {}))
    return video.path if video.frames_written else None


# ================================================================== summary
def _fmt(value: Any, spec: str, unit: str = "") -> str:
    """A number formatted with ``spec`` and its unit, or MISSING for None / non-numbers."""
    if value is None:
        return MISSING
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return f"{v}{' ' + unit if unit else ''}"
    return f"{v:{spec}}{' ' + unit if unit else ''}"


def _limit_row(label: str, value: Any, limit: Any, spec: str, unit: str) -> str:
    """``label  value  ≤ limit  ✓/✗`` (no mark when either is missing)."""
    val = _fmt(value, spec, unit)
    if limit is None:
        return f"  {label:<18}{val:>12}"
    lim = f"≤ {_fmt(limit, spec, unit)}"
    mark = ""
    try:
        if value is not None:
            v, lim_v = float(value), float(limit)
            mark = CHECK_OK if (math.isfinite(v) and v <= lim_v) else CHECK_FAIL
    except (TypeError, ValueError):
        mark = ""
    return f"  {label:<18}{val:>12}   {lim:<14}{mark}"


def _flight_software_lines(summary: Mapping[str, Any]) -> list[str]:
    """The summary table's lines on the injected faults, the flight software's fault detection, its map fixes
    and its hazard scan (each only when the run had it), so that what did not happen shows too: a fault whose
    trigger never came, a map that never gave a lock, a scan that found no safe site."""
    lines: list[str] = []
    for f in summary.get("faults") or []:
        what = f"fault {f.get('kind')} on {f.get('target')}"
        if not f.get("triggered"):
            lines.append(f"{what}: never triggered (its trigger was not met in flight)")
        elif f.get("detected"):
            lines.append(f"{what}: from t = {_fmt(f.get('start_t_s'), '.2f', 's')}, detected after "
                         f"{_fmt(f.get('latency_s'), '.2f', 's')} ({f.get('detection')})")
        else:
            lines.append(f"{what}: from t = {_fmt(f.get('start_t_s'), '.2f', 's')}, not detected")
    fdir = summary.get("fdir") or {}
    if fdir.get("abort_declared"):
        lines.append(f"fault detection: abort declared at t = {_fmt(fdir.get('abort_t_s'), '.2f', 's')} "
                     f"({fdir.get('abort_reason')})")
    elif fdir.get("n_events"):
        lines.append(f"fault detection: {fdir['n_events']} event(s) ({fdir.get('subsystems')}), first at t = "
                     f"{_fmt(fdir.get('first_event_t_s'), '.2f', 's')}")
    mn = summary.get("map_nav")
    if mn:
        refused = {k: v for k, v in (mn.get("refused") or {}).items() if v}
        top = max(refused, key=refused.get) if refused else None
        why = f"; most refused: {top} ({refused[top]})" if top else ""
        lock = "locked" if mn.get("locked") else "NEVER LOCKED (navigation stayed on the hand-over estimate)"
        lines.append(f"map fixes: {mn.get('updates', 0)} used of {mn.get('attempts', 0)} attempts, {lock}{why}")
        if mn.get("miss_vs_map_target_m") is not None:
            lines.append(f"  miss against the map's target {_fmt(mn['miss_vs_map_target_m'], '.2f', 'm')}, "
                         f"false locks {mn.get('false_locks', 0)}")
    hz = summary.get("hazard")
    if hz:
        scan = hz.get("scan") or {}
        if hz.get("avoidance") == "on":
            if not scan.get("scanned"):
                lines.append("hazard scan: none taken")
            elif scan.get("no_safe_site"):
                lines.append(f"hazard scan at {_fmt(scan.get('height_m'), '.0f', 'm')}: no safe site"
                             + (" (after a second scan)" if scan.get("rescanned") else ""))
            else:
                site = scan if not scan.get("first_no_site") else (hz.get("rescan") or {})
                td = summary.get("touchdown") or {}
                where = list(site.get("site_truth_xy_m") or [None, None]) + [td.get("x_m"), td.get("y_m")]
                off = (f"; touchdown {_fmt(math.hypot(where[2] - where[0], where[3] - where[1]), '.2f', 'm')} from it"
                       if None not in where else "")
                lines.append(f"hazard scan at {_fmt(scan.get('height_m'), '.0f', 'm')}: site "
                             f"{_fmt(site.get('divert_m'), '.1f', 'm')} away, margin "
                             f"{_fmt(site.get('margin_m'), '.2f', 'm')}"
                             + (" (from the second scan)" if scan.get("rescanned") else "") + off)
        free = hz.get("hazard_free")
        verdict = ("hazard-free" if free else "unscored" if free is None
                   else f"HAZARDOUS ({(hz.get('footprint') or {}).get('hazards') or 'see summary.json'})")
        lines.append(f"touchdown footprint: {verdict}")
    return lines


def summary_table(summary: Mapping[str, Any], outputs: Mapping[str, str | Path] | None = None) -> str:
    """A one-screen plain-text summary of a run, for the terminal.

    Args:
        summary: The run summary (``summary.json`` contract): ``outcome``
            (str), ``landed`` (bool), ``touchdown`` (dict ``t_s``,
            ``v_vertical_mps``, ``v_horizontal_mps``, ``tilt_deg``,
            ``miss_distance_m``; values None without touchdown),
            ``fuel_used_kg``, ``sim_time_s``, ``wall_time_s``,
            ``realtime_factor``, ``seed``, ``criteria`` (dict
            ``v_vertical_max_mps``, ``v_horizontal_max_mps``,
            ``tilt_max_deg``, ``settle_s``); optional ``error``,
            ``guidance_law``, ``final_tilt_deg``, ``outputs``.
        outputs: Output files to list, label -> path (defaults to
            ``summary['outputs']`` when present).

    Returns:
        Lines joined with ``\\n`` (no trailing newline): the outcome in
        capitals, the touchdown values against the criteria with ✓ / ✗,
        fuel, times, seed and the output paths.

    Raises:
        ValueError: ``summary`` is not a mapping or lacks a required key,
            or ``touchdown`` / ``criteria`` is not a mapping.
    """
    if not isinstance(summary, Mapping):
        raise ValueError(f"summary must be a mapping, got {type(summary).__name__}")
    missing = [k for k in SUMMARY_REQUIRED_KEYS if k not in summary]
    if missing:
        raise ValueError(f"summary lacks the required key(s) {', '.join(map(repr, missing))}")
    td = summary["touchdown"] or {}
    crit = summary["criteria"] or {}
    for name, value in (("touchdown", td), ("criteria", crit)):
        if not isinstance(value, Mapping):
            raise ValueError(f"summary[{name!r}] must be a mapping or None, got {type(value).__name__}")

    outcome = str(summary["outcome"]).replace("_", " ").upper()
    landed = bool(summary["landed"])
    if landed:
        head = f"{CHECK_OK} {outcome}"
    else:
        head = f"{CHECK_FAIL} {outcome}" + ("" if outcome.startswith("FAIL") else " (failed)")
    lines = [f"landbench run: {head}"]
    info = [f"seed {summary['seed']}"]
    if summary.get("guidance_law"):
        info.append(f"guidance {summary['guidance_law']}")
    lines.append("  " + ", ".join(info))
    if summary.get("error"):
        lines.append(f"  error: {summary['error']}")

    t_td = td.get("t_s")
    if t_td is None:
        lines.append("touchdown: none")
    else:
        hull = " on the hull, body first (a crash)" if td.get("first_contact") == "hull" else ""
        lines.append(f"touchdown at t = {_fmt(t_td, '.2f', 's')}{hull}")
    lines.append(_limit_row("vertical speed", td.get("v_vertical_mps"), crit.get("v_vertical_max_mps"), ".2f", "m/s"))
    lines.append(_limit_row("horizontal speed", td.get("v_horizontal_mps"), crit.get("v_horizontal_max_mps"),
                            ".2f", "m/s"))
    lines.append(_limit_row("tilt", td.get("tilt_deg"), crit.get("tilt_max_deg"), ".1f", "deg"))
    lines.append(_limit_row("miss distance", td.get("miss_distance_m"), crit.get("miss_distance_max_m"), ".2f", "m"))
    if "final_tilt_deg" in summary and summary["final_tilt_deg"] is not None:
        settle = crit.get("settle_s")
        label = f"tilt after {_fmt(settle, 'g', 's')}" if settle is not None else "final tilt"
        lines.append(_limit_row(label, summary["final_tilt_deg"], crit.get("tilt_max_deg"), ".1f", "deg"))

    nav, vis = summary.get("nav") or {}, summary.get("vision") or {}
    if nav.get("vel_err_touchdown_mps") is not None:
        lines.append(
            f"navigation: velocity error at touchdown {_fmt(nav['vel_err_touchdown_mps'], '.3f', 'm/s')}, "
            f"position {_fmt(nav['pos_err_touchdown_m'], '.1f', 'm')}"
        )
        per_dof = nav.get("nees_per_dof_mean") or {}
        if per_dof:
            lines.append("  mean (e/sigma)^2 per block: " + ", ".join(f"{k} {_fmt(v, '.2f')}" for k, v in per_dof.items())
                         + "  (one run shows little; a campaign's consistency.json is the test)")
    if vis.get("frames"):
        lines.append(
            f"vision: {vis['frames']} frames, median {_fmt(vis.get('tracks_median'), '.0f')} tracks, "
            f"{_fmt(vis.get('rejected_frac'), '.1%')} of measurements gated out"
        )
    lines.extend(_flight_software_lines(summary))
    lines.append(f"fuel used          {_fmt(summary['fuel_used_kg'], '.2f', 'kg'):>12}")
    rtf = summary["realtime_factor"]
    lines.append(
        f"sim time {_fmt(summary['sim_time_s'], '.2f', 's')}, wall time {_fmt(summary['wall_time_s'], '.2f', 's')}, "
        f"real-time factor {_fmt(rtf, '.2f')}{'×' if rtf is not None else ''}"
    )
    outputs = outputs if outputs is not None else summary.get("outputs")
    if outputs:
        lines.append("outputs:")
        width = max(len(str(k)) for k in outputs)
        lines.extend(f"  {str(k):<{width}}  {v}" for k, v in outputs.items())
    return "\n".join(lines)
