"""``landbench track-eval --imagery textures``: both trackers on real imagery.

scikit-image's natural textures (``data.gravel()``, ``data.grass()``,
``data.brick()``: photographs shipped inside its wheel, nothing is downloaded)
are warped by known descent-like homographies: the image scale grows by a
fixed fraction per frame (zoom-in, as in a descent), with a slow rotation, a
drift and a slight, slowly turning perspective tilt. The truth correspondence
of a point of frame k is taken from the warp: back through frame k's
homography into the texture, forward through frame k+1's.

Both trackers run on the same frames in the same process, interleaved
(:func:`bench.evaluation.tracking_eval.run_interleaved`), and are scored with
the same statistics as the rendered descent (tracks per frame, median and p95
endpoint error, share within 1 px, lifetime, ms per frame).

Pixels: x = column, y = row, integer values at pixel centres (OpenCV's
``warpPerspective`` convention as well). A homography ``H`` maps texture
pixels (x, y, 1) to image pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from bench.evaluation.tracking_eval import (
    FULL_SCALE_DN,
    BaselineConfig,
    OpenCVBaseline,
    Stepper,
    endpoint_error_stats,
    format_subpixel_setup,
    run_interleaved,
    sequence_metrics,
)
from vision import Tracker, TrackerConfig
from vision.tracks import Tracks

TEXTURES = ("gravel", "grass", "brick")
"""scikit-image textures used, each a 512 x 512 uint8 photograph."""

TRUTH_BORDER_PX = 2.0
"""Truth is invalid where the texture point lies closer than this to the
texture's edge (the warp reflects the texture there)."""

TEXTURE_FRAMES = 48
"""Default frames per texture: the scale grows from 0.75 to about 1.9 image
pixels per texture pixel at 2 % per frame."""


@dataclass(frozen=True)
class DescentWarp:
    """Per-frame motion of the warped-texture descent (image pixels of a
    256 x 256 image; :meth:`for_size` scales it to other sizes).

    Attributes:
        start_scale: Image pixels per texture pixel in frame 0 [-].
        zoom_per_frame: Relative growth of the scale per frame [-] (the
            rendered default descent zooms ~1.9 % per frame).
        rotation_deg_per_frame: Image rotation per frame [deg].
        drift_px_per_frame: Image translation per frame (x, y) [px].
        tilt_per_px: Amplitude of the projective terms h20, h21 [1/px] (a
            slight perspective: the scale varies by +-tilt x half-size across
            the image).
        tilt_turn_deg_per_frame: Rotation of the tilt direction per frame [deg].
        noise_dn: Gaussian pixel noise added to each frame, 1-sigma [DN].
    """

    start_scale: float = 0.75
    zoom_per_frame: float = 0.02
    rotation_deg_per_frame: float = 0.25
    drift_px_per_frame: tuple[float, float] = (0.6, -0.4)
    tilt_per_px: float = 1e-4
    tilt_turn_deg_per_frame: float = 4.0
    noise_dn: float = 1.0

    def for_size(self, size: int) -> DescentWarp:
        """The same motion seen by a ``size`` x ``size`` image (same field of
        view over the texture): pixel quantities scale by size / 256."""
        k = size / 256.0
        return replace(self, start_scale=self.start_scale * k, tilt_per_px=self.tilt_per_px / k,
                       drift_px_per_frame=(self.drift_px_per_frame[0] * k, self.drift_px_per_frame[1] * k))


