"""Navigation filter (gnc/estimator.py) against a small numpy truth simulator.

The simulator here is independent of the filter: a smooth powered descent with an
analytic trajectory, the attitude built from the thrust direction, and the sensors
of models/sensors.py re-implemented from their specs (IMU white noise, turn-on bias
and bias walk; star-tracker rotation noise; altimeter range to a plane with noise,
terrain relief and dropouts; a velocity measurement with a known covariance).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from gnc.estimator import (
    EstimatorConfig,
    NavFilter,
    initial_covariance,
    make_estimator,
    quat_to_matrix,
)
from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage
from gnc.navstate import NavState

NS = 1_000_000_000
G = 1.62  # lunar gravity [m/s^2]
G_L = np.array([0.0, 0.0, -G])
IMU_DT_NS = 10_000_000  # 100 Hz
ALT_EVERY = 5  # altimeter every 5 IMU ticks (20 Hz)
ST_EVERY = 10  # star tracker every 10 ticks (10 Hz)
VEL_EVERY = 10  # velocity measurement every 10 ticks (10 Hz)
DURATION_S = 60.0
BORESIGHT_B = np.array([0.0, 0.0, -1.0])

# Sensor specs (the default sensors of models/sensors.py).
ACC_DENSITY = 1e-3
ACC_BIAS_SIGMA = 5e-3
ACC_BIAS_WALK = 1e-4
GYRO_DENSITY = 1e-5
GYRO_BIAS_SIGMA = 1e-5
ST_SIGMA_RAD = math.radians(10.0 / 3600.0)
ALT_FLOOR_M = 0.05
ALT_FRAC = 1e-3
ALT_DROPOUT = 0.01
TERRAIN_SIGMA_M = 3.0
LEVER_B = np.array([0.3, 0.0, -0.77])
# Velocity measurement covariance (a full SPD matrix) [(m/s)^2].
R_VEL = np.array([[0.010, 0.002, 0.0], [0.002, 0.008, 0.001], [0.0, 0.001, 0.02]])

N_SEEDS = 10
NEES_BAND_PROB = 0.95
# The filter's specification of the simulated sensors (the estimator's defaults are the default campaign's
# specification, the top of its dispersed ranges; this simulator draws exactly these values).
SIM_SPEC = {
    "accel_noise_density": ACC_DENSITY,
    "init_accel_bias_sigma_mps2": ACC_BIAS_SIGMA,
    "attitude_sigma_arcsec": 10.0,
    "altimeter_noise_sigma_m": ALT_FLOOR_M,
    "terrain_relief_sigma_m": TERRAIN_SIGMA_M,
    "site_radius_m": 0.0,  # this world's relief is stationary: no cleared landing site (tested on its own below)
}


def make(cfg, r0, v0, t0, q0_LB=None, mount=LEVER_B) -> NavFilter:
    """make_estimator with this file's altimeter mount."""
    return make_estimator(cfg, r0, v0, t0, q0_LB, altimeter_mount_B_m=mount)


# --------------------------------------------------------------------------- truth simulator
@dataclass
class Truth:
    t_ns: np.ndarray  # (N+1,) tick times
    r: np.ndarray  # (N+1, 3) position of B in L [m]
    v: np.ndarray  # (N+1, 3) [m/s]
    rot: Rotation  # (N+1,) R_LB at the ticks
    imu: list[ImuMessage]  # sample k covers (t_{k-1}, t_k], k = 1..N (index k-1)
    bias_after: np.ndarray  # (N+1, 3): accelerometer bias the filter should hold after tick k [m/s^2]
    star: dict[int, AttitudeMessage]  # tick -> fix
    alt: dict[int, AltimeterMessage]  # tick -> sample
    vel: dict[int, np.ndarray]  # tick -> measured velocity (3,)


def _cubic(p0, v0, p1, v1, T):
    """Coefficients c2, c3 of p0 + v0 t + c2 t^2 + c3 t^3 meeting p1, v1 at T."""
    d = p1 - p0 - v0 * T
    dv = v1 - v0
    c3 = (dv * T - 2 * d) / T**3
    c2 = (d - c3 * T**3) / T**2
    return c2, c3


def _kinematics(t):
    """Analytic position, velocity, acceleration of a powered descent, each (n, 3)."""
    p0, v0 = np.array([-400.0, 250.0, 500.0]), np.array([12.0, -6.0, -12.0])
    p1, v1 = np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.0, -1.0])
    c2, c3 = _cubic(p0, v0, p1, v1, DURATION_S)
    tt = t[:, None]
    r = p0 + v0 * tt + c2 * tt**2 + c3 * tt**3
    v = v0 + 2 * c2 * tt + 3 * c3 * tt**2
    a = 2 * c2 + 6 * c3 * tt
    # A horizontal weave, so the acceleration is not a polynomial.
    w, amp = 0.15, 4.0
    s, c = np.sin(w * t), np.cos(w * t)
    r[:, 0] += amp * s
    v[:, 0] += amp * w * c
    a[:, 0] += -amp * w * w * s
    r[:, 1] += amp * c
    v[:, 1] += -amp * w * s
    a[:, 1] += -amp * w * w * c
    return r, v, a


def _attitude(t, a_L):
    """R_LB: body +z along the thrust (a - g), slow yaw, plus a 2 deg tilt wobble."""
    z = a_L - G_L
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    yaw = 0.2 * np.sin(0.05 * t) + 0.01 * t
    xh = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(t)], axis=1)
    y = np.cross(z, xh)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    x = np.cross(y, z)
    base = Rotation.from_matrix(np.stack([x, y, z], axis=2))
    wobble = Rotation.from_rotvec(np.radians(2.0) * np.sin(0.4 * t)[:, None] * np.array([1.0, 0.0, 0.0]))
    return wobble * base


FIELD_WINDOW = 40  # the last footprints a new height is conditioned on (a smooth field: the nearest screen the rest)


def _field_sample(here: np.ndarray, spots: list, heights: list, length_m: float,
                  rng: np.random.Generator, sigma_m: float = TERRAIN_SIGMA_M, anchors: int = 0) -> float:
    """A Matern-3/2 field's height at ``here`` given its heights at the last FIELD_WINDOW spots
    (and at the first ``anchors`` spots, always)."""
    def cov(d):
        return sigma_m**2 * (1.0 + d / length_m) * np.exp(-d / length_m)
    if not spots:
        return float(rng.normal(0.0, sigma_m))
    X = np.array(spots[:anchors] + spots[anchors:][-FIELD_WINDOW:])
    y = np.array(heights[:anchors] + heights[anchors:][-FIELD_WINDOW:])
    C = cov(np.linalg.norm(X[:, None, :] - X[None, :, :], axis=2)) + 1e-9 * np.eye(len(X))
    c = cov(np.linalg.norm(X - here, axis=1))
    w = np.linalg.solve(C, c)
    var = max(sigma_m**2 - float(c @ w), 0.0)
    return float(w @ y + math.sqrt(var) * rng.normal())


