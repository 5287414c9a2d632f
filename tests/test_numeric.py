"""The flight software's hot-path helpers against the plain NumPy they replace."""

import numpy as np
import pytest

from gnc.numeric import all_finite, finite_small, median
from gnc.vision_nav import _image_cells, _rays_L


def test_median_equals_numpy_bit_for_bit_odd_and_even():
    rng = np.random.default_rng(3)
    for n in range(1, 60):
        a = rng.standard_normal(n) * 10.0 ** rng.integers(-3, 4)
        assert median(a) == float(np.median(a)), n
    assert median(np.array([1.0, 1.0, 5.0, 7.0])) == 3.0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_all_finite_finds_one_bad_value_in_any_array(bad):
    arrays = [np.zeros(2), np.eye(3), np.ones((2, 3))]
    assert all_finite(*arrays)
    for k, a in enumerate(arrays):
        for i in range(a.size):
            b = [x.copy() for x in arrays]
            b[k].flat[i] = bad
            assert not all_finite(*b)


def test_finite_small_is_np_all_isfinite():
    rng = np.random.default_rng(8)
    for shape in [(3,), (4,), (2, 2), (1,)]:
        for _ in range(200):
            a = rng.normal(0.0, 10.0, shape) * 10.0 ** rng.integers(-300, 300)
            if rng.random() < 0.5:
                a.flat[rng.integers(a.size)] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e308])
            assert finite_small(a) == bool(np.all(np.isfinite(a))), a


def test_image_cells_label_like_numpy_unique():
    rng = np.random.default_rng(5)
    for _ in range(50):
        xy = rng.uniform(-0.5, 255.5, size=(rng.integers(1, 80), 2))
        cell = np.floor(xy / 64.0).astype(np.int64)
        _, expected = np.unique(cell[:, 0] * 1_000_003 + cell[:, 1], return_inverse=True)
        label, n = _image_cells(xy, 64.0)
        np.testing.assert_array_equal(label, expected.reshape(-1))
        assert n == int(expected.max()) + 1


def test_rays_are_R_LC_K_inv_homogeneous_pixels():
    rng = np.random.default_rng(6)
    K = np.array([[300.0, 0.0, 127.5], [0.0, 310.0, 128.5], [0.0, 0.0, 1.0]])
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    xy = rng.uniform(0.0, 255.0, size=(20, 2))
    loop = np.array([q @ np.linalg.solve(K, np.array([x, y, 1.0])) for x, y in xy])
    np.testing.assert_allclose(_rays_L(xy, np.linalg.inv(K), q), loop, rtol=1e-12, atol=1e-15)


def test_chi2_ppf_is_scipy_stats_chi2_ppf_bit_for_bit():
    from scipy.stats import chi2

    from gnc.numeric import chi2_ppf

    rng = np.random.default_rng(7)
    p = np.concatenate([rng.uniform(0.0, 1.0, 5000), [1e-9, 0.0013, 0.025, 0.5, 0.975, 0.9973, 0.99, 1 - 1e-9]])
    dof = rng.integers(1, 4000, p.size)
    assert np.array_equal(chi2_ppf(p, dof), chi2.ppf(p, dof))
    for n in (1, 2, 3, 80, 249 * 2):  # the filter's gates and the campaign bands' counts
        for q in (0.025, 0.975, 0.9973):
            assert float(chi2_ppf(q, n)) == float(chi2.ppf(q, n))
    assert abs(float(chi2_ppf(0.95, 1)) - 3.841458820694124) < 1e-12  # the textbook 5 % point of one dof
