"""Tests of vision.Tracker: contract, robustness and tracking on known motion."""

from __future__ import annotations

import warnings

import ast
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

import vision
from vision import Tracker, TrackerConfig, Tracks

VISION_DIR = Path(vision.__file__).parent


def texture(n: int = 400, seed: int = 0) -> np.ndarray:
    """Multi-scale random texture, float32 (n, n) in 0..255 [DN]."""
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.float32)
    for scale in (2, 4, 8, 16):
        grid = rng.standard_normal((n // scale + 2, n // scale + 2)).astype(np.float32)
        img += cv2.resize(grid, (n + 2 * scale, n + 2 * scale), interpolation=cv2.INTER_CUBIC)[
            scale : scale + n, scale : scale + n
        ] * np.float32(scale**0.5)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    return np.clip(128 + 40 * (img - img.mean()) / img.std(), 0, 255).astype(np.float32)


def translated_frames(n_frames: int, step_xy: tuple[float, float], size: int = 160, seed: int = 0) -> list[np.ndarray]:
    """Crops of a large texture moving by ``step_xy`` px per frame (sub-pixel
    steps through bilinear warps of the big texture)."""
    big = texture(size + 2 * int(abs(step_xy[0]) * n_frames + abs(step_xy[1]) * n_frames) + 40, seed)
    frames = []
    c0 = big.shape[0] / 2 - size / 2
    for k in range(n_frames):
        # Content moves by +step per frame: the crop window moves by -step.
        m = np.array([[1.0, 0.0, -(c0 - k * step_xy[0])], [0.0, 1.0, -(c0 - k * step_xy[1])]])
        frames.append(np.rint(cv2.warpAffine(big, m, (size, size), flags=cv2.INTER_LINEAR)).astype(np.uint8))
    return frames


# ------------------------------------------------------------------ contract
def test_tracks_contract_ids_prev_xy_and_age():
    frames = translated_frames(5, (2.0, 1.0))
    tr = Tracker()
    out0 = tr.step(frames[0])
    assert len(out0) > 20
    assert out0.ids.dtype == np.int64 and out0.xy.dtype == np.float64 and out0.age.dtype == np.int64
    assert out0.xy.shape == (len(out0), 2) and out0.prev_xy.shape == (len(out0), 2)
    assert np.isnan(out0.prev_xy).all() and (out0.age == 0).all()
    assert len(np.unique(out0.ids)) == len(out0)
    prev = out0
    for img in frames[1:]:
        out = tr.step(img)
        _, ia, ib = np.intersect1d(prev.ids, out.ids, return_indices=True)
        assert len(ia) > 0.8 * len(prev)
        np.testing.assert_array_equal(out.prev_xy[ib], prev.xy[ia])
        np.testing.assert_array_equal(out.age[ib], prev.age[ia] + 1)
        born = ~np.isin(out.ids, prev.ids)
        assert np.isnan(out.prev_xy[born]).all() and (out.age[born] == 0).all()
        assert not np.isnan(out.prev_xy[~born]).any()
        prev = out


def test_tracks_follow_known_translation():
    step = (2.4, -1.3)
    frames = translated_frames(8, step)
    tr = Tracker()
    prev = tr.step(frames[0])
    errors = []
    for img in frames[1:]:
        out = tr.step(img)
        old = ~np.isnan(out.prev_xy[:, 0])
        errors.append(np.linalg.norm(out.xy[old] - out.prev_xy[old] - step, axis=1))
        prev = out
    err = np.concatenate(errors)
    assert err.size > 200
    assert np.median(err) < 0.05 and (err < 0.5).all()
    assert len(prev) > 30


def test_geometry_scales_with_frames_larger_than_the_reference():
    cfg = TrackerConfig()
    assert cfg.reference_side_px == 256
    # At or below the reference: the configuration as given.
    for side in (64, 200, 256):
        assert cfg.for_side(side) is cfg
    # 512: k = 2. Written out by hand from the rule in for_side's docstring.
    big = cfg.for_side(512)
    assert (big.template_size, big.border_px, big.fp_window) == (60, 42, 5)
    assert big.lambda_t == pytest.approx(10.0 * 25.0 / 9.0)
    assert big.reference_side_px is None and big.for_side(1024) is big
    assert big.model_dump(exclude={"template_size", "border_px", "fp_window", "lambda_t", "reference_side_px"}) == \
        cfg.model_dump(exclude={"template_size", "border_px", "fp_window", "lambda_t", "reference_side_px"})
    # 384: k = 1.5 -> 45 px (a multiple of Sx = Sy = 5), border round(31.5) = 32, W1 = 2 round(1.5) + 1 = 5.
    mid = cfg.for_side(384)
    assert (mid.template_size, mid.border_px, mid.fp_window) == (45, 32, 5)
    # Without a reference the geometry is used as given at every size.
    fixed = TrackerConfig(reference_side_px=None)
    assert fixed.for_side(512) is fixed


def test_the_scaled_geometry_stops_at_the_fields_limits():
    # A camera of up to 4096 px is a valid scenario: its frames must get a valid configuration, not a
    # ValidationError. Below the limits the rule above; above them W1 stops at 15, the template at 255
    # (the largest multiple of Sx = Sy = 5 up to 256), and the edge margin grows to W1's detection margin.
    cfg = TrackerConfig()
    expected = {1024: (120, 84, 9, 8), 2048: (240, 168, 15, 8), 4096: (255, 336, 15, 8)}
    for side, (size, border, w1, edge) in expected.items():
        big = cfg.for_side(side)
        assert (big.template_size, big.border_px, big.fp_window, big.edge_margin_px) == (size, border, w1, edge)
        assert big.lambda_t == pytest.approx(10.0 * w1**2 / 9.0)
    # A small reference scales a 512 frame by 8 (W1 = 17 uncapped) and a 3 px edge margin must grow to 8.
    small = TrackerConfig(reference_side_px=64, template_size=10, lk_window=3, edge_margin_px=3, border_px=6)
    scaled = small.for_side(512)
    assert (scaled.template_size, scaled.fp_window, scaled.edge_margin_px, scaled.border_px) == (80, 15, 8, 48)
    frames = translated_frames(2, (2.0, 1.0), size=512, seed=4)
    tr = Tracker(small)
    tr.step(frames[0])
    out = tr.step(frames[1])
    old = ~np.isnan(out.prev_xy[:, 0])
    assert old.sum() > 20 and np.median(np.linalg.norm(out.xy[old] - out.prev_xy[old] - (2.0, 1.0), axis=1)) < 0.1


def test_a_512_frame_is_tracked_with_the_scaled_geometry():
    step = (2.4, -1.3)
    frames = translated_frames(6, step, size=512, seed=3)
    tr = Tracker()
    tr.step(frames[0])
    assert tr.config_for(frames[0].shape).template_size == 60
    errors = []
    for img in frames[1:]:
        out = tr.step(img)
        old = ~np.isnan(out.prev_xy[:, 0])
        errors.append(np.linalg.norm(out.xy[old] - out.prev_xy[old] - step, axis=1))
    # Every track lies in a 60 px template (within the drift slack).
    tl = tr.templates
    c = tr.track_templates
    rel = out.xy - tl[c]
    assert ((rel >= -15.0) & (rel <= 59.0 + 15.0)).all()
    err = np.concatenate(errors)
    assert err.size > 200 and np.median(err) < 0.05 and (err < 0.5).all()
    # A new sequence of another size after reset() gets its own geometry.
    tr.reset()
    tr.step(translated_frames(1, step, size=256)[0])
    assert tr.config_for((256, 256)).template_size == 30


def test_large_motion_converges_through_block_matching():
    step = (9.6, 7.3)  # beyond a 9 px LK window: only the block-matching seed helps
    frames = translated_frames(5, step, size=200)
    tr = Tracker()
    tr.step(frames[0])
    out = None
    for img in frames[1:]:
        out = tr.step(img)
        old = ~np.isnan(out.prev_xy[:, 0])
        assert old.sum() > 10
        err = np.linalg.norm(out.xy[old] - out.prev_xy[old] - step, axis=1)
        assert np.median(err) < 0.1 and (err < 1.0).all()


def test_reset_restarts_ids_and_is_deterministic():
    frames = translated_frames(4, (1.5, 0.5))
    tr = Tracker()
    first = [tr.step(f) for f in frames]
    tr.reset()
    second = [tr.step(f) for f in frames]
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.xy, b.xy)
    assert second[0].ids.min() == 0


def test_float32_input_equals_uint8_input():
    frames = translated_frames(4, (1.5, 0.5))
    a = Tracker()
    b = Tracker()
    c = Tracker(TrackerConfig(float_full_scale=1.0))
    for f in frames:
        ta, tb, tc = a.step(f), b.step(f.astype(np.float32)), c.step(f.astype(np.float32) / 255)
        np.testing.assert_array_equal(ta.ids, tb.ids)
        np.testing.assert_allclose(ta.xy, tb.xy)
        np.testing.assert_allclose(ta.xy, tc.xy)


@pytest.mark.parametrize("full_scale", [1e-38, 1e-20, 3e38])
def test_extreme_float_full_scales_track_as_uint8(full_scale):
    # Scaled in float32, 255 / 1e-38 overflowed (inf, then 0 * inf = NaN) and a frame near 3e38 did too:
    # every track was lost with a RuntimeWarning.
    frames = translated_frames(4, (1.5, 0.5))
    a, c = Tracker(), Tracker(TrackerConfig(float_full_scale=full_scale))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for f in frames:
            ta = a.step(f)
            tc = c.step((f.astype(np.float64) * (full_scale / 255)).astype(np.float32))
    assert len(ta) > 20
    np.testing.assert_array_equal(ta.ids, tc.ids)
    np.testing.assert_allclose(ta.xy, tc.xy)


def test_numpy_backend_matches_opencv_backend():
    frames = translated_frames(5, (2.2, -0.7))
    a = Tracker(TrackerConfig(lk_backend="opencv"))
    b = Tracker(TrackerConfig(lk_backend="numpy"))
    for f in frames:
        ta, tb = a.step(f), b.step(f)
    _, ia, ib = np.intersect1d(ta.ids, tb.ids, return_indices=True)
    assert len(ia) > 0.8 * max(len(ta), len(tb))
    d = np.linalg.norm(ta.xy[ia] - tb.xy[ib], axis=1)
    assert np.median(d) < 0.02 and d.max() < 0.1


def test_random_search_strategy_runs_with_its_own_generator():
    frames = translated_frames(3, (1.0, 1.0))
    state = np.random.get_state()
    cfg = TrackerConfig(fp_search="random")
    runs = []
    for _ in range(2):
        tr = Tracker(cfg, rng=np.random.default_rng(5))
        runs.append([tr.step(f) for f in frames])
    assert np.random.get_state()[1].tolist() == state[1].tolist()
    np.testing.assert_array_equal(runs[0][-1].xy, runs[1][-1].xy)
    assert len(runs[0][-1]) > 20
    tr = Tracker(cfg, rng=np.random.default_rng(1))
    assert len(tr.step(frames[0])) > 20
    with pytest.raises(ValueError, match="Generator"):
        Tracker(cfg, rng=np.random.RandomState(0))
    with pytest.raises(ValueError, match="needs rng"):
        Tracker(cfg)


def test_redetection_replaces_lost_tracks():
    frames = translated_frames(3, (1.0, 0.0))
    tr = Tracker()
    t0 = tr.step(frames[0])
    tr.step(frames[1])
    # A completely new scene: every template and track is lost and replaced.
    other = translated_frames(1, (0.0, 0.0), seed=7)[0]
    t2 = tr.step(other)
    assert len(t2) > 20
    assert not np.isin(t2.ids, t0.ids).any()
    assert np.isnan(t2.prev_xy).all()


def test_templates_left_without_a_track_are_tracked_on_without_error():
    # A scene fading to a flat grey (glare, haze): at 3 % contrast LK and the
    # forward-backward check lose every point, the block matching keeps some
    # templates (their energy is under the floor) and re-detection finds no
    # point in them. The next frame then has templates but no point to solve,
    # which OpenCV's LK refuses (an empty point set); the tracker must carry on.
    frames = translated_frames(6, (1.3, 0.6), size=256, seed=2)
    tr = Tracker()
    for frame, contrast in zip(frames, (1.0, 0.3, 0.1, 0.03)):
        out = tr.step(np.rint(128 + contrast * (frame.astype(np.float32) - 128)).astype(np.uint8))
    assert len(out) == 0 and tr.templates.shape[0] > 0  # the state under test
    dim = tr.step(np.rint(128 + 0.03 * (frames[4].astype(np.float32) - 128)).astype(np.uint8))
    assert len(dim) == 0 and dim.xy.shape == (0, 2)
    back = tr.step(frames[5])  # full contrast again: new templates and points
    assert len(back) > 20


def test_templates_are_spread_and_inside():
    frames = translated_frames(2, (1.0, 0.0), size=256)
    cfg = TrackerConfig()
    tr = Tracker(cfg)
    tr.step(frames[0])
    tl = tr.templates
    assert 1 <= len(tl) <= cfg.n_templates
    assert (tl >= cfg.border_px).all() and (tl + cfg.template_size <= 256 - cfg.border_px).all()
    c = tl + 0.5 * (cfg.template_size - 1)
    d = np.linalg.norm(c[:, None] - c[None, :], axis=2) + np.eye(len(c)) * 1e9
    assert d.min() >= cfg.template_separation_frac * 256
    # Every track lies in its sub-image.
    out = tr.step(frames[1])
    owner = tr.templates[tr.track_templates]
    rel = out.xy - owner
    slack = 0.25 * cfg.template_size
    assert ((rel >= -slack) & (rel <= cfg.template_size - 1 + slack)).all()


# ---------------------------------------------------------------- robustness
@pytest.mark.parametrize(
    ("bad", "pattern"),
    [
        (np.zeros((32, 32, 3), np.uint8), "2-D"),
        (np.zeros(32, np.uint8), "2-D"),
        (np.zeros((32, 32), np.float64), "dtype"),
        (np.zeros((32, 32), np.int16), "dtype"),
        (np.zeros((0, 32), np.uint8), "non-empty"),
        (np.full((32, 32), np.nan, np.float32), "NaN"),
        (np.pad(np.full((31, 32), 5, np.float32), ((0, 1), (0, 0)), constant_values=np.inf), "NaN or infinite"),
        ([[1, 2], [3, 4]], "numpy.ndarray"),
    ],
)
def test_bad_images_raise_clear_value_errors(bad, pattern):
    with pytest.raises(ValueError, match=pattern) as exc:
        Tracker().step(bad)
    assert "image" in str(exc.value)


def test_shape_change_without_reset_raises():
    tr = Tracker()
    tr.step(np.zeros((64, 64), np.uint8))
    with pytest.raises(ValueError, match="reset"):
        tr.step(np.zeros((64, 80), np.uint8))
    tr.reset()
    tr.step(np.zeros((64, 80), np.uint8))


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((128, 128), np.uint8),
        np.full((128, 128), 200, np.uint8),
        np.tile(np.linspace(0, 255, 128, dtype=np.float32), (128, 1)),  # smooth ramp: no corners
        np.zeros((8, 8), np.uint8),  # too small for any template
        np.zeros((1, 1), np.float32),
    ],
)
def test_featureless_images_give_zero_tracks(image):
    tr = Tracker()
    for _ in range(3):
        out = tr.step(image)
        assert isinstance(out, Tracks) and len(out) == 0
        assert out.xy.shape == (0, 2)


