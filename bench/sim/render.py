"""Stand-alone views of the world: a camera frame at an altitude, a terrain map."""

from __future__ import annotations

from pathlib import Path


from bench.report.io import save_figure, write_npy, write_png
from bench.scenario import Scenario
from bench.sim.world_builder import (build_sensors, build_terrain, build_world, check_initial_position,
                                     place_above_target)
from models.camera import apply_detector_noise


def render_view(scenario: Scenario, altitude_m: float, out: Path, depth_out: Path | None = None,
                noise: bool = True) -> list[Path]:
    """Render the nadir camera ``altitude_m`` above the target, level and at rest.

    Args:
        scenario: The scenario (terrain, sun, camera).
        altitude_m: Camera height above the landing target [m].
        out: PNG path of the frame.
        depth_out: Optional .npy path for the z-depth image [m], (H, W) float32.
        noise: Apply the detector noise model.

    Returns:
        The paths written.
    """
    with build_world(scenario) as world:
        near, far = world.camera_cfg.near_m, world.clip_far_m
        if not near < altitude_m < far:  # outside the clip planes the frame is black and the depth the far plane
            raise ValueError(f"--altitude {altitude_m:g}: the camera draws from camera.near_m = {near:g} m to "
                             f"{far:g} m (4 x the terrain's size); allowed: an altitude between them")
        place_above_target(world, altitude_m)
        signal = world.render_signal()
        frame = apply_detector_noise(signal, scenario.camera, build_sensors(scenario).camera_rng) if noise else signal
        depth = world.render_depth() if depth_out is not None else None
    written = [write_png(out, frame)]
    if depth is not None:
        written.append(write_npy(depth_out, depth))
    return written


def draw_world(scenario: Scenario, out: Path) -> Path:
    """Hillshade of the terrain with the landing target and the start point marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    terrain = build_terrain(scenario)
    check_initial_position(scenario, terrain)  # as run refuses it: a start off the tile, or in the ground
    shade = terrain.hillshade(scenario.sun.elevation_deg, scenario.sun.azimuth_deg)
    half = terrain.size_m / 2.0
    fig, ax = plt.subplots(figsize=(7.5, 7))
    ax.imshow(shade, cmap="gray", origin="lower", extent=(-half, half, -half, half), vmin=0, vmax=1)
    ax.plot(0, 0, marker="+", color="red", markersize=18, mew=2, label="landing target")
    r0 = scenario.initial.r_BL_L_m
    ax.plot(r0[0], r0[1], marker="^", color="cyan", markersize=9, ls="none",
            label=f"start ({r0[0]:.0f}, {r0[1]:.0f}, {r0[2]:.0f}) m")
    ax.add_patch(plt.Circle((0, 0), scenario.terrain.target_clear_radius_m, fill=False, color="red", lw=1))
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(f"{scenario.name}: terrain seed {scenario.terrain_seed()}, "
                 f"{len(terrain.craters)} craters, {len(terrain.boulders)} boulders, "
                 f"sun el {scenario.sun.elevation_deg:.0f}° az {scenario.sun.azimuth_deg:.0f}°", fontsize=9)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path = save_figure(fig, out)
    plt.close(fig)
    return path
