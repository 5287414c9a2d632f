"""Natural textures warped by known homographies: truth from the warp, and both trackers on it."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage

from bench.cli import main
from bench.evaluation.textures_eval import (
    TEXTURES,
    DescentWarp,
    descent_homographies,
    homography_truth,
    load_texture,
    run_textures_eval,
    warp_frames,
)

SIZE = 256


def test_textures_ship_inside_the_scikit_image_wheel():
    # Nothing may download at run time: the three photographs are package files.
    data_dir = Path(skimage.__file__).parent / "data"
    for name in TEXTURES:
        assert (data_dir / f"{name}.png").is_file(), name
        tex = load_texture(name)
        assert tex.shape == (512, 512) and tex.dtype == np.float32 and tex.std() > 10


def test_pure_translation_warp_gives_exactly_the_shift():
    tex = load_texture("gravel")
    shift = (2.0, -1.0)  # integer drift: frame k+1 is frame k moved by whole pixels
    warp = DescentWarp(start_scale=1.0, zoom_per_frame=0.0, rotation_deg_per_frame=0.0, drift_px_per_frame=shift,
                       tilt_per_px=0.0, noise_dn=0.0)
    hs = descent_homographies(tex.shape, SIZE, 3, warp)
    rng = np.random.default_rng(0)
    xy = rng.uniform(10, SIZE - 10, (300, 2))
    truth, valid = homography_truth(xy, hs[0], hs[1], tex.shape, SIZE)
    assert valid.all()
    np.testing.assert_allclose(truth - xy, np.tile(shift, (300, 1)), atol=1e-9)
    # Independently of the truth code: the rendered images themselves moved by the shift.
    f0, f1 = warp_frames(tex, hs[:2], SIZE, noise_dn=0.0)
    np.testing.assert_array_equal(f1[20:-20, 20:-20], f0[21:-19, 18:-22])


def test_truth_matches_an_independent_similarity_computation():
    # Without tilt the warp is a similarity: zoom s, rotation theta and drift d
    # about the image centre c. Then x_k1 = c + d1 + s1 R1 R0^T (x_k - c - d0) / s0.
    tex = load_texture("grass")
    warp = DescentWarp(tilt_per_px=0.0)
    hs = descent_homographies(tex.shape, SIZE, 10, warp)
    c = (SIZE - 1) / 2.0
    rng = np.random.default_rng(1)
    xy = rng.uniform(40, SIZE - 40, (200, 2))

    def rot(deg: float) -> np.ndarray:
        t = np.radians(deg)
        return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])

    for k in (0, 4, 8):
        s0 = warp.start_scale * (1 + warp.zoom_per_frame) ** k
        s1 = s0 * (1 + warp.zoom_per_frame)
        d0, d1 = np.multiply(warp.drift_px_per_frame, k), np.multiply(warp.drift_px_per_frame, k + 1)
        r0, r1 = rot(warp.rotation_deg_per_frame * k), rot(warp.rotation_deg_per_frame * (k + 1))
        expected = c + d1 + (s1 / s0) * ((xy - c - d0) @ r0 @ r1.T)
        truth, valid = homography_truth(xy, hs[k], hs[k + 1], tex.shape, SIZE)
        assert valid.all()
        np.testing.assert_allclose(truth, expected, atol=1e-9)


def test_truth_with_perspective_agrees_with_opencv():
    tex = load_texture("brick")
    hs = descent_homographies(tex.shape, SIZE, 6, DescentWarp(tilt_per_px=3e-4))
    xy = np.random.default_rng(2).uniform(30, SIZE - 30, (100, 2))
    truth, valid = homography_truth(xy, hs[3], hs[4], tex.shape, SIZE)
    ref = cv2.perspectiveTransform(xy.reshape(-1, 1, 2), hs[4] @ np.linalg.inv(hs[3])).reshape(-1, 2)
    np.testing.assert_allclose(truth[valid], ref[valid], atol=1e-9)
    assert valid.mean() > 0.95
    # A point whose texture source lies outside the texture (reflected content) has no truth.
    outside = np.array([[-200.0, -200.0]])
    assert not homography_truth(outside, hs[0], hs[1], tex.shape, SIZE)[1][0]


def test_the_tracker_is_accurate_on_a_warped_texture():
    report = run_textures_eval(size=SIZE, frames=16, repeats=1, textures=("gravel",))
    for name in ("tracker", "opencv"):
        m = report["results"]["gravel"][name]
        assert m["n_errors"] > 300, (name, m)
        assert m["epe_median_px"] < 0.1 and m["within_1px_frac"] >= 0.99, (name, m)
        assert m["tracks_per_frame_mean"] > 40, (name, m)
    assert report["results"]["all"]["tracker"]["epe_median_px"] == pytest.approx(
        report["results"]["gravel"]["tracker"]["epe_median_px"])


def test_track_eval_textures_cli(capsys):
    assert main(["track-eval", "--imagery", "textures", "--frames", "5", "--repeats", "1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["imagery"] == "textures" and report["size"] == SIZE
    assert report["tracker_setup"] == {"lk_bias_correction": SIZE > 256, "fb_blend": 0.3}
    assert set(report["results"]) == {*TEXTURES, "all"}
    for res in report["results"].values():
        for name in ("tracker", "opencv"):
            assert np.isfinite(res[name]["ms_per_frame_min_of_repeats_mean"]), name
    assert main(["track-eval", "--imagery", "textures", "--frames", "2"]) == 2
    assert "--frames" in capsys.readouterr().err


def test_track_eval_textures_table(capsys):
    """The terminal table (no --json): every row of track-eval's report in each texture's block and in the
    pooled one, which lacked the page faults and raised a KeyError."""
    from bench.evaluation.track_eval import REPORT_KEYS
    assert main(["track-eval", "--imagery", "textures", "--frames", "5", "--repeats", "1"]) == 0
    blocks = capsys.readouterr().out.split("\n\n")
    assert [b.splitlines()[0].split()[0] for b in blocks[1:]] == [*TEXTURES, "all"]
    for block in blocks[1:]:
        labels = [line[:22].strip() for line in block.splitlines()[1:]]
        assert labels == [label for _, label, _ in REPORT_KEYS] + ["time ratio"], block
