"""Feature-point detection inside fixation areas (paper §3, Benedetti & Perona).

Stages, each a plain function:

1. :func:`gradients` -- central differences, eqs. (3.1)-(3.2).
2. :func:`structure_tensor` -- G = [[a, b], [b, c]] summed over the W1 x W1
   patch, eq. (3.3).
3. :func:`p_lambda` / :func:`eigen_threshold_test` -- the square-root-free test
   of eq. (3.4): keep a pixel when P(lambda_t) > 0 and a > lambda_t, which is
   exactly "smallest eigenvalue of G > lambda_t".
4. Non-maximum suppression on the smallest eigenvalue lambda_1 (computed,
   with its square root, only at the retained pixels), then the strongest
   points are kept.

Search strategies (§3): ``"exhaustive"`` evaluates every pixel (the paper's
choice, because sub-images are small); ``"random"`` draws pixels in a random
order from a caller-supplied ``numpy.random.Generator`` and accepts each one
whose test passes (and that is not next to an accepted one) until enough are
found.

All functions work on the last two axes, so a stack of sub-images (T, h, w) is
processed in one vectorised pass. Rate: run when features are (re)detected.
"""

from __future__ import annotations

import functools

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Strategy = Literal["exhaustive", "random"]
STRATEGIES = ("exhaustive", "random")

RANDOM_BATCH_FACTOR = 4
"""Random search evaluates candidates in batches of this many per wanted point."""


def gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference image gradients, eqs. (3.1)-(3.2).

    ``Ix(x, y) = (I(x+1, y) - I(x-1, y)) / 2`` and
    ``Iy(x, y) = (I(x, y+1) - I(x, y-1)) / 2``.

    Args:
        image: (..., H, W) uint8 or float [DN].

    Returns:
        (Ix, Iy), each (..., H, W) float32 [DN/px]; zero on the outermost
        column (Ix) / row (Iy), where the difference is undefined.
    """
    img = image.astype(np.float32, copy=False)
    ix = np.zeros(img.shape, np.float32)
    iy = np.zeros(img.shape, np.float32)
    ix[..., :, 1:-1] = 0.5 * (img[..., :, 2:] - img[..., :, :-2])
    iy[..., 1:-1, :] = 0.5 * (img[..., 2:, :] - img[..., :-2, :])
    return ix, iy


def _centred_box_sum(x: np.ndarray, window: int) -> np.ndarray:
    """Sum over the window x window neighbourhood centred at each element of
    the last two axes; zero where the window leaves the array.

    A stack (..., H, W) is filtered as one tall 2-D image: rows near a seam
    between two arrays see the neighbour, but those are exactly the rows
    where the window leaves its own array, which are zeroed anyway.
    """
    r = window // 2
    shape = x.shape
    out = np.zeros(shape, np.float32)
    if shape[-1] < window or shape[-2] < window:
        return out
    flat = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, shape[-1])
    summed = cv2.boxFilter(flat, cv2.CV_32F, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)
    summed = summed.reshape(shape)
    rows, cols = shape[-2], shape[-1]
    out[..., r : rows - r, r : cols - r] = summed[..., r : rows - r, r : cols - r]
    return out


def structure_tensor(ix: np.ndarray, iy: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradient matrix G summed over the W1 x W1 patch W1, eq. (3.3).

    Args:
        ix, iy: Gradients from :func:`gradients`, (..., H, W) [DN/px].
        window: Patch side W1 [px], odd and >= 1.

    Returns:
        (a, b, c) = (sum Ix^2, sum Ix Iy, sum Iy^2), each (..., H, W) float32
        [DN^2]; zero where the patch does not fit in the array.

    Raises:
        ValueError: If ``window`` is not a positive odd integer.
    """
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd integer (W1), got {window!r}")
    return (
        _centred_box_sum(ix * ix, window),
        _centred_box_sum(ix * iy, window),
        _centred_box_sum(iy * iy, window),
    )


def p_lambda(a: np.ndarray, b: np.ndarray, c: np.ndarray, lambda_t: float) -> np.ndarray:
    """``P(lambda_t) = (a - lambda_t)(c - lambda_t) - b^2``, eq. (3.4) [DN^4]."""
    return (a - lambda_t) * (c - lambda_t) - b * b


