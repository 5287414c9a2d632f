"""Open-loop replay of recorded descents: did a change to the tracker, vision measurement or filter help?

Inputs: a dataset written by ``landbench record`` (:mod:`bench.evaluation.record`:
one recording, or a folder of ``seed_NNN`` recordings, each verified against
its manifest) and ``--set`` overrides of the flight software's ``tracker``,
``vision_nav`` and ``estimator`` sections only (everything else shaped the
recorded world and sensors, which a replay cannot change).

What happens: per recording, the flight software is built from the recorded
(resolved) scenario with the overrides applied, exactly as the closed loop
builds it (:func:`bench.sim.flight_build.build_flight_software` with the
hand-over estimate drawn from the seed's "estimator" stream around the
recorded truth at t = 0), and every recorded message is fed in recorded order
to the same :class:`~gnc.flight.FlightSoftware` methods (``on_imu``,
``on_attitude``, ``on_altimeter``, ``on_image``). At each control tick the
mass gauge takes the thrust command that was flown (telemetry
``thrust_cmd_N``, ``engine_on``; :meth:`~gnc.flight.FlightSoftware.on_flown_command`).
Guidance and control are not run: the vehicle does not respond in an open-loop
replay, so a recomputed command would fly nothing, and navigation does not
depend on them. No MuJoCo model is built, stepped or rendered.

Outputs (:func:`write_replay`):
    ``DIR/metrics.json``: per sequence and over the dataset, against the
        recorded truth: navigation (velocity error RMS, horizontal velocity
        error at the vision cut-off, position error at the end, gate rejections
        and mean NIS per sensor) and vision (tracks per frame, tracker and
        vision ms per frame, measurements), and whether the replayed estimates
        equal the recorded ones bit for bit.
    ``DIR/frames.parquet``: per camera frame: seed, frame index in its
        recording, t, tracks, tracker ms,
        measurement formed / accepted / rejected, its NIS.
    ``DIR/nav.parquet``: per control tick: seed, t and the replayed ``nav_*``
        telemetry columns (as the closed loop names them).

With no overrides the replayed ``nav_*`` columns equal the recording's
telemetry bit for bit (``identical_to_recording``), on the machine and
library versions that recorded it.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from bench.evaluation.consistency import NEES_BLOCKS, block_nees_many
from bench.evaluation.record import (KINDS, MANIFEST, Recording, find_recordings, open_recording, recorded_scenario,
                                     sha256_file, verify_recording)
from bench.evaluation.tracking_eval import endpoint_error_stats, pair_endpoint_errors
from bench.report.io import atomic_write_text, json_safe
from bench.scenario import NS_PER_S, Scenario, ScenarioError
from bench.sim.flight_build import build_flight_software, handover_estimate
from gnc.estimator import IDX_BA, IDX_R, IDX_V, KIND_ALTIMETER, KIND_VELOCITY, KIND_VISION
from gnc.messages import N_LEGS, AltimeterMessage, AttitudeMessage, ContactMessage, ImageMessage, ImuMessage

REPLAYABLE_SECTIONS = ("tracker", "vision_nav", "estimator")
FORMAT = "landbench-replay"
FORMAT_VERSION = 1
EPE_KEYS = ("epe_median_px", "epe_p95_px", "within_1px_frac")  # as landbench track-eval names them
METRICS = "metrics.json"
FRAMES = "frames.parquet"
NAV = "nav.parquet"
VEL_RMS_BELOW_M = 100.0  # as the closed loop's vel_err_rms_mps
UPDATE_KINDS = (KIND_ALTIMETER, KIND_VELOCITY, KIND_VISION)
NAV_COLUMNS = (
    "nav_r_x_m", "nav_r_y_m", "nav_r_z_m", "nav_v_x_mps", "nav_v_y_mps", "nav_v_z_mps",
    "nav_err_r_x_m", "nav_err_r_y_m", "nav_err_r_z_m", "nav_err_v_x_mps", "nav_err_v_y_mps", "nav_err_v_z_mps",
    "nav_sigma_r_x_m", "nav_sigma_r_y_m", "nav_sigma_r_z_m",
    "nav_sigma_v_x_mps", "nav_sigma_v_y_mps", "nav_sigma_v_z_mps",
    "nav_err_ba_x_mps2", "nav_err_ba_y_mps2", "nav_err_ba_z_mps2",
    *(f"nees_{block}" for block in NEES_BLOCKS), "fsw_mass_kg",
    "vision_tracks", "vision_measurements", "vision_rejected", "vision_v_x_mps", "vision_v_y_mps",
)
"""The closed loop's telemetry columns that come from the flight software (bench.sim.run._row, same order)."""
_INT_COLUMNS = ("vision_tracks", "vision_measurements", "vision_rejected")
_IMU, _ATTITUDE, _ALTIMETER, _IMAGE, _CONTROL = (KINDS.index(k) for k in ("imu", "attitude", "altimeter", "image",
                                                                            "control"))


