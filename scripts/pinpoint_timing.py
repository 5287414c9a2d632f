"""Time one map fix and one hazard map on one core (issue 14's goals: <= 50 ms and <= 1 s per 100 x 100 m at 0.1 m).

Run: ``taskset -c 0 env OMP_NUM_THREADS=1 python scripts/pinpoint_timing.py`` from the repository root.
The map is the default scenario's; frames are synthetic (:mod:`bench.maps.synthetic`) from known poses.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bench.maps import scenario_onboard_map
from bench.maps.synthetic import render_map_frame
from bench.scenario import load_scenario
from gnc.hazard import choose_site, hazard_map
from gnc.map_nav import MapMatcher

REPEATS = 20


def main() -> None:
    cv2.setNumThreads(1)
    onboard, _ = scenario_onboard_map(load_scenario(None))
    matcher = MapMatcher(onboard)
    f_px = 128.0 / math.tan(math.radians(30.0))
    K = np.array([[f_px, 0.0, 127.5], [0.0, f_px, 127.5], [0.0, 0.0, 1.0]])
    R_LC = Rotation.from_euler("xyz", [3.0, -2.0, 40.0], degrees=True).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    rng = np.random.default_rng(0)
    print("| altitude | prior sigma | work resolution | inliers | error | median | slowest |")
    for alt, sigma, xy in [(500, 35.0, (-120, 80)), (500, 20.0, (-120, 80)), (250, 10.0, (-50, 30)),
                           (100, 5.0, (-10, 5)), (50, 3.0, (0, 0))]:
        r = np.array([xy[0], xy[1], float(onboard.dem_height(*xy)) + alt])
        frame = render_map_frame(onboard, K, r, R_LC, rng)
        est = r + np.r_[rng.normal(0.0, sigma, 2), 0.0]
        fix = matcher.fix(frame, K, R_LC, est, sigma)  # warm-up (map pyramid)
        ts = []
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            fix = matcher.fix(frame, K, R_LC, est, sigma)
            ts.append(time.perf_counter() - t0)
        err = np.hypot(*(fix.r_CM_xy_m - r[:2]))
        print(f"| {alt} m | {sigma:g} m | {fix.work_res_m:g} m | {fix.n_inliers}/{fix.n_patches} | {err:.2f} m | "
              f"{1e3 * np.median(ts):.1f} ms | {1e3 * max(ts):.1f} ms |")
    dem = np.cumsum(rng.normal(0.0, 0.01, (1001, 1001)), axis=1).astype(np.float32)
    ts, ts_site = [], []
    for _ in range(7):
        t0 = time.perf_counter()
        hm = hazard_map(dem, 0.1, (-50.0, -50.0))
        ts.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        choose_site(hm, np.zeros(2), 1.0)
        ts_site.append(time.perf_counter() - t0)
    print(f"hazard map, 100 x 100 m at 0.1 m (1001^2 posts): median {np.median(ts):.3f} s, fastest {min(ts):.3f} s; "
          f"site choice median {1e3 * np.median(ts_site):.0f} ms")


if __name__ == "__main__":
    main()
