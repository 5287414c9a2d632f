"""Packaging: the distribution ships every package of the source tree (a wheel, not just the editable install)."""

from __future__ import annotations

import tomllib
from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).resolve().parents[1]
TOP_LEVEL = ("bench", "gnc", "vision", "models")


def _packages_on_disk() -> set[str]:
    return {".".join(p.parent.relative_to(ROOT).parts) for top in TOP_LEVEL for p in (ROOT / top).rglob("__init__.py")
            if "__pycache__" not in p.parts}


def _packages_shipped() -> set[str]:
    """What setuptools puts in the wheel, read from pyproject.toml (an explicit list, or find's patterns)."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = tool.get("packages")
    if isinstance(listed, list):
        return set(listed)
    find = listed["find"] if isinstance(listed, dict) else {}
    return set(find_packages(str(ROOT), include=find.get("include", ["*"]), exclude=find.get("exclude", ())))


def test_every_package_on_disk_is_shipped():
    on_disk = _packages_on_disk()
    assert {"bench.maps", "bench.sim", "gnc", "vision", "models"} <= on_disk
    assert _packages_shipped() == on_disk


def test_the_console_command_and_the_package_data_are_declared():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["name"] == "landbench"
    assert project["project"]["scripts"]["landbench"] == "bench.cli:console_main"
    data = project["tool"]["setuptools"]["package-data"]
    assert (ROOT / "bench/scenario/default.toml").is_file() and "*.toml" in data["bench.scenario"]
