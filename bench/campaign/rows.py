"""Campaign rows as numbers: one reading of a flattened case row for every campaign summary."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


def row_float(value: Any) -> float:
    """A row value as a float; NaN for None, non-numbers and booleans."""
    if value is None or isinstance(value, (bool, str, bytes)):
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def column(rows: Sequence[Mapping[str, Any]], key: str) -> np.ndarray:
    """One key over the rows as floats, (len(rows),); NaN where missing or not a number."""
    return np.array([row_float(r.get(key)) for r in rows], dtype=np.float64)
