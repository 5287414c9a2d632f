"""The terminal phase's fly-out of a missed gate: the propellant bingo and vision below its cut-off.

A probe of held-out settings found the case (Beresheet preset: a gyro dropout at 150 m, then a computer reset
at 120 m with the engine off for 3 s). The lander reached its terminal phase at 22 m, 53 m from the target
at 7.6 m/s, and flew the miss out at hover height for 40 s below the vision cut-off. On the IMU alone its
velocity drifted with the accelerometer bias's error (0.007 m/s^2) and it touched down at 0.59 m/s horizontal,
nothing declared; with vision kept on, the fly-out ran the tank dry 2.5 m above the ground. The terminal phase
now uses the flow while it flies out (``vision_nav.flyout_cutoff_m``) and lands where it is once the propellant
gauge no longer covers the descent and a reserve (``guidance.terminal_bingo``, ``terminal_reserve_kg``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gnc.control import Controller
from gnc.estimator import IDX_H, make_estimator
from gnc.fdir import FdirConfig, HealthMonitor
from gnc.flight import FlightSoftware
from gnc.guidance import PHASE_TERMINAL, GuidanceConfig, make_guidance
from gnc.messages import AttitudeMessage, ContactMessage
from gnc.vision_nav import VisionNavConfig
from tests.test_fdir_nav import SPEC, _knowledge

G0 = 9.80665


def _terminal_flight(r_L, mass_kg: float, guidance_cfg: GuidanceConfig | None = None,
                     vision_cfg: VisionNavConfig | None = None, tracker: bool = False) -> FlightSoftware:
    """Flight software in its terminal phase, its filter at ``r_L`` at rest, its gauge at ``mass_kg``."""
    k = _knowledge()
    controller = Controller(None, k.vehicle)
    guidance = make_guidance(guidance_cfg, controller.guidance_limits())
    nav = make_estimator(None, list(r_L), [0.0, 0.0, 0.0], 0, q0_LB=[1, 0, 0, 0], altimeter_mount_B_m=k.r_alt_B_m)
    trk = None
    if tracker:
        from vision import Tracker

        trk = Tracker()
    fsw = FlightSoftware(guidance, controller, nav, trk, vision_cfg or VisionNavConfig(), tracker, k,
                         fdir=HealthMonitor(FdirConfig(), SPEC))
    fsw.on_attitude(AttitudeMessage(0, np.array([1.0, 0.0, 0.0, 0.0])))
    guidance.phase = PHASE_TERMINAL
    fsw.mass_kg = mass_kg
    return fsw


def _need_kg(fsw: FlightSoftware, height_m: float) -> float:
    """Hover propellant for a descent of ``height_m`` at the terminal rate, by hand: flow m g / (Isp g0)."""
    cfg = fsw.guidance.cfg
    return fsw.mass_kg * cfg.gravity_mps2 / (fsw.knowledge.isp_s * G0) * height_m / cfg.terminal_descent_rate_mps


def _tick(fsw: FlightSoftware, t_ns: int = 20_000_000) -> None:
    fsw.control(t_ns, ContactMessage(t_ns, np.zeros(4, bool)))


def test_the_terminal_phase_flies_a_missed_gate_out_at_hover_height():
    g = make_guidance(None, Controller(None, _knowledge().vehicle).guidance_limits())
    cfg = g.cfg
    r, v, target = np.array([20.0, -4.0, 24.0]), np.array([0.3, 0.1, -0.2]), np.zeros(3)
    w, zeta = cfg.terminal_position_bandwidth_radps, cfg.terminal_damping_ratio
    # 20.4 m from the target: the speed reference saturates toward it, and the rate is a hover's (0).
    v_ref = -(w / (2 * zeta)) * r[:2]
    v_ref *= cfg.terminal_speed_max_mps / np.linalg.norm(v_ref)
    a = g.terminal_accel_L(r, v, target)
    assert a[:2] == pytest.approx(2 * zeta * w * (v_ref - v[:2]), rel=1e-12)
    assert a[2] == pytest.approx(cfg.terminal_rate_gain_per_s * (0.0 - v[2]), rel=1e-12)


def _bingo_rate_by_hand(cfg: GuidanceConfig, h: float) -> tuple[float, float]:
    """The bingo profile written out: the terminal rate for the last 5 m, then sqrt(v_t^2 + 2 a (h - 5)) with
    a = 0.2 m/s^2, capped at bingo_descent_rate_mps (no deceleration where capped)."""
    v_t = cfg.terminal_descent_rate_mps
    if h <= 5.0:
        return v_t, 0.0
    v = math.sqrt(v_t**2 + 0.4 * (h - 5.0))
    return (cfg.bingo_descent_rate_mps, 0.0) if v >= cfg.bingo_descent_rate_mps else (v, 0.2)


def test_a_bingo_nulls_the_horizontal_speed_then_holds_and_descends_by_its_profile():
    g = make_guidance(None, Controller(None, _knowledge().vehicle).guidance_limits())
    cfg = g.cfg
    w, zeta, k_z = cfg.terminal_position_bandwidth_radps, cfg.terminal_damping_ratio, cfg.terminal_rate_gain_per_s
    for h in (0.0, 3.0, 5.0, 6.0, 10.0, 13.39, 13.41, 25.0):  # the cap (2 m/s) is reached at 13.4 m
        assert g.bingo_rate_mps(h) == pytest.approx(_bingo_rate_by_hand(cfg, h), rel=1e-12)
    g.phase = PHASE_TERMINAL
    g.land_here(ground_z_L=4.0)
    target = np.zeros(3)
    # Flying out at 1.2 m/s, 24 m above the target (20 m above the ground): the speed is nulled, no position loop,
    # and the rate is the terminal one (the speed above 0.5 m/s).
    r, v = np.array([20.0, -4.0, 24.0]), np.array([-1.2, 0.0, -0.5])
    a = g.terminal_accel_L(r, v, target)
    assert a[:2] == pytest.approx(-2 * zeta * w * v[:2], rel=1e-12) and g.hold_xy_L is None
    assert a[2] == pytest.approx(k_z * (-cfg.terminal_descent_rate_mps - v[2]), rel=1e-12)
    # At 0.4 m/s: not yet held; the rate halfway between the terminal rate and the profile's (the blend).
    v = np.array([-0.4, 0.0, -0.5])
    a = g.terminal_accel_L(r, v, target)
    rate, brake = _bingo_rate_by_hand(cfg, 20.0)
    v_t = cfg.terminal_descent_rate_mps
    assert g.hold_xy_L is None
    assert a[2] == pytest.approx(k_z * (-(v_t + 0.5 * (rate - v_t)) - v[2]) + 0.5 * brake, rel=1e-12)
    # Below 0.3 m/s the position is held where it is then, and the profile flown, its deceleration fed forward.
    v = np.array([-0.2, 0.1, -1.5])
    r2 = np.array([18.0, -4.0, 14.0])
    a = g.terminal_accel_L(r2, v, target)
    assert g.hold_xy_L == pytest.approx(r2[:2], abs=0.0)
    rate, brake = _bingo_rate_by_hand(cfg, 10.0)
    assert brake == 0.2
    assert a[:2] == pytest.approx(-2 * zeta * w * v[:2], rel=1e-12)  # at the hold point: the velocity term alone
    assert a[2] == pytest.approx(k_z * (-rate - v[2]) + brake, rel=1e-12)
    a = g.terminal_accel_L(r2 + np.array([1.0, 0.0, 0.0]), v, target)  # 1 m off the hold point, pulled back
    assert a[0] == pytest.approx(2 * zeta * w * (-(w / (2 * zeta)) * 1.0 - v[0]), rel=1e-12)
    g.reset()
    assert not g.bingo and g.hold_xy_L is None


@pytest.mark.parametrize("margin_kg, bingo", [(-0.5, True), (0.5, False)])
def test_the_bingo_comes_when_the_gauge_no_longer_covers_the_descent_and_the_reserve(margin_kg, bingo):
    r = np.array([20.0, 5.0, 24.0])
    dry = _knowledge().vehicle.dry_mass_kg
    fsw = _terminal_flight(r, dry + 40.0)
    reserve = fsw.guidance.cfg.terminal_reserve_kg
    # The gauge set so that what is left less the reserve is the need plus the margin (the need at that mass).
    for _ in range(50):  # the need depends on the mass itself: a fixed point, by iteration
        fsw.mass_kg = dry + reserve + _need_kg(fsw, 24.0) + margin_kg
    _tick(fsw)
    g = fsw.guidance
    if bingo:
        assert g.bingo and g.bingo_ground_z_L == float(fsw.filter.ekf.x[IDX_H])
        (ev,) = [e for e in fsw.fdir.events if e.subsystem == "propellant"]
        assert "bingo" in ev.reason and ev.action.startswith("landing where it is")
    else:
        assert not g.bingo and not fsw.fdir.events


def test_the_bingo_judges_the_height_above_the_filters_ground():
    """The need is the descent to the ground under the vehicle (the filter's terrain height), not to the target's
    elevation: ground 10 m up leaves 14 m to descend, which the same gauge covers."""
    dry = _knowledge().vehicle.dry_mass_kg
    fsw = _terminal_flight([20.0, 5.0, 24.0], dry + 40.0)
    reserve = fsw.guidance.cfg.terminal_reserve_kg
    for _ in range(50):
        fsw.mass_kg = dry + reserve + _need_kg(fsw, 24.0) - 1.0  # short for 24 m
    fsw.filter.ekf.x[IDX_H] = 10.0
    assert _need_kg(fsw, 14.0) < fsw.mass_kg - dry - reserve  # but enough for 14 m
    _tick(fsw)
    assert not fsw.guidance.bingo


def test_the_bingo_takes_the_ground_the_altimeter_shows_when_the_filters_is_lower():
    """A filter whose terrain height went wrong (a probe's Hakuto-R case: 255 m below the ground after the plateau)
    must neither call a bingo for a 285 m descent nor set a fast descent's floor there: the ground is
    :meth:`FlightSoftware._ground_under_m`'s, the higher of the filter's and the altimeter's fresh returns."""
    from gnc.messages import ImuMessage
    from tests.test_fdir_nav import ALT_NS, G

    dry = _knowledge().vehicle.dry_mass_kg
    fsw = _terminal_flight([20.0, 5.0, 24.0], dry + 40.0)
    reserve = fsw.guidance.cfg.terminal_reserve_kg
    for _ in range(50):
        fsw.mass_kg = dry + reserve + _need_kg(fsw, 24.0) + 3.0  # enough for 24 m, not for 279 m
    fsw.filter.ekf.x[IDX_H] = -255.0
    t = 0
    for _ in range(5):  # returns of 23.2 m: the body 24 m up, the altimeter 0.77 m below it, level ground at 0
        t += ALT_NS
        fsw.on_imu(ImuMessage(t, np.array([0.0, 0.0, G]), np.zeros(3)))
        fsw._raw_ground.append((t, float(fsw.filter.ekf.x[2]) - 23.23))
    assert fsw._ground_under_m(t, observed=True) == pytest.approx(0.77, abs=0.05)
    _tick(fsw, t)
    assert not fsw.guidance.bingo  # 24 m to descend, covered
    fsw.mass_kg -= 6.0
    _tick(fsw, t + 20_000_000)
    g = fsw.guidance
    assert g.bingo and g.bingo_ground_z_L == pytest.approx(0.77, abs=0.05)
    assert g.bingo_rate_mps(math.nan) == (g.cfg.terminal_descent_rate_mps, 0.0)  # the ground unknown: no fast descent


@pytest.mark.parametrize("case", ["over the target", "approach", "switched off"])
def test_no_bingo_over_the_target_in_the_approach_or_switched_off(case):
    dry = _knowledge().vehicle.dry_mass_kg
    r = [5.0, 2.0, 24.0] if case == "over the target" else [20.0, 5.0, 24.0]  # 5.4 m: within twice the hold radius
    cfg = GuidanceConfig(terminal_bingo=False) if case == "switched off" else None
    fsw = _terminal_flight(r, dry + 1.0, guidance_cfg=cfg)  # 1 kg left: short by any measure
    if case == "approach":
        fsw.guidance.phase = "approach"
        fsw._bingo_check(0, fsw.filter.nav_state(fsw.mass_kg))  # the approach itself is not flown here
    else:
        _tick(fsw)
    assert not fsw.guidance.bingo
    assert not [e for e in fsw.fdir.events if e.subsystem == "propellant"]


def test_vision_is_used_below_its_cutoff_while_the_terminal_phase_flies_out():
    fsw = _terminal_flight([20.0, 5.0, 20.0], 1700.0, tracker=True)
    cfg = fsw.vision_cfg
    assert cfg.flyout_cutoff_m < 20.0 < cfg.cutoff_altitude_m
    assert fsw.vision_active() and fsw.wants_image()  # 20.6 m from the target at 20 m: flying out
    fsw.guidance.phase = "approach"
    assert not fsw.vision_active()  # the approach's own cut-off
    fsw.guidance.phase = PHASE_TERMINAL
    x = fsw.filter.ekf.x
    x[0], x[1] = 5.0, 2.0  # within twice the hold radius: descending over the target
    assert not fsw.vision_active()
    x[0], x[1], x[2] = 20.0, 5.0, cfg.flyout_cutoff_m - 0.1  # below the fly-out's cut-off
    assert not fsw.vision_active()
    x[2] = 20.0
    assert fsw.vision_active()
    fsw.vision.unusable, fsw.vision.measurements = 31, 29  # most of the descent's pairs gave nothing: featureless
    assert not fsw.vision_active()
    fsw.vision.unusable, fsw.vision.measurements = 30, 30  # half: not more than fdir.vision_unusable_max
    assert fsw.vision_active()
    fsw.guidance.land_here(0.0)  # a bingo: landing where it is, so no longer flying out
    assert not fsw.vision_active()
    off = _terminal_flight([20.0, 5.0, 20.0], 1700.0, tracker=True,
                           vision_cfg=VisionNavConfig(flyout_cutoff_m=cfg.cutoff_altitude_m))
    assert not off.vision_active()  # at or above the cut-off: the fly-out's rule is off


@pytest.mark.slow
def test_a_fly_out_below_the_vision_cutoff_lands_instead_of_drifting_or_running_dry():
    """Closed loop, the probe's case (see the module docstring): with both rules it lands (41 m from the target,
    where the bingo stopped it); without the flow in the fly-out it touches down at 0.55 m/s horizontal (the
    drift); without the bingo the tank runs dry above the ground."""
    from bench.scenario import load_scenario
    from bench.sim.run import run

    sets = ["seed=420065", "sun.elevation_deg=26.8", "sun.azimuth_deg=243.7", "camera.width_px=192",
            "camera.height_px=192", "camera.fovy_deg=67.9", "initial.r_BL_L_m=[172.4, -137.7, 540.8]",
            "initial.v_BL_L_mps=[3.25, -7.03, -15.56]", "terrain.seed=243663"]
    on = run(load_scenario(None, sets, preset="beresheet")).summary
    assert on["outcome"] == "landed", on["touchdown"]
    assert any(e["subsystem"] == "propellant" for e in on["fdir_events"])
    drift = run(load_scenario(None, sets + ["vision_nav.flyout_cutoff_m=30"], preset="beresheet")).summary
    assert drift["outcome"] == "hard_landing" and drift["touchdown"]["v_horizontal_mps"] > 0.5
    assert not drift["fdir"]["abort_declared"]
    dry = run(load_scenario(None, sets + ["guidance.terminal_bingo=false"], preset="beresheet")).summary
    assert dry["outcome"] == "fuel_exhausted" and math.isfinite(dry["fuel_exhausted_t_s"])