def simulate(seed: int, duration_s: float = DURATION_S, terrain_corr_m: float = 0.0,
             regional: tuple[float, float] | None = None) -> Truth:
    """Truth and sensor messages of one descent (no filter inside).

    The ground under the altimeter is at height ``h`` above z = 0, with ``h ~ N(0, TERRAIN_SIGMA_M^2)``: independent per sample when
    ``terrain_corr_m`` is 0, else an isotropic Gaussian field of Matern-3/2 covariance
    ``C(d) = TERRAIN_SIGMA_M^2 (1 + d / l) exp(-d / l)`` with ``l = terrain_corr_m``, sampled
    at each footprint conditionally on the last ``FIELD_WINDOW`` footprints' heights (the
    exact Gaussian conditional, not the filter's Markov recursion).

    ``regional = (sigma_m, length_m)`` adds a second, smoother Matern-3/2 field ``u``, taken about
    its value at the target: the ground is ``h + u(p) - u(0)`` higher. ``u(0)`` is drawn first and
    every later sample is conditioned on it as well as on the last footprints.
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * NS / IMU_DT_NS))
    dt = IMU_DT_NS / NS
    t_ns = np.arange(n + 1, dtype=np.int64) * IMU_DT_NS
    t = t_ns / NS
    r, v, a = _kinematics(t)
    rot = _attitude(t, a)

    # IMU sample k: mean specific force over (t_{k-1}, t_k] in B at the mid-interval attitude,
    # mean body rate over the interval; plus bias and white noise (sigma = density / sqrt(dt)).
    rotvec = (rot[:-1].inv() * rot[1:]).as_rotvec()  # (n, 3)
    rot_mid = rot[:-1] * Rotation.from_rotvec(0.5 * rotvec)
    f_mean_L = (v[1:] - v[:-1]) / dt - G_L
    bias = np.empty((n + 2, 3))
    bias[0] = rng.normal(0.0, ACC_BIAS_SIGMA, 3)
    bias[1:] = bias[0] + np.cumsum(rng.normal(0.0, ACC_BIAS_WALK * math.sqrt(dt), (n + 1, 3)), axis=0)
    f_B = rot_mid.inv().apply(f_mean_L) + bias[:n] + rng.normal(0.0, ACC_DENSITY / math.sqrt(dt), (n, 3))
    gyro_bias = rng.normal(0.0, GYRO_BIAS_SIGMA, 3)
    w_B = rotvec / dt + gyro_bias + rng.normal(0.0, GYRO_DENSITY / math.sqrt(dt), (n, 3))
    imu = [ImuMessage(int(t_ns[k + 1]), f_B[k], w_B[k]) for k in range(n)]
    # Sample k (k >= 1) used bias[k - 1]; after tick k the filter holds the bias of sample k + 1.
    bias_after = bias[: n + 1]

    star = {}
    for k in range(0, n + 1, ST_EVERY):
        err = Rotation.from_rotvec(rng.normal(0.0, ST_SIGMA_RAD, 3))
        star[k] = AttitudeMessage(int(t_ns[k]), (rot[k] * err).as_quat(canonical=True, scalar_first=True))

    alt = {}
    h, spots, heights = 0.0, [], []
    rspots, rheights = [np.zeros(2)], []
    if regional is not None:
        rheights.append(float(rng.normal(0.0, regional[0])))
    ground = 0.0
    for k in range(ALT_EVERY, n + 1, ALT_EVERY):
        R = rot[k].as_matrix()
        b_L = R @ BORESIGHT_B
        p_alt = r[k] + R @ LEVER_B
        here = p_alt[:2] + (p_alt[2] - ground) / -b_L[2] * b_L[:2]
        if terrain_corr_m == 0:
            h = rng.normal(0.0, TERRAIN_SIGMA_M)
        else:
            h = _field_sample(here, spots, heights, terrain_corr_m, rng)
            spots.append(here)
            heights.append(h)
        ground = h
        if regional is not None:
            u = _field_sample(here, rspots, rheights, regional[1], rng, sigma_m=regional[0], anchors=1)
            rspots.append(here)
            rheights.append(u)
            ground = h + u - rheights[0]
        rho = (p_alt[2] - ground) / -b_L[2]
        noise = rng.normal(0.0, math.hypot(ALT_FLOOR_M, ALT_FRAC * rho))
        if rng.random() < ALT_DROPOUT:
            alt[k] = AltimeterMessage(int(t_ns[k]), math.nan, False, BORESIGHT_B)
        else:
            alt[k] = AltimeterMessage(int(t_ns[k]), rho + noise, True, BORESIGHT_B)

    chol = np.linalg.cholesky(R_VEL)
    vel = {k: v[k] + chol @ rng.normal(size=3) for k in range(VEL_EVERY, n + 1, VEL_EVERY)}
    return Truth(t_ns, r, v, rot, imu, bias_after, star, alt, vel)


# The simulator's relief is white unless a test asks otherwise, so the filters under test
# model it as white too (the bench default, Matern-3/2 over 30 m, matches the rendered world's terrain).
WHITE_RELIEF = {"terrain_correlation_length_m": 0.0}


def start_filter(truth: Truth, seed: int, cfg=None, **factory) -> NavFilter:
    """Filter started the way the bench does it: estimate = truth + N(0, sigma) (``factory``: more
    keywords of make_estimator)."""
    cfg = {**SIM_SPEC, **WHITE_RELIEF, **(cfg or {})}
    c = EstimatorConfig.model_validate(cfg)
    rng = np.random.default_rng(10_000 + seed)
    r0 = truth.r[0] + rng.normal(0.0, c.init_pos_sigma_m, 3)
    v0 = truth.v[0] + rng.normal(0.0, c.init_vel_sigma_mps, 3)
    nav = make_estimator(cfg, r0, v0, 0, altimeter_mount_B_m=LEVER_B, **factory)
    nav.set_attitude(truth.star[0])
    return nav


@dataclass
class RunStats:
    nees6: np.ndarray  # at 10 Hz
    nees9: np.ndarray
    nees_z: np.ndarray  # the height's (1 dof), at 10 Hz
    err_v_final: np.ndarray  # (3,)
    sig_v_final: np.ndarray  # (3,)
    nis_alt: np.ndarray
    nis_vel: np.ndarray
    nav: NavFilter


def run_filter(truth: Truth, nav: NavFilter, use_velocity: bool) -> RunStats:
    """Feed every message in time order; NEES at 10 Hz after the updates."""
    nees6, nees9, nees_z = [], [], []
    for k in range(1, len(truth.t_ns)):
        nav.propagate_imu(truth.imu[k - 1])
        if k in truth.star:
            nav.set_attitude(truth.star[k])
        if k in truth.alt:
            nav.update_altimeter(truth.alt[k])
        if use_velocity and k in truth.vel:
            nav.update_velocity(int(truth.t_ns[k]), truth.vel[k], R_VEL)
        if k % VEL_EVERY == 0:
            e = nav.ekf.x[:9] - np.concatenate([truth.r[k], truth.v[k], truth.bias_after[k]])
            P = nav.ekf.P[:9, :9]
            nees6.append(e[:6] @ np.linalg.solve(P[:6, :6], e[:6]))
            nees9.append(e @ np.linalg.solve(P, e))
            nees_z.append(e[2] * e[2] / P[2, 2])
    nis = {kind: np.array([r.nis for r in nav.log if r.kind == kind and r.accepted]) for kind in ("altimeter", "velocity")}
    return RunStats(
        np.array(nees6), np.array(nees9), np.array(nees_z), nav.ekf.x[3:6] - truth.v[-1], np.sqrt(np.diag(nav.ekf.P)[3:6]),
        nis["altimeter"], nis["velocity"], nav,
    )


@pytest.fixture(scope="module")
def campaign() -> dict[bool, list[RunStats]]:
    """N_SEEDS descents, each filtered with and without the velocity updates."""
    out: dict[bool, list[RunStats]] = {True: [], False: []}
    for seed in range(N_SEEDS):
        truth = simulate(seed)
        for use_vel in (True, False):
            out[use_vel].append(run_filter(truth, start_filter(truth, seed), use_vel))
    return out


# --------------------------------------------------------------------------- consistency and accuracy
def test_nees_is_consistent_over_seeds(campaign):
    runs = campaign[True]
    for dof, key in ((6, "nees6"), (9, "nees9")):
        nees = np.concatenate([getattr(r, key) for r in runs])
        lo, hi = chi2.ppf((1 - NEES_BAND_PROB) / 2, dof), chi2.ppf((1 + NEES_BAND_PROB) / 2, dof)
        inside = np.mean((nees >= lo) & (nees <= hi))
        assert inside >= 0.9, f"{dof}-dof NEES inside the 95% band only {inside:.3f} of the time"
        # Pooled mean within 20 % of dof (errors are strongly correlated in time, so the
        # effective sample is a few dozen: +-20 % is a loose but meaningful check).
        assert abs(nees.mean() / dof - 1) < 0.2, f"mean {dof}-dof NEES {nees.mean():.2f}"


@pytest.mark.parametrize("use_velocity", [True, False])
def test_final_nees_summed_over_seeds_is_chi_square(campaign, use_velocity):
    # The seeds are independent, so the sum of their final NEES is chi-square with
    # N_SEEDS * dof degrees of freedom. This is the check that also holds without vision,
    # where the horizontal error is nearly constant in time (so a fraction of time steps in
    # the band is, in effect, a fraction of only N_SEEDS draws).
    runs = campaign[use_velocity]
    for dof, key in ((6, "nees6"), (9, "nees9")):
        total = sum(getattr(r, key)[-1] for r in runs)
        lo, hi = chi2.ppf([0.005, 0.995], N_SEEDS * dof)
        assert lo < total < hi, f"sum of final {dof}-dof NEES {total:.1f} outside [{lo:.1f}, {hi:.1f}]"


def test_nis_averages_match_measurement_dimension(campaign):
    runs = campaign[True]
    nis_alt = np.concatenate([r.nis_alt for r in runs])
    nis_vel = np.concatenate([r.nis_vel for r in runs])
    assert len(nis_alt) > 5000 and len(nis_vel) > 5000
    # Thousands of nearly independent innovations: the means are tight around 1 and 3.
    assert abs(nis_alt.mean() - 1.0) < 0.1, nis_alt.mean()
    assert abs(nis_vel.mean() - 3.0) < 0.2, nis_vel.mean()
    # Consistent measurements are almost never gated out (gate_prob 0.999).
    for r in runs:
        counts = r.nav.counters
        assert counts["velocity"]["rejected"] <= 3
        assert counts["altimeter"]["rejected"] <= 6
        assert counts["altimeter"]["skipped"] > 0  # the dropouts


def test_velocity_updates_make_horizontal_velocity_observable(campaign):
    sig_meas = np.sqrt(np.diag(R_VEL))
    with_vel = np.array([r.err_v_final for r in campaign[True]])
    without = np.array([r.err_v_final for r in campaign[False]])
    # With vision: the final velocity error is below the measurement sigma (RMS over seeds).
    rms_with = np.sqrt(np.mean(with_vel**2, axis=0))
    assert np.all(rms_with < sig_meas), (rms_with, sig_meas)
    # Without: the altimeter fixes the vertical channel but not the horizontal one, whose
    # error stays at the initial 1 m/s sigma; the filter knows it.
    rms_h_without = np.sqrt(np.mean(without[:, :2] ** 2))
    assert 0.5 < rms_h_without < 1.6, rms_h_without
    sig_h_without = np.array([r.sig_v_final[:2] for r in campaign[False]])
    assert np.all((sig_h_without > 0.9) & (sig_h_without < 1.1))
    assert np.sqrt(np.mean(without[:, 2] ** 2)) < 0.3
    assert np.sqrt(np.mean(with_vel[:, :2] ** 2)) < 0.15 * rms_h_without


TERRAIN_CORR_M = 30.0  # correlation length of the relief in the correlated-terrain campaign [m]
N_SEEDS_CORRELATED = 6


def test_correlated_terrain_needs_the_terrain_state():
    # Relief correlated along the track is a slowly varying altimeter bias. Treated as white
    # (terrain_correlation_length_m = 0) it is averaged away and the vertical channel becomes
    # overconfident; the Gauss-Markov terrain state with the right length stays consistent.
    runs: dict[float, list[RunStats]] = {0.0: [], TERRAIN_CORR_M: []}
    for seed in range(N_SEEDS_CORRELATED):
        truth = simulate(seed, terrain_corr_m=TERRAIN_CORR_M)
        for length in runs:
            nav = start_filter(truth, seed, {"terrain_correlation_length_m": length})
            runs[length].append(run_filter(truth, nav, use_velocity=True))
    nees_gm = np.concatenate([r.nees6 for r in runs[TERRAIN_CORR_M]])
    lo, hi = chi2.ppf([(1 - NEES_BAND_PROB) / 2, (1 + NEES_BAND_PROB) / 2], 6)
    assert np.mean((nees_gm >= lo) & (nees_gm <= hi)) >= 0.9
    assert abs(nees_gm.mean() / 6 - 1) < 0.2, nees_gm.mean()
    nis_alt = np.concatenate([r.nis_alt for r in runs[TERRAIN_CORR_M]])
    assert abs(nis_alt.mean() - 1.0) < 0.1, nis_alt.mean()
    nees_white = np.concatenate([r.nees6 for r in runs[0.0]])
    assert nees_white.mean() > 5 * 6, nees_white.mean()


REGIONAL = (2.5, 150.0)  # the regional field of the regional-relief campaign: 1-sigma, length [m]


def _vertical_anees(regional_relief: bool, truths: dict[int, Truth]) -> np.ndarray:
    """Mean over seeds of the height's NEES (1 dof) at 10 Hz, over ground that carries a regional field
    (``truths``: each seed's descent, flown by both filters)."""
    cfg = {"terrain_correlation_length_m": TERRAIN_CORR_M,
           "regional_relief_sigma_m": REGIONAL[0], "regional_relief_length_m": REGIONAL[1]}
    out = []
    for seed, truth in truths.items():
        nav = start_filter(truth, seed, cfg, map_bias_sigma_m=1.0, regional_relief=regional_relief)
        out.append(run_filter(truth, nav, use_velocity=True).nees_z)
    return np.mean(out, axis=0)


def test_regional_relief_keeps_the_height_consistent_over_ground_correlated_with_the_target():
    # The ground about the target's elevation is a local Matern field plus a smooth regional one taken
    # about its value at the target (what site selection leaves: it clears craters, not the regional
    # slope). A filter that models only the local field averages the regional offset as if each 30 m
    # brought new ground, and its height is overconfident for the whole descent; with the regional
    # states it stays consistent. (A diagnostic of this kind on the rendered world, case by case, is
    # what found it: errors of 1-3 m under a 0.5-0.8 m sigma.)
    truths = {seed: simulate(seed, terrain_corr_m=TERRAIN_CORR_M, regional=REGIONAL) for seed in range(6)}
    local_only = _vertical_anees(False, truths)
    both = _vertical_anees(True, truths)
    half = local_only.size // 2
    assert local_only[half:].mean() > 2.5, local_only[half:].mean()
    assert 0.3 < both[half:].mean() < 1.6, both[half:].mean()
    assert 0.3 < both.mean() < 2.0, both.mean()


def test_regional_relief_prior_is_the_fields_covariance():
    """The (u, grad u, u(0)) prior against finite differences of the Matern-3/2 covariance, and the height it adds."""
    from gnc.estimator import regional_relief_prior

    cfg = EstimatorConfig(regional_relief_sigma_m=2.0, regional_relief_length_m=120.0)
    s, length = 2.0, 120.0

    def C(d):
        return s * s * (1.0 + d / length) * np.exp(-d / length)

    p = np.array([90.0, -40.0])
    P = regional_relief_prior(cfg, p)
    eps = 1e-3
    ex, ey = np.array([eps, 0.0]), np.array([0.0, eps])
    ref = np.empty((4, 4))
    ref[0, 0] = ref[3, 3] = C(0.0)
    ref[0, 3] = C(np.linalg.norm(p))
    # cov(grad u(p), u(0)) by central differences of cov(u(p +- e), u(0)).
    ref[1, 3] = (C(np.linalg.norm(p + ex)) - C(np.linalg.norm(p - ex))) / (2 * eps)
    ref[2, 3] = (C(np.linalg.norm(p + ey)) - C(np.linalg.norm(p - ey))) / (2 * eps)
    # var of the slope: var((u(p+e) - u(p-e)) / 2e) = (2 C(0) - 2 C(2e)) / 4e^2; at one place slope and height
    # are independent, and so are the two slope axes.
    ref[1, 1] = ref[2, 2] = (2 * C(0.0) - 2 * C(2 * eps)) / (4 * eps * eps)
    ref[0, 1] = ref[0, 2] = ref[1, 2] = 0.0
    ref = np.triu(ref) + np.triu(ref, 1).T
    np.testing.assert_allclose(P, ref, rtol=1e-4, atol=1e-9)
    assert np.linalg.eigvalsh(P).min() > 0.0
    # The height above the target's elevation it adds, u(p) - u(0): none at the target, 2 (s^2 - C) away from it.
    a = np.array([1.0, 0.0, 0.0, -1.0])
    assert a @ P @ a == pytest.approx(2 * (C(0.0) - C(np.linalg.norm(p))))
    assert a @ regional_relief_prior(cfg, np.zeros(2)) @ a == pytest.approx(0.0, abs=1e-12)


def test_altimeter_update_with_the_regional_relief_is_the_textbook_update():
    # Two ranges 10 m apart: the step moves the local field (Matern, site-scaled) and the regional field (its
    # own Matern) over the same displacement, u(0) stays; the range reads r_z - h - u + u(0).
    from gnc.estimator import IDX_RR, IDX_RR0, matern32_terrain_step

    cfg = {**SIM_SPEC, "terrain_correlation_length_m": 20.0, "regional_relief_sigma_m": 2.0,
           "regional_relief_length_m": 100.0}
    nav = make_estimator(cfg, [40.0, 10.0, 100.0], [0, 0, 0], 0, [1, 0, 0, 0], altimeter_mount_B_m=LEVER_B,
                         map_bias_sigma_m=1.0, regional_relief=True)
    assert nav.dim_x == 31 and nav.has_map_bias
    rho = 100.0 + LEVER_B[2] + 0.7
    assert nav.update_altimeter(AltimeterMessage(0, rho, True, BORESIGHT_B)).accepted
    x0, P0 = nav.ekf.x.copy(), nav.ekf.P.copy()
    x0[0] += 10.0  # the lander (and the footprint) 10 m east
    nav.ekf.x = x0.copy()
    F_l, Q_l = matern32_terrain_step(np.array([10.0, 0.0]), 3.0, 20.0)
    F_r, Q_r = matern32_terrain_step(np.array([10.0, 0.0]), 2.0, 100.0)
    idx = [9, 20, 21, 27, 28, 29]
    T = np.eye(31)
    T[np.ix_(idx[:3], idx[:3])] = F_l
    T[np.ix_(idx[3:], idx[3:])] = F_r
    P = T @ P0 @ T.T
    P[np.ix_(idx[:3], idx[:3])] += Q_l
    P[np.ix_(idx[3:], idx[3:])] += Q_r
    x = T @ x0
    H = np.zeros(31)
    H[2], H[9], H[IDX_RR], H[IDX_RR0] = 1.0, -1.0, -1.0, 1.0
    rho_hat = x[2] + LEVER_B[2] - x[9] - x[IDX_RR] + x[IDX_RR0]
    r_var = ALT_FLOOR_M**2 + (ALT_FRAC * rho_hat) ** 2
    rec = nav.update_altimeter(AltimeterMessage(0, rho + 0.4, True, BORESIGHT_B))
    assert rec.accepted
    S = H @ P @ H + r_var
    assert rec.S[0, 0] == pytest.approx(S, rel=1e-9)
    assert rec.y[0] == pytest.approx(rho + 0.4 - rho_hat, abs=1e-9)
    K = P @ H / S
    np.testing.assert_allclose(nav.ekf.x, x + K * (rho + 0.4 - rho_hat), atol=1e-9)
    np.testing.assert_allclose(nav.ekf.P, P - np.outer(K, H @ P), rtol=1e-6, atol=1e-10)
    # It needs the map's states (the regional ones follow them).
    with pytest.raises(ValueError, match="map_bias_sigma_m"):
        make_estimator(cfg, [0, 0, 100.0], [0, 0, 0], 0, altimeter_mount_B_m=LEVER_B, regional_relief=True)


# --------------------------------------------------------------------------- gating
@pytest.fixture(scope="module")
def _converged_once() -> tuple[Truth, NavFilter]:
    truth = simulate(99, duration_s=20.0)
    nav = start_filter(truth, 99)
    run_filter(truth, nav, use_velocity=True)
    return truth, nav


@pytest.fixture
def converged(_converged_once) -> tuple[Truth, NavFilter]:
    """A filter after 20 s of the descent, with every update: each test gets its own copy to change.

    (The copy's arrays are writeable again: read the original, ``_converged_once``, for
    checks of the filter's own read-only records.)
    """
    truth, nav = _converged_once
    return truth, copy.deepcopy(nav)


def _assert_unchanged(nav: NavFilter, x: np.ndarray, P: np.ndarray) -> None:
    np.testing.assert_array_equal(nav.ekf.x, x)
    np.testing.assert_array_equal(nav.ekf.P, P)


def test_outlier_velocity_is_rejected_and_leaves_state_unchanged(converged):
    truth, nav = converged
    x, P = nav.x, nav.P
    rec = nav.update_velocity(nav.time_ns, truth.v[-1] + [20.0, 0.0, 0.0], R_VEL)
    assert not rec.accepted and rec.reason == "gate" and rec.nis > 1e3
    _assert_unchanged(nav, x, P)
    np.testing.assert_array_equal(rec.x_post, x)
    assert nav.log[-1] is rec


def test_altimeter_blunder_is_rejected_and_leaves_state_unchanged(converged):
    truth, nav = converged
    R = truth.rot[-1].as_matrix()
    rho = (truth.r[-1, 2] + R[2] @ LEVER_B) / -(R @ BORESIGHT_B)[2]
    x, P = nav.x, nav.P
    rejected_before = nav.counters["altimeter"]["rejected"]
    rec = nav.update_altimeter(AltimeterMessage(nav.time_ns, rho + 200.0, True, BORESIGHT_B))
    assert not rec.accepted and rec.reason == "gate" and rec.nis > 1e3
    assert nav.counters["altimeter"]["rejected"] == rejected_before + 1
    _assert_unchanged(nav, x, P)
    # The same range without the blunder passes.
    assert nav.update_altimeter(AltimeterMessage(nav.time_ns, rho, True, BORESIGHT_B)).accepted


def test_burst_of_bad_velocities_does_not_diverge_the_filter():
    truth = simulate(7, duration_s=30.0)
    nav = start_filter(truth, 7)
    rng = np.random.default_rng(1)
    bad_ticks = set(range(100 * VEL_EVERY, 120 * VEL_EVERY, VEL_EVERY))  # 20 in a row, from 10 s
    nees = []
    for k in range(1, len(truth.t_ns)):
        nav.propagate_imu(truth.imu[k - 1])
        if k in truth.star:
            nav.set_attitude(truth.star[k])
        if k in truth.alt:
            nav.update_altimeter(truth.alt[k])
        if k in truth.vel:
            z = truth.vel[k]
            if k in bad_ticks:
                d = rng.normal(size=3)
                z = z + 20.0 * d / np.linalg.norm(d)
            rec = nav.update_velocity(int(truth.t_ns[k]), z, R_VEL)
            if k in bad_ticks:
                assert not rec.accepted and rec.nis > 1e3
        if k % VEL_EVERY == 0 and k > 120 * VEL_EVERY:
            e = nav.ekf.x[:6] - np.concatenate([truth.r[k], truth.v[k]])
            nees.append(e @ np.linalg.solve(nav.ekf.P[:6, :6], e))
    assert 20 <= nav.counters["velocity"]["rejected"] <= 22  # the burst, and at most a rare good one
    assert nav.consecutive_rejections["velocity"] == 0  # good data was taken again
    assert np.mean(nees) < 12.0
    assert np.linalg.norm(nav.ekf.x[3:6] - truth.v[-1]) < 0.5


# --------------------------------------------------------------------------- prediction
def _imu(k: int, f_B, w_B=(0.0, 0.0, 0.0)) -> ImuMessage:
    return ImuMessage(k * IMU_DT_NS, np.asarray(f_B, float), np.asarray(w_B, float))


def test_prediction_matches_closed_form_constant_acceleration():
    q = Rotation.from_euler("xyz", [10.0, -20.0, 35.0], degrees=True)
    f_B = np.array([0.3, -0.2, 2.5])
    a_L = q.apply(f_B) + G_L
    r0, v0 = np.array([-100.0, 50.0, 400.0]), np.array([5.0, -3.0, -20.0])
    nav = make({"init_accel_bias_sigma_mps2": 1e-3}, r0, v0, 0, q0_LB=q.as_quat(scalar_first=True))
    n = 1000
    for k in range(1, n + 1):
        assert nav.propagate_imu(_imu(k, f_B))
    t = n * IMU_DT_NS / NS
    np.testing.assert_allclose(nav.x[:3], r0 + v0 * t + 0.5 * a_L * t**2, rtol=1e-9)
    np.testing.assert_allclose(nav.x[3:6], v0 + a_L * t, rtol=1e-9)
    assert nav.time_ns == n * IMU_DT_NS


def test_covariance_and_rotating_prediction_match_an_explicit_loop():
    cfg = EstimatorConfig()
    q0 = Rotation.from_euler("xyz", [5.0, 3.0, -40.0], degrees=True)
    w_B = np.array([0.02, -0.01, 0.05])  # [rad/s]
    f_B = np.array([0.1, 0.2, 2.0])
    r0, v0 = np.array([10.0, 20.0, 300.0]), np.array([1.0, 2.0, -10.0])
    nav = make(cfg, r0, v0, 0, q0_LB=q0.as_quat(scalar_first=True))
    n, dt = 300, IMU_DT_NS / NS
    # Independent recursion: mid-interval attitude by scipy, F and Q written out.
    # State: r, v, b_a, h_terrain, then the position clone (r0), two image offsets, the flow bias,
    # the viewed ground's height, the terrain's slope and the viewed ground's slope.
    x = np.concatenate([r0, v0, np.zeros(4), r0, np.zeros(11)])
    P = initial_covariance(cfg, 300.0, r0[:2])  # the site map's relief where the filter starts
    assert x.shape == (24,) and P.shape == (24, 24)
    att_psd = cfg.accel_noise_density**2 + (math.radians(cfg.attitude_sigma_arcsec / 3600)
                                             * np.linalg.norm(f_B)) ** 2 * cfg.attitude_period_s
    I3 = np.eye(3)
    for k in range(1, n + 1):
        R = (q0 * Rotation.from_rotvec(w_B * (k - 0.5) * dt)).as_matrix()
        F = np.eye(24)  # the clone, the offsets and the ground's heights and slope do not move between updates
        F[0:3, 3:6] = dt * I3
        F[0:3, 6:9] = -0.5 * dt**2 * R
        F[3:6, 6:9] = -dt * R
        Q = np.zeros((24, 24))
        Q[0:3, 0:3] = att_psd * dt**3 / 4 * I3
        Q[0:3, 3:6] = Q[3:6, 0:3] = att_psd * dt**2 / 2 * I3
        Q[3:6, 3:6] = att_psd * dt * I3
        Q[6:9, 6:9] = cfg.accel_bias_walk**2 * dt * I3
        a = R @ (f_B - x[6:9]) + G_L
        x = np.concatenate([x[0:3] + x[3:6] * dt + 0.5 * a * dt**2, x[3:6] + a * dt, x[6:]])
        P = F @ P @ F.T + Q
        nav.propagate_imu(_imu(k, f_B, w_B))
    np.testing.assert_allclose(nav.x, x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(nav.P, P, rtol=1e-9, atol=1e-15)
    q_end = q0 * Rotation.from_rotvec(w_B * n * dt)
    np.testing.assert_allclose(Rotation.from_quat(nav.q_LB, scalar_first=True).as_matrix(), q_end.as_matrix(),
                               atol=1e-12)
    # With no fix after the first, the gyro-only attitude is the same integral.
    np.testing.assert_allclose(Rotation.from_quat(nav.gyro_attitude(), scalar_first=True).as_matrix(),
                               q_end.as_matrix(), atol=1e-12)


def test_integrating_gyro_samples_compose_to_the_product_of_their_rotations():
    # An integrating gyro's sample k is its interval's delta-angle / dt: the rotation over the interval is
    # exp(w_k dt), whatever the rate did inside it. With gyro_delta_angle the filter's attitudes are the
    # product of those rotations; the trapezoid of consecutive samples (a point-sampling gyro) is not.
    rng = np.random.default_rng(12)
    q0 = Rotation.from_euler("xyz", [5.0, -8.0, 30.0], degrees=True)
    w = rng.normal(0.0, 0.05, size=(40, 3))  # a different mean rate every interval [rad/s]
    dt = IMU_DT_NS / 1e9
    truth = q0
    for w_k in w:
        truth = truth * Rotation.from_rotvec(w_k * dt)
    ends = {}
    for delta_angle in (True, False):
        nav = make_estimator({}, np.zeros(3), np.zeros(3), 0, q0.as_quat(scalar_first=True),
                             altimeter_mount_B_m=LEVER_B, gyro_delta_angle=delta_angle)
        for k, w_k in enumerate(w, start=1):
            assert nav.propagate_imu(_imu(k, [0.0, 0.0, 1.62], w_k))
        ends[delta_angle] = [Rotation.from_quat(q, scalar_first=True) for q in (nav.q_LB, nav.gyro_attitude())]
    for q in ends[True]:
        assert (truth.inv() * q).magnitude() < 1e-12
    assert (truth.inv() * ends[False][0]).magnitude() > 1e-6  # the trapezoid rotates by other angles


def test_quat_to_matrix_matches_scipy():
    rng = np.random.default_rng(3)
    for q in Rotation.random(20, random_state=rng).as_quat(scalar_first=True):
        np.testing.assert_allclose(quat_to_matrix(tuple(q)),
                                   Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=1e-14)


def test_hold_mode_keeps_the_last_fix():
    q0 = Rotation.from_euler("z", 30.0, degrees=True).as_quat(scalar_first=True)
    nav = make({"attitude_propagation": "hold"}, [0, 0, 100.0], [0, 0, 0], 0, q0_LB=q0)
    for k in range(1, 11):
        nav.propagate_imu(_imu(k, [0, 0, G], [0.0, 0.0, 0.5]))
    np.testing.assert_allclose(nav.q_LB, q0)


def test_measurement_time_offset_is_predicted_with_velocity():
    # An altimeter sample 10 ms ahead of the filter (it arrived before that tick's IMU sample).
    nav = make(None, [0, 0, 100.0], [0, 0, -20.0], 0, q0_LB=[1, 0, 0, 0])
    rho = 100.0 - 20.0 * 0.01 + LEVER_B[2]
    rec = nav.update_altimeter(AltimeterMessage(IMU_DT_NS, rho, True, BORESIGHT_B))
    assert rec.accepted and abs(rec.y[0]) < 1e-9
    # Beyond max_update_lag_s it is refused, and the state is unchanged.
    x = nav.x
    rec = nav.update_altimeter(AltimeterMessage(NS, rho, True, BORESIGHT_B))
    assert not rec.accepted and rec.reason == "stale"
    np.testing.assert_array_equal(nav.x, x)
    # A velocity stamped 30 ms behind the filter is predicted with the last acceleration.
    f_B = np.array([0.5, 0.0, 2.0])
    assert nav.propagate_imu(_imu(1, f_B))
    a_L = f_B + G_L  # identity attitude, zero bias estimate
    z = nav.x[3:6] - a_L * 0.03
    rec = nav.update_velocity(nav.time_ns - 30_000_000, z, 1e-4 * np.eye(3))
    assert rec.accepted
    np.testing.assert_allclose(rec.y, 0.0, atol=1e-6)


def test_oblique_boresight_is_skipped():
    tilt = Rotation.from_euler("x", 65.0, degrees=True).as_quat(scalar_first=True)
    nav = make(None, [0, 0, 100.0], [0, 0, 0], 0, q0_LB=tilt)
    assert nav.update_altimeter(AltimeterMessage(0, 240.0, True, BORESIGHT_B)) is None
    assert nav.counters["altimeter"]["skipped"] == 1 and not nav.log


# --------------------------------------------------------------------------- inputs, outputs and bookkeeping
@pytest.mark.parametrize(
    "cfg, field",
    [
        ({"init_pos_sigma_m": -1.0}, "estimator.init_pos_sigma_m"),
        ({"gate_prob": 1.5}, "estimator.gate_prob"),
        ({"accel_noise_density": float("nan")}, "estimator.accel_noise_density"),
        ({"attitude_propagation": "magic"}, "estimator.attitude_propagation"),
        ({"no_such_knob": 1}, "estimator.no_such_knob"),
    ],
)
def test_bad_config_is_a_one_line_error_naming_the_field(cfg, field):
    with pytest.raises(ValueError) as exc:
        make(cfg, [0, 0, 100.0], [0, 0, 0], 0)
    msg = str(exc.value)
    assert field in msg and "\n" not in msg


@pytest.mark.parametrize(
    "r0, v0, t0, q0, field",
    [
        ([0, 0], [0, 0, 0], 0, None, "x0_r_L"),
        ([0, 0, 100.0], [0, math.nan, 0], 0, None, "x0_v_L"),
        ([0, 0, 100.0], [0, 0, 0], 1.5, None, "t0_ns"),
        ([0, 0, 100.0], [0, 0, 0], 0, [2.0, 0, 0, 0], "q0_LB"),
    ],
)
def test_bad_initial_state_is_a_one_line_error_naming_it(r0, v0, t0, q0, field):
    with pytest.raises(ValueError, match=field):
        make(None, r0, v0, t0, q0_LB=q0)


def test_bad_altimeter_mount_is_a_one_line_error_naming_it():
    with pytest.raises(ValueError, match="altimeter_mount_B_m") as exc:
        make(None, [0, 0, 100.0], [0, 0, 0], 0, mount=(0.0, 0.0))
    assert "\n" not in str(exc.value)


def test_nan_messages_are_rejected_and_counted():
    nav = make(None, [0, 0, 100.0], [1, 0, -5.0], 0, q0_LB=[1, 0, 0, 0])
    assert nav.propagate_imu(_imu(1, [0, 0, G]))
    x, P, t = nav.x, nav.P, nav.time_ns
    assert not nav.propagate_imu(_imu(2, [0, math.nan, G]))
    assert not nav.set_attitude(AttitudeMessage(t, np.array([math.nan, 0, 0, 1.0])))
    rec_a = nav.update_altimeter(AltimeterMessage(t, math.nan, True, BORESIGHT_B))
    rec_v = nav.update_velocity(t, [1.0, math.inf, 0.0], np.eye(3))
    assert not rec_a.accepted and rec_a.reason == "nonfinite"
    assert not rec_v.accepted and rec_v.reason == "nonfinite"
    _assert_unchanged(nav, x, P)
    assert nav.time_ns == t
    c = nav.counters
    assert (c["imu"]["invalid"], c["attitude"]["invalid"], c["altimeter"]["invalid"], c["velocity"]["invalid"]) == (
        1, 1, 1, 1)
    # A dropout (valid False) is not an error: skipped, no record.
    assert nav.update_altimeter(AltimeterMessage(t, math.nan, False, BORESIGHT_B)) is None
    assert c["altimeter"]["skipped"] == 1 and len(nav.log) == 2
    # A non-positive-definite velocity covariance is refused too.
    assert nav.update_velocity(t, [1.0, 0.0, -5.0], -np.eye(3)).reason == "invalid_covariance"
    with pytest.raises(ValueError, match="z_v_L"):
        nav.update_velocity(t, [1.0, 0.0], np.eye(3))


def test_old_or_repeated_imu_samples_are_not_propagated_twice():
    nav = make(None, [0, 0, 100.0], [1, 0, -5.0], 0, q0_LB=[1, 0, 0, 0])
    assert nav.propagate_imu(_imu(2, [0, 0, G]))
    x = nav.x
    assert not nav.propagate_imu(_imu(2, [0, 0, G]))
    assert not nav.propagate_imu(_imu(1, [0, 0, G]))
    np.testing.assert_array_equal(nav.x, x)
    assert nav.counters["imu"] == {"used": 1, "stale": 2, "invalid": 0, "no_attitude": 0}


def test_no_propagation_before_the_first_attitude():
    nav = make(None, [0, 0, 100.0], [1, 0, -5.0], 0)
    assert not nav.propagate_imu(_imu(1, [0, 0, G]))
    assert nav.time_ns == 0 and nav.counters["imu"]["no_attitude"] == 1
    assert not np.all(np.isfinite(nav.nav_state(2000.0).q_LB))
    assert nav.set_attitude(AttitudeMessage(0, np.array([1.0, 0, 0, 0])))
    assert nav.propagate_imu(_imu(2, [0, 0, G]))


def test_nav_state_and_records(_converged_once):
    truth, nav = _converged_once  # read only
    ns = nav.nav_state(1800.0)
    assert isinstance(ns, NavState) and ns.is_finite()
    assert ns.t_ns == nav.time_ns == truth.t_ns[-1]
    np.testing.assert_array_equal(ns.r_BL_L, nav.ekf.x[:3])
    np.testing.assert_array_equal(ns.P, nav.ekf.P[:6, :6])
    np.testing.assert_array_equal(ns.omega_B, truth.imu[-1].omega_B)
    angle = (Rotation.from_quat(ns.q_LB, scalar_first=True).inv() * truth.rot[-1]).magnitude()
    assert angle < 10 * ST_SIGMA_RAD
    rec = next(r for r in nav.log if r.accepted and r.kind == "velocity")
    assert rec.z.shape == rec.y.shape == (3,) and rec.S.shape == (3, 3) and rec.P_post.shape == (24, 24)
    assert not rec.x_post.flags.writeable  # records are immutable
    assert np.all(np.diag(rec.P_post)[3:6] < np.diag(rec.P_prior)[3:6])


def test_filter_is_a_filterpy_ekf():
    nav = make(None, [0, 0, 100.0], [0, 0, 0], 0)
    assert isinstance(nav.ekf, ExtendedKalmanFilter)
    assert nav.ekf.x.shape == (24,) and nav.ekf.P.shape == (24, 24)


def test_flight_computer_names_and_altimeter_sigma():
    nav = make(None, [0, 0, 100.0], [0, 0, 0], 0)
    assert nav.update_attitude(AttitudeMessage(0, np.array([1.0, 0, 0, 0])))
    assert nav.predict_imu(_imu(1, [0, 0, G])) and nav.time_ns == IMU_DT_NS
    # Spec hypot(0.08, 1e-3 * range), plus the default 4 m relief over the cosine.
    assert nav.altimeter_sigma_m(400.0, include_relief=False) == pytest.approx(math.hypot(0.08, 0.4))
    assert nav.altimeter_sigma_m(400.0, 0.5) == pytest.approx(math.sqrt(0.08**2 + 0.4**2 + 8.0**2))


def _matern32_step_reference(d_xy, sigma, length):
    """(F, Q) of the terrain's (h, dh/dx, dh/dy) over d_xy, from the Matern-3/2 SDE itself.

    Along the track, (h, g_u)' = A (h, g_u) + (0, w) with A = [[0, 1], [-lam^2, -2 lam]] and
    white noise of density 4 lam^3 sigma^2 (the SDE whose stationary covariance is
    sigma^2 (1 + lam d) exp(-lam d)); across it, g_p' = -lam g_p + w_p, stationary at
    (lam sigma)^2. Phi by scipy's expm, Q by Van Loan's method.
    """
    from scipy.linalg import expm
    lam, s = 1.0 / length, float(np.hypot(*d_xy))
    A = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -lam]])
    A[:2, :2] = [[0.0, 1.0], [-lam * lam, -2.0 * lam]]
    W = np.diag([0.0, 4.0 * lam**3 * sigma**2, 2.0 * lam * (lam * sigma) ** 2])
    M = expm(np.block([[-A, W], [np.zeros((3, 3)), A.T]]) * s)
    phi = M[3:, 3:].T
    Q = phi @ M[:3, 3:]
    u = np.asarray(d_xy, float) / s
    T = np.array([[1.0, 0, 0], [0, u[0], u[1]], [0, -u[1], u[0]]])
    return T.T @ phi @ T, T.T @ Q @ T


