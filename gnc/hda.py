"""Hazard detection and avoidance in flight (flight software, NumPy + OpenCV).

Ports:
    Inputs: the filter's estimate (position, velocity and their covariance,
        the star tracker's attitude), the current target, and one
        :class:`gnc.messages.LidarScanMessage` (ranges + the sensor's nominal
        geometry), asked for by :meth:`HazardAvoidance.wants_scan`.
    Output: a new :class:`gnc.guidance.LandingTarget` (the safe site), or a
        declared "no safe site" event; :class:`HdaStats` for the summary.
    Rate: one scan, when the estimated height above the target first falls to
        ``scan_altitude_m`` during the approach (Chang'e-3/4: a hover near
        100 m; here a pass: a flash lidar takes its whole image in one pulse),
        of ``flashes`` flashes on consecutive control ticks; and a second scan
        at ``rescan_altitude_m`` only when the first found no safe site.

Steps of :meth:`HazardAvoidance.on_scan`:

0. **Several flashes, one DEM** (ALHAT's mosaic): a flash of 256^2 rays from
   100 m samples the ground every 0.14 m, coarser than the 0.1 m posts, so
   half the posts get no return and are filled from their neighbours, and a
   rock's top is read up to 0.1 m off it: a rock at the 0.3 m threshold (a
   Gaussian of sigma D/4 = 0.15 m) reads up to 20 % low. ``flashes`` flashes
   on consecutive control ticks (the first ``flashes - 1`` are kept by
   :meth:`HazardAvoidance.add_flash`) sample it at different sub-pixel
   phases: the lander moves (about 0.2 m down, 0.06 m across) and turns
   (0.1 deg: 0.17 m on the ground at 100 m) between ticks. The flashes are
   registered to the last one through the estimated motion (the estimated
   velocity and the gyro's relative rotation), not through the estimate at
   each tick, which a filter update can move by 10 cm between two ticks
   (:meth:`HazardAvoidance._mosaic_points`); 8 flashes (0.14 s at 50 Hz)
   give about 4 returns per post: a steadier read of a rock's top than 4
   (2 returns per post), so fewer false alarms at the same detection rate
   (README: eight flashes instead of four).
1. **DEM in the estimated frame**: each ray's return point is placed through
   the filter's pose (estimated position, star-tracker attitude, the nominal
   mounting), never the truth: the navigation error enters as it would in
   flight. The points are binned on a grid of ``dem_spacing_m`` posts (mean
   per post); empty posts are filled from their neighbours (a normalized
   3 x 3 box, a few passes); posts still empty are unknown.
2. **Hazard map** (:func:`gnc.hazard.hazard_map`): tilt of the pads' plane at
   the worst yaw, roughness under the body; unknown ground is unsafe. With
   ``sampling_margin = "on"`` a rock counts from ``roughness_max_m`` less the
   most a rock at the threshold can read low on the DEM's posts
   (:func:`sampling_margin_m`): the post nearest its top may be s / sqrt(2)
   from it (s the post spacing) and holds the mean of the returns in its
   s x s cell, so the returns sit a mean square s^2 / 2 + s^2 / 6 from the
   top; on a top of curvature kappa = 4 / h (the rock model above) that is
   kappa (2 s^2 / 3) / 2 = 4 s^2 / (3 h) low: 0.044 m at 0.1 m posts (a
   threshold of 0.256 m), 0.022 m at the second scan's 0.07 m.
3. **Safe site** (:func:`gnc.hazard.choose_site`): at least ``nav_sigmas``
   sigmas of the navigation error from any hazard, within ``max_divert_m`` of
   the current target. The map is made and flown in the same estimated frame,
   so the error that matters is what the estimate drifts between the scan and
   touchdown, not its absolute error: sigma^2 = (sigma_vh T)^2 + (rho
   sigma_att)^2 + (sigma_z tan(fov/2))^2 + floor^2, with sigma_vh the filter's
   horizontal-velocity 1-sigma, T the time left (the height over
   ``mean_descent_mps``, or the guidance plan's time left when that is
   longer: the time to the gate plus the terminal descent), rho the slant range, sigma_att the star
   tracker's 1-sigma, sigma_z the filter's height 1-sigma (a height error
   scales the map about nadir).
4. The target moves to the site (its height: the DEM's mean under the body
   there); guidance re-plans on a moved target. No safe site: a declared event
   (``no_safe_site``); the flight software then aborts (``no_site_action =
   "abort"``, the safe-abort hover of :mod:`gnc.fdir`) or lands at the target
   it had (``"land"``).
5. **Second chance** (``rescan = "on"``): when the first scan finds no site
   with the margin, nothing is declared yet. The target moves to the safe
   post of the largest margin within the divert limit (the best-margin area;
   it stays where it is when no post is safe) and a second scan is taken once
   the estimated height is at most ``rescan_altitude_m`` (50 m) and the target
   lies within ``rescan_view_frac`` of the footprint's half-width from where
   the boresight meets the ground (estimated pose, nominal mounting: at 50 m
   the lander may still be braking toward the target, tilted, looking
   elsewhere). From there the drift to touchdown is smaller (so is its
   margin) and the ground sample finer (0.07 m at 50 m). Its site must lie on
   ground it rated safe itself (DEM posts of ``rescan_dem_spacing_m``), but
   the margin counts the hazards of both scans (:func:`fuse_maps`): the
   second scan's where it rated the ground, the first's around it, so its
   small footprint's edge is not taken for a hazard. The first scan's hazards
   may have moved in the estimated frame by the estimate's drift between the
   scans (1-sigma sigma_reg = sigma_vh x the time between them), so they must
   keep ``nav_sigmas`` x sqrt(sigma^2 + sigma_reg^2): their distance loses
   the excess over ``nav_sigmas`` x sigma.
   It retargets, or declares no safe site.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from gnc.hazard import HazardConfig, HazardMap, SafeSite, _disk, choose_site, hazard_map
from gnc.messages import LidarScanMessage, lidar_ray_dirs_S

FILL_PASSES = 3  # passes of the 3 x 3 normalized box that fill empty posts
# The rocks' shape the detection margin assumes (a design assumption, as ALHAT's rock models): a rock of
# height h is a Gaussian of sigma h / 2 (height 0.5 D, sigma D / 4), whose top has curvature h / sigma^2 = 4 / h.
ROCK_TOP_CURVATURE_X_HEIGHT = 4.0


class HdaConfig(BaseModel):
    """When the flight software scans, how it builds its DEM, and the hazard map's settings."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    scan_altitude_m: float = Field(100.0, gt=0.0, description="estimated height above the target of the one scan [m]")
    dem_spacing_m: float = Field(0.1, gt=0.0, le=2.0, description="post spacing of the DEM built from the scan [m]")
    mean_descent_mps: float = Field(
        2.0, ge=0.01, description="height over this is the time left to touchdown, for the drift margin [m/s]")
    attitude_sigma_rad: float = Field(1e-4, ge=0.0, description="star tracker's attitude 1-sigma (specification) [rad]")
    nav_sigma_floor_m: float = Field(0.1, ge=0.0, le=1000.0,
                                     description="floor of the navigation sigma of the margin [m]")
    flashes: int = Field(
        8, ge=1, le=16, description="flashes per scan, one per control tick, mosaicked into one DEM: each flash "
                                    "samples the ground at another sub-pixel phase (the lander moves and turns "
                                    "between ticks), so a rock's top is read closer to it [-]")
    rescan: Literal["on", "off"] = Field(
        "on", description="no safe site in the first scan: divert to its best-margin area and scan again at "
                          "rescan_altitude_m before declaring no safe site ('off': declare at once)")
    rescan_altitude_m: float = Field(
        50.0, gt=0.0, description="estimated height above the target of the second scan (only after a first "
                                  "scan with no safe site) [m]")
    rescan_view_frac: float = Field(
        0.5, gt=0.0, le=1.0, description="the second scan waits until the target is within this fraction of the "
                                         "footprint's half-width of where the boresight meets the ground (its "
                                         "estimate; the lander may still be braking toward the target, looking "
                                         "elsewhere) [-]")
    rescan_dem_spacing_m: float = Field(
        0.07, gt=0.0, le=2.0, description="post spacing of the second scan's DEM: about its ground sample "
                                          "(50 m x 2 tan 10 deg / 256 = 0.069 m) [m]")
    sampling_margin: Literal["on", "off"] = Field(
        "on", description="rocks count from roughness_max_m less the most a rock at the threshold reads low on "
                          "the DEM's posts, 4 s^2 / (3 h) for post spacing s (0.044 m at 0.1 m; module docstring)")
    no_site_action: Literal["abort", "land"] = Field(
        "abort", description="no safe site: the safe-abort hover, or land at the current target")
    map: HazardConfig = Field(HazardConfig(), description="hazard thresholds, legs and site-choice weights")

    @model_validator(mode="after")
    def _margin_below_the_rock(self) -> HdaConfig:
        """With the sampling margin, a rock counts from roughness_max_m less the margin: posts so coarse that the
        margin is half the rock or more would make every bump a rock (a false 'no safe site')."""
        if self.sampling_margin == "on":
            h = self.map.roughness_max_m
            widest = h * math.sqrt(3.0 / (2.0 * ROCK_TOP_CURVATURE_X_HEIGHT))  # margin(s) = h / 2
            for name in ("dem_spacing_m", "rescan_dem_spacing_m"):
                s = getattr(self, name)
                margin = sampling_margin_m(s, h)
                if margin >= 0.5 * h:
                    raise ValueError(f"hazard.hda.{name} = {s} makes a rock of roughness_max_m = {h} m count from "
                                     f"{h - margin:.3f} m (the sampling margin); allowed: posts "
                                     f"finer than {widest:.3f} m, a larger roughness_max_m, or sampling_margin = "
                                     "'off'")
        return self


