"""``landbench compare``'s HTML report: self-contained, and rendered by a real browser.

The inputs are tiny synthetic campaign and replay folders (``tests.test_compare``,
``tests.replay_synth``), so every test runs in seconds. The browser test opens
``report.html`` in headless Debian Chromium (``/usr/bin/chromium``, installed by
``scripts/bootstrap.sh``) with every network path closed, and checks in the
DOM after the scripts ran that plotly drew every figure (``main-svg``) and
that the tables and flipped cases are there. Without Chromium it is skipped
locally and fails under CI (``CI`` set).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from bench.cli import main
from bench.evaluation import compare as cmp
from bench.report import compare_html
from bench.report.mc_report import wilson_interval
from tests.replay_synth import replay_pair
from tests.test_compare import write_campaign

CHROMIUM = os.environ.get("LANDBENCH_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--host-resolver-rules=MAP * ~NOTFOUND",  # no name resolves: a CDN script could not load
                  "--virtual-time-budget=10000")  # let plotly's scripts finish before the DOM is dumped
N = 12
FLIPPED = {2: "lost", 7: "gained", 9: "lost"}


def _campaign_rows(landed: list[bool], miss: np.ndarray, seeds: list[int]) -> list[dict]:
    return [{"case": i, "seed": seeds[i], "disp_lander.dry_mass_kg": 1500.0 + i,
             "outcome": "landed" if landed[i] else "tipped_over", "landed": landed[i],
             "touchdown_miss_distance_m": float(miss[i]), "fuel_used_kg": 80.0 + i} for i in range(len(seeds))]


@pytest.fixture(scope="module")
def campaign_cmp(tmp_path_factory) -> Path:
    """compare's output folder for two 12-case campaigns with cases 2 and 9 lost and 7 gained."""
    root = tmp_path_factory.mktemp("cmp_report")
    rng = np.random.default_rng(3)
    seeds = [1000 + i for i in range(N)]
    landed_b = [i != 7 for i in range(N)]
    landed_c = [i not in (2, 9) for i in range(N)]
    miss = rng.uniform(1.0, 30.0, N)
    base = write_campaign(root / "base", _campaign_rows(landed_b, miss, seeds))
    cand = write_campaign(root / "cand", _campaign_rows(landed_c, miss + rng.normal(2.0, 0.5, N), seeds))
    out = root / "cmp"
    assert main(["compare", str(base), str(cand), "--gate", "success_rate:-2pp",
                 "--gate", "touchdown_miss_distance_m:+1", "--out", str(out)]) == 1
    return out


