"""Small NumPy helpers for the flight software's hot path (per message or per frame).

Each gives what the plain NumPy expression named in its docstring gives
(tested against it), at a fraction of the per-call cost on the small arrays of
one message: NumPy's fixed cost per call, not the arithmetic, dominates there.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaincinv


def all_finite(*arrays: np.ndarray) -> bool:
    """``all(np.all(np.isfinite(a)) for a in arrays)`` in one pass over one concatenation."""
    return bool(np.isfinite(np.concatenate([np.ravel(a) for a in arrays])).all())


def finite_small(a: np.ndarray) -> bool:
    """``bool(np.all(np.isfinite(a)))`` of one small float array (a 3- or 4-vector of one control
    tick): element by element on floats, several times cheaper there than :func:`all_finite`."""
    return all(map(math.isfinite, a.ravel().tolist()))


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` of a non-empty 1-D array, by one partition."""
    n = a.size
    mid = n // 2
    if n % 2:
        return float(np.partition(a, mid)[mid])
    part = np.partition(a, (mid - 1, mid))
    return 0.5 * (float(part[mid - 1]) + float(part[mid]))


def cross3(ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> tuple[float, float, float]:
    """``np.cross(a, b)`` of two 3-vectors given as floats: the same products and differences, so the same bits."""
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def norm(v: np.ndarray) -> float:
    """``float(np.linalg.norm(v))`` of a float64 array: NumPy's own ``sqrt(v.ravel(order="K").dot(...))``
    without its argument handling (the same dot product on the same memory, so the same bits)."""
    v = v.ravel(order="K")
    return math.sqrt(v.dot(v))


def max_abs3(x: float, y: float, z: float) -> float:
    """``float(np.max(np.abs([x, y, z])))``: NaN if any is NaN."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax != ax or ay != ay or az != az:
        return math.nan
    return max(ax, ay, az)


def clip_float(x: float, lo: float, hi: float) -> float:
    """``np.clip`` of one float: ``x`` itself at a tie (signed zeros kept) and NaN passed through."""
    return lo if x < lo else (hi if x > hi else x)


def chi2_ppf(p: float | np.ndarray, dof: float | np.ndarray) -> float | np.ndarray:
    """``scipy.stats.chi2.ppf(p, dof)`` for ``0 < p < 1``: the same ``2 * gammaincinv(dof / 2, p)``
    that ``scipy.stats`` evaluates (tested bit for bit), without importing ``scipy.stats``, whose
    import (about 0.5 s, the distributions' construction) a run would otherwise pay for a handful of
    quantiles."""
    return 2.0 * gammaincinv(np.divide(dof, 2.0), p)