@pytest.mark.parametrize("d_xy", [(10.0, 0.0), (6.0, 8.0), (-0.3, 0.05), (-40.0, -25.0), (0.0, 120.0)])
def test_matern32_step_closed_form_equals_the_sde(d_xy):
    """The filter's closed-form (F, Q) against the matrix exponential and Van Loan's integral of the SDE."""
    from gnc.estimator import matern32_terrain_step

    F, Q = matern32_terrain_step(np.array(d_xy), 3.0, 30.0)
    F_ref, Q_ref = _matern32_step_reference(d_xy, 3.0, 30.0)
    np.testing.assert_allclose(F, F_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-7, atol=1e-12)
    np.testing.assert_array_equal(Q, Q.T)


def test_terrain_state_is_carried_between_footprints():
    # Two ranges whose footprints lie 10 m apart (east, then north-east), with a 10 m length:
    # the updates' innovation covariances use the Matern-3/2 step on the height and the slope,
    # checked against the SDE's matrix exponential (not the filter's closed form).
    length, sigma_t = 10.0, 3.0
    cfg = {**SIM_SPEC, "terrain_correlation_length_m": length, "terrain_relief_sigma_m": sigma_t}
    nav = make(cfg, [0, 0, 100.0], [0, 0, 0], 0, q0_LB=[1, 0, 0, 0])
    rho = 100.0 + LEVER_B[2]
    rec = nav.update_altimeter(AltimeterMessage(0, rho, True, BORESIGHT_B))
    assert rec.accepted
    idx = [9, 20, 21]
    H = np.zeros(24)
    H[2], H[9] = 1.0, -1.0
    for step in ([10.0, 0.0], [6.0, 8.0]):
        x = nav.ekf.x.copy()
        x[:2] += step  # move the lander (and the footprint)
        nav.ekf.x = x
        P_before = rec.P_post.copy() if step[1] == 0 else nav.ekf.P.copy()
        x_before = nav.ekf.x.copy()
        F, Q = _matern32_step_reference(step, sigma_t, length)
        T = np.eye(24)
        T[np.ix_(idx, idx)] = F
        P = T @ P_before @ T.T
        P[np.ix_(idx, idx)] += Q
        new = nav.update_altimeter(AltimeterMessage(0, rho, True, BORESIGHT_B))
        rho_hat = x[2] + LEVER_B[2] - (T @ x_before)[9]
        spec_var = ALT_FLOOR_M**2 + (ALT_FRAC * rho_hat) ** 2
        assert new.S[0, 0] == pytest.approx(H @ P @ H + spec_var, rel=1e-9)
        assert new.y[0] == pytest.approx(rho - rho_hat, abs=1e-9)
        # The posterior on the terrain states (the record's prior is the one before the step).
        k = P @ H / (H @ P @ H + spec_var)
        P_post = P - np.outer(k, H @ P)
        np.testing.assert_allclose(new.P_post[np.ix_(idx, idx)], P_post[np.ix_(idx, idx)], rtol=1e-7, atol=1e-12)
        rec = new
    # The slope's prior: sigma / length per axis, so the relief 1 m away differs by about that.
    P0 = make(cfg, [0, 0, 100.0], [0, 0, 0], 0).ekf.P
    np.testing.assert_allclose(np.sqrt(np.diag(P0)[20:22]), sigma_t / length)
    # White relief (length 0): the spec plus the relief variance, whatever came before.
    white = make({**SIM_SPEC, **WHITE_RELIEF}, [0, 0, 100.0], [0, 0, 0], 0, q0_LB=[1, 0, 0, 0])
    for _ in range(2):
        rec = white.update_altimeter(AltimeterMessage(0, rho, True, BORESIGHT_B))
        rho_hat = rec.x_prior[2] + LEVER_B[2]
        spec_var = ALT_FLOOR_M**2 + (ALT_FRAC * rho_hat) ** 2
        assert rec.S[0, 0] == pytest.approx(rec.P_prior[2, 2] + sigma_t**2 + spec_var, rel=1e-12)


