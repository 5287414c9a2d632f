"""Tracker output type and input-image validation shared by the vision stages.

Pixel convention (everywhere in :mod:`vision`): ``x`` is the column and ``y``
the row, and integer values lie at pixel centres, so pixel ``image[r, c]``
covers ``[c - 0.5, c + 0.5] x [r - 0.5, r + 0.5]``. Intensities are 8-bit
digital numbers [DN] (0..255); float32 images are taken on the same scale
unless the tracker is configured otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

ALLOWED_DTYPES = (np.uint8, np.float32)
"""Image dtypes accepted by :func:`check_image` and the tracker."""


@dataclass(frozen=True, slots=True)
class Tracks:
    """Feature tracks reported by a tracker for one frame.

    Rate: one per processed frame.

    Attributes:
        ids: Persistent track identifiers, (N,) int64; an id is never reused
            by the same tracker until :meth:`reset`.
        xy: Track positions in this frame, (N, 2) float64 [px], ``(x, y)`` =
            (column, row), integer values at pixel centres.
        prev_xy: Position of the same track in the previous frame, (N, 2)
            float64 [px]; NaN for tracks born in this frame.
        age: Frames since the track was born, (N,) int64 (0 on its first frame).
    """

    ids: np.ndarray
    xy: np.ndarray
    prev_xy: np.ndarray
    age: np.ndarray

    def __post_init__(self) -> None:
        n = self.ids.shape[0]
        # Internal invariants: trackers build Tracks, users only read them.
        assert self.ids.shape == (n,) and self.ids.dtype == np.int64
        assert self.xy.shape == (n, 2) and self.xy.dtype == np.float64
        assert self.prev_xy.shape == (n, 2) and self.prev_xy.dtype == np.float64
        assert self.age.shape == (n,) and self.age.dtype == np.int64

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @classmethod
    def empty(cls) -> Tracks:
        """Zero tracks (a blank or featureless frame)."""
        return cls(
            ids=np.zeros(0, np.int64),
            xy=np.zeros((0, 2), np.float64),
            prev_xy=np.zeros((0, 2), np.float64),
            age=np.zeros(0, np.int64),
        )


def check_image(image: object, name: str = "image") -> np.ndarray:
    """Validate a grayscale camera frame.

    Args:
        image: Candidate frame; must be a 2-D ``numpy.ndarray`` of dtype uint8
            or float32, non-empty, and (float32) free of NaN/inf.
        name: Argument name used in error messages.

    Returns:
        The same array (no copy), (H, W).

    Raises:
        ValueError: Naming the argument, what was passed and what is allowed.
    """
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name} must be a numpy.ndarray (2-D uint8 or float32), got {type(image).__name__}")
    if image.ndim != 2:
        raise ValueError(
            f"{name} must be a 2-D (H, W) grayscale array, got ndim={image.ndim} with shape {image.shape}"
        )
    if image.dtype not in ALLOWED_DTYPES:
        raise ValueError(f"{name} dtype must be uint8 or float32, got {image.dtype}")
    if image.size == 0:
        raise ValueError(f"{name} must be non-empty, got shape {image.shape}")
    # cv2.checkRange is a single fast pass that rejects NaN and +-inf.
    if image.dtype == np.float32 and not cv2.checkRange(image)[0]:
        raise ValueError(f"{name} contains NaN or infinite values; only finite intensities are allowed")
    return image