def check_overrides(overrides: list[str] | tuple[str, ...]) -> None:
    """Refuse any ``--set`` outside the replayable sections, with one line saying why."""
    for assignment in overrides:
        key = assignment.partition("=")[0].strip()
        section = key.split(".", 1)[0].strip().strip('"').strip("'")
        if section not in REPLAYABLE_SECTIONS:
            raise ValueError(
                f"--set {assignment!r}: a replay may change only the flight software's "
                f"{', '.join(REPLAYABLE_SECTIONS)} sections; '{section}' shaped the recorded world, sensors or "
                "vehicle, which a replay cannot change (record again with it instead)")


@dataclass
class SequenceReplay:
    """What one recording's replay produced."""

    seed: int
    path: Path
    metrics: dict[str, Any]
    frames: dict[str, np.ndarray]
    nav: dict[str, np.ndarray]
    epe: np.ndarray | None = field(default=None, repr=False)  # every endpoint error [px]; None without depth


class _Timed:
    """Wraps the tracker's ``step`` to time it; the result is passed through untouched."""

    def __init__(self, step):
        self.step = step
        self.last_s = 0.0

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return self.step(*args, **kwargs)
        finally:
            self.last_s = time.perf_counter() - t0


def _vec(cols: dict[str, np.ndarray], names: tuple[str, ...], i: int) -> np.ndarray:
    return np.array([cols[n][i] for n in names])


_R = ("r_x_m", "r_y_m", "r_z_m")
_V = ("v_x_mps", "v_y_mps", "v_z_mps")
_BA = ("accel_bias_x_mps2", "accel_bias_y_mps2", "accel_bias_z_mps2")


