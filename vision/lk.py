"""Lucas-Kanade / Tomasi-Kanade point tracking (paper §4).

:func:`lucas_kanade` is the reference implementation of eqs. (4.1)-(4.7):
for each point the gradient matrix ``G`` of eq. (4.5) is built from the
central-difference gradients (eqs. 3.1-3.2) of frame k around the point, and
the displacement is refined iteratively, ``d <- d + G^-1 e`` (eqs. 4.6-4.7),
with ``e = -sum [Ix It, Iy It]`` and ``It = J(x + d) - I(x)``, until the update
is smaller than ``eps``. Sampling at sub-pixel positions is exact bilinear
interpolation, vectorised over all points (all samples of one window share the
same fractional offset, so four shifted integer patches suffice).

:func:`lucas_kanade_opencv` runs the same single-level iteration through
``cv2.calcOpticalFlowPyrLK(maxLevel=0, OPTFLOW_USE_INITIAL_FLOW)``; it differs
only in OpenCV's Scharr derivative and 14-bit fixed-point interpolation, and
the tests check that both agree on the same inputs.

:func:`forward_backward` tracks points forward and back again and rejects the
ones that do not return to where they started.

:func:`lk_bias_gain` and :func:`lk_bias` give the bias of the translational solve
where the motion varies across its window (a descent's zoom and turn), for the
motion gradient :func:`affine_from_moments` solves for: the tracker's LK bias correction
(``TrackerConfig.lk_affine_correction``).

Rate: once per frame for all live tracks.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Backend = Literal["numpy", "opencv"]
BACKENDS = ("numpy", "opencv")

DEFAULT_WINDOW = 9
"""Default LK window side [px]."""
DEFAULT_MAX_ITER = 20
"""Default cap on LK iterations."""
DEFAULT_EPS = 0.01
"""Default convergence threshold on the update |delta d| [px]."""
DEFAULT_MIN_EIG = 1e-2
"""Default lower bound on the smallest eigenvalue of G per window pixel
[DN^2/px^2 per px]: below it the window is too flat to track (aperture)."""
OPENCV_DERIV_SCALE = 32
"""OpenCV's LK derivative (3-10-3 Scharr, kept as int16) over the central
difference of eqs. (3.1)-(3.2): 2 x (3 + 10 + 3) / 2 = 32 on a smooth image."""
OPENCV_G_SHIFT_BITS = 20
"""OpenCV's LK sums its integer gradient products and scales the sums by
2^-20 (FLT_SCALE in lkpyramid.cpp) before taking the eigenvalue."""
OPENCV_MIN_EIG_SCALE = OPENCV_DERIV_SCALE**2 / 2.0**OPENCV_G_SHIFT_BITS
"""``min_eig`` [DN^2/px^2 per px] -> OpenCV's ``minEigThreshold``: = 1/1024.

OpenCV's LK (``calcOpticalFlowPyrLK``, also its ``err`` with
``OPTFLOW_LK_GET_MIN_EIGENVALS``) tests ``lambda_1(G_cv) / (w h)`` where G_cv
sums products of the Scharr derivatives (32 x ours) scaled by 2^-20, i.e.
``G_cv = G * 32^2 / 2^20 = G / 1024`` with G of eq. (4.5). Both divide by the
window area, so the NumPy gate ``lambda_1(G) / w^2 >= min_eig`` is OpenCV's
``minEig >= min_eig / 1024`` (exact where Scharr's cross smoothing is
neutral, within a few per cent on smooth texture; tested)."""


@dataclass(frozen=True, slots=True)
class LKResult:
    """Outcome of a Lucas-Kanade solve for P points.

    Attributes:
        xy: Tracked positions in the new frame, (P, 2) float64 [px].
        status: True where the solve is valid (inside the image, G well
            conditioned and, for :func:`lucas_kanade`, converged: an update
            below ``eps`` within ``max_iter`` iterations), (P,) bool.
        iterations: Iterations used per point, (P,) int64 (-1 if unknown).
    """

    xy: np.ndarray
    status: np.ndarray
    iterations: np.ndarray


def _check_points(xy: object, name: str) -> np.ndarray:
    arr = np.asarray(xy, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2) [px], got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite [px]; got NaN or inf")
    return arr


def bilinear_patches(image: np.ndarray, xy: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample square windows centred at sub-pixel points by bilinear interpolation.

    Args:
        image: (H, W) uint8 or float32 [DN].
        xy: Window centres (x, y), (P, 2) float [px].
        half: Half-width r; windows are (2r + 1) x (2r + 1) samples at integer
            offsets from the centre.

    Returns:
        (patches, inside): patches (P, 2r + 1, 2r + 1) float32 [DN]; inside
        (P,) bool, False where the window plus its interpolation neighbours
        leaves the image (those patches hold clamped, meaningless values).
    """
    height, width = image.shape
    n = 2 * half + 1
    flat = np.ascontiguousarray(image).ravel()
    base = np.floor(xy).astype(np.int64)
    frac = (xy - base).astype(np.float32)
    x0 = base[:, 0] - half
    y0 = base[:, 1] - half
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + n < width) & (y0 + n < height)
    x0 = np.clip(x0, 0, width - n - 1)
    y0 = np.clip(y0, 0, height - n - 1)
    offs = (np.arange(n + 1)[:, None] * width + np.arange(n + 1)[None, :]).ravel()
    block = flat[(y0 * width + x0)[:, None] + offs[None, :]].reshape(-1, n + 1, n + 1).astype(np.float32)
    fx = frac[:, 0, None, None]
    fy = frac[:, 1, None, None]
    top = block[:, :-1, :-1] + fx * (block[:, :-1, 1:] - block[:, :-1, :-1])
    bottom = block[:, 1:, :-1] + fx * (block[:, 1:, 1:] - block[:, 1:, :-1])
    return top + fy * (bottom - top), inside