def test_relative_update_is_a_consider_update_that_leaves_the_vertical_channel_alone():
    # A vision pair after 0.1 s of flight: the update must equal the Schmidt-Kalman consider update
    # written out here (gain rows of the vertical channel and the terrain zeroed, Joseph form),
    # with this frame's offset (and the clone frame's, first pair) entered at R_frame.
    nav = make(None, [5.0, -3.0, 200.0], [2.0, 1.0, -10.0], 0, q0_LB=[1, 0, 0, 0])
    assert nav.clone_frame(0)
    for k in range(1, 51):
        nav.propagate_imu(_imu(k, [0.05, -0.02, G]))
    x0, P0 = nav.ekf.x.copy(), nav.ekf.P.copy()
    h0 = 200.0
    H_r = np.array([[1.0, 0.0, 0.3], [0.0, 1.0, -0.1]]) / h0
    H_c = -np.array([[1.0, 0.0, 0.31], [0.0, 1.0, -0.09]]) / h0
    H_g = np.array([4e-5, -2e-5])
    R = np.diag([3e-9, 4e-9])
    R_frame = np.diag([1e-9, 2e-9])
    hx = np.array([1e-3, 5e-4])
    z = hx + np.array([2e-5, -1e-5])
    t_ns = nav.time_ns
    H_s = np.array([[2e-4, 1e-5], [-3e-5, 1.5e-4]])
    rec = nav.update_relative(t_ns, z, hx, H_r, H_c, R, R_frame, H_g, H_s)
    assert rec.accepted
    # Explicit: enter both offsets, build H, consider gain, Joseph.
    x, P = x0.copy(), P0.copy()
    for sl in (slice(13, 15), slice(15, 17)):
        x[sl] = 0.0
        P[sl, :] = 0.0
        P[:, sl] = 0.0
        P[sl, sl] = R_frame
    H = np.zeros((2, 24))
    H[:, 0:3], H[:, 10:13], H[:, 19], H[:, 22:24] = H_r, H_c, H_g, H_s
    H[:, 17:19] = np.eye(2)
    H[:, 15:17], H[:, 13:15] = np.eye(2), -np.eye(2)
    y = z - hx
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    for i in (2, 5, 8, 9, 12, 20, 21):
        K[i, :] = 0.0
    x_post = x + K @ y
    A = np.eye(24) - K @ H
    P_post = A @ P @ A.T + K @ R @ K.T
    np.testing.assert_allclose(rec.S, S, rtol=1e-9)
    np.testing.assert_allclose(nav.ekf.x, x_post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(nav.ekf.P, 0.5 * (P_post + P_post.T), rtol=1e-7, atol=1e-10)  # P up to 400 m^2
    for i in (2, 5, 8, 9, 12, 20, 21):  # the vertical channel and the terrain are not corrected
        assert nav.ekf.x[i] == x0[i]
    assert np.any(nav.ekf.x[:2] != x0[:2]) and np.any(nav.ekf.x[3:5] != x0[3:5])
    # The consider columns count: without them, S is smaller.
    H_h = H.copy()
    H_h[:, [2, 12]] = 0.0
    assert np.all(np.diag(H_h @ P @ H_h.T + R) < np.diag(S))


# --------------------------------------------------------------------------- the site map
def test_site_relief_factor_follows_the_map():
    from gnc.estimator import site_relief_factor

    cfg = EstimatorConfig(terrain_relief_sigma_m=4.0, site_relief_sigma_m=1.0, site_radius_m=70.0,
                          site_relief_ramp_m=30.0)
    rho = np.array([0.0, 69.9, 70.0, 85.0, 100.0, 500.0])
    np.testing.assert_allclose(site_relief_factor(cfg, rho), [0.25, 0.25, 0.25, 0.625, 1.0, 1.0])
    no_map = cfg.model_copy(update={"site_radius_m": 0.0})
    np.testing.assert_array_equal(site_relief_factor(no_map, rho), np.ones(rho.size))


@pytest.mark.parametrize("r_xy, sigma_m", [((0.0, 0.0), 20.0), ((60.0, 30.0), 20.0), ((90.0, 0.0), 10.0),
                                           ((300.0, 0.0), 20.0), ((75.0, -5.0), 1e-6)])
def test_relief_scale_is_the_rms_factor_over_the_position_uncertainty(r_xy, sigma_m):
    """The 3x3 Gauss-Hermite mix against a Monte Carlo average of k(|p|)^2 over p ~ N(r, C)."""
    from gnc.estimator import relief_scale, site_relief_factor

    cfg = EstimatorConfig()
    C = np.array([[1.0, 0.3], [0.3, 0.6]]) * sigma_m**2
    p = np.random.default_rng(5).multivariate_normal(r_xy, C, 400_000)
    mc = math.sqrt(float(np.mean(site_relief_factor(cfg, np.hypot(p[:, 0], p[:, 1])) ** 2)))
    assert relief_scale(cfg, np.array(r_xy), C) == pytest.approx(mc, rel=0.03)


def test_relief_scale_equals_the_gauss_hermite_rule_on_eigh_axes():
    """The closed-form principal axes and the all-inside / all-outside shortcuts against the rule done longhand:
    numpy's eigh of the covariance, the 7x7 nodes placed on its axes by an explicit loop."""
    from gnc.estimator import relief_scale, site_relief_factor

    cfg = EstimatorConfig()
    x, w = np.polynomial.hermite_e.hermegauss(7)
    w = w / w.sum()
    rng = np.random.default_rng(11)
    for _ in range(300):
        r = rng.uniform(-160.0, 160.0, 2)
        A = rng.normal(size=(2, 2)) * rng.choice([0.1, 3.0, 15.0, 40.0])
        C = A @ A.T + np.eye(2) * 1e-6
        lam, vec = np.linalg.eigh(C)
        total = 0.0
        for i in range(7):
            for j in range(7):
                p = r + vec[:, 0] * math.sqrt(lam[0]) * x[i] + vec[:, 1] * math.sqrt(lam[1]) * x[j]
                total += w[i] * w[j] * float(site_relief_factor(cfg, math.hypot(*p))) ** 2
        assert relief_scale(cfg, r, C) == pytest.approx(math.sqrt(total), rel=1e-12)


def test_terrain_step_keeps_the_relief_stationary_at_the_new_amplitude():
    """From the stationary covariance at the old footprint's amplitude, one step gives the new one's exactly."""
    from gnc.estimator import terrain_slope_sigma

    cfg = EstimatorConfig()
    nav = make(cfg, [150.0, 0.0, 400.0], [0.0, 0.0, -10.0], 0)
    sigma, slope = cfg.terrain_relief_sigma_m, terrain_slope_sigma(cfg)

    def stationary(k):
        return np.diag([sigma**2, slope**2, slope**2]) * k * k

    nav._footprint_L = np.array([110.0, 0.0])
    nav._k_terrain = 0.8
    F, Q = nav._terrain_step(np.array([95.0, 4.0]), 0.5)
    np.testing.assert_allclose(F @ stationary(0.8) @ F.T + Q, stationary(0.5), rtol=1e-12, atol=1e-15)


def test_scaled_gauss_markov_step_reaches_the_new_amplitude():
    """_decay with a change of amplitude: a stationary state at sigma0 steps to exactly sigma1."""
    from gnc.estimator import _decay, vision_bias_sigma

    cfg = EstimatorConfig()
    s0, s1 = vision_bias_sigma(cfg, 300.0), vision_bias_sigma(cfg, 120.0)
    assert s1 == pytest.approx(s0 * 2.5) and s0 == pytest.approx(cfg.vision_bias_ground_m / 300.0)
    x, P = np.array([2e-6, -1e-6]), np.eye(2) * s0**2
    _decay(x, P, slice(0, 2), 0.4, s1, s1 / s0)
    np.testing.assert_allclose(P, np.eye(2) * s1**2, rtol=1e-12)
    np.testing.assert_allclose(x, np.array([2e-6, -1e-6]) * 0.4 * 2.5, rtol=1e-12)


def test_frame_overlap_is_the_shared_tracks_over_the_geometric_mean_of_the_counts():
    from gnc.flight import frame_overlap

    a = np.arange(10, dtype=np.int64)
    b = np.arange(6, 20, dtype=np.int64)  # 4 shared of 10 and 14
    assert frame_overlap(a, b) == pytest.approx(4 / math.sqrt(10 * 14))
    assert frame_overlap(a, a) == 1.0 and frame_overlap(None, b) == 1.0
    assert frame_overlap(a, np.arange(30, 35, dtype=np.int64)) == 0.0
    # Independent per-track errors of one frame, averaged over each pair's own tracks: the correlation
    # of the two means, by Monte Carlo, is the overlap.
    e = np.random.default_rng(3).normal(size=(200_000, 20))
    m1, m2 = e[:, a].mean(axis=1), e[:, b].mean(axis=1)
    assert np.corrcoef(m1, m2)[0, 1] == pytest.approx(frame_overlap(a, b), abs=0.01)


def test_relative_update_carries_the_clone_frames_offset_over_by_the_track_overlap():
    # Two pairs: the first enters both frames' offsets; after cloning, the second pair shares the clone
    # frame with it. With overlap a, its prior holds a * d and a^2 P_dd + (1 - a^2) R_frame.
    nav = make(None, [5.0, -3.0, 200.0], [2.0, 1.0, -10.0], 0, q0_LB=[1, 0, 0, 0])
    assert nav.clone_frame(0)
    h0 = 200.0
    H_r = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) / h0
    H_c = -H_r
    R, R_frame = np.diag([3e-9, 4e-9]), np.diag([1e-9, 2e-9])
    k = 0
    for pair, overlap in ((1, 1.0), (2, 0.6)):
        for _ in range(50):
            k += 1
            nav.propagate_imu(_imu(k, [0.05, -0.02, G]))
        hx = np.array([1e-3, 5e-4])
        if pair == 2:
            x_before, P_before = nav.ekf.x.copy(), nav.ekf.P.copy()
        rec = nav.update_relative(nav.time_ns, hx + np.array([2e-5, -1e-5]), hx, H_r, H_c, R, R_frame,
                                  frame_overlap=overlap)
        assert rec.accepted
        assert nav.clone_frame(nav.time_ns)
    # Explicit prior of the second pair: this frame's offset entered fresh, the clone frame's carried over.
    x, P = x_before.copy(), P_before.copy()
    dn, dc = slice(15, 17), slice(13, 15)
    x[dn] = 0.0
    P[dn, :] = 0.0
    P[:, dn] = 0.0
    P[dn, dn] = R_frame
    x[dc] *= 0.6
    P[dc, :] *= 0.6
    P[:, dc] *= 0.6
    P[dc, dc] += 0.64 * R_frame
    H = np.zeros((2, 24))
    H[:, 0:3], H[:, 10:13], H[:, 17:19], H[:, dn], H[:, dc] = H_r, H_c, np.eye(2), np.eye(2), -np.eye(2)
    np.testing.assert_allclose(rec.S, H @ P @ H.T + R, rtol=1e-9)
    hx_full = hx + x[17:19] + x[dn] - x[dc]
    np.testing.assert_allclose(rec.y, hx + np.array([2e-5, -1e-5]) - hx_full, rtol=1e-9, atol=1e-15)
    assert abs(x_before[dc]).max() > 0  # the first pair did estimate the clone frame's offset


