"""Synthetic ``landbench replay`` folders (metrics.json + frames.parquet) for the compare tests.

Written with the replay's own writers' formats: ``metrics.json`` as
:func:`bench.evaluation.replay.replay_dataset` lays it out and
``frames.parquet`` through :func:`bench.report.report.write_telemetry_parquet`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from bench.report.report import write_telemetry_parquet

FRAMES_PER_SEQ = 30
FRAME_PERIOD_NS = 100_000_000


def sequence(seed: int, epe_median_px: float, vel_rms_mps: float, gate_rejections: int) -> dict:
    """One sequence's entry of metrics.json (the fields compare reads)."""
    return {
        "seed": seed, "recording": f"ds/seed_{seed:03d}", "recording_manifest_sha256": f"{seed:064x}",
        "control_ticks": 301, "touchdown_t_s": None,
        "navigation": {"vel_err_rms_mps": vel_rms_mps, "pos_err_end_m": 10.0 + seed,
                       "updates": {"vision": {"updates": 50, "gate_rejections": gate_rejections}}},
        "vision": {"frames": FRAMES_PER_SEQ, "tracks_per_frame_mean": 70.0 + seed, "epe_median_px": epe_median_px,
                   "tracker_ms_per_frame_mean": 0.5},
        "replay_wall_s": 1.0, "identical_to_recording": True, "differing_nav_columns": [],
    }


def frames_table(seeds: Sequence[int], tracks: np.ndarray, nis: np.ndarray, accepted: np.ndarray,
                 with_frame: bool = True) -> dict[str, np.ndarray]:
    """frames.parquet columns for ``len(seeds)`` sequences of FRAMES_PER_SEQ frames each, in file order."""
    n = len(seeds) * FRAMES_PER_SEQ
    frame = np.tile(np.arange(FRAMES_PER_SEQ), len(seeds)).astype(np.int64)
    t_ns = frame * FRAME_PERIOD_NS
    cols = {"seed": np.repeat(np.asarray(seeds, np.int64), FRAMES_PER_SEQ), "t_s": t_ns / 1e9}
    if with_frame:
        cols["frame"] = frame
    cols.update({"t_ns": t_ns, "vision_active": np.ones(n, bool), "tracks": np.asarray(tracks, np.int64),
                 "tracker_ms": np.full(n, 0.5), "measurement": np.ones(n, bool), "accepted": np.asarray(accepted, bool),
                 "rejected": ~np.asarray(accepted, bool), "nis": np.asarray(nis, float)})
    return cols


def write_replay(path: Path, seqs: Sequence[Mapping], frames: Mapping[str, np.ndarray]) -> Path:
    """A replay folder: metrics.json and frames.parquet."""
    path.mkdir(parents=True)
    doc = {"format": "landbench-replay", "format_version": 1, "dataset": "ds", "seeds": [s["seed"] for s in seqs],
           "overrides": [], "sequences": list(seqs), "dataset_metrics": {}}
    (path / "metrics.json").write_text(json.dumps(doc, indent=1))
    write_telemetry_parquet(dict(frames), path / "frames.parquet")
    return path


def replay_pair(root: Path, seeds: Sequence[int] = (1, 2, 3), rng_seed: int = 5, with_frame: bool = True
                ) -> tuple[Path, Path, dict]:
    """BASE and CAND replay folders of the same recordings; CAND has a worse EPE and flips some accepted frames.

    Returns (base, cand, the arrays written: tracks, nis, accepted per side).
    """
    rng = np.random.default_rng(rng_seed)
    n = len(seeds) * FRAMES_PER_SEQ
    tracks_b = rng.integers(60, 90, n)
    tracks_c = tracks_b - rng.integers(0, 5, n)
    nis_b = rng.chisquare(2, n)
    nis_c = nis_b * 1.3 + rng.normal(0, 0.05, n)
    acc_b = rng.random(n) < 0.9
    acc_c = acc_b.copy()
    flips = rng.choice(n, 9, replace=False)
    acc_c[flips] = ~acc_c[flips]
    base = write_replay(root / "base", [sequence(s, 0.07 + 0.001 * s, 0.05, 1) for s in seeds],
                        frames_table(seeds, tracks_b, nis_b, acc_b, with_frame))
    cand = write_replay(root / "cand", [sequence(s, 0.14 + 0.002 * s, 0.06, 2 + s) for s in seeds],
                        frames_table(seeds, tracks_c, nis_c, acc_c, with_frame))
    return base, cand, {"tracks": (tracks_b, tracks_c), "nis": (nis_b, nis_c), "accepted": (acc_b, acc_c)}