def eigen_threshold_test(a: np.ndarray, b: np.ndarray, c: np.ndarray, lambda_t: float) -> np.ndarray:
    """Square-root-free corner test of eq. (3.4) (Benedetti & Perona, step 4).

    Keeps a pixel when ``P(lambda_t) > 0`` and ``a > lambda_t``. Since
    ``G - lambda_t I`` is then positive definite (Sylvester), this equals
    ``min eig(G) > lambda_t`` without square roots or divisions.

    Args:
        a, b, c: Entries of G, same shape [DN^2].
        lambda_t: Threshold [DN^2].

    Returns:
        Boolean mask, same shape.
    """
    return (a > lambda_t) & (p_lambda(a, b, c, lambda_t) > 0.0)


def min_eigenvalue(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue lambda_1 of [[a, b], [b, c]] [DN^2] (NMS score)."""
    half_diff = 0.5 * (a - c)
    return 0.5 * (a + c) - np.sqrt(half_diff * half_diff + b * b)


def detection_margin(window: int) -> int:
    """Pixels next to a (sub-)image edge where G is undefined: the central
    difference needs one neighbour and the W1 patch ``window // 2`` more."""
    return window // 2 + 1


@dataclass(frozen=True, slots=True)
class Features:
    """Detected feature points.

    Attributes:
        xy: Positions (x, y), (M, 2) float64 [px], integer pixel centres.
        score: Smallest eigenvalue lambda_1 of G at each point, (M,) float64 [DN^2].
        region: Index of the sub-image each point was found in, (M,) int64.
    """

    xy: np.ndarray
    score: np.ndarray
    region: np.ndarray


def _check_detector_args(
    window: int, lambda_t: float, max_features: int, nms_radius: int, strategy: str, rng: object
) -> None:
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd integer (W1), got {window!r}")
    if not np.isfinite(lambda_t) or lambda_t < 0:
        raise ValueError(f"lambda_t must be a finite threshold >= 0 [DN^2], got {lambda_t!r}")
    if max_features < 1:
        raise ValueError(f"max_features must be >= 1, got {max_features!r}")
    if nms_radius < 0:
        raise ValueError(f"nms_radius must be >= 0 [px], got {nms_radius!r}")
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    if strategy == "random" and not isinstance(rng, np.random.Generator):
        raise ValueError(f"strategy='random' needs rng to be a numpy.random.Generator, got {type(rng).__name__}")


def detect_in_subimages(
    image: np.ndarray,
    top_left: np.ndarray,
    size: tuple[int, int],
    window: int = 3,
    lambda_t: float = 1500.0,
    max_features: int = 8,
    nms_radius: int = 1,
    strategy: Strategy = "exhaustive",
    rng: np.random.Generator | None = None,
) -> Features:
    """Detect feature points inside equally sized sub-images (paper §3).

    The sub-images (with a margin of :func:`detection_margin` pixels, so that
    G is defined on the whole sub-image) are cut out and stacked, and the
    detector runs once, vectorised, over the stack.

    Args:
        image: Frame, (H, W) uint8 or float32 [DN].
        top_left: Sub-image corners (x, y), (T, 2) int [px]; each sub-image
            plus margin must lie inside the image.
        size: (w, h) sub-image size [px].
        window: W1, side of the patch G is summed over [px], odd.
        lambda_t: Threshold on the smallest eigenvalue of G [DN^2], eq. (3.4).
        max_features: Most points kept per sub-image (strongest lambda_1 first).
        nms_radius: Non-maximum suppression radius [px]: a kept point is the
            largest lambda_1 in its (2 r + 1)^2 neighbourhood, ties going to
            the first pixel in raster order (exhaustive), or is
            more than r pixels (Chebyshev) from earlier accepted points (random).
        strategy: ``"exhaustive"`` (default, paper) or ``"random"``.
        rng: Generator for ``"random"``; never the global NumPy state.

    Returns:
        :class:`Features` with ``region`` indexing ``top_left``; per sub-image
        in decreasing ``score`` (exhaustive) or acceptance order (random).

    Raises:
        ValueError: On invalid parameters or a sub-image outside the image.
    """
    _check_detector_args(window, lambda_t, max_features, nms_radius, strategy, rng)
    w, h = int(size[0]), int(size[1])
    if w < 1 or h < 1:
        raise ValueError(f"size must be positive (w, h), got {size!r}")
    top_left = np.asarray(top_left, dtype=np.int64).reshape(-1, 2)
    n_t = top_left.shape[0]
    if n_t == 0:
        return Features(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    m = detection_margin(window)
    height, width = image.shape
    if (
        top_left.min() < m
        or (top_left[:, 0] + w + m).max() > width
        or (top_left[:, 1] + h + m).max() > height
    ):
        raise ValueError(
            f"sub-images of size {size} at top_left must keep a margin of {m} px inside the image {image.shape}"
        )
    # Stack (T, h + 2m, w + 2m); slicing in a loop beats one fancy index here.
    stack = np.empty((n_t, h + 2 * m, w + 2 * m), np.float32)
    for t, (x, y) in enumerate(top_left.tolist()):
        stack[t] = image[y - m : y + h + m, x - m : x + w + m]
    if strategy == "exhaustive":
        a, b, c = _inner_structure_tensor(stack, window, m, h, w)
        keep = eigen_threshold_test(a, b, c, lambda_t)
        t_idx, r_idx, c_idx, score = _nms_top_k(keep, a, b, c, nms_radius, max_features)
    else:
        assert rng is not None
        ix, iy = gradients(stack)
        t_idx, r_idx, c_idx, score = _random_search(ix, iy, m, (h, w), window, lambda_t, max_features, nms_radius, rng)
    xy = np.stack([top_left[t_idx, 0] + c_idx, top_left[t_idx, 1] + r_idx], axis=1).astype(np.float64)
    return Features(xy=xy.reshape(-1, 2), score=score.astype(np.float64), region=t_idx.astype(np.int64))


def _inner_structure_tensor(
    stack: np.ndarray, window: int, m: int, h: int, w: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`gradients` then :func:`structure_tensor` of a stack of
    sub-images (T, h + 2m, w + 2m), cropped to the inner (T, h, w): the same
    values in fewer array operations (the detector's hot path at refills).

    Only what the inner sums read is computed: the central differences on
    the (h + 2r) x (w + 2r) block around the inner pixels (r = window // 2,
    m = r + 1, so they never use the outermost row or column), their three
    products in one array, and the W1 x W1 sums as W1 shifted additions
    along the rows, then W1 along the columns. On 8-bit data every value is
    an exact multiple of 1/16 well inside float32's integers, so the sums do
    not depend on their order and equal the two-stage result exactly.
    """
    r = window // 2
    lo = m - r
    n_r, n_c = h + 2 * r, w + 2 * r
    ix = stack[:, lo : lo + n_r, lo + 1 : lo + n_c + 1] - stack[:, lo : lo + n_r, lo - 1 : lo + n_c - 1]
    iy = stack[:, lo + 1 : lo + n_r + 1, lo : lo + n_c] - stack[:, lo - 1 : lo + n_r - 1, lo : lo + n_c]
    ix *= 0.5
    iy *= 0.5
    prods = np.empty((3,) + ix.shape, np.float32)
    np.multiply(ix, ix, out=prods[0])
    np.multiply(ix, iy, out=prods[1])
    np.multiply(iy, iy, out=prods[2])
    rows = prods[..., 0:w].copy()
    for k in range(1, window):
        rows += prods[..., k : k + w]
    boxed = rows[..., 0:h, :].copy()
    for k in range(1, window):
        boxed += rows[..., k : k + h, :]
    return boxed[0], boxed[1], boxed[2]


@functools.lru_cache(maxsize=8)
def _nms_kernels(r: int) -> tuple[np.ndarray, np.ndarray]:
    """The (2r + 1)^2 dilation kernels of :func:`_nms_top_k`, anchored at the
    centre: the whole neighbourhood, and the neighbours before the centre in
    raster order (the rows above, the columns to its left in its row). Read-only."""
    side = 2 * r + 1
    full = np.ones((side, side), np.uint8)
    earlier = np.zeros((side, side), np.uint8)
    earlier[:r, :] = 1
    earlier[r, :r] = 1
    full.flags.writeable = False
    earlier.flags.writeable = False
    return full, earlier


def _nms_top_k(
    keep: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, nms_radius: int, max_features: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Non-maximum suppression on lambda_1 over retained pixels, then the
    ``max_features`` strongest per sub-image. Arrays are (T, h, w).

    A pixel survives when its lambda_1 is the largest in its (2r + 1)^2
    neighbourhood, ties going to the first pixel in raster order: it must be
    >= every neighbour and > every neighbour before it (the rows above, and
    the columns to its left in its row). So exactly one pixel of a plateau of
    equal maxima survives, and no two kept points are within r of each other.
    """
    # lambda_1 at the pixels that passed eq. (3.4), zero elsewhere. On the
    # tracker's sub-images nearly every pixel passes, so computing it
    # everywhere and masking costs less than gathering and scattering the
    # passed ones (the same element-wise values either way).
    lam = min_eigenvalue(a, b, c)
    lam[~keep] = 0.0
    if nms_radius > 0:
        n_t, h, w = keep.shape
        r = nms_radius
        side = 2 * r + 1
        # Zero padding of r on every side keeps sub-images from seeing each
        # other when the stack is dilated as one 2-D image.
        padded = np.zeros((n_t, h + 2 * r, w + 2 * r), np.float32)
        padded[:, r : r + h, r : r + w] = lam
        flat = padded.reshape(n_t * (h + 2 * r), w + 2 * r)
        full, earlier = _nms_kernels(r)

        def neighbourhood_max(kernel: np.ndarray) -> np.ndarray:
            out = cv2.dilate(flat, kernel)
            return out.reshape(n_t, h + 2 * r, w + 2 * r)[:, r : r + h, r : r + w]

        keep = keep & (lam >= neighbourhood_max(full)) & (lam > neighbourhood_max(earlier))
    t_idx, r_idx, c_idx = np.nonzero(keep)
    score = lam[t_idx, r_idx, c_idx].astype(np.float64)
    # Sort by (sub-image, -score) and keep the first max_features of each group.
    order = np.lexsort((-score, t_idx))
    t_idx, r_idx, c_idx, score = t_idx[order], r_idx[order], c_idx[order], score[order]
    first = np.searchsorted(t_idx, t_idx, side="left")
    rank = np.arange(t_idx.size) - first
    sel = rank < max_features
    return t_idx[sel], r_idx[sel], c_idx[sel], score[sel]


def _random_search(
    ix: np.ndarray,
    iy: np.ndarray,
    m: int,
    hw: tuple[int, int],
    window: int,
    lambda_t: float,
    max_features: int,
    nms_radius: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's random search: draw pixels at random, keep those whose
    interest value passes eq. (3.4), until ``max_features`` are found or every
    pixel has been drawn. G is evaluated only at drawn pixels."""
    h, w = hw
    r = window // 2
    off = np.arange(-r, r + 1)
    out_t, out_r, out_c, out_s = [], [], [], []
    batch = RANDOM_BATCH_FACTOR * max_features
    for t in range(ix.shape[0]):
        order = rng.permutation(h * w)
        acc_r: list[int] = []
        acc_c: list[int] = []
        for start in range(0, order.size, batch):
            draw = order[start : start + batch]
            pr, pc = draw // w + m, draw % w + m
            rr = pr[:, None, None] + off[None, :, None]
            cc = pc[:, None, None] + off[None, None, :]
            gx, gy = ix[t][rr, cc].astype(np.float64), iy[t][rr, cc].astype(np.float64)
            a = (gx * gx).sum(axis=(1, 2))
            b = (gx * gy).sum(axis=(1, 2))
            c = (gy * gy).sum(axis=(1, 2))
            ok = np.nonzero(eigen_threshold_test(a, b, c, lambda_t))[0]
            for k in ok:
                y0, x0 = int(pr[k]) - m, int(pc[k]) - m
                if all(max(abs(y0 - yy), abs(x0 - xx)) > nms_radius for yy, xx in zip(acc_r, acc_c)):
                    acc_r.append(y0)
                    acc_c.append(x0)
                    out_t.append(t)
                    out_r.append(y0)
                    out_c.append(x0)
                    out_s.append(float(min_eigenvalue(a[k], b[k], c[k])))
                    if len(acc_r) == max_features:
                        break
            if len(acc_r) == max_features:
                break
    as_int = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return as_int(out_t), as_int(out_r), as_int(out_c), np.asarray(out_s, dtype=np.float64)


def detect_features(
    image: np.ndarray,
    window: int = 3,
    lambda_t: float = 1500.0,
    max_features: int = 100,
    nms_radius: int = 1,
    strategy: Strategy = "exhaustive",
    rng: np.random.Generator | None = None,
) -> Features:
    """Detect feature points over a whole image (paper §3, Figs. 6).

    Same detector as :func:`detect_in_subimages` with the whole image (less
    the :func:`detection_margin`) as the single sub-image; the paper applies it
    to each fixation area (sub-image) in turn.

    Args:
        image: (H, W) uint8 or float32 [DN].
        window, lambda_t, max_features, nms_radius, strategy, rng: As in
            :func:`detect_in_subimages`.

    Returns:
        :class:`Features` (``region`` all zero).
    """
    m = detection_margin(window)
    height, width = image.shape
    if height <= 2 * m or width <= 2 * m:
        _check_detector_args(window, lambda_t, max_features, nms_radius, strategy, rng)
        return Features(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    return detect_in_subimages(
        image,
        np.array([[m, m]]),
        (width - 2 * m, height - 2 * m),
        window=window,
        lambda_t=lambda_t,
        max_features=max_features,
        nms_radius=nms_radius,
        strategy=strategy,
        rng=rng,
    )