def test_config_validation():
    with pytest.raises(ValidationError, match="multiple"):
        TrackerConfig(template_size=22)
    with pytest.raises(ValidationError, match="odd"):
        TrackerConfig(lk_window=8)
    with pytest.raises(ValidationError):
        TrackerConfig(unknown_field=1)
    with pytest.raises(ValidationError):
        TrackerConfig(n_templates=0)
    with pytest.raises(ValueError, match="TrackerConfig"):
        Tracker({"n_templates": 3})
    for name, field in TrackerConfig.model_fields.items():
        assert field.description and "[" in field.description, f"{name} lacks a description with units"


# The former default geometry (20 px templates, 9 px LK window), which the
# configuration-message tests below were written for.
GEOMETRY_20 = {"template_size": 20, "lk_window": 9, "edge_margin_px": 6, "border_px": 16}


def test_config_refuses_template_size_not_a_multiple_of_block_size():
    # The variance window of eq. (2.2) is template_size / S blocks: refused at
    # configuration time with a one-line message naming field, value and rule.
    for kw, size in (({"template_size": 22}, 22), ({"subsample_x": 3}, 20), ({"subsample_y": 8}, 20)):
        msg = rf"template_size \({size}\) must be a multiple of subsample_x"
        with pytest.raises(ValidationError, match=msg) as exc:
            TrackerConfig(**{**GEOMETRY_20, **kw})
        assert len(exc.value.errors()) == 1 and "\n" not in exc.value.errors()[0]["msg"]
    TrackerConfig(template_size=24, subsample_x=4, subsample_y=6)


