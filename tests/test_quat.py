"""The flight software's NumPy quaternion helpers (gnc/quat.py) against scipy's Rotation on random inputs."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gnc.quat import (body_z_L, quat_conjugate, quat_error, quat_from_matrix, quat_multiply, quat_normalize,
                      unit_quaternion)

N = 2000


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(20261123)


def _random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_multiply_matches_scipy_composition(rng):
    p, q = _random_quats(rng, N), _random_quats(rng, N)
    expected = (Rotation.from_quat(p, scalar_first=True) * Rotation.from_quat(q, scalar_first=True)).as_quat(
        scalar_first=True)
    got = np.array([quat_multiply(a, b) for a, b in zip(p, q)])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14)


def test_body_z_of_a_normalised_quaternion_matches_scipy(rng):
    q = rng.normal(size=(N, 4)) * rng.choice([1e-150, 1.0, 1e150], size=(N, 1))  # not unit, some extreme scales
    expected = Rotation.from_quat(q, scalar_first=True).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.array([body_z_L(unit_quaternion(a)) for a in q]), expected, rtol=0, atol=1e-14)
    for bad in (np.zeros(4), np.array([np.nan, 0.0, 0.0, 1.0]), np.array([np.inf, 0.0, 0.0, 1.0]), np.ones(3)):
        assert unit_quaternion(bad) is None


def test_conjugate_matches_scipy_inverse(rng):
    q = _random_quats(rng, N)
    expected = Rotation.from_quat(q, scalar_first=True).inv().as_quat(scalar_first=True)
    np.testing.assert_allclose(np.array([quat_conjugate(a) for a in q]), expected, rtol=0, atol=1e-15)


def test_error_matches_scipy_on_unnormalised_inputs(rng):
    # scipy normalises what from_quat is given; so does quat_error.
    q_cmd = _random_quats(rng, N) * rng.uniform(0.5, 2.0, (N, 1))
    q = _random_quats(rng, N) * rng.uniform(0.5, 2.0, (N, 1))
    expected = (Rotation.from_quat(q_cmd, scalar_first=True).inv() * Rotation.from_quat(q, scalar_first=True)).as_quat(
        scalar_first=True)
    got = np.array([quat_error(a, b) for a, b in zip(q_cmd, q)])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm([quat_normalize(a) for a in q], axis=1), 1.0, atol=1e-15)


def test_from_matrix_matches_scipy_sign_included(rng):
    # Random rotations cover all four branches (largest of the diagonal or the trace); add one of each by hand.
    R = Rotation.from_quat(_random_quats(rng, N), scalar_first=True).as_matrix()
    special = Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [0, 0, 0], [0.1, -0.2, 0.3]]).as_matrix()
    R = np.concatenate([R, special])
    expected = Rotation.from_matrix(R).as_quat(scalar_first=True)
    got = np.array([quat_from_matrix(m) for m in R])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-14)
    branches = np.argmax(np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], np.trace(R, axis1=1, axis2=2)], 1), 1)
    assert set(branches.tolist()) == {0, 1, 2, 3}


def test_from_matrix_round_trips_through_an_independent_matrix(rng):
    # Independent of scipy's algorithm: the quaternion's own rotation matrix is the input.
    for q in _random_quats(rng, 200):
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        got = quat_from_matrix(R)
        assert min(np.abs(got - q).max(), np.abs(got + q).max()) < 1e-13
