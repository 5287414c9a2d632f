"""bench.evaluation.vision_figures writes one non-empty PNG per stage (paper Figs. 3-8)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.evaluation.tracking_eval import synthetic_descent
from bench.evaluation.vision_figures import write_vision_figures
from vision import TrackerConfig

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_writes_one_png_per_stage(tmp_path):
    frames = synthetic_descent(size=128, n_frames=5, seed=2).frames
    paths = write_vision_figures(frames, tmp_path / "figs", TrackerConfig())
    names = [p.name for p in paths]
    assert names == [
        "fig3a_averaged.png",
        "fig3b_laplacian.png",
        "fig3c_variance.png",
        "fig3d_areas.png",
        "fig4_templates.png",
        "fig5_template_match.png",
        "fig6_fp_detection.png",
        "fig7_fp_tracks_subimage.png",
        "fig8_fp_tracks_whole.png",
    ]
    for p in paths:
        data = p.read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 2000, p.name


def test_blank_frames_still_write_figures(tmp_path):
    frames = [np.zeros((96, 96), np.uint8)] * 3
    paths = write_vision_figures(frames, tmp_path)
    assert all(p.stat().st_size > 0 for p in paths)


def test_needs_three_frames(tmp_path):
    with pytest.raises(ValueError, match="at least 3"):
        write_vision_figures([np.zeros((64, 64), np.uint8)] * 2, tmp_path)
