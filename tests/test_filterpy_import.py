"""filterpy imported without its unused subpackages (``gnc.filterpy_import``): the filter is filterpy's own, and
``filterpy.stats`` / ``filterpy.discrete_bayes`` still work for whoever uses them, imported at first use."""

import subprocess
import sys
import textwrap


def _run(code: str) -> None:
    subprocess.run([sys.executable, "-c", textwrap.dedent(code)], check=True, timeout=120)


def test_the_filter_is_filterpys_and_the_deferred_subpackages_load_on_first_use():
    _run("""
        import sys
        import numpy as np
        import gnc.estimator
        from gnc.filterpy_import import ExtendedKalmanFilter
        import filterpy.kalman
        assert ExtendedKalmanFilter is filterpy.kalman.ExtendedKalmanFilter
        assert "scipy.stats" not in sys.modules and "scipy.ndimage" not in sys.modules

        # logpdf, which filterpy's filter modules bound at their import, loads filterpy.stats when called.
        from filterpy.kalman import EKF
        x, mean, cov = np.array([0.3, -1.2]), np.array([0.1, 0.4]), np.array([[2.0, 0.3], [0.3, 0.5]])
        d = x - mean
        explicit = -0.5 * (d @ np.linalg.solve(cov, d) + np.log(np.linalg.det(2 * np.pi * cov)))
        assert abs(EKF.logpdf(x, mean, cov) - explicit) < 1e-12
        import filterpy.stats
        from gnc.filterpy_import import _Deferred
        assert not isinstance(sys.modules["filterpy.stats"], _Deferred) and "scipy.stats" in sys.modules
        assert filterpy.stats is sys.modules["filterpy.stats"]
        assert abs(filterpy.stats.logpdf(x, mean, cov) - explicit) < 1e-12
        assert abs(filterpy.stats.gaussian(1.0, 0.0, 4.0) - np.exp(-1 / 8) / np.sqrt(8 * np.pi)) < 1e-12

        # discrete_bayes: any attribute read imports it.
        from filterpy.discrete_bayes import normalize
        assert np.allclose(normalize(np.array([1.0, 3.0])), [0.25, 0.75]) and "scipy.ndimage" in sys.modules
        assert not isinstance(sys.modules["filterpy.discrete_bayes"], _Deferred)
        """)


def test_a_submodule_of_a_deferred_subpackage_imports():
    _run("""
        import sys
        import numpy as np
        import gnc.filterpy_import
        from filterpy.stats.stats import logpdf
        assert sys.modules["filterpy.stats"].__file__.endswith("__init__.py")
        assert abs(logpdf(0.0, 0.0, 1.0) + 0.5 * np.log(2 * np.pi)) < 1e-12
        """)


def test_the_filters_log_likelihood_after_an_update():
    _run("""
        import numpy as np
        from gnc.filterpy_import import ExtendedKalmanFilter
        ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
        ekf.x = np.array([1.0, 0.0]); ekf.P = np.diag([4.0, 1.0]); ekf.R = np.array([[0.25]])
        H = np.array([[1.0, 0.0]])
        ekf.update(np.array([2.0]), lambda x: H, lambda x: H @ x)
        S = 4.0 + 0.25
        assert abs(ekf.log_likelihood - (-0.5 * (1.0 / S + np.log(2 * np.pi * S)))) < 1e-12
        """)


def test_nothing_is_deferred_once_filterpy_has_been_imported():
    _run("""
        import sys
        import filterpy.stats
        real = sys.modules["filterpy.stats"]
        import gnc.filterpy_import
        assert sys.modules["filterpy.stats"] is real
        """)
