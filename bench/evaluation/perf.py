"""``landbench perf``: rendering and physics speed of the truth world.

Reported, all on the scenario's terrain:
    * terrain generation and world build time [s];
    * render time per frame at 256^2 and 512^2 [ms] (median and mean over the
      timed frames, the camera sweeping down a descent so caching cannot
      flatter it), with and without the detector noise model;
    * physics steps per second in free flight and at rest on the ground;
    * with ``--campaign N``, instead: Monte Carlo throughput [cases/h] of the
      same N cases at 1 and 2 workers (or ``--campaign-workers``), the
      speed-up over the first count, and each worker's peak memory [MB].

These are figures for the README, not pass/fail tests: CI machines are noisy.
"""

from __future__ import annotations

import time

import numpy as np

from bench.scenario import Scenario
from bench.sim.world_builder import build_sensors, build_world, generate_scenario_terrain, place_above_target
from models.camera import apply_detector_noise

RESOLUTIONS_PX = (256, 512)
PHYSICS_STEPS = 20_000
WARMUP_FRAMES = 3


def _time_renders(scenario: Scenario, terrain, size_px: int, frames: int) -> dict[str, float]:
    sc = scenario.model_copy(update={"camera": scenario.camera.model_copy(update={"width_px": size_px, "height_px": size_px})})
    rng = build_sensors(sc).camera_rng
    with build_world(sc, terrain) as world:
        altitudes = np.geomspace(scenario.initial.r_BL_L_m[2], 30.0, frames)
        place_above_target(world, float(altitudes[0]))
        for _ in range(WARMUP_FRAMES):
            world.render_signal()
        render_ms, noisy_ms = [], []
        for h in altitudes:
            place_above_target(world, float(h))
            t0 = time.perf_counter()
            signal = world.render_signal()
            t1 = time.perf_counter()
            apply_detector_noise(signal, sc.camera, rng)
            t2 = time.perf_counter()
            render_ms.append((t1 - t0) * 1e3)
            noisy_ms.append((t2 - t0) * 1e3)
    return {
        "render_ms_median": float(np.median(render_ms)),
        "render_ms_mean": float(np.mean(render_ms)),
        "render_plus_noise_ms_median": float(np.median(noisy_ms)),
    }