@pytest.fixture(scope="module")
def replay_cmp(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cmp_report_replay")
    base, cand, _ = replay_pair(root)
    out = root / "cmp"
    assert main(["compare", str(base), str(cand), "--gate", "epe_median_px:+10%", "--out", str(out)]) == 1
    return out


def _no_network_references(html: str) -> None:
    """No external script, stylesheet, frame, image or font: the page needs no network."""
    assert not re.search(r"<script[^>]*\bsrc\s*=", html, re.I), "a <script src=...> tag"
    assert not re.search(r"<link\b", html, re.I), "a <link> tag"
    assert not re.search(r"<(img|iframe|source|embed)\b[^>]*\bsrc\s*=\s*[\"']?https?:", html, re.I)
    assert not re.search(r"@import|url\(\s*[\"']?https?:", html.split("<script", 1)[0], re.I)  # CSS before the JS


# ------------------------------------------------------------------ the page itself
def test_report_is_written_beside_compare_json_and_is_self_contained(campaign_cmp):
    html = (campaign_cmp / compare_html.REPORT_HTML).read_text(encoding="utf-8")
    _no_network_references(html)
    from plotly.offline import get_plotlyjs

    assert get_plotlyjs() in html  # plotly.js itself, inline
    doc = json.loads((campaign_cmp / cmp.COMPARE_JSON).read_text())
    # Every flipped case, with both replay commands (HTML-escaped as jinja writes them).
    for f in doc["flipped"]:
        assert f"BASE: {f['replay']['base']}" in html and f"CAND: {f['replay']['cand']}" in html
    assert sorted(f["case"] for f in doc["flipped"]) == sorted(FLIPPED)
    for name in ("success-table", "mcnemar-table", "gates-table", "flipped-table", "metrics-table"):
        assert f'id="{name}"' in html, name
    assert "FAILED gates: success_rate:-2pp, touchdown_miss_distance_m:+1" in html


def test_report_from_the_same_document_is_the_same_page(campaign_cmp):
    doc = json.loads((campaign_cmp / cmp.COMPARE_JSON).read_text())
    assert compare_html.render_compare_html(doc) == (campaign_cmp / compare_html.REPORT_HTML).read_text("utf-8")


def test_too_small_a_campaign_is_said_plainly_with_its_wilson_intervals():
    # The example: 95 of 100 landed gives a Wilson 95 % interval of 88.8-97.8 %.
    lo, hi = wilson_interval(95, 100)
    assert (round(100 * lo, 1), round(100 * hi, 1)) == (88.8, 97.8)
    ok = np.arange(100) >= 5
    cand = ok.copy()
    cand[[10, 20]] = False  # 93/100 on the other side: not resolvable
    text = compare_html.success_statement(cmp._success(ok, cand), 100)
    assert "BASE landed 95/100 (95.0 %, Wilson 95 % interval 88.8–97.8 %)" in text
    assert "100 cases are too few to resolve a difference" in text and "Run more cases" in text
    lost = np.ones(100, bool)
    lost[:40] = False
    resolved = compare_html.success_statement(cmp._success(np.ones(100, bool), lost), 100)
    assert "is resolved" in resolved and "too few" not in resolved
    apart = compare_html.success_statement(cmp._success(np.ones(4, bool), np.zeros(4, bool)), 4)
    assert "4 cases are too few" in apart and "do not overlap, but the cases are paired" in apart


def test_a_replay_report_has_the_per_frame_tables(replay_cmp):
    html = (replay_cmp / compare_html.REPORT_HTML).read_text(encoding="utf-8")
    _no_network_references(html)
    for name in ("metrics-table", "frame-metrics-table", "frame-booleans-table", "gates-table"):
        assert f'id="{name}"' in html, name
    assert 'id="flipped-table"' not in html and "open-loop replays do not land" in html


# ------------------------------------------------------------------ in a real browser
def _chromium() -> str:
    if shutil.which(CHROMIUM) or os.path.isfile(CHROMIUM):
        return CHROMIUM
    reason = (f"headless Chromium not found at {CHROMIUM}: install Debian's chromium package "
              "(scripts/bootstrap.sh does, through apt) or set LANDBENCH_CHROMIUM")
    if os.environ.get("CI"):
        pytest.fail(f"CI is set, so the browser test must run: {reason}")
    pytest.skip(reason)


def _dump_dom(page: Path, tmp_path: Path) -> str:
    argv = [_chromium(), *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--dump-dom",
            page.resolve().as_uri()]
    res = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


@pytest.mark.parametrize("which", ["campaign", "replay"])
def test_the_report_renders_in_headless_chromium(which, campaign_cmp, replay_cmp, tmp_path):
    out = campaign_cmp if which == "campaign" else replay_cmp
    html = (out / compare_html.REPORT_HTML).read_text(encoding="utf-8")
    dom = _dump_dom(out / compare_html.REPORT_HTML, tmp_path)
    n_plots = html.count('<div class="plot" data-metric=')
    assert n_plots >= (2 if which == "campaign" else 4)
    # Plotly ran: each figure's div became a js-plotly-plot holding its main-svg and its points.
    assert "main-svg" not in html.split("<body>", 1)[1].split("<script", 1)[0]  # not in the page as written
    assert dom.count("js-plotly-plot") >= n_plots
    assert dom.count('class="main-svg"') >= n_plots
    doc = json.loads((out / cmp.COMPARE_JSON).read_text())
    assert dom.count('class="point"') >= doc["n_cases"]  # the scatter markers were drawn
    assert 'id="metrics-table"' in dom and 'id="gates-table"' in dom
    if which == "campaign":
        rows = re.findall(r'<tr class="flipped">(.*?)</tr>', dom, re.S)
        assert len(rows) == len(FLIPPED)
        for f in doc["flipped"]:
            assert f"--case {f['case']} --out" in dom
    else:
        assert 'id="frame-booleans-table"' in dom and dom.count("js-plotly-plot") >= n_plots
