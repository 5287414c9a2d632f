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

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from bench.evaluation.footprint import FootprintCriteria
from gnc.hda import HdaConfig
from models.flash_lidar import FlashLidarConfig


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
    site_spacing_m: float = Field(0.1, gt=0.0, le=0.25, description="post spacing of the fine truth DEM [m]")
    criteria: FootprintCriteria = Field(FootprintCriteria(), description="what counts as a hazardous footprint")
    lidar: FlashLidarConfig = Field(FlashLidarConfig(), description="the flash lidar (truth model; its nominal "
                                                                    "geometry is in each message)")
    hda: HdaConfig = Field(HdaConfig(), description="the flight software's scan, DEM, hazard map and site choice")

    @property
    def scored(self) -> bool:
        """The touchdown footprint is scored."""
        return self.scoring == "on" or self.avoidance == "on"
