"""The fixation-area feature tracker (paper Fig. 1): images in, tracks out.

Per frame (Step 1-3 of the paper):

1. **Fixation areas** (§2). N templates (Wx x Wy pixels of the full frame) are
   kept. Each is found again in the new frame by least-squares block matching
   (:func:`vision.fixation.match_one`) inside a search window centred on
   its constant-velocity prediction; a parabola through the SSD minimum and
   its neighbours refines the displacement to sub-pixel. A template that is
   lost (SSD too large relative to its contrast, minimum on the search-window
   edge) or that comes close to the
   image edge is dropped, and replacements are chosen from the variance map of
   the current frame (:func:`block_average` -> :func:`laplacian8` ->
   :func:`variance_map` -> :func:`select_templates`), away from the border and
   from the other templates.
2. **Feature points** (§3) are detected only inside the templates (the
   "sub-images") with the square-root-free min-eigenvalue test of eq. (3.4)
   and non-maximum suppression (:func:`vision.features.detect_in_subimages`).
3. **Tracking** (§4). Every feature is refined to sub-pixel accuracy by
   iterative Lucas-Kanade (eqs. 4.5-4.7) in a small window, seeded by the
   block matching -- which plays the role of the image pyramid, so large
   motions still converge: a new feature starts at its template's sub-pixel
   displacement, an older one at its own last displacement plus the change of
   its template's displacement (``lk_seed``). It is kept only if tracking it
   back (in a ``fb_window`` window) lands within ``fb_max_px`` of its start
   (forward-backward check).
   Tracks keep their id for life; when the live tracks fall below
   ``redetect_below_frac`` of what the templates held after their last
   detection, the templates are topped up with new points.

Only image-processing happens here: no truth, no simulator.

Cost: per frame, one vectorised SSD pass over every template's narrow
search window (:func:`vision.fixation.ssd_maps`; ``cv2.matchTemplate`` only
for the rarer re-searches) and two single-level LK passes (the backward one in a smaller window) over mosaics
of the sub-images (not the whole frame);
the variance map and feature detection run only when templates are replaced
or tracks run low. The per-frame cost therefore hardly grows with the frame
size -- the paper's point that detecting and tracking inside sub-images saves
computation.

LK backend: by default the LK iteration runs through
``cv2.calcOpticalFlowPyrLK(maxLevel=0, OPTFLOW_USE_INITIAL_FLOW)`` seeded by
block matching (:func:`vision.lk.forward_backward_opencv_fast`), because it
measured about 3x faster than the NumPy reference :func:`vision.lk.lucas_kanade`
for ~100 points (0.26 vs 0.80 ms per forward-backward pass on 2 cores); the
two are tested to agree on the same inputs, and ``lk_backend="numpy"``
selects the reference. OpenCV's LK is 8-bit only, so with that backend
float32 frames are rounded to uint8 after scaling.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from vision.features import detect_in_subimages, detection_margin
from vision.fixation import (
    TEMPLATE_ENERGY_FLOOR,
    FixationAreas,
    centred_energy,
    fixation_areas,
    match_one,
    ssd_maps,
    ssd_maps_rows,
)
from vision.lk import (
    affine_from_moments,
    forward_backward,
    forward_backward_opencv_ok,
    forward_opencv_fast,
    lk_bias,
    lk_bias_gain,
    seeded_lk_kwargs,
)
from vision.tracks import Tracks, check_image

TEMPLATE_SIZE_MAX = 256
"""Largest template side [px] (``TrackerConfig.template_size``, also for frames scaled up)."""

LK_BIAS_AUTO_MIN_SIDE_PX = 256
"""``lk_affine_correction = "auto"`` corrects the LK bias in frames whose shorter side exceeds this [px]."""

FP_WINDOW_MAX = 15
"""Largest odd W1 [px] (``TrackerConfig.fp_window``, also for frames scaled up)."""

FULL_SCALE_DN = 255.0
"""8-bit full scale [DN]: the intensity scale every threshold is expressed in."""
_F32_MAX = float(np.finfo(np.float32).max)  # largest finite float32 [DN]

TILE_GUARD_PX = 2
"""Extra tile rows/columns around the LK window: one for the derivative ring,
one for the bilinear neighbour."""

FP_BOX_SLACK_FRAC = 0.25
"""A feature is dropped when it drifts further than this fraction of the
template size outside its template (it no longer belongs to the sub-image, and
its template's displacement no longer predicts its own)."""


def lk_tile_margin(template_size: int, lk_window: int) -> int:
    """Rows/columns [px] an LK tile adds on each side of its template: the
    drift slack, half the LK window and the guard. A tile is
    ``template_size + 2 * margin`` px square."""
    return math.ceil(FP_BOX_SLACK_FRAC * template_size) + lk_window // 2 + TILE_GUARD_PX


def _match_region(
    img: np.ndarray, tpl: np.ndarray, cx: int, cy: int, radius: int, xmax: int, ymax: int
) -> tuple[int, int, float, bool, float, float]:
    """:func:`vision.fixation.match_one` of a float32 template in a frame of
    any dtype: only the search region (clipped to the frame as match_one
    clips it) is converted to float32, not the whole frame."""
    wy, wx = tpl.shape
    x0, x1 = min(max(cx - radius, 0), xmax), min(max(cx + radius, 0), xmax)
    y0, y1 = min(max(cy - radius, 0), ymax), min(max(cy + radius, 0), ymax)
    region = img[y0 : y1 + wy, x0 : x1 + wx].astype(np.float32)
    bx, by, ssd, at_edge, fx, fy = match_one(region, tpl, cx - x0, cy - y0, radius, x1 - x0, y1 - y0)
    return bx + x0, by + y0, ssd, at_edge, fx, fy


def _map_minimum(vals: list[float], n_side: int, x0: int, y0: int) -> tuple[int, int, float, bool, float, float]:
    """:func:`vision.fixation.match_one`'s verdict on an SSD map already
    computed: ``vals`` is the (n_side x n_side) map in raster order (plain
    floats), its placement (0, 0) at top-left corner (x0, y0). The first
    minimum in raster order, ``at_edge`` on the map's border, and the
    parabola through the minimum and its neighbours on each axis
    (:func:`vision.fixation.parabola_vertex`, inlined).

    Returns:
        (bx, by, ssd, at_edge, fx, fy) as match_one.
    """
    mid = min(vals)
    k = vals.index(mid)
    my, mx = divmod(k, n_side)
    last = n_side - 1
    fx = fy = 0.0
    if 0 < mx < last:
        lo, hi = vals[k - 1], vals[k + 1]
        curv = lo - 2.0 * mid + hi
        if curv > 0.0:
            fx = min(max(0.5 * (lo - hi) / curv, -0.5), 0.5)
    if 0 < my < last:
        lo, hi = vals[k - n_side], vals[k + n_side]
        curv = lo - 2.0 * mid + hi
        if curv > 0.0:
            fy = min(max(0.5 * (lo - hi) / curv, -0.5), 0.5)
    at_edge = mx == 0 or my == 0 or mx == last or my == last
    return x0 + mx, y0 + my, (mid if mid > 0.0 else 0.0), at_edge, fx, fy


def _match_near(
    img: np.ndarray, tpl: np.ndarray, cx: int, cy: int, radius: int, xmax: int, ymax: int
) -> tuple[int, int, float, bool, float, float]:
    """:func:`_match_region` for a narrow search: where the search window is
    inside the frame, the SSD map comes from :func:`vision.fixation.ssd_maps`
    (exact sums, a few microseconds) instead of ``cv2.matchTemplate`` (whose
    fixed cost per call is several times that); near the frame edge it is
    :func:`_match_region`, which clips the window."""
    wy, wx = tpl.shape
    if radius <= cx <= xmax - radius and radius <= cy <= ymax - radius:
        x0, y0 = cx - radius, cy - radius
        win = img[y0 : cy + radius + wy, x0 : cx + radius + wx].astype(np.float32)
        vals = ssd_maps(win[None], tpl[None]).reshape(-1).tolist()
        return _map_minimum(vals, 2 * radius + 1, x0, y0)
    return _match_region(img, tpl, cx, cy, radius, xmax, ymax)


def _median_rows(a: np.ndarray) -> np.ndarray:
    """Column-wise median of a small (n >= 1, k) array (``np.median`` costs ~10x
    more on arrays this small)."""
    s = np.sort(a, axis=0)
    n = s.shape[0]
    return 0.5 * (s[(n - 1) // 2] + s[n // 2])


def _affine_from_templates(kept: list[tuple]) -> np.ndarray | None:
    """The motion gradient ``A`` (2, 2) [-] fitted to the kept templates' block-matching
    displacements ``(t, bx, by, sx, sy)``: ``s = c + A (b - s)`` over their old top-left
    corners ``b - s`` (None: fewer than four, on a line, or too large; as
    :func:`vision.lk.affine_from_moments`, the moments in plain floats: seven points cost less than arrays)."""
    n = len(kept)
    if n < 4:
        return None
    mx = my = mu = mv = 0.0
    for _, bx, by, sx, sy in kept:
        mx += bx - sx
        my += by - sy
        mu += sx
        mv += sy
    mx, my, mu, mv = mx / n, my / n, mu / n, mv / n
    sxx = sxy = syy = bxx = bxy = byx = byy = 0.0
    for _, bx, by, sx, sy in kept:
        x, y, u, v = bx - sx - mx, by - sy - my, sx - mu, sy - mv
        sxx += x * x
        sxy += x * y
        syy += y * y
        bxx += x * u
        bxy += x * v
        byx += y * u
        byy += y * v
    return affine_from_moments(sxx, sxy, syy, bxx, bxy, byx, byy)


def similarity_prediction(xy: np.ndarray, disp: np.ndarray, new_xy: np.ndarray) -> np.ndarray:
    """Displacements at ``new_xy`` (M, 2) predicted by the least-squares
    similarity motion field d(x) = t + [[a, -b], [b, a]] (x - m) of the
    displacements ``disp`` (K, 2) observed at ``xy`` (K, 2) [px]: a
    translation, a uniform scale change and a rotation, the image motion of
    a descent over flat ground with a nadir camera. m and t are the means of
    ``xy`` and ``disp``; (a, b) minimise the squared residuals in closed form.
    With fewer than two points, or points spread less than one pixel (RMS),
    it is the mean displacement (zero without points). Plain Python on the
    few templates: NumPy's fixed cost per call would dominate.

    Returns:
        (M, 2) float64 [px].
    """
    a, b, (mx, my), (tx, ty) = similarity_field(xy, disp)
    r = new_xy - (mx, my)
    return np.column_stack([tx + a * r[:, 0] - b * r[:, 1], ty + b * r[:, 0] + a * r[:, 1]])


def similarity_field(xy: np.ndarray, disp: np.ndarray) -> tuple[float, float, tuple[float, float], tuple[float, float]]:
    """The (a, b, m, t) of :func:`similarity_prediction`'s field (a = b = 0
    and t the mean, or zero, where it falls back)."""
    k = xy.shape[0]
    if k == 0:
        return 0.0, 0.0, (0.0, 0.0), (0.0, 0.0)
    pts, ds = xy.tolist(), disp.tolist()
    mx, my = sum(p[0] for p in pts) / k, sum(p[1] for p in pts) / k
    tx, ty = sum(d[0] for d in ds) / k, sum(d[1] for d in ds) / k
    qq = qu = qv = 0.0
    for (x, y), (dx, dy) in zip(pts, ds):
        qx, qy, ux, uy = x - mx, y - my, dx - tx, dy - ty
        qq += qx * qx + qy * qy
        qu += qx * ux + qy * uy
        qv += qx * uy - qy * ux
    if k < 2 or qq < k:
        return 0.0, 0.0, (mx, my), (tx, ty)
    return qu / qq, qv / qq, (mx, my), (tx, ty)


class TrackerConfig(BaseModel):
    """Parameters of :class:`Tracker` (pixel units refer to the full frame).

    Defaults follow the paper where it gives values (Sx = Sy = 5, W1 = 3) and
    were otherwise chosen with ``landbench track-eval`` (the rendered descent
    at 256^2 and 512^2, against truth and the OpenCV baseline, interleaved in
    one process) and checked on recorded closed-loop descents (README,
    "Vision"):

    * 7 templates of 30 x 30 px, up to 15 points each (~90 tracks): every
      template costs one block-matching call per frame and a share of the
      refills, so a few well-filled sub-images are cheaper than many sparse
      ones; larger sub-images hold more strong points to choose from (the
      paper's 20 x 20 gave 0.077 px median error against the baseline's 0.064
      at 256^2). A separation of 20 % of the shorter image side spreads them
      over the frame (paper §2.3 b);
    * lambda_t = 10 DN^2 (30 until the thirty-sixth session): the paper's
      1500 suits its high-contrast imagery; soft, low-sun lunar texture
      rendered at 256^2 gives lambda_1 of a few tens to hundreds over a 3 x 3
      patch. The threshold only decides how many candidates a sub-image has
      before its strongest fifteen are taken: the rendered descents, the
      default landing and a 20-case campaign are identical at 10 and 30; on
      smooth photographs (the Moon, coffee, a rocket) 30 left templates with
      fewer than fifteen points and the tracks under the baseline's (Moon
      67 against 83 a frame at 256^2, 90 at 10);
    * LK window 13 px: LK's error is the detector noise over the gradient
      energy of its window, and 13 px halves the gap to the baseline that 9 px
      left; the forward-backward check's backward solve uses 9 px
      (``fb_window``), which rejects the same mis-tracks at half the cost;
    * block matching searches +-1 px around the constant-velocity prediction
      (following a minimum on its edge up to ``search_follow_steps`` = 4 times:
      one narrow SSD map each, against about ten for the wide search), then
      +-12 px; the displacement is refined
      to sub-pixel, and LK starts from each track's own last displacement
      plus the change of its template's displacement, so it has ~0.1 px to
      find;
    * lost templates are replaced two at a time (``refill_min_missing``):
      each replacement costs a variance-map pass;
    * LK stops at updates below 0.03 px: the bilinear-interpolation bias is of
      that size, and iterating further did not improve the endpoint error.
      Stopping at 0.05 px and the backward solve after 3 iterations cost
      ~10-20 % less LK time at the same median error on the rendered
      descents, but on 10 closed-loop cases the vision NIS at 400-600 m rose
      (1.19 against 1.10 per dof, 17 against 13 measurements gated out), so
      ``fb_eps_px`` stays an option. The backward solve alone capped at 4
      iterations (``fb_max_iter``, twenty-fourth session) takes 4-10 % off
      the tracker's time in a process that rendered nothing (about 2 % in
      ``track-eval``'s, which rendered the descent) with the same or smaller
      median error and as many tracks (rendered, held-out and 512^2
      descents, photographs), and on 10 closed-loop cases (seed 1) the
      vision NIS at 400-600 m fell (0.78 against 0.87 per dof, 5 against 7
      gated out): it starts at the forward result minus the seed, a few
      hundredths of a pixel from where a good track's round trip closes;
    * forward-backward limit 0.5 px rejects mis-tracks well before the 1 px
      accuracy requirement. Without the check (``fb_check=False``: one LK pass
      validated against its seed and residual) the tracker is as accurate on
      the rendered descent, but on recorded closed-loop descents the vision
      measurement's NIS at 400-600 m and its gated-out measurements rose;
    * the 256^2 margin round (README, "Margin at 256^2"), checked on the rendered
      descent, the held-out one, three more unseen seeds and suns, and the
      photographs: non-maximum suppression radius 1 instead of 2 (the
      strongest corners of a sub-image sit close together; radius 2 traded
      them for weaker, spread-out ones), the reported position blended 0.3
      of the way towards the backward solve's estimate (``fb_blend``: the
      13 px window is the better one against noise, the 9 px one against the
      scale change across the window in a descent; on the photographs it cut
      the median error by a twentieth), templates kept up to an SSD of 0.6
      x their energy instead of 0.5 (on low-contrast, low-sun frames the 0.5
      limit dropped templates still matched in place), a template whose
      narrow-search minimum is inside its window but matches poorly dropped
      at once instead of searched over +-12 px (``wide_search_on_poor_match``:
      on every sequence tried the wide search never saved one; it was most of
      the wide searches on the held-out descent), and
      new templates predicted from the similarity motion field of the others
      (``new_template_seed``) instead of their median;
    * the LK bias correction (``lk_affine_correction``, thirty-sixth session):
      a translational window on a descent's zoom returns the gradient-weighted
      mean of the displacement over the window, ``G^-1 sum g g^T A (x - xy)``
      off the point's own (the texture's gradient energy is rarely centred on
      it); with A fitted to the templates' displacements the bias of the
      reported position (the blend of the two windows' solves) is taken out.
      On the photographs it takes the median error from 0.047 to 0.030 px at
      256^2 and from 0.052 to 0.026 at 512^2 (the baseline 0.043 and 0.046),
      on the rendered descents 10-20 % off. It costs 30-40 us a frame (the
      gains are recomputed every ``lk_bias_refresh_frames`` frames and when
      tracks are added): 11-14 % of the tracker's time at 256^2, which would
      spend most of the time margin over the baseline there, so ``"auto"``
      turns it on only in larger frames. The blend stays: on a featureless
      mare at 512^2 the correction without it safe-aborted 3 of 20 cases
      against 1 (the blend's averaging of two solves keeps the vision
      measurement in its gate); the correction corrects the blended position.

    Re-detection is adaptive: it runs when the live tracks fall below
    ``redetect_below_frac`` of what the templates held after their last
    detection (a fixed target would re-detect every frame on sparse texture).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    subsample_x: int = Field(5, ge=1, le=64, description="Sx, block-averaging interval along x, eq. (2.1) [px]")
    subsample_y: int = Field(5, ge=1, le=64, description="Sy, block-averaging interval along y, eq. (2.1) [px]")
    template_size: int = Field(
        30, ge=5, le=TEMPLATE_SIZE_MAX, description="Wx = Wy, side of a template / sub-image [px]; a multiple of Sx and Sy"
    )
    n_templates: int = Field(7, ge=1, le=256, description="N, number of templates kept in track [-]")
    template_separation_frac: float = Field(
        0.2, ge=0.0, le=1.0, description="minimum distance between template centres / shorter image side [-]"
    )
    border_px: int = Field(
        21,
        ge=0,
        description="new templates keep at least this distance to the image edge [px]; >= edge_margin_px and "
        ">= ceil(template_size / 4) + lk_window // 2 + 2 (the LK tile margin)",
    )
    edge_margin_px: int = Field(
        8, ge=0, description="a template closer than this to the image edge is leaving the image and replaced [px]"
    )
    min_template_variance: float = Field(
        1.0, ge=0.0, description="least Laplacian variance V, eq. (2.2), of a template [DN^2]; flat areas get none"
    )
    refill_min_missing: int = Field(
        2,
        ge=1,
        description="lost templates are replaced once this many are missing (or tracks run low) [-]; "
        "batching replacements saves variance-map passes",
    )
    search_radius_px: int = Field(
        12, ge=1, le=128, description="half-width of the block-matching search window around the prediction [px]"
    )
    search_radius_near_px: int = Field(
        1, ge=1, le=128,
        description="first, narrow search half-width around the constant-velocity prediction [px]; a template "
        "whose minimum lands on its edge or fails max_rel_ssd is searched again over search_radius_px",
    )
    search_follow_steps: int = Field(
        4, ge=1, le=32,
        description="times the narrow search moves to a minimum on its window's edge and searches around it "
        "again before falling back to search_radius_px (each move is one narrow SSD map; the wide search "
        "costs about ten) [-]",
    )
    wide_search_on_poor_match: bool = Field(
        False,
        description="a template whose narrow-search minimum lies inside its window but fails max_rel_ssd is "
        "searched again over search_radius_px (True), or dropped at once (False: its appearance changed; a "
        "minimum inside the window is where it went) [-]",
    )
    max_rel_ssd: float = Field(
        0.6, gt=0.0, description="template lost if min SSD / template centred energy exceeds this [-] (~2: unrelated)"
    )
    fp_window: int = Field(3, ge=1, le=FP_WINDOW_MAX, description="W1, patch side for G, eq. (3.3) [px]; odd")
    lambda_t: float = Field(10.0, ge=0.0, description="lambda_t, min-eigenvalue threshold of eq. (3.4) [DN^2]")
    fp_nms_radius: int = Field(1, ge=0, le=10, description="non-maximum suppression radius for feature points [px]")
    max_features_per_template: int = Field(15, ge=1, le=256, description="most feature points per sub-image [-]")
    fp_search: Literal["exhaustive", "random"] = Field(
        "exhaustive", description="feature search strategy (§3): exhaustive (paper's choice) or random [-]"
    )
    min_track_separation_px: float = Field(
        3.0, ge=0.0, description="new points closer than this to a live track are not added [px]"
    )
    lk_backend: Literal["opencv", "numpy"] = Field(
        "opencv", description="LK solver: OpenCV single-level LK (fast) or the NumPy reference of eqs. (4.5)-(4.7) [-]"
    )
    lk_window: int = Field(13, ge=3, le=31, description="LK window side [px]; odd")
    lk_max_iter: int = Field(20, ge=1, le=100, description="LK iteration cap [-]")
    lk_eps_px: float = Field(
        0.03, gt=0.0, le=1.0, description="LK stops when the update is below this [px] (bilinear bias is ~0.03 px)"
    )
    lk_min_eig: float = Field(
        1e-2, ge=0.0, description="least min-eigenvalue of G per window pixel for a valid LK solve [DN^2/px^2]"
    )
    subpixel_match: bool = Field(
        True, description="refine the block-matching displacement to sub-pixel by a parabola through the SSD "
        "minimum and its neighbours [-]"
    )
    lk_seed: Literal["track", "template"] = Field(
        "track",
        description="LK starting displacement: 'track' = the track's own last displacement plus the change of its "
        "template's block-matching displacement (new tracks: the template's); 'template' = the template's "
        "block-matching displacement [-]",
    )
    new_template_seed: Literal["median", "similarity"] = Field(
        "similarity",
        description="block-matching prediction of a new template's first displacement: 'median' = the median of "
        "the other templates' last displacements; 'similarity' = the least-squares similarity motion field "
        "(translation, scale, rotation) of the other templates' displacements, at the new template's centre "
        "(a descent's zoom moves templates near the edge faster than the median) [-]",
    )
    template_lookahead_frames: int = Field(
        0, ge=0, le=1000,
        description="new templates are taken first (in decreasing variance) among the areas that the similarity "
        "motion field of the templates in track (see new_template_seed) keeps at least edge_margin_px inside the "
        "frame for this many frames, then among the others; 0: no preference (the paper's selection) [frames]",
    )
    fb_max_px: float = Field(0.5, gt=0.0, description="largest forward-backward round-trip error kept [px]")
    fb_check: bool = Field(
        True, description="validate each LK result by tracking it back (forward-backward check, fb_max_px); "
        "False: one LK pass, validated against its seed (max_seed_deviation_px) and its residual "
        "(max_residual_dn) [-]"
    )
    fb_window: int | None = Field(
        9, ge=3, le=31,
        description="LK window of the backward solve of the forward-backward check [px]; odd; the smaller of "
        "this and lk_window is used (None: lk_window)",
    )
    fb_blend: float = Field(
        0.3, ge=0.0, le=1.0,
        description="sub-pixel refinement from the forward-backward check: the track's new position is the forward "
        "LK solution minus this fraction of the round trip (back-tracked point - start), i.e. (1 - w) x the "
        "forward (lk_window) displacement + w x the backward (fb_window) one; 0: the forward solution [-]",
    )
    lk_affine_correction: Literal["auto", "on", "off"] = Field(
        "auto",
        description="sub-pixel refinement: each track's position (the forward-backward blend) less the bias that "
        "its translational windows take from the frame's motion gradient A (a descent's zoom and turn across the "
        "window), b = G^-1 sum g g^T A (x - xy) per window (vision.lk.lk_bias_gain), A fitted to the templates' "
        "block-matching displacements (none with fewer than four templates); 'auto': on for frames whose shorter "
        f"side exceeds {LK_BIAS_AUTO_MIN_SIDE_PX} px, off at and below it, where its cost (11-14 % of the "
        "tracker's time) would spend the tracker's time lead over the OpenCV baseline [-]",
    )
    lk_bias_refresh_frames: int = Field(
        8, ge=1, le=1000,
        description="with the LK bias correction: every track's bias gain (which depends only on the texture around "
        "it, carried with it) is recomputed every this many frames, and at the first solve after new tracks "
        "were added [frames]",
    )
    fb_max_iter: int | None = Field(
        4, ge=1, le=100, description="iteration cap of the backward solve of the forward-backward check [-] "
        "(None: lk_max_iter)",
    )
    fb_eps_px: float | None = Field(
        None, gt=0.0, le=1.0, description="the backward solve stops when its update is below this [px] "
        "(None: lk_eps_px)",
    )
    max_seed_deviation_px: float = Field(
        0.6, gt=0.0, description="without fb_check: largest distance of an LK result from its seed [px]"
    )
    max_residual_dn: float = Field(
        8.0, gt=0.0, description="without fb_check: largest mean absolute difference of the aligned LK windows [DN]"
    )
    redetect_below_frac: float = Field(
        0.75,
        ge=0.0,
        le=1.0,
        description="re-detect when live tracks < this x the tracks the templates held after their last detection [-]",
    )
    float_full_scale: float = Field(
        255.0, gt=0.0, description="value of full white in float32 input frames (1.0 for [0, 1] images) [DN]"
    )
    reference_side_px: int | None = Field(
        256, ge=16,
        description="the sub-image geometry (template_size, border_px, fp_window, lambda_t) is given for frames "
        "of this shorter side; larger frames scale it up by side / reference_side_px (see TrackerConfig.for_side), "
        "smaller ones use it as given; None: used as given at every size [px]",
    )

    @model_validator(mode="after")
    def _check_consistency(self) -> TrackerConfig:
        if self.template_size % self.subsample_x or self.template_size % self.subsample_y:
            raise ValueError(
                f"template_size ({self.template_size}) must be a multiple of subsample_x ({self.subsample_x}) "
                f"and subsample_y ({self.subsample_y}) so the variance window of eq. (2.2) is whole"
            )
        if self.fp_window % 2 == 0:
            raise ValueError(f"fp_window (W1) must be odd, got {self.fp_window}")
        if self.lk_window % 2 == 0:
            raise ValueError(f"lk_window must be odd, got {self.lk_window}")
        if self.fb_window is not None and self.fb_window % 2 == 0:
            raise ValueError(f"fb_window must be odd, got {self.fb_window}")
        need = max(detection_margin(self.fp_window), self.lk_window // 2 + 2)
        if self.edge_margin_px < need:
            raise ValueError(
                f"edge_margin_px ({self.edge_margin_px}) must be >= {need} so detection and LK windows fit "
                f"(fp_window={self.fp_window}, lk_window={self.lk_window})"
            )
        if self.border_px < self.edge_margin_px:
            raise ValueError(f"border_px ({self.border_px}) must be >= edge_margin_px ({self.edge_margin_px})")
        # Templates are placed only in frames of at least template_size +
        # 2 border_px; the LK tile around one must fit in such a frame.
        tile_margin = lk_tile_margin(self.template_size, self.lk_window)
        if self.border_px < tile_margin:
            raise ValueError(
                f"border_px ({self.border_px}) must be >= {tile_margin} = ceil({FP_BOX_SLACK_FRAC} x template_size) "
                f"+ lk_window // 2 + {TILE_GUARD_PX}, so the LK tile around a template fits in every frame that "
                f"holds one (template_size={self.template_size}, lk_window={self.lk_window})"
            )
        return self

    def corrects_lk_bias(self, side_px: int) -> bool:
        """Whether frames of shorter side ``side_px`` [px] get the LK bias correction: 'on', or
        'auto' in frames larger than ``LK_BIAS_AUTO_MIN_SIDE_PX``."""
        if self.lk_affine_correction == "auto":
            return side_px > LK_BIAS_AUTO_MIN_SIDE_PX
        return self.lk_affine_correction == "on"

    def subpixel_setup(self, side_px: int) -> dict[str, object]:
        """How frames of shorter side ``side_px`` are refined to sub-pixel: ``{"lk_bias_correction":
        bool, "fb_blend": float}`` (for reports; the blend is 0 without the forward-backward check, which
        it needs)."""
        blend = self.fb_blend if self.fb_check else 0.0
        return {"lk_bias_correction": self.corrects_lk_bias(side_px), "fb_blend": blend}

    @property
    def target_tracks(self) -> int:
        """Number of tracks the tracker aims for (N x points per template)."""
        return self.n_templates * self.max_features_per_template

    def for_side(self, side_px: int) -> TrackerConfig:
        """The configuration a frame of shorter side ``side_px`` is tracked with.

        With ``reference_side_px`` set and a larger frame, the sub-images keep
        their share of the frame and their points their share of a sub-image:
        for k = side_px / reference_side_px > 1, ``template_size`` becomes k x template_size rounded
        to a multiple of Sx and Sy, ``border_px`` round(k x border_px) (at
        least the LK tile margin), ``fp_window`` (W1) the odd size nearest
        k x W1, and ``lambda_t`` scales with W1's area (G sums over W1^2
        pixels). The template and W1 stop at their fields' limits
        (``TEMPLATE_SIZE_MAX``, ``FP_WINDOW_MAX``), and ``edge_margin_px`` grows
        to W1's detection margin where that is larger. For frames no larger than the reference, or with
        ``reference_side_px`` None, it is this configuration (smaller
        sub-images would not hold the detection and LK windows). The result has ``reference_side_px`` None and is
        validated as any other.
        """
        if self.reference_side_px is None or side_px <= self.reference_side_px:
            return self
        k = side_px / self.reference_side_px
        block = math.lcm(self.subsample_x, self.subsample_y)
        size = min(max(block, block * round(k * self.template_size / block)), block * (TEMPLATE_SIZE_MAX // block))
        w1 = min(2 * max(round(k * (self.fp_window - 1) / 2), 0) + 1, FP_WINDOW_MAX)
        edge = max(self.edge_margin_px, detection_margin(w1))
        border = max(round(k * self.border_px), edge, lk_tile_margin(size, self.lk_window))
        return TrackerConfig.model_validate({
            **self.model_dump(), "template_size": size, "border_px": border, "fp_window": w1, "edge_margin_px": edge,
            "lambda_t": self.lambda_t * (w1 / self.fp_window) ** 2, "reference_side_px": None,
        })


class Tracker:
    """Fixation-area + feature-point tracker of the paper.

    Input: a grayscale frame (H, W) uint8 or float32 per call to :meth:`step`.
    Output: :class:`vision.tracks.Tracks` for that frame.
    State: the previous frame, the templates and the live tracks.
    Rate: camera frame rate (one call per frame, frames in time order).
    Cost (2-core x86, single OpenCV thread, ``landbench track-eval``, each
    tracker interleaved with the OpenCV baseline in one process): about 0.78x
    the baseline's time at 256^2 and 0.56x at 512^2 on the rendered descent,
    0.81x and 0.62x on the held-out one (README, "Margin at 256^2").
    Shares at 256^2: LK about 40 %, refills and re-detection about 15 %,
    block matching about 12 %, the rest the Python and small NumPy
    operations of the per-frame step.

    Args:
        config: A :class:`TrackerConfig` (defaults when None).
        rng: Generator for the random search strategy (required with
            ``fp_search="random"``; the bench passes the run's "tracker"
            stream). Never NumPy's global state.
    """

    def __init__(self, config: TrackerConfig | None = None, rng: np.random.Generator | None = None) -> None:
        if config is None:
            config = TrackerConfig()
        if not isinstance(config, TrackerConfig):
            raise ValueError(f"config must be a TrackerConfig, got {type(config).__name__}")
        if rng is not None and not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy.random.Generator or None, got {type(rng).__name__}")
        if config.fp_search == "random" and rng is None:
            raise ValueError(
                "fp_search='random' needs rng: pass Tracker(config, rng=numpy.random.default_rng(seed)) "
                "(randomness only comes from a Generator passed in)"
            )
        self.config = config
        self._rng_arg = rng
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the previous frame, templates and tracks; ids restart at 0."""
        self._rng = self._rng_arg
        self._prev: np.ndarray | None = None
        self._tpl_xy = np.zeros((0, 2), np.int64)  # template top-left corners (x, y) [px]
        self._tpl_pred = np.zeros((0, 2), np.int64)  # predicted next displacement (last one, rounded) [px]
        self._tpl_sub = np.zeros((0, 2), np.float64)  # last (sub-pixel) block-matching displacement [px]
        self._tpl_expect = np.zeros(0, np.int64)  # tracks each template held after its last detection
        self._ids = np.zeros(0, np.int64)
        self._xy = np.zeros((0, 2), np.float64)
        self._age = np.zeros(0, np.int64)
        self._flow = np.zeros((0, 2), np.float64)  # last displacement of each track (new: its template's) [px]
        self._gain = np.zeros((0, 2, 4), np.float64)  # each track's LK bias gain (lk_affine_correction) [px]
        self._gain_steps = -1  # steps since every track's bias gain was computed (-1: due now)
        self._correct_bias = False  # config_for: whether this frame size gets the LK bias correction
        self._tpl_of = np.zeros(0, np.int64)  # index of each track's template
        self._next_id = 0
        self._mos_cache: tuple | None = None  # (frame, its LK mosaic, tile corners) of the last step
        self._cfg: TrackerConfig | None = None  # the configuration for this sequence's frame size

    def config_for(self, shape: tuple[int, ...]) -> TrackerConfig:
        """The configuration frames of ``shape`` (H, W) are tracked with:
        :meth:`TrackerConfig.for_side` of the shorter side (fixed by the first
        frame until :meth:`reset`)."""
        if self._cfg is None or self._prev is None:
            cfg = self._cfg = self.config.for_side(int(min(shape[:2])))
            back_window = cfg.lk_window if cfg.fb_window is None else min(cfg.fb_window, cfg.lk_window)
            # New sub-images keep their centres template_separation_frac x side
            # from the others (Chebyshev: that / sqrt 2), so points inside two
            # of them are at least that minus template_size apart.
            gap = cfg.template_separation_frac * min(shape[:2]) / math.sqrt(2.0) - cfg.template_size
            self._merge_top_up = gap >= cfg.min_track_separation_px
            self._correct_bias = self.config.corrects_lk_bias(int(min(shape[:2])))
            self._lk_kwargs = seeded_lk_kwargs(
                cfg.lk_window, cfg.lk_max_iter, cfg.lk_eps_px, cfg.lk_min_eig, back_window,
                back_max_iter=cfg.fb_max_iter, back_eps=cfg.fb_eps_px,
            )
        return self._cfg

    @property
    def templates(self) -> np.ndarray:
        """Current template top-left corners (x, y), (T, 2) int64 [px]."""
        return self._tpl_xy.copy()

    @property
    def track_templates(self) -> np.ndarray:
        """Template index (into :attr:`templates`) of each current track, (N,) int64."""
        return self._tpl_of.copy()

    # ------------------------------------------------------------------- step
    def _prepare(self, image: object) -> np.ndarray:
        img = check_image(image)
        if img.dtype == np.float32:
            if self.config.float_full_scale != FULL_SCALE_DN:
                # Scaled in float64 and clipped to float32's range: a full scale of 1e-38 or a frame of 1e38
                # would overflow float32 (inf, and 0 * inf = NaN) and lose every track.
                img = np.multiply(img, FULL_SCALE_DN / self.config.float_full_scale, dtype=np.float64)
                img = np.clip(img, -_F32_MAX, _F32_MAX).astype(np.float32)
            if self.config.lk_backend == "opencv":
                img = np.clip(np.rint(img), 0, FULL_SCALE_DN).astype(np.uint8)
        if self._prev is not None and img.shape != self._prev.shape:
            raise ValueError(
                f"image shape changed from {self._prev.shape} to {img.shape}; call reset() between sequences"
            )
        # Keep our own copy: the caller may reuse its buffer for the next frame.
        return np.array(img, copy=True, order="C")

    def step(self, image: np.ndarray) -> Tracks:
        """Process one frame.

        Args:
            image: Grayscale frame, (H, W) uint8 or float32 [DN] (float32 is
                scaled by 255 / ``float_full_scale``).

        Returns:
            The live tracks in this frame.

        Raises:
            ValueError: On a non-2-D, non-uint8/float32, empty or non-finite
                image, or a change of image shape without :meth:`reset`.
        """
        img = self._prepare(image)
        cfg = self.config_for(img.shape)
        # OpenCV's float32 matchTemplate has a smaller fixed cost per call than its
        # 8-bit one on windows this small; convert each frame once and keep it.
        if self._prev is not None and self._tpl_xy.shape[0]:
            prev_xy = self._track(self._prev, img)
        else:
            prev_xy = np.full((self._ids.size, 2), np.nan)
        self._prev = img
        n_before = self._ids.size
        # Adaptive threshold: what the templates held after their detections
        # (a fixed target would re-detect every frame on sparse texture).
        expected = int(self._tpl_expect.sum())
        low = expected == 0 or self._ids.size < cfg.redetect_below_frac * expected
        missing = cfg.n_templates - self._tpl_xy.shape[0]
        # Templates holding fewer tracks than after their last detection. A
        # refill below changes neither their indices nor their counts.
        top_up = None
        if low:
            counts = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])
            top_up = np.flatnonzero(counts < self._tpl_expect)
        if missing > 0 and (missing >= cfg.refill_min_missing or low):
            # Where new and old sub-images cannot hold points closer than
            # min_track_separation_px (_merge_top_up), their detections run in
            # one pass: the same points, ids and order as two passes.
            if self._add_templates(img, top_up if self._merge_top_up else None) and self._merge_top_up:
                top_up = None
        if top_up is not None:
            self._detect(img, top_up)
        n_new = self._ids.size - n_before
        if n_new:
            prev_xy = np.concatenate([prev_xy, np.full((n_new, 2), np.nan)])
        return Tracks(ids=self._ids.copy(), xy=self._xy.copy(), prev_xy=prev_xy, age=self._age.copy())

    def _track(self, prev: np.ndarray, img: np.ndarray) -> np.ndarray:
        """Block-match the templates (§2.4), then LK-track their features (§4)
        inside the sub-images; returns the survivors' previous positions.

        Block matching (SSD: :func:`vision.fixation.ssd_maps` for every
        template's narrow window at once, :func:`vision.fixation.match_one`
        for the re-searches) first searches
        ``search_radius_near_px`` around the prediction (the template's last
        displacement, rounded), again around a minimum that lies on that
        window's edge (up to ``search_follow_steps`` times: a descent on the SSD
        surface in narrow windows), and falls back to ``search_radius_px`` when
        the minimum is still on the edge or does not match well enough. A
        parabola through the SSD minimum and its neighbours refines the
        displacement to sub-pixel (``subpixel_match``). A template is lost when
        its minimum is on the search edge, its SSD exceeds ``max_rel_ssd`` of
        its centred energy, or it comes within ``edge_margin_px`` of the image
        edge; its tracks go with it.

        The LK solves run on mosaics of the sub-images only (§4: tracking
        "within each sub-image"): tile t is the neighbourhood of template t,
        cut from frame k around its old place and from frame k+1 around its
        matched place, so the cost does not grow with the frame size. Each
        feature's forward solve starts at its position plus its seed
        displacement (``lk_seed``), the backward solve at the forward result
        minus the same seed. A point is kept when its round trip closes
        within ``fb_max_px``, its LK window (with its derivative ring) stays
        inside its tile, and it stays within ``FP_BOX_SLACK_FRAC`` of its
        template's new box.

        Per-template work is one plain Python loop over the templates;
        per-point work a handful of vectorised NumPy operations (the hot path).
        """
        cfg = self._cfg
        size = cfg.template_size
        height, width = img.shape
        e = cfg.edge_margin_px
        wide = cfg.search_radius_px
        near = min(cfg.search_radius_near_px, wide)
        follow = cfg.search_follow_steps
        wide_if_poor = cfg.wide_search_on_poor_match
        xmax, ymax = width - size, height - size
        xok_hi, yok_hi = width - e - size, height - e - size
        max_rel = cfg.max_rel_ssd
        subpixel = cfg.subpixel_match
        track_seed = cfg.lk_seed == "track"
        half = cfg.lk_window // 2
        slack = math.ceil(FP_BOX_SLACK_FRAC * size)
        margin = lk_tile_margin(size, cfg.lk_window)
        tile = size + 2 * margin
        # Tiles are shifted to stay inside the frame. Invariant: templates are
        # placed only in frames of >= size + 2 border_px, and the config
        # ensures border_px >= margin, so the frame holds a tile.
        assert tile <= min(height, width)
        tx_max, ty_max = width - tile, height - tile
        n_t = self._tpl_xy.shape[0]
        # Tiles side by side: OpenCV's LK computes the derivatives of its whole
        # first image, and does so about twice as fast on a wide mosaic as on
        # a tall one of the same area.
        # Frame k's tiles: a template kept through the last step has its
        # tile in last step's frame-(k) mosaic already, at the same corner
        # (the same pixels of the same frame), so only the others are copied.
        cached = self._mos_cache
        if cached is not None and cached[0] is prev and cached[1].shape == (tile, n_t * tile):
            mos_prev, corners_prev = cached[1], cached[2]
        else:
            mos_prev, corners_prev = np.empty((tile, n_t * tile), prev.dtype), [None] * n_t
        mos_cur = np.empty((tile, n_t * tile), img.dtype)
        corners_cur: list[tuple[int, int]] = []
        lo_in, hi_in = half + 1, tile - 2 - half
        rows: list[tuple] = []
        kept: list[tuple] = []
        tpl_xy, tpl_pred = self._tpl_xy.tolist(), self._tpl_pred.tolist()
        # Block matching, first the narrow search of every template at once
        # (ssd_maps: one SSD map of (2 near + 1)^2 placements per template).
        # A template whose window would leave the frame is searched alone
        # (match_one clips the window to the frame).
        side = size + 2 * near
        # ssd_maps_rows' layout: window rows back to back (plus 2 near
        # padding elements), template rows padded with zeros to the window's
        # width; tpls is the (T, size, size) view of the templates.
        win_rows = np.zeros((n_t, side * side + 2 * near), np.float32)
        windows = win_rows[:, : side * side].reshape(n_t, side, side)
        tpl_rows = np.zeros((n_t, size * side), np.float32)
        tpls = tpl_rows.reshape(n_t, size, side)[:, :, :size]
        batched: list[bool] = []
        # Plain Python ints and floats in the loops: NumPy scalar handling would
        # cost more than the small array operations themselves.
        for t, ((x, y), (px, py)) in enumerate(zip(tpl_xy, tpl_pred)):
            cx, cy = x + px, y + py
            tpls[t] = prev[y : y + size, x : x + size]
            inside = near <= cx <= xmax - near and near <= cy <= ymax - near
            if inside:
                windows[t] = img[cy - near : cy + near + size, cx - near : cx + near + size]
            else:
                windows[t] = 0.0  # searched alone below; no uninitialised values in ssd_maps
            batched.append(inside)
        n_side = 2 * near + 1
        ssd_all = ssd_maps_rows(win_rows, tpl_rows, size, size, near, near).reshape(n_t, n_side * n_side).tolist()
        energies = centred_energy(tpl_rows, size * size).tolist()
        for t, ((x, y), (px, py), (sx0, sy0)) in enumerate(zip(tpl_xy, tpl_pred, self._tpl_sub.tolist())):
            limit = max_rel * max(energies[t], TEMPLATE_ENERGY_FLOOR)
            cx, cy = x + px, y + py
            if batched[t]:
                # As match_one on the same map (_map_minimum).
                bx, by, ssd, at_edge, fx, fy = _map_minimum(ssd_all[t], n_side, cx - near, cy - near)
            else:
                bx, by, ssd, at_edge, fx, fy = _match_region(img, tpls[t], cx, cy, near, xmax, ymax)
            if near < wide and (at_edge or (ssd > limit and wide_if_poor)):
                tpl = tpls[t]
                # The minimum may lie just beyond the narrow window: search
                # around it again, up to search_follow_steps times.
                for _ in range(follow if at_edge else 0):
                    bx, by, ssd, at_edge, fx, fy = _match_near(img, tpl, bx, by, near, xmax, ymax)
                    if not at_edge:
                        break
                if at_edge or (ssd > limit and wide_if_poor):
                    bx, by, ssd, at_edge, fx, fy = _match_region(img, tpl, cx, cy, wide, xmax, ymax)
            if not subpixel:
                fx = fy = 0.0
            sx, sy = bx - x + fx, by - y + fy
            ok = not at_edge and ssd <= limit and e <= bx <= xok_hi and e <= by <= yok_hi
            # Tile corners in frames k and k+1, and the tiles.
            xp, yp = min(max(x - margin, 0), tx_max), min(max(y - margin, 0), ty_max)
            xc, yc = min(max(bx - margin, 0), tx_max), min(max(by - margin, 0), ty_max)
            c0 = t * tile
            if corners_prev[t] != (xp, yp):
                mos_prev[:, c0 : c0 + tile] = prev[yp : yp + tile, xp : xp + tile]
            mos_cur[:, c0 : c0 + tile] = img[yc : yc + tile, xc : xc + tile]
            corners_cur.append((xc, yc))
            # Per template, in mosaic coordinates: the offsets that take a
            # point's frame position (and its last displacement, with the
            # 'track' seed) to its LK start in each solve, the offset back to
            # the frame, and the bounds of a tracked point (window inside the
            # tile, point within the slack of the template's new box; empty
            # for a lost template, so its tracks go with it).
            ox_p, oy_p, ox_c, oy_c = xp - c0, yp, xc - c0, yc
            dx, dy = (sx - sx0, sy - sy0) if track_seed else (sx, sy)
            bxt, byt = bx - xc, by - yc
            if ok:
                kept.append((t, bx, by, sx, sy))
                bounds = (
                    max(bxt - slack, lo_in) + c0, max(byt - slack, lo_in),
                    min(bxt + size - 1 + slack, hi_in) + c0, min(byt + size - 1 + slack, hi_in),
                )
            else:
                bounds = (math.inf, math.inf, -math.inf, -math.inf)
            rows.append((
                -ox_p, -oy_p, dx - ox_c, dy - oy_c, ox_c - ox_p - dx, oy_c - oy_p - dy, ox_c, oy_c, *bounds,
            ))
        per_t = np.array(rows, dtype=np.float64).reshape(-1, 12)
        # Per point: one gather of its template's row. The points of a template
        # lost in this step go with it: they are not solved (LK solves each
        # point on its own, so the others' results do not change).
        xy, flow, tpl_of = self._xy, self._flow, self._tpl_of
        live = None
        if len(kept) < n_t:
            live = np.flatnonzero(np.isfinite(per_t[tpl_of, 8]))
            xy, flow, tpl_of = xy[live], flow[live], tpl_of[live]
        g = per_t[tpl_of]
        n = xy.shape[0]
        # LK inputs in mosaic coordinates, float32 as OpenCV takes them: the
        # points of frame k, the forward starts (position + seed) and the
        # backward offsets (the backward solve starts at the forward result
        # minus the seed). The 'track' seed is the track's own last
        # displacement plus the change of its template's block-matching
        # displacement; a new track's "last displacement" is its template's
        # (set in _detect), so it starts at its template's displacement. The
        # 'template' seed is the template's displacement.
        pts = np.empty((3, n, 2), np.float32)
        np.add(xy, g[:, 0:2], out=pts[0], casting="unsafe")
        if track_seed:
            np.add(xy + flow, g[:, 2:4], out=pts[1], casting="unsafe")
            np.subtract(g[:, 4:6], flow, out=pts[2], casting="unsafe")
        else:
            np.add(xy, g[:, 2:4], out=pts[1], casting="unsafe")
            pts[2] = g[:, 4:6]
        if n == 0:  # no point to solve (OpenCV's LK refuses an empty set)
            q_mos, ok = np.zeros((0, 2), np.float32), np.zeros(0, bool)
        elif cfg.lk_backend == "opencv" and cfg.fb_check:
            kw_fwd, kw_back = self._lk_kwargs
            q_mos, ok = forward_backward_opencv_ok(mos_prev, mos_cur, pts, kw_fwd, kw_back, cfg.fb_max_px,
                                                   cfg.fb_blend)
        elif cfg.lk_backend == "opencv":
            q_mos, ok, resid = forward_opencv_fast(
                mos_prev, mos_cur, pts[0], pts[1], cfg.lk_window, cfg.lk_max_iter, cfg.lk_eps_px, cfg.lk_min_eig
            )
            dev = q_mos - pts[1]
            ok &= (resid <= cfg.max_residual_dn) & ((dev * dev).sum(axis=1) <= cfg.max_seed_deviation_px**2)
        else:
            back_window = cfg.lk_window if cfg.fb_window is None else min(cfg.fb_window, cfg.lk_window)
            p_mos = xy + g[:, 0:2]
            guess = (xy + flow if track_seed else xy) + g[:, 2:4]
            fb = forward_backward(mos_prev, mos_cur, p_mos, guess, None, cfg.fb_max_px, backend="numpy",
                                  window=cfg.lk_window, max_iter=cfg.lk_max_iter, eps=cfg.lk_eps_px,
                                  min_eig=cfg.lk_min_eig, back_window=back_window)
            q_mos, ok = fb.xy, fb.fb_error <= cfg.fb_max_px
            if cfg.fb_blend:
                q_mos = q_mos - cfg.fb_blend * (fb.back_xy - p_mos)
        inside = (q_mos >= g[:, 8:10]) & (q_mos <= g[:, 10:12])
        ok &= inside[:, 0] & inside[:, 1]
        # The frame-(k+1) mosaic is next step's frame-k mosaic for the
        # templates kept (same corners); LK never writes into its inputs.
        self._mos_cache = (img, mos_cur, corners_cur)
        idx = np.flatnonzero(ok)
        old_xy = xy[idx]
        new_xy = q_mos[idx] + g[idx, 6:8]
        if self._correct_bias:
            new_xy = self._without_lk_bias(mos_prev, pts[0], idx, live, new_xy, kept)
        self._xy = new_xy
        self._flow = self._xy - old_xy
        self._tpl_of = tpl_of[idx]
        if live is not None:
            idx = live[idx]  # back to the indices of all this step's tracks
        self._ids = self._ids[idx]
        self._age = self._age[idx] + 1
        # (t, bx, by, sx, sy) of the kept templates; integers and their
        # sub-pixel displacements are exact in float64.
        kept_arr = np.array(kept, dtype=np.float64).reshape(-1, 5)
        if len(kept) < n_t:
            # Re-index tracks onto the surviving templates.
            keep = np.zeros(n_t, bool)
            keep[kept_arr[:, 0].astype(np.int64)] = True
            self._tpl_of = (np.cumsum(keep) - 1)[self._tpl_of]
            self._tpl_expect = self._tpl_expect[keep]
        self._tpl_xy = kept_arr[:, 1:3].astype(np.int64)
        self._tpl_sub = kept_arr[:, 3:5].copy()
        # The next prediction: the displacement rounded half to even, as round().
        self._tpl_pred = np.rint(self._tpl_sub).astype(np.int64)
        return old_xy

    def _without_lk_bias(self, mos_prev: np.ndarray, p_mos: np.ndarray, idx: np.ndarray, live: np.ndarray | None,
                         new_xy: np.ndarray, kept: list[tuple]) -> np.ndarray:
        """The LK bias correction: the surviving tracks' new positions ``new_xy`` (frame k+1) less
        their LK window's bias under this frame's motion gradient (:func:`vision.lk.lk_bias_gain`).

        ``idx`` indexes the survivors among the solved points (``live``: the solved among all
        tracks), ``p_mos`` the solved points in frame k's mosaic, ``kept`` the templates' block
        matches (``A``'s fit). Keeps the survivors' gains for the next step: all recomputed every
        ``lk_bias_refresh_frames`` steps and at the first step after tracks were added.
        """
        cfg = self._cfg
        if self._gain_steps < 0 or self._gain_steps >= cfg.lk_bias_refresh_frames - 1:
            # The bias of the position reported: the forward-backward blend of the two solves, when on.
            back = cfg.fb_window if cfg.fb_check and cfg.fb_blend else None
            gain = lk_bias_gain(mos_prev, p_mos[idx], cfg.lk_window, back, cfg.fb_blend if back else 0.0)
            self._gain_steps = 0
        else:
            gain = (self._gain if live is None else self._gain[live])[idx]
            self._gain_steps += 1
        self._gain = gain
        # A from the templates spread over the frame; with fewer than four (a featureless frame) the
        # tracks bunch in one or two sub-images, where a fit's error would move them all alike.
        a = _affine_from_templates(kept)
        return new_xy if a is None else new_xy - lk_bias(gain, a)

    def fixation_areas(self, img: np.ndarray, n: int) -> FixationAreas:
        """§2 on ``img`` with this tracker's parameters: ``n`` new templates
        away from the ones in use (also used for the paper's figures)."""
        cfg = self.config_for(img.shape)
        preferred = None
        if cfg.template_lookahead_frames > 0 and self._tpl_xy.shape[0]:
            preferred = self._lasting_areas(img.shape, cfg)
        return fixation_areas(
            img,
            n,
            cfg.subsample_x,
            cfg.subsample_y,
            cfg.template_size,
            cfg.border_px,
            cfg.template_separation_frac * min(img.shape),
            cfg.min_template_variance,
            occupied_xy=self._tpl_xy + 0.5 * (cfg.template_size - 1),
            preferred=preferred,
        )

    def _lasting_areas(self, shape: tuple[int, int], cfg: TrackerConfig) -> np.ndarray:
        """Mask over the variance map's candidates (top-left corners Sx u,
        Sy v): True where a template moved ``template_lookahead_frames`` times
        by the similarity field of the templates' last displacements (at its
        corner, :func:`similarity_field`) stays ``edge_margin_px`` inside
        the frame, where it would be dropped."""
        height, width = shape
        sx, sy, size = cfg.subsample_x, cfg.subsample_y, cfg.template_size
        n = float(cfg.template_lookahead_frames)
        a, b, (mx, my), (tx, ty) = similarity_field(self._tpl_xy.astype(np.float64), self._tpl_sub)
        x = np.arange(width // sx - size // sx + 1, dtype=np.float64) * sx
        y = np.arange(height // sy - size // sy + 1, dtype=np.float64) * sy
        rx, ry = x[None, :] - mx, y[:, None] - my
        px = x[None, :] + n * (tx + a * rx - b * ry)
        py = y[:, None] + n * (ty + b * rx + a * ry)
        e = cfg.edge_margin_px
        return (px >= e) & (px <= width - size - e) & (py >= e) & (py <= height - size - e)

    def _add_templates(self, img: np.ndarray, top_up: np.ndarray | None = None) -> bool:
        """Select replacement templates on the current frame (§2.3) and detect
        features in them; with ``top_up`` (indices of existing templates) top
        those up in the same detection pass, after the new ones. Returns
        whether templates were added (and so ``top_up`` detected)."""
        cfg = self._cfg
        size = cfg.template_size
        height, width = img.shape
        if height < size + 2 * cfg.border_px or width < size + 2 * cfg.border_px:
            return False  # the frame is too small to hold a template away from the border
        new = self.fixation_areas(img, cfg.n_templates - self._tpl_xy.shape[0]).top_left
        if new.shape[0] == 0:
            return False
        # New areas most likely move with the rest of the image.
        first = self._tpl_xy.shape[0]
        n_new = new.shape[0]
        if cfg.new_template_seed == "similarity":
            guess = similarity_prediction(self._tpl_xy.astype(np.float64), self._tpl_sub, new.astype(np.float64))
        else:
            guess = np.broadcast_to(_median_rows(self._tpl_sub) if first else np.zeros(2), (n_new, 2))
        self._tpl_xy = np.concatenate([self._tpl_xy, new])
        self._tpl_sub = np.concatenate([self._tpl_sub, guess])
        self._tpl_pred = np.concatenate([self._tpl_pred, np.rint(guess).astype(np.int64)])
        self._tpl_expect = np.concatenate([self._tpl_expect, np.full(new.shape[0], cfg.max_features_per_template)])
        which = np.arange(first, self._tpl_xy.shape[0])
        self._detect(img, which if top_up is None else np.concatenate([which, top_up]))
        # A new area without a single feature point is of no use: free its slot.
        counts = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])
        empty = np.zeros(self._tpl_xy.shape[0], bool)
        empty[first:] = counts[first:] == 0
        if empty.any():
            keep = ~empty
            self._tpl_of = (np.cumsum(keep) - 1)[self._tpl_of]
            self._tpl_xy, self._tpl_sub, self._tpl_pred, self._tpl_expect = (
                self._tpl_xy[keep],
                self._tpl_sub[keep],
                self._tpl_pred[keep],
                self._tpl_expect[keep],
            )
        return True

    def _detect(self, img: np.ndarray, which: np.ndarray) -> None:
        """Top up the templates ``which`` with feature points (§3)."""
        cfg = self._cfg
        counts = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])
        which = which[counts[which] < cfg.max_features_per_template]
        if which.size == 0:
            return
        feats = detect_in_subimages(
            img,
            self._tpl_xy[which],
            (cfg.template_size, cfg.template_size),
            window=cfg.fp_window,
            lambda_t=cfg.lambda_t,
            max_features=cfg.max_features_per_template,
            nms_radius=cfg.fp_nms_radius,
            strategy=cfg.fp_search,
            rng=self._rng,
        )
        # Features arrive grouped by sub-image in the order of ``which``,
        # strongest first within each.
        xy, region = feats.xy, feats.region
        if xy.shape[0] and self._xy.shape[0] and cfg.min_track_separation_px > 0:
            d2 = (xy[:, 0, None] - self._xy[:, 0]) ** 2 + (xy[:, 1, None] - self._xy[:, 1]) ** 2
            far = d2.min(axis=1) >= cfg.min_track_separation_px**2
            xy, region = xy[far], region[far]
        tpl = which[region]
        # Respect the per-template cap (rank within its group).
        rank = np.arange(region.size) - np.searchsorted(region, region, side="left")
        room = cfg.max_features_per_template - counts[tpl]
        sel = rank < room
        xy, tpl = xy[sel], tpl[sel]
        n = xy.shape[0]
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n, dtype=np.int64)])
        self._next_id += n
        self._xy = np.concatenate([self._xy, xy])
        self._age = np.concatenate([self._age, np.zeros(n, np.int64)])
        self._flow = np.concatenate([self._flow, self._tpl_sub[tpl]])
        if self._correct_bias and n:
            self._gain = np.concatenate([self._gain, np.zeros((n, 2, 4))])
            self._gain_steps = -1  # the new tracks' gains at their first solve
        self._tpl_of = np.concatenate([self._tpl_of, tpl.astype(np.int64)])
        self._tpl_expect[which] = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])[which]
