"""Tracking accuracy and speed against truth (bench side: truth allowed).

Pure NumPy/OpenCV, no simulator:

* :func:`truth_flow` -- where a pixel of frame k truly is in frame k+1, from
  the depth image and both camera poses.
* :class:`OpenCVBaseline` -- the reference tracker the paper's method must
  beat: ``goodFeaturesToTrack`` + pyramidal ``calcOpticalFlowPyrLK`` with a
  forward-backward check.
* :func:`evaluate` / :func:`compare` -- endpoint error, track counts and
  lifetimes, and milliseconds per ``step``.
* :func:`synthetic_descent` -- a textured ground plane seen by a descending
  pinhole camera, rendered by homography, with analytic depth; used by the
  tests and by ``python -m bench.evaluation.tracking_eval``.

Frames: L is the landing frame (x east, y north, z up, ground z = 0); C is
OpenCV's camera frame (x right, y down, z forward); ``R_LC`` rotates C vectors
into L and ``r_C_L`` is the camera position in L [m]. Depth is the z-depth
along the optical axis [m]. Pixels: x = column, y = row, integer values at
pixel centres.
"""

from __future__ import annotations

import argparse
import resource
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from vision.tracks import Tracks, check_image

Pose = tuple[np.ndarray, np.ndarray]
"""(R_LC (3, 3), r_C_L (3,) [m])."""

DEPTH_JUMP_REL = 0.05
"""Truth is invalid where the four depths around a point differ by more than
this fraction (a depth discontinuity: bilinear depth would be meaningless)."""
OCCLUSION_TOL_REL = 0.01
"""A point is occluded in frame k+1 when its depth exceeds the depth image
there by more than this fraction."""
FULL_SCALE_DN = 255.0
"""8-bit full scale [DN]."""


class Stepper(Protocol):
    """Anything with ``step(image) -> Tracks`` (the Tracker and the baseline)."""

    def step(self, image: np.ndarray) -> Tracks: ...


