"""ALHAT-style hazard map and safe-site choice from a DEM (flight software, NumPy + OpenCV).

Ports:
    Inputs: a DEM of the landing area (e.g. from a flash lidar), a (rows, cols)
        float grid of heights [m], south-up (row index increases with +y,
        column with +x), post spacing ``spacing_m`` and the L coordinates of
        post (0, 0); the lander's nominal leg geometry; :class:`HazardConfig`.
        For the site choice also the current target and the navigation
        error's 1-sigma.
    Output: :class:`HazardMap` (per post, as the lander's centre: worst-yaw
        tilt, roughness, unsafe mask, distance to the nearest hazard) and
        :class:`SafeSite` (or None: no safe site within the divert limit).
    Rate: once per hazard scan (a hover or slow pass near 100 m).

Every post is a candidate position of the lander's centre (the vertical
through its body axis). For each:

* **Pad heights**: the highest point under each footpad, a grey dilation of
  the DEM by a disk of ``footpad_radius_m``, read at the pad's offset.
* **Plane through the pads, worst yaw**: the four pads sit at
  ``leg_radius_m`` on the diagonals of the body (at the nearest posts), at
  yaw ``psi``. A four-legged lander rests on three pads whose plane has the
  fourth on or below it (it may rock between two such planes), so the tilt
  is the largest over those planes, and over ``yaw_count`` yaws spread over
  90 deg (the pads' symmetry): the yaw at touchdown is not controlled to
  better than that.
* **Roughness**: the highest point within ``body_radius_m`` of the centre
  above the terrain's local mean surface (the box mean over the body's
  square, which is the least-squares plane evaluated at its centre, so a
  plane of any slope has no roughness): a rock under the body.
* **Unsafe**: tilt above ``slope_max_deg`` or roughness above
  ``roughness_max_m``, or a footprint that leaves the DEM.

Safe site: among safe posts at least ``nav_sigmas`` navigation sigmas from
the nearest unsafe post (so the lander's own error keeps it on safe ground)
and within ``max_divert_m`` of the current target, the one of least cost
``w_divert * divert / max_divert + w_slope * tilt / slope_max
+ w_margin * (1 - min(margin, margin_cap) / margin_cap)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class HazardConfig(BaseModel):
    """Hazard thresholds, the lander's nominal legs, and the site choice's weights."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    slope_max_deg: float = Field(10.0, gt=0.0, lt=45.0, description="largest safe tilt of the pads' plane [deg]")
    roughness_max_m: float = Field(0.3, gt=0.0, description="largest safe rock height under the body [m]")
    leg_radius_m: float = Field(2.2, gt=0.0, description="horizontal distance of each footpad from the axis [m]")
    footpad_radius_m: float = Field(0.2, gt=0.0, description="radius of the ground a footpad rests on [m]")
    body_radius_m: float = Field(2.2, gt=0.0, description="radius under the body checked for rocks [m]")
    yaw_count: int = Field(6, ge=1, le=90, description="yaws tried, spread evenly over 90 deg [-]")
    nav_sigmas: float = Field(3.0, ge=0.0, description="margin to the nearest hazard, in navigation sigmas [-]")
    max_divert_m: float = Field(50.0, gt=0.0, description="largest divert from the current target [m]")
    w_divert: float = Field(1.0, ge=0.0, description="cost weight of the divert distance [-]")
    w_slope: float = Field(0.5, ge=0.0, description="cost weight of the tilt [-]")
    w_margin: float = Field(1.0, ge=0.0, description="cost weight of a small margin to hazards [-]")
    margin_cap_m: float = Field(10.0, gt=0.0, description="margins beyond this count as this [m]")