def lucas_kanade(
    prev_image: np.ndarray,
    image: np.ndarray,
    xy: np.ndarray,
    init_xy: np.ndarray | None = None,
    window: int = DEFAULT_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    eps: float = DEFAULT_EPS,
    min_eig: float = DEFAULT_MIN_EIG,
) -> LKResult:
    """Iterative Lucas-Kanade solve of ``G d = e``, eqs. (4.5)-(4.7).

    Inputs: two frames and points of frame k. Output: the points' sub-pixel
    positions in frame k+1. Rate: per frame, vectorised over points.

    Args:
        prev_image: Frame k (I), (H, W) uint8 or float32 [DN].
        image: Frame k+1 (J), same shape [DN].
        xy: Points in frame k, (P, 2) [px].
        init_xy: Initial guess of the points in frame k+1 (e.g. from block
            matching), (P, 2) [px]; None means ``xy``. The solve converges
            when the guess is within about half the window of the truth.
        window: Odd window side [px].
        max_iter: Iteration cap, >= 1.
        eps: Stop when the update is below this [px]; a point whose update
            is still >= eps after ``max_iter`` iterations is invalid.
        min_eig: Smallest eigenvalue of G / window^2 needed [DN^2/px^2].

    Returns:
        :class:`LKResult`.

    Raises:
        ValueError: On mismatched frames or invalid parameters.
    """
    if prev_image.shape != image.shape:
        raise ValueError(f"prev_image and image must share a shape, got {prev_image.shape} and {image.shape}")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3 [px], got {window!r}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter!r}")
    xy = _check_points(xy, "xy")
    guess = xy.copy() if init_xy is None else _check_points(init_xy, "init_xy")
    if guess.shape != xy.shape:
        raise ValueError(f"init_xy must match xy's shape {xy.shape}, got {guess.shape}")
    half = window // 2
    n_pts = xy.shape[0]
    # Template window with a one-pixel ring for the central differences.
    ring, inside = bilinear_patches(prev_image, xy, half + 1)
    tpl = ring[:, 1:-1, 1:-1]
    ix = 0.5 * (ring[:, 1:-1, 2:] - ring[:, 1:-1, :-2])  # eq. (3.1)
    iy = 0.5 * (ring[:, 2:, 1:-1] - ring[:, :-2, 1:-1])  # eq. (3.2)
    a = np.einsum("pij,pij->p", ix, ix, dtype=np.float64)  # eq. (4.5), G
    b = np.einsum("pij,pij->p", ix, iy, dtype=np.float64)
    c = np.einsum("pij,pij->p", iy, iy, dtype=np.float64)
    det = a * c - b * b
    lam_min = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    status = inside & (lam_min / float(window * window) >= min_eig) & (det > 0)
    safe_det = np.where(status, det, 1.0)
    pos = guess.copy()
    iterations = np.zeros(n_pts, np.int64)
    active = status.copy()
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.nonzero(active)[0]
        warped, ok = bilinear_patches(image, pos[idx], half)
        it = warped - tpl[idx]  # temporal difference I_t
        e0 = -np.einsum("pij,pij->p", ix[idx], it, dtype=np.float64)  # eq. (4.5), e
        e1 = -np.einsum("pij,pij->p", iy[idx], it, dtype=np.float64)
        # d = G^-1 e, eq. (4.7), with the 2 x 2 inverse written out.
        dx = (c[idx] * e0 - b[idx] * e1) / safe_det[idx]
        dy = (a[idx] * e1 - b[idx] * e0) / safe_det[idx]
        pos[idx, 0] += np.where(ok, dx, 0.0)
        pos[idx, 1] += np.where(ok, dy, 0.0)
        iterations[idx] += 1
        status[idx] &= ok
        active[idx] = ok & (dx * dx + dy * dy >= eps * eps)
    # Still active after max_iter updates: the last update was >= eps, so the
    # solve did not converge and its position is not a result.
    status &= ~active
    height, width = image.shape
    on_image = (pos[:, 0] >= half) & (pos[:, 1] >= half) & (pos[:, 0] <= width - 1 - half) & (pos[:, 1] <= height - 1 - half)
    return LKResult(xy=pos, status=status & on_image, iterations=iterations)