def test_config_refuses_a_border_too_small_for_the_lk_tiles():
    # LK runs on tiles of template_size + 2 (ceil(template_size / 4) +
    # lk_window // 2 + 2) px around each template; a frame that holds a
    # template border_px from its edges must hold such a tile. This config was
    # accepted and Tracker.step then failed an internal assert on 64 x 64
    # frames (a 40 px template 10 px from the edges, a 72 px tile).
    with pytest.raises(ValidationError, match=r"border_px \(6\) must be >= 16 .*template_size=40, lk_window=9") as exc:
        TrackerConfig(**{**GEOMETRY_20, "template_size": 40, "border_px": 6})
    assert len(exc.value.errors()) == 1 and "\n" not in exc.value.errors()[0]["msg"]
    with pytest.raises(ValidationError, match=r"border_px \(13\) must be >= 14 .*lk_window=15"):
        TrackerConfig(**{**GEOMETRY_20, "lk_window": 15, "edge_margin_px": 9, "border_px": 13})
    # At the smallest allowed border, frames just large enough to hold a
    # template track without error.
    smallest_borders = (
        {"template_size": 40, "border_px": 16},
        {"border_px": 11},
        {"lk_window": 15, "edge_margin_px": 9, "border_px": 14},
        {"template_size": 30, "lk_window": 13, "edge_margin_px": 8, "border_px": 16},  # the default geometry
    )
    for kw in smallest_borders:
        cfg = TrackerConfig(**{**GEOMETRY_20, **kw})
        smallest = cfg.template_size + 2 * cfg.border_px
        held = 0
        for size in range(smallest, smallest + 8):
            for seed in (0, 1):
                tr = Tracker(cfg)
                for img in translated_frames(3, (1.0, 0.5), size=size, seed=seed):
                    out = tr.step(img)
                held += len(tr.templates) > 0
        assert held > 0, kw  # templates were placed, so the LK path ran