def replay_recording(rec: Recording, scenario: Scenario) -> SequenceReplay:
    """Feed one recording's messages to a flight software built from ``scenario``; score it against the truth."""
    truth = rec.truth
    if int(truth["t_ns"][0]) != 0:
        raise ValueError(f"recording {str(rec.path)!r}: its truth does not start at t = 0")
    truth0 = SimpleNamespace(r_BL_L=_vec(truth, _R, 0), v_BL_L=_vec(truth, _V, 0))
    maps = None
    if scenario.nav_map == "on":  # the map the closed loop flew with (the recorded scenario's, seeded alike)
        from bench.maps import scenario_onboard_map

        maps = scenario_onboard_map(scenario)
    fsw = build_flight_software(scenario, *handover_estimate(scenario, truth0),
                                onboard_map=maps[0] if maps is not None else None)
    timer = None
    if fsw.tracker is not None:
        timer = _Timed(fsw.tracker.step)
        fsw.tracker.step = timer  # an instance attribute: times the call, changes nothing

    s = rec.sensors
    imu_t, imu_f, imu_w = s["imu_t_ns"].tolist(), s["imu_f_B"], s["imu_omega_B"]
    att_t, att_q = s["attitude_t_ns"].tolist(), s["attitude_q_LB"]
    alt_t, alt_r, alt_ok, alt_b = (s["altimeter_t_ns"].tolist(), s["altimeter_range_m"].tolist(),
                                   s["altimeter_valid"].tolist(), s["altimeter_boresight_B"])
    ctl_t = s["control_t_ns"].tolist()
    tel = rec.telemetry
    if "thrust_cmd_N" not in tel or "engine_on" not in tel or len(tel["thrust_cmd_N"]) != len(ctl_t):
        raise ValueError(f"recording {str(rec.path)!r}: its telemetry lacks the flown commands "
                         "(thrust_cmd_N, engine_on) of every control tick")
    thrust_cmd, engine_on = tel["thrust_cmd_N"].tolist(), tel["engine_on"].tolist()
    # The fault detection's clocked checks run on the flown commands and contacts, as in flight.
    legs_in = tel["legs_in_contact"].tolist() if "legs_in_contact" in tel else [0] * len(ctl_t)
    torque = (np.column_stack([tel[f"torque_{a}_Nm"] for a in "xyz"]).astype(float)
              if all(f"torque_{a}_Nm" in tel for a in "xyz") else np.zeros((len(ctl_t), 3)))
    oracle = scenario.nav == "truth"
    frame_t = rec.frames_t_ns.tolist()

    # Per control tick, what the telemetry columns are computed from after the loop (_nav_columns).
    tick_x: list[np.ndarray] = []  # the filter's state
    tick_P: list[np.ndarray] = []  # its covariance's position / velocity / accelerometer-bias block
    tick_rest: list[tuple] = []  # mass gauge and vision counters
    tick_i: list[int] = []  # the tick's row in the truth
    true_r, true_v, true_ba = (np.column_stack([truth[n] for n in names]).astype(float) for names in (_R, _V, _BA))
    if maps is not None:  # with map fixes the flight software navigates in the map's frame: truth + its shift
        true_r = true_r + np.array([*maps[1].shift_xy_m, 0.0])
    fr: dict[str, list] = {k: [] for k in ("frame", "t_ns", "vision_active", "tracks", "tracker_ms", "vision_ms",
                                            "measurement", "accepted", "rejected", "nis")}
    frame_tracks: list = []  # the tracker's output per frame (None where vision was off)
    codes, _, index = rec.events
    wall0 = time.perf_counter()
    for kind, i in zip(codes.tolist(), index.tolist(), strict=True):
        if kind == _IMU:
            fsw.on_imu(ImuMessage(imu_t[i], imu_f[i], imu_w[i]))
        elif kind == _ATTITUDE:
            fsw.on_attitude(AttitudeMessage(att_t[i], att_q[i]))
        elif kind == _ALTIMETER:
            fsw.on_altimeter(AltimeterMessage(alt_t[i], alt_r[i], alt_ok[i], alt_b[i]))
        elif kind == _IMAGE:
            v = fsw.vision
            n_meas, n_rej, active = v.measurements, v.rejected, fsw.vision_active()
            if timer is not None:
                timer.last_s = math.nan
            t0 = time.perf_counter()
            tracks = fsw.on_image(ImageMessage(frame_t[i], rec.frames[i], rec.K, rec.R_BC))
            vision_s = time.perf_counter() - t0
            measured = v.measurements > n_meas
            frame_tracks.append(tracks)
            fr["frame"].append(i)
            fr["t_ns"].append(frame_t[i])
            fr["vision_active"].append(active)
            fr["tracks"].append(len(tracks) if tracks is not None else 0)
            fr["tracker_ms"].append(timer.last_s * 1e3 if timer is not None and tracks is not None else math.nan)
            fr["vision_ms"].append(vision_s * 1e3)
            fr["measurement"].append(measured)
            fr["rejected"].append(v.rejected > n_rej)
            fr["accepted"].append(measured and v.rejected == n_rej)
            fr["nis"].append(float(v.last_record.nis) if measured and v.last_record is not None else math.nan)
        elif kind == _CONTROL:
            legs = np.arange(N_LEGS) < int(legs_in[i])  # the count of footpads in contact; the checks read any()
            fsw.on_flown_command(ctl_t[i], thrust_cmd[i], engine_on[i], ContactMessage(ctl_t[i], legs), torque[i],
                                 oracle)  # guidance's commands would fly nothing
            ekf, v = fsw.filter.ekf, fsw.vision
            tick_x.append(ekf.x.copy())
            tick_P.append(ekf.P[:9, :9].copy())
            tick_rest.append((fsw.mass_kg, len(v.last_tracks) if v.last_tracks is not None else 0, v.measurements,
                              v.rejected, *(v.last.v_L if v.last is not None else (math.nan,) * 2)))
            tick_i.append(i)
        else:  # pragma: no cover - open_recording checks the kinds
            raise ValueError(f"unknown event kind {kind}")
    wall_s = time.perf_counter() - wall0

    if tick_i != list(range(len(truth["t_ns"]))):
        raise ValueError(f"recording {str(rec.path)!r}: {len(tick_i)} control events for {len(truth['t_ns'])} "
                         "truth rows, or out of order")
    nav = _nav_columns(tick_x, tick_P, tick_rest, true_r, true_v, true_ba)
    nav = {"t_ns": np.asarray(truth["t_ns"], np.int64), **nav}
    frames = {k: np.array(v) for k, v in fr.items()}
    frames["t_ns"] = frames["t_ns"].astype(np.int64)
    frames["frame"] = frames["frame"].astype(np.int64)
    for k in ("vision_active", "measurement", "accepted", "rejected"):
        frames[k] = frames[k].astype(bool)
    frames["tracks"] = frames["tracks"].astype(np.int64)
    for k in ("tracker_ms", "vision_ms", "nis"):
        frames[k] = frames[k].astype(float)
    epe = None
    if "depth" in rec.camera:
        epe, frames["epe_median_px"], frames["epe_count"] = endpoint_errors(rec, frame_tracks)
    metrics = _sequence_metrics(rec, scenario, fsw, nav, frames, wall_s, epe)
    return SequenceReplay(seed=rec.seed, path=rec.path, metrics=metrics, frames=frames, nav=nav, epe=epe)


