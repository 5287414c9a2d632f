"""Faults (issue 13): the scenario's [[faults]], the truth-side injector against the unfaulted signals,
the presets, and short closed-loop runs that check what reaches the flight software."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.scenario import ScenarioError, apply_dispersions, load_scenario, scenario_to_toml
from bench.scenario.presets import PRESETS, REFERENCE, apply_preset, get_preset
from bench.scenario.schema import scenario_from_dict
from bench.sim.world_builder import build_fault_injector, with_terrain_steps
from models.faults import terrain_step_heights
from models.sensors import AltimeterConfig, AltimeterModel, ImuConfig, ImuModel, StarTrackerConfig, StarTrackerModel
from tests.conftest import SMALL_SET, make_terrain

NS = 1_000_000_000


def _scenario(*faults: str, extra: tuple[str, ...] = ()):
    return load_scenario(None, [f"faults=[{', '.join(faults)}]", *extra])


def _injector(*faults: str):
    return build_fault_injector(_scenario(*faults))


# --------------------------------------------------------------------------- the scenario
def test_faults_parse_round_trip_and_disperse():
    sc = _scenario('{kind="bias_step", target="altimeter", value=5.0, t_s=10.0, duration_s=3.0}',
                   '{kind="frame_drop", probability=0.5}',
                   extra=('dispersions."faults.0.value"={dist="uniform", low=1.0, high=9.0, own_stream=true}',))
    assert [f.kind for f in sc.faults] == ["bias_step", "frame_drop"]
    import tomllib

    assert scenario_from_dict(tomllib.loads(scenario_to_toml(sc))) == sc
    case, drawn = apply_dispersions(sc)
    assert 1.0 <= drawn["faults.0.value"] <= 9.0 and case.faults[0].value == drawn["faults.0.value"]
    # own_stream: the other paths draw exactly as without the fault dispersion.
    _, plain = apply_dispersions(sc.model_copy(update={"dispersions": {
        k: v for k, v in sc.dispersions.items() if k != "faults.0.value"}}))
    assert {k: v for k, v in drawn.items() if k != "faults.0.value"} == plain


@pytest.mark.parametrize("fault, words", [
    ('{kind="bias_step", target="altimeter", value=1.0, t_s=1.0, altitude_m=50.0}', "at most one of"),
    ('{kind="scale", target="star_tracker", factor=2.0}', "star_tracker"),
    ('{kind="noise", target="altimeter", factor=0.5}', "factor"),
    ('{kind="bias_step", target="altimeter", value=nan}', "value"),
    ('{kind="terrain_step", height_m=10.0, center_xy_m=[30.0, 0.0], radius_m=20.0}', "target"),
    ('{kind="terrain_step", height_m=10.0, center_xy_m=[-300.0, 0.0], radius_m=20.0, t_s=3.0}', "no trigger"),
    ('{kind="nope"}', "kind"),
    ('{kind="dropout", target="altimeter", axes=[0, 0]}', "axes"),
    ('{kind="rcs_stuck_on", axis=3}', "axis"),
    ('{kind="rcs_loss", direction="up"}', "direction"),
    ('{kind="rcs_loss", axes=[1, 1]}', "axes"),
])
def test_bad_faults_get_one_line(fault, words):
    with pytest.raises(ScenarioError) as err:
        _scenario(fault)
    msg = str(err.value)
    assert "\n" not in msg and "faults" in msg and words in msg


# --------------------------------------------------------------------------- sensors against truth
def _alt_stream(inj, ranges, dt_ns=50_000_000, seed=3):
    """Raw altimeter messages and what the injector delivers, one per sample time."""
    model = AltimeterModel(AltimeterConfig(dropout_prob=0.0), np.random.default_rng(seed))
    raw, out = [], []
    for k, r in enumerate(ranges):
        t = k * dt_ns
        inj.update(t)
        m = model.sample(t, r)
        raw.append(m)
        out.append(inj.altimeter(m))
    return raw, out


def test_altimeter_bias_step_is_the_bias_after_the_trigger_and_not_before():
    inj = _injector('{kind="bias_step", target="altimeter", value=7.5, t_s=1.0, duration_s=2.0}')
    raw, out = _alt_stream(inj, np.linspace(400.0, 300.0, 80))
    t = np.array([m.t_ns for m in raw]) / NS
    d = np.array([o.range_m - m.range_m for m, o in zip(raw, out)])
    inside = (t >= 1.0) & (t < 3.0)
    assert np.all(d[inside] == pytest.approx(7.5, abs=1e-9)) and np.all(d[~inside] == 0.0)


def test_altimeter_ramp_scale_saturation_and_flag():
    ranges = np.full(60, 200.0)
    for fault, expect in [
        ('{kind="bias_ramp", target="altimeter", rate_per_s=2.0, t_s=0.5}', lambda r, t: r + 2.0 * max(t - 0.5, 0.0)),
        ('{kind="scale", target="altimeter", factor=1.1, t_s=0.5}', lambda r, t: r * 1.1 if t >= 0.5 else r),
        ('{kind="saturation", target="altimeter", limit=150.0, t_s=0.5}', lambda r, t: min(r, 150.0) if t >= 0.5 else r),
    ]:
        raw, out = _alt_stream(_injector(fault), ranges)
        for m, o in zip(raw, out):
            assert o.range_m == pytest.approx(expect(m.range_m, m.t_ns / NS), abs=1e-9), fault
    raw, out = _alt_stream(_injector('{kind="flagged_invalid", target="altimeter", t_s=1.0}'), ranges)
    for m, o in zip(raw, out):
        assert o.range_m == m.range_m and o.valid == (m.t_ns < NS)


def test_altimeter_dropout_and_stuck_windows():
    raw, out = _alt_stream(_injector('{kind="dropout", target="altimeter", t_s=1.0, duration_s=1.0}'),
                           np.linspace(300, 250, 60))
    t = np.array([m.t_ns for m in raw]) / NS
    gone = np.array([o is None for o in out])
    assert np.array_equal(gone, (t >= 1.0) & (t < 2.0))
    raw, out = _alt_stream(_injector('{kind="stuck", target="altimeter", t_s=1.0, duration_s=1.0}'),
                           np.linspace(300, 250, 60))
    k1 = int(np.argmax(t >= 1.0))
    held = raw[k1 - 1].range_m  # the last message before the trigger
    for k, (m, o) in enumerate(zip(raw, out)):
        assert o.range_m == (held if 1.0 <= t[k] < 2.0 else m.range_m)


def test_noise_factor_scales_the_white_noise():
    k, n = 5.0, 4000
    sc = _scenario(f'{{kind="noise", target="altimeter", factor={k}}}')
    raw, out = _alt_stream(build_fault_injector(sc), np.full(n, 100.0))
    extra = np.array([o.range_m - m.range_m for m, o in zip(raw, out)])
    alt = sc.sensors.altimeter
    sigma = math.hypot(alt.noise_sigma_m, alt.noise_frac * 100.0)
    assert np.std(extra) == pytest.approx(math.sqrt(k * k - 1.0) * sigma, rel=0.05)
    assert abs(np.mean(extra)) < 4.0 * sigma * k / math.sqrt(n)


def _imu_stream(inj, n=100, seed=4):
    model = ImuModel(ImuConfig(), np.random.default_rng(seed))
    raw, out = [], []
    for k in range(n):
        t = k * 10_000_000
        inj.update(t)
        m = model.sample(t, np.array([0.1, -0.2, 3.5]), np.array([0.01, 0.0, -0.02]))
        raw.append(m)
        out.append(inj.imu(m))
    return raw, out


def test_imu_faults_act_on_their_channel_and_axes_only():
    raw, out = _imu_stream(_injector('{kind="bias_step", target="imu.gyro", axes=[0, 2], value=0.01, t_s=0.5}'))
    for m, o in zip(raw, out):
        on = m.t_ns >= NS // 2
        assert np.array_equal(o.f_B, m.f_B)
        assert np.allclose(o.omega_B - m.omega_B, [0.01 * on, 0.0, 0.01 * on], atol=1e-15)
    raw, out = _imu_stream(_injector('{kind="stuck", target="imu.accel", axes=[1], t_s=0.5}'))
    k1 = 50
    for k, (m, o) in enumerate(zip(raw, out)):
        assert o.f_B[1] == (raw[k1 - 1].f_B[1] if k >= k1 else m.f_B[1])
        assert o.f_B[0] == m.f_B[0] and np.array_equal(o.omega_B, m.omega_B)
    raw, out = _imu_stream(_injector('{kind="saturation", target="imu.accel", axes=[2], limit=2.0, t_s=0.5}'))
    assert all(o.f_B[2] == (2.0 if m.t_ns >= NS // 2 else m.f_B[2]) for m, o in zip(raw, out))
    raw, out = _imu_stream(_injector('{kind="dropout", target="imu.gyro", t_s=0.2, duration_s=0.3}'))
    assert [o is None for o in out] == [0.2 <= m.t_ns / NS < 0.5 for m in raw]
    raw, out = _imu_stream(_injector('{kind="flagged_invalid", target="imu.accel", t_s=0.2}'))
    assert all(o.valid == (m.t_ns / NS < 0.2) and np.array_equal(o.f_B, m.f_B) for m, o in zip(raw, out))


def test_star_tracker_bias_step_rotates_by_the_bias():
    inj = _injector('{kind="bias_step", target="star_tracker", axes=[1], value=120.0, t_s=0.5}')
    model = StarTrackerModel(StarTrackerConfig(), np.random.default_rng(5))
    q_true = Rotation.from_euler("xyz", [3.0, -2.0, 40.0], degrees=True).as_quat(scalar_first=True)
    for k in range(10):
        t = k * 100_000_000
        inj.update(t)
        m = model.sample(t, q_true)
        o = inj.star_tracker(m)
        err = (Rotation.from_quat(m.q_LB, scalar_first=True).inv()
               * Rotation.from_quat(o.q_LB, scalar_first=True)).as_rotvec()
        want = np.array([0.0, 120.0, 0.0]) * math.pi / (180 * 3600) if t >= NS // 2 else np.zeros(3)
        assert np.allclose(err, want, atol=1e-12)


# --------------------------------------------------------------------------- camera, engine, computer, triggers
def test_camera_blackout_window_and_frame_drop_rate():
    inj = _injector('{kind="camera_blackout", t_s=2.0, duration_s=5.0}')
    times = np.arange(0, 100) * 100_000_000
    got = []
    for t in times:
        inj.update(int(t))
        got.append(inj.frame_delivered(int(t)))
    assert np.array_equal(np.array(got), ~((times >= 2 * NS) & (times < 7 * NS)))
    drops = []
    for seed in (1, 1, 2):
        inj = build_fault_injector(_scenario('{kind="frame_drop", probability=0.3}', extra=(f"seed={seed}",)))
        inj.update(0)
        drops.append(np.array([not inj.frame_delivered(int(t)) for t in np.arange(2000) * 100_000_000]))
    assert np.array_equal(drops[0], drops[1]) and not np.array_equal(drops[0], drops[2])
    assert drops[0].mean() == pytest.approx(0.3, abs=0.04)


def test_engine_and_computer_faults():
    inj = _injector('{kind="thrust_loss", fraction=0.25, torque_B_Nm=[0.0, 60.0, 0.0], t_s=1.0}',
                    '{kind="misalignment", angle_deg=2.0, azimuth_deg=90.0, t_s=2.0}',
                    '{kind="stuck_throttle", t_s=3.0, duration_s=1.0}',
                    '{kind="computer_reset", t_s=5.0, down_s=2.0}')
    seen = {}
    for t_s in (0.5, 1.5, 2.5, 3.0, 3.5, 4.5, 5.5, 7.5):
        t = int(t_s * NS)
        inj.update(t)
        seen[t_s] = (inj.thrust_gain(t), inj.fault_torque_B_Nm(t), inj.thrust_direction_B(t),
                     inj.thrust_command(t, 1000.0 * t_s), inj.computer_down(t))
    assert seen[0.5] == (1.0, None, None, 500.0, False)
    assert seen[1.5][0] == 0.75 and np.array_equal(seen[1.5][1], [0.0, 60.0, 0.0]) and seen[1.5][2] is None
    assert seen[2.5][2] == (2.0, 90.0)
    assert seen[3.0][3] == 3000.0 and seen[3.5][3] == 3000.0 and seen[4.5][3] == 4500.0  # held, then released
    assert [seen[s][4] for s in (4.5, 5.5, 7.5)] == [False, True, False]


def test_altitude_and_phase_triggers_latch_once():
    inj = _injector('{kind="dropout", target="altimeter", altitude_m=100.0, duration_s=1.0}',
                    '{kind="camera_blackout", phase="terminal"}')
    assert inj.needs_altitude()
    assert inj.update(0, 150.0, "approach") == []
    assert inj.update(NS, 99.0, "approach") == [0]
    assert not inj.needs_altitude()
    assert inj.update(2 * NS, 150.0, "terminal") == [1]  # climbing back does not re-trigger the first
    assert inj.windows() == [(NS, 2 * NS), (2 * NS, None)]


def test_terrain_step_raises_the_disc_only():
    h = np.zeros((65, 65), np.float32)
    sc = _scenario('{kind="terrain_step", height_m=40.0, center_xy_m=[-150.0, 100.0], radius_m=50.0}')
    stepped = terrain_step_heights(h, 512.0, list(sc.faults))
    c = (np.arange(65) - 32) * 8.0
    X, Y = np.meshgrid(c, c)
    want = np.where(np.hypot(X + 150.0, Y - 100.0) <= 50.0, 40.0, 0.0)
    assert np.array_equal(stepped, want.astype(np.float32))
    terrain = with_terrain_steps(make_terrain(h, 512.0), sc)
    assert terrain.height_at(-150.0, 100.0) == pytest.approx(40.0) and terrain.height_at(0.0, 0.0) == 0.0


# --------------------------------------------------------------------------- presets
def test_every_preset_validates_and_names_its_faults():
    base = load_scenario(None)
    for name in [*PRESETS, REFERENCE.name]:
        sc = load_scenario(None, [], name)
        assert get_preset(name).provenance
        assert len(sc.faults) == len(get_preset(name).layer.get("faults", []))
        assert sc.dispersions.keys() == base.dispersions.keys()
    # A preset is a layer under --set, and its faults are appended to the file's.
    data = {"faults": [{"kind": "dropout", "target": "star_tracker"}]}
    assert [f["kind"] for f in apply_preset(data, "im1")["faults"]] == ["dropout", "flagged_invalid"]
    sc = load_scenario(None, ["sun.elevation_deg=7.0"], "sun_5deg")
    assert sc.sun.elevation_deg == 7.0
    with pytest.raises(ValueError, match="no such preset"):
        get_preset("nope")


# --------------------------------------------------------------------------- closed loop (short runs)
SHORT = [*SMALL_SET, "sim.t_max_ns=6_000_000_000"]


class _Collect:
    want_depth = False

    def __init__(self):
        self.kinds: dict[str, list[int]] = {}

    def message(self, kind, msg):
        self.kinds.setdefault(kind, []).append(msg.t_ns)

    def camera_truth(self, *a):
        pass

    def control_tick(self, *a):
        pass


def test_camera_blackout_in_the_loop_no_frame_in_the_window_and_frames_resume():
    from bench.sim.run import run

    rec = _Collect()
    sc = load_scenario(None, [*SHORT, 'faults=[{kind="camera_blackout", t_s=2.0, duration_s=2.5}]'])
    res = run(sc, recorder=rec)
    t = np.array(rec.kinds["image"]) / NS
    assert not np.any((t >= 2.0) & (t < 4.5))
    assert np.any(t < 2.0) and np.any(t >= 4.5)
    assert np.all(np.diff(t[t >= 4.5]) == pytest.approx(0.1))  # every frame after the window
    f = res.summary["faults"][0]
    assert f["detected"] and 0.0 <= f["latency_s"] <= 0.5 and f["start_t_s"] == 2.0 and f["end_t_s"] == 4.5


def test_reset_and_thrust_loss_in_the_loop():
    from bench.sim.run import run

    rec = _Collect()
    # The idealised engine delivers its command at once, so the delivered / commanded ratio is exactly the loss
    # (the realistic engine's lag would blur it).
    sc = load_scenario(None, [*SHORT, 'realism="ideal"', 'faults=[{kind="computer_reset", t_s=1.0, down_s=1.5}, '
                                                         '{kind="thrust_loss", fraction=0.2, t_s=3.0}]'])
    res = run(sc, recorder=rec)
    tel = res.telemetry
    for kind in ("imu", "attitude", "altimeter"):
        t = np.array(rec.kinds[kind]) / NS
        assert not np.any((t >= 1.0) & (t < 2.5)) and np.any(t >= 2.5), kind
    down = (tel["t_s"] >= 1.0) & (tel["t_s"] < 2.5)
    assert np.all(tel["thrust_cmd_N"][down] == 0.0) and not np.any(tel["engine_on"][down])
    on = tel["engine_on"] & (tel["thrust_cmd_N"] > 0)
    ratio = tel["thrust_N"][on] / np.clip(tel["thrust_cmd_N"][on], 1500.0, 7500.0)
    late = tel["t_s"][on] >= 3.0
    assert np.allclose(ratio[late], 0.8) and np.allclose(ratio[~late], 1.0)
    events = [e["subsystem"] for e in res.summary["fdir_events"]]
    assert "computer" in events and res.summary["faults"][0]["detected"]


def test_a_reset_at_hand_over_restarts_from_the_hand_over_data():
    from bench.sim.run import run

    # Down from t = 0, before the first control tick: no checkpoint yet, so the restart takes the hand-over's
    # own estimate (as loaded, never updated) carried ballistically over the second down.
    sc = load_scenario(None, [*SHORT, 'faults=[{kind="computer_reset", t_s=0.0, down_s=1.0}]'])
    res = run(sc)
    tel = res.telemetry
    down = tel["t_s"] < 1.0
    assert set(tel["phase"][down]) == {"off"} and np.isnan(tel["t_go_s"][down]).all()  # guidance never ran
    assert not tel["engine_on"][down].any() and set(tel["phase"][~down]) <= {"approach", "terminal", "touchdown"}
    r0 = np.array([tel[f"nav_r_{a}_m"][0] for a in "xyz"])
    v0 = np.array([tel[f"nav_v_{a}_mps"][0] for a in "xyz"])
    first = np.flatnonzero(~down)[0]
    r1 = np.array([tel[f"nav_r_{a}_m"][first] for a in "xyz"])
    g_L = np.array([0.0, 0.0, -sc.estimator.gravity_mps2])
    # Horizontally nothing has updated it yet; the height has had the altimeter's update at t = 1 s.
    np.testing.assert_allclose(r1[:2], (r0 + v0 * 1.0)[:2], atol=1e-3)
    assert abs(r1[2] - (r0 + v0 * 1.0 + 0.5 * g_L)[2]) < 2.0
    assert [e["reason"] for e in res.summary["fdir_events"]][:1] == ["computer restarted after 1.00 s down"]


def test_a_fault_that_never_triggers_changes_nothing():
    from bench.sim.run import run

    a = run(load_scenario(None, SHORT)).telemetry
    # Triggers the 6 s flight from 500 m never reaches (a time trigger after the run's end is refused at load).
    b = run(load_scenario(None, [*SHORT, 'faults=[{kind="frame_drop", probability=0.5, altitude_m=10.0}, '
                                         '{kind="noise", target="altimeter", factor=3.0, phase="terminal"}]'])).telemetry
    for k in a:
        assert np.array_equal(a[k], b[k]) or np.array_equal(a[k], b[k], equal_nan=True), k


def test_dead_altimeter_without_altitude_declares_a_safe_abort():
    from bench.sim.run import run

    sc = load_scenario(None, [*SMALL_SET, "initial.v_BL_L_mps=[0.0, 0.0, -2.0]", "sim.t_max_ns=30_000_000_000",
                              'faults=[{kind="dropout", target="altimeter"}]', "fdir.abort_sigma_z_min_m=1.0",
                              "fdir.abort_sigma_z_frac=0.001"])
    s = run(sc).summary
    assert s["outcome"] == "safe_abort" and s["fdir"]["abort_declared"]
    assert s["faults"][0]["detected"] and s["touchdown"]["t_s"] is None


def test_dead_altimeter_vision_divergence_carries_the_height():
    """No altimeter from the start: vision's flow divergence (the vertical velocity over the height, whose
    scale the IMU's accelerations make observable) must shrink the height's 1-sigma from its 20 m at hand-over
    within 8 s (dead reckoning alone grows it), with the error inside 3 sigma throughout."""
    from bench.sim.run import run

    res = run(load_scenario(None, [*SMALL_SET, "sim.t_max_ns=8_000_000_000",
                                   'faults=[{kind="dropout", target="altimeter"}]']))
    tel = res.telemetry
    sz, ez = tel["nav_sigma_r_z_m"], tel["nav_err_r_z_m"]
    assert sz[-1] < 0.7 * sz[0], (sz[0], sz[-1])
    assert np.all(np.abs(ez) < 3.0 * sz)
    assert res.summary["faults"][0]["detected"]


@pytest.mark.slow
def test_dead_altimeter_default_descent_lands():
    """The default descent with no altimeter range at all lands within the criteria on vision's divergence."""
    from bench.sim.run import run

    s = run(load_scenario(None, ["seed=1", 'faults=[{kind="dropout", target="altimeter"}]'])).summary
    assert s["outcome"] == "landed", s["outcome"]
    assert s["touchdown"]["v_vertical_mps"] < 1.0


