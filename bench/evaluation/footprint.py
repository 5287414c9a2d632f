"""Touchdown footprint scoring against the fine truth DEM and the boulder list (bench side, truth).

Inputs: the footpads' horizontal positions at touchdown (4, 2) [m] and the
body axis's (2,), a :class:`models.site_dem.SiteDem` around them, the lander's
footpad radius, and :class:`FootprintCriteria`.
Output: a dict of figures and ``hazard_free`` (see :func:`score_footprint`).
Rate: once per run, after touchdown.

This judges the ground the lander actually came down on, apart from the
physics outcome (the physics terrain is the coarse heightfield, which carries
no boulder). It is computed here from first principles, independently of the
flight software's hazard map (:mod:`gnc.hazard`):

* **pad support heights**: the highest DEM post within the footpad's radius of
  each pad's centre;
* **tilt of the pads' plane**: of the planes through three pads that have the
  fourth on or below them (the lander rests on one of them; it may rock
  between two), the steepest;
* **slope**: the least-squares plane of every post within the footprint (leg
  radius plus footpad radius of the axis), its angle from level;
* **rock under the body**: the highest post within ``body_radius_m`` of the
  axis above that plane (``rock_dem_m``), and, from the boulder list, the
  highest boulder surface at the nearest point of the body's disk
  (``rock_list_m``: each boulder's own profile at that distance);
* ``hazard_free``: tilt and slope at most ``slope_max_deg`` and ``rock_dem_m``
  at most ``rock_max_m`` (the ground's shape: what the body would strike);
  ``hazard_free_strict``: and ``rock_list_m`` too (a boulder's own protrusion
  above its base, even where the ground around it sits below the
  footprint's plane, so that the DEM shows less of it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from models.site_dem import SiteDem
from models.terrain import _boulder_rho2


class FootprintCriteria(BaseModel):
    """What counts as a hazardous touchdown footprint (ALHAT's thresholds)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    slope_max_deg: float = Field(10.0, gt=0.0, lt=45.0, description="largest safe tilt of the pads' plane and slope [deg]")
    rock_max_m: float = Field(0.3, gt=0.0, description="largest safe rock under the body [m]")
    body_radius_m: float = Field(2.2, gt=0.0, description="radius under the body checked for rocks [m]")


def _plane_tilts_deg(pads: np.ndarray) -> list[float]:
    """Tilts of the resting planes through three of four pads (x, y, z) (4, 3) [deg]."""
    out = []
    for skip in range(4):
        p = pads[[q for q in range(4) if q != skip]]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        if n[2] < 0:
            n = -n
        # The fourth pad on or below the plane: the lander can rest on these three.
        if float(n @ (pads[skip] - p[0])) <= 1e-9 * float(np.linalg.norm(n)):
            out.append(math.degrees(math.atan2(math.hypot(n[0], n[1]), n[2])))
    return out


def score_footprint(dem: SiteDem, pads_xy_m: np.ndarray, axis_xy_m: np.ndarray, footpad_radius_m: float,
                    crit: FootprintCriteria | None = None) -> dict[str, Any]:
    """Judge a touchdown footprint (see the module's docstring).

    Args:
        dem: Fine truth DEM covering the footprint.
        pads_xy_m: Footpad centres at touchdown, (4, 2) [m], in order around the square or any order.
        axis_xy_m: The body axis's ground point at touchdown (2,) [m].
        footpad_radius_m: Footpad radius [m].
        crit: Thresholds.

    Returns:
        ``hazard_free`` (bool, or None when the footprint leaves the DEM), ``tilt_deg``, ``slope_deg``,
        ``rock_dem_m``, ``rock_list_m``, ``pad_heights_m`` (4), ``hazards`` (the criteria exceeded).
    """
    crit = crit if crit is not None else FootprintCriteria()
    pads_xy = np.asarray(pads_xy_m, float).reshape(4, 2)
    axis = np.asarray(axis_xy_m, float).reshape(2)
    s = dem.spacing_m
    n_r, n_c = dem.height_m.shape
    x0, y0 = dem.origin_xy_m
    reach = max(float(np.max(np.hypot(*(pads_xy - axis).T))) + footpad_radius_m, crit.body_radius_m) + 2 * s
    if not (x0 + reach <= axis[0] <= x0 + (n_c - 1) * s - reach and y0 + reach <= axis[1] <= y0 + (n_r - 1) * s - reach):
        return {"hazard_free": None, "hazard_free_strict": None, "tilt_deg": None, "slope_deg": None, "rock_dem_m": None, "rock_list_m": None,
                "pad_heights_m": None, "hazards": ["outside_site_dem"]}
    j0 = int(math.floor((axis[0] - reach - x0) / s))
    i0 = int(math.floor((axis[1] - reach - y0) / s))
    j1 = int(math.ceil((axis[0] + reach - x0) / s)) + 1
    i1 = int(math.ceil((axis[1] + reach - y0) / s)) + 1
    h = dem.height_m[i0:i1, j0:j1].astype(np.float64)
    X = x0 + s * np.arange(j0, j1)[None, :] + np.zeros_like(h)
    Y = y0 + s * np.arange(i0, i1)[:, None] + np.zeros_like(h)

    pad_h = np.array([h[np.hypot(X - px, Y - py) <= footpad_radius_m + 1e-9].max() for px, py in pads_xy])
    tilts = _plane_tilts_deg(np.column_stack([pads_xy, pad_h]))
    tilt = max(tilts) if tilts else 90.0

    foot = np.hypot(X - axis[0], Y - axis[1]) <= float(np.max(np.hypot(*(pads_xy - axis).T))) + footpad_radius_m
    A = np.column_stack([np.ones(int(foot.sum())), X[foot] - axis[0], Y[foot] - axis[1]])
    coef = np.linalg.lstsq(A, h[foot], rcond=None)[0]
    slope = math.degrees(math.atan(math.hypot(coef[1], coef[2])))
    body = np.hypot(X - axis[0], Y - axis[1]) <= crit.body_radius_m
    plane = coef[0] + coef[1] * (X - axis[0]) + coef[2] * (Y - axis[1])
    rock_dem = float(np.max((h - plane)[body]))

    rock_list = 0.0
    if len(dem.boulders):
        b = dem.boulders
        gap = np.maximum(np.hypot(b[:, 0] - axis[0], b[:, 1] - axis[1]) - crit.body_radius_m, 0.0)
        rho2 = (gap / (b[:, 2] / 2)) ** 2
        rock_list = float(np.max(b[:, 2] * _boulder_rho2(rho2)))

    hazards = [name for name, bad in (("tilt", tilt > crit.slope_max_deg), ("slope", slope > crit.slope_max_deg),
                                      ("rock", rock_dem > crit.rock_max_m)) if bad]
    return {"hazard_free": not hazards, "hazard_free_strict": not hazards and rock_list <= crit.rock_max_m,
            "tilt_deg": float(tilt), "slope_deg": float(slope), "rock_dem_m": rock_dem,
            "rock_list_m": rock_list, "pad_heights_m": [float(v) for v in pad_h], "hazards": hazards}