@dataclass
class HdaStats:
    """What hazard detection did (summary)."""

    scan_t_ns: int | None = None
    points: int = 0  # returns placed
    posts_known_frac: float | None = None
    nav_sigma_m: float | None = None
    unsafe_frac: float | None = None
    site: SafeSite | None = None
    target_before_L: np.ndarray | None = None
    no_safe_site: bool = False  # this scan found no site with the margin
    flashes: int = 0
    best_margin_m: float | None = None  # no site: the largest margin of a safe post within the divert limit
    roughness_detect_m: float | None = None  # the roughness a rock counts from (less the sampling margin) [m]
    compute_s: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ScanDem:
    """The DEM built from one scan, in the estimated L frame.

    Attributes:
        height_m: (n, n) float32 [m], south-up (row with +y, column with +x); filled where unknown.
        known: (n, n) bool, posts with data (a return or filled from neighbours).
        spacing_m: Post spacing [m]; origin_xy_m: L position of post (0, 0) [m].
    """

    height_m: np.ndarray
    known: np.ndarray
    spacing_m: float
    origin_xy_m: tuple[float, float]


def scan_points_L(msg: LidarScanMessage, r_BL_L: np.ndarray, R_LB: np.ndarray) -> np.ndarray:
    """Return points of a scan in L through a pose (the flight software's estimate), (k, 3) [m] (returns only)."""
    dirs_S = lidar_ray_dirs_S(msg.ranges_m.shape[0], msg.fov_deg).reshape(-1, 3)
    rng = msg.ranges_m.reshape(-1)
    ok = np.isfinite(rng)
    p_S = dirs_S[ok] * rng[ok, None]
    p_B = p_S @ np.asarray(msg.R_BS, float).T + np.asarray(msg.r_SB_m, float)
    return np.asarray(r_BL_L, float) + p_B @ np.asarray(R_LB, float).T


