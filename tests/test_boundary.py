"""The hard boundary: flight software (vision/, gnc/) never touches the simulator or truth."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FLIGHT_PACKAGES = ("vision", "gnc")
# Truth lives in the simulator and in the world/bench packages.
FORBIDDEN_ROOTS = {"mujoco", "models", "bench", "dm_control"}


def _imported_roots(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    roots: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
            "import_module", "__import__"
        ):
            for arg in node.args[:1]:
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    roots.add(arg.value.split(".")[0])
    return roots


def test_flight_software_sources_import_no_simulator_or_truth():
    offenders = {}
    files = [f for pkg in FLIGHT_PACKAGES for f in (ROOT / pkg).rglob("*.py")]
    assert files, "no flight-software sources found"
    for f in files:
        bad = _imported_roots(f) & FORBIDDEN_ROOTS
        if bad:
            offenders[str(f.relative_to(ROOT))] = sorted(bad)
    assert not offenders, f"flight software imports simulator/truth modules: {offenders}"


def test_the_scan_catches_a_forbidden_import(tmp_path):
    # The scan itself must be able to fail.
    f = tmp_path / "leak.py"
    f.write_text("import numpy\nfrom mujoco import MjModel\nimport importlib\nimportlib.import_module('bench.run')\n")
    assert _imported_roots(f) & FORBIDDEN_ROOTS == {"mujoco", "bench"}


def test_importing_all_flight_software_loads_no_mujoco():
    code = (
        "import pkgutil, importlib, sys\n"
        "for pkg in ('vision', 'gnc'):\n"
        "    m = importlib.import_module(pkg)\n"
        "    for info in pkgutil.walk_packages(m.__path__, pkg + '.'):\n"
        "        importlib.import_module(info.name)\n"
        "leaked = sorted(k for k in sys.modules if k.split('.')[0] in ('mujoco', 'models', 'bench'))\n"
        "assert not leaked, leaked\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
