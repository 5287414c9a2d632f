"""Fixation-area detection and block matching (paper §2, after Misu et al.).

Pipeline, each stage a plain function so that it can be studied on its own:

1. :func:`block_average` -- averaging + sub-sampling low-pass filter, eq. (2.1).
2. :func:`laplacian8` -- 8-neighbour Laplacian high-pass filter (§2.1 mask).
3. :func:`variance_map` -- local variance over the template window, eq. (2.2).
4. :func:`select_templates` -- high-variance, border-free, spread-out areas (§2.3).
5. :func:`match_templates` -- least-squares (SSD) block matching inside a search
   window (§2.4).

Inputs are grayscale frames (H, W) in DN; coordinates follow
:mod:`vision.tracks` (x = column, y = row). Rate: stages 1-4 run only when a
template must be (re)placed; stage 5 runs once per frame.
"""

from __future__ import annotations

import functools
import math

from dataclasses import dataclass

import cv2
import numpy as np

LAPLACIAN8_KERNEL = np.array([[1.0, 1.0, 1.0], [1.0, -8.0, 1.0], [1.0, 1.0, 1.0]], dtype=np.float32)
"""The paper's 8-neighbour Laplacian mask (§2.1)."""

LAPLACIAN_BORDER = cv2.BORDER_REPLICATE
"""Border rule of the Laplacian: replicate, so a flat border yields zero response."""

TEMPLATE_ENERGY_FLOOR = 1.0
"""Lower bound on a template's centred energy sum((T - mean T)^2) [DN^2], so that
the relative SSD of a (never selected) flat template stays finite."""


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def block_average(image: np.ndarray, sx: int, sy: int) -> np.ndarray:
    """Averaging and sub-sampling low-pass filter, eq. (2.1).

    ``Es(u, v) = 1/(Sx Sy) * sum_{i<Sx, j<Sy} E(Sx u + i, Sy v + j)`` with
    ``u`` the column and ``v`` the row. Trailing rows/columns that do not fill
    a whole block are dropped. ``cv2.resize(INTER_AREA)`` with integer factors
    computes exactly this block mean.

    Args:
        image: Frame E, (H, W) uint8 or float32 [DN].
        sx: Sub-sampling interval along x (columns), Sx >= 1.
        sy: Sub-sampling interval along y (rows), Sy >= 1.

    Returns:
        Es, (H // Sy, W // Sx) float32 [DN].

    Raises:
        ValueError: If ``sx``/``sy`` are not positive integers or exceed the
            image size.
    """
    sx = _positive_int(sx, "sx")
    sy = _positive_int(sy, "sy")
    h, w = image.shape
    ho, wo = h // sy, w // sx
    if ho == 0 or wo == 0:
        raise ValueError(f"sub-sampling (sx={sx}, sy={sy}) must not exceed the image size {image.shape}")
    # float32 first: resizing uint8 would round the block means to integers.
    src = image[: ho * sy, : wo * sx].astype(np.float32, copy=False)
    return cv2.resize(src, (wo, ho), interpolation=cv2.INTER_AREA)


def laplacian8(image: np.ndarray) -> np.ndarray:
    """8-neighbour Laplacian, the paper's high-pass filter (§2.1).

    Args:
        image: (H, W) uint8 or float32 [DN].

    Returns:
        E_L, (H, W) float32 [DN]; borders use replicated pixels.
    """
    return cv2.filter2D(
        image.astype(np.float32, copy=False), cv2.CV_32F, LAPLACIAN8_KERNEL, borderType=LAPLACIAN_BORDER
    )


