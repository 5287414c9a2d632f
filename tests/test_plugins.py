"""Guidance laws as plug-ins: ``guidance.law = "package.module:ClassName"`` with a ``[guidance.options]`` table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.cli import main
from bench.scenario import ScenarioError, load_scenario
from bench.sim.run import run
from gnc.guidance import GuidanceLimits, LandingTarget, make_guidance
from gnc.navstate import NavState

ROOT = Path(__file__).resolve().parents[1]
NO_CAMERA = ["camera.enabled=false", 'nav="truth"', 'vision="off"']
PLUGIN = 'guidance.law="plugin_laws:ScaledZemZev"'


def test_plugin_from_tests_flies_and_lands():
    sc = load_scenario(None, [*NO_CAMERA, PLUGIN, "guidance.options.position_gain=6.0"])
    s = run(sc).summary
    assert s["outcome"] == "landed", s["outcome"]
    assert s["guidance_law"] == "plugin_laws:ScaledZemZev"


def test_plugin_options_are_validated_and_reach_the_law():
    sc = load_scenario(None, [PLUGIN, "guidance.options.position_gain=9.0"])
    law = make_guidance(sc.guidance, GuidanceLimits())
    assert law.options.position_gain == 9.0
    # k_r = 9, k_v = 4 against the formula written out here.
    r, v, t = np.array([10.0, -5.0, 200.0]), np.array([1.0, 2.0, -10.0]), 20.0
    r_f, v_f, g = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -0.8]), np.array([0.0, 0.0, -1.62])
    zem = r_f - r - v * t - 0.5 * g * t * t
    zev = v_f - v - g * t
    assert np.allclose(law.accel_L(r, v, r_f, v_f, t), 9.0 * zem / t**2 - 4.0 * zev / t + g)
    # The closed loop of the generalised law reaches the gate (explicit integration).
    for _ in range(int(t / 1e-3) - 1):
        tg = t
        a = law.accel_L(r, v, r_f, v_f, tg)
        v = v + a * 1e-3
        r = r + v * 1e-3
        t -= 1e-3
    assert np.linalg.norm(r - r_f) < 0.05 and np.linalg.norm(v - v_f) < 0.05


def test_the_shipped_example_law_loads_and_reaches_its_gate_acceleration(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "examples"))
    sc = load_scenario(None, ['guidance.law="my_guidance:GateAccelApollo"', "guidance.options.gate_accel_up_mps2=0.4"])
    law = make_guidance(sc.guidance, GuidanceLimits())
    r, v = np.array([-120.0, 80.0, 500.0]), np.array([6.0, -4.0, -15.0])
    r_f, v_f = law.gate_L(LandingTarget())
    T = 40.0
    c0, c1, c2 = law.coeffs(r, v, r_f, v_f, T)
    # The open-loop path, integrated step by step, meets the gate with the targeted acceleration.
    dt, rr, vv = 1e-3, r.copy(), v.copy()
    for k in range(int(T / dt)):
        s = (k + 0.5) * dt
        vv = vv + (c0 + c1 * s + c2 * s * s) * dt
        rr = rr + vv * dt - (c0 + c1 * s + c2 * s * s) * dt * dt / 2
    assert np.allclose(rr, r_f, atol=0.05) and np.allclose(vv, v_f, atol=0.01)
    assert np.allclose(c0 + c1 * T + c2 * T * T, [0.0, 0.0, 0.4], atol=1e-9)
    cmd = law.update(NavState(0, r, v, np.array([1.0, 0, 0, 0]), np.zeros(3), 1800.0), LandingTarget())
    assert cmd.valid and cmd.phase == "approach"


@pytest.mark.parametrize("law, options, needle", [
    ("no_such_module:Law", None, "no module named 'no_such_module'"),
    ("plugin_laws:NoSuchClass", None, "has no class 'NoSuchClass'; classes there implementing the interface: ScaledZemZev"),
    ("plugin_laws:NotALaw", None, "does not implement the guidance law interface"),
    ("plugin_laws:HalfALaw", None, "lacks the interface's methods coeffs"),
    ("plugin_broken_import:Law", None, "RuntimeError: this module is broken on purpose"),
    ("plugin_boundary_breaker:Peeker", None, "imports models"),
    ("not an import path", None, "not an import path"),
    ("pdg", None, "unknown law"),
    ("plugin_laws:ScaledZemZev", "guidance.options.position_gain=1.0", "guidance.options.position_gain = 1.0"),
    ("plugin_laws:ScaledZemZev", "guidance.options.gain=7", "unknown field 'guidance.options.gain'"),
    ("plugin_laws:ScaledZemZev", "guidance.options.position_gain=true",
     "guidance.options.position_gain = true: a number is expected, not a boolean"),
    ("zem_zev", "guidance.options.gain=7", "takes no options"),
])
def test_a_bad_plugin_gets_one_error_line(law, options, needle, capsys, tmp_path):
    sets = ["--set", f'guidance.law="{law}"'] + (["--set", options] if options else [])
    out = tmp_path / "run"
    assert main(["run", *sets, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: guidance."), err
    assert needle in err, err
    assert not out.exists()  # nothing written
    with pytest.raises(ScenarioError):
        load_scenario(None, sets[1::2])


def test_a_controller_plugin_flies_and_lands_and_gets_its_options():
    from gnc.control import ControlConfig, Controller, make_controller
    from gnc.guidance import GuidanceCommand

    sc = load_scenario(None, [*NO_CAMERA, 'control.law="plugin_laws:RetunedController"',
                              "control.options.attitude_bandwidth_radps=3.5"])
    ctl = make_controller(sc.control)
    assert type(ctl).__name__ == "RetunedController" and ctl.cfg.attitude_bandwidth_radps == 3.5
    # Its torque is the built-in controller's at that bandwidth.
    ref = Controller(ControlConfig(attitude_bandwidth_radps=3.5))
    nav = NavState(0, np.array([0.0, 0.0, 200.0]), np.zeros(3), np.array([0.99, 0.1, 0.0, 0.0]) / np.hypot(0.99, 0.1),
                   np.array([0.01, 0.0, 0.0]), 1900.0)
    cmd = GuidanceCommand(0, np.array([0.3, 0.0, 0.5]), "approach", 10.0)
    assert np.allclose(ctl.update(nav, cmd).torque_B_Nm, ref.update(nav, cmd).torque_B_Nm)
    s = run(sc).summary
    assert s["outcome"] == "landed", s["outcome"]


@pytest.mark.parametrize("sets, needle", [
    (['control.law="plugin_laws:ScaledZemZev"'], "does not implement the controller interface"),
    (['control.law="pid"'], "control.law = 'pid': unknown controller"),
    (['control.law="plugin_laws:RetunedController"', "control.options.attitude_bandwidth_radps=0"],
     "control.options.attitude_bandwidth_radps = 0"),
    (["control.options.x=1"], "takes no options"),
])
def test_a_bad_controller_plugin_gets_one_error_line(sets, needle, capsys, tmp_path):
    assert main(["run", *[a for s in sets for a in ("--set", s)], "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: control.") and needle in err, err


# --------------------------------------------------------------------------- output a vehicle cannot fly
def test_check_law_vector_passes_finite_vectors_and_names_law_value_and_time():
    from gnc.plugins import LawOutputError, check_law_vector

    check_law_vector(np.array([0.1, -2.0, 1.62]), 3, "guidance.law", "apollo", "accel_L", 0, "m/s^2")
    check_law_vector([0.0, 0.0, 0.0], 3, "guidance.law", "apollo", "accel_L", 0, "m/s^2")
    check_law_vector(1500.0, 0, "control.law", "x:Y", "update", 0, "N")
    for bad, shown in [(np.array([0.0, np.nan, 1.0]), "nan"), (np.array([np.inf, 0.0, 0.0]), "inf"),
                       (np.zeros(2), "shape (2,)"), (np.zeros((1, 3)), "shape (1, 3)"), (None, "nan"),
                       ("up", "'up'")]:
        with pytest.raises(LawOutputError) as exc:
            check_law_vector(bad, 3, "guidance.law", "my_law:MyLaw", "accel_L", 12_345_000_000, "m/s^2")
        msg = str(exc.value)
        assert msg.startswith("guidance.law = 'my_law:MyLaw': accel_L returned ") and shown in msg, msg
        assert "t = 12.345 s" in msg and "allowed: a finite vector of 3 numbers" in msg and "\n" not in msg, msg
    with pytest.raises(LawOutputError, match=r"control.law = 'x:Y': update returned nan at t = 0.000 s; allowed: a "
                                             r"finite number \[N\]"):
        check_law_vector(float("nan"), 0, "control.law", "x:Y", "update", 0, "N")


@pytest.mark.parametrize("law, start", [
    # Before the check, the controller held its last good command and the run went on to a
    # fuel-exhausted or hard landing, with nothing naming the law.
    ("NanLateLaw", "accel_L returned [nan, nan, nan] at t = "),
    # A plug-in raising in flight: its exception and its own line, on one line.
    ("RaisingLaw", "update raised ZeroDivisionError: float division by zero (plugin_bad_outputs.py:"),
])
def test_a_law_failing_in_flight_ends_the_run_with_one_error_line(law, start, capsys, tmp_path):
    out = tmp_path / "run"
    sets = [a for s in [*NO_CAMERA, f'guidance.law="plugin_bad_outputs:{law}"'] for a in ("--set", s)]
    assert main(["run", *sets, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"landbench: error: guidance.law = 'plugin_bad_outputs:{law}': "
                                                   + start), err
    assert " at t = " in err and not out.exists()  # nothing written


@pytest.mark.parametrize("sets, needle", [
    (['guidance.law="plugin_bad_outputs:TwoAxisLaw"'], "guidance.law = 'plugin_bad_outputs:TwoAxisLaw': accel_L returned shape (2,)"),
    (['guidance.law="plugin_bad_outputs:TupleLaw"'], "guidance.law = 'plugin_bad_outputs:TupleLaw': update returned tuple at t = "),
    (['control.law="plugin_bad_outputs:NanTorqueController"'],
     "control.law = 'plugin_bad_outputs:NanTorqueController': update (ActuatorCommand.torque_B_Nm) returned [nan, nan, nan] "
     "at t = 2.02"),
    (['guidance.law="plugin_bad_outputs:StringTgoLaw"'],
     "guidance.law = 'plugin_bad_outputs:StringTgoLaw': update returned t_go_s = 'soon' at t = 0.000 s"),
])
def test_a_law_output_that_cannot_be_flown_stops_the_run(sets, needle):
    from gnc.plugins import LawOutputError

    with pytest.raises(LawOutputError) as exc:
        run(load_scenario(None, [*NO_CAMERA, *sets]))
    assert needle in str(exc.value), str(exc.value)


def test_a_controller_torque_given_as_a_list_is_flown_as_an_array():
    # Before: an AttributeError in the first tick's telemetry row. Two seconds of flight tell.
    sc = load_scenario(None, [*NO_CAMERA, 'control.law="plugin_bad_outputs:TorqueListController"',
                              "sim.t_max_ns=2_000_000_000"])
    result = run(sc)
    assert result.summary["outcome"] == "timeout"
    torque = np.column_stack([result.telemetry[f"torque_{a}_Nm"] for a in "xyz"])
    assert np.isfinite(torque).all() and np.abs(torque).max() > 0.0


def test_a_plugin_whose_constructor_raises_is_one_line(capsys, tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--set", 'control.law="plugin_bad_outputs:InitRaisingController"', "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("landbench: error: control.law = 'plugin_bad_outputs:"
                                                   "InitRaisingController': __init__ raised KeyError: 'kp' "
                                                   "(plugin_bad_outputs.py:"), err
    assert not out.exists()
