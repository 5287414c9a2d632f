"""The fixation-area feature tracker (paper Fig. 1): images in, tracks out.

Per frame (Step 1-3 of the paper):

1. **Fixation areas** (§2). N templates (Wx x Wy pixels of the full frame) are
   kept. Each is found again in the new frame by least-squares block matching
   (:func:`vision.fixation.match_templates`) inside a search window centred on
   its constant-velocity prediction; the integer displacement is exact for
   integer motions. A template that is lost (SSD too large relative to its
   contrast, minimum on the search-window edge) or that comes close to the
   image edge is dropped, and replacements are chosen from the variance map of
   the current frame (:func:`block_average` -> :func:`laplacian8` ->
   :func:`variance_map` -> :func:`select_templates`), away from the border and
   from the other templates.
2. **Feature points** (§3) are detected only inside the templates (the
   "sub-images") with the square-root-free min-eigenvalue test of eq. (3.4)
   and non-maximum suppression (:func:`vision.features.detect_in_subimages`).
3. **Tracking** (§4). Every feature is refined to sub-pixel accuracy by
   iterative Lucas-Kanade (eqs. 4.5-4.7) in a small window, starting from its
   template's block-matching displacement -- which plays the role of the image
   pyramid, so large motions still converge -- and is kept only if tracking it
   back lands within ``fb_max_px`` of its start (forward-backward check).
   Tracks keep their id for life; when the live tracks fall below
   ``redetect_below_frac`` of what the templates held after their last
   detection, the templates are topped up with new points.

Only image-processing happens here: no truth, no simulator.

Cost: per frame, one ``cv2.matchTemplate`` per template and two
single-level LK passes over mosaics of the sub-images (not the whole frame);
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

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from vision.features import detect_in_subimages, detection_margin
from vision.fixation import FixationAreas, MatchResult, _match_core, fixation_areas
from vision.lk import forward_backward, forward_backward_opencv_fast
from vision.tracks import Tracks, check_image

FULL_SCALE_DN = 255.0
"""8-bit full scale [DN]: the intensity scale every threshold is expressed in."""

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
    return int(np.ceil(FP_BOX_SLACK_FRAC * template_size)) + lk_window // 2 + TILE_GUARD_PX


class TrackerConfig(BaseModel):
    """Parameters of :class:`Tracker` (pixel units refer to the full frame).

    Defaults follow the paper where it gives values (Sx = Sy = 5, 20 x 20
    templates, i.e. its 4 x 4 variance window, W1 = 3) and were otherwise
    chosen on synthetic lunar-like descents at 256^2 and 512^2
    (``python -m bench.tracking_eval``), trading tracks for time:

    * 8 templates x up to 12 points (~70-100 tracks): every template costs one
      block-matching call per frame, so fewer, well-filled sub-images are
      cheaper than many sparse ones; a separation of 20 % of the shorter image
      side spreads them over the frame (paper §2.3 b);
    * lambda_t = 30 DN^2: the paper's 1500 suits its high-contrast imagery;
      soft, low-sun lunar texture rendered at 256^2 gives lambda_1 of a few
      tens to hundreds over a 3 x 3 patch, and ranking by lambda_1 plus the
      forward-backward check already keep the good points;
    * LK window 9 px: fits inside a 20 px sub-image, a few hundredths of a
      pixel accurate on rendered texture, and cheaper than 15 or 21;
    * search radius 12 px around the constant-velocity prediction covers the
      frame-to-frame changes of image motion of a descent at both sizes;
    * lost templates are replaced two at a time (``refill_min_missing``):
      each replacement costs a variance-map pass;
    * LK stops at updates below 0.03 px: the bilinear-interpolation bias is of
      that size, and iterating further did not improve the endpoint error;
    * forward-backward limit 0.5 px rejects mis-tracks well before the 1 px
      accuracy requirement.

    Re-detection is adaptive: it runs when the live tracks fall below
    ``redetect_below_frac`` of what the templates held after their last
    detection (a fixed target would re-detect every frame on sparse texture).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    subsample_x: int = Field(5, ge=1, le=64, description="Sx, block-averaging interval along x, eq. (2.1) [px]")
    subsample_y: int = Field(5, ge=1, le=64, description="Sy, block-averaging interval along y, eq. (2.1) [px]")
    template_size: int = Field(
        20, ge=5, le=256, description="Wx = Wy, side of a template / sub-image [px]; a multiple of Sx and Sy"
    )
    n_templates: int = Field(8, ge=1, le=256, description="N, number of templates kept in track [-]")
    template_separation_frac: float = Field(
        0.2, ge=0.0, le=1.0, description="minimum distance between template centres / shorter image side [-]"
    )
    border_px: int = Field(
        16,
        ge=0,
        description="new templates keep at least this distance to the image edge [px]; >= edge_margin_px and "
        ">= ceil(template_size / 4) + lk_window // 2 + 2 (the LK tile margin)",
    )
    edge_margin_px: int = Field(
        6, ge=0, description="a template closer than this to the image edge is leaving the image and replaced [px]"
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
        4, ge=1, le=128,
        description="first, narrow search half-width around the constant-velocity prediction [px]; a template "
        "whose minimum lands on its edge or fails max_rel_ssd is searched again over search_radius_px",
    )
    max_rel_ssd: float = Field(
        0.5, gt=0.0, description="template lost if min SSD / template centred energy exceeds this [-] (~2: unrelated)"
    )
    fp_window: int = Field(3, ge=1, le=15, description="W1, patch side for G, eq. (3.3) [px]; odd")
    lambda_t: float = Field(30.0, ge=0.0, description="lambda_t, min-eigenvalue threshold of eq. (3.4) [DN^2]")
    fp_nms_radius: int = Field(2, ge=0, le=10, description="non-maximum suppression radius for feature points [px]")
    max_features_per_template: int = Field(12, ge=1, le=256, description="most feature points per sub-image [-]")
    fp_search: Literal["exhaustive", "random"] = Field(
        "exhaustive", description="feature search strategy (§3): exhaustive (paper's choice) or random [-]"
    )
    min_track_separation_px: float = Field(
        3.0, ge=0.0, description="new points closer than this to a live track are not added [px]"
    )
    lk_backend: Literal["opencv", "numpy"] = Field(
        "opencv", description="LK solver: OpenCV single-level LK (fast) or the NumPy reference of eqs. (4.5)-(4.7) [-]"
    )
    lk_window: int = Field(9, ge=3, le=31, description="LK window side [px]; odd")
    lk_max_iter: int = Field(20, ge=1, le=100, description="LK iteration cap [-]")
    lk_eps_px: float = Field(
        0.03, gt=0.0, le=1.0, description="LK stops when the update is below this [px] (bilinear bias is ~0.03 px)"
    )
    lk_min_eig: float = Field(
        1e-2, ge=0.0, description="least min-eigenvalue of G per window pixel for a valid LK solve [DN^2/px^2]"
    )
    fb_max_px: float = Field(0.5, gt=0.0, description="largest forward-backward round-trip error kept [px]")
    redetect_below_frac: float = Field(
        0.75,
        ge=0.0,
        le=1.0,
        description="re-detect when live tracks < this x the tracks the templates held after their last detection [-]",
    )
    float_full_scale: float = Field(
        255.0, gt=0.0, description="value of full white in float32 input frames (1.0 for [0, 1] images) [DN]"
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

    @property
    def target_tracks(self) -> int:
        """Number of tracks the tracker aims for (N x points per template)."""
        return self.n_templates * self.max_features_per_template


class Tracker:
    """Fixation-area + feature-point tracker of the paper.

    Input: a grayscale frame (H, W) uint8 or float32 per call to :meth:`step`.
    Output: :class:`vision.tracks.Tracks` for that frame.
    State: the previous frame, the templates and the live tracks.
    Rate: camera frame rate (one call per frame, frames in time order).
    Cost (2-core x86, single OpenCV thread, synthetic descent): ~0.4-0.5 ms
    per frame at both 256^2 and 512^2 with the default configuration.

    Args:
        config: A :class:`TrackerConfig` (defaults when None).
        rng: Generator for the random search strategy (required with
            ``fp_search="random"``; the bench passes the run's "vision"
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
        self._prev_f32: np.ndarray | None = None  # the same frame in float32, for block matching
        self._tpl_xy = np.zeros((0, 2), np.int64)  # template top-left corners (x, y) [px]
        self._tpl_shift = np.zeros((0, 2), np.int64)  # last block-matching displacement [px]
        self._tpl_expect = np.zeros(0, np.int64)  # tracks each template held after its last detection
        self._ids = np.zeros(0, np.int64)
        self._xy = np.zeros((0, 2), np.float64)
        self._age = np.zeros(0, np.int64)
        self._tpl_of = np.zeros(0, np.int64)  # index of each track's template
        self._next_id = 0

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
                img = img * np.float32(FULL_SCALE_DN / self.config.float_full_scale)
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
        cfg = self.config
        prev_xy = np.full((self._ids.size, 2), np.nan)
        template_lost = False
        # OpenCV's float32 matchTemplate has a smaller fixed cost per call than its
        # 8-bit one on windows this small; convert each frame once and keep it.
        img_f32 = img.astype(np.float32)
        if self._prev is not None and self._tpl_xy.shape[0]:
            prev_xy, template_lost = self._track(self._prev, img, self._prev_f32, img_f32)
        self._prev, self._prev_f32 = img, img_f32
        n_before = self._ids.size
        # Adaptive threshold: what the templates held after their detections
        # (a fixed target would re-detect every frame on sparse texture).
        expected = int(self._tpl_expect.sum())
        low = expected == 0 or self._ids.size < cfg.redetect_below_frac * expected
        missing = cfg.n_templates - self._tpl_xy.shape[0]
        if missing > 0 and (missing >= cfg.refill_min_missing or low):
            self._add_templates(img)
        if low:
            counts = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])
            self._detect(img, np.flatnonzero(counts < self._tpl_expect))
        n_new = self._ids.size - n_before
        prev_xy = np.concatenate([prev_xy, np.full((n_new, 2), np.nan)])
        return Tracks(ids=self._ids.copy(), xy=self._xy.copy(), prev_xy=prev_xy, age=self._age.copy())

    def _track(self, prev: np.ndarray, img: np.ndarray, prev_f32: np.ndarray, img_f32: np.ndarray
               ) -> tuple[np.ndarray, bool]:
        """Block-match templates, LK-track features; returns the survivors'
        previous positions and whether any template was lost."""
        cfg = self.config
        size = cfg.template_size
        height, width = img.shape
        m = self._block_match(prev_f32, img_f32)
        e = cfg.edge_margin_px
        tl = m.top_left
        t_ok = (
            ~m.at_edge
            & (m.rel_ssd <= cfg.max_rel_ssd)
            & (tl.min(axis=1) >= e)
            & (tl[:, 0] <= width - e - size)
            & (tl[:, 1] <= height - e - size)
        )
        old_xy = self._xy
        keep = t_ok[self._tpl_of]
        new_xy = old_xy.copy()
        run = np.flatnonzero(keep)
        if run.size:
            new_xy[run], keep[run] = self._lk_in_subimages(prev, img, old_xy[run], self._tpl_of[run], tl)
        # Re-index tracks onto the surviving templates.
        remap = np.cumsum(t_ok) - 1
        self._ids = self._ids[keep]
        self._xy = new_xy[keep]
        self._age = self._age[keep] + 1
        self._tpl_of = remap[self._tpl_of[keep]]
        self._tpl_xy = tl[t_ok]
        self._tpl_shift = m.shift[t_ok]
        self._tpl_expect = self._tpl_expect[t_ok]
        return old_xy[keep], bool((~t_ok).any())

    def _block_match(self, prev: np.ndarray, img: np.ndarray) -> MatchResult:
        """SSD block matching (§2.4), narrow window first, full window where needed.

        Image motion between frames is mostly what it was a frame ago, so the
        search starts in a small window around the constant-velocity
        prediction (~8x fewer placements than the full window). A template
        whose minimum lies on that window's edge, or that does not match well
        enough, is searched again over the full ``search_radius_px``, so large
        or sudden motions are still found.
        """
        cfg = self.config
        size = cfg.template_size
        centre = self._tpl_xy + self._tpl_shift
        near = min(cfg.search_radius_near_px, cfg.search_radius_px)
        m = _match_core(prev, img, self._tpl_xy, centre, size, size, near)
        if near == cfg.search_radius_px:
            return m
        redo = np.flatnonzero(m.at_edge | (m.rel_ssd > cfg.max_rel_ssd))
        if redo.size == 0:
            return m
        wide = _match_core(prev, img, self._tpl_xy[redo], centre[redo], size, size, cfg.search_radius_px)
        top_left, shift, ssd = m.top_left.copy(), m.shift.copy(), m.ssd.copy()
        rel_ssd, at_edge = m.rel_ssd.copy(), m.at_edge.copy()
        top_left[redo], shift[redo], ssd[redo] = wide.top_left, wide.shift, wide.ssd
        rel_ssd[redo], at_edge[redo] = wide.rel_ssd, wide.at_edge
        return MatchResult(top_left=top_left, shift=shift, ssd=ssd, rel_ssd=rel_ssd, at_edge=at_edge)

    def _lk_in_subimages(
        self, prev: np.ndarray, img: np.ndarray, xy: np.ndarray, tpl: np.ndarray, new_tl: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forward-backward LK of points ``xy`` (P, 2) of templates ``tpl``
        (P,) whose new corners are ``new_tl`` (T, 2); returns the new positions
        (P, 2) and a validity mask (P,).

        The LK solves run on mosaics of the sub-images only (§4: tracking
        "within each sub-image"): tile t is the neighbourhood of template t,
        cut from frame k around its old place and from frame k+1 around its
        matched place, so the cost does not grow with the frame size. The
        forward solve starts at "old position + block-matching shift", the
        backward one at "forward result - shift".
        """
        cfg = self.config
        size = cfg.template_size
        half = cfg.lk_window // 2
        slack = int(np.ceil(FP_BOX_SLACK_FRAC * size))
        margin = lk_tile_margin(size, cfg.lk_window)
        tile = size + 2 * margin
        height, width = img.shape
        n_t = new_tl.shape[0]
        # Tiles are shifted to stay inside the frame. Invariant: templates are
        # placed only in frames of >= size + 2 border_px, and the config
        # ensures border_px >= margin, so the frame holds a tile.
        assert tile <= min(height, width)
        lim = np.array([width - tile, height - tile])
        # np.minimum/np.maximum: np.clip's dispatch costs ~10 us on arrays this small.
        c_prev = np.minimum(np.maximum(self._tpl_xy - margin, 0), lim)
        c_cur = np.minimum(np.maximum(new_tl - margin, 0), lim)

        def mosaic(image: np.ndarray, corners: np.ndarray) -> np.ndarray:
            out = np.empty((n_t * tile, tile), image.dtype)
            for t, (x, y) in enumerate(corners.tolist()):
                out[t * tile : (t + 1) * tile] = image[y : y + tile, x : x + tile]
            return out

        row0 = (tpl * tile).astype(np.float64)
        off_prev = c_prev[tpl].astype(np.float64)
        off_prev[:, 1] -= row0
        off_cur = c_cur[tpl].astype(np.float64)
        off_cur[:, 1] -= row0
        shift = (new_tl - self._tpl_xy)[tpl]
        p_mos = xy - off_prev
        guess = xy + shift - off_cur
        back = off_cur - off_prev - shift  # backward guess = forward result + back
        mos_prev, mos_cur = mosaic(prev, c_prev), mosaic(img, c_cur)
        if cfg.lk_backend == "opencv":
            q_mos, fb_err = forward_backward_opencv_fast(
                mos_prev, mos_cur, p_mos, guess, back, cfg.lk_window, cfg.lk_max_iter, cfg.lk_eps_px, cfg.lk_min_eig
            )
        else:
            fb = forward_backward(
                mos_prev,
                mos_cur,
                p_mos,
                guess,
                None,
                cfg.fb_max_px,
                backend="numpy",
                window=cfg.lk_window,
                max_iter=cfg.lk_max_iter,
                eps=cfg.lk_eps_px,
                min_eig=cfg.lk_min_eig,
            )
            q_mos, fb_err = fb.xy, fb.fb_error
        out = q_mos + off_cur
        # Window (with its derivative ring) inside its own tile; the point
        # inside the frame and near its template's new box.
        tx = q_mos[:, 0]
        ty = q_mos[:, 1] - row0
        rel = out - new_tl[tpl]
        lo, hi = half + 1, tile - 2 - half
        ok = (
            (fb_err <= cfg.fb_max_px)
            & (tx >= lo)
            & (tx <= hi)
            & (ty >= lo)
            & (ty <= hi)
            & (out[:, 0] >= half + 1)
            & (out[:, 1] >= half + 1)
            & (out[:, 0] <= width - 2 - half)
            & (out[:, 1] <= height - 2 - half)
            & (rel.min(axis=1) >= -slack)
            & (rel.max(axis=1) <= size - 1 + slack)
        )
        return out, ok

    def fixation_areas(self, img: np.ndarray, n: int) -> FixationAreas:
        """§2 on ``img`` with this tracker's parameters: ``n`` new templates
        away from the ones in use (also used for the paper's figures)."""
        cfg = self.config
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
        )

    def _add_templates(self, img: np.ndarray) -> None:
        """Select replacement templates on the current frame (§2.3) and detect
        features in them."""
        cfg = self.config
        size = cfg.template_size
        height, width = img.shape
        if height < size + 2 * cfg.border_px or width < size + 2 * cfg.border_px:
            return  # the frame is too small to hold a template away from the border
        new = self.fixation_areas(img, cfg.n_templates - self._tpl_xy.shape[0]).top_left
        if new.shape[0] == 0:
            return
        # New areas most likely move with the rest of the image.
        guess = np.median(self._tpl_shift, axis=0) if self._tpl_shift.shape[0] else np.zeros(2)
        first = self._tpl_xy.shape[0]
        self._tpl_xy = np.concatenate([self._tpl_xy, new])
        self._tpl_shift = np.concatenate([self._tpl_shift, np.tile(np.rint(guess).astype(np.int64), (new.shape[0], 1))])
        self._tpl_expect = np.concatenate([self._tpl_expect, np.full(new.shape[0], cfg.max_features_per_template)])
        self._detect(img, np.arange(first, self._tpl_xy.shape[0]))
        # A new area without a single feature point is of no use: free its slot.
        counts = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])
        empty = np.zeros(self._tpl_xy.shape[0], bool)
        empty[first:] = counts[first:] == 0
        if empty.any():
            keep = ~empty
            self._tpl_of = (np.cumsum(keep) - 1)[self._tpl_of]
            self._tpl_xy, self._tpl_shift, self._tpl_expect = (
                self._tpl_xy[keep],
                self._tpl_shift[keep],
                self._tpl_expect[keep],
            )

    def _detect(self, img: np.ndarray, which: np.ndarray) -> None:
        """Top up the templates ``which`` with feature points (§3)."""
        cfg = self.config
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
        xy, tpl = feats.xy, which[feats.region]
        if xy.shape[0] and self._xy.shape[0] and cfg.min_track_separation_px > 0:
            d2 = ((xy[:, None, :] - self._xy[None, :, :]) ** 2).sum(axis=2)
            far = d2.min(axis=1) >= cfg.min_track_separation_px**2
            xy, tpl = xy[far], tpl[far]
        # Respect the per-template cap: features arrive strongest first per template.
        order = np.argsort(tpl, kind="stable")
        xy, tpl = xy[order], tpl[order]
        rank = np.arange(tpl.size) - np.searchsorted(tpl, tpl, side="left")
        room = cfg.max_features_per_template - counts[tpl]
        sel = rank < room
        xy, tpl = xy[sel], tpl[sel]
        n = xy.shape[0]
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n, dtype=np.int64)])
        self._next_id += n
        self._xy = np.concatenate([self._xy, xy])
        self._age = np.concatenate([self._age, np.zeros(n, np.int64)])
        self._tpl_of = np.concatenate([self._tpl_of, tpl.astype(np.int64)])
        self._tpl_expect[which] = np.bincount(self._tpl_of, minlength=self._tpl_xy.shape[0])[which]
