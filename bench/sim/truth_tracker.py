"""Truth tracker: known terrain points projected into the camera, as :class:`vision.Tracks`.

With ``tracks = "truth"`` the loop feeds the navigation these instead of the
paper's tracker, which separates vision error from filter error: same type,
same rate, exact correspondences (plus optional pixel noise).

Ports:
    Input: the truth camera pose (R_LC, r_CL_L) at each frame.
    Output: :class:`vision.Tracks` (ids persist while a point stays in view).
    Rate: camera rate.

Points are drawn where random pixels' rays meet the terrain surface (the
triangulated surface MuJoCo collides with), topped up whenever fewer than
``n_points`` are in view. Occlusion is ignored (nadir view of gentle relief).
"""

from __future__ import annotations

import numpy as np

from models.terrain import Terrain
from vision.tracks import Tracks

SURFACE_ITERATIONS = 8  # fixed-point steps for a ray meeting the terrain
EDGE_MARGIN_PX = 4.0


class TruthTracker:
    """Exact correspondences of terrain points.

    Args:
        terrain: The terrain (its triangulated surface).
        K: Intrinsics (3, 3) [px].
        image_size: (width, height) [px].
        n_points: Points kept in view.
        rng: The run's vision stream (point sampling and pixel noise).
        pixel_sigma_px: Gaussian pixel noise added to the projections [px].
    """

    def __init__(self, terrain: Terrain, K: np.ndarray, image_size: tuple[int, int], n_points: int,
                 rng: np.random.Generator, pixel_sigma_px: float = 0.0):
        self.terrain = terrain
        self.K = np.asarray(K, float)
        self.K_inv = np.linalg.inv(self.K)
        self.width, self.height = image_size
        self.n_points = n_points
        self.rng = rng
        self.pixel_sigma_px = pixel_sigma_px
        self.reset()

    def reset(self) -> None:
        self._pts_L = np.zeros((0, 3))
        self._ids = np.zeros(0, np.int64)
        self._age = np.zeros(0, np.int64)
        self._prev_xy: dict[int, np.ndarray] = {}
        self._next_id = 0

    def _project(self, R_LC: np.ndarray, r_CL_L: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_C = (pts - r_CL_L) @ R_LC  # rows: R_LC^T (p - r)
        z = p_C[:, 2]
        uv = p_C @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = uv[:, :2] / uv[:, 2:3]
        inside = (z > 0) & (xy[:, 0] >= EDGE_MARGIN_PX) & (xy[:, 0] <= self.width - 1 - EDGE_MARGIN_PX) \
            & (xy[:, 1] >= EDGE_MARGIN_PX) & (xy[:, 1] <= self.height - 1 - EDGE_MARGIN_PX)
        return xy, inside

    def _sample(self, R_LC: np.ndarray, r_CL_L: np.ndarray, n: int) -> np.ndarray:
        pix = np.column_stack([self.rng.uniform(EDGE_MARGIN_PX, self.width - 1 - EDGE_MARGIN_PX, n),
                               self.rng.uniform(EDGE_MARGIN_PX, self.height - 1 - EDGE_MARGIN_PX, n),
                               np.ones(n)])
        d = (R_LC @ (self.K_inv @ pix.T)).T
        d = d[d[:, 2] < -1e-6]
        s = (r_CL_L[2] - self.terrain.surface_height(r_CL_L[0], r_CL_L[1])) / -d[:, 2]
        for _ in range(SURFACE_ITERATIONS):  # walk along each ray to the surface
            p = r_CL_L + s[:, None] * d
            s = (r_CL_L[2] - self.terrain.surface_height(p[:, 0], p[:, 1])) / -d[:, 2]
        return r_CL_L + s[:, None] * d

    def step(self, R_LC: np.ndarray, r_CL_L: np.ndarray) -> Tracks:
        """Tracks of the frame taken from this camera pose."""
        xy, inside = self._project(R_LC, r_CL_L, self._pts_L)
        self._pts_L, xy = self._pts_L[inside], xy[inside]
        self._ids, self._age = self._ids[inside], self._age[inside] + 1
        missing = self.n_points - len(self._ids)
        if missing > 0:
            new = self._sample(R_LC, r_CL_L, missing)
            new_xy, ok = self._project(R_LC, r_CL_L, new)
            new, new_xy = new[ok], new_xy[ok]
            self._pts_L = np.vstack([self._pts_L, new])
            xy = np.vstack([xy, new_xy])
            self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + len(new))])
            self._age = np.concatenate([self._age, np.zeros(len(new), np.int64)])
            self._next_id += len(new)
        if self.pixel_sigma_px > 0:
            xy = xy + self.rng.normal(0.0, self.pixel_sigma_px, xy.shape)
        prev = np.array([self._prev_xy.get(int(i), (np.nan, np.nan)) for i in self._ids]).reshape(-1, 2)
        self._prev_xy = {int(i): p for i, p in zip(self._ids, xy)}
        return Tracks(ids=self._ids.copy(), xy=xy, prev_xy=prev, age=self._age.copy())
