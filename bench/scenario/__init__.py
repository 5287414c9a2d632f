"""The scenario: the validated schema of one landing, its Monte Carlo dispersions, seeding, and the bundled TOML scenarios.

The schema lives in :mod:`bench.scenario.schema`; its public names are
re-exported here, so ``from bench.scenario import load_scenario`` is the
stable path. Import order is one-way: schema -> dispersions -> seeding.
"""

from bench.scenario.dispersions import case_seeds
from bench.scenario.schema import (
    DEFAULT_SCENARIO,
    NS_PER_S,
    Scenario,
    ScenarioError,
    apply_dispersions,
    apply_override,
    default_scenario_text,
    load_scenario,
    scenario_from_dict,
    scenario_to_toml,
)

__all__ = [
    "DEFAULT_SCENARIO",
    "NS_PER_S",
    "Scenario",
    "ScenarioError",
    "apply_dispersions",
    "apply_override",
    "case_seeds",
    "default_scenario_text",
    "load_scenario",
    "scenario_from_dict",
    "scenario_to_toml",
]