def _physics_rate(scenario: Scenario, terrain, on_ground: bool) -> float:
    with build_world(scenario, terrain) as world:
        if on_ground:
            place_above_target(world, 0.0)
            world.reset(np.array([0.0, 0.0, scenario.lander.footpad_clearance_m + 0.05]), np.zeros(3),
                        np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
            hover = 0.0
        else:
            hover = world.truth().mass_kg * scenario.sim.gravity_mps2
        chunk = max(1, scenario.sim.control_period_ns // scenario.sim.physics_dt_ns)
        t0 = time.perf_counter()
        for _ in range(PHYSICS_STEPS // chunk):
            world.step(chunk, hover, np.zeros(3))
        return (PHYSICS_STEPS // chunk) * chunk / (time.perf_counter() - t0)


def run_perf(scenario: Scenario, frames: int = 60) -> dict:
    """Measure and return the figures as a dict (see module docstring)."""
    if frames < 1:
        raise ValueError(f"--frames {frames}: must be >= 1")
    t0 = time.perf_counter()
    terrain = generate_scenario_terrain(scenario)  # not the process cache: this times the generation
    t_terrain = time.perf_counter() - t0
    t0 = time.perf_counter()
    with build_world(scenario, terrain) as world:
        world.render_signal()
    t_build = time.perf_counter() - t0
    result: dict = {
        "terrain": {
            "geometry_px": int(terrain.height_m.shape[0]),
            "texture_px": int(terrain.albedo.shape[0]),
            "size_m": float(terrain.size_m),
            "generate_s": t_terrain,
        },
        "world_build_first_frame_s": t_build,
        "shadows": scenario.sun.shadows,
        "render": {f"{s}x{s}": _time_renders(scenario, terrain, s, frames) for s in RESOLUTIONS_PX},
        "physics_steps_per_s": {
            "free_flight": _physics_rate(scenario, terrain, on_ground=False),
            "on_ground_contacts": _physics_rate(scenario, terrain, on_ground=True),
        },
        "physics_dt_ns": scenario.sim.physics_dt_ns,
    }
    return result


def format_perf(r: dict) -> str:
    lines = [
        f"terrain: {r['terrain']['geometry_px']}^2 geometry, {r['terrain']['texture_px']}^2 texture over "
        f"{r['terrain']['size_m']:.0f} m; generated in {r['terrain']['generate_s']:.2f} s; "
        f"world build + first frame {r['world_build_first_frame_s']:.2f} s; shadows {'on' if r['shadows'] else 'off'}",
    ]
    for res, v in r["render"].items():
        lines.append(
            f"render {res}: {v['render_ms_median']:.1f} ms/frame median ({v['render_ms_mean']:.1f} mean), "
            f"{v['render_plus_noise_ms_median']:.1f} ms with detector noise"
        )
    p = r["physics_steps_per_s"]
    lines.append(
        f"physics: {p['free_flight']:,.0f} steps/s in flight, {p['on_ground_contacts']:,.0f} steps/s on the ground "
        f"(dt = {r['physics_dt_ns'] / 1e6:g} ms)"
    )
    return "\n".join(lines)


# ------------------------------------------------------------ campaign speed
def run_campaign_perf(scenario: Scenario, runs: int, workers: tuple[int, ...] = (1, 2), campaign_seed: int = 1,
                      backend: str = "local") -> dict:
    """Throughput of the same campaign at several worker counts (``landbench perf --campaign N``).

    The same ``runs`` cases (same campaign seed) are flown once per worker
    count, one after the other in this process, so the ratio compares like
    with like on the same machine at the same time.

    Args:
        scenario: Base scenario (its dispersions are drawn per case).
        runs: Cases per campaign.
        workers: Worker counts to time; the first is the baseline of the speed-ups.
        campaign_seed: Campaign seed.
        backend: ``local`` or ``ray``.

    Returns:
        ``{"runs", "backend", "results": {k: {wall_s, cases_per_hour, speedup,
        landed, peak_rss_mb_max, identical_to_baseline}}}``.
    """
    import tempfile
    from pathlib import Path

    from bench.campaign.mc import landing_values, run_campaign

    if runs < 1:
        raise ValueError(f"--campaign {runs}: must be >= 1 case")
    if not workers or min(workers) < 1:
        raise ValueError(f"--campaign-workers {list(workers)}: give worker counts >= 1, e.g. 1,2")
    results: dict[int, dict] = {}
    baseline = None
    with tempfile.TemporaryDirectory(prefix="landbench-perf-") as tmp:
        for k in workers:
            t0 = time.perf_counter()
            rows = run_campaign(scenario, runs, Path(tmp) / f"w{k}", campaign_seed, workers=k, backend=backend,
                                progress=False)
            wall_s = time.perf_counter() - t0
            values = [landing_values(r) for r in rows]
            baseline = baseline if baseline is not None else (values, wall_s)
            results[k] = {
                "wall_s": wall_s,
                "cases_per_hour": runs * 3600.0 / wall_s,
                "speedup": baseline[1] / wall_s,
                "landed": sum(r["outcome"] == "landed" for r in rows),
                "peak_rss_mb_max": max(float(r.get("case_peak_rss_mb", float("nan"))) for r in rows),
                "identical_to_baseline": values == baseline[0],
            }
    return {"runs": runs, "backend": backend, "campaign_seed": campaign_seed, "results": results}


def format_campaign_perf(r: dict) -> str:
    lines = [f"campaign of {r['runs']} cases (seed {r['campaign_seed']}, backend {r['backend']}):"]
    for k, v in r["results"].items():
        lines.append(
            f"  {k} worker{'s' if k > 1 else ' '}: {v['wall_s']:7.1f} s, {v['cases_per_hour']:6.0f} cases/h "
            f"({v['speedup']:.2f}x), {v['landed']}/{r['runs']} landed, peak memory per worker "
            f"{v['peak_rss_mb_max']:.0f} MB, cases identical to the first: {'yes' if v['identical_to_baseline'] else 'NO'}")
    return "\n".join(lines)
