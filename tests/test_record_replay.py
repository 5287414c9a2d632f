"""Recorded descents and open-loop replay (``landbench record`` / ``landbench replay``).

One short descent (150 m, 6 s, camera + tracker + filter in the loop) is
recorded once per module; every test replays or inspects that recording.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.cli import main
from bench.evaluation import record as rec_mod
from bench.evaluation.record import MANIFEST, open_recording, parse_seeds
from bench.evaluation.replay import NAV_COLUMNS, replay_dataset
from bench.report.io import json_safe
from bench.report.report import read_telemetry_parquet
from bench.scenario import load_scenario
from bench.sim.run import run

SEGMENT = ["initial.r_BL_L_m=[20.0,-10.0,150.0]", "initial.v_BL_L_mps=[1.0,-1.0,-6.0]", "sim.t_max_ns=6_000_000_000"]
SEED = 1
WALL_CLOCK_KEYS = ("wall_time_s", "setup_time_s", "realtime_factor", "time_split_s")


def _sets(assignments: list[str]) -> list[str]:
    return [a for s in assignments for a in ("--set", s)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    ds = tmp_path_factory.mktemp("rr") / "ds"
    # --depth: the second (depth) render must not disturb the run either.
    assert main(["record", *_sets(SEGMENT), "--seeds", str(SEED), "--out", str(ds), "--depth"]) == 0
    return ds


@pytest.fixture(scope="module")
def seq(dataset) -> Path:
    return dataset / f"seed_{SEED:03d}"


def _copy(seq: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds" / seq.name
    shutil.copytree(seq, dst)
    return dst


def _assert_refused(capsys, argv: list[str], out: Path, needle: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("landbench: error:") and "\n" not in err, err
    assert needle in err, err
    assert not out.exists()


# --------------------------------------------------------------------------- recording
def test_parse_seeds():
    assert parse_seeds("1-3") == [1, 2, 3]
    assert parse_seeds("1,4,7") == [1, 4, 7]
    assert parse_seeds("0-1,5") == [0, 1, 5]
    for bad in ("", "a", "3-1", "1,1", "-2", "1-2-3"):
        with pytest.raises(ValueError, match="--seeds"):
            parse_seeds(bad)


def test_recording_does_not_change_the_run(seq):
    # The same descent without a recorder: telemetry and summary identical to the recorded ones, bit for bit.
    plain = run(load_scenario(None, [*SEGMENT, f"seed={SEED}"]))
    recorded = read_telemetry_parquet(seq / "telemetry.parquet")
    assert plain.telemetry.keys() == recorded.keys()
    for k, col in plain.telemetry.items():
        assert col.dtype == recorded[k].dtype and col.tobytes() == recorded[k].tobytes(), k
    summary = json.loads(json.dumps(json_safe(plain.summary)))
    rec_summary = json.loads((seq / "summary.json").read_text())
    for k in WALL_CLOCK_KEYS:
        summary.pop(k), rec_summary.pop(k)
    assert summary == rec_summary


def test_dataset_layout(seq):
    manifest = json.loads((seq / MANIFEST).read_text())
    assert manifest["format"] == "landbench-recording" and manifest["format_version"] == 1
    assert manifest["seed"] == SEED and "[initial]" in manifest["scenario_toml"]
    assert set(manifest["packages"]) >= {"numpy", "mujoco", "opencv", "filterpy"}
    assert set(manifest["files"]) == set(rec_mod.REQUIRED_FILES)
    for name, entry in manifest["files"].items():
        assert rec_mod.sha256_file(seq / name) == entry["sha256"]
    r = open_recording(seq)
    kinds = pq.read_table(seq / "messages.parquet").column("kind").to_pylist()
    counts = {k: kinds.count(k) for k in rec_mod.KINDS}
    assert counts == {k: manifest["counts"][k] for k in rec_mod.KINDS}
    assert counts["image"] == 61 and counts["control"] == 301  # 10 Hz camera, 50 Hz control over 6 s
    assert r.frames.dtype == np.uint8 and r.frames.shape == (61, 256, 256)
    assert r.camera["R_LC"].shape == (61, 3, 3) and r.camera["depth"].shape == (61, 256, 256)
    assert np.all(np.diff(r.events[1]) >= 0)  # the events are in time order
    assert r.truth["t_ns"].tolist() == r.sensors["control_t_ns"].tolist()
    np.testing.assert_array_equal(r.truth["r_z_m"], r.telemetry["r_z_m"])


def test_record_refuses_truth_tracks_and_bad_seeds(tmp_path, capsys):
    out = tmp_path / "ds"
    _assert_refused(capsys, ["record", "--set", "tracks=truth", "--seeds", "1", "--out", str(out)], out, "truth")
    _assert_refused(capsys, ["record", "--seeds", "3-1", "--out", str(out)], out, "--seeds")


    reset = 'faults=[{kind="computer_reset", t_s=2.0, down_s=1.0}]'
    _assert_refused(capsys, ["record", *_sets([*SEGMENT, reset]), "--seeds", "1", "--out", str(out)], out,
                    "faults[0] is a computer_reset, which an open-loop replay cannot reproduce")


def test_a_replay_reproduces_the_fault_detection_acting_on_navigation(tmp_path):
    # The gyro lost for 1 s: the flight software dead-reckons on a synthetic IMU from the thrust command at its
    # control ticks. Before the replay ran the monitoring, 31 nav columns split from the recording at 2.04 s.
    ds, out = tmp_path / "ds", tmp_path / "replay"
    drop = 'faults=[{kind="dropout", target="imu.gyro", t_s=2.0, duration_s=1.0}]'
    assert main(["record", *_sets([*SEGMENT, drop, 'vision="off"', "camera.enabled=false"]), "--seeds", "1",
                 "--out", str(ds)]) == 0
    summary = json.loads((ds / "seed_001" / "summary.json").read_text())
    assert any("IMU" in e["reason"] for e in summary["fdir_events"]), summary["fdir_events"]
    assert main(["replay", str(ds), "--out", str(out)]) == 0
    (m,) = json.loads((out / "metrics.json").read_text())["sequences"]
    assert m["identical_to_recording"], m.get("differing_nav_columns")


def test_a_stuck_throttle_replays_the_flight_softwares_own_commands(tmp_path):
    # The telemetry's thrust_cmd_N was the stuck engine's command, not the computer's: the replay's mass gauge
    # (fed thrust_cmd_N) drifted from the one that flew, and the replay was not identical.
    ds, out = tmp_path / "ds", tmp_path / "replay"
    stuck = 'faults=[{kind="stuck_throttle", target="engine", t_s=2.0}]'
    assert main(["record", *_sets([*SEGMENT, stuck, 'vision="off"', "camera.enabled=false"]), "--seeds", "1",
                 "--out", str(ds)]) == 0
    assert main(["replay", str(ds), "--out", str(out)]) == 0
    (m,) = json.loads((out / "metrics.json").read_text())["sequences"]
    assert m["identical_to_recording"], m.get("differing_nav_columns")
    tel = read_telemetry_parquet(ds / "seed_001" / "telemetry.parquet")
    after = tel["t_s"] > 3.0  # the engine held its command; the computer's went on changing
    assert np.ptp(tel["thrust_cmd_N"][after]) > 1.0 and np.ptp(tel["thrust_applied_cmd_N"][after]) < 1e-9


def test_a_replay_with_map_fixes_scores_in_the_maps_frame(tmp_path):
    # With nav_map on the flight software navigates in the map's frame (truth + the map's shift); the replay
    # took its errors against the plain truth: nav_err_r_x/y and nees_r_h differed by the shift (2.7, -1.8) m.
    ds, out = tmp_path / "ds", tmp_path / "replay"
    assert main(["record", *_sets([*SEGMENT, 'nav_map="on"']),
                 "--seeds", "1", "--out", str(ds)]) == 0
    assert main(["replay", str(ds), "--out", str(out)]) == 0
    (m,) = json.loads((out / "metrics.json").read_text())["sequences"]
    assert m["identical_to_recording"], m.get("differing_nav_columns")
    closed = json.loads((ds / "seed_001" / "summary.json").read_text())
    assert m["navigation"]["pos_err_end_m"] < 2.0, (m["navigation"], closed["nav"])


# --------------------------------------------------------------------------- replay
def test_replay_reproduces_the_recorded_estimates_bit_for_bit(dataset, tmp_path):
    out = tmp_path / "replay"
    assert main(["replay", str(dataset), "--out", str(out)]) == 0
    recorded = read_telemetry_parquet(dataset / f"seed_{SEED:03d}" / "telemetry.parquet")
    nav = read_telemetry_parquet(out / "nav.parquet")
    assert nav["t_s"].tobytes() == recorded["t_s"].tobytes()
    for k in NAV_COLUMNS:
        assert nav[k].dtype == recorded[k].dtype and nav[k].tobytes() == recorded[k].tobytes(), k
    metrics = json.loads((out / "metrics.json").read_text())
    (m,) = metrics["sequences"]
    assert m["identical_to_recording"] and metrics["dataset_metrics"]["identical_to_recording"]
    assert m["navigation"]["updates"]["vision"]["accepted"] >= 50  # vision was in the replayed loop
    assert m["vision"]["tracks_per_frame_mean"] > 20
    frames = read_telemetry_parquet(out / "frames.parquet")
    assert frames["t_s"].size == 61 and frames["measurement"].sum() == m["vision"]["measurements"]


def test_a_changed_estimator_setting_changes_the_replayed_estimates(dataset):
    seqs, doc = replay_dataset(dataset, ["estimator.accel_noise_density=0.01"])
    (m,) = doc["sequences"]
    assert not m["identical_to_recording"]
    assert {"nav_v_x_mps", "nav_r_x_m", "nav_sigma_v_x_mps"} <= set(m["differing_nav_columns"])
    recorded = open_recording(dataset / f"seed_{SEED:03d}").telemetry
    assert not np.array_equal(seqs[0].nav["nav_sigma_v_x_mps"], recorded["nav_sigma_v_x_mps"])


def test_a_changed_tracker_setting_changes_the_tracks(dataset):
    _, base = replay_dataset(dataset)
    _, fewer = replay_dataset(dataset, ["tracker.n_templates=2"])
    n_base = base["sequences"][0]["vision"]["tracks_per_frame_mean"]
    assert fewer["sequences"][0]["vision"]["tracks_per_frame_mean"] < n_base
    assert not fewer["sequences"][0]["identical_to_recording"]


def test_a_tampered_file_is_refused(seq, tmp_path, capsys):
    copy = _copy(seq, tmp_path)
    data = bytearray((copy / "sensors.npz").read_bytes())
    data[len(data) // 2] ^= 0x01
    (copy / "sensors.npz").write_bytes(bytes(data))
    out = tmp_path / "replay"
    _assert_refused(capsys, ["replay", str(copy.parent), "--out", str(out)], out, "sensors.npz does not match")


def test_a_damaged_dataset_layout_is_refused(seq, tmp_path, capsys):
    copy = _copy(seq, tmp_path)  # tmp_path/ds/seed_001
    out = tmp_path / "replay"
    shutil.copytree(copy, copy.parent / "seed_009")  # a copied seed: its figures would count twice
    _assert_refused(capsys, ["replay", str(copy.parent), "--out", str(out)], out,
                    "seed_001 and seed_009 hold the same seed 1")
    (copy.parent / "seed_009" / MANIFEST).unlink()  # a recording without its manifest dropped out unnoticed
    _assert_refused(capsys, ["replay", str(copy.parent), "--out", str(out)], out, "seed_009 has no manifest.json")
    shutil.rmtree(copy.parent / "seed_009")
    manifest = json.loads((copy / MANIFEST).read_text())
    del manifest["seed"]  # was a KeyError traceback
    (copy / MANIFEST).write_text(json.dumps(manifest))
    _assert_refused(capsys, ["replay", str(copy.parent), "--out", str(out)], out, "has no seed")


def test_outputs_that_would_land_on_other_results_are_refused(dataset, seq, tmp_path, capsys):
    _assert_refused(capsys, ["replay", str(dataset), "--out", str(dataset / "r")], dataset / "r",
                    "inside the dataset being replayed")
    # record into a recording (or any other command's results) is refused, and so is a seed it would replace
    before = sorted(p.name for p in seq.iterdir())
    assert main(["record", "--seeds", "1", "--out", str(seq)]) == 2
    assert "holds a run's results" in capsys.readouterr().err and sorted(p.name for p in seq.iterdir()) == before
    _assert_refused(capsys, ["record", "--set", "seed=7", "--seeds", "1", "--out", str(tmp_path / "d")],
                    tmp_path / "d", "give --seeds instead")


def test_an_unknown_format_version_is_refused(seq, tmp_path, capsys):
    copy = _copy(seq, tmp_path)
    manifest = json.loads((copy / MANIFEST).read_text())
    manifest["format_version"] = 99
    (copy / MANIFEST).write_text(json.dumps(manifest))
    out = tmp_path / "replay"
    _assert_refused(capsys, ["replay", str(copy), "--out", str(out)], out, "format version 99 is unknown")


@pytest.mark.parametrize("assignment", ["sensors.imu.accel_noise_density=0.01", "seed=2", "camera.width_px=128",
                                        "guidance.law=\"zem\""])
def test_a_forbidden_override_is_refused(dataset, tmp_path, capsys, assignment):
    out = tmp_path / "replay"
    _assert_refused(capsys, ["replay", str(dataset), "--set", assignment, "--out", str(out)], out,
                    "may change only the flight software's tracker, vision_nav, estimator")


def test_a_bad_override_value_is_refused(dataset, tmp_path, capsys):
    out = tmp_path / "replay"
    _assert_refused(capsys, ["replay", str(dataset), "--set", "estimator.gate_prob=2.0", "--out", str(out)], out,
                    "gate_prob")


def test_replay_builds_no_model_and_renders_nothing(dataset, monkeypatch):
    import mujoco

    def forbidden(*_a, **_k):
        raise AssertionError("the replay touched MuJoCo")

    for name in ("MjModel", "MjData", "Renderer", "mj_step", "mj_forward"):
        monkeypatch.setattr(mujoco, name, forbidden)
    _, doc = replay_dataset(dataset)
    assert doc["dataset_metrics"]["identical_to_recording"]


def test_replay_imports_no_mujoco_and_no_renderer(dataset):
    # In a fresh process: the replay path (scenario schema included) never imports MuJoCo or the world.
    import subprocess
    import sys

    code = ("import sys; from pathlib import Path; from bench.evaluation.replay import replay_dataset; "
            f"_, doc = replay_dataset(Path({str(dataset)!r})); "
            "assert doc['dataset_metrics']['identical_to_recording']; "
            "print(sorted(m for m in ('mujoco', 'models.world', 'models.gl', 'bench.sim.run') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "[]"


# --------------------------------------------------------------------------- tracker endpoint error
@pytest.fixture(scope="module")
def replayed(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rr_replay") / "base"
    assert main(["replay", str(dataset), "--out", str(out)]) == 0
    return out


def test_replayed_endpoint_error_equals_tracking_eval_on_the_recorded_frames(dataset, replayed):
    from bench.evaluation.record import recorded_scenario
    from bench.evaluation.tracking_eval import track_metrics
    from vision import Tracker

    r = open_recording(dataset / f"seed_{SEED:03d}")
    frames = read_telemetry_parquet(replayed / "frames.parquet")
    (m,) = json.loads((replayed / "metrics.json").read_text())["sequences"]
    v = m["vision"]
    assert v["truth_depth"] and v["epe_count"] > 1000 and v["frames_tracked"] == frames["t_s"].size  # all tracked
    # Independently: the recorded scenario's tracker on the recorded frames, scored by tracking_eval.
    tracker = Tracker(recorded_scenario(r.scenario_toml).tracker)
    tracks = [tracker.step(img) for img in r.frames]
    poses = list(zip(r.camera["R_LC"], r.camera["r_CL_L"]))
    depths = list(r.camera["depth"])
    k = 30
    pair = track_metrics(tracks[k - 1:k + 1], depths[k - 1:k + 1], r.K, poses[k - 1:k + 1])
    assert pair["n_errors"] == frames["epe_count"][k] > 0
    assert frames["epe_median_px"][k] == pytest.approx(pair["epe_median_px"], rel=1e-12)
    assert frames["epe_count"][0] == 0 and np.isnan(frames["epe_median_px"][0])  # no previous frame
    whole = track_metrics(tracks, depths, r.K, poses)
    for key in ("epe_median_px", "epe_p95_px", "within_1px_frac"):
        assert v[key] == pytest.approx(whole[key], rel=1e-12), key
    assert v["epe_count"] == whole["n_errors"] == frames["epe_count"].sum()


@pytest.fixture(scope="module")
def worse_tracker(dataset) -> dict:
    """The replay document with a 3 px LK window: about twice the median endpoint error here."""
    return replay_dataset(dataset, ["tracker.lk_window=3"])[1]


def test_a_worse_tracker_has_a_larger_endpoint_error(worse_tracker, replayed):
    worse = worse_tracker
    base = json.loads((replayed / "metrics.json").read_text())
    assert worse["sequences"][0]["vision"]["epe_median_px"] > 1.5 * base["sequences"][0]["vision"]["epe_median_px"]
    assert worse["dataset_metrics"]["epe_pooled"]["epe_median_px"] > base["dataset_metrics"]["epe_pooled"][
        "epe_median_px"]


def test_without_depth_the_endpoint_error_is_null(seq, tmp_path):
    copy = _copy(seq, tmp_path)
    with np.load(copy / rec_mod.CAMERA_TRUTH) as z:
        cam = {k: z[k] for k in z.files if k != "depth"}
    np.savez(copy / rec_mod.CAMERA_TRUTH, **cam)
    manifest = json.loads((copy / MANIFEST).read_text())
    manifest["files"][rec_mod.CAMERA_TRUTH]["sha256"] = rec_mod.sha256_file(copy / rec_mod.CAMERA_TRUTH)
    (copy / MANIFEST).write_text(json.dumps(manifest))
    out = tmp_path / "replay"
    assert main(["replay", str(copy.parent), "--out", str(out)]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    v = doc["sequences"][0]["vision"]
    assert v["truth_depth"] is False and all(v[k] is None for k in ("epe_median_px", "epe_p95_px", "within_1px_frac"))
    assert doc["dataset_metrics"]["epe_pooled"] is None
    assert "epe_median_px" not in read_telemetry_parquet(out / "frames.parquet")


# --------------------------------------------------------------------------- landbench compare on replays
def _last_line(capsys) -> str:
    return capsys.readouterr().out.strip().splitlines()[-1]


def test_the_same_replay_twice_compares_identical(dataset, replayed, tmp_path, capsys):
    again = tmp_path / "again"
    assert main(["replay", str(dataset), "--out", str(again)]) == 0
    capsys.readouterr()
    out = tmp_path / "cmp"
    assert main(["compare", str(replayed), str(again), "--gate", "epe_median_px:+0", "--out", str(out)]) == 0
    assert _last_line(capsys) == "all 1 gates passed"
    doc = json.loads((out / "compare.json").read_text())
    assert doc["kind"] == "replay" and doc["success"] is None and doc["flipped"] == [] and doc["n_cases"] == 1
    assert {"epe_median_px", "vel_err_rms_mps", "vision_gate_rejections", "tracks_per_frame_mean"} <= set(doc["metrics"])
    assert not {"tracker_ms_per_frame_mean", "replay_wall_s"} & set(doc["metrics"])  # wall-clock: not compared
    assert all(m["identical"] for m in doc["metrics"].values())
    fr = doc["frames"]
    assert fr["n_frames"] == 61 and {"epe_median_px", "tracks", "nis"} <= set(fr["metrics"])
    assert all(m["identical"] for m in fr["metrics"].values())
    assert fr["paired_on"] == ["seed", "frame"] and {"accepted", "rejected", "measurement"} <= set(fr["booleans"])
    assert all(b["identical"] and b["flipped"] == 0 for b in fr["booleans"].values())
    assert (out / "report.html").is_file()


def test_a_worse_tracker_replay_fails_an_epe_gate(dataset, replayed, tmp_path, capsys):
    worse = tmp_path / "worse"
    assert main(["replay", str(dataset), "--set", "tracker.lk_window=3", "--out", str(worse)]) == 0
    capsys.readouterr()
    out = tmp_path / "cmp"
    assert main(["compare", str(replayed), str(worse), "--gate", "epe_median_px:+10%", "--out", str(out)]) == 1
    last = _last_line(capsys)
    assert last.startswith("FAILED gates:") and "epe_median_px:+10%" in last
    doc = json.loads((out / "compare.json").read_text())
    assert doc["metrics"]["epe_median_px"]["diff"]["mean"] > 0 and not doc["frames"]["metrics"]["tracks"]["identical"]


def test_compare_refuses_a_replay_against_a_campaign_or_other_recordings(dataset, replayed, seq, tmp_path, capsys):
    from tests.test_compare import write_campaign

    campaign = write_campaign(tmp_path / "camp", [{"case": 0, "seed": SEED, "outcome": "landed",
                                                   "touchdown_miss_distance_m": 1.0}])
    out = tmp_path / "cmp"
    _assert_refused(capsys, ["compare", str(replayed), str(campaign), "--out", str(out)], out,
                    "is a replay folder, CAND")
    # The same seed, but a different recording (tampered copy, re-signed): refused, the sequence named.
    other = _copy(seq, tmp_path)
    (other / "summary.json").write_text((other / "summary.json").read_text() + " ")
    manifest = json.loads((other / MANIFEST).read_text())
    manifest["files"]["summary.json"]["sha256"] = rec_mod.sha256_file(other / "summary.json")
    (other / MANIFEST).write_text(json.dumps(manifest))
    cand = tmp_path / "other"
    assert main(["replay", str(other.parent), "--out", str(cand)]) == 0
    capsys.readouterr()
    _assert_refused(capsys, ["compare", str(replayed), str(cand), "--out", str(out)], out,
                    "sequence 0 (seed 1)")
    _assert_refused(capsys, ["compare", str(replayed), str(replayed), "--gate", "success_rate:-2pp", "--out",
                             str(out)], out, "no success rate")


# --------------------------------------------------------------------------- the pytest tier: metric snapshots
SNAPSHOT = Path(__file__).with_name("snapshots") / "replay_segment.json"
TOLERANCES = Path(__file__).with_name("snapshots") / "replay_segment.tolerances.json"
REGEN = "make snapshots (pytest tests/test_record_replay.py -k snapshot --regen-snapshots)"


def snapshot_metrics(doc: dict) -> dict:
    """The replayed segment's per-sequence metrics under their leaf names, as compare reads them (NaN -> None)."""
    from bench.evaluation.compare import replay_row

    (seq,) = doc["sequences"]
    return json_safe({k: v for k, v in replay_row(seq).items()})


