"""``landbench track-eval``: the paper's tracker against truth and against OpenCV.

A descent is rendered from the simulated world (:mod:`bench.sim.descent`). Both
trackers run on the same frames in the same process, interleaved
(:func:`bench.evaluation.tracking_eval.compare`). Every tracked point is back-projected
through the depth image and the camera pose of its frame and projected into
the next frame; the endpoint error is the distance to where the tracker put
it. Reported per tracker: tracks per frame, median and p95 endpoint error
[px], share of tracks within 1 px, mean track lifetime [frames], ms per
frame, and the minor page faults per frame inside the timed steps (a tracker
that faults pays the kernel in its time: see
:func:`bench.evaluation.tracking_eval.run_interleaved`).
"""

from __future__ import annotations

from typing import Any

from bench.sim.descent import render_descent
from bench.scenario import Scenario
from bench.evaluation.tracking_eval import BaselineConfig, OpenCVBaseline, compare, format_subpixel_setup
from vision import Tracker, TrackerConfig

REPORT_KEYS = (
    ("tracks_per_frame_mean", "tracks/frame", "{:.1f}"),
    ("epe_median_px", "EPE median [px]", "{:.3f}"),
    ("epe_p95_px", "EPE p95 [px]", "{:.3f}"),
    ("within_1px_frac", "within 1 px", "{:.2%}"),
    ("mean_lifetime_frames", "lifetime [frames]", "{:.1f}"),
    ("ms_per_frame_min_of_repeats_mean", "ms/frame", "{:.3f}"),
    ("ms_per_frame_median", "ms/frame median", "{:.3f}"),
    ("minor_faults_per_frame", "page faults/frame", "{:.1f}"),
)


def run_track_eval(scenario: Scenario, sizes: list[int], frames: int, repeats: int,
                   tracker_config: TrackerConfig | None = None,
                   baseline_config: BaselineConfig | None = None) -> dict[str, Any]:
    """Render a descent per image size and compare the trackers on it.

    Returns:
        ``{"frames": N, "descent": {...}, "results": {"256": {"tracker": metrics, "opencv": metrics}, ...},
        "tracker_setup": {"256": {"lk_bias_correction": bool, "fb_blend": w}, ...}}``: the tracker's
        sub-pixel refinement at each size (``TrackerConfig.subpixel_setup``).
    """
    tcfg = tracker_config or TrackerConfig()
    bcfg = baseline_config or BaselineConfig()
    out: dict[str, Any] = {
        "frames": frames,
        "repeats": repeats,
        "descent": {"from_altitude_m": scenario.initial.r_BL_L_m[2], "to_altitude_m": 30.0,
                    "camera_period_ns": scenario.camera.period_ns, "fovy_deg": scenario.camera.fovy_deg},
        "results": {},
        "tracker_setup": {},
    }
    for size in sizes:
        cam = scenario.camera.model_copy(update={"width_px": size, "height_px": size})
        sc = scenario.model_copy(update={"camera": cam})
        d = render_descent(sc, frames)
        poses = list(zip(d.R_LC, d.r_CL_L))
        res = compare(
            {"tracker": lambda: Tracker(tcfg), "opencv": lambda: OpenCVBaseline(bcfg)},
            list(d.frames), list(d.depths), d.K, poses, repeats=repeats,
        )
        out["results"][str(size)] = res
        out["tracker_setup"][str(size)] = tcfg.subpixel_setup(size)
    return out


def format_track_eval(report: dict[str, Any]) -> str:
    d = report["descent"]
    lines = [f"descent {d['from_altitude_m']:.0f} m -> {d['to_altitude_m']:.0f} m, {report['frames']} frames at "
             f"{1e9 / d['camera_period_ns']:.0f} Hz, {report['repeats']} timed repeats (ms/frame: mean over frames "
             "of the fastest repeat)"]
    for size, res in report["results"].items():
        setup = format_subpixel_setup(report.get("tracker_setup", {}).get(size))
        lines.append(f"\n{size}x{size}{setup}" + "".join(f"{name:>14}" for name in res))
        for key, label, fmt in REPORT_KEYS:
            lines.append(f"  {label:<20}" + "".join(f"{fmt.format(m[key]):>14}" for m in res.values()))
    return "\n".join(lines)
