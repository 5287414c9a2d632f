"""The flight computer (gnc/flight.py): mass gauging, the vision cut-off, cloning per frame, knowledge checks.

And the filter's horizontal-only velocity update, against an explicit Kalman update.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gnc.control import Controller, VehicleParams
from gnc.estimator import IDX_C, IDX_R, make_estimator
from gnc.flight import G0_MPS2, FlightSoftware, OnboardKnowledge
from gnc.guidance import make_guidance
from gnc.messages import AttitudeMessage, ContactMessage, ImuMessage
from gnc.vision_nav import VisionNavConfig
from vision.tracks import Tracks

G = 1.62
K = np.array([[221.7, 0.0, 127.5], [0.0, 221.7, 127.5], [0.0, 0.0, 1.0]])
R_BC = np.diag([1.0, -1.0, -1.0])


def _knowledge(**kw) -> OnboardKnowledge:
    base = dict(vehicle=VehicleParams(), wet_mass_kg=2100.0, isp_s=310.0, K=K, R_BC=R_BC,
                r_cam_B_m=np.array([0.0, 0.0, -0.77]), r_alt_B_m=np.array([0.3, 0.0, -0.77]))
    base.update(kw)
    return OnboardKnowledge(**base)


def _fsw(z0=200.0, knowledge=None, cutoff=30.0) -> FlightSoftware:
    k = knowledge or _knowledge()
    controller = Controller(None, k.vehicle)
    guidance = make_guidance(None, controller.guidance_limits())
    nav = make_estimator(None, [0.0, 0.0, z0], [0.0, 0.0, -5.0], 0, q0_LB=[1, 0, 0, 0],
                         altimeter_mount_B_m=k.r_alt_B_m)
    return FlightSoftware(guidance, controller, nav, None, VisionNavConfig(cutoff_altitude_m=cutoff), True, k)


def test_mass_gauge_integrates_the_believed_thrust_over_the_nominal_isp():
    scale = 1.02  # the flight software believes the engine delivers 2 % more than commanded
    fsw = _fsw(knowledge=_knowledge(vehicle=VehicleParams(thrust_scale=scale)))
    legs = ContactMessage(0, np.zeros(4, bool))
    burned, t_ns, last = 0.0, 0, None
    for k in range(50):  # 1 s at 50 Hz; an explicit sum of the held commands
        t_ns = k * 20_000_000
        if last is not None:
            burned += last * scale / (310.0 * G0_MPS2) * 0.02
        act = fsw.control(t_ns, ContactMessage(t_ns, legs.legs))
        last = act.thrust_N if act.engine_on else 0.0
    assert fsw.mass_kg == pytest.approx(2100.0 - burned, rel=1e-12)
    assert burned > 0.0


def test_replayed_flown_commands_give_the_flight_mass_gauge_bit_for_bit():
    """Open-loop replay: the mass gauge fed the commands that were flown equals the one that flew them."""
    flown, replayed = _fsw(), _fsw()
    commands = []
    for k in range(60):
        t_ns = k * 20_000_000
        act = flown.control(t_ns, ContactMessage(t_ns, np.zeros(4, bool)))
        commands.append((t_ns, act.thrust_N, act.engine_on))
        replayed.on_flown_command(t_ns, act.thrust_N, act.engine_on)
    assert replayed.mass_kg == flown.mass_kg < 2100.0
    # An engine-off tick holds zero thrust until the next one: the explicit sum.
    commands[30] = (commands[30][0], 4321.0, False)
    off = _fsw()
    for t_ns, thrust_N, on in commands:
        off.on_flown_command(t_ns, thrust_N, on)
    burned = sum((f if on else 0.0) / (310.0 * G0_MPS2) * (t1 - t0) / 1e9
                 for (t0, f, on), (t1, _, _) in zip(commands, commands[1:]))
    assert off.mass_kg == pytest.approx(2100.0 - burned, rel=1e-12)
    assert off.mass_kg > flown.mass_kg


def test_thrust_command_divides_the_wanted_force_by_the_believed_thrust_scale():
    from gnc.control import thrust_vector_command
    from gnc.guidance import TiltLimitConfig

    a_cmd = np.array([0.0, 0.0, 0.4])
    plain, _ = thrust_vector_command(a_cmd, np.array([0, 0, -G]), 2000.0, 200.0, VehicleParams(), TiltLimitConfig())
    scaled, _ = thrust_vector_command(a_cmd, np.array([0, 0, -G]), 2000.0, 200.0, VehicleParams(thrust_scale=1.05),
                                      TiltLimitConfig())
    assert plain == pytest.approx(2000.0 * (0.4 + G))
    assert scaled == pytest.approx(plain / 1.05)


def _tracks(n=40, shift=(0.5, -0.3)) -> Tracks:
    rng = np.random.default_rng(0)
    xy0 = rng.uniform(20, 236, (n, 2))
    return Tracks(ids=np.arange(n, dtype=np.int64), xy=xy0 + np.array(shift), prev_xy=xy0, age=np.ones(n, np.int64))


def _feed(fsw: FlightSoftware, t_ns: int) -> None:
    """IMU and star tracker up to t_ns (hover attitude, free fall specific force zero)."""
    fsw.on_attitude(AttitudeMessage(t_ns, np.array([1.0, 0.0, 0.0, 0.0])))
    fsw.on_imu(ImuMessage(t_ns, np.zeros(3), np.zeros(3)))


def test_each_frame_clones_the_position_and_the_next_frame_measures_against_it():
    fsw = _fsw()
    _feed(fsw, 10_000_000)
    fsw.on_tracks(10_000_000, _tracks())
    assert fsw.filter.clone_time_ns == 10_000_000
    np.testing.assert_array_equal(fsw.filter.ekf.x[IDX_C], fsw.filter.ekf.x[IDX_R])
    assert fsw.vision.measurements == 0  # the first frame has nothing to pair with
    for k in range(2, 11):
        _feed(fsw, k * 10_000_000)
    fsw.on_tracks(110_000_000, _tracks())
    assert fsw.vision.measurements == 1 and fsw.vision.last_record is not None
    assert fsw.vision.last_record.kind == "vision"
    assert fsw.filter.clone_time_ns == 110_000_000


def test_below_the_cut_off_vision_stops_and_drops_the_clone():
    fsw = _fsw(z0=25.0, cutoff=30.0)
    _feed(fsw, 10_000_000)
    assert not fsw.vision_active()
    fsw.on_tracks(10_000_000, _tracks())
    assert fsw.filter.clone_time_ns is None and fsw.vision.track_counts == []
    off = _fsw(z0=200.0)
    off.vision_enabled = False
    _feed(off, 10_000_000)
    assert not off.vision_active()


def test_knowledge_refuses_a_bad_mass_or_isp():
    with pytest.raises(ValueError, match="wet_mass_kg"):
        _knowledge(wet_mass_kg=-1.0)
    with pytest.raises(ValueError, match="isp_s"):
        _knowledge(isp_s=math.nan)
    k = _knowledge()
    assert not k.K.flags.writeable  # calibration is read-only


def test_horizontal_only_velocity_update_matches_an_explicit_kalman_update():
    nav = make_estimator(None, [1.0, 2.0, 100.0], [3.0, -1.0, -5.0], 0, q0_LB=[1, 0, 0, 0],
                         altimeter_mount_B_m=[0.3, 0.0, -0.77])
    x, P = nav.x, nav.P
    z = np.array([3.4, -0.8])
    R = np.array([[0.04, 0.01], [0.01, 0.09]])
    rec = nav.update_velocity(0, z, R, axes=(0, 1))
    assert rec.accepted
    H = np.zeros((2, x.size))
    H[0, 3] = H[1, 4] = 1.0
    S = H @ P @ H.T + R
    Kg = P @ H.T @ np.linalg.inv(S)
    x_post = x + Kg @ (z - H @ x)
    P_post = (np.eye(x.size) - Kg @ H) @ P @ (np.eye(x.size) - Kg @ H).T + Kg @ R @ Kg.T  # Joseph form
    np.testing.assert_allclose(rec.S, S, rtol=1e-12)
    np.testing.assert_allclose(nav.x, x_post, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(nav.P, P_post, rtol=1e-9, atol=1e-12)
    assert nav.x[5] == x[5]  # the vertical velocity, unmeasured and uncorrelated at start, is untouched