def snapshot_violations(values: dict, snapshot: dict, tolerances: dict) -> list[str]:
    """One line per metric outside its tolerance (|new - old| > abs + rel |old|), missing, new, or null on one side."""
    out = []
    for key in sorted(values.keys() | snapshot.keys()):
        if key not in snapshot:
            out.append(f"{key}: new metric ({values[key]!r}), not in the snapshot")
            continue
        if key not in values:
            out.append(f"{key}: in the snapshot ({snapshot[key]!r}), no longer reported")
            continue
        new, old = values[key], snapshot[key]
        if new is None or old is None:
            if new is not old:
                out.append(f"{key}: {new!r}, snapshot {old!r}")
            continue
        tol = tolerances["metrics"].get(key, tolerances["default"])
        allowed = tol["abs"] + tol["rel"] * abs(old)
        if abs(new - old) > allowed:
            out.append(f"{key}: {new:.6g}, snapshot {old:.6g}: moved {new - old:+.3g}, allowed +-{allowed:.3g}")
    return out


def test_snapshot_violations_apply_the_tolerances():
    tol = {"default": {"abs": 0.0, "rel": 0.0}, "metrics": {"a": {"abs": 0.1, "rel": 0.1}}}
    assert snapshot_violations({"a": 2.29, "b": 3, "c": None}, {"a": 2.0, "b": 3, "c": None}, tol) == []
    bad = snapshot_violations({"a": 2.31, "b": 4, "c": 1.0, "d": 0.0}, {"a": 2.0, "b": 3, "c": None, "e": 1}, tol)
    assert [line.split(":")[0] for line in bad] == ["a", "b", "c", "d", "e"]


