"""The landbench command line: outputs, one-line errors, and nothing written on error."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bench.cli import main
from bench.scenario import load_scenario
from tests.conftest import SMALL_SET


def _sets(extra=()):
    return [a for s in (*SMALL_SET, *extra) for a in ("--set", s)]


def test_scenario_show_prints_resolved_toml(capsys, tmp_path):
    assert main(["scenario", "show", "--set", "seed=7"]) == 0
    text = capsys.readouterr().out
    f = tmp_path / "s.toml"
    f.write_text(text)
    sc = load_scenario(f)
    assert sc.seed == 7 and sc == load_scenario(None, ["seed=7"])


def test_render_writes_frame_and_depth(tmp_path):
    import cv2

    out, depth = tmp_path / "frame.png", tmp_path / "depth.npy"
    assert main(["render", "--altitude", "100", "--out", str(out), "--depth", str(depth), *_sets()]) == 0
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    d = np.load(depth)
    assert img.shape == (256, 256) and img.dtype == np.uint8 and img.std() > 3
    # Level camera 100 m above the target: the centre depth is ~100 m (terrain relief aside).
    assert d.shape == (256, 256) and abs(float(d[128, 128]) - 100.0) < 10.0


def test_world_map(tmp_path):
    out = tmp_path / "world.png"
    assert main(["world", "--out", str(out), *_sets()]) == 0
    assert out.stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "--altitude", "100", "--set", "lander.dry_mass_kg=-1"], "lander.dry_mass_kg"),
        (["render", "--altitude", "100", "--set", "bogus=1"], "bogus"),
        (["render", "--altitude", "-3"], "--altitude"),
        (["render", "--altitude", "100", "--set", "sensors.imu.period_ns=3000001"], "sensors.imu.period_ns"),
    ],
)
def test_errors_are_one_line_and_write_nothing(tmp_path, capsys, argv, needle):
    out = tmp_path / "frame.png"
    out.write_bytes(b"previous result")  # an earlier result must survive a bad run
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("landbench: error:") and needle in err
    assert out.read_bytes() == b"previous result"
    assert list(tmp_path.iterdir()) == [out]


def test_console_script_entry_point():
    res = subprocess.run([sys.executable, "-m", "bench.cli", "scenario", "show", "--set", "seed=3"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "seed = 3" in res.stdout
