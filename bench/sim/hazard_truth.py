"""The bench's side of hazard detection and avoidance: the lidar's flash, and the truth the run is judged by.

Inputs: the scenario's ``[hazard]``, the terrain seed (the fine truth DEM is
the terrain's own ground, :class:`models.site_dem.SiteGround`), the truth
pose at a flash and at touchdown, the flight software's hazard-avoidance
state.
Outputs: :class:`gnc.messages.LidarScanMessage` for the flight software, and
the summary's ``hazard`` block.
Rate: setup once per run (about 1 s), the flashes of one scan (two when the
first found no safe site), one scoring after touchdown.

The summary's ``hazard`` block:

* ``footprint``: :func:`bench.evaluation.footprint.score_footprint` of the pads
  at touchdown (``hazard_free``, tilt, slope, rock);
* ``scan`` (avoidance on): when and from how high, the flight software's
  DEM and hazard map figures and their compute time, the site, its divert and
  margin; ``no_safe_site`` (declared, after the second scan when there was
  one), ``first_no_site`` (the first scan found none) and ``rescanned``; the
  site's **truth** position (the flight software's site minus its horizontal
  navigation error at the scan) and the truth footprint there;
* ``rescan`` (avoidance on): the same figures for the second scan, when the
  first found no safe site (``scanned`` false otherwise);
* ``detection``: the flight software's unsafe posts against the truth's. The
  truth hazard map is :func:`gnc.hazard.hazard_map` of the fine truth DEM at
  the same posts moved to where they truly are (each post's estimated
  position minus the navigation error at the scan), so what is compared is
  the sensor and the DEM it gives, not the algorithm. Over the posts known
  and rated in both: ``detection_rate`` = detected unsafe / truth unsafe,
  ``false_alarm_rate`` = detected unsafe / truth safe.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bench.evaluation.footprint import score_footprint
from bench.scenario import Scenario, ScenarioError
from bench.scenario.seeding import component_rng
from gnc.hazard import _disk, hazard_map
from gnc.messages import LidarScanMessage
from models.camera import R_BC
from models.flash_lidar import FlashLidar
from models.lander import footpad_positions_B
from models.site_dem import SiteGround

TOUCHDOWN_DEM_HALF_M = 5.0  # half-side of the fine DEM scored around the touchdown point [m]
SCAN_GAP_NS = 1_000_000_000  # a flash this long after the last starts a new scan [ns]


class HazardTruth:
    """The fine truth ground of a run and the flash lidar that sees it."""

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        self.cfg = scenario.hazard
        self.ground = SiteGround(scenario.terrain, component_rng(scenario.terrain_seed(), "terrain"))
        self.lidar = (FlashLidar(self.cfg.lidar, component_rng(scenario.seed, "lidar"))
                      if self.cfg.avoidance == "on" else None)
        self.scans: list[dict[str, Any]] = []  # the truth at each scan's first flash
        self.scan_truth: dict[str, Any] | None = None  # the first scan's
        self._last_flash_ns: int | None = None

    def flash(self, t_ns: int, r_BL_L: np.ndarray, q_LB: np.ndarray, nav_r_L: np.ndarray) -> LidarScanMessage:
        """One flash from the truth pose; remembers each scan's truth (and navigation error) for the summary.

        A flash more than ``SCAN_GAP_NS`` after the last starts a new scan (the flashes of one scan are on
        consecutive control ticks); its truth DEM (the footprint with a 2 m and 10 deg allowance) serves
        the scan's later flashes too.
        """
        assert self.lidar is not None
        R_LB = Rotation.from_quat(q_LB, scalar_first=True).as_matrix()
        r_SL_L = np.asarray(r_BL_L, float) + R_LB @ np.asarray(self.cfg.lidar.mount_B_m, float)
        R_LS = R_LB @ R_BC
        if self._last_flash_ns is None or t_ns - self._last_flash_ns > SCAN_GAP_NS:
            nadir = r_SL_L[:2]
            height = float(r_SL_L[2])
            tilt = math.degrees(math.acos(min(1.0, abs(float(R_LS[2, 2])))))
            half = self.lidar.footprint_half_m(height, tilt)
            try:
                dem = self.ground.dem((float(nadir[0]), float(nadir[1])), half, self.cfg.site_spacing_m)
            except ValueError as exc:  # a user's settings, found in flight: name them (the truth has no ground there)
                raise ScenarioError(
                    f"hazard.hda.scan_altitude_m = {self.scenario.hazard.hda.scan_altitude_m:g} (rescan "
                    f"{self.scenario.hazard.hda.rescan_altitude_m:g}): the lidar's footprint at {height:.0f} m, "
                    f"+-{half:.0f} m about ({nadir[0]:.0f}, {nadir[1]:.0f}) m, leaves the ground modelled for it "
                    f"({exc}); allowed: a lower scan altitude, a narrower hazard.lidar.fov_deg, or a larger "
                    "terrain.size_m") from None
            self.scans.append({"t_ns": int(t_ns), "r_BL_L": np.asarray(r_BL_L, float).copy(),
                               "nav_err_xy_m": (np.asarray(nav_r_L, float) - np.asarray(r_BL_L, float))[:2],
                               "dem": dem})
            self.scan_truth = self.scans[0]
        self._last_flash_ns = int(t_ns)
        return self.lidar.scan(t_ns, r_SL_L, R_LS, R_BC, self.scans[-1]["dem"])

    def footprint(self, r_BL_L: np.ndarray, q_LB: np.ndarray) -> dict[str, Any]:
        """The footprint score of a pose (the pads' positions), against a fine DEM around it."""
        lander = self.scenario.lander
        R_LB = Rotation.from_quat(q_LB, scalar_first=True).as_matrix()
        pads = np.asarray(r_BL_L, float) + footpad_positions_B(lander) @ R_LB.T
        axis = np.asarray(r_BL_L, float)[:2]
        try:
            # Wide enough for the pads and for the body's radius (a large body_radius_m left it unjudged).
            half = max(TOUCHDOWN_DEM_HALF_M, self.cfg.criteria.body_radius_m + 1.0) + lander.leg_radius_m
            dem = self.ground.dem((float(axis[0]), float(axis[1])), half, self.cfg.site_spacing_m)
        except ValueError:
            return {"hazard_free": None, "hazards": ["outside_terrain"]}
        out = score_footprint(dem, pads[:, :2], axis, lander.footpad_radius_m, self.cfg.criteria)
        out["x_m"], out["y_m"] = float(axis[0]), float(axis[1])
        return out

    def level_footprint(self, xy_m: np.ndarray) -> dict[str, Any]:
        """The footprint score of an upright lander with its axis at ``xy_m`` (yaw 0)."""
        z = self.ground.dem((float(xy_m[0]), float(xy_m[1])), 3.0, self.cfg.site_spacing_m).height_at(*xy_m)
        return self.footprint(np.array([xy_m[0], xy_m[1], float(z)]), np.array([1.0, 0.0, 0.0, 0.0]))

    def summary(self, fsw: Any, touchdown_pose: tuple[np.ndarray, np.ndarray] | None) -> dict[str, Any]:
        """The ``hazard`` block of the summary (module docstring)."""
        out: dict[str, Any] = {"avoidance": self.cfg.avoidance,
                               "footprint": (self.footprint(*touchdown_pose) if touchdown_pose is not None
                                             else {"hazard_free": None, "hazards": ["no_touchdown"]})}
        free = out["footprint"].get("hazard_free")
        out["footprint"]["hazards"] = ",".join(out["footprint"].get("hazards", []))  # one column in a campaign
        out["hazard_free"] = free
        out["hazard_free_strict"] = out["footprint"].get("hazard_free_strict")
        out["unsafe"] = None if free is None else float(not free)  # numeric, for landbench compare
        if self.cfg.avoidance == "on":
            out["scan"] = self._scan_summary(fsw)
            out["rescan"] = self._rescan_summary(fsw)
        return out

    def _scan_summary(self, fsw: Any) -> dict[str, Any]:
        hda = fsw.hda
        st = hda.stats
        if st.scan_t_ns is None or self.scan_truth is None:
            return {"scanned": False, "no_safe_site": False}
        out = self._one_scan(st, self.scan_truth, hda.last_dem, hda.last_map, hda.cfg.map)
        # no_safe_site: declared (after the second scan, when there was one); first_no_site: this scan found none.
        out.update({"no_safe_site": bool(hda.no_safe_site), "first_no_site": st.no_safe_site,
                    "best_margin_m": st.best_margin_m, "rescanned": bool(hda.rescanned)})
        return out

    def _rescan_summary(self, fsw: Any) -> dict[str, Any]:
        hda = fsw.hda
        st = hda.rescan_stats
        if st is None or st.scan_t_ns is None or len(self.scans) < 2:
            return {"scanned": False}
        out = self._one_scan(st, self.scans[1], hda.rescan_dem, hda.rescan_map, hda.cfg.map)
        out["no_safe_site"] = st.no_safe_site
        return out

    def _one_scan(self, st: Any, truth: dict[str, Any], dem: Any, hmap: Any, map_cfg: Any) -> dict[str, Any]:
        err = truth["nav_err_xy_m"]
        out: dict[str, Any] = {
            "scanned": True, "t_s": st.scan_t_ns / 1e9, "height_m": float(truth["r_BL_L"][2]),
            "flashes": st.flashes, "returns": st.points, "posts_known_frac": st.posts_known_frac,
            "nav_sigma_m": st.nav_sigma_m, "nav_err_at_scan_m": float(np.hypot(*err)), "unsafe_frac": st.unsafe_frac,
            "compute_s": st.compute_s, "no_safe_site": st.no_safe_site, "roughness_detect_m": st.roughness_detect_m,
            "site_xy_m": [None, None], "divert_m": None, "margin_m": None, "site_truth_xy_m": [None, None],
            "site_truth_hazard_free": None,
        }
        if st.site is not None:
            site_true = st.site.xy_m - err
            out.update({"site_xy_m": [float(c) for c in st.site.xy_m], "divert_m": st.site.divert_m,
                        "margin_m": st.site.margin_m, "site_truth_xy_m": [float(c) for c in site_true],
                        "site_truth_hazard_free": self.level_footprint(site_true).get("hazard_free")})
        if dem is not None:
            out["detection"] = self.detection(dem, hmap, err, map_cfg, truth["dem"])
        return out

    def detection(self, scan_dem: Any, det_map: Any, nav_err_xy_m: np.ndarray, map_cfg: Any,
                  truth_dem: Any = None) -> dict[str, Any]:
        """The flight software's unsafe posts against the truth's (module docstring); ``truth_dem``: the scan's
        fine truth DEM (None: the first scan's)."""
        rows, cols = scan_dem.height_m.shape
        x = scan_dem.origin_xy_m[0] + scan_dem.spacing_m * np.arange(cols) - nav_err_xy_m[0]
        y = scan_dem.origin_xy_m[1] + scan_dem.spacing_m * np.arange(rows) - nav_err_xy_m[1]
        X, Y = np.meshgrid(x, y)
        dem = truth_dem if truth_dem is not None else self.scan_truth["dem"]
        h = dem.height_at(X, Y)
        inside = np.isfinite(h)
        truth_map = hazard_map(np.where(inside, h, 0.0).astype(np.float32), scan_dem.spacing_m,
                               (float(x[0]), float(y[0])), map_cfg, known=inside)
        # Posts rated in both: known to the flight software's footprint and inside the truth DEM's.
        rated = ~np.isnan(det_map.tilt_deg) & ~np.isnan(truth_map.tilt_deg)
        reach = int(math.ceil(max(map_cfg.leg_radius_m + map_cfg.footpad_radius_m, map_cfg.body_radius_m)
                              / scan_dem.spacing_m))
        unknown_any = cv2.dilate((~(scan_dem.known & inside)).astype(np.uint8), _disk(reach)).astype(bool)
        rated &= ~unknown_any
        t_uns = truth_map.unsafe & rated
        d_uns = det_map.unsafe & rated
        n_t, n_s = int(t_uns.sum()), int((rated & ~truth_map.unsafe).sum())
        return {"posts_rated": int(rated.sum()), "truth_unsafe": n_t, "detected_unsafe": int(d_uns.sum()),
                "hits": int((t_uns & d_uns).sum()), "false_alarms": int((d_uns & ~truth_map.unsafe).sum()),
                "detection_rate": float((t_uns & d_uns).sum() / n_t) if n_t else None,
                "false_alarm_rate": float((d_uns & ~truth_map.unsafe).sum() / n_s) if n_s else None}
