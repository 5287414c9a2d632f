"""Issue 6's acceptance campaign (slow: about 15 minutes on 2 cores; ``make test-slow``).

Twenty cases of the default scenario, vision in the loop, every default
dispersion: the campaign finishes, lands at least 95 % of its cases, and is
identical case by case with 1 or 2 local workers and on the Ray backend.
"""

from __future__ import annotations

import pytest

from bench.campaign import mc
from bench.scenario import load_scenario

RUNS = 20
SEED = 1
MIN_LANDED = 0.95


@pytest.mark.slow
def test_twenty_case_default_campaign(tmp_path, monkeypatch):
    base = load_scenario(None)
    assert base.vision == "on" and base.tracks == "vision" and base.dispersions  # the default flies vision
    one = mc.run_campaign(base, RUNS, tmp_path / "w1", campaign_seed=SEED, workers=1, progress=False)
    assert [r["case"] for r in one] == list(range(RUNS))
    landed = sum(r["outcome"] == "landed" for r in one)
    failures = {r["case"]: (r["outcome"], r.get("error")) for r in one if r["outcome"] != "landed"}
    assert landed >= MIN_LANDED * RUNS, f"{landed}/{RUNS} landed; the others: {failures}"
    two = mc.run_campaign(base, RUNS, tmp_path / "w2", campaign_seed=SEED, workers=2, progress=False)
    assert [mc.landing_values(r) for r in two] == [mc.landing_values(r) for r in one]
    pytest.importorskip("ray", reason="the Ray extra is not installed: pip install 'landbench[ray]'")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)  # a local Ray instance, started and stopped by the campaign
    on_ray = mc.run_campaign(base, RUNS, tmp_path / "ray", campaign_seed=SEED, workers=2, backend="ray",
                             progress=False)
    assert [mc.landing_values(r) for r in on_ray] == [mc.landing_values(r) for r in one]