# --------------------------------------------------------------- flight rule
def test_vision_never_imports_simulator_or_bench():
    for path in VISION_DIR.glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for n in names:
                root = n.split(".")[0]
                assert root not in {"mujoco", "bench", "models"}, f"{path.name} imports {n}"


@pytest.mark.parametrize("kw", [{}, {"fb_check": False}, {"lk_seed": "template"}, {"subpixel_match": False},
                                {"fb_window": None}])
def test_tracker_variants_follow_a_known_translation(kw):
    # The forward-backward check (default, its backward solve in fb_window) or
    # one pass validated by its seed; seeds from the track's own motion or from
    # its template's; sub-pixel block matching or not: every variant tracks a
    # known sub-pixel motion.
    step = (1.7, 2.2)
    tr = Tracker(TrackerConfig(**kw))
    errors = []
    for img in translated_frames(8, step):
        out = tr.step(img)
        old = ~np.isnan(out.prev_xy[:, 0])
        errors.append(np.linalg.norm(out.xy[old] - out.prev_xy[old] - step, axis=1))
    err = np.concatenate(errors)
    assert err.size > 200, kw
    assert np.median(err) < 0.05 and (err < 0.5).all(), kw


def test_tracks_remember_their_last_displacement_for_the_next_seed():
    # On a steady translation a track's last displacement is the motion
    # itself, so the track seed lands within the block matching's sub-pixel
    # error of the truth, and LK hardly moves from it.
    step = (2.4, -1.3)
    tr = Tracker(TrackerConfig())
    frames = translated_frames(6, step)
    for img in frames[:-1]:
        tr.step(img)
    g_flow = tr._flow.copy()
    assert np.isfinite(g_flow).all()
    # Every track's last displacement is the step (LK's accuracy) or, for a
    # track born in the last frame, its template's sub-pixel displacement.
    np.testing.assert_allclose(g_flow, np.tile(step, (len(g_flow), 1)), atol=0.2)