def load_texture(name: str) -> np.ndarray:
    """One of scikit-image's shipped textures as float32 grey [DN].

    Raises:
        ValueError: On an unknown name, or when scikit-image is not installed
            (with the install command).
    """
    if name not in TEXTURES:
        raise ValueError(f"texture {name!r} unknown; choose from {', '.join(TEXTURES)}")
    try:
        from skimage import data
    except ImportError:  # pragma: no cover - depends on the environment
        raise ValueError(
            "--imagery textures needs scikit-image (its shipped textures gravel, grass, brick): "
            "pip install 'landbench[textures]' or pip install scikit-image"
        ) from None
    img = getattr(data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


def descent_homographies(tex_shape: tuple[int, int], size: int, n_frames: int,
                         warp: DescentWarp = DescentWarp()) -> list[np.ndarray]:
    """Texture -> image homographies of a zoom-in descent over the texture.

    ``H_k = T(c_img + d_k) P_k R(theta_k) S(s_k) T(-c_tex)``: the texture's
    centre ``c_tex`` is scaled by ``s_k = start_scale (1 + zoom)^k`` and
    rotated by ``theta_k`` about the image centre ``c_img``, tilted by the
    projective row ``P_k = [[1, 0, 0], [0, 1, 0], [p cos phi_k, p sin phi_k, 1]]``
    (image coordinates centred) and shifted by the drift ``d_k``.

    Args:
        tex_shape: (H, W) of the texture [px].
        size: Side of the square image [px].
        n_frames: Number of frames.
        warp: The motion (in this image's pixels).

    Returns:
        ``n_frames`` (3, 3) float64 homographies, normalised to ``H[2, 2] = 1``.
    """
    ht, wt = tex_shape
    c_tex = np.array([(wt - 1) / 2.0, (ht - 1) / 2.0])
    c_img = (size - 1) / 2.0
    out = []
    for k in range(n_frames):
        s = warp.start_scale * (1.0 + warp.zoom_per_frame) ** k
        th = np.radians(warp.rotation_deg_per_frame * k)
        ph = np.radians(warp.tilt_turn_deg_per_frame * k)
        to_centre = np.array([[1.0, 0.0, -c_tex[0]], [0.0, 1.0, -c_tex[1]], [0.0, 0.0, 1.0]])
        rs = np.array([[s * np.cos(th), -s * np.sin(th), 0.0], [s * np.sin(th), s * np.cos(th), 0.0], [0.0, 0.0, 1.0]])
        tilt = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                         [warp.tilt_per_px * np.cos(ph), warp.tilt_per_px * np.sin(ph), 1.0]])
        dx, dy = warp.drift_px_per_frame
        to_image = np.array([[1.0, 0.0, c_img + dx * k], [0.0, 1.0, c_img + dy * k], [0.0, 0.0, 1.0]])
        h = to_image @ tilt @ rs @ to_centre
        out.append(h / h[2, 2])
    return out