@pytest.mark.parametrize("width_m", [15.0, 60.0, 150.0, 350.0, 1000.0])
def test_view_ground_sigma_averages_the_relief_over_the_patch(width_m):
    """The patch mean's 1-sigma against a Monte Carlo of the Matern-3/2 correlation over a square patch
    (a uniform average): never below it (conservative), at most 12 % above it."""
    from gnc.estimator import view_ground_sigma

    cfg = EstimatorConfig(view_ground_samples=1_000_000)  # a uniform average over the patch
    length = cfg.terrain_correlation_length_m
    rng = np.random.default_rng(11)
    p, q = rng.uniform(0, width_m, (200_000, 2)), rng.uniform(0, width_m, (200_000, 2))
    r = np.linalg.norm(p - q, axis=1)
    exact = cfg.view_ground_sigma_m * math.sqrt(float(np.mean((1 + r / length) * np.exp(-r / length))))
    model = view_ground_sigma(cfg, width_m / cfg.view_width_per_height, 1.0)
    assert 0.995 * exact <= model <= 1.12 * exact
    assert view_ground_sigma(cfg, width_m / cfg.view_width_per_height, 0.25) == pytest.approx(0.25 * model)
    # Sampled at n places: the mean of n independent draws adds (1 - rho) sigma^2 / n.
    few = cfg.model_copy(update={"view_ground_samples": 4})
    big = cfg.view_ground_samples
    rho = ((model / cfg.view_ground_sigma_m) ** 2 - 1 / big) / (1 - 1 / big)
    assert view_ground_sigma(few, width_m / cfg.view_width_per_height, 1.0) == pytest.approx(
        cfg.view_ground_sigma_m * math.sqrt(rho + (1 - rho) / 4))