def endpoint_errors(rec: Recording, frame_tracks: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracker's endpoint errors against the recorded truth (the recording must hold depth).

    For each frame k whose tracker output and frame k-1's both exist, the
    tracks of k-1 are back-projected through k-1's depth image and truth
    camera pose and projected into k (:func:`bench.evaluation.tracking_eval.pair_endpoint_errors`,
    what ``landbench track-eval`` scores).

    Returns:
        (every error [px], per frame the median error [px] (NaN where none), per frame the number of errors).
    """
    cam = rec.camera
    depth, R_LC, r_CL_L = cam["depth"], cam["R_LC"], cam["r_CL_L"]
    n = len(frame_tracks)
    if depth.shape[0] != n or R_LC.shape[0] != n:
        raise ValueError(f"recording {str(rec.path)!r}: {depth.shape[0]} depth images for {n} frames")
    med, count, errs = np.full(n, math.nan), np.zeros(n, np.int64), []
    for k in range(1, n):
        a, b = frame_tracks[k - 1], frame_tracks[k]
        if a is None or b is None:
            continue
        e = pair_endpoint_errors(a, b, depth[k - 1], depth[k], rec.K, (R_LC[k - 1], r_CL_L[k - 1]),
                                 (R_LC[k], r_CL_L[k]))
        count[k] = e.size
        if e.size:
            med[k] = float(np.median(e))
            errs.append(e)
    return (np.concatenate(errs) if errs else np.zeros(0)), med, count


def _epe_metrics(epe: np.ndarray | None) -> dict[str, Any]:
    if epe is None:
        return {"truth_depth": False, "epe_count": None, **{k: None for k in EPE_KEYS}}
    st = endpoint_error_stats(epe)
    return {"truth_depth": True, "epe_count": st["n_errors"], **{k: _f(st[k]) if epe.size else None for k in EPE_KEYS}}


def _nav_columns(tick_x: list[np.ndarray], tick_P: list[np.ndarray], tick_rest: list[tuple], r_true: np.ndarray,
                 v_true: np.ndarray, ba_true: np.ndarray) -> dict[str, np.ndarray]:
    """The flight-software telemetry columns (``NAV_COLUMNS``) of every control tick, as ``bench.sim.run._row`` computes them.

    The closed loop builds them row by row; here they are built column-wise after the replay
    from each tick's state, covariance block and counters, with the same elementwise operations
    (so the same bits), and the NEES of every row at once (:func:`block_nees_many`, the same
    values as ``block_nees``).
    """
    n = len(tick_x)
    X = np.array(tick_x).reshape(n, -1)
    P = np.array(tick_P).reshape(n, 9, 9)
    e = np.concatenate([X[:, IDX_R] - r_true, X[:, IDX_V] - v_true, X[:, IDX_BA] - ba_true], axis=1)
    sig = np.sqrt(np.diagonal(P, axis1=1, axis2=2)[:, :6])
    nees = block_nees_many(e, P) if n else np.zeros((0, len(NEES_BLOCKS)))
    rest = list(zip(*tick_rest, strict=True)) if n else [()] * 6
    cols = [*X[:, IDX_R].T, *X[:, IDX_V].T, *e[:, :6].T, *sig.T, *e[:, 6:9].T, *nees.T, *rest]
    return {name: np.array(col, dtype=np.int64 if name in _INT_COLUMNS else float)
            for name, col in zip(NAV_COLUMNS, cols, strict=True)}


def differing_columns(replayed: dict[str, np.ndarray], recorded: dict[str, np.ndarray]) -> list[str]:
    """The ``nav_*`` columns whose bits differ between the replay and the recorded telemetry."""
    out = []
    for name in NAV_COLUMNS:
        a, b = replayed[name], recorded.get(name)
        if b is None or a.shape != b.shape or a.astype(b.dtype).tobytes() != b.tobytes():
            out.append(name)
    return out


def _f(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _sequence_metrics(rec: Recording, scenario: Scenario, fsw, nav: dict[str, np.ndarray],
                      frames: dict[str, np.ndarray], wall_s: float, epe: np.ndarray | None = None) -> dict[str, Any]:
    truth = rec.truth
    t = truth["t_s"]
    td = (rec.summary.get("touchdown") or {}).get("t_s")
    flying = t < td if td is not None else np.ones(t.size, bool)
    if not flying.any():
        flying[0] = True
    e_r = np.column_stack([nav[f"nav_err_r_{a}_m"] for a in "xyz"])
    e_v = np.column_stack([nav[f"nav_err_v_{a}_mps"] for a in "xyz"])
    k_end = int(np.flatnonzero(flying)[-1])
    low = flying & (truth["r_z_m"] < VEL_RMS_BELOW_M)
    cutoff_m = recorded_scenario(rec.scenario_toml).vision_nav.cutoff_altitude_m  # the recording's, so settings compare
    below = np.flatnonzero(flying & (truth["r_z_m"] <= cutoff_m))
    k_cut = int(below[0]) if below.size else None

    updates: dict[str, Any] = {}
    for kind in UPDATE_KINDS:
        recs = [r for r in fsw.filter.log if r.kind == kind]
        nis = np.array([r.nis for r in recs if math.isfinite(r.nis)])
        dof = np.array([r.z.size for r in recs if math.isfinite(r.nis)])
        updates[kind] = {
            "updates": len(recs),
            "accepted": sum(r.accepted for r in recs),
            "gate_rejections": sum(r.reason == "gate" for r in recs),
            "other_rejections": sum((not r.accepted) and r.reason != "gate" for r in recs),
            "nis_mean": _f(nis.mean()) if nis.size else None,
            "nis_per_dof_mean": _f((nis / dof).mean()) if nis.size else None,
        }
    tracked = frames["tracker_ms"][np.isfinite(frames["tracker_ms"])]
    counts = frames["tracks"][np.isfinite(frames["tracker_ms"])]
    differing = differing_columns(nav, rec.telemetry)
    sim_s = float(t[-1] - t[0]) if t.size else 0.0
    return {
        "seed": rec.seed,
        "recording": str(rec.path),
        "recording_manifest_sha256": sha256_file(rec.path / MANIFEST),  # it lists every file's sha256
        "control_ticks": int(t.size),
        "touchdown_t_s": td,
        "navigation": {
            "vel_err_rms_mps": _f(np.sqrt(np.mean(np.sum(e_v[flying] ** 2, axis=1)))),
            "vel_err_rms_below_100m_mps": (_f(np.sqrt(np.mean(np.sum(e_v[low] ** 2, axis=1)))) if low.any()
                                           else None),
            "vision_cutoff_altitude_m": cutoff_m,
            "vel_err_horizontal_at_cutoff_mps": _f(np.hypot(*e_v[k_cut, :2])) if k_cut is not None else None,
            "pos_err_end_m": _f(np.linalg.norm(e_r[k_end])),
            "pos_err_end_horizontal_m": _f(np.hypot(*e_r[k_end, :2])),
            "vel_err_end_mps": _f(np.linalg.norm(e_v[k_end])),
            "end_t_s": float(t[k_end]),
            "updates": updates,
        },
        "vision": {
            "frames": int(frames["t_ns"].size),
            "frames_tracked": int(tracked.size),
            "tracks_per_frame_mean": _f(counts.mean()) if counts.size else None,
            "tracks_per_frame_median": _f(np.median(counts)) if counts.size else None,
            "tracker_ms_per_frame_mean": _f(tracked.mean()) if tracked.size else None,
            "tracker_ms_per_frame_median": _f(np.median(tracked)) if tracked.size else None,
            "vision_ms_per_frame_mean": _f(frames["vision_ms"].mean()) if frames["vision_ms"].size else None,
            "measurements": fsw.vision.measurements,
            "rejected": fsw.vision.rejected,
            "unusable_pairs": fsw.vision.unusable,
            **_epe_metrics(epe),
        },
        "replay_wall_s": wall_s,
        "replay_realtime_factor": sim_s / wall_s if wall_s > 0 else None,
        "identical_to_recording": not differing,
        "differing_nav_columns": differing,
    }


def _scalars(d: dict[str, Any], prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_scalars(v, f"{prefix}{k}."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and k != "seed":
            out[prefix + k] = float(v)
    return out


def dataset_metrics(seqs: list[SequenceReplay]) -> dict[str, Any]:
    """Over the dataset: the mean of every per-sequence figure (sequences where it is defined) and the sums of counts."""
    flat = [_scalars({"navigation": s.metrics["navigation"], "vision": s.metrics["vision"]}) for s in seqs]
    keys = sorted({k for f in flat for k in f})
    mean = {k: float(np.mean([f[k] for f in flat if k in f])) for k in keys}
    sums = {k: float(sum(f.get(k, 0.0) for f in flat)) for k in keys
            if k.rsplit(".", 1)[-1] in ("updates", "accepted", "gate_rejections", "other_rejections", "frames",
                                       "frames_tracked", "measurements", "rejected", "unusable_pairs",
                                       "epe_count")}
    pooled = None
    if seqs and all(s.epe is not None for s in seqs):
        pooled = _epe_metrics(np.concatenate([s.epe for s in seqs]))
    return {"sequences": len(seqs), "mean": mean, "sum": sums,
            "epe_pooled": pooled,  # over every track of every sequence; None unless every recording has depth
            "identical_to_recording": all(s.metrics["identical_to_recording"] for s in seqs),
            "replay_wall_s": float(sum(s.metrics["replay_wall_s"] for s in seqs))}


def prepare_replay(dataset: Path, overrides: list[str] | tuple[str, ...]) -> list[tuple[Path, Scenario, dict]]:
    """Check everything before anything runs: the overrides, every recording's manifest and checksums, the scenarios.

    Returns per recording: its folder, its scenario with the overrides, and its verified manifest.
    """
    check_overrides(overrides)
    paths = find_recordings(dataset)
    out = []
    seen: dict[int, Path] = {}
    for p in paths:
        manifest = verify_recording(p)
        try:
            scenario = recorded_scenario(manifest["scenario_toml"], overrides)
        except ScenarioError as exc:
            raise ScenarioError(f"recording {str(p)!r}: {exc}") from None
        if scenario.seed != manifest["seed"]:
            raise ValueError(f"recording {str(p)!r}: its {MANIFEST} says seed {manifest['seed']}, its scenario "
                             f"seed {scenario.seed}; re-record it")
        if scenario.seed in seen:  # a copied folder: its frames would pair with themselves, its figures count twice
            raise ValueError(f"dataset {str(dataset)!r}: {seen[scenario.seed].name} and {p.name} hold the same seed "
                             f"{scenario.seed}; a dataset holds each seed once")
        seen[scenario.seed] = p
        out.append((p, scenario, manifest))
    return out


def replay_dataset(dataset: Path, overrides: list[str] | tuple[str, ...] = ()) -> tuple[list[SequenceReplay], dict]:
    """Replay every recording of ``dataset`` with ``overrides``; returns (per sequence, the metrics document)."""
    prepared = prepare_replay(dataset, overrides)
    seqs = [replay_recording(open_recording(p, manifest), scenario) for p, scenario, manifest in prepared]
    doc = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "dataset": str(dataset),
        "seeds": [s.seed for s in seqs],
        "overrides": list(overrides),
        "sequences": [s.metrics for s in seqs],
        "dataset_metrics": dataset_metrics(seqs),
    }
    return seqs, json_safe(doc)


def write_replay(seqs: list[SequenceReplay], doc: dict[str, Any], out: Path) -> dict[str, Path]:
    """Write ``metrics.json``, ``frames.parquet`` and ``nav.parquet`` into ``out`` (each atomically)."""
    from bench.report.report import write_telemetry_parquet

    def joined(part: str) -> dict[str, np.ndarray]:
        names = ["seed", "t_s"]
        for s in seqs:
            names += [k for k in getattr(s, part) if k not in names]
        cols: dict[str, list[np.ndarray]] = {k: [] for k in names}
        for s in seqs:
            table = getattr(s, part)
            t_ns = table["t_ns"]
            extra = {"seed": np.full(t_ns.size, s.seed, np.int64), "t_s": t_ns / NS_PER_S}
            for k in names:  # a column only some sequences have (epe_*: recorded with depth) is NaN in the others
                cols[k].append(extra[k] if k in extra else table.get(k, np.full(t_ns.size, math.nan)))
        return {k: np.concatenate(v) for k, v in cols.items()}

    written = {"metrics": out / METRICS}
    frames = joined("frames")
    if frames["t_s"].size:
        written["frames"] = write_telemetry_parquet(frames, out / FRAMES)
    else:  # no frame replayed: an older replay's frames.parquet in this folder would be read as this one's
        (out / FRAMES).unlink(missing_ok=True)
    written["nav"] = write_telemetry_parquet(joined("nav"), out / NAV)
    atomic_write_text(out / METRICS, json.dumps(doc, indent=2) + "\n")
    return written


def format_replay(doc: dict[str, Any]) -> str:
    """A short terminal table of a replay."""
    lines = [f"{'seed':>6} {'vel rms':>9} {'v_h@cut':>9} {'pos end':>9} {'trk/frm':>8} {'ms/frm':>7} "
             f"{'vis rej':>8} {'identical':>9}"]

    def fmt(x: Any, spec: str = "9.3f") -> str:
        return format(x, spec) if isinstance(x, (int, float)) else format("-", ">" + spec.split(".")[0])

    for m in doc["sequences"]:
        n, v = m["navigation"], m["vision"]
        lines.append(f"{m['seed']:>6} {fmt(n['vel_err_rms_mps'])} {fmt(n['vel_err_horizontal_at_cutoff_mps'])} "
                     f"{fmt(n['pos_err_end_m'])} {fmt(v['tracks_per_frame_mean'], '8.1f')} "
                     f"{fmt(v['tracker_ms_per_frame_mean'], '7.2f')} "
                     f"{n['updates'][KIND_VISION]['gate_rejections']:>8} {str(m['identical_to_recording']):>9}")
    return "\n".join(lines)
