"""Map-relative navigation (LVS-style): the onboard map and the map fix from one camera frame.

Ports:
    Inputs: an :class:`OnboardMap` (plain arrays and their georeferencing,
        loaded before flight); one camera frame (H, W) uint8; the filter's
        estimate of the camera pose (position ``r_CL_L`` and attitude
        ``R_LC``), the camera calibration ``K``, and the 1-sigma of the
        horizontal position prior; :class:`MapFixConfig`.
    Output: :class:`MapFix`: the measured horizontal camera position in the
        map frame, its 2x2 covariance, and the diagnostics (coarse peak,
        peak-to-sidelobe ratio, inliers), or a refusal with its reason.
    Rate: about 1-2 Hz from 500 m down to about 50 m (the caller chooses).

Frames: the map frame M is the landing frame L as the map states it (x east,
y north, z up); the flight software takes M for L, so a georeferencing error
of the map is an error of the landing-site knowledge, not of the fix.
Camera frame C is OpenCV's (x right, y down, z along the boresight).

Algorithm (one frame):
    1. **Orthorectify**: a grid of map points (map pixel centres, heights from
       the map DEM) around the estimated ground footprint is projected through
       the estimated pose into the frame and the frame sampled there
       (``cv2.remap``). With a correct pose the result is the frame laid on the
       map's pixel grid; a horizontal position error ``e`` (estimate minus
       truth) shifts it by ``-e``: the ortho image at map point ``p`` shows the
       ground at ``p - e``.
    2. **Coarse fix**: the central part of the ortho image is correlated
       (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``) over the map window that
       the prior's ``search_sigmas``-sigma ellipse allows. The peak is accepted
       only if it stands clear of its sidelobes: the peak-to-sidelobe ratio
       (peak minus the mean of the correlation surface outside an exclusion
       zone, over its standard deviation) and the ratio of the peak to the
       highest sidelobe must pass their thresholds; otherwise the fix is
       refused (no false lock on a featureless or repetitive map).
    3. **Fine fix**: a grid of patches (about 30-60 with texture) is matched
       each in a small window around the coarse offset, with a sub-pixel peak
       (parabola through the peak and its neighbours on each axis). Outliers
       are rejected by a robust median/MAD test, iterated.
    4. **Covariance**: the inlier offsets' scatter over the effective number of
       independent patches (neighbouring patches err together: their
       correlation is estimated from the residuals of grid neighbours and
       inflates the variance of the mean), plus the sub-pixel floor, plus the
       attitude error and the map DEM's height error seen through the view
       angle (relief parallax).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


# ------------------------------------------------------------------ the onboard map
@dataclass(frozen=True, eq=False)
class OnboardMap:
    """The map the flight software carries: an orthoimage, a DEM and their georeferencing (no truth).

    Arrays are south-up (row index increases with +y, column with +x).

    Attributes:
        image: (N, M) uint8 orthoimage; pixel (i, j) covers the square centred on
            (x0 + (j + 0.5) res, y0 + (i + 0.5) res) in M, (x0, y0) = ``image_origin_xy_m``.
        image_res_m: Orthoimage pixel size [m].
        image_origin_xy_m: M coordinates of the image's south-west corner (pixel edge) [m].
        dem_m: (K, L) float32 heights [m]; post (i, j) at (x0 + j s, y0 + i s), (x0, y0) = ``dem_origin_xy_m``.
        dem_spacing_m: DEM post spacing s [m].
        dem_origin_xy_m: M coordinates of post (0, 0) [m].
        target_xy_m: The landing target in M [m].
        georef_sigma_m: The map's stated georeferencing uncertainty, 1-sigma per axis [m] (its specification).
        dem_sigma_m: The DEM's stated height uncertainty, 1-sigma [m].
    """

    image: np.ndarray
    image_res_m: float
    image_origin_xy_m: tuple[float, float]
    dem_m: np.ndarray
    dem_spacing_m: float
    dem_origin_xy_m: tuple[float, float]
    target_xy_m: tuple[float, float]
    georef_sigma_m: float
    dem_sigma_m: float

    def __post_init__(self) -> None:
        if self.image.ndim != 2 or self.image.dtype != np.uint8:
            raise ValueError(f"image has shape {self.image.shape} and dtype {self.image.dtype}; expected 2-D uint8")
        if self.dem_m.ndim != 2 or min(self.dem_m.shape) < 2:
            raise ValueError(f"dem_m has shape {self.dem_m.shape}; expected a 2-D grid of at least 2 x 2 posts")
        if not (self.image_res_m > 0 and self.dem_spacing_m > 0):
            raise ValueError(f"image_res_m={self.image_res_m} and dem_spacing_m={self.dem_spacing_m} must be > 0")

    def dem_height(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Bilinear DEM height at M points [m] (clamped at the DEM's edge), float64 of the broadcast shape."""
        x, y = np.broadcast_arrays(np.asarray(x_m, np.float64), np.asarray(y_m, np.float64))
        rows, cols = self.dem_m.shape
        u = np.clip((x - self.dem_origin_xy_m[0]) / self.dem_spacing_m, 0.0, cols - 1)
        v = np.clip((y - self.dem_origin_xy_m[1]) / self.dem_spacing_m, 0.0, rows - 1)
        j0 = np.minimum(np.floor(u).astype(np.intp), cols - 2)
        i0 = np.minimum(np.floor(v).astype(np.intp), rows - 2)
        fu, fv = u - j0, v - i0
        h = self.dem_m
        south = (1.0 - fu) * h[i0, j0] + fu * h[i0, j0 + 1]
        north = (1.0 - fu) * h[i0 + 1, j0] + fu * h[i0 + 1, j0 + 1]
        return (1.0 - fv) * south + fv * north

    def pixel_of(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (column, row) of M points, pixel centres at integers [px]."""
        col = (np.asarray(x_m, np.float64) - self.image_origin_xy_m[0]) / self.image_res_m - 0.5
        row = (np.asarray(y_m, np.float64) - self.image_origin_xy_m[1]) / self.image_res_m - 0.5
        return col, row