def test_replay_metrics_stay_within_their_snapshot_tolerances(replayed, request):
    values = snapshot_metrics(json.loads((replayed / "metrics.json").read_text()))
    if request.config.getoption("--regen-snapshots"):
        doc = {"about": f"Replay metrics of the 150 m test segment (tests/test_record_replay.py, seed {SEED}, "
                        f"recorded with --depth, replayed with its own settings). Regenerate: {REGEN}; the "
                        f"tolerances are in {TOLERANCES.name}.",
               "recording": {"overrides": SEGMENT, "seed": SEED, "depth": True}, "metrics": values}
        SNAPSHOT.write_text(json.dumps(doc, indent=1, sort_keys=False) + "\n")
        pytest.skip(f"snapshot regenerated: {SNAPSHOT}")
    snap = json.loads(SNAPSHOT.read_text())
    assert snap["recording"] == {"overrides": SEGMENT, "seed": SEED, "depth": True}, \
        f"the snapshot was taken of another recording; regenerate it: {REGEN}"
    bad = snapshot_violations(values, snap["metrics"], json.loads(TOLERANCES.read_text()))
    assert not bad, ("replay metrics moved outside their tolerances (" + TOLERANCES.name + "):\n  "
                     + "\n  ".join(bad) + f"\nIf the change is intended, regenerate: {REGEN}")


def test_a_worse_tracker_breaks_the_snapshot(worse_tracker):
    snap = json.loads(SNAPSHOT.read_text())
    bad = snapshot_violations(snapshot_metrics(worse_tracker), snap["metrics"], json.loads(TOLERANCES.read_text()))
    assert any(line.startswith("epe_median_px:") for line in bad), bad


def test_a_replay_without_frames_leaves_no_older_frames_file(tmp_path):
    # An earlier replay's frames.parquet (of other seeds) stayed beside the new metrics and compare read it.
    from bench.evaluation.replay import FRAMES, SequenceReplay, write_replay

    (tmp_path / FRAMES).write_bytes(b"an older replay's frames")
    seq = SequenceReplay(seed=1, path=tmp_path, metrics={}, frames={"t_ns": np.zeros(0, np.int64)},
                         nav={"t_ns": np.array([0, 20_000_000], np.int64), "nav_r_x_m": np.zeros(2)}, epe=None)
    written = write_replay([seq], {"sequences": []}, tmp_path)
    assert "frames" not in written and not (tmp_path / FRAMES).exists() and (tmp_path / "nav.parquet").is_file()
