"""Time the hazard map on the hazardous preset's own ground (issue 14's goal: <= 1 s per 100 x 100 m at 0.1 m).

Run on one core: ``taskset -c 0 env OMP_NUM_THREADS=1 python scripts/hda_timing.py``. The ground is the fine
truth DEM (models.site_dem) of the hazardous preset, seed 1, 100 x 100 m at 0.1 m around the target (1001^2
posts); also timed: one flash-lidar scan from 100 m (bench side, 256^2 rays) and the flight software's DEM from it.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from bench.scenario import load_scenario
from bench.scenario.seeding import component_rng
from bench.sim.hazard_truth import HazardTruth
from gnc.hazard import choose_site, hazard_map
from gnc.hda import grid_dem, scan_points_L

REPEATS = 7


def main() -> None:
    cv2.setNumThreads(1)
    sc = load_scenario(None, ["hazard.avoidance=on"], "hazardous")
    t0 = time.perf_counter()
    truth = HazardTruth(sc)
    print(f"fine truth ground (fBm + catalogs): {time.perf_counter() - t0:.2f} s")
    t0 = time.perf_counter()
    dem = truth.ground.dem((0.0, 0.0), 50.0, 0.1)
    print(f"fine truth DEM 100 x 100 m at 0.1 m ({dem.height_m.shape[0]}^2 posts): {time.perf_counter() - t0:.2f} s")
    ts, ts_site = [], []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        hm = hazard_map(dem.height_m, dem.spacing_m, dem.origin_xy_m, sc.hazard.hda.map)
        ts.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        choose_site(hm, np.zeros(2), 1.0, sc.hazard.hda.map)
        ts_site.append(time.perf_counter() - t0)
    print(f"hazard map 100 x 100 m at 0.1 m: median {np.median(ts):.3f} s, slowest {max(ts):.3f} s "
          f"(unsafe {hm.unsafe.mean():.0%}); site choice median {1e3 * np.median(ts_site):.0f} ms")
    r = np.array([2.0, -3.0, 100.0])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    t0 = time.perf_counter()
    msg = truth.flash(0, r, q, r)
    t_scan = time.perf_counter() - t0
    t0 = time.perf_counter()
    sdem = grid_dem(scan_points_L(msg, r, np.eye(3)), sc.hazard.hda.dem_spacing_m)
    t_dem = time.perf_counter() - t0
    t0 = time.perf_counter()
    hazard_map(sdem.height_m, sdem.spacing_m, sdem.origin_xy_m, sc.hazard.hda.map, known=sdem.known)
    t_map = time.perf_counter() - t0
    print(f"one scan from 100 m: lidar simulation {t_scan:.2f} s (truth side, with its DEM); flight software: DEM "
          f"{1e3 * t_dem:.0f} ms ({sdem.height_m.shape[0]} x {sdem.height_m.shape[1]} posts), hazard map "
          f"{1e3 * t_map:.0f} ms")


if __name__ == "__main__":
    main()