def test_divergence_update_is_the_textbook_scalar_update_and_corrects_the_vertical_channel():
    """The flow divergence (no altimeter): the update must equal the ordinary Kalman update written out here
    (H on the position, the clone, the viewed ground's height and slope; no consider rows, the frames' offsets
    not involved), and unlike the horizontal flow it moves the height and the vertical velocity."""
    nav = make(None, [5.0, -3.0, 60.0], [1.0, 0.5, -3.0], 0, q0_LB=[1, 0, 0, 0])
    assert nav.clone_frame(0)
    for k in range(1, 11):
        nav.propagate_imu(_imu(k, [0.05, -0.02, G + 0.4]))
    x0, P0 = nav.ekf.x.copy(), nav.ekf.P.copy()
    h0 = 60.0
    H_r = np.array([2e-4, -1e-4, 1.0 / h0])
    H_c = np.array([-2e-4, 1e-4, -1.0 / h0 - 0.005 / h0])
    H_g, H_s, R = 0.005 / h0, np.array([3e-4, -2e-4]), 4e-8
    hx = -0.3 / h0
    z = hx + 4e-4
    rec = nav.update_divergence(nav.time_ns, z, hx, H_r, H_c, H_g, H_s, R)
    assert rec.accepted and rec.kind == "divergence" and nav.counters["divergence"]["accepted"] == 1
    H = np.zeros((1, 24))
    H[0, 0:3], H[0, 10:13], H[0, 19], H[0, 22:24] = H_r, H_c, H_g, H_s
    S = float((H @ P0 @ H.T)[0, 0]) + R
    K = (P0 @ H.T / S)[:, 0]
    x_post = x0 + K * (z - hx)
    P_post = P0 - np.outer(K, K) * S
    np.testing.assert_allclose(nav.ekf.x, x_post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(nav.ekf.P, P_post, rtol=1e-7, atol=1e-10)
    assert abs(nav.ekf.x[2] - x0[2]) > 1e-3 and abs(nav.ekf.x[5] - x0[5]) > 1e-4  # the vertical channel moved
    assert "divergence" not in make(None, [0.0, 0.0, 60.0], [0.0, 0.0, -3.0], 0).counters  # counted once used



def test_local_site_relief_keeps_the_site_slope_with_the_regional_relief():
    # With the regional field carried, the cleared site's local relief keeps the rest of the survey's slope
    # variance: local^2 + regional^2 = the site's, per axis; the initial terrain prior follows it, and the
    # viewed ground (vision's model) keeps the survey's site map.
    from gnc.estimator import IDX_G, IDX_S, local_site_config, site_relief_factor, terrain_slope_sigma

    cfg = EstimatorConfig()
    local = local_site_config(cfg)
    slope_local = terrain_slope_sigma(local) * float(site_relief_factor(local, 0.0))
    slope_regional = cfg.regional_relief_sigma_m / cfg.regional_relief_length_m
    site_slope = cfg.site_relief_sigma_m / cfg.terrain_correlation_length_m
    assert slope_local**2 + slope_regional**2 == pytest.approx(site_slope**2)
    assert local.site_relief_sigma_m == pytest.approx(0.61, abs=0.005) and local.terrain_relief_sigma_m == 4.0
    kw = {"altimeter_mount_B_m": LEVER_B, "map_bias_sigma_m": 1.0}
    nav = make_estimator(cfg, [0.0, 0.0, 100.0], [0, 0, 0], 0, regional_relief=True, **kw)
    plain = make_estimator(cfg, [0.0, 0.0, 100.0], [0, 0, 0], 0, **kw)
    # At the target with a 20 m 1-sigma the prior mixes site and ramp: the local share is the smaller.
    assert nav.P[IDX_S, IDX_S][0, 0] < plain.P[IDX_S, IDX_S][0, 0]
    np.testing.assert_array_equal(nav.P[:9, :9], plain.P[:9, :9])
    assert nav.P[IDX_G, IDX_G] == plain.P[IDX_G, IDX_G]
    with pytest.raises(ValueError, match="regional_relief_length_m"):
        local_site_config(EstimatorConfig(regional_relief_sigma_m=4.0))
