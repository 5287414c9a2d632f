"""What a command does not need is not imported: a campaign case flies without matplotlib, pyarrow, pandas or Ray,
and writing the telemetry Parquet does not pull in pandas (about a second of import)."""

import subprocess
import sys


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_campaign_worker_imports_no_plotting_parquet_or_ray():
    mods = _modules_after("import bench.cli, bench.campaign.mc, bench.sim.run")
    assert not {"matplotlib", "pyarrow", "pandas", "ray", "statsmodels"} & mods


def test_a_landing_imports_neither_scipy_stats_nor_scipy_ndimage():
    """A run, a campaign worker and the helper processes' fork server import the filter without filterpy's
    ``stats`` and ``discrete_bayes`` subpackages (``gnc.filterpy_import``) and take their chi-square
    quantiles from ``scipy.special``: ``scipy.stats`` alone is about 0.5 s of every process's start."""
    mods = _modules_after("import bench.cli, bench.campaign.mc, bench.sim.run, bench.report.run_outputs, "
                          "bench.report.video_process, bench.report.plot_process, gnc.estimator")
    assert "filterpy.kalman" in mods
    assert not {"scipy.stats", "scipy.ndimage"} & mods


def test_the_command_line_parses_before_it_imports_the_simulation():
    """``landbench --help`` and the start of every command: the scenario's schema (with the filter, filterpy
    and SciPy behind it, about 0.9 s) is imported by the command that needs it, so that a campaign can
    start its workers' fork server first."""
    mods = _modules_after("import bench.cli; bench.cli.build_parser()")
    assert not {"scipy", "filterpy", "mujoco", "cv2", "pydantic", "bench.scenario", "bench.sim"} & mods


def test_parquet_writing_does_not_import_pandas(tmp_path):
    path = tmp_path / "t.parquet"
    code = f"""
import numpy as np
from bench.report.report import read_telemetry_parquet, write_telemetry_parquet
cols = {{"t_s": np.arange(5) * 0.02, "n": np.arange(5, dtype=np.int16), "u": np.arange(5, dtype=np.uint32),
        "ok": np.array([True, False, True, True, False]), "phase": np.array(["a", "bb", "", "ccc", "é"]),
        "h": np.arange(5, dtype=np.float32)[::-1]}}
write_telemetry_parquet(cols, {str(path)!r})
import sys
assert "pandas" not in sys.modules, "pandas imported"
back = read_telemetry_parquet({str(path)!r})
for k, v in cols.items():
    assert back[k].dtype == v.dtype and np.array_equal(back[k], v), k
"""
    subprocess.run([sys.executable, "-c", code], check=True)