def apply_homography(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``h`` applied to points (N, 2) [px] -> (N, 2) [px]."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    p = h @ np.vstack([xy.T, np.ones(len(xy))])
    return (p[:2] / p[2]).T


def warp_frames(texture: np.ndarray, homographies: Sequence[np.ndarray], size: int, noise_dn: float,
                seed: int = 0) -> list[np.ndarray]:
    """Render the frames: ``cv2.warpPerspective`` (bilinear, texture reflected
    past its edge) plus Gaussian noise, rounded to uint8 [DN]."""
    rng = np.random.default_rng(seed)
    frames = []
    for h in homographies:
        img = cv2.warpPerspective(texture, h, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        if noise_dn > 0:
            img = img + rng.normal(0.0, noise_dn, img.shape).astype(np.float32)
        frames.append(np.clip(np.rint(img), 0, FULL_SCALE_DN).astype(np.uint8))
    return frames


def homography_truth(xy_k: np.ndarray, h_k: np.ndarray, h_k1: np.ndarray, tex_shape: tuple[int, int],
                     size: int) -> tuple[np.ndarray, np.ndarray]:
    """True position in frame k+1 of points of frame k, from the warp.

    Returns:
        (xy_k1 (N, 2) [px], NaN where invalid; valid (N,) bool). Invalid: the
        texture point is within ``TRUTH_BORDER_PX`` of the texture's edge
        (reflected content), or the point leaves frame k+1's pixel-centre hull.
    """
    t = apply_homography(np.linalg.inv(h_k), xy_k)
    ht, wt = tex_shape
    b = TRUTH_BORDER_PX
    valid = (t[:, 0] >= b) & (t[:, 0] <= wt - 1 - b) & (t[:, 1] >= b) & (t[:, 1] <= ht - 1 - b)
    xy_k1 = apply_homography(h_k1, t)
    valid &= (xy_k1[:, 0] >= 0) & (xy_k1[:, 0] <= size - 1) & (xy_k1[:, 1] >= 0) & (xy_k1[:, 1] <= size - 1)
    return np.where(valid[:, None], xy_k1, np.nan), valid


def _pair_errors(hs: Sequence[np.ndarray], tex_shape: tuple[int, int], size: int
                 ) -> Callable[[int, Tracks, Tracks], np.ndarray]:
    def errors(k: int, a: Tracks, b: Tracks) -> np.ndarray:
        _, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
        if ia.size == 0:
            return np.zeros(0)
        truth, valid = homography_truth(a.xy[ia], hs[k], hs[k + 1], tex_shape, size)
        return np.linalg.norm(b.xy[ib][valid] - truth[valid], axis=1)

    return errors


def run_textures_eval(size: int = 256, frames: int = TEXTURE_FRAMES, repeats: int = 3,
                      tracker_config: TrackerConfig | None = None, baseline_config: BaselineConfig | None = None,
                      textures: Sequence[str] = TEXTURES, warp: DescentWarp = DescentWarp(),
                      cv_threads: int | None = 1) -> dict[str, Any]:
    """Score the tracker and the OpenCV baseline on every texture.

    ``warp`` is given for a 256 x 256 image and scaled to ``size``
    (:meth:`DescentWarp.for_size`), so both sizes see the same part of the
    texture. OpenCV runs on ``cv_threads`` threads (1: as ``track-eval``).

    Returns:
        ``{"imagery": "textures", "size": N, "frames": F, "repeats": R,
        "warp": {...}, "results": {texture: {"tracker": metrics, "opencv":
        metrics}, ..., "all": {...}}}``; "all" pools the endpoint errors of
        every texture and averages tracks, lifetimes and ms per frame over
        the textures.
    """
    if frames < 3:
        raise ValueError(f"frames = {frames}: need at least 3")
    if repeats < 1:
        raise ValueError(f"repeats = {repeats}: must be >= 1")
    tcfg = tracker_config or TrackerConfig()
    bcfg = baseline_config or BaselineConfig()
    warp = warp.for_size(size)
    factories: Mapping[str, Callable[[], Stepper]] = {
        "tracker": lambda: Tracker(tcfg), "opencv": lambda: OpenCVBaseline(bcfg)}
    results: dict[str, Any] = {}
    pooled: dict[str, list[np.ndarray]] = {n: [] for n in factories}
    saved = cv2.getNumThreads()
    if cv_threads is not None:
        cv2.setNumThreads(int(cv_threads))
    try:
        for i, name in enumerate(textures):
            tex = load_texture(name)
            hs = descent_homographies(tex.shape, size, frames, warp)
            imgs = warp_frames(tex, hs, size, warp.noise_dn, seed=i)
            outputs, timing = run_interleaved(factories, imgs, repeats)
            pair = _pair_errors(hs, tex.shape, size)
            results[name] = {}
            for n in factories:
                results[name][n] = {**sequence_metrics(outputs[n], pair), **timing[n]}
                pooled[n].extend(pair(k, outputs[n][k], outputs[n][k + 1]) for k in range(frames - 1))
    finally:
        cv2.setNumThreads(saved)
    results["all"] = {}
    for n in factories:
        per = [results[t][n] for t in textures]
        results["all"][n] = {
            **endpoint_error_stats(np.concatenate(pooled[n]) if pooled[n] else np.zeros(0)),
            **{k: float(np.mean([m[k] for m in per])) for k in (
                "tracks_per_frame_mean", "mean_lifetime_frames", "ms_per_frame_mean", "ms_per_frame_median",
                "ms_per_frame_min_of_repeats_mean", "minor_faults_per_frame")},
        }
    return {"imagery": "textures", "size": size, "frames": frames, "repeats": repeats,
            "tracker_setup": tcfg.subpixel_setup(size),
            "warp": {**warp.__dict__, "drift_px_per_frame": list(warp.drift_px_per_frame)}, "results": results}


def format_textures_eval(report: dict[str, Any], keys: Sequence[tuple[str, str, str]]) -> str:
    """Terminal table: one block per texture and the pooled "all", then the time ratio."""
    w = report["warp"]
    lines = [f"scikit-image textures warped by a descent: {report['size']}x{report['size']}, {report['frames']} "
             f"frames each, zoom {100 * w['zoom_per_frame']:.1f} %/frame from scale {w['start_scale']}, "
             f"{w['rotation_deg_per_frame']} deg/frame, drift {w['drift_px_per_frame']} px/frame, tilt "
             f"{w['tilt_per_px']}/px, noise {w['noise_dn']} DN; {report['repeats']} timed repeats"
             f"{format_subpixel_setup(report.get('tracker_setup'))}"]
    ms = "ms_per_frame_min_of_repeats_mean"
    for tex, res in report["results"].items():
        lines.append(f"\n{tex}" + "".join(f"{name:>14}" for name in res))
        for key, label, fmt in keys:
            lines.append(f"  {label:<20}" + "".join(f"{fmt.format(m[key]):>14}" for m in res.values()))
        lines.append(f"  {'time ratio':<20}{res['tracker'][ms] / res['opencv'][ms]:>14.2f}")
    return "\n".join(lines)
