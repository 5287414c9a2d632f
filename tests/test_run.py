"""The closed loop: landings, outcomes, determinism and limits (perfect navigation)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.sim.run import OUTCOMES, run, tilt_deg
from bench.scenario import ScenarioError, load_scenario
from tests.conftest import SMALL_SET

# Issue 4's checks fly with perfect navigation and no vision.
PERFECT = ['nav="truth"', 'vision="off"']
NO_CAMERA = ["camera.enabled=false", *PERFECT]
WALL_KEYS = ("wall_time_s", "setup_time_s", "realtime_factor", "time_split_s")


def _meets_criteria(summary: dict) -> None:
    crit, td = summary["criteria"], summary["touchdown"]
    assert summary["outcome"] == "landed" and summary["landed"], summary
    assert td["v_vertical_mps"] <= crit["v_vertical_max_mps"]
    assert td["v_horizontal_mps"] <= crit["v_horizontal_max_mps"]
    assert td["tilt_deg"] <= crit["tilt_max_deg"]
    assert summary["final_tilt_deg"] <= crit["tilt_max_deg"]
    assert summary["sim_time_s"] >= td["t_s"] + crit["settle_s"] - 1e-9


@pytest.fixture(scope="module")
def default_run():
    # No camera: guidance and control do not look at it with perfect navigation (the camera's rate
    # over a whole default run is checked on the vision run, tests/test_nav_loop.py).
    return run(load_scenario(None, NO_CAMERA)), None


def test_default_scenario_lands_and_meets_every_criterion(default_run):
    result, _ = default_run
    _meets_criteria(result.summary)
    assert result.summary["touchdown"]["miss_distance_m"] < 1.0


def test_telemetry_never_exceeds_actuator_and_tilt_limits(default_run):
    result, _ = default_run
    tel, sc = result.telemetry, load_scenario(None, PERFECT)
    eng = sc.lander.engine
    on = tel["engine_on"]
    assert np.all(tel["thrust_cmd_N"][on] >= eng.thrust_min_N - 1e-9)
    assert np.all(tel["thrust_cmd_N"] <= eng.thrust_max_N + 1e-9)
    assert np.all(tel["thrust_cmd_N"][~on] == 0.0)
    assert np.all((tel["throttle"] >= 0.0) & (tel["throttle"] <= 1.0 + 1e-12))
    torques = np.column_stack([tel[f"torque_{a}_Nm"] for a in "xyz"])
    assert np.all(np.abs(torques) <= sc.lander.rcs_torque_max_Nm + 1e-9)
    # Commanded tilt within the schedule that tightens near the ground (independent recomputation).
    tilt = sc.control.tilt
    q_cmd = np.column_stack([tel[f"q_cmd_{c}"] for c in "wxyz"])
    cmd_tilt = np.array([tilt_deg(q) for q in q_cmd])
    alt = np.clip(tel["r_z_m"], 0.0, None)
    limit = tilt.tilt_max_touchdown_deg + (tilt.tilt_max_high_deg - tilt.tilt_max_touchdown_deg) * np.clip(
        alt / tilt.taper_altitude_m, 0.0, 1.0)
    flying = tel["phase"] != "touchdown"
    assert np.all(cmd_tilt[flying] <= limit[flying] + 1e-6)
    assert np.all(tel["tilt_deg"][flying] <= tilt.tilt_max_high_deg + 2.0)  # the attitude loop tracks it


def test_true_thrust_axis_tracks_the_commanded_one(default_run):
    result, _ = default_run
    tel = result.telemetry

    def thrust_axis_L(prefix: str) -> np.ndarray:  # body +z in L, per tick
        q = np.column_stack([tel[f"{prefix}{c}"] for c in "wxyz"])
        return Rotation.from_quat(q, scalar_first=True).apply([0.0, 0.0, 1.0])

    cos = np.sum(thrust_axis_L("q_") * thrust_axis_L("q_cmd_"), axis=1)
    err_deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    t, phase = tel["t_s"], tel["phase"]
    # The lander starts upright while the first command is tilted (~7 deg here); the 2 rad/s,
    # damping-0.9 attitude loop acquires it within 4 / (zeta w) = 2.2 s. After that the error is
    # the loop's lag behind a slowly turning command, about 2 zeta / w = 0.9 s times the command's
    # turn rate (0.05-0.14 deg/s): measured median 0.05 deg, p99 and max 0.13 deg from 3 s on. Bounds
    # 4-8x that: they catch a steady offset of a quarter degree or a loop several times slower,
    # where the limit check above only holds the true tilt within the tilt limit + 2 deg.
    settled = (phase == "approach") & (t >= 3.0)
    assert settled.sum() > 1000
    assert np.median(err_deg[settled]) < 0.25, np.median(err_deg[settled])
    assert np.percentile(err_deg[settled], 99) < 0.5, np.percentile(err_deg[settled], 99)
    assert err_deg[settled].max() < 1.0, err_deg[settled].max()


def test_telemetry_columns_and_touchdown_consistency(default_run):
    result, _ = default_run
    tel, td = result.telemetry, result.summary["touchdown"]
    n = len(tel["t_s"])
    assert all(len(v) == n for v in tel.values())
    assert np.all(np.diff(tel["t_s"]) > 0)
    assert tel["engine_on"][0] and not tel["engine_on"][-1]
    k = int(np.searchsorted(tel["t_s"], td["t_s"]))
    # The lowest footpad is at the ground when contact is declared (soft contact: a few cm at most).
    assert abs(tel["height_m"][k]) < 0.05, tel["height_m"][k - 2:k + 2]
    assert np.all(tel["height_m"][:k - 1] > 0.0)
    assert math.isclose(result.summary["fuel_used_kg"], tel["propellant_kg"][0] - tel["propellant_kg"][-1], rel_tol=1e-9)


INITIAL_CONDITIONS = [
    ["initial.r_BL_L_m=[150.0, -100.0, 500.0]", "initial.v_BL_L_mps=[-5.0, 5.0, -12.0]", "initial.euler_LB_deg=[3.0, -2.0, 0.0]"],
    ["initial.r_BL_L_m=[-60.0, -140.0, 450.0]", "initial.v_BL_L_mps=[2.0, 8.0, -18.0]", "initial.euler_LB_deg=[-4.0, 0.0, 10.0]"],
    ["initial.r_BL_L_m=[100.0, 120.0, 550.0]", "initial.v_BL_L_mps=[-8.0, -6.0, -10.0]", "initial.euler_LB_deg=[0.0, 5.0, -5.0]",
     "initial.omega_B_radps=[0.01, -0.01, 0.0]"],
]


@pytest.mark.parametrize("law, ic", [
    ("apollo", 0),
    # ZEM/ZEV, the default law, lands the default hand-over in make test (default_run above); its landings from
    # these other hand-overs, like Apollo's from the second and third, are multi-case landings for make test-slow.
    *(pytest.param(law, ic, marks=pytest.mark.slow) for law in ("apollo", "zem_zev")
      for ic in range(len(INITIAL_CONDITIONS)) if (law, ic) != ("apollo", 0)),
])
def test_each_guidance_law_lands_from_several_initial_conditions(law, ic):
    sc = load_scenario(None, [*NO_CAMERA, f'guidance.law="{law}"', *INITIAL_CONDITIONS[ic]])
    _meets_criteria(run(sc).summary)


def test_same_seed_same_landing():
    # A short landing (from 20 m, below the 30 m gate: the terminal descent only) flies the same loop.
    sc = load_scenario(None, [*NO_CAMERA, *SMALL_SET, "seed=11", "initial.r_BL_L_m=[8.0, 6.0, 20.0]",
                              "initial.v_BL_L_mps=[0.0, 0.0, -1.0]"])
    a, b = run(sc), run(sc)
    assert a.summary["landed"]
    strip = lambda s: {k: v for k, v in s.items() if k not in WALL_KEYS}  # noqa: E731
    assert strip(a.summary) == strip(b.summary)
    assert a.telemetry.keys() == b.telemetry.keys()
    for k in a.telemetry:
        np.testing.assert_array_equal(a.telemetry[k], b.telemetry[k], err_msg=k)
    # Another seed draws other noise from the first samples on: its first 2 s are enough to show it.
    c = run(sc.model_copy(update={"seed": 12, "sim": sc.sim.model_copy(update={"t_max_ns": 2_000_000_000})}))
    n = c.telemetry["imu_f_z_mps2"].size
    assert 50 <= n < a.telemetry["imu_f_z_mps2"].size
    assert not np.array_equal(a.telemetry["imu_f_z_mps2"][:n], c.telemetry["imu_f_z_mps2"])


LOW = ["initial.r_BL_L_m=[0.0, 0.0, 120.0]", "initial.v_BL_L_mps=[0.0, 0.0, -5.0]"]


@pytest.mark.parametrize(
    "sets, outcome",
    [
        (["lander.propellant_kg=20"], "fuel_exhausted"),
        (["lander.propellant_kg=0"], "fuel_exhausted"),  # loaded empty: the first thrust asked for finds none
        (['guidance.law="off"'], "hard_landing"),
        (['guidance.law="off"', "initial.r_BL_L_m=[0.0, 0.0, 4.0]", "initial.v_BL_L_mps=[0.0, 0.0, 0.0]",
          "initial.euler_LB_deg=[50.0, 0.0, 0.0]", "landing.tilt_max_deg=60", "landing.v_vertical_max_mps=5",
          "landing.v_horizontal_max_mps=5"], "tipped_over"),
        (["sim.t_max_ns=5000000000"], "timeout"),
        (["initial.v_BL_L_mps=[0.0, 0.0, -1e11]"], "diverged"),
        # 40 m/s sideways with the engine off: past the 512 m terrain's edge in 6.4 s, 12 s before it would
        # reach the ground; the run ends there instead of falling on with no ground under it.
        (['guidance.law="off"', "initial.v_BL_L_mps=[40.0, 0.0, 0.0]"], "off_terrain"),
    ],
)
def test_every_failure_outcome_is_reachable(sets, outcome):
    s = run(load_scenario(None, [*NO_CAMERA, *SMALL_SET, *LOW, *sets])).summary
    assert s["outcome"] == outcome and not s["landed"], s
    assert outcome in OUTCOMES
    if outcome == "diverged":
        assert "diverged" in s["error"] and "physics_dt_ns" in s["error"]
    if outcome == "timeout":
        assert s["touchdown"]["t_s"] is None and s["sim_time_s"] == pytest.approx(5.0)
    if outcome == "off_terrain":
        assert s["touchdown"]["t_s"] is None and s["sim_time_s"] == pytest.approx(256.0 / 40.0, abs=0.05)


def test_a_body_first_fall_is_a_hard_landing_at_its_impact_speed():
    # Upside down, engine off (no deep-throttle floor), no RCS authority to turn over: the hull meets the ground first. Touchdown was the
    # first footpad contact only, so such a crash went unseen (the probe's 52 m/s impact bounced and was judged a
    # "safe_abort" later); it is the hull's contact, a hard landing at the free-fall speed.
    sc = load_scenario(None, [*NO_CAMERA, *SMALL_SET, *LOW, 'guidance.law="off"', "initial.euler_LB_deg=[180.0, 0.0, 0.0]",
                              "lander.engine.thrust_min_N=0", "lander.rcs_torque_max_Nm=1e-6"])
    res = run(sc)
    s, tel = res.summary, res.telemetry
    assert s["outcome"] == "hard_landing" and s["touchdown"]["first_contact"] == "hull", s["touchdown"]
    k = int(np.searchsorted(tel["t_s"], s["touchdown"]["t_s"])) - 1  # the tick the speed is read at
    z0, vz0 = sc.initial.r_BL_L_m[2], sc.initial.v_BL_L_mps[2]
    expected = math.sqrt(vz0**2 + 2.0 * sc.sim.gravity_mps2 * (z0 - tel["r_z_m"][k]))
    assert s["touchdown"]["v_vertical_mps"] == pytest.approx(expected, rel=0.01)
    assert s["touchdown"]["tilt_deg"] > 170.0


def test_unstable_timestep_is_refused_at_load():
    with pytest.raises(ScenarioError, match=r"sim.physics_dt_ns = 20000000 is too large.*<= 10000000"):
        load_scenario(None, ["sim.physics_dt_ns=20000000"])


@pytest.mark.parametrize(
    "sets, needle",
    [
        (['guidance.law="pdg"'], "guidance.law = 'pdg'"),
        (["guidance.gate_altitude_m=-5"], "guidance.gate_altitude_m = -5"),
        (["guidance.gate_altitude=30"], "unknown field 'guidance.gate_altitude'"),
        (["control.attitude_bandwidth_radps=0"], "control.attitude_bandwidth_radps = 0"),
        (["guidance.gravity_mps2=9.81"], "sim.gravity_mps2"),
    ],
)
def test_bad_guidance_or_control_settings_give_a_clear_error(sets, needle):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(None, sets)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_tilt_of_a_known_rotation():
    q = Rotation.from_euler("xyz", [0.0, 25.0, 40.0], degrees=True).as_quat(scalar_first=True)
    assert tilt_deg(q) == pytest.approx(25.0)
