"""Stable import path for one landing: ``from bench.run import run``.

The implementation lives in :mod:`bench.sim.run`; this thin module re-exports
its public entry points so scripts written against ``bench.run`` keep working.
Patch behaviour (e.g. with ``monkeypatch``) on :mod:`bench.sim.run`, the
module that uses the names.
"""

from bench.sim.run import RunResult, build_flight_software, handover_estimate, onboard_knowledge, run

__all__ = ["RunResult", "build_flight_software", "handover_estimate", "onboard_knowledge", "run"]
