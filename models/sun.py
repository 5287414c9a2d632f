"""The sun's settings (``[sun]``): the truth world's lighting, with no simulator behind it.

A module of its own, importing neither MuJoCo nor a renderer, so that loading a
scenario (``landbench replay``, ``landbench scenario show``, the compare tools)
needs neither; :mod:`models.world` lights the world with it and
:mod:`bench.scenario` names it in the schema (models never import bench).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class SunConfig(BaseModel):
    """Direction of the sun and shadow rendering."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    elevation_deg: float = Field(30.0, gt=0.0, le=90.0, description="sun elevation above the horizon [deg]")
    azimuth_deg: float = Field(
        120.0, ge=0.0, lt=360.0, description="sun azimuth, from north (+y) clockwise toward east (+x) [deg]"
    )
    shadows: bool = Field(False, description="render cast shadows (costly on a CPU renderer; see README)")

    def direction_L(self) -> np.ndarray:
        """Unit vector from the surface toward the sun, in L (3,)."""
        el, az = math.radians(self.elevation_deg), math.radians(self.azimuth_deg)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
