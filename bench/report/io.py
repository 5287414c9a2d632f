"""Output helpers: files appear whole or not at all.

Every result is written to a temporary file in the destination folder and
renamed into place, so an error half-way (bad input, a crash, Ctrl-C) never
leaves a truncated file or clobbers a result that was already there.
"""

from __future__ import annotations

import io
import math
import os
from typing import Any
import tempfile
from pathlib import Path

import cv2
import numpy as np

from bench.report.split_draw import figure_png


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def json_safe(value: Any) -> Any:
    """A JSON-ready copy: NumPy scalars become Python ones, non-finite floats None (recursively)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; parent folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; results are ordinary files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a uint8 (H, W) or (H, W, 3) RGB image as PNG, atomically."""
    img = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    return atomic_write_bytes(path, buf.tobytes())


def write_npy(path: str | Path, array: np.ndarray) -> Path:
    buf = io.BytesIO()
    np.save(buf, array)
    return atomic_write_bytes(path, buf.getvalue())


def save_figure(fig, path: str | Path, dpi: int = 110, processes: int = 1) -> Path:
    """Save a matplotlib figure as PNG, atomically (``processes=2``: its axes drawn by two processes,
    the same bytes: :func:`bench.report.split_draw.figure_png`)."""
    return atomic_write_bytes(path, figure_png(fig, dpi, processes))