def variance_map(image: np.ndarray, wx: int, wy: int) -> np.ndarray:
    """Local variance over a ``wx`` x ``wy`` window, eq. (2.2).

    ``V(u, v) = mean(E_L^2) - mean(E_L)^2`` over the window whose top-left
    element is ``(u, v)`` (the population variance). In the paper ``wx =
    Wx / Sx`` so that the window covers one template of the full-size image.
    Window sums come from one integral image.

    Args:
        image: Filtered, sub-sampled image E_L, (h, w) float32 [DN].
        wx: Window width in columns, 1 <= wx <= w.
        wy: Window height in rows, 1 <= wy <= h.

    Returns:
        V, (h - wy + 1, w - wx + 1) float64 [DN^2]; ``V[v, u]`` belongs to the
        window with top-left element ``image[v, u]``.

    Raises:
        ValueError: If the window is not a positive integer size that fits.
    """
    wx = _positive_int(wx, "wx")
    wy = _positive_int(wy, "wy")
    h, w = image.shape
    if wx > w or wy > h:
        raise ValueError(f"variance window (wx={wx}, wy={wy}) must fit in the image of shape {image.shape}")
    s, sq = cv2.integral2(image.astype(np.float32, copy=False), sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
    n = float(wx * wy)

    def window_sum(integ: np.ndarray) -> np.ndarray:
        return integ[wy:, wx:] - integ[:-wy, wx:] - integ[wy:, :-wx] + integ[:-wy, :-wx]

    mean = window_sum(s) / n
    var = window_sum(sq) / n - mean * mean
    # Cancellation can leave tiny negatives on flat areas; variance is >= 0.
    np.maximum(var, 0.0, out=var)
    return var


@functools.lru_cache(maxsize=16)
def _separation_disc(min_sep: float, sx: int, sy: int) -> tuple[int, int, np.ndarray]:
    """The grid offsets (rows, columns of sy x sx px) closer than ``min_sep``
    px to the centre, as a read-only (2 n_r + 1, 2 n_c + 1) mask, with n_r and
    n_c: the same for every refill of a sequence, so built once."""
    min_sep2 = min_sep * min_sep
    n_r, n_c = -(-math.ceil(min_sep) // sy), -(-math.ceil(min_sep) // sx)
    dr = np.arange(-n_r, n_r + 1, dtype=np.float64)[:, None] * sy
    dc = np.arange(-n_c, n_c + 1, dtype=np.float64)[None, :] * sx
    disc = dr * dr + dc * dc < min_sep2
    disc.flags.writeable = False
    return n_r, n_c, disc


def select_templates(
    variance: np.ndarray,
    n: int,
    sx: int,
    sy: int,
    template_size: tuple[int, int],
    image_shape: tuple[int, int],
    border_px: int,
    min_separation_px: float,
    min_variance: float = 0.0,
    occupied_xy: np.ndarray | None = None,
    preferred: np.ndarray | None = None,
) -> np.ndarray:
    """Pick fixation areas (templates) from a variance map (§2.3).

    Rules from the paper: (a) the highest local variance first; (b) not near
    the image border; (c) spread out -- no template centre closer than
    ``min_separation_px`` to another one (nor to ``occupied_xy``), which also
    rules out clusters; (d) a fixed number ``n`` (fewer when the image does not
    hold enough distinct textured areas, none on a blank image). Every block
    of the variance map inside the border is a candidate, not only its local
    maxima: the best free block may lie on the flank of a peak that is inside
    the border or already taken. Candidates are taken greedily in decreasing
    variance (ties in raster order), each ruling out the candidates closer
    than ``min_separation_px``.

    Args:
        variance: V from :func:`variance_map`, (hv, wv) [DN^2], computed on an
            image sub-sampled by (sx, sy).
        n: Number of templates wanted, >= 0.
        sx, sy: Sub-sampling intervals used for ``variance`` [px].
        template_size: (Wx, Wy) full-resolution template size [px].
        image_shape: (H, W) of the full-resolution frame [px].
        border_px: Minimum distance between template and image edge [px].
        min_separation_px: Minimum distance between template centres [px].
        min_variance: Candidates need V above this [DN^2] (featureless -> none).
        occupied_xy: Centres of templates already in use, (K, 2) [px], or None.
        preferred: Optional bool mask of the shape of ``variance``: the
            candidates where it is True are all taken before any other (each
            group in decreasing variance, the separation rule applying across
            both), e.g. the areas that will stay in view longest. None: no
            preference.

    Returns:
        Top-left corners (x, y) of the new templates, (M, 2) int64 [px], M <= n,
        in decreasing order of variance.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    wx_full, wy_full = template_size
    height, width = image_shape
    if n == 0 or variance.size == 0:
        return np.zeros((0, 2), np.int64)
    # Map elements whose template lies inside the border: v (rows) in
    # [v_lo, v_hi], u (columns) in [u_lo, u_hi]; top-left (x, y) = (Sx u, Sy v).
    hv, wv = variance.shape
    u_lo, v_lo = -(-border_px // sx), -(-border_px // sy)
    u_hi = min((width - border_px - wx_full) // sx, wv - 1)
    v_hi = min((height - border_px - wy_full) // sy, hv - 1)
    if u_hi < u_lo or v_hi < v_lo:
        return np.zeros((0, 2), np.int64)
    score = np.where(
        variance[v_lo : v_hi + 1, u_lo : u_hi + 1] > min_variance,
        variance[v_lo : v_hi + 1, u_lo : u_hi + 1].astype(np.float64),
        -np.inf,
    )
    if preferred is not None:
        # The others rank below every preferred candidate: shifted under the
        # lowest finite score (variances are >= 0), still above -inf.
        pref = np.asarray(preferred, dtype=bool)[v_lo : v_hi + 1, u_lo : u_hi + 1]
        finite = np.isfinite(score)
        if finite.any():
            shift = float(score[finite].max()) + 1.0
            score = np.where(pref | ~finite, score, score - shift)
    # Template centres of the candidates [px], per column and per row.
    cx = np.arange(u_lo, u_hi + 1) * sx + 0.5 * (wx_full - 1)
    cy = np.arange(v_lo, v_hi + 1) * sy + 0.5 * (wy_full - 1)
    min_sep = float(min_separation_px)
    min_sep2 = min_sep * min_sep
    if occupied_xy is not None and len(occupied_xy):
        # All occupied centres at once: no candidate closer than the separation.
        occ = np.asarray(occupied_xy, dtype=np.float64).reshape(-1, 2)
        dy2 = (cy[None, :] - occ[:, 1, None]) ** 2
        dx2 = (cx[None, :] - occ[:, 0, None]) ** 2
        score[(dy2[:, :, None] + dx2[:, None, :] < min_sep2).any(axis=0)] = -np.inf
    # Candidates lie on a grid of sx x sy px, so the candidates within the
    # separation of a chosen one are a fixed disc of grid offsets around it
    # (the same distances as between the centres: sums of exact squares).
    n_r, n_c, disc = _separation_disc(min_sep, sx, sy)
    rows, cols = score.shape
    chosen: list[tuple[int, int]] = []
    # Greedy in decreasing variance (np.argmax: first in raster order on ties):
    # take the best free candidate, then rule out every candidate within the
    # separation of it (itself included).
    while len(chosen) < n:
        k = int(np.argmax(score))
        r, c = divmod(k, cols)
        if score[r, c] == -np.inf:
            break
        chosen.append(((u_lo + c) * sx, (v_lo + r) * sy))
        score[r, c] = -np.inf
        r0, r1, c0, c1 = max(r - n_r, 0), min(r + n_r + 1, rows), max(c - n_c, 0), min(c + n_c + 1, cols)
        score[r0:r1, c0:c1][disc[r0 - r + n_r : r1 - r + n_r, c0 - c + n_c : c1 - c + n_c]] = -np.inf
    return np.array(chosen, dtype=np.int64).reshape(-1, 2)


@dataclass(frozen=True, slots=True)
class FixationAreas:
    """The stages of §2 on one frame, kept for study and figures.

    Attributes:
        averaged: Block-averaged image E_s, eq. (2.1), (H // Sy, W // Sx) float32 [DN].
        laplacian: Its 8-neighbour Laplacian E_L, same shape.
        variance: Variance map V, eq. (2.2) [DN^2].
        top_left: Selected template corners (x, y), (M, 2) int64 [px], full resolution.
    """

    averaged: np.ndarray
    laplacian: np.ndarray
    variance: np.ndarray
    top_left: np.ndarray


def fixation_areas(
    image: np.ndarray,
    n: int,
    sx: int,
    sy: int,
    template_size: int,
    border_px: int,
    min_separation_px: float,
    min_variance: float = 0.0,
    occupied_xy: np.ndarray | None = None,
    preferred: np.ndarray | None = None,
) -> FixationAreas:
    """Fixation-area detection of §2 on one frame: eqs. (2.1), Laplacian, (2.2), selection.

    Args:
        image: Frame, (H, W) uint8 or float32 [DN].
        n: Templates wanted.
        sx, sy: Block-averaging intervals [px].
        template_size: Template side [px], a multiple of sx and sy.
        border_px, min_separation_px, min_variance, occupied_xy, preferred: As in
            :func:`select_templates` (``preferred`` has the variance map's shape).

    Returns:
        The intermediate images and the selected templates.

    Raises:
        ValueError: If ``template_size`` is not a multiple of ``sx`` and
            ``sy`` (the variance window ``template_size / S`` must be whole,
            eq. 2.2; it is not rounded).
    """
    sx, sy = _positive_int(sx, "sx"), _positive_int(sy, "sy")
    template_size = _positive_int(template_size, "template_size")
    if template_size % sx or template_size % sy:
        raise ValueError(
            f"template_size ({template_size}) must be a multiple of sx ({sx}) and sy ({sy}) "
            "so the variance window of eq. (2.2) is whole"
        )
    averaged = block_average(image, sx, sy)
    lap = laplacian8(averaged)
    var = variance_map(lap, template_size // sx, template_size // sy)
    top_left = select_templates(
        var, n, sx, sy, (template_size, template_size), image.shape, border_px, min_separation_px,
        min_variance, occupied_xy=occupied_xy, preferred=preferred,
    )
    return FixationAreas(averaged=averaged, laplacian=lap, variance=var, top_left=top_left)


@dataclass(frozen=True, slots=True)
class MatchResult:
    """Outcome of :func:`match_templates` for T templates.

    Attributes:
        top_left: Best-match top-left corners (x, y) in the new frame, (T, 2) int64 [px].
        shift: Integer displacement new - old, (T, 2) int64 [px].
        ssd: Minimum sum of squared differences, (T,) float64 [DN^2].
        rel_ssd: ``ssd`` over the template's centred energy, (T,) float64 [-];
            about 2 for an unrelated patch of the same contrast.
        at_edge: True where the minimum lies on the search-window boundary (the
            true match may be outside it), (T,) bool.
    """

    top_left: np.ndarray
    shift: np.ndarray
    ssd: np.ndarray
    rel_ssd: np.ndarray
    at_edge: np.ndarray


def match_templates(
    prev_image: np.ndarray,
    image: np.ndarray,
    top_left: np.ndarray,
    template_size: tuple[int, int],
    search_radius: int,
    predicted_shift: np.ndarray | None = None,
) -> MatchResult:
    """Least-squares (SSD) block matching of templates into the next frame (§2.4).

    Each template ``prev_image[y:y+Wy, x:x+Wx]`` is compared with every
    placement whose top-left corner lies within ``search_radius`` of
    ``(x, y) + predicted_shift`` (clipped to the image), minimising
    ``sum (T - I)^2`` via ``cv2.matchTemplate(TM_SQDIFF)``.

    Rate: once per frame per template.

    Args:
        prev_image: Frame k holding the templates, (H, W) uint8 or float32.
        image: Frame k+1, same shape and dtype.
        top_left: Template corners (x, y) in frame k, (T, 2) int [px]; the
            templates must lie inside ``prev_image``.
        template_size: (Wx, Wy) [px].
        search_radius: Half-width of the square search window [px], >= 1.
        predicted_shift: Expected displacement (T, 2) int [px] (e.g. last
            frame's); None means zero.

    Returns:
        A :class:`MatchResult`.

    Raises:
        ValueError: If the two frames differ in shape or dtype, or a template
            is not inside ``prev_image``.
    """
    if prev_image.shape != image.shape or prev_image.dtype != image.dtype:
        raise ValueError(
            f"prev_image and image must share shape and dtype, got {prev_image.shape} {prev_image.dtype} "
            f"and {image.shape} {image.dtype}"
        )
    search_radius = _positive_int(search_radius, "search_radius")
    wx, wy = template_size
    height, width = image.shape
    top_left = np.asarray(top_left, dtype=np.int64).reshape(-1, 2)
    n_t = top_left.shape[0]
    if n_t and (
        top_left.min() < 0 or (top_left[:, 0] + wx).max() > width or (top_left[:, 1] + wy).max() > height
    ):
        raise ValueError(f"top_left templates of size {template_size} must lie inside the image {image.shape}")
    pred = np.zeros((n_t, 2), np.int64) if predicted_shift is None else np.asarray(predicted_shift, np.int64)
    return _match_core(prev_image, image, top_left, top_left + pred, wx, wy, search_radius)


def _match_core(
    prev_image: np.ndarray,
    image: np.ndarray,
    top_left: np.ndarray,
    centre: np.ndarray,
    wx: int,
    wy: int,
    radius: int,
) -> MatchResult:
    """:func:`match_templates` without argument checks (the tracker's hot
    path); ``centre`` is ``top_left + predicted_shift``."""
    height, width = image.shape
    xmax, ymax = width - wx, height - wy
    area = wx * wy
    best: list[tuple[int, int]] = []
    ssd: list[float] = []
    rel: list[float] = []
    edge: list[bool] = []
    # Plain Python ints and lists in the loop: NumPy scalar handling would
    # cost more than the tiny matchTemplate calls themselves.
    for (x, y), (cx, cy) in zip(top_left.tolist(), centre.tolist()):
        x0, x1 = min(max(cx - radius, 0), xmax), min(max(cx + radius, 0), xmax)
        y0, y1 = min(max(cy - radius, 0), ymax), min(max(cy + radius, 0), ymax)
        tpl = prev_image[y : y + wy, x : x + wx]
        res = cv2.matchTemplate(image[y0 : y1 + wy, x0 : x1 + wx], tpl, cv2.TM_SQDIFF)
        min_val, _, (mx, my), _ = cv2.minMaxLoc(res)
        bx, by = x0 + mx, y0 + my
        best.append((bx, by))
        min_val = max(min_val, 0.0)
        ssd.append(min_val)
        energy = cv2.meanStdDev(tpl)[1][0, 0] ** 2 * area
        rel.append(min_val / max(energy, TEMPLATE_ENERGY_FLOOR))
        # A minimum on a search limit that the image did not impose is suspect.
        edge.append(abs(bx - cx) == radius or abs(by - cy) == radius)
    best_arr = np.array(best, dtype=np.int64).reshape(-1, 2)
    return MatchResult(
        top_left=best_arr,
        shift=best_arr - top_left,
        ssd=np.array(ssd, dtype=np.float64),
        rel_ssd=np.array(rel, dtype=np.float64),
        at_edge=np.array(edge, dtype=bool),
    )


def match_one(
    image: np.ndarray, tpl: np.ndarray, cx: int, cy: int, radius: int, xmax: int, ymax: int
) -> tuple[int, int, float, bool, float, float]:
    """SSD block matching of one template (§2.4), plain Python scalars in and out
    (the tracker's hot path: no argument checks).

    Args:
        image: Frame k+1, (H, W), the dtype of ``tpl`` (uint8 or float32).
        tpl: Template cut from frame k, (Wy, Wx).
        cx, cy: Predicted top-left corner in frame k+1 [px].
        radius: Search half-width [px].
        xmax, ymax: Largest top-left corner inside the frame, W - Wx and H - Wy [px].

    Returns:
        (bx, by, ssd, at_edge, fx, fy): best top-left corner [px], its SSD
        [DN^2], whether it lies on a search limit that the image did not
        impose, and the sub-pixel offsets of the SSD minimum along x and y
        [px]: the vertex of the parabola through the minimum and its two
        neighbours on each axis (:func:`parabola_vertex`), 0 where the
        minimum lies on the border of the SSD map.
    """
    wy, wx = tpl.shape
    x0, x1 = min(max(cx - radius, 0), xmax), min(max(cx + radius, 0), xmax)
    y0, y1 = min(max(cy - radius, 0), ymax), min(max(cy + radius, 0), ymax)
    res = cv2.matchTemplate(image[y0 : y1 + wy, x0 : x1 + wx], tpl, cv2.TM_SQDIFF)
    min_val, _, (mx, my), _ = cv2.minMaxLoc(res)
    bx, by = x0 + mx, y0 + my
    at_edge = abs(bx - cx) == radius or abs(by - cy) == radius
    h, w = res.shape
    mid = min_val
    fx = parabola_vertex(float(res[my, mx - 1]), mid, float(res[my, mx + 1])) if 0 < mx < w - 1 else 0.0
    fy = parabola_vertex(float(res[my - 1, mx]), mid, float(res[my + 1, mx])) if 0 < my < h - 1 else 0.0
    return bx, by, max(min_val, 0.0), at_edge, fx, fy


def ssd_maps(windows: np.ndarray, templates: np.ndarray) -> np.ndarray:
    """SSD block matching (§2.4) of several templates at once, each inside its
    own search window: what ``cv2.matchTemplate(window, template, TM_SQDIFF)``
    gives for each pair, summed directly (the differences first, so the
    minimum is not lost to cancellation) in a few vectorised operations
    instead of one OpenCV call per template (whose fixed cost dominates at
    the tracker's +-1 px windows).

    Rate: once per frame, for all templates (the tracker's hot path).

    Args:
        windows: Search windows, (T, Wy + 2 ry, Wx + 2 rx) float32 [DN].
        templates: Templates, (T, Wy, Wx) float32 [DN].

    Returns:
        (T, 2 ry + 1, 2 rx + 1) float32 [DN^2]: ``out[t, j, i] = sum((windows[t,
        j:j+Wy, i:i+Wx] - templates[t]) ** 2)``.
    """
    n_t, wy, wx = templates.shape
    ny, nx = windows.shape[1] - wy + 1, windows.shape[2] - wx + 1
    assert windows.shape[0] == n_t and ny >= 1 and nx >= 1
    windows = np.ascontiguousarray(windows, dtype=np.float32)
    s0, s1, s2 = windows.strides
    # A read-only strided view of every placement (the ndarray constructor:
    # numpy's as_strided wrapper costs more than the subtraction here).
    placements = np.ndarray((n_t, ny, nx, wy, wx), np.float32, windows, 0, (s0, s1, s2, s1, s2))
    placements.flags.writeable = False
    diff = np.empty((n_t, ny, nx, wy, wx), np.float32)
    np.subtract(placements, templates.reshape(n_t, 1, 1, wy, wx), out=diff)
    flat = diff.reshape(n_t * ny * nx, 1, wy * wx)
    # Row-wise sums of squares as a stack of 1 x 1 matrix products: matmul's
    # dispatch costs about a third of einsum's at these sizes.
    return np.matmul(flat, flat.reshape(n_t * ny * nx, wy * wx, 1)).reshape(n_t, ny, nx)


def centred_energy(templates: np.ndarray, n_pixels: int | None = None) -> np.ndarray:
    """``sum((T - mean T) ** 2)`` of each template, (T, Wy, Wx) -> (T,) float64
    [DN^2] (the scale of :attr:`MatchResult.rel_ssd`).

    ``n_pixels``: the template's pixel count when ``templates`` carries zero
    padding (:func:`ssd_maps_rows`' layout: zeros add nothing to the sums);
    None: every element is a pixel."""
    n_t = templates.shape[0]
    flat = templates.reshape(n_t, 1, -1).astype(np.float64)
    s1 = flat.sum(axis=2).reshape(n_t)
    s2 = np.matmul(flat, flat.reshape(n_t, -1, 1)).reshape(n_t)
    return np.maximum(s2 - s1 * s1 / (flat.shape[2] if n_pixels is None else n_pixels), 0.0)


@functools.lru_cache(maxsize=8)
def _row_mask(wy: int, wx: int, row: int) -> np.ndarray:
    """(wy * row,) float32, 1 on the first wx elements of each row of ``row``. Read-only."""
    mask = np.zeros((wy, row), np.float32)
    mask[:, :wx] = 1.0
    mask = mask.reshape(-1)
    mask.flags.writeable = False
    return mask


def ssd_maps_rows(windows: np.ndarray, templates: np.ndarray, wy: int, wx: int, ry: int, rx: int) -> np.ndarray:
    """:func:`ssd_maps` with the windows and templates laid out so that every
    placement is one contiguous run of memory (the tracker's hot path: the
    subtraction then runs over long rows instead of Wx-element pieces).

    Layout (row = Wx + 2 rx, the window's width):

    * ``windows``: (T, (Wy + 2 ry) row + 2 rx) float32, each window's rows
      one after the other, then 2 rx finite padding elements (read by the
      last placements' masked tail);
    * ``templates``: (T, Wy row) float32, each template row followed by 2 rx
      zeros.

    Placement (j, i) of template t is then ``windows[t, j row + i : j row + i
    + Wy row]``, its element k lining up with template element k; elements
    in a template's padding columns pair with pixels outside the placement
    and are masked out of the sum (the squared differences times a 0/1 mask,
    summed by one matrix-vector product). Every sum of squared integer
    differences below 2^24 is exact in float32, whatever its order, so the
    values equal :func:`ssd_maps`' there (tested).

    Returns:
        (T, 2 ry + 1, 2 rx + 1) float32 [DN^2].
    """
    n_t = windows.shape[0]
    row = wx + 2 * rx
    length = wy * row
    ny, nx = 2 * ry + 1, 2 * rx + 1
    assert windows.shape[1] >= (wy + 2 * ry) * row + 2 * rx and templates.shape == (n_t, length)
    assert windows.dtype == np.float32 and windows.strides[1] == 4
    s0, s1 = windows.strides
    placements = np.ndarray((n_t, ny, nx, length), np.float32, windows, 0, (s0, row * s1, s1, s1))
    placements.flags.writeable = False
    diff = placements - templates.reshape(n_t, 1, 1, length)
    np.square(diff, out=diff)
    return np.matmul(diff.reshape(n_t * ny * nx, length), _row_mask(wy, wx, row)).reshape(n_t, ny, nx)


def parabola_vertex(lo: float, mid: float, hi: float) -> float:
    """Offset [px] of the vertex of the parabola through (-1, lo), (0, mid),
    (1, hi), clamped to +-0.5; 0 where the three values do not curve upwards.

    Sub-pixel refinement of an SSD minimum (``mid`` the smallest of the three)."""
    curv = lo - 2.0 * mid + hi
    if curv <= 0.0:
        return 0.0
    return min(max(0.5 * (lo - hi) / curv, -0.5), 0.5)