def _as_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def lucas_kanade_opencv(
    prev_image: np.ndarray,
    image: np.ndarray,
    xy: np.ndarray,
    init_xy: np.ndarray | None = None,
    window: int = DEFAULT_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    eps: float = DEFAULT_EPS,
    min_eig: float = DEFAULT_MIN_EIG,
) -> LKResult:
    """Single-level LK through OpenCV, same contract as :func:`lucas_kanade`.

    ``cv2.calcOpticalFlowPyrLK(maxLevel=0, flags=OPTFLOW_USE_INITIAL_FLOW)``:
    the same iteration as eqs. (4.5)-(4.7) (no pyramid: the initial guess from
    block matching replaces it), with Scharr derivatives and fixed-point
    bilinear weights. Frames are converted to uint8 (rounded) when float32,
    since OpenCV's LK accepts only 8-bit images.

    OpenCV keeps ``status`` 1 when it stops at the iteration cap, and reports
    neither the iteration count nor the last update, so unlike
    :func:`lucas_kanade` this status does not include convergence; the
    forward-backward check (:func:`forward_backward`) is what rejects such
    points here.

    Returns:
        :class:`LKResult` (``iterations`` are -1: OpenCV does not report them).
    """
    xy = _check_points(xy, "xy")
    guess = xy if init_xy is None else _check_points(init_xy, "init_xy")
    n_pts = xy.shape[0]
    if n_pts == 0:
        return LKResult(np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0, np.int64))
    nxt, st, _ = cv2.calcOpticalFlowPyrLK(
        _as_uint8(prev_image),
        _as_uint8(image),
        xy.astype(np.float32).reshape(-1, 1, 2),
        guess.astype(np.float32).reshape(-1, 1, 2),
        winSize=(window, window),
        maxLevel=0,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iter), float(eps)),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        minEigThreshold=float(min_eig) * OPENCV_MIN_EIG_SCALE,
    )
    pos = nxt.reshape(-1, 2).astype(np.float64)
    half = window // 2
    height, width = image.shape
    on_image = (pos[:, 0] >= half) & (pos[:, 1] >= half) & (pos[:, 0] <= width - 1 - half) & (pos[:, 1] <= height - 1 - half)
    return LKResult(xy=pos, status=st.reshape(-1).astype(bool) & on_image, iterations=np.full(n_pts, -1, np.int64))


def _seeded_lk_kwargs(window: int, max_iter: int, eps: float, min_eig: float, residual: bool = True) -> dict:
    """``calcOpticalFlowPyrLK`` keywords of the lean paths: one level, seeded, OpenCV's eigenvalue gate.

    With ``residual`` False the caller discards OpenCV's third output, so it
    asks for the window's min-eigenvalue there (``OPTFLOW_LK_GET_MIN_EIGENVALS``),
    which OpenCV has computed anyway, instead of the mean absolute difference
    of the aligned windows, which costs one more interpolation pass over every
    point's window after the solve. The tracked points and the status are the
    same either way (the flag only chooses what goes into the third output);
    at the tracker's 13 px window it takes about a fifth off the
    forward-backward LK time.
    """
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW if residual else cv2.OPTFLOW_USE_INITIAL_FLOW | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
    return dict(
        winSize=(window, window),
        maxLevel=0,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iter), float(eps)),
        flags=flags,
        minEigThreshold=float(min_eig) * OPENCV_MIN_EIG_SCALE,
    )


