"""Small NumPy helpers for the flight software's hot path (per message or per frame).

Each gives what the plain NumPy expression named in its docstring gives
(tested against it), at a fraction of the per-call cost on the small arrays of
one message: NumPy's fixed cost per call, not the arithmetic, dominates there.
"""

from __future__ import annotations

import numpy as np


def all_finite(*arrays: np.ndarray) -> bool:
    """``all(np.all(np.isfinite(a)) for a in arrays)`` in one pass over one concatenation."""
    return bool(np.isfinite(np.concatenate([np.ravel(a) for a in arrays])).all())


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` of a non-empty 1-D array, by one partition."""
    n = a.size
    mid = n // 2
    if n % 2:
        return float(np.partition(a, mid)[mid])
    part = np.partition(a, (mid - 1, mid))
    return 0.5 * (float(part[mid - 1]) + float(part[mid]))
