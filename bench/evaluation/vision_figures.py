"""Figures of the vision pipeline, one PNG per stage, after the paper's Figs. 3-8.

Pure: images in, PNG files out (matplotlib, Agg backend); no simulator.

=====================================  =========================================
file                                   paper
=====================================  =========================================
``fig3a_averaged.png``                 Fig. 3(a): averaged image, eq. (2.1)
``fig3b_laplacian.png``                Fig. 3(b): 8-neighbour Laplacian
``fig3c_variance.png``                 Fig. 3(c): variance map, eq. (2.2)
``fig3d_areas.png``                    Fig. 3(d): extracted areas on the image
``fig4_templates.png``                 Fig. 4: the templates (sub-images)
``fig5_template_match.png``            Fig. 5: template matching over 3 frames
``fig6_fp_detection.png``              Fig. 6: feature points (W1 = 3)
``fig7_fp_tracks_subimage.png``        Fig. 7: FP tracks in one sub-image
``fig8_fp_tracks_whole.png``           Fig. 8: FP tracks in the whole image
=====================================  =========================================
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from vision import Tracker, TrackerConfig, check_image, detect_in_subimages  # noqa: E402

FIG_DPI = 110
"""Resolution of the written PNGs [dots per inch]."""
FIG_SIZE_IN = 5.0
"""Side of a single-panel figure [in]."""
MATCH_FRAMES = 3
"""Frames shown in the template-matching figure (as in the paper's Fig. 5)."""
BOX_COLOUR = "yellow"
TRACK_COLOUR = "lime"
POINT_COLOUR = "red"


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=FIG_DPI)
    plt.close(fig)
    return path


def _image_axes(title: str) -> tuple[plt.Figure, plt.Axes]:
    fig, ax = plt.subplots(figsize=(FIG_SIZE_IN, FIG_SIZE_IN))
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()
    return fig, ax


def _show(ax: plt.Axes, img: np.ndarray, cmap: str = "gray") -> None:
    # extent puts integer coordinates at pixel centres (x = column, y = row).
    h, w = img.shape
    ax.imshow(img, cmap=cmap, interpolation="nearest", extent=(-0.5, w - 0.5, h - 0.5, -0.5))


