"""A rendered descent: camera frames with truth depth and camera poses.

Used by ``landbench track-eval`` and ``landbench vision-figures`` to score the
vision tracker without the closed loop. The trajectory is kinematic: the
lander is placed at each pose, not flown.

Trajectory (from the scenario's initial state down to the vision cut-off):
    * altitude falls exponentially, ``h(t) = h0 exp(-t / tau)``, so the
      image scale changes by the same fraction every frame, as in a
      constant-time-to-go descent (vertical speed proportional to altitude);
    * the horizontal offset shrinks in proportion to altitude (a straight
      approach down a cone to the target);
    * the attitude wobbles by a few degrees and the yaw drifts, as a real
      attitude loop would, so the image motion is not a pure zoom.
Frames are taken at the camera period; ``tau`` is chosen so that
``n_frames`` frames span the descent from ``h0`` to ``cutoff_altitude_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bench.scenario import Scenario
from bench.sim.world_builder import build_sensors, build_terrain, build_world

NS_PER_S = 1_000_000_000
WOBBLE_AMPLITUDE_DEG = 2.0  # roll/pitch oscillation of the attitude loop
WOBBLE_PERIOD_S = 9.0
YAW_RATE_DEG_S = 0.8


@dataclass
class Descent:
    """A rendered descent.

    Attributes:
        t_ns: Frame times, (N,) int64 [ns].
        frames: Camera frames with detector noise, (N, H, W) uint8.
        depths: Truth z-depth, (N, H, W) float32 [m].
        R_LC: Camera-to-L rotations, (N, 3, 3).
        r_CL_L: Camera positions in L, (N, 3) [m].
        K: Intrinsics, (3, 3) [px].
    """

    t_ns: np.ndarray
    frames: np.ndarray
    depths: np.ndarray
    R_LC: np.ndarray
    r_CL_L: np.ndarray
    K: np.ndarray


def descent_poses(scenario: Scenario, n_frames: int, cutoff_altitude_m: float = 30.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body poses of the kinematic descent.

    Returns:
        (t_ns (N,), r_BL_L (N, 3) [m], q_LB (N, 4)).
    """
    if n_frames < 2:
        raise ValueError(f"frames = {n_frames}: need at least 2 frames")
    r0 = np.array(scenario.initial.r_BL_L_m, float)
    h0 = float(r0[2])
    if not h0 > cutoff_altitude_m:
        raise ValueError(
            f"initial.r_BL_L_m altitude {h0} m must be above the vision cut-off {cutoff_altitude_m} m for a descent"
        )
    period_s = scenario.camera.period_ns / NS_PER_S
    t_ns = np.arange(n_frames, dtype=np.int64) * scenario.camera.period_ns
    t_s = t_ns / NS_PER_S
    tau_s = (n_frames - 1) * period_s / math.log(h0 / cutoff_altitude_m)
    h = h0 * np.exp(-t_s / tau_s)
    r = np.column_stack([r0[0] * h / h0, r0[1] * h / h0, h])
    phase = 2 * math.pi * t_s / WOBBLE_PERIOD_S
    euler = np.column_stack([
        WOBBLE_AMPLITUDE_DEG * np.sin(phase),
        WOBBLE_AMPLITUDE_DEG * np.sin(0.7 * phase + 1.0),
        YAW_RATE_DEG_S * t_s,
    ])
    q = Rotation.from_euler("xyz", euler, degrees=True) * Rotation.from_quat(scenario.initial.q_LB(), scalar_first=True)
    return t_ns, r, q.as_quat(scalar_first=True)


def render_descent(scenario: Scenario, n_frames: int, cutoff_altitude_m: float = 30.0, with_depth: bool = True) -> Descent:
    """Render the kinematic descent of the scenario (see module docstring)."""
    t_ns, r_BL_L, q_LB = descent_poses(scenario, n_frames, cutoff_altitude_m)
    sensors = build_sensors(scenario)
    H, W = scenario.camera.height_px, scenario.camera.width_px
    frames = np.empty((n_frames, H, W), np.uint8)
    depths = np.empty((n_frames, H, W), np.float32) if with_depth else np.empty((0, H, W), np.float32)
    R_LC = np.empty((n_frames, 3, 3))
    r_CL_L = np.empty((n_frames, 3))
    with build_world(scenario, build_terrain(scenario)) as world:
        for k in range(n_frames):
            world.set_pose(r_BL_L[k], q_LB[k])
            frames[k] = sensors.camera_frame(world)
            if with_depth:
                depths[k] = world.render_depth()
            R_LC[k], r_CL_L[k] = world.camera_pose()
        K = world.K.copy()
    return Descent(t_ns=t_ns, frames=frames, depths=depths, R_LC=R_LC, r_CL_L=r_CL_L, K=K)