@dataclass(frozen=True, eq=False)
class HazardMap:
    """Hazard map on the DEM's grid (each post as the lander's centre).

    Attributes:
        tilt_deg: (rows, cols) worst-yaw tilt of the pads' plane [deg] (NaN where the footprint leaves the DEM).
        roughness_m: (rows, cols) highest rock under the body above the local mean surface [m] (NaN likewise).
        unsafe: (rows, cols) bool.
        hazard_distance_m: (rows, cols) distance to the nearest unsafe post [m] (0 on unsafe posts).
        spacing_m: Post spacing [m].
        origin_xy_m: L coordinates of post (0, 0) [m].
    """

    tilt_deg: np.ndarray
    roughness_m: np.ndarray
    unsafe: np.ndarray
    hazard_distance_m: np.ndarray
    spacing_m: float
    origin_xy_m: tuple[float, float]

    def xy_of(self, row: np.ndarray | int, col: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """L coordinates of posts [m]."""
        return (self.origin_xy_m[0] + np.asarray(col) * self.spacing_m,
                self.origin_xy_m[1] + np.asarray(row) * self.spacing_m)


@dataclass(frozen=True)
class SafeSite:
    """The chosen landing site.

    Attributes:
        xy_m: Site in L (2,) [m]; divert_m: from the current target [m]; margin_m: to the nearest hazard [m];
        tilt_deg: worst-yaw tilt there [deg]; cost: its cost [-].
    """

    xy_m: np.ndarray
    divert_m: float
    margin_m: float
    tilt_deg: float
    cost: float


def _disk(radius_px: float) -> np.ndarray:
    r = max(int(math.floor(radius_px)), 0)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return (x * x + y * y <= radius_px * radius_px + 1e-9).astype(np.uint8)


def _shift(a: np.ndarray, drow: int, dcol: int, fill: float) -> np.ndarray:
    """out[i, j] = a[i + drow, j + dcol], ``fill`` outside."""
    out = np.full_like(a, fill)
    rows, cols = a.shape
    r0, r1 = max(0, -drow), min(rows, rows - drow)
    c0, c1 = max(0, -dcol), min(cols, cols - dcol)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = a[r0 + drow:r1 + drow, c0 + dcol:c1 + dcol]
    return out


def hazard_map(dem_m: np.ndarray, spacing_m: float, origin_xy_m: tuple[float, float] = (0.0, 0.0),
               cfg: HazardConfig | None = None, known: np.ndarray | None = None) -> HazardMap:
    """The hazard map of a DEM (see the module's docstring).

    Args:
        dem_m: (rows, cols) heights [m], south-up.
        spacing_m: Post spacing [m].
        origin_xy_m: L coordinates of post (0, 0) [m].
        cfg: Thresholds and geometry.
        known: (rows, cols) bool, posts with data (None: all). A post whose footprint (pads and body)
            touches an unknown post is unsafe: unknown ground counts as a hazard.

    Returns:
        The hazard map.
    """
    cfg = cfg if cfg is not None else HazardConfig()
    dem = np.ascontiguousarray(dem_m, dtype=np.float32)
    if dem.ndim != 2 or min(dem.shape) < 3:
        raise ValueError(f"dem_m has shape {dem.shape}; expected a 2-D grid of at least 3 x 3 posts")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m={spacing_m} must be > 0")
    pad_top = cv2.dilate(dem, _disk(cfg.footpad_radius_m / spacing_m), borderType=cv2.BORDER_REPLICATE)
    nan = np.float32(np.nan)
    R = cfg.leg_radius_m
    tilt_tan = np.zeros_like(dem)
    for k in range(cfg.yaw_count):
        psi = math.radians(45.0 + 90.0 * k / cfg.yaw_count)  # pads on the body's diagonals
        offs, h = [], []
        for q in range(4):  # around the square
            ang = psi + q * math.pi / 2
            di, dj = int(round(R * math.sin(ang) / spacing_m)), int(round(R * math.cos(ang) / spacing_m))
            offs.append(np.array([dj * spacing_m, di * spacing_m]))  # the pad's actual (post) position [m]
            h.append(_shift(pad_top, di, dj, nan))
        for skip in range(4):  # the plane through the other three; the lander can rest on it if pad `skip` is not above
            p0, p1, p2 = (q for q in range(4) if q != skip)
            inv = np.linalg.inv(np.array([offs[p1] - offs[p0], offs[p2] - offs[p0]]))
            dz1, dz2 = h[p1] - h[p0], h[p2] - h[p0]
            gx = np.float32(inv[0, 0]) * dz1 + np.float32(inv[0, 1]) * dz2
            gy = np.float32(inv[1, 0]) * dz1 + np.float32(inv[1, 1]) * dz2
            ds = offs[skip] - offs[p0]
            plane_at_skip = h[p0] + gx * np.float32(ds[0]) + gy * np.float32(ds[1])
            rests = h[skip] <= plane_at_skip + np.float32(1e-6)
            np.fmax(tilt_tan, np.where(rests, np.hypot(gx, gy), np.float32(0.0)), out=tilt_tan)
    tilt_deg = np.degrees(np.arctan(tilt_tan))

    side = 2 * int(round(cfg.body_radius_m / spacing_m)) + 1
    mean = cv2.blur(dem, (side, side), borderType=cv2.BORDER_REPLICATE)
    rough = cv2.dilate(dem - mean, _disk(cfg.body_radius_m / spacing_m), borderType=cv2.BORDER_REPLICATE)
    # Posts whose footprint leaves the DEM are unknown.
    reach = int(math.ceil((max(R + cfg.footpad_radius_m, cfg.body_radius_m)) / spacing_m))
    valid = np.zeros(dem.shape, bool)
    valid[reach:dem.shape[0] - reach, reach:dem.shape[1] - reach] = True
    rough[~valid] = nan
    tilt_deg[~valid] = nan
    unsafe = ~valid | (tilt_deg > cfg.slope_max_deg) | (rough > cfg.roughness_max_m)
    if known is not None:
        if known.shape != dem.shape:
            raise ValueError(f"known has shape {known.shape}; expected the DEM's {dem.shape}")
        unknown = (~np.asarray(known, bool)).astype(np.uint8)
        unsafe |= cv2.dilate(unknown, _disk(reach), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    safe_u8 = (~unsafe).astype(np.uint8)
    dist = cv2.distanceTransform(safe_u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(spacing_m)
    return HazardMap(tilt_deg=tilt_deg, roughness_m=rough, unsafe=unsafe, hazard_distance_m=dist,
                     spacing_m=float(spacing_m), origin_xy_m=(float(origin_xy_m[0]), float(origin_xy_m[1])))


def choose_site(hmap: HazardMap, target_xy_m: np.ndarray, nav_sigma_m: float,
                cfg: HazardConfig | None = None) -> SafeSite | None:
    """The safe site of least cost near the target, or None when none is safe enough within the divert limit.

    Args:
        hmap: The hazard map.
        target_xy_m: Current target in L (2,) [m].
        nav_sigma_m: 1-sigma of the horizontal navigation error per axis [m].
        cfg: Weights and limits (the same as the map's).

    Returns:
        The site, or None.
    """
    cfg = cfg if cfg is not None else HazardConfig()
    rows, cols = hmap.unsafe.shape
    x, y = hmap.xy_of(np.arange(rows)[:, None], np.arange(cols)[None, :])
    divert = np.hypot(x - target_xy_m[0], y - target_xy_m[1])
    margin = hmap.hazard_distance_m
    ok = ~hmap.unsafe & (margin >= cfg.nav_sigmas * nav_sigma_m) & (divert <= cfg.max_divert_m)
    if not ok.any():
        return None
    cost = (cfg.w_divert * divert / cfg.max_divert_m
            + cfg.w_slope * np.nan_to_num(hmap.tilt_deg, nan=90.0) / cfg.slope_max_deg
            + cfg.w_margin * (1.0 - np.minimum(margin, cfg.margin_cap_m) / cfg.margin_cap_m))
    cost = np.where(ok, cost, np.inf)
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return SafeSite(xy_m=np.array([float(x[0, j]), float(y[i, 0])]),
                    divert_m=float(divert[i, j]), margin_m=float(margin[i, j]),
                    tilt_deg=float(hmap.tilt_deg[i, j]), cost=float(cost[i, j]))
