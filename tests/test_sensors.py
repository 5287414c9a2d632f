"""Sensor models against independent computations."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from bench.scenario.seeding import component_rng
from models.camera import CameraConfig
from models.lander import LanderConfig
from models.sensors import (
    AltimeterConfig,
    AltimeterModel,
    ImuConfig,
    ImuModel,
    StarTrackerConfig,
    StarTrackerModel,
)
from models.world import SunConfig, World
from tests.conftest import make_terrain

LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
NOISELESS_ALT = AltimeterConfig(noise_sigma_m=0.0, noise_frac=0.0, dropout_prob=0.0)


def _world(terrain) -> World:
    return World(terrain, LanderConfig(), CameraConfig(width_px=64, height_px=64), SunConfig(), 2_000_000)


def test_altimeter_over_a_grid_vertex_equals_height_difference():
    rng = np.random.default_rng(3)
    n, size = 65, 320.0
    h = rng.normal(0.0, 3.0, (n, n)).astype(np.float32)
    terrain = make_terrain(h, size)
    world = _world(terrain)
    spacing = size / (n - 1)
    row, col = 40, 23  # an arbitrary vertex; rows run south to north
    x_v, y_v = -size / 2 + col * spacing, -size / 2 + row * spacing
    alt_site_B = world.model.site("altimeter").pos.copy()
    world.reset(np.array([x_v, y_v, 60.0]) - np.array([alt_site_B[0], alt_site_B[1], 0.0]), np.zeros(3), LEVEL, np.zeros(3))
    origin, direction = world.altimeter_ray()
    assert np.allclose(direction, [0, 0, -1])
    expected = origin[2] - h[row, col]
    model = AltimeterModel(NOISELESS_ALT, np.random.default_rng(0))
    msg = model.sample(0, world.altimeter_range_truth())
    assert msg.valid and abs(msg.range_m - expected) < 1e-4, (msg.range_m, expected)


def test_altimeter_slant_range_on_a_plane_matches_analytic_intersection():
    n, size = 65, 320.0
    a, b = 0.12, -0.07  # plane z = a x + b y: every triangulation of it is the plane itself
    coords = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(coords, coords)  # rows follow y (south to north)
    terrain = make_terrain(a * X + b * Y, size)
    world = _world(terrain)
    q = Rotation.from_euler("xyz", [12.0, -8.0, 30.0], degrees=True).as_quat(scalar_first=True)
    world.reset(np.array([10.0, -15.0, 80.0]), np.zeros(3), q, np.zeros(3))
    p0, d = world.altimeter_ray()
    # Solve p0_z + s d_z = a (p0_x + s d_x) + b (p0_y + s d_y) for s.
    s = (a * p0[0] + b * p0[1] - p0[2]) / (d[2] - a * d[0] - b * d[1])
    model = AltimeterModel(NOISELESS_ALT, np.random.default_rng(0))
    msg = model.sample(0, world.altimeter_range_truth())
    assert abs(msg.range_m - s) < 1e-3, (msg.range_m, s)


def test_altimeter_max_range_dropouts_and_noise():
    cfg = AltimeterConfig(max_range_m=100.0, dropout_prob=0.2, noise_sigma_m=0.5, noise_frac=0.0)
    model = AltimeterModel(cfg, np.random.default_rng(1))
    assert not model.sample(0, 150.0).valid
    assert not model.sample(0, math.nan).valid
    samples = [model.sample(0, 50.0) for _ in range(20000)]
    valid = np.array([m.range_m for m in samples if m.valid])
    assert abs(1 - len(valid) / len(samples) - 0.2) < 0.015
    assert abs(valid.mean() - 50.0) < 0.02 and abs(valid.std() - 0.5) < 0.02


def test_imu_noise_matches_density_and_zero_noise_is_exact():
    cfg = ImuConfig(period_ns=10_000_000, accel_noise_density=2e-3, gyro_noise_density=1e-4,
                    accel_bias_sigma=0.0, gyro_bias_sigma=0.0, accel_bias_walk=0.0, gyro_bias_walk=0.0)
    imu = ImuModel(cfg, np.random.default_rng(2))
    f = np.array([0.1, -0.2, 1.62])
    w = np.array([0.01, 0.0, -0.02])
    s = [imu.sample(i, f, w) for i in range(20000)]
    fa = np.array([m.f_B for m in s])
    wa = np.array([m.omega_B for m in s])
    dt = cfg.period_ns / 1e9
    assert np.allclose(fa.std(axis=0), 2e-3 / math.sqrt(dt), rtol=0.03)
    assert np.allclose(wa.std(axis=0), 1e-4 / math.sqrt(dt), rtol=0.03)
    assert np.allclose(fa.mean(axis=0), f, atol=5e-4)
    quiet = ImuModel(ImuConfig(accel_noise_density=0, gyro_noise_density=0, accel_bias_sigma=0, gyro_bias_sigma=0,
                               accel_bias_walk=0, gyro_bias_walk=0), np.random.default_rng(0))
    m = quiet.sample(0, f, w)
    assert np.array_equal(m.f_B, f) and np.array_equal(m.omega_B, w)


def test_imu_sample_is_the_four_draws_of_three_it_stands_for():
    """One draw of twelve normals per sample: bit for bit the four ``rng.normal(0, sigma, 3)`` of its
    definition (noise, noise, walk, walk), the biases after it and the stream left behind included."""
    cfg = ImuConfig(period_ns=10_000_000, accel_noise_density=2e-3, gyro_noise_density=0.0,
                    accel_bias_sigma=0.02, gyro_bias_sigma=1e-4, accel_bias_walk=1e-3, gyro_bias_walk=3e-6)
    imu = ImuModel(cfg, np.random.default_rng(9))
    rng = np.random.default_rng(9)
    acc_bias, gyro_bias = rng.normal(0.0, cfg.accel_bias_sigma, 3), rng.normal(0.0, cfg.gyro_bias_sigma, 3)
    dt = cfg.period_ns / 1e9
    rates = (cfg.accel_noise_density / math.sqrt(dt), cfg.gyro_noise_density / math.sqrt(dt),
             cfg.accel_bias_walk * math.sqrt(dt), cfg.gyro_bias_walk * math.sqrt(dt))
    f, w = np.array([0.1, -0.2, 1.62]), np.array([0.01, -0.0, -0.02])
    for i in range(500):
        m = imu.sample(i, f, w)
        f_want = f + acc_bias + rng.normal(0.0, rates[0], 3)
        w_want = w + gyro_bias + rng.normal(0.0, rates[1], 3)
        acc_bias = acc_bias + rng.normal(0.0, rates[2], 3)
        gyro_bias = gyro_bias + rng.normal(0.0, rates[3], 3)
        assert m.f_B.tobytes() == f_want.tobytes() and m.omega_B.tobytes() == w_want.tobytes()
        assert imu.accel_bias.tobytes() == acc_bias.tobytes() and imu.gyro_bias.tobytes() == gyro_bias.tobytes()
    assert imu._rng.random() == rng.random()


def test_a_rotation_vector_turns_a_quaternion_as_scipy_rotations_do():
    """The star tracker's error composition, through SciPy's kernels, against the Rotation objects it
    stands for: the same bits over rotations from arcseconds to whole turns (both signs of w)."""
    import models.sensors as sensors

    rng = np.random.default_rng(12)
    ways = [sensors.rotated_by_rotvec] + ([sensors._rotated_kernels] if sensors._rotation_cy is not None else [])
    for i in range(3000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        rotvec = 10.0 ** rng.uniform(-8, 0.5) * rng.normal(size=3)
        want = (Rotation.from_quat(q, scalar_first=True) * Rotation.from_rotvec(rotvec)).as_quat(
            canonical=True, scalar_first=True)
        for way in ways:
            assert way(q, rotvec).tobytes() == want.tobytes(), (i, way.__name__)


def test_imu_bias_random_walk_grows_as_sqrt_time():
    cfg = ImuConfig(period_ns=10_000_000, accel_noise_density=0.0, gyro_noise_density=0.0, accel_bias_sigma=0.0,
                    gyro_bias_sigma=0.0, accel_bias_walk=1e-3, gyro_bias_walk=0.0)
    finals = []
    for k in range(400):
        imu = ImuModel(cfg, np.random.default_rng(k))
        for i in range(100):  # 1 s
            imu.sample(i, np.zeros(3), np.zeros(3))
        finals.append(imu.accel_bias)
    assert np.allclose(np.std(finals, axis=0), 1e-3 * math.sqrt(1.0), rtol=0.12)


def test_star_tracker_error_statistics():
    cfg = StarTrackerConfig(noise_sigma_arcsec=20.0)
    st = StarTrackerModel(cfg, np.random.default_rng(4))
    q_true = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    errs = []
    for _ in range(5000):
        q = st.sample(0, q_true.as_quat(scalar_first=True)).q_LB
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
        errs.append((q_true.inv() * Rotation.from_quat(q, scalar_first=True)).as_rotvec())
    sigma = math.radians(20.0 / 3600)
    assert np.allclose(np.std(errs, axis=0), sigma, rtol=0.05)


def test_component_streams_are_reproducible_and_independent():
    a1 = component_rng(7, "imu").normal(size=5)
    a2 = component_rng(7, "imu").normal(size=5)
    b = component_rng(7, "altimeter").normal(size=5)
    c = component_rng(8, "imu").normal(size=5)
    assert np.array_equal(a1, a2)
    assert not np.array_equal(a1, b) and not np.array_equal(a1, c)
