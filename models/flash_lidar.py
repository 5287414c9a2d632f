"""Simulated flash lidar (truth side, NumPy): one range image per flash, ray-marched against the fine truth DEM.

Inputs: the sensor's truth pose (its position in L and the rotation from its
frame S to L), a :class:`models.site_dem.SiteDem` that covers its footprint,
and :class:`FlashLidarConfig`; the range noise comes from the passed-in
generator.
Output: :class:`gnc.messages.LidarScanMessage`: ranges (NaN: no return) and the
sensor's nominal geometry (field of view, pixel count, mounting), which is all
the flight software gets.
Rate: on demand (the flight software asks for a flash at its scan altitude).

Geometry: the sensor frame S follows the camera's convention (x right, y down,
z along the boresight); pixel (row i, column j) looks along
``normalize([t_j, t_i, 1])`` with ``t_k = tan(fov/2) * (2 (k + 0.5) / N - 1)``
(a pinhole grid of N x N rays over the full field ``fov_deg`` edge to edge),
the same function the flight software uses (:func:`gnc.messages.lidar_ray_dirs_S`).
The sensor is co-boresighted with the camera (``R_BS = R_BC``: nadir when the
lander is upright), ``mount_B_m`` below the body origin.

Ray marching: along each ray from where it is at the DEM's highest point down
to where it is at its lowest, the ray's height above the bilinear DEM is
sampled every ``march_step_m`` of height (a horizontal step of at most
``march_step_m * tan(angle off vertical)``: 2 cm for a 5 cm step at 20 deg,
finer than the 0.1 m posts), and the first sign change is refined by the
secant (the bilinear surface is close to planar between two samples).
Vectorised over all rays. Then white range noise of ``range_sigma_m`` is added
and rays beyond ``max_range_m`` or off the DEM return NaN.

Why not ``mj_multiRay``: the physics heightfield is the coarse 8 m grid, which
carries no boulder; the hazards exist only in the fine truth DEM.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gnc.messages import LidarScanMessage, lidar_ray_dirs_S
from models.site_dem import SiteDem


MOUNT_MAX_M = 10.0  # the lidar sits on the vehicle: each mount axis within this of the body origin [m]
MARCH_STEP_MIN_M = 0.005  # finest ray-march step [m]: 1e-9 m marched for ever
FOV_MIN_DEG = 0.5  # narrowest field of view [deg] (ALHAT's flash lidar: about 1 deg at 1 km)
FOOTPRINT_TILT_DEG = 10.0  # attitude allowance of a scan's footprint [deg]


def footprint_half_m(fov_deg: float, range_m: float, tilt_deg: float = FOOTPRINT_TILT_DEG) -> float:
    """Half-side of a square that holds the footprint of a lidar of this field of view at this slant range
    with this much tilt [m] (the diagonal's half-angle plus the tilt, and 2 m)."""
    return range_m * math.tan(math.radians(fov_deg / 2 * math.sqrt(2) + tilt_deg)) + 2.0


class FlashLidarConfig(BaseModel):
    """The flash lidar's specification (the flight software knows these nominal values)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    pixels: int = Field(256, ge=8, le=1024, description="rays per side of the square range image [-]")
    fov_deg: float = Field(20.0, ge=FOV_MIN_DEG, lt=90.0, description="full field of view, edge to edge [deg]")
    range_sigma_m: float = Field(0.03, ge=0.0, le=1.0, description="1-sigma white range noise [m]")
    max_range_m: float = Field(1000.0, gt=0.0, description="no return beyond this range [m]")
    mount_B_m: tuple[float, float, float] = Field(
        (0.0, 0.0, -0.5), description="sensor position in the body frame [m] (boresight = the camera's); on the "
                                      "vehicle: each axis within 10 m of the body origin")
    march_step_m: float = Field(
        0.05, ge=MARCH_STEP_MIN_M, le=1.0,
        description="ray-march step in height [m] (the march's cost grows as relief / step: at least 5 mm, a "
                    "tenth of the finest range noise worth modelling)")

    @field_validator("mount_B_m")
    @classmethod
    def _on_the_vehicle(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        # 150 m below the body put the sensor under the ground: its site DEM had a negative size mid-flight.
        if max(abs(c) for c in v) > MOUNT_MAX_M:
            raise ValueError(f"{list(v)} puts the lidar off the vehicle; allowed: each axis within {MOUNT_MAX_M:g} m "
                             "of the body origin")
        return v


def ray_ranges(origin_L: np.ndarray, dirs_L: np.ndarray, dem: SiteDem, step_m: float = 0.05) -> np.ndarray:
    """Range to the first intersection of each ray with the DEM's bilinear surface [m] (NaN: none).

    Args:
        origin_L: Ray origin in L (3,) [m], above the DEM.
        dirs_L: Unit directions in L (n, 3), pointing down (d_z < 0).
        dem: The surface.
        step_m: Height step of the march [m].

    Returns:
        (n,) ranges [m].
    """
    o = np.asarray(origin_L, float)
    d = np.asarray(dirs_L, float)
    n = d.shape[0]
    out = np.full(n, np.nan)
    down = d[:, 2] < -1e-6
    if not down.any():
        return out
    h = dem.height_m
    z_hi, z_lo = float(np.max(h)), float(np.min(h))
    dz = -d[down, 2]
    t0 = np.maximum((o[2] - z_hi) / dz, 0.0) - 1e-6
    t1 = (o[2] - z_lo) / dz + 1e-6
    steps = int(math.ceil((z_hi - z_lo) / step_m)) + 1
    dd = d[down]
    t_prev = t0
    f_prev = o[2] + t_prev * dd[:, 2] - dem.height_at(o[0] + t_prev * dd[:, 0], o[1] + t_prev * dd[:, 1])
    hit = np.full(dd.shape[0], np.nan)
    open_ = np.ones(dd.shape[0], bool)
    for k in range(1, steps + 1):
        t = t0 + (t1 - t0) * (k / steps)
        f = o[2] + t * dd[:, 2] - dem.height_at(o[0] + t * dd[:, 0], o[1] + t * dd[:, 1])
        cross = open_ & (f <= 0.0) & np.isfinite(f_prev)
        if cross.any():
            # Secant between the last sample above and the first below.
            frac = f_prev[cross] / (f_prev[cross] - f[cross])
            hit[cross] = t_prev[cross] + frac * (t[cross] - t_prev[cross])
            open_ &= ~cross
        open_ &= np.isfinite(f) | ~np.isfinite(f_prev)  # a ray that left the DEM has no return
        if not open_.any():
            break
        t_prev, f_prev = t, f
    out[down] = hit
    return out


class FlashLidar:
    """A flash lidar with its own noise stream.

    Args:
        cfg: The specification.
        rng: The range-noise stream (the run's "lidar" stream).
    """

    def __init__(self, cfg: FlashLidarConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.dirs_S = lidar_ray_dirs_S(cfg.pixels, cfg.fov_deg)

    def footprint_half_m(self, range_m: float, tilt_deg: float = FOOTPRINT_TILT_DEG) -> float:
        """Half-side of a square that holds the footprint at this slant range with this much tilt [m]."""
        return footprint_half_m(self.cfg.fov_deg, range_m, tilt_deg)

    def scan(self, t_ns: int, r_SL_L: np.ndarray, R_LS: np.ndarray, R_BS: np.ndarray,
             dem: SiteDem) -> LidarScanMessage:
        """One flash from the truth pose.

        Args:
            t_ns: Time of the flash [ns].
            r_SL_L: Sensor position in L (3,) [m].
            R_LS: Sensor-to-L rotation (3, 3).
            R_BS: The nominal mounting (sensor-to-body rotation) the message states (3, 3).
            dem: Fine truth DEM covering the footprint.

        Returns:
            The message.
        """
        cfg = self.cfg
        dirs_L = self.dirs_S.reshape(-1, 3) @ np.asarray(R_LS, float).T
        rng_m = ray_ranges(r_SL_L, dirs_L, dem, cfg.march_step_m)
        noise = self.rng.standard_normal(rng_m.shape) * cfg.range_sigma_m
        rng_m = rng_m + noise
        rng_m[~(rng_m <= cfg.max_range_m)] = np.nan
        return LidarScanMessage(t_ns=int(t_ns), ranges_m=rng_m.reshape(cfg.pixels, cfg.pixels),
                                fov_deg=cfg.fov_deg, R_BS=np.asarray(R_BS, float).copy(),
                                r_SB_m=np.asarray(cfg.mount_B_m, float))