def forward_backward_opencv_fast(
    prev_image: np.ndarray,
    image: np.ndarray,
    xy: np.ndarray,
    init_xy: np.ndarray,
    back_offset: np.ndarray,
    window: int,
    max_iter: int,
    eps: float,
    min_eig: float,
    back_window: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Lean forward-backward OpenCV LK for callers that validated everything
    already (the tracker's hot path; :func:`forward_backward` is the checked
    version).

    Args:
        prev_image, image: uint8 frames k and k+1.
        xy: Points in frame k, (P, 2) [px].
        init_xy: Forward initial guesses in frame k+1, (P, 2) [px].
        back_offset: The backward solve starts at forward result + this, (P, 2) [px].
        window, max_iter, eps, min_eig: As in :func:`lucas_kanade`.
        back_window: LK window of the backward solve [px] (None: ``window``).

    Returns:
        (xy_k1 (P, 2) float64 [px], fb_error (P,) float64 [px], inf where a
        solve failed).
    """
    kw = _seeded_lk_kwargs(window, max_iter, eps, min_eig, residual=False)
    p0 = xy.astype(np.float32).reshape(-1, 1, 2)
    fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev_image, image, p0, init_xy.astype(np.float32).reshape(-1, 1, 2), **kw)
    bwd_init = fwd + back_offset.astype(np.float32).reshape(-1, 1, 2)
    if back_window is not None and back_window != window:
        kw["winSize"] = (back_window, back_window)
    bwd, st2, _ = cv2.calcOpticalFlowPyrLK(image, prev_image, fwd, bwd_init, **kw)
    err = np.sqrt(((bwd - p0) ** 2).sum(axis=2, dtype=np.float64)).ravel()
    err[(st1.ravel() == 0) | (st2.ravel() == 0)] = np.inf
    return fwd.reshape(-1, 2).astype(np.float64), err


def seeded_lk_kwargs(
    window: int,
    max_iter: int,
    eps: float,
    min_eig: float,
    back_window: int | None = None,
    back_max_iter: int | None = None,
    back_eps: float | None = None,
) -> tuple[dict, dict]:
    """``calcOpticalFlowPyrLK`` keywords of :func:`forward_backward_opencv_ok`'s
    forward and backward solves (built once per sequence by the tracker); the
    backward solve's window, iteration cap and convergence threshold default
    to the forward one's."""
    fwd = _seeded_lk_kwargs(window, max_iter, eps, min_eig, residual=False)
    back = _seeded_lk_kwargs(
        window if back_window is None else back_window,
        max_iter if back_max_iter is None else back_max_iter,
        eps if back_eps is None else back_eps,
        min_eig,
        residual=False,
    )
    return fwd, back


def forward_backward_opencv_ok(
    prev_image: np.ndarray, image: np.ndarray, pts: np.ndarray, kw_fwd: dict, kw_back: dict, fb_max_px: float,
    blend: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`forward_backward_opencv_fast` with the tracker's inputs already
    in OpenCV's form, returning the verdict instead of the round-trip error
    (the tracker's hot path: fewer conversions and array operations).

    Args:
        prev_image, image: uint8 frames k and k+1.
        pts: (3, P, 2) float32 [px]: the points in frame k, the forward
            initial guesses in frame k+1, and the backward offsets (the
            backward solve starts at forward result + offset).
        kw_fwd, kw_back: Keywords of the forward and backward solves
            (:func:`seeded_lk_kwargs`).
        fb_max_px: Largest accepted round-trip error [px].
        blend: The returned position is the forward solution minus this
            fraction of the round trip (backward result - start): 0 gives the
            forward solution; w gives (1 - w) x the forward solve's
            displacement + w x the backward solve's, the two windows'
            estimates averaged (see ``TrackerConfig.fb_blend``).

    Returns:
        (xy_k1 (P, 2) float32 [px], ok (P,) bool: both solves valid and the
        round trip within ``fb_max_px``; the same verdict as
        ``forward_backward_opencv_fast(...)[1] <= fb_max_px``).
    """
    p0 = pts[0]
    fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev_image, image, p0, pts[1].copy(), **kw_fwd)
    fwd = fwd.reshape(-1, 2)
    bwd, st2, _ = cv2.calcOpticalFlowPyrLK(image, prev_image, fwd, fwd + pts[2], **kw_back)
    d = (bwd.reshape(-1, 2) - p0).astype(np.float64)
    dx, dy = d[:, 0], d[:, 1]
    ok = dx * dx + dy * dy <= fb_max_px * fb_max_px
    ok &= (st1 & st2).reshape(-1).view(bool)
    if blend:
        fwd = (fwd - blend * d).astype(np.float32)
    return fwd, ok


def forward_opencv_fast(
    prev_image: np.ndarray,
    image: np.ndarray,
    xy: np.ndarray,
    init_xy: np.ndarray,
    window: int,
    max_iter: int,
    eps: float,
    min_eig: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One lean OpenCV LK pass, frame k to k+1 (the tracker's hot path
    without the forward-backward check; arguments as in
    :func:`forward_backward_opencv_fast`).

    Returns:
        (xy_k1 (P, 2) float64 [px], ok (P,) bool: the solve converged with a
        well-conditioned G, residual (P,) float64 [DN]: OpenCV's mean absolute
        difference of the aligned windows).
    """
    kw = _seeded_lk_kwargs(window, max_iter, eps, min_eig)
    p0 = xy.astype(np.float32).reshape(-1, 1, 2)
    fwd, st, err = cv2.calcOpticalFlowPyrLK(prev_image, image, p0, init_xy.astype(np.float32).reshape(-1, 1, 2), **kw)
    return fwd.reshape(-1, 2).astype(np.float64), st.ravel() != 0, err.ravel().astype(np.float64)


@dataclass(frozen=True, slots=True)
class FBResult:
    """Outcome of :func:`forward_backward`.

    Attributes:
        xy: Forward-tracked positions in frame k+1, (P, 2) float64 [px].
        ok: Both solves valid and the round trip closes within the limit, (P,) bool.
        fb_error: Distance between the start point and the back-tracked point,
            (P,) float64 [px] (inf where a solve failed).
        back_xy: The back-tracked points in frame k, (P, 2) float64 [px].
    """

    xy: np.ndarray
    ok: np.ndarray
    fb_error: np.ndarray
    back_xy: np.ndarray | None = None


def forward_backward(
    prev_image: np.ndarray,
    image: np.ndarray,
    xy: np.ndarray,
    init_xy: np.ndarray,
    back_init_xy: np.ndarray,
    fb_max_px: float,
    backend: Backend = "numpy",
    window: int = DEFAULT_WINDOW,
    max_iter: int = DEFAULT_MAX_ITER,
    eps: float = DEFAULT_EPS,
    min_eig: float = DEFAULT_MIN_EIG,
    back_window: int | None = None,
) -> FBResult:
    """Forward-backward consistency check (Kalal et al.) around LK.

    Track ``xy`` from frame k into k+1 starting at ``init_xy``, then track the
    result back into frame k starting at ``back_init_xy`` (seed it
    independently of the forward result, e.g. result - block-matching shift),
    and accept a point when it returns within ``fb_max_px`` of where it began.

    Args:
        prev_image, image: Frames k and k+1, (H, W) [DN].
        xy: Points in frame k, (P, 2) [px].
        init_xy: Forward initial guesses in frame k+1, (P, 2) [px].
        back_init_xy: Backward initial guesses in frame k, (P, 2) [px]; None
            re-uses the forward seed's displacement.
        fb_max_px: Largest accepted round-trip error [px].
        backend: ``"numpy"`` (:func:`lucas_kanade`) or ``"opencv"``
            (:func:`lucas_kanade_opencv`).
        window, max_iter, eps, min_eig: As in :func:`lucas_kanade`.
        back_window: LK window of the backward solve [px] (None: ``window``).

    Returns:
        :class:`FBResult`.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    solve = lucas_kanade if backend == "numpy" else lucas_kanade_opencv
    kw = dict(window=window, max_iter=max_iter, eps=eps, min_eig=min_eig)
    fwd = solve(prev_image, image, xy, init_xy, **kw)
    if back_init_xy is None:
        back_init_xy = fwd.xy - (np.asarray(init_xy) - xy)
    if back_window is not None:
        kw["window"] = back_window
    bwd = solve(image, prev_image, fwd.xy, back_init_xy, **kw)
    err = np.linalg.norm(bwd.xy - xy, axis=1) if xy.shape[0] else np.zeros(0)
    valid = fwd.status & bwd.status
    err = np.where(valid, err, np.inf)
    return FBResult(xy=fwd.xy, ok=valid & (err <= fb_max_px), fb_error=err, back_xy=bwd.xy)


AFFINE_MAX_NORM = 0.25
"""Largest accepted frame-to-frame motion gradient |A| (Frobenius) [-]: a 25 % change of scale or a
14 deg turn between two frames is no motion a tracker seeded by block matching follows; beyond it the
fit is taken as failed."""


def affine_from_moments(sxx: float, sxy: float, syy: float, bxx: float, bxy: float, byx: float,
                        byy: float) -> np.ndarray | None:
    """The gradient ``A`` of a frame's motion field, least squares ``d = c + A x`` over its points, from the
    centred moments of the positions (``sxx = sum x x``, ``sxy``, ``syy``) and of positions with displacements
    (``bxy = sum x d_y``, ``b[j][i] = sum x_j d_i``); ``A[i, j] = d(d_i) / d(x_j)``, the motion's Jacobian
    minus the identity.

    Returns:
        A (2, 2) [-], or None: points on a line, or ``|A| > AFFINE_MAX_NORM``.
    """
    det = sxx * syy - sxy * sxy
    if not det > 1e-9 * sxx * syy:
        return None
    # A[i, :] = M^-1 [sum x d_i, sum y d_i], M = [[sxx, sxy], [sxy, syy]].
    axx, axy = (syy * bxx - sxy * byx) / det, (sxx * byx - sxy * bxx) / det
    ayx, ayy = (syy * bxy - sxy * byy) / det, (sxx * byy - sxy * bxy) / det
    if not axx * axx + axy * axy + ayx * ayx + ayy * ayy <= AFFINE_MAX_NORM * AFFINE_MAX_NORM:  # also NaN
        return None
    return np.array([[axx, axy], [ayx, ayy]])


def lk_bias_gain(image: np.ndarray, xy: np.ndarray, window: int, blend_window: int | None = None,
                 blend: float = 0.0) -> np.ndarray:
    """The gain ``K`` of a translational LK solve's bias on the motion's gradient ``A``.

    Where the displacement varies across the window, ``d(x) = d0 + A (x - xy)``, the solve of
    ``G d = e`` (eq. 4.5) linearised about the truth returns ``d0 + b`` with

        ``b = G^-1 sum_w g g^T A (x - xy) = K vec(A)``,  ``vec(A) = (A_xx, A_xy, A_yx, A_yy)``,

    the gradient-weighted mean of the displacement's variation: zero for a window whose gradient
    energy is centred on the point, up to ``|A| x`` its off-centre distance otherwise (a 2 % zoom
    and gradient energy 2 px off centre: 0.04 px). ``g`` is the central-difference gradient
    (eqs. 3.1-3.2; its scale cancels) over the integer window nearest ``xy``, ``x - xy`` measured
    from the sub-pixel point. ``K`` depends only on the point's own texture, which moves with it,
    so a track can keep it for a few frames (:func:`lk_bias`).

    With ``blend``: the gain of the forward-backward blend's position, the forward solve in
    ``window`` less ``blend`` x the round trip through a backward solve in ``blend_window``
    (:func:`forward_backward_opencv_ok`), i.e. ``(1 - blend) K_window + blend K_blend_window``: the
    backward solve runs on the inverse motion, ``-A`` to first order, over the same texture.

    Args:
        image: Frame k (the solve's first image), 2-D [DN].
        xy: (N, 2) the points in frame k [px]; their window plus a one-pixel ring must lie inside
            ``image`` (indices are clipped to it otherwise).
        window: The solve's window side [px], odd.
        blend_window: The backward solve's window side [px], odd, at most ``window`` (None: ``window``).
        blend: The blend's weight on the backward solve [-], 0..1.

    Returns:
        (N, 2, 4) float64 ``K`` [px]; 0 where ``G`` is singular.
    """
    n = xy.shape[0]
    h = window // 2
    side = window + 2
    height, width = image.shape
    ij = np.rint(xy).astype(np.intp)
    np.maximum(ij, h + 1, out=ij)
    np.minimum(ij, _upper(width - h - 2, height - h - 2), out=ij)
    st = image.strides
    view = np.ndarray((height - side + 1, width - side + 1, side, side), image.dtype, image, 0, st + st)
    # Each patch flattened: the window's pixels are those of the patch's rows and columns 1 .. window,
    # a run of flat indices [side + 1, side * (side - 1) - 1) that also holds the ring's columns
    # (weighted 0 by the moment basis). Gradients along the run are then long contiguous operations.
    p = view[ij[:, 1] - h - 1, ij[:, 0] - h - 1].reshape(n, side * side).astype(np.float32)
    lo, hi = side + 1, side * (side - 1) - 1
    gx = p[:, lo + 1 : hi + 1] - p[:, lo - 1 : hi - 1]
    gy = p[:, lo + side : hi + side] - p[:, lo - side : hi - side]
    q = np.empty((3, n, hi - lo), np.float32)
    np.multiply(gx, gx, out=q[0])
    np.multiply(gx, gy, out=q[1])
    np.multiply(gy, gy, out=q[2])
    inner = window if blend_window is None or not blend else min(blend_window, window)
    windows = 1 if inner == window else 2
    # m[product (xx, xy, yy), point, window, (sum, sum * ox, sum * oy, -)] (o from the centre pixel)
    basis = _moment_basis(window, inner)
    m = (q.reshape(3 * n, hi - lo) @ basis).astype(np.float64).reshape(3, n, windows, 4)
    s = m[..., 0]
    # With x - xy = o - f (f: the point's offset from its window's centre pixel):
    # r2[point, window, product, axis] = sum g_i g_j (x - xy)_axis.
    f = xy - ij
    r2 = (m[..., 1:3] - s[..., None] * f[None, :, None, :]).transpose(1, 2, 0, 3).copy()
    # T[point, window, i] = sum_jk A_jk sum g_i g_j r_k: row i reads products (i, i + 1), a view.
    st2 = r2.strides
    t = np.ndarray((n, windows, 2, 4), np.float64, r2, 0, (st2[0], st2[1], st2[2], st2[3]))
    gxx, gxy, gyy = s
    det = gxx * gyy - gxy * gxy
    inv = 1.0 / np.where(det > 1e-9 * gxx * gyy, det, np.inf)
    ginv = (s[[2, 1, 1, 0]].transpose(1, 2, 0) * (inv[..., None] * _SIGNS)).reshape(n, windows, 2, 2)
    k = ginv @ t
    if windows == 1:
        return k[:, 0]
    return (1.0 - blend) * k[:, 0] + blend * k[:, 1]


_SIGNS = np.array([1.0, -1.0, -1.0, 1.0])


@functools.lru_cache(maxsize=16)
def _upper(x_max: int, y_max: int) -> np.ndarray:
    """The (2,) intp upper bounds (x, y) of :func:`lk_bias_gain`'s window centres (read-only)."""
    a = np.array([x_max, y_max], np.intp)
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=16)
def _moment_basis(window: int, inner: int) -> np.ndarray:
    """(run, 4) or (run, 8) float32 rows [1, ox, oy, 0] over the flat run of :func:`lk_bias_gain`'s
    patch (side = window + 2), zero on the ring's columns, then the same for the centred ``inner``
    window when it is smaller (the fourth columns pad the product to a shape OpenBLAS multiplies
    faster); read-only."""
    side, h = window + 2, window // 2
    j = np.arange(side + 1, side * (side - 1) - 1)
    oy, ox = j // side - h - 1, j % side - h - 1
    cols = []
    for w in (window,) if inner == window else (window, inner):
        inside = ((np.abs(ox) <= w // 2) & (np.abs(oy) <= w // 2)).astype(np.float32)
        cols += [inside, inside * ox, inside * oy, 0 * inside]
    b = np.stack(cols, axis=1).astype(np.float32)
    b.flags.writeable = False
    return b


def lk_bias(gain: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(N, 2) bias ``b = K vec(A)`` [px] of translational LK solves with gains ``gain`` (N, 2, 4)
    (:func:`lk_bias_gain`) under the motion gradient ``a`` (2, 2) (:func:`affine_from_moments`)."""
    return (gain.reshape(-1, 4) @ a.reshape(4)).reshape(-1, 2)
