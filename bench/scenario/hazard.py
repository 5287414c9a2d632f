"""The scenario's ``[hazard]`` table: hazard detection and avoidance, and touchdown footprint scoring.

* ``avoidance = "off"|"on"`` (default off: the run flies exactly as without it): the flight
  software takes one flash-lidar scan (``hda.flashes`` flashes mosaicked) near
  ``hda.scan_altitude_m``, builds its hazard map in its estimated frame and retargets to a safe
  site (:mod:`gnc.hda`); when it finds none, a second scan lower down over its best-margin area
  (``hda.rescan``) before it declares no safe site; the bench simulates the lidar against the
  fine truth DEM (:mod:`models.flash_lidar`, :mod:`models.site_dem`).
* ``scoring = "off"|"on"``: the touchdown footprint is judged against the fine truth DEM and the
  boulder list (:mod:`bench.evaluation.footprint`); on whenever avoidance is on.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from bench.evaluation.footprint import FootprintCriteria
from gnc.hda import HdaConfig
from models.flash_lidar import FlashLidarConfig, footprint_half_m

# Most posts in one scan's DEM, the truth's or the flight software's: micrometre posts over a scan's footprint
# ran out of memory (a raw MemoryError). The default scan's truth DEM has 936^2 posts; 4096^2 built in 1.3 s
# with 240 MB more at its peak, 6144^2 in 3.7 s with 665 MB more. 4608^2 holds a scan from the 500 m
# hand-over at 0.1 m posts (4522^2).
SCAN_DEM_POSTS_MAX = 4608**2


class HazardSettings(BaseModel):
    """Hazard detection and avoidance (flight) and footprint scoring (bench)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    avoidance: Literal["off", "on"] = Field(
        "off", description="hazard detection and avoidance: one lidar scan (a mosaic of hda.flashes flashes), a "
                           "hazard map, a retarget to a safe site, a second scan when the first finds none "
                           "(hda.rescan); 'off' flies exactly as without it")
    scoring: Literal["off", "on"] = Field(
        "off", description="judge the touchdown footprint against the fine truth DEM and the boulder list "
                           "(on whenever avoidance is on)")
    site_spacing_m: float = Field(0.1, ge=0.005, le=0.25,
                                  description="post spacing of the fine truth DEM [m] (5 mm at the finest: the "
                                              "touchdown's DEM then has 2880^2 posts)")
    criteria: FootprintCriteria = Field(FootprintCriteria(), description="what counts as a hazardous footprint")
    lidar: FlashLidarConfig = Field(FlashLidarConfig(), description="the flash lidar (truth model; its nominal "
                                                                    "geometry is in each message)")
    hda: HdaConfig = Field(HdaConfig(), description="the flight software's scan, DEM, hazard map and site choice")

    @property
    def scored(self) -> bool:
        """The touchdown footprint is scored."""
        return self.scoring == "on" or self.avoidance == "on"