# --------------------------------------------------------------------------- command line and the matrix
def test_faults_list_and_bad_names_get_one_line(capsys, tmp_path):
    from bench.cli import main

    assert main(["faults", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == [*PRESETS, REFERENCE.name] and all(len(line.split()) > 3 for line in out)
    for argv in (["faults", "--presets", "im1,nope", "--runs", "1", "--out", str(tmp_path / "m")],
                 ["run", "--preset", "nope", "--out", str(tmp_path / "r")],
                 ["faults", "--presets", "im1", "--out", str(tmp_path / "m")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("landbench: error:") and "\n" not in err
    # Listing runs nothing: a matrix option beside it is named, not dropped.
    for extra, named in ((["--runs", "5"], "--runs"), (["--set", "seed=3", "--out", str(tmp_path / "m")], "--set, --out"),
                         (["--presets", "im1"], "--presets"), (["--seed", "2"], "--seed")):
        assert main(["faults", "list", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("landbench: error: faults list") and f"drop {named} " in err and "\n" not in err
    assert not any(tmp_path.iterdir())


@pytest.mark.slow  # a real two-preset campaign (16 s); the fast suite keeps the matrix's bad-input checks
def test_fault_matrix_of_two_presets(tmp_path, capsys):
    import json

    import pyarrow.parquet as pq

    from bench.campaign.faults import MATRIX_PARQUET, format_matrix, preset_stats
    from bench.cli import main

    out = tmp_path / "m"
    argv = ["faults", "--presets", "camera_blackout_5s,nominal", "--runs", "1", "--workers", "2", "--out", str(out),
            *sum((["--set", s] for s in [*SMALL_SET, "sim.t_max_ns=12_000_000_000"]), [])]
    assert main(argv) == 0
    doc = json.loads((out / "faults.json").read_text())
    rows = {m["preset"]: m for m in doc["matrix"]}
    assert rows["camera_blackout_5s"]["faults_injected"] == 1 and rows["camera_blackout_5s"]["faults_detected"] == 1
    assert rows["nominal"]["faults_injected"] == 0 and rows["nominal"]["n_cases"] == 1
    assert pq.read_table(out / MATRIX_PARQUET).num_rows == 2
    assert (out / "report.png").stat().st_size > 0 and (out / "presets" / "nominal" / "report.png").exists()
    assert format_matrix(doc) in capsys.readouterr().out
    # The statistics from rows built here: one detected, one missed, a false alarm in a faultless case.
    rows = [
        {"outcome": "landed", "faults_0_kind": "dropout", "faults_0_triggered": True, "faults_0_detected": True,
         "faults_0_latency_s": 0.4, "fdir_n_events": 1},
        {"outcome": "hard_landing", "faults_0_kind": "dropout", "faults_0_triggered": True,
         "faults_0_detected": False, "fdir_n_events": 1, "fdir_abort_declared": False},
        {"outcome": "hard_landing", "faults_0_kind": "dropout", "faults_0_triggered": False,
         "fdir_n_events": 1, "fdir_abort_declared": True},
        {"outcome": "safe_abort", "fdir_n_events": 2, "fdir_abort_declared": True},
    ]
    stats = preset_stats(rows)
    assert (stats["faults_injected"], stats["faults_detected"], stats["failed"], stats["unseen"],
            stats["false_alarm"]) == (2, 1, 2, 1, None)
    assert preset_stats([{"outcome": "landed", "fdir_n_events": 0}, {"outcome": "landed", "fdir_n_events": 3}],
                        reference=True)["false_alarm"] == 1
    assert stats["land_or_abort_rate"] == pytest.approx(2 / 4) and stats["latency_median_s"] == 0.4
    # Resuming a finished matrix reruns nothing and gives the same matrix.
    assert main(["faults", "--resume", str(out)]) == 0
    assert json.loads((out / "faults.json").read_text())["matrix"][0]["outcomes"] == doc["matrix"][0]["outcomes"]


# --------------------------------------------------------------------------- RCS
def test_rcs_fault_windows_and_per_axis_factors():
    """The injector's RCS factors, written out by hand for each window: a one-sense loss on x and y, a loss of
    70 % on z, and a stuck-on thruster about -y at half the limit, each on its own trigger."""
    inj = _injector('{kind="rcs_loss", axes=[0, 1], direction="positive", t_s=1.0, duration_s=2.0}',
                    '{kind="rcs_loss", axes=[2], fraction=0.7, t_s=2.0}',
                    '{kind="rcs_stuck_on", axis=1, sign=-1, fraction=0.5, t_s=4.0}')
    seen = {}
    for t_s in (0.5, 1.5, 2.5, 3.5, 4.5):
        t = int(t_s * NS)
        inj.update(t)
        seen[t_s] = inj.rcs_fault(t)
    assert seen[0.5] is None
    pos, neg, stuck = seen[1.5]
    assert pos.tolist() == [0.0, 0.0, 1.0] and neg.tolist() == [1.0, 1.0, 1.0] and stuck.tolist() == [0, 0, 0]
    pos, neg, stuck = seen[2.5]
    assert pos.tolist() == pytest.approx([0.0, 0.0, 0.3]) and neg.tolist() == pytest.approx([1.0, 1.0, 0.3])
    pos, neg, stuck = seen[3.5]  # the one-sense loss has ended
    assert pos.tolist() == pytest.approx([1.0, 1.0, 0.3]) and stuck.tolist() == [0.0, 0.0, 0.0]
    pos, neg, stuck = seen[4.5]
    assert stuck.tolist() == [0.0, -0.5, 0.0]


@pytest.mark.parametrize("mode", ["continuous", "pwm"])
def test_rcs_faults_change_the_delivered_torque_as_specified(mode):
    """Delivered torque against the unfaulted actuator, window by window: a positive command about x delivers
    nothing with the positive sense lost, a negative one is untouched; z delivers 30 % under a 70 % loss; a
    stuck-on thruster adds half the limit about -y to whatever is delivered (PWM: the windows' impulses)."""
    from models.actuators import PropulsionModel
    from models.lander import EngineConfig, LanderConfig, RcsConfig

    def model():
        return PropulsionModel(LanderConfig(rcs=RcsConfig(mode=mode, draws_propellant=False),
                                            engine=EngineConfig(time_constant_s=0.0, slew_rate_Nps=math.inf)))

    dt_ns = 2_000_000
    cmds = ([120.0, 80.0, -90.0], [-120.0, -40.0, 150.0])
    tau_max = float(LanderConfig().rcs_torque_max_Nm)
    for cmd in cmds:
        cmd = np.array(cmd)
        clean, faulty = model(), model()
        faulty.set_rcs_fault((np.array([0.0, 1.0, 0.3]), np.array([1.0, 1.0, 0.3]), np.array([0.0, -0.5, 0.0])))
        n = 50  # whole PWM windows
        a = np.array([clean.physics_step(3000.0, cmd, k, dt_ns)[1] for k in range(n)]).mean(axis=0)
        b = np.array([faulty.physics_step(3000.0, cmd, k, dt_ns)[1] for k in range(n)]).mean(axis=0)
        expect = np.array([a[0] * (0.0 if cmd[0] > 0 else 1.0), a[1], 0.3 * a[2]]) + np.array([0.0, -0.5 * tau_max, 0.0])
        np.testing.assert_allclose(b, expect, atol=1e-9)
        np.testing.assert_allclose(a, cmd, atol=1e-9)  # the clean RCS delivers the command on average
        faulty.set_rcs_fault(None)
        c = np.array([faulty.physics_step(3000.0, cmd, k, dt_ns)[1] for k in range(n, 2 * n)]).mean(axis=0)
        np.testing.assert_allclose(c, cmd, atol=1e-9)  # cleared: as the clean one


def test_rcs_torque_check_against_rates_made_from_a_known_torque():
    """The monitor's torque residual on gyro rates integrated by hand (Euler's equations) from a known delivered
    torque: the residual is the delivered torque less the commanded one; the nominal vehicle's torque (thrust times a lever
    inside the tolerance) raises nothing, a stuck-on thruster beyond it raises one 'rcs' event after the
    persistence time, and nothing is checked with the engine off."""
    from gnc.fdir import FdirConfig, HealthMonitor, SensorSpec
    from gnc.messages import ImuMessage

    spec = SensorSpec(imu_period_ns=10_000_000, altimeter_period_ns=50_000_000, star_tracker_period_ns=100_000_000,
                      camera_period_ns=100_000_000, altimeter_max_range_m=3000.0)
    inertia = np.array([900.0, 950.0, 1100.0])
    cmd = np.array([20.0, -35.0, 5.0])
    thrust = 3000.0
    cfg = FdirConfig()

    def fly(extra_torque, seconds=3.0, thrust_N=thrust):
        m = HealthMonitor(cfg, spec)
        w = np.zeros(3)
        out = []
        t = 0
        while t <= seconds * NS:
            if t % 20_000_000 == 0:
                m.control_tick(t, thrust_N, 1.0, 2000.0, False)
                out.append(m.torque_check(t, cmd, thrust_N, inertia, 200.0))
            t += spec.imu_period_ns
            for _ in range(10):  # Euler's equations, I w' = tau - w x I w, in 1 ms steps
                w = w + (cmd + extra_torque - np.cross(w, inertia * w)) / inertia * 1e-3
            m.imu(ImuMessage(t, np.array([0.0, 0.0, 1.5]), w.copy()))
        return m, [r for r in out if r is not None]

    nominal = np.array([0.8, -0.8, 0.0]) * cfg.torque_lever_m * thrust  # inside the engine's envelope
    m, res = fly(nominal)
    np.testing.assert_allclose(res[-1], nominal, atol=1.0)
    assert not [e for e in m.events if e.subsystem == "rcs"]
    stuck = np.array([0.0, 0.0, 0.0])
    stuck[1] = -(cfg.torque_lever_m * thrust + cfg.torque_margin_Nm) - 30.0
    m, res = fly(stuck)
    np.testing.assert_allclose(res[-1], stuck, atol=1.0)
    ev = [e for e in m.events if e.subsystem == "rcs"]
    assert len(ev) == 1 and "body y" in ev[0].reason
    # the first full window is at 0.9 s, then the residual must persist 0.5 s
    assert 1.3 * NS <= ev[0].t_ns <= 1.6 * NS
    m, res = fly(stuck, thrust_N=0.0)
    assert res == [] and not [e for e in m.events if e.subsystem == "rcs"]


def test_rcs_stuck_on_in_the_loop_is_detected_and_a_partial_one_flown_through():
    """In the loop (6 s of the descent): a thruster stuck fully on about y from 2 s (the opposite jet can only
    just cancel it) is seen by the torque check within 2 s; one at a quarter of the limit about x is inside the
    engine's envelope (not reported), and the attitude loop holds the tilt within 2 deg of the run without it."""
    from bench.sim.run import run

    res = run(load_scenario(None, [*SHORT, 'faults=[{kind="rcs_stuck_on", axis=1, sign=-1, fraction=1.0, t_s=2.0}]']))
    f = res.summary["faults"][0]
    assert f["triggered"] and f["detected"] and 0.0 < f["latency_s"] <= 2.0, f
    clean = run(load_scenario(None, SHORT)).telemetry
    part = run(load_scenario(None, [*SHORT, 'faults=[{kind="rcs_stuck_on", axis=0, sign=1, fraction=0.25, '
                                            't_s=2.0}]']))
    assert not [e for e in part.summary["fdir_events"] if e["subsystem"] == "rcs"]
    assert np.max(np.abs(part.telemetry["tilt_deg"] - clean["tilt_deg"])) < 2.0


@pytest.mark.parametrize("fault, start", [
    # Before: a trigger time or duration of 1e300 s overflowed in ns (OverflowError traceback, exit 1), a bias of
    # 1e308 m overflowed the filter's innovation, a reset's duration_s was ignored without a word, and a trigger
    # after the run's end was accepted and never acted.
    ('{kind="dropout", target="altimeter", t_s=1e300}', "faults.0.t_s = 1e+300: Input should be less than"),
    ('{kind="dropout", target="altimeter", t_s=5.0, duration_s=1e300}', "faults.0.duration_s = 1e+300"),
    ('{kind="bias_step", target="altimeter", value=1e308, t_s=10.0}', "faults.0.value = 1e+308"),
    ('{kind="bias_ramp", target="altimeter", rate_per_s=-1e200, t_s=10.0}', "faults.0.rate_per_s = -1e+200"),
    ('{kind="computer_reset", t_s=20.0, down_s=1.0, duration_s=30.0}',
     "faults.0.duration_s = 30: a reset lasts its down_s"),
    ('{kind="dropout", target="altimeter", t_s=500.0}',
     "faults.0.t_s = 500 s is at or after the run's end (sim.t_max_ns = 240000000000)"),
])
def test_fault_settings_that_overflowed_or_never_acted_are_refused_at_load(fault, start):
    from bench.scenario import ScenarioError, load_scenario

    with pytest.raises(ScenarioError) as exc:
        load_scenario(None, [f"faults=[{fault}]"])
    assert str(exc.value).startswith(start), str(exc.value)


@pytest.mark.parametrize("fault, needle", [
    ('{kind = "bias_step", target = "altimeter", value = 5.0, axes = [2]}', "the altimeter has one value"),
    ('{kind = "dropout", target = "imu.accel", axes = [0]}', "a dropout acts on the whole message"),
    ('{kind = "flagged_invalid", target = "star_tracker", axes = [1, 2]}', "a flagged_invalid acts on the whole message"),
    ('{kind = "stuck", target = "star_tracker", axes = [0]}', "a stuck star tracker repeats its whole attitude"),
])
def test_axes_a_fault_would_ignore_are_refused(fault, needle):
    # They were accepted and ignored: the whole message (or the altimeter's one value) was affected.
    with pytest.raises(ScenarioError, match=r"faults\.0: axes = \[.*\] on a '.*' fault of '.*': " + needle):
        load_scenario(None, [f"faults=[{fault}]"])
    load_scenario(None, ['faults=[{kind = "bias_step", target = "imu.gyro", value = 1e-3, axes = [2]}]'])


def test_a_terrain_step_under_the_start_is_named_in_the_refusal():
    from bench.sim.world_builder import build_world

    # It blamed initial.r_BL_L_m alone ("ground at 598.84 m there"), not the fault that raised the ground.
    sc = load_scenario(None, ['faults=[{kind = "terrain_step", height_m = 600, center_xy_m = [-120, 80], '
                              'radius_m = 30}]'])
    with pytest.raises(ScenarioError, match=r"initial.r_BL_L_m = \[-120.0, 80.0, 500.0\]: the footpads would start at "
                                            r"or below the terrain \(ground at .* m there; faults.0 \(a terrain_step of "
                                            r"\+600 m, radius 30 m about \[-120.0, 80.0\]\) raises it there\); give z > "
                                            r".* m or a terrain_step that leaves the start clear"):
        build_world(sc)


def test_overlapping_misalignments_or_stuck_throttles_are_refused():
    # The second acted not at all (the injector takes the first listed): accepted without a word before.
    both = ('faults=[{kind = "misalignment", angle_deg = 1.0, t_s = 10.0}, '
            '{kind = "misalignment", angle_deg = 2.0, azimuth_deg = 90.0, t_s = 20.0}]')
    with pytest.raises(ScenarioError, match=r"faults\.1: a second misalignment while faults\.0's is active \(from 10 s\)"
                                            r": only the first listed would act"):
        load_scenario(None, [both])
    with pytest.raises(ScenarioError, match=r"faults\.1: a second stuck_throttle while faults\.0's is active \(from 5 s "
                                            r"to 15 s\)"):
        load_scenario(None, ['faults=[{kind = "stuck_throttle", t_s = 5.0, duration_s = 10.0}, '
                             '{kind = "stuck_throttle", t_s = 12.0}]'])
    # One after the other, or of different kinds: accepted.
    load_scenario(None, ['faults=[{kind = "misalignment", angle_deg = 1.0, t_s = 10.0, duration_s = 5.0}, '
                         '{kind = "misalignment", angle_deg = 2.0, t_s = 15.0}, {kind = "stuck_throttle", t_s = 12.0}]'])


def test_a_terrain_step_acts_from_when_the_altimeter_ranges_it_not_when_the_body_flies_over_it():
    """Seed 7's case 6 of the Hakuto-R preset started 35 m inside the 60 m plateau at 496 m, tilted: its beam
    reached the ground 100 m away, beyond the edge, so the step never acted on a sensor, yet it was scored a
    missed detection (9 of 10). The step now starts at the first valid range whose footprint (the mount and
    boresight carried by the true attitude, out to the reported range) lies on the disc, computed here by hand
    for a tilt about y: a body inside the disc whose beam lands outside never triggers it; a body outside whose
    beam lands inside does, at its first valid sample."""
    from types import SimpleNamespace

    from bench.sim.run import _beam_on_disc_ns
    from models.lander import LanderConfig, altimeter_position_B

    lander = LanderConfig()
    mx, _, mz = altimeter_position_B(lander)
    step = SimpleNamespace(center_xy_m=[0.0, 0.0], radius_m=60.0)
    theta = math.radians(11.6)
    q = [math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0]  # about +y: x' = x cos + z sin
    z = 496.0
    rng = z / math.cos(theta)  # flat ground at 0 m
    n = 4

    def tel(x0, valid):
        return {"t_s": np.arange(n) * 0.02, "r_x_m": np.full(n, x0), "r_y_m": np.zeros(n), "r_z_m": np.full(n, z),
                "q_w": np.full(n, q[0]), "q_x": np.zeros(n), "q_y": np.full(n, q[2]), "q_z": np.zeros(n),
                "alt_range_m": np.full(n, rng), "alt_valid": np.array(valid)}

    def foot_x(x0):  # the boresight (0, 0, -1) out to the range, plus the mount
        return x0 + mx * math.cos(theta) + (mz - rng) * math.sin(theta)

    assert foot_x(35.0) < -60.0 and abs(foot_x(70.0)) < 60.0
    assert _beam_on_disc_ns(tel(35.0, [True] * n), step, lander) is None  # the body over the disc throughout
    assert _beam_on_disc_ns(tel(70.0, [False, True, True, True]), step, lander) == 20_000_000  # never over it
    assert _beam_on_disc_ns(tel(70.0, [False] * n), step, lander) is None