def write_vision_figures(
    frames: Sequence[np.ndarray], out_dir: str | Path, config: TrackerConfig | None = None
) -> list[Path]:
    """Write one PNG per pipeline stage for a short image sequence.

    Args:
        frames: At least 3 grayscale frames, each (H, W) uint8 or float32 [DN];
            the static stages use ``frames[0]``.
        out_dir: Output directory (created if missing).
        config: Tracker parameters (Sx, Sy, template size, W1, ...); defaults
            to :class:`vision.TrackerConfig` (Sx = Sy = 5, W1 = 3 as in the paper).

    Returns:
        Paths of the written PNG files, in the order of the table above.

    Raises:
        ValueError: If fewer than 3 frames are given or a frame is invalid.
    """
    if len(frames) < MATCH_FRAMES:
        raise ValueError(f"frames must hold at least {MATCH_FRAMES} images, got {len(frames)}")
    for k, f in enumerate(frames):
        check_image(f, name=f"frames[{k}]")
    cfg = config if config is not None else TrackerConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    first = frames[0]
    height, width = first.shape
    sx, sy, size = cfg.subsample_x, cfg.subsample_y, cfg.template_size
    paths: list[Path] = []

    # Fig. 3: band-pass filtering and variance map of frame 0 (the tracker's own §2 pipeline).
    areas = Tracker(cfg).fixation_areas(first, cfg.n_templates)
    avg, lap, var, tl = areas.averaged, areas.laplacian, areas.variance, areas.top_left
    fig, ax = _image_axes(f"averaged image, eq. (2.1), Sx = {sx}, Sy = {sy}  ({avg.shape[1]} x {avg.shape[0]})")
    _show(ax, avg)
    paths.append(_save(fig, out / "fig3a_averaged.png"))

    fig, ax = _image_axes("8-neighbour Laplacian of the averaged image")
    _show(ax, lap)
    paths.append(_save(fig, out / "fig3b_laplacian.png"))

    wx, wy = size // sx, size // sy
    fig, ax = _image_axes(f"variance map, eq. (2.2), window {wx} x {wy}")
    _show(ax, var, cmap="magma")
    paths.append(_save(fig, out / "fig3c_variance.png"))

    fig, ax = _image_axes(f"extracted areas ({len(tl)} templates of {size} x {size} px)")
    _show(ax, first)
    for x, y in tl.tolist():
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, ec=BOX_COLOUR, lw=1.2))
    paths.append(_save(fig, out / "fig3d_areas.png"))

    # Fig. 4: template montage.
    n_tpl = max(len(tl), 1)
    fig, axes = plt.subplots(1, n_tpl, figsize=(1.6 * n_tpl, 1.9), squeeze=False)
    for i, ax in enumerate(axes[0]):
        ax.set_axis_off()
        if i < len(tl):
            x, y = tl[i]
            ax.imshow(first[y : y + size, x : x + size], cmap="gray", interpolation="nearest")
            ax.set_title(f"T{i}", fontsize=8)
    fig.suptitle(f"templates (sub-images), {size} x {size} px", fontsize=9)
    paths.append(_save(fig, out / "fig4_templates.png"))

    # Fig. 5-8 need the tracker over the sequence.
    tracker = Tracker(cfg)
    tracks, templates = [], []
    for img in frames:
        tracks.append(tracker.step(img))
        templates.append((tracker.templates, tracker.track_templates))

    fig, ax = _image_axes(f"template matching over {MATCH_FRAMES} frames (boxes: positions; arrows: motion)")
    _show(ax, first)
    styles = ["-", "--", ":"]
    for k in range(MATCH_FRAMES):
        for x, y in templates[k][0].tolist():
            ax.add_patch(
                Rectangle((x - 0.5, y - 0.5), size, size, fill=False, ec=BOX_COLOUR, lw=1.0, ls=styles[k % 3])
            )
    # Follow each frame-0 template through the frames by its nearest successor.
    start = templates[0][0].astype(float)
    pos = start.copy()
    for k in range(1, MATCH_FRAMES):
        nxt = templates[k][0].astype(float)
        if len(nxt) and len(pos):
            d2 = ((pos[:, None, :] - nxt[None, :, :]) ** 2).sum(axis=2)
            pos = nxt[d2.argmin(axis=1)]
    half = 0.5 * (size - 1)
    for (x0, y0), (x1, y1) in zip(start.tolist(), pos.tolist()):
        ax.annotate(
            "",
            xy=(x1 + half, y1 + half),
            xytext=(x0 + half, y0 + half),
            arrowprops=dict(arrowstyle="->", color="cyan", lw=1.2),
        )
    paths.append(_save(fig, out / "fig5_template_match.png"))

    feats = detect_in_subimages(
        first,
        templates[0][0],
        (size, size),
        window=cfg.fp_window,
        lambda_t=cfg.lambda_t,
        max_features=cfg.max_features_per_template,
        nms_radius=cfg.fp_nms_radius,
    )
    fig, ax = _image_axes(f"feature points, W1 = {cfg.fp_window}, lambda_t = {cfg.lambda_t:g} ({len(feats.xy)} points)")
    _show(ax, first)
    for x, y in templates[0][0].tolist():
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, ec=BOX_COLOUR, lw=0.8))
    ax.plot(feats.xy[:, 0], feats.xy[:, 1], "+", color=POINT_COLOUR, ms=5)
    paths.append(_save(fig, out / "fig6_fp_detection.png"))

    # Tracks: polylines of each id over the sequence.
    history: dict[int, list[tuple[float, float]]] = {}
    for t in tracks:
        for i, (x, y) in zip(t.ids.tolist(), t.xy.tolist()):
            history.setdefault(i, []).append((x, y))

    # Fig. 7: the sub-image of template 0 in frame 0, with the tracks of its points.
    fig, ax = _image_axes("FP tracks in a sub-image")
    if len(templates[0][0]):
        x, y = templates[0][0][0].tolist()
        pad = size // 2
        x0, y0 = max(x - pad, 0), max(y - pad, 0)
        x1, y1 = min(x + size + pad, width), min(y + size + pad, height)
        ax.imshow(first[y0:y1, x0:x1], cmap="gray", interpolation="nearest", extent=(x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5))
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, ec=BOX_COLOUR, lw=1.0))
        ids0 = tracks[0].ids[templates[0][1] == 0]
        for i in ids0.tolist():
            pts = np.asarray(history[i])
            ax.plot(pts[:, 0], pts[:, 1], "-", color=TRACK_COLOUR, lw=1.0)
            ax.plot(pts[-1, 0], pts[-1, 1], "o", color=POINT_COLOUR, ms=3)
    paths.append(_save(fig, out / "fig7_fp_tracks_subimage.png"))

    fig, ax = _image_axes(f"FP tracks in the whole image ({len(frames)} frames, {len(history)} tracks)")
    _show(ax, frames[-1])
    for pts in history.values():
        p = np.asarray(pts)
        if len(p) > 1:
            ax.plot(p[:, 0], p[:, 1], "-", color=TRACK_COLOUR, lw=0.8)
        ax.plot(p[-1, 0], p[-1, 1], ".", color=POINT_COLOUR, ms=2)
    paths.append(_save(fig, out / "fig8_fp_tracks_whole.png"))
    return paths