# --------------------------------------------------------------------- truth
def _bilinear(img: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` at ``xy`` (N, 2), the 2 x 2 corner values
    (N, 4) and an in-image mask (N,)."""
    height, width = img.shape
    x, y = xy[:, 0], xy[:, 1]
    finite = np.isfinite(x) & np.isfinite(y)
    x0 = np.floor(np.where(finite, x, 0)).astype(np.int64)
    y0 = np.floor(np.where(finite, y, 0)).astype(np.int64)
    # A point exactly on the last row/column uses the last cell.
    x0 = np.where(x0 == width - 1, width - 2, x0)
    y0 = np.where(y0 == height - 1, height - 2, y0)
    inside = finite & (x0 >= 0) & (y0 >= 0) & (x0 + 1 < width) & (y0 + 1 < height)
    inside &= (x <= width - 1) & (y <= height - 1)  # no extrapolation past the last centre
    xc, yc = np.clip(x0, 0, max(width - 2, 0)), np.clip(y0, 0, max(height - 2, 0))
    fx, fy = np.where(finite, x, 0) - xc, np.where(finite, y, 0) - yc
    corners = np.stack(
        [img[yc, xc], img[yc, xc + 1], img[yc + 1, xc], img[yc + 1, xc + 1]], axis=1
    ).astype(np.float64)
    val = (
        corners[:, 0] * (1 - fx) * (1 - fy)
        + corners[:, 1] * fx * (1 - fy)
        + corners[:, 2] * (1 - fx) * fy
        + corners[:, 3] * fx * fy
    )
    return val, corners, inside


def _check_pose(R: np.ndarray, r: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or r.shape != (3,):
        raise ValueError(f"{name}: R_LC must be (3, 3) and r_C_L (3,), got {R.shape} and {r.shape}")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
        raise ValueError(f"{name}: R_LC must be a rotation matrix (orthonormal), got {R.tolist()}")
    return R, r


def truth_flow(
    xy_k: np.ndarray,
    depth_k: np.ndarray,
    K: np.ndarray,
    R_LC_k: np.ndarray,
    r_C_L_k: np.ndarray,
    R_LC_k1: np.ndarray,
    r_C_L_k1: np.ndarray,
    depth_k1: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """True position in frame k+1 of points tracked in frame k.

    Each point is back-projected with the bilinearly interpolated depth of
    frame k and the pose of frame k into L, then projected with the pose of
    frame k+1.

    Args:
        xy_k: Points in frame k, (N, 2) [px].
        depth_k: z-depth image of frame k, (H, W) float [m]; non-finite or
            <= 0 means no surface.
        K: Pinhole intrinsics, (3, 3) [px].
        R_LC_k, r_C_L_k: Camera attitude (3, 3) and position (3,) [m] at frame k.
        R_LC_k1, r_C_L_k1: The same at frame k+1.
        depth_k1: Optional z-depth image of frame k+1 for an occlusion check.

    Returns:
        (xy_k1_true (N, 2) [px], NaN where invalid; valid (N,) bool).
        Invalid: outside the pixel-centre hull [0, W-1] x [0, H-1] of frame k
        or of frame k+1, no depth or a depth discontinuity under the point
        (relative spread of the four surrounding depths > ``DEPTH_JUMP_REL``),
        behind the camera in frame k+1, or (with ``depth_k1``) occluded there.
    """
    xy_k = np.asarray(xy_k, dtype=np.float64)
    if xy_k.ndim != 2 or xy_k.shape[1] != 2:
        raise ValueError(f"xy_k must have shape (N, 2) [px], got {xy_k.shape}")
    depth_k = np.asarray(depth_k)
    if depth_k.ndim != 2 or min(depth_k.shape) < 2:
        raise ValueError(f"depth_k must be a 2-D (H, W) depth image of at least 2 x 2, got shape {depth_k.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    R0, r0 = _check_pose(R_LC_k, r_C_L_k, "pose k")
    R1, r1 = _check_pose(R_LC_k1, r_C_L_k1, "pose k+1")
    z, corners, valid = _bilinear(depth_k, xy_k)
    with np.errstate(invalid="ignore"):
        good_depth = np.isfinite(corners).all(axis=1) & (corners > 0).all(axis=1)
        spread = (corners.max(axis=1) - corners.min(axis=1)) / np.where(good_depth, corners.min(axis=1), 1.0)
    valid &= good_depth & (spread <= DEPTH_JUMP_REL)
    z = np.where(valid, z, 1.0)
    rays = np.linalg.solve(K, np.column_stack([xy_k, np.ones(len(xy_k))]).T)  # (3, N), z = 1
    p_L = R0 @ (rays * z) + r0[:, None]
    p_C1 = R1.T @ (p_L - r1[:, None])
    z1 = p_C1[2]
    valid &= z1 > 0
    proj = K @ p_C1
    xy_k1 = (proj[:2] / np.where(valid, z1, 1.0)).T
    height, width = depth_k.shape
    valid &= (xy_k1[:, 0] >= 0) & (xy_k1[:, 0] <= width - 1) & (xy_k1[:, 1] >= 0) & (xy_k1[:, 1] <= height - 1)
    if depth_k1 is not None:
        z_seen, _, inside1 = _bilinear(np.asarray(depth_k1), np.where(valid[:, None], xy_k1, 0.0))
        with np.errstate(invalid="ignore"):
            visible = inside1 & np.isfinite(z_seen) & (z1 <= z_seen * (1.0 + OCCLUSION_TOL_REL))
        valid &= visible
    xy_k1 = np.where(valid[:, None], xy_k1, np.nan)
    return xy_k1, valid


# ------------------------------------------------------------------ baseline
class BaselineConfig(BaseModel):
    """Parameters of :class:`OpenCVBaseline`.

    Tuning (``python -m bench.evaluation.tracking_eval --sweep``: synthetic descent, 40
    frames, 256^2 and 512^2, one OpenCV thread, 2-core x86). Every setting
    below was as accurate as the alternatives; the sweep's cost per frame
    (mean over frames of the fastest of 3 repeats) was:

    ====================  ===========  ===========
    win_size / max_level  256^2 [ms]   512^2 [ms]
    ====================  ===========  ===========
    9 / 1                 0.32         0.66
    9 / 2 (default)       0.40         0.77
    9 / 3                 0.46         0.85
    15 / 1 .. 3           0.69 - 1.13  1.05 - 1.54
    21 / 1 .. 3           0.85 - 1.40  1.23 - 1.83
    ====================  ===========  ===========

    * ``max_corners`` = 96, the number of tracks the fixation-area tracker
      aims for (8 templates x 12), so both deliver similar track counts;
    * ``quality_level`` 0.01, ``min_distance`` 5 px, ``block_size`` 3:
      OpenCV's usual values; the minimum distance spreads the points;
    * ``win_size`` 9 px: as accurate as 15 or 21 on this imagery (median
      endpoint error 0.026-0.031 px for all) and by far the cheapest;
    * ``max_level`` 2 (3 levels): with a 9 px window one level above the base
      captures about +-8 px and already sufficed on this sequence (the
      cheapest setting, 9 / 1), but frame-to-frame motions of 10-20 px are
      expected at 512^2 in closed loop, so the default keeps one more level;
      use ``max_level=1`` for the most favourable baseline timing;
    * each LK call builds its own pyramids: OpenCV 5's Python bindings do not
      accept the pre-built pyramids of ``cv2.buildOpticalFlowPyramid``;
    * LK termination (20 iterations or 0.03 px), forward-backward limit
      0.5 px and re-detection below 75 % of ``max_corners``, as in the tracker.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    max_corners: int = Field(96, ge=1, description="most tracks kept (goodFeaturesToTrack maxCorners) [-]")
    quality_level: float = Field(0.01, gt=0.0, lt=1.0, description="corner quality relative to the best [-]")
    min_distance_px: float = Field(5.0, ge=0.0, description="minimum distance between corners [px]")
    block_size: int = Field(3, ge=1, le=31, description="corner-measure neighbourhood [px]")
    win_size: int = Field(9, ge=3, le=61, description="LK window side [px]; odd")
    max_level: int = Field(2, ge=0, le=6, description="pyramid levels above the base [-]")
    max_iter: int = Field(20, ge=1, description="LK iteration cap [-]")
    eps_px: float = Field(0.03, gt=0.0, description="LK convergence threshold [px]")
    fb_max_px: float = Field(0.5, gt=0.0, description="largest forward-backward round-trip error kept [px]")
    redetect_below_frac: float = Field(0.75, ge=0.0, le=1.0, description="re-detect below this x max_corners [-]")
    border_px: int = Field(6, ge=0, description="tracks closer than this to the image edge are dropped [px]")
    float_full_scale: float = Field(255.0, gt=0.0, description="value of full white in float32 frames [DN]")


class OpenCVBaseline:
    """goodFeaturesToTrack + pyramidal LK + forward-backward check.

    Input: grayscale frame (H, W) uint8 or float32 per :meth:`step`.
    Output: :class:`vision.tracks.Tracks` (same contract as ``vision.Tracker``).
    Rate: one call per frame.

    Args:
        config: :class:`BaselineConfig` (defaults when None).
    """

    def __init__(self, config: BaselineConfig | None = None) -> None:
        self.config = config if config is not None else BaselineConfig()
        if not isinstance(self.config, BaselineConfig):
            raise ValueError(f"config must be a BaselineConfig, got {type(self.config).__name__}")
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame and all tracks."""
        self._prev: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._xy = np.zeros((0, 2), np.float32)
        self._age = np.zeros(0, np.int64)
        self._next_id = 0

    def step(self, image: np.ndarray) -> Tracks:
        """Track into ``image`` and top up features; see the class docstring."""
        cfg = self.config
        img = check_image(image)
        if img.dtype != np.uint8:
            img = np.clip(np.rint(img * (FULL_SCALE_DN / cfg.float_full_scale)), 0, FULL_SCALE_DN).astype(np.uint8)
        img = np.ascontiguousarray(img)
        cur = img
        height, width = img.shape
        prev_xy = np.zeros((0, 2))
        if self._prev is not None and self._xy.shape[0]:
            lk = dict(
                winSize=(cfg.win_size, cfg.win_size),
                maxLevel=cfg.max_level,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.max_iter, cfg.eps_px),
            )
            p0 = self._xy.reshape(-1, 1, 2)
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev, cur, p0, None, **lk)
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, self._prev, p1, None, **lk)
            fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
            p1 = p1.reshape(-1, 2)
            b = cfg.border_px
            keep = (
                (st1.ravel() == 1)
                & (st2.ravel() == 1)
                & (fb <= cfg.fb_max_px)
                & (p1[:, 0] >= b)
                & (p1[:, 1] >= b)
                & (p1[:, 0] <= width - 1 - b)
                & (p1[:, 1] <= height - 1 - b)
            )
            prev_xy = self._xy[keep].astype(np.float64)
            self._xy, self._ids, self._age = p1[keep], self._ids[keep], self._age[keep] + 1
        elif self._xy.shape[0]:
            prev_xy = np.full((self._xy.shape[0], 2), np.nan)
        self._prev = cur
        n_old = self._ids.size
        if n_old < cfg.redetect_below_frac * cfg.max_corners:
            self._redetect(img)
        n_new = self._ids.size - n_old
        prev_xy = np.concatenate([prev_xy.reshape(-1, 2), np.full((n_new, 2), np.nan)])
        return Tracks(
            ids=self._ids.copy(), xy=self._xy.astype(np.float64), prev_xy=prev_xy, age=self._age.copy()
        )

    def _redetect(self, img: np.ndarray) -> None:
        cfg = self.config
        height, width = img.shape
        b = cfg.border_px
        if height <= 2 * b or width <= 2 * b:
            return
        mask = np.zeros(img.shape, np.uint8)
        mask[b : height - b, b : width - b] = 255
        radius = max(int(round(cfg.min_distance_px)), 1)
        for x, y in self._xy:
            cv2.circle(mask, (int(round(x)), int(round(y))), radius, 0, -1)
        want = cfg.max_corners - self._ids.size
        pts = cv2.goodFeaturesToTrack(
            img, want, cfg.quality_level, cfg.min_distance_px, mask=mask, blockSize=cfg.block_size
        )
        if pts is None:
            return
        pts = pts.reshape(-1, 2).astype(np.float32)
        n = pts.shape[0]
        self._xy = np.concatenate([self._xy, pts])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + n, dtype=np.int64)])
        self._age = np.concatenate([self._age, np.zeros(n, np.int64)])
        self._next_id += n


# ---------------------------------------------------------------- evaluation
def _check_sequence(frames: Sequence[np.ndarray], depths: Sequence[np.ndarray], poses: Sequence[Pose]) -> None:
    if len(frames) < 2:
        raise ValueError(f"frames must hold at least 2 images, got {len(frames)}")
    if len(depths) != len(frames) or len(poses) != len(frames):
        raise ValueError(
            f"frames, depths and poses must have equal lengths, got {len(frames)}, {len(depths)}, {len(poses)}"
        )


def track_metrics(
    tracks: Sequence[Tracks], depths: Sequence[np.ndarray], K: np.ndarray, poses: Sequence[Pose]
) -> dict[str, float]:
    """Accuracy and track statistics of one tracker's output sequence.

    Endpoint error of a track present in frames k and k+1:
    ``|xy_{k+1} - truth_flow(xy_k)|`` over the points with valid truth.

    Returns:
        Dict with ``tracks_per_frame_mean/median``, ``n_errors``,
        ``epe_median_px``, ``epe_p95_px``, ``epe_max_px``,
        ``within_1px_frac`` and ``mean_lifetime_frames`` (frames each track id
        was reported, tracks still alive at the end included).
    """
    return sequence_metrics(
        tracks,
        lambda k, a, b: pair_endpoint_errors(a, b, depths[k], depths[k + 1], K, poses[k], poses[k + 1]),
    )


def sequence_metrics(
    tracks: Sequence[Tracks], pair_errors: Callable[[int, Tracks, Tracks], np.ndarray]
) -> dict[str, float]:
    """:func:`track_metrics` for any source of truth.

    Args:
        tracks: One tracker's output per frame.
        pair_errors: ``(k, tracks_k, tracks_k1) -> endpoint errors [px]`` of the
            tracks present in frames k and k+1 that have valid truth.

    Returns:
        The keys of :func:`track_metrics`.
    """
    errs = [pair_errors(k, tracks[k], tracks[k + 1]) for k in range(len(tracks) - 1)]
    err = np.concatenate(errs) if errs else np.zeros(0)
    counts = np.array([len(t) for t in tracks])
    all_ids = np.concatenate([t.ids for t in tracks]) if tracks else np.zeros(0, np.int64)
    _, life = np.unique(all_ids, return_counts=True)
    return {
        "tracks_per_frame_mean": float(counts.mean()),
        "tracks_per_frame_median": float(np.median(counts)),
        **endpoint_error_stats(err),
        "mean_lifetime_frames": float(life.mean()) if life.size else float("nan"),
    }


def pair_endpoint_errors(a: Tracks, b: Tracks, depth_k: np.ndarray, depth_k1: np.ndarray, K: np.ndarray,
                         pose_k: Pose, pose_k1: Pose) -> np.ndarray:
    """Endpoint errors [px] of the tracks present in both frame k (``a``) and frame k+1 (``b``).

    ``|xy_{k+1} - truth_flow(xy_k)|`` over the points with valid truth
    (occlusion-checked with ``depth_k1``); empty when no track id is shared.
    """
    _, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    if ia.size == 0:
        return np.zeros(0)
    truth, valid = truth_flow(a.xy[ia], depth_k, K, *pose_k, *pose_k1, depth_k1=depth_k1)
    return np.linalg.norm(b.xy[ib][valid] - truth[valid], axis=1)


def endpoint_error_stats(err: np.ndarray) -> dict[str, float]:
    """``n_errors``, ``epe_median_px``, ``epe_p95_px``, ``epe_max_px``, ``within_1px_frac`` of endpoint errors (NaN if none)."""
    err = np.asarray(err, dtype=np.float64)
    nan = float("nan")
    return {
        "n_errors": int(err.size),
        "epe_median_px": float(np.median(err)) if err.size else nan,
        "epe_p95_px": float(np.percentile(err, 95)) if err.size else nan,
        "epe_max_px": float(err.max()) if err.size else nan,
        "within_1px_frac": float((err <= 1.0).mean()) if err.size else nan,
    }


def compare(
    factories: Mapping[str, Callable[[], Stepper]],
    frames: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    K: np.ndarray,
    poses: Sequence[Pose],
    repeats: int = 3,
    cv_threads: int | None = 1,
) -> dict[str, dict[str, float]]:
    """Run several trackers on the same frames in one process, interleaved.

    Each tracker is warmed up once (untimed, ``WARMUP_FRAMES`` frames on a throw-away
    instance). Then, ``repeats`` times, fresh instances process the sequence
    frame by frame, the trackers taking turns on each frame (order rotating),
    and only the ``step`` calls are timed with ``time.perf_counter``. Accuracy
    comes from the first repeat (the trackers are deterministic).

    Args:
        factories: Name -> zero-argument constructor of a tracker.
        frames: Images, each (H, W) uint8 or float32.
        depths: z-depth images [m], one per frame.
        K: Intrinsics (3, 3) [px].
        poses: (R_LC, r_C_L) per frame.
        repeats: Number of timed passes over the sequence, >= 1.
        cv_threads: OpenCV worker threads during the run (restored after);
            1 (default) times a single core, as on a flight computer, and
            avoids the multi-millisecond thread-pool wake-up stalls seen on
            a loaded 2-core machine; None leaves OpenCV's setting alone.

    Returns:
        Name -> :func:`track_metrics` plus ``ms_per_frame_mean`` and
        ``ms_per_frame_median`` (over all timed steps) and
        ``ms_per_frame_min_of_repeats_mean`` (mean over frames of each
        frame's fastest repeat: the noise-robust cost on a shared machine), and
        ``minor_faults_per_frame`` (see :func:`run_interleaved`).
    """
    _check_sequence(frames, depths, poses)
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    saved_threads = cv2.getNumThreads()
    if cv_threads is not None:
        cv2.setNumThreads(int(cv_threads))
    try:
        return _compare(factories, frames, depths, K, poses, repeats)
    finally:
        cv2.setNumThreads(saved_threads)


def _compare(
    factories: Mapping[str, Callable[[], Stepper]],
    frames: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    K: np.ndarray,
    poses: Sequence[Pose],
    repeats: int,
) -> dict[str, dict[str, float]]:
    outputs, timing = run_interleaved(factories, frames, repeats)
    return {name: {**track_metrics(outputs[name], depths, K, poses), **timing[name]} for name in factories}


WARMUP_FRAMES = 30
"""Untimed frames each tracker runs before the timed repeats. Two were too few:
in a fresh process the baseline's first pass over the sequence ran up to 20 %
slower than its later ones (its pyramids' buffers are large enough for glibc to
map and unmap them per call until its dynamic mmap threshold has risen; with the
threshold fixed through ``MALLOC_MMAP_THRESHOLD_`` the first pass was as fast),
while ``track-eval``, whose process had rendered the frames first, did not show
it. Steady state is what a flight computer runs in."""


def run_interleaved(
    factories: Mapping[str, Callable[[], Stepper]], frames: Sequence[np.ndarray], repeats: int
) -> tuple[dict[str, list[Tracks]], dict[str, dict[str, float]]]:
    """The timed part of :func:`compare`, shared with other truth sources.

    Each tracker is warmed up once, untimed, on a throw-away instance over
    the first ``WARMUP_FRAMES`` frames; then, ``repeats`` times, fresh instances process the sequence
    frame by frame, the trackers taking turns on each frame (order rotating),
    and only the ``step`` calls are timed. OpenCV's thread count is the
    caller's business (:func:`compare` sets it).

    Returns:
        (name -> the first repeat's Tracks per frame, name ->
        ``ms_per_frame_mean``, ``ms_per_frame_median``,
        ``ms_per_frame_min_of_repeats_mean`` and ``minor_faults_per_frame``: the
        calling thread's minor page faults in the timed steps, per step. A tracker
        whose per-call buffers the allocator hands back to the kernel and takes
        again pays the kernel's page zeroing inside its time: in a fresh process
        the OpenCV baseline took about 72 a frame at 256^2 and none once the
        process had rendered (README, issue 11), so a timing is comparable only
        between processes whose trackers fault alike.)
    """
    names = list(factories)
    for name in names:
        warm = factories[name]()
        for img in frames[:WARMUP_FRAMES]:
            warm.step(img)
    times: dict[str, list[float]] = {n: [] for n in names}
    faults = dict.fromkeys(names, 0)
    outputs: dict[str, list[Tracks]] = {n: [] for n in names}
    for rep in range(repeats):
        inst = {n: factories[n]() for n in names}
        for k, img in enumerate(frames):
            shift = (k + rep) % len(names)
            for name in names[shift:] + names[:shift]:
                f0 = _minor_faults()  # read outside the timed call
                t0 = time.perf_counter()
                out = inst[name].step(img)
                times[name].append(time.perf_counter() - t0)
                faults[name] += _minor_faults() - f0
                if rep == 0:
                    outputs[name].append(out)
    timing = {}
    for name in names:
        t_ms = 1e3 * np.asarray(times[name]).reshape(repeats, len(frames))
        # The trackers are deterministic: frame k costs the same work in every
        # repeat, so the minimum over repeats removes preemption spikes while
        # keeping the real per-frame costs (re-detections included).
        timing[name] = {
            "ms_per_frame_mean": float(t_ms.mean()),
            "ms_per_frame_median": float(np.median(t_ms)),
            "ms_per_frame_min_of_repeats_mean": float(t_ms.min(axis=0).mean()),
            "minor_faults_per_frame": faults[name] / t_ms.size,
        }
    return outputs, timing


def _minor_faults() -> int:
    """Minor page faults of the calling thread so far (Linux; the process's where threads are not counted apart)."""
    who = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)
    return resource.getrusage(who).ru_minflt


def evaluate(
    tracker_factory: Callable[[], Stepper],
    frames: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    K: np.ndarray,
    poses: Sequence[Pose],
    repeats: int = 1,
    cv_threads: int | None = 1,
) -> dict[str, float]:
    """Accuracy, track statistics and ms per frame of one tracker.

    See :func:`compare` (use it to time several trackers fairly) and
    :func:`track_metrics` for the keys.
    """
    return compare(
        {"tracker": tracker_factory}, frames, depths, K, poses, repeats=repeats, cv_threads=cv_threads
    )["tracker"]


# -------------------------------------------------------- synthetic descent
@dataclass(frozen=True)
class SyntheticDescent:
    """A rendered descent over a textured plane.

    Attributes:
        frames: Images, each (H, W) uint8 [DN].
        depths: z-depth images, each (H, W) float32 [m].
        K: Intrinsics (3, 3) [px].
        poses: (R_LC, r_C_L) per frame.
        homographies: Ground plane (X, Y, 1) [m] -> pixel maps, each (3, 3).
    """

    frames: list[np.ndarray]
    depths: list[np.ndarray]
    K: np.ndarray
    poses: list[Pose]
    homographies: list[np.ndarray]


R_LC_NADIR = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
"""Nadir camera: image x east, image y south, boresight down."""


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def lunar_texture(size: int, rng: np.random.Generator, n_craters: int | None = None) -> np.ndarray:
    """Lunar-like albedo/shading texture: fractal noise plus shaded craters.

    Args:
        size: Side of the square texture [texels].
        rng: Random generator.
        n_craters: Number of craters (default ~ size^2 / 4000).

    Returns:
        (size, size) float32 [DN], roughly 40..220.
    """
    tex = np.zeros((size, size), np.float32)
    octave = 2
    while octave <= size // 4:
        grid = rng.standard_normal((size // octave + 3, size // octave + 3)).astype(np.float32)
        up = cv2.resize(grid, None, fx=octave, fy=octave, interpolation=cv2.INTER_CUBIC)
        tex += up[octave : octave + size, octave : octave + size] * np.float32(octave**0.5)
        octave *= 2
    tex = (tex - tex.mean()) / tex.std()
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    n_craters = size * size // 4000 if n_craters is None else n_craters
    for _ in range(n_craters):
        cx, cy = rng.uniform(0, size, 2)
        rad = float(rng.uniform(3, size / 25))
        x0, x1 = int(max(cx - 2 * rad, 0)), int(min(cx + 2 * rad + 1, size))
        y0, y1 = int(max(cy - 2 * rad, 0)), int(min(cy + 2 * rad + 1, size))
        dx, dy = xx[y0:y1, x0:x1] - cx, yy[y0:y1, x0:x1] - cy
        rr = np.sqrt(dx * dx + dy * dy) / rad
        # Sun from the west: the west inner wall is shadowed, the east one lit.
        bowl = np.where(rr < 1.0, -dx / rad * 1.5, 0.0)
        rim = np.exp(-(((rr - 1.0) / 0.15) ** 2)) * 0.8
        tex[y0:y1, x0:x1] += (bowl + rim).astype(np.float32)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.0)
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(128.0 + 35.0 * tex, 0.0, 255.0).astype(np.float32)


def synthetic_descent(
    size: int = 256,
    n_frames: int = 30,
    seed: int = 0,
    altitude_m: tuple[float, float] = (120.0, 80.0),
    fov_deg: float = 60.0,
    lateral_m: tuple[float, float] = (12.0, -6.0),
    yaw_deg: float = 8.0,
    tilt_deg: float = 2.0,
    noise_dn: float = 0.0,
) -> SyntheticDescent:
    """Render a camera descending over a textured ground plane (z = 0).

    The plane carries :func:`lunar_texture` with a texel size equal to the
    ground sample distance at the lowest altitude (so rendering never
    minifies by more than the altitude ratio). Images come from
    ``cv2.warpPerspective`` with the texture -> image homography (INTER_LINEAR);
    the depth is analytic.

    Args:
        size: Image side [px] (square images, centred principal point).
        n_frames: Number of frames.
        seed: Texture / noise seed.
        altitude_m: (first, last) camera height [m].
        fov_deg: Horizontal field of view [deg].
        lateral_m: Total (east, north) travel over the sequence [m].
        yaw_deg: Total yaw about L z over the sequence [deg].
        tilt_deg: Amplitude of a sinusoidal tilt (about camera x and y) [deg].
        noise_dn: Standard deviation of added Gaussian pixel noise [DN].

    Returns:
        :class:`SyntheticDescent`.
    """
    rng = np.random.default_rng(seed)
    f = 0.5 * size / np.tan(np.radians(fov_deg) / 2)
    c = (size - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    h_hi, h_lo = altitude_m
    texel = min(h_hi, h_lo) / f  # GSD at the lowest altitude [m]
    half_extent = max(h_hi, h_lo) * (c + 1) / f * np.sqrt(2) * 1.2 + float(np.hypot(*lateral_m)) + 5.0
    n_tex = int(np.ceil(2 * half_extent / texel))
    tex = lunar_texture(n_tex, rng)
    # Texel (tx, ty) centre -> ground (X, Y): columns east, rows south.
    A = np.array([[texel, 0.0, -half_extent], [0.0, -texel, half_extent], [0.0, 0.0, 1.0]])
    frames, depths, poses, homs = [], [], [], []
    uu, vv = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    rays_C = np.stack([(uu - c) / f, (vv - c) / f, np.ones_like(uu)], axis=0).reshape(3, -1)
    for k in range(n_frames):
        s = k / max(n_frames - 1, 1)
        phase = 2 * np.pi * s
        R = (
            _rot(2, np.radians(yaw_deg) * s)
            @ R_LC_NADIR
            @ _rot(0, np.radians(tilt_deg) * np.sin(phase))
            @ _rot(1, np.radians(tilt_deg) * np.cos(phase))
        )
        r = np.array([lateral_m[0] * s, lateral_m[1] * s, h_hi + (h_lo - h_hi) * s])
        R_CL = R.T
        H_ground = K @ np.column_stack([R_CL[:, 0], R_CL[:, 1], -R_CL @ r])
        H_ground /= H_ground[2, 2]
        img = cv2.warpPerspective(tex, H_ground @ A, (size, size), flags=cv2.INTER_LINEAR)
        if noise_dn > 0:
            img = img + rng.normal(0.0, noise_dn, img.shape).astype(np.float32)
        frames.append(np.clip(np.rint(img), 0, FULL_SCALE_DN).astype(np.uint8))
        d_L = R @ rays_C
        depths.append((-r[2] / d_L[2]).reshape(size, size).astype(np.float32))
        poses.append((R, r))
        homs.append(H_ground)
    return SyntheticDescent(frames=frames, depths=depths, K=K, poses=poses, homographies=homs)


# ----------------------------------------------------------------------- CLI
def format_subpixel_setup(setup: dict[str, Any] | None) -> str:
    """``" (LK bias correction on)"`` or ``" (LK bias correction off, blend 0.3)"`` for a size's header."""
    if not setup:
        return ""
    if setup["lk_bias_correction"]:
        return " (LK bias correction on)"
    return f" (LK bias correction off, blend {setup['fb_blend']:g})"


def _table(results: Mapping[str, Mapping[str, float]], title: str) -> str:
    keys = [
        "tracks_per_frame_mean",
        "epe_median_px",
        "epe_p95_px",
        "within_1px_frac",
        "mean_lifetime_frames",
        "ms_per_frame_mean",
        "ms_per_frame_median",
        "ms_per_frame_min_of_repeats_mean",
    ]
    short = ["tracks", "epe_med", "epe_p95", "in_1px", "life", "ms_mean", "ms_median", "ms_min_rep"]
    lines = [title, f"{'':<16}" + "".join(f"{k:>11}" for k in short)]
    for name, m in results.items():
        lines.append(f"{name:<16}" + "".join(f"{m[k]:>11.4f}" for k in keys))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    """Compare the tracker with the OpenCV baseline on synthetic descents."""
    from vision import Tracker, TrackerConfig

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--noise", type=float, default=0.0, help="pixel noise [DN]")
    parser.add_argument("--sweep", action="store_true", help="also sweep baseline win_size / max_level")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads while timing (0: OpenCV default)")
    args = parser.parse_args(argv)
    for size in args.sizes:
        d = synthetic_descent(size=size, n_frames=args.frames, noise_dn=args.noise)
        facs: dict[str, Callable[[], Stepper]] = {
            "tracker": lambda: Tracker(TrackerConfig()),
            "opencv_baseline": lambda: OpenCVBaseline(BaselineConfig()),
        }
        if args.sweep:
            for win in (9, 15, 21):
                for lvl in (1, 2, 3):
                    cfg = BaselineConfig(win_size=win, max_level=lvl)
                    facs[f"cv w{win} L{lvl}"] = lambda cfg=cfg: OpenCVBaseline(cfg)
        res = compare(
            facs, d.frames, d.depths, d.K, d.poses, repeats=args.repeats, cv_threads=args.threads or None
        )
        print(_table(res, f"synthetic descent {size}x{size}, {args.frames} frames, noise {args.noise} DN"))


if __name__ == "__main__":
    main()