def test_a_soft_low_contrast_texture_still_fills_the_templates():
    """lambda_t = 10 DN^2: a soft texture at 30 % of the lunar one's contrast (blurred, like a smooth
    mare or a photograph of the Moon) gave 7 tracks a frame at the former 30; its strongest points
    are trackable, and the tracks stay within a fraction of a pixel of the warp's truth."""
    import cv2

    from bench.evaluation.textures_eval import DescentWarp, _pair_errors, descent_homographies, warp_frames
    from bench.evaluation.tracking_eval import lunar_texture

    tex = cv2.GaussianBlur(lunar_texture(512, np.random.default_rng(11)), (0, 0), 2.0)
    tex = (tex.mean() + 0.3 * (tex - tex.mean())).astype(np.float32)
    warp = DescentWarp()
    hs = descent_homographies(tex.shape, 256, 12, warp)
    imgs = warp_frames(tex, hs, 256, warp.noise_dn, seed=2)
    tr = Tracker(TrackerConfig())
    outs = [tr.step(im) for im in imgs]
    assert np.mean([o.ids.size for o in outs[1:]]) >= 80
    pair = _pair_errors(hs, tex.shape, 256)
    err = np.concatenate([pair(k, outs[k], outs[k + 1]) for k in range(len(imgs) - 1)])
    assert err.size > 500 and np.median(err) < 0.15