def grid_dem(points_L: np.ndarray, spacing_m: float) -> ScanDem:
    """Bin points on a square grid (mean per post), fill small gaps from neighbours (see the module docstring)."""
    x, y, z = points_L[:, 0], points_L[:, 1], points_L[:, 2]
    x0 = math.floor(float(x.min()) / spacing_m) * spacing_m
    y0 = math.floor(float(y.min()) / spacing_m) * spacing_m
    n_c = int(math.floor((float(x.max()) - x0) / spacing_m + 0.5)) + 1
    n_r = int(math.floor((float(y.max()) - y0) / spacing_m + 0.5)) + 1
    j = np.clip(np.rint((x - x0) / spacing_m).astype(np.intp), 0, n_c - 1)
    i = np.clip(np.rint((y - y0) / spacing_m).astype(np.intp), 0, n_r - 1)
    lin = i * n_c + j
    total = np.bincount(lin, weights=z, minlength=n_r * n_c).reshape(n_r, n_c).astype(np.float32)
    count = np.bincount(lin, minlength=n_r * n_c).reshape(n_r, n_c).astype(np.float32)
    for _ in range(FILL_PASSES):
        empty = count == 0
        if not empty.any():
            break
        s = cv2.boxFilter(total, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        c = cv2.boxFilter(count, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        fill = empty & (c > 0)
        # A filled post counts as one sample of its neighbours' mean.
        total[fill] = s[fill] / c[fill]
        count[fill] = 1.0
    known = count > 0
    height = np.where(known, total / np.maximum(count, 1.0), np.float32(np.median(z))).astype(np.float32)
    return ScanDem(height_m=height, known=known, spacing_m=float(spacing_m), origin_xy_m=(x0, y0))


def sampling_margin_m(spacing_m: float, roughness_max_m: float) -> float:
    """Most a rock of height ``roughness_max_m`` reads low on DEM posts of ``spacing_m`` (module docstring, step 2) [m].

    The returns binned into the post nearest the top lie a mean square distance s^2 / 2 + s^2 / 6 from it
    at worst (the post s / sqrt(2) off, the cell's own spread s^2 / 6); a top of curvature
    kappa = ROCK_TOP_CURVATURE_X_HEIGHT / h falls kappa r^2 / 2 at distance r.
    """
    kappa = ROCK_TOP_CURVATURE_X_HEIGHT / roughness_max_m
    return 0.5 * kappa * (spacing_m**2 / 2 + spacing_m**2 / 6)


def drift_sigma_m(cfg: HdaConfig, sigma_vh_mps: float, sigma_z_m: float, height_m: float, range_m: float,
                  fov_deg: float, t_go_plan_s: float | None = None) -> float:
    """1-sigma of the estimate's horizontal drift from the scan to touchdown (module docstring, step 3) [m]."""
    t_go = max(height_m, 0.0) / cfg.mean_descent_mps
    if t_go_plan_s is not None and math.isfinite(t_go_plan_s):
        t_go = max(t_go, t_go_plan_s)
    return math.sqrt((sigma_vh_mps * t_go) ** 2 + (range_m * cfg.attitude_sigma_rad) ** 2
                     + (sigma_z_m * math.tan(math.radians(fov_deg) / 2)) ** 2 + cfg.nav_sigma_floor_m ** 2)


def best_margin_post(hmap: HazardMap, target_xy_m: np.ndarray, max_divert_m: float) -> tuple[np.ndarray, float] | None:
    """The safe post of the largest margin within ``max_divert_m`` of the target (the nearer on a tie), or None.

    Returns:
        (its L position (2,) [m], its margin [m]), or None when no post there is safe.
    """
    rows, cols = hmap.unsafe.shape
    x, y = hmap.xy_of(np.arange(rows)[:, None], np.arange(cols)[None, :])
    divert = np.hypot(x - target_xy_m[0], y - target_xy_m[1])
    ok = ~hmap.unsafe & (divert <= max_divert_m)
    if not ok.any():
        return None
    margin = np.where(ok, hmap.hazard_distance_m, -1.0)
    best = margin == margin.max()
    i, j = np.unravel_index(int(np.argmin(np.where(best, divert, np.inf))), margin.shape)
    return np.array([float(x[0, j]), float(y[i, 0])]), float(margin[i, j])


def rated_mask(hmap: HazardMap, dem: ScanDem, cfg: HazardConfig) -> np.ndarray:
    """Posts the map rated from data: the footprint inside the DEM and touching no unknown post, (rows, cols) bool."""
    reach = int(math.ceil(max(cfg.leg_radius_m + cfg.footpad_radius_m, cfg.body_radius_m) / dem.spacing_m))
    unknown_near = cv2.dilate((~dem.known).astype(np.uint8), _disk(reach), borderType=cv2.BORDER_CONSTANT,
                              borderValue=0).astype(bool)
    return ~np.isnan(hmap.tilt_deg) & ~unknown_near


def fuse_maps(second: HazardMap, second_rated: np.ndarray, first: HazardMap, pad_m: float,
              first_shift_m: float) -> HazardMap:
    """The second scan's map, padded by ``pad_m``, with the margins to the hazards of both scans (step 5).

    Candidate sites: the posts the second scan rated safe. Hazards: the second scan's unsafe posts where it
    rated the ground, elsewhere the first scan's unsafe posts (its nearest post; outside the first map:
    unknown, a hazard). The margin is the distance to the nearest second-scan hazard, or to the nearest
    first-scan hazard less ``first_shift_m`` (how far the first map may have moved in the estimated frame
    between the scans), whichever is less.

    Returns:
        A :class:`gnc.hazard.HazardMap` on the padded grid of the second scan (tilt and roughness NaN in the pad).
    """
    s = second.spacing_m
    p = int(math.ceil(pad_m / s))
    rows, cols = second.unsafe.shape[0] + 2 * p, second.unsafe.shape[1] + 2 * p
    ox, oy = second.origin_xy_m[0] - p * s, second.origin_xy_m[1] - p * s
    rated = np.zeros((rows, cols), bool)
    rated[p:rows - p, p:cols - p] = second_rated
    uns2 = np.zeros((rows, cols), bool)
    uns2[p:rows - p, p:cols - p] = second.unsafe & second_rated
    x = ox + s * np.arange(cols)
    y = oy + s * np.arange(rows)
    j1 = np.rint((x - first.origin_xy_m[0]) / first.spacing_m).astype(np.intp)
    i1 = np.rint((y - first.origin_xy_m[1]) / first.spacing_m).astype(np.intp)
    in_j = (j1 >= 0) & (j1 < first.unsafe.shape[1])
    in_i = (i1 >= 0) & (i1 < first.unsafe.shape[0])
    uns1 = np.ones((rows, cols), bool)
    uns1[np.ix_(in_i, in_j)] = first.unsafe[np.ix_(i1[in_i], j1[in_j])]
    uns1 &= ~rated
    d2 = cv2.distanceTransform((~uns2).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(s)
    d1 = cv2.distanceTransform((~uns1).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(s)
    candidate = rated & ~uns2
    margin = np.where(candidate, np.minimum(d2, np.maximum(d1 - np.float32(first_shift_m), 0.0)), 0.0)

    def pad(a: np.ndarray) -> np.ndarray:
        out = np.full((rows, cols), np.nan, np.float32)
        out[p:rows - p, p:cols - p] = a
        return out

    return HazardMap(tilt_deg=pad(second.tilt_deg), roughness_m=pad(second.roughness_m), unsafe=~candidate,
                     hazard_distance_m=margin.astype(np.float32), spacing_m=s, origin_xy_m=(ox, oy))


class HazardAvoidance:
    """The hazard scan(s) and the retarget they lead to (module docstring)."""

    def __init__(self, cfg: HdaConfig):
        self.cfg = cfg
        self.stats = HdaStats()  # the first scan
        self.rescan_stats: HdaStats | None = None  # the second scan, when there was one
        self.scanned = False  # the first scan is done
        self.awaiting_rescan = False  # the first found no site: a second scan is due
        self.rescanned = False
        self.no_safe_site = False  # declared: no safe site (after the second scan, when there is one)
        self.last_dem: ScanDem | None = None  # the first scan's DEM and map
        self.last_map: HazardMap | None = None
        self.rescan_dem: ScanDem | None = None
        self.rescan_map: HazardMap | None = None
        # The flashes kept for the scan under way: (message, estimated position, attitude, gyro attitude or None).
        self._flashes: list[tuple[LidarScanMessage, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._mount: tuple[np.ndarray, np.ndarray, float] | None = None  # (R_BS, r_SB_m, fov_deg), nominal
        self._first_t_ns: int | None = None

    def abandon_rescan(self) -> None:
        """The second scan did not come in time (the target never in its view, or the descent already below its
        height): declare no safe site, as a second scan that found none would."""
        if self.awaiting_rescan:
            self.awaiting_rescan = False
            self.no_safe_site = True

    def wants_scan(self, height_above_target_m: float, phase: str | None, r_BL_L: np.ndarray | None = None,
                   R_LB: np.ndarray | None = None, target_L: np.ndarray | None = None) -> bool:
        """A flash now: a scan under way, the first scan due (on the approach, at or below its height), or the
        second (at or below its height, the target in view: needs the estimated pose and the target)."""
        if self._flashes:
            return True
        if not math.isfinite(height_above_target_m):
            return False
        if not self.scanned:
            return phase == "approach" and height_above_target_m <= self.cfg.scan_altitude_m
        if not (self.awaiting_rescan and phase in ("approach", "terminal")
                and height_above_target_m <= self.cfg.rescan_altitude_m):
            return False
        if r_BL_L is None or R_LB is None or target_L is None or self._mount is None:
            return False
        offset = self.view_offset_m(r_BL_L, R_LB, target_L)
        half = height_above_target_m * math.tan(math.radians(self._mount[2]) / 2)
        return offset <= self.cfg.rescan_view_frac * half

    def view_offset_m(self, r_BL_L: np.ndarray, R_LB: np.ndarray, target_L: np.ndarray) -> float:
        """Horizontal distance from the target to where the lidar's boresight meets the target's height [m]
        (estimated pose, the nominal mounting of the first scan's message; inf when it looks above the horizon)."""
        assert self._mount is not None
        R_BS, r_SB, _ = self._mount
        r_S = np.asarray(r_BL_L, float) + np.asarray(R_LB, float) @ r_SB
        d = np.asarray(R_LB, float) @ R_BS[:, 2]
        if d[2] > -1e-6:
            return math.inf
        t = (float(target_L[2]) - r_S[2]) / d[2]
        g = r_S + t * d
        return float(math.hypot(g[0] - target_L[0], g[1] - target_L[1]))

    def flashes_wanted(self) -> int:
        """Flashes still to come in the scan under way, this one included (1: this flash completes the scan)."""
        return self.cfg.flashes - len(self._flashes)

    def add_flash(self, msg: LidarScanMessage, r_BL_L: np.ndarray, R_LB: np.ndarray,
                  R_gyro: np.ndarray | None = None) -> None:
        """Keep one flash of a scan (not its last), with the pose estimated at its tick and the gyro-only
        attitude there (None: none; see :meth:`_mosaic_points`)."""
        self._flashes.append((msg, np.asarray(r_BL_L, float).copy(), np.asarray(R_LB, float).copy(),
                              None if R_gyro is None else np.asarray(R_gyro, float).copy()))

    def _mosaic_points(self, last: tuple[LidarScanMessage, np.ndarray, np.ndarray, np.ndarray | None],
                       v_BL_L: np.ndarray | None) -> np.ndarray:
        """The returns of the scan's flashes in L, (k, 3) [m], registered to the last flash.

        The flashes must sit on one another to a few millimetres, which the estimate at each tick does not
        give: a filter update between two ticks moves it (measured: 12 cm in height, 4 cm across between
        two flashes 20 ms apart), and a flash placed through it would read a rock's top that much off.
        So each flash is placed through the last flash's pose carried back by the estimated motion: the
        position ``r_last - v (t_last - t_k)`` (``v_BL_L`` the estimated velocity; a velocity error of
        0.1 m/s moves it 6 mm over 60 ms) and the attitude ``R_LB,last R_g,last^T R_g,k`` (the gyro's
        relative rotation, when every flash has its gyro attitude). An error common to all flashes only
        moves and tilts the whole map, as it does a single flash. Without ``v_BL_L`` each flash keeps the
        position estimated at its own tick.
        """
        flashes = self._flashes + [last]
        msg_last, r_last, R_last, G_last = last
        gyro = G_last is not None and all(f[3] is not None for f in flashes)
        pts = []
        for msg, r, R, G in flashes:
            if v_BL_L is not None:
                r = r_last - np.asarray(v_BL_L, float) * ((msg_last.t_ns - msg.t_ns) / 1e9)
            if gyro:
                R = R_last @ G_last.T @ G
            pts.append(scan_points_L(msg, r, R))
        return np.concatenate(pts, axis=0)

    def on_scan(self, msg: LidarScanMessage, r_BL_L: np.ndarray, R_LB: np.ndarray, sigma_vh_mps: float,
                sigma_z_m: float, target_L: np.ndarray, t_go_plan_s: float | None = None,
                R_gyro: np.ndarray | None = None, v_BL_L: np.ndarray | None = None) -> np.ndarray | None:
        """The scan's last flash: process the scan; the new target (3,) [m], or None (the target stays).

        After a None, :attr:`no_safe_site` says whether no safe site was declared (the first scan's
        no-site, with ``rescan = "on"``, is not: it may move the target to the best-margin area, and
        a second scan follows).

        Args:
            msg: The scan's last flash (the flashes before it were given to :meth:`add_flash`).
            r_BL_L: Estimated body position in L (3,) [m].
            R_LB: Estimated attitude (3, 3).
            sigma_vh_mps: Filter's horizontal-velocity 1-sigma per axis [m/s].
            sigma_z_m: Filter's height 1-sigma [m].
            target_L: Current target (3,) [m].
            t_go_plan_s: The guidance plan's time left to touchdown [s] (None: the height over
                ``mean_descent_mps`` alone).
            R_gyro: The gyro-only attitude at this tick (3, 3), to register the scan's flashes (None: none).
            v_BL_L: Estimated velocity in L (3,) [m/s], to register the scan's flashes (None: none).
        """
        cfg = self.cfg
        first = not self.scanned
        if first:
            self.scanned = True
            self._mount = (np.asarray(msg.R_BS, float).copy(), np.asarray(msg.r_SB_m, float).copy(), msg.fov_deg)
            st = self.stats
            spacing = cfg.dem_spacing_m
        else:
            self.awaiting_rescan = False
            self.rescanned = True
            st = self.rescan_stats = HdaStats()
            spacing = cfg.rescan_dem_spacing_m
        st.scan_t_ns = msg.t_ns
        if first:
            self._first_t_ns = msg.t_ns
        st.target_before_L = np.asarray(target_L, float).copy()
        t0 = time.perf_counter()
        pts = self._mosaic_points((msg, np.asarray(r_BL_L, float), np.asarray(R_LB, float),
                                   None if R_gyro is None else np.asarray(R_gyro, float)), v_BL_L)
        st.flashes = len(self._flashes) + 1
        self._flashes = []
        st.points = int(pts.shape[0])
        if pts.shape[0] < 16:
            st.no_safe_site = True
            return self._no_site(first, None, target_L)
        dem = grid_dem(pts, spacing)
        t1 = time.perf_counter()
        map_cfg = cfg.map
        if cfg.sampling_margin == "on":
            map_cfg = cfg.map.model_copy(update={"roughness_max_m": cfg.map.roughness_max_m
                                                 - sampling_margin_m(spacing, cfg.map.roughness_max_m)})
        st.roughness_detect_m = map_cfg.roughness_max_m
        hmap = hazard_map(dem.height_m, dem.spacing_m, dem.origin_xy_m, map_cfg, known=dem.known)
        t2 = time.perf_counter()
        height = float(r_BL_L[2] - target_L[2])
        range_m = float(np.nanmedian(msg.ranges_m))
        sigma = drift_sigma_m(cfg, sigma_vh_mps, sigma_z_m, height, range_m, msg.fov_deg, t_go_plan_s)
        choice_map = hmap
        if not first and self.last_map is not None:  # the margins count both scans' hazards
            # The first map may have moved by the estimate's drift between the scans (1-sigma sigma_vh x gap):
            # its hazards must keep nav_sigmas x sqrt(sigma^2 + sigma_reg^2), so their distance loses the excess.
            sigma_reg = sigma_vh_mps * (msg.t_ns - (self._first_t_ns or msg.t_ns)) / 1e9
            shift = cfg.map.nav_sigmas * (math.hypot(sigma, sigma_reg) - sigma)
            choice_map = fuse_maps(hmap, rated_mask(hmap, dem, cfg.map), self.last_map, cfg.map.margin_cap_m, shift)
        site = choose_site(choice_map, np.asarray(target_L, float)[:2], sigma, cfg.map)
        t3 = time.perf_counter()
        st.compute_s = {"dem_s": t1 - t0, "hazard_map_s": t2 - t1, "site_s": t3 - t2}
        st.posts_known_frac = float(dem.known.mean())
        st.nav_sigma_m = sigma
        st.unsafe_frac = float(hmap.unsafe.mean())
        if first:
            self.last_dem, self.last_map = dem, hmap
        else:
            self.rescan_dem, self.rescan_map = dem, hmap
        if site is None:
            st.no_safe_site = True
            return self._no_site(first, (dem, hmap), target_L)
        st.site = site
        return np.array([site.xy_m[0], site.xy_m[1], _height_under_body(dem, site.xy_m, cfg.map.body_radius_m)])

    def _no_site(self, first: bool, scan: tuple[ScanDem, HazardMap] | None, target_L: np.ndarray) -> np.ndarray | None:
        """No site with the margin in this scan: the second chance after the first, else a declared no-site."""
        if not (first and self.cfg.rescan == "on"):
            self.no_safe_site = True
            return None
        self.awaiting_rescan = True
        if scan is None:
            return None
        dem, hmap = scan
        best = best_margin_post(hmap, np.asarray(target_L, float)[:2], self.cfg.map.max_divert_m)
        if best is None:  # nothing safe in view: the second scan looks from lower over the same target
            return None
        xy, self.stats.best_margin_m = best
        return np.array([xy[0], xy[1], _height_under_body(dem, xy, self.cfg.map.body_radius_m)])


def _height_under_body(dem: ScanDem, xy_m: np.ndarray, body_radius_m: float) -> float:
    """The DEM's mean under the body at ``xy_m`` (the site's height) [m]."""
    j = int(round((xy_m[0] - dem.origin_xy_m[0]) / dem.spacing_m))
    i = int(round((xy_m[1] - dem.origin_xy_m[1]) / dem.spacing_m))
    r = max(int(round(body_radius_m / dem.spacing_m)), 1)
    return float(np.mean(dem.height_m[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1]))
