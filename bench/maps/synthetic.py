"""Synthetic nadir frames of a map's ground, for tests and timing (truth side; no MuJoCo).

Each frame pixel's ray (pinhole ``K``, camera-to-L rotation ``R_LC``, camera
position ``r_C``) is intersected with the map's DEM by fixed-point iteration
(the ray's height at the DEM's height under it), and the ground image is
sampled there with SciPy's cubic spline: an independent computation from the
flight software's orthorectification (which projects map points into the
frame with OpenCV).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from gnc.map_nav import OnboardMap

FIXED_POINT_ITERATIONS = 30


def render_map_frame(m: OnboardMap, K: np.ndarray, r_C: np.ndarray, R_LC: np.ndarray, rng: np.random.Generator,
                     shape: tuple[int, int] = (256, 256), ground: np.ndarray | None = None,
                     noise_dn: float = 2.0) -> np.ndarray:
    """A camera frame of the map's ground (or of ``ground``, an image on the map's grid) from a true pose.

    Args:
        m: The map whose DEM (and, unless ``ground`` is given, image) is the ground.
        K: (3, 3) intrinsics [px].
        r_C: (3,) camera position in L [m].
        R_LC: (3, 3) camera-to-L rotation (OpenCV camera frame).
        rng: Noise stream.
        shape: (H, W) of the frame [px].
        ground: Optional image on ``m``'s pixel grid to show instead of ``m.image``.
        noise_dn: Gaussian noise, 1-sigma [DN].

    Returns:
        (H, W) uint8 frame.
    """
    h, w = shape
    img = (m.image if ground is None else ground).astype(np.float64)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ np.asarray(R_LC).T
    z = np.zeros_like(u)
    dem = m.dem_m.astype(np.float64)
    for _ in range(FIXED_POINT_ITERATIONS):
        t = (z - r_C[2]) / rays[..., 2]
        x, y = r_C[0] + t * rays[..., 0], r_C[1] + t * rays[..., 1]
        rows = (y - m.dem_origin_xy_m[1]) / m.dem_spacing_m
        cols = (x - m.dem_origin_xy_m[0]) / m.dem_spacing_m
        z = scipy.ndimage.map_coordinates(dem, [rows, cols], order=1, mode="nearest")
    col, row = m.pixel_of(x, y)
    frame = scipy.ndimage.map_coordinates(img, [row, col], order=3, mode="nearest")
    frame += noise_dn * rng.standard_normal(frame.shape)
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)