def check_scan_plan(hazard: HazardSettings, gate_altitude_m: float, terrain_size_m: float,
                    start_r_L_m: tuple[float, float, float]) -> None:
    """Refuse a hazard-avoidance plan that could not scan, before anything is built.

    Checked for the first scan (and the second, with ``hda.rescan = "on"``): the scan comes on the
    approach, so above the guidance gate; the second below the first; the lidar reaches the ground
    from the scan height and its footprint there holds the lander; the footprint (nadir on the
    straight line from the hand-over to the gate, or ``max_divert_m`` from the target for the second
    scan) stays on the terrain; and neither the truth's fine DEM nor the flight software's has more
    than ``SCAN_DEM_POSTS_MAX`` posts.

    Args:
        hazard: The ``[hazard]`` table.
        gate_altitude_m: ``guidance.gate_altitude_m`` [m].
        terrain_size_m: The procedural terrain's side [m].
        start_r_L_m: ``initial.r_BL_L_m`` [m].

    Raises:
        ValueError: One line naming the field, its value and the ways out.
    """
    if hazard.avoidance != "on":
        return
    hda, lidar = hazard.hda, hazard.lidar
    if hda.scan_altitude_m <= gate_altitude_m:
        raise ValueError(f"hazard.hda.scan_altitude_m = {hda.scan_altitude_m:g} is at or below guidance.gate_altitude_m "
                         f"= {gate_altitude_m:g}: the scan is taken on the approach, which ends at the gate, so it "
                         f"would never be taken; allowed: a scan altitude above {gate_altitude_m:g} m (e.g. 100), or "
                         "a lower gate")
    scans = [("scan_altitude_m", hda.scan_altitude_m, "dem_spacing_m", hda.dem_spacing_m)]
    if hda.rescan == "on":
        if hda.rescan_altitude_m >= hda.scan_altitude_m:
            raise ValueError(f"hazard.hda.rescan_altitude_m = {hda.rescan_altitude_m:g} is not below "
                             f"hazard.hda.scan_altitude_m = {hda.scan_altitude_m:g}: the second scan looks again from "
                             f"lower down; allowed: below {hda.scan_altitude_m:g} m (e.g. 50), or hazard.hda.rescan "
                             "= 'off'")
        scans.append(("rescan_altitude_m", hda.rescan_altitude_m, "rescan_dem_spacing_m", hda.rescan_dem_spacing_m))
    x0, y0, z0 = (float(c) for c in start_r_L_m)
    if z0 <= gate_altitude_m:
        raise ValueError(f"initial.r_BL_L_m = {[x0, y0, z0]} starts {z0:g} m above the target, at or below "
                         f"guidance.gate_altitude_m = {gate_altitude_m:g}: the hazard scan is taken on the approach, "
                         "which this descent never flies; allowed: a start above the gate, or hazard.avoidance = 'off'")
    # A scan set above the hand-over height is taken at once, from the hand-over height; each scan's footprint
    # (half side [m]) at the height it is taken.
    scans = [(name, min(h, z0), spacing_name, spacing, footprint_half_m(lidar.fov_deg, min(h, z0)))
             for name, h, spacing_name, spacing in scans]
    reaches: list[tuple[float, str, float, float]] = []  # (reach from the target, scan, half side, nadir offset) [m]
    for name, h, _, _, half_m in scans:
        if name == "scan_altitude_m":  # nadir on the straight line from hand-over to the gate
            frac = min(max((h - gate_altitude_m) / max(z0 - gate_altitude_m, 1e-9), 0.0), 1.0)
            offset_m = frac * math.hypot(x0, y0)
        else:  # over a site within max_divert_m of the target
            offset_m = hda.map.max_divert_m
        reaches.append((offset_m + half_m, f"hazard.hda.{name} = {getattr(hda, name):g}", half_m, offset_m))
    reach_m, where, half_m, offset_m = max(reaches)
    if reach_m > terrain_size_m / 2 - 1.0:  # the size that holds every scan's footprint
        raise ValueError(f"{where}: the lidar's footprint (+-{half_m:.0f} m, nadir about {offset_m:.0f} m from "
                         f"the target) reaches {reach_m:.0f} m from the target, beyond the terrain (terrain.size_m "
                         f"= {terrain_size_m:g}, half {terrain_size_m / 2:g} m less 1 m); allowed: a larger "
                         f"terrain.size_m (at least {2 * math.ceil(reach_m + 1):g}), a lower scan, or a narrower "
                         "hazard.lidar.fov_deg")
    half_fov = math.radians(lidar.fov_deg / 2)
    lander_m = 2.0 * (max(hda.map.leg_radius_m + hda.map.footpad_radius_m, hda.map.body_radius_m))
    for name, h, spacing_name, spacing, half_m in scans:
        where = f"hazard.hda.{name} = {getattr(hda, name):g} m" + (
            f" (taken at the hand-over height, {h:g} m)" if h != getattr(hda, name) else "")
        slant_m = h / math.cos(half_fov * math.sqrt(2.0))  # to the footprint's corner, level ground
        if lidar.max_range_m < slant_m:
            raise ValueError(f"hazard.lidar.max_range_m = {lidar.max_range_m:g} is shorter than the slant range of "
                             f"the scan ({slant_m:.0f} m at {where}): the footprint would have no returns; allowed: "
                             f"a max_range_m of at least {math.ceil(slant_m):g} m, or a lower scan")
        side_m = 2.0 * h * math.tan(half_fov)
        if side_m < lander_m:
            raise ValueError(f"hazard.lidar.fov_deg = {lidar.fov_deg:g}: at {where} the footprint is "
                             f"{side_m:.2f} m across, less than the lander it must find room for "
                             f"({lander_m:g} m: legs, pads and body); allowed: a fov_deg of at least "
                             f"{math.degrees(2 * math.atan(lander_m / (2 * h))):.2f}, or a higher scan")
        for post_name, post_m in (("hazard.site_spacing_m", hazard.site_spacing_m), (f"hazard.hda.{spacing_name}", spacing)):
            side_posts = 2.0 * half_m / post_m
            if side_posts**2 > SCAN_DEM_POSTS_MAX:
                raise ValueError(f"{post_name} = {post_m:g} over the scan's footprint at {where} (+-{half_m:.0f} m) "
                                 f"makes {side_posts:.0f}^2 DEM posts, more than {math.isqrt(SCAN_DEM_POSTS_MAX)}^2; "
                                 f"allowed: posts of at least {2 * half_m / math.isqrt(SCAN_DEM_POSTS_MAX):.3f} m, a "
                                 "lower scan, or a narrower hazard.lidar.fov_deg")
