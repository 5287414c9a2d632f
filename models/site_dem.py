"""Fine truth DEM of the landing site (truth side, NumPy/OpenCV): the terrain's own surface at 0.1 m posts.

Inputs:
    The scenario's :class:`models.terrain.TerrainConfig` (procedural), a
    generator in the terrain's state (the terrain stream), the square to cover
    (centre, half-side) and the post spacing.
Output:
    :class:`SiteDem`: heights on a square grid of posts, south-up, in the
    terrain's datum (``Terrain.height_at(0, 0) == 0``), with the crater and
    boulder catalogs that touch it.
Rate:
    Once per run, when hazards are scored or sensed (about 1 s: one 4096^2
    fBm synthesis, the rest is local).

The ground is the one :func:`models.terrain.generate_terrain` builds, drawn
from the same child streams, but resolved where it matters for a lander's
footprint: the terrain stamps its craters and boulders on 0.25 m texels,
which cannot carry a 0.5 m boulder (a Gaussian of sigma 0.125 m). Here:

* the fBm roughness is the terrain's own texel field (the same spectral
  synthesis), interpolated to the posts with a cubic kernel (it is smooth at
  this scale: H = 0.8);
* every crater and boulder whose support reaches the square is evaluated
  analytically at each post (the terrain's own profiles and catalogs);
* the datum is the terrain's: the tent average of the texel field at the
  centre vertex, recomputed from a local window of texels.

So at texel centres this DEM equals :func:`models.terrain.generate_surface`'s
``height_m`` (a test checks it), and between them it holds what the texels
cannot. Procedural terrains only (a user DEM has no boulder catalog to
resolve).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from models.terrain import (
    BOULDER_SUPPORT_R, CRATER_SUPPORT_R, TerrainConfig, _boulder_rho2, _catalogs, _crater_profile_rho2,
    _tent_matrix, _texel_centres_m, _vertices_m, fbm_surface,
)


@dataclass(frozen=True, eq=False)
class SiteDem:
    """Heights on a square grid of posts.

    Attributes:
        height_m: (n, n) float32 [m], south-up: post (i, j) at
            x = origin_x + j * spacing, y = origin_y + i * spacing.
        spacing_m: Post spacing [m].
        origin_xy_m: L coordinates of post (0, 0) [m].
        boulders: (k, 3) [x_m, y_m, diameter_m] of the boulders whose support reaches the grid.
        craters: (c, 3) [x_m, y_m, diameter_m] likewise.
    """

    height_m: np.ndarray
    spacing_m: float
    origin_xy_m: tuple[float, float]
    boulders: np.ndarray
    craters: np.ndarray

    def __post_init__(self) -> None:
        self.height_m.setflags(write=False)

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the posts [m]."""
        n_r, n_c = self.height_m.shape
        x0, y0 = self.origin_xy_m
        return x0, x0 + (n_c - 1) * self.spacing_m, y0, y0 + (n_r - 1) * self.spacing_m

    def height_at(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> np.ndarray:
        """Bilinear height at L points [m] (NaN outside the grid)."""
        x = np.asarray(x_m, float)
        y = np.asarray(y_m, float)
        u = (x - self.origin_xy_m[0]) / self.spacing_m
        v = (y - self.origin_xy_m[1]) / self.spacing_m
        n_r, n_c = self.height_m.shape
        inside = (u >= 0) & (u <= n_c - 1) & (v >= 0) & (v <= n_r - 1)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, n_c - 2)
        i0 = np.clip(np.floor(v).astype(np.intp), 0, n_r - 2)
        fu, fv = u - j0, v - i0
        h = self.height_m
        out = ((h[i0, j0] * (1 - fu) + h[i0, j0 + 1] * fu) * (1 - fv)
               + (h[i0 + 1, j0] * (1 - fu) + h[i0 + 1, j0 + 1] * fu) * fv)
        return np.where(inside, out, np.nan)


def _add_features(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, catalog: np.ndarray, amplitude: np.ndarray,
                  profile_rho2, support_r: float) -> np.ndarray:
    """Add each feature's ``amplitude * profile((r / R)^2)`` to the posts (xs along columns, ys along rows).

    Returns the mask of features that touch the grid.
    """
    radius = catalog[:, 2] / 2
    reach = support_r * radius
    touch = ((catalog[:, 0] + reach >= xs[0]) & (catalog[:, 0] - reach <= xs[-1])
             & (catalog[:, 1] + reach >= ys[0]) & (catalog[:, 1] - reach <= ys[-1]))
    for k in np.flatnonzero(touch):
        cx, cy, r, rr = catalog[k, 0], catalog[k, 1], radius[k], reach[k]
        j0, j1 = np.searchsorted(xs, cx - rr), np.searchsorted(xs, cx + rr, side="right")
        i0, i1 = np.searchsorted(ys, cy - rr), np.searchsorted(ys, cy + rr, side="right")
        if j0 >= j1 or i0 >= i1:
            continue
        dx2 = (((xs[j0:j1] - cx) / r) ** 2).astype(np.float32)
        dy2 = (((ys[i0:i1] - cy) / r) ** 2).astype(np.float32)
        field[i0:i1, j0:j1] += profile_rho2(dy2[:, None] + dx2[None, :]) * np.float32(amplitude[k])
    return touch


class SiteGround:
    """The terrain's surface at any resolution over any square of it (see the module's docstring).

    Holds the terrain's fBm texel field and catalogs (drawn once, about 1 s and 70 MB for a 4096^2
    texture); :meth:`dem` then makes the DEM of a square in a time proportional to its posts.

    Args:
        cfg: The terrain's configuration (``kind = "procedural"``).
        rng: A generator in the state the terrain was generated from (the terrain stream).

    Raises:
        ValueError: A user-DEM terrain.
    """

    def __init__(self, cfg: TerrainConfig, rng: np.random.Generator):
        if cfg.kind != "procedural":
            raise ValueError("the fine site DEM needs a procedural terrain (terrain.kind = 'procedural'); a user "
                             "DEM has no boulder catalog to resolve")
        self.cfg = cfg
        rng_craters, rng_rough, rng_boulders, _, _ = rng.spawn(5)
        self.size_m = size_m = cfg.size_m
        self.m = m = cfg.texture_px
        self.texel_m = size_m / m
        self._fbm = fbm_surface(m, self.texel_m, cfg.roughness_rms_m, cfg.roughness_hurst, rng_rough)
        self.craters, self._freshness, self.boulders = _catalogs(cfg, rng_craters, rng_boulders, size_m,
                                                                 cfg.crater_max_diameter_m)
        # The datum: the tent average of the texel field at the centre vertex (as generate_surface takes it).
        texels = _texel_centres_m(size_m, m)
        n = cfg.geometry_px
        geo_spacing = size_m / (n - 1)
        centre_vertex = _vertices_m(size_m, n)[[(n - 1) // 2]]
        lo = np.searchsorted(texels, -geo_spacing - 2 * self.texel_m)
        hi = np.searchsorted(texels, geo_spacing + 2 * self.texel_m)
        win = texels[lo:hi]
        field_win, _, _ = self._surface(win, win, self._fbm[lo:hi, lo:hi])
        tent = _tent_matrix(win, centre_vertex, geo_spacing)
        self.datum_m = float((tent @ field_win @ tent.T)[0, 0])

    def _surface(self, xs: np.ndarray, ys: np.ndarray,
                 fbm_part: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.cfg
        d, hr = cfg.crater_depth_ratio, cfg.crater_rim_height_ratio
        field = fbm_part.astype(np.float32, copy=True)
        c_touch = _add_features(field, xs, ys, self.craters, self.craters[:, 2] * self._freshness,
                                lambda rho2: _crater_profile_rho2(rho2, d, hr), CRATER_SUPPORT_R)
        b_touch = _add_features(field, xs, ys, self.boulders, self.boulders[:, 2], _boulder_rho2, BOULDER_SUPPORT_R)
        return field, c_touch, b_touch

    def dem(self, center_xy_m: tuple[float, float] = (0.0, 0.0), half_size_m: float = 80.0,
            spacing_m: float = 0.1) -> SiteDem:
        """The DEM of a square.

        Args:
            center_xy_m: Centre of the square in L [m].
            half_size_m: Half its side [m].
            spacing_m: Post spacing [m].

        Returns:
            The DEM (posts at centre + k * spacing, k = -K..K).

        Raises:
            ValueError: A square that leaves the tile, or a bad spacing.
        """
        if not (spacing_m > 0 and half_size_m > spacing_m):
            raise ValueError(f"spacing_m={spacing_m}, half_size_m={half_size_m}: need 0 < spacing_m < half_size_m")
        size_m, m, texel_m = self.size_m, self.m, self.texel_m
        if max(abs(center_xy_m[0]), abs(center_xy_m[1])) + half_size_m > size_m / 2 - 1.0:
            raise ValueError(f"the site square (centre {center_xy_m}, half side {half_size_m} m) leaves the "
                             f"terrain tile (half side {size_m / 2} m)")
        half_count = int(round(half_size_m / spacing_m))
        xs = center_xy_m[0] + spacing_m * np.arange(-half_count, half_count + 1)
        ys = center_xy_m[1] + spacing_m * np.arange(-half_count, half_count + 1)
        # Texel window around the square (cubic support 2 texels), in texel-index coordinates.
        c0 = int(math.floor((xs[0] + size_m / 2) / texel_m - 0.5)) - 3
        r0 = int(math.floor((ys[0] + size_m / 2) / texel_m - 0.5)) - 3
        c1 = int(math.ceil((xs[-1] + size_m / 2) / texel_m - 0.5)) + 4
        r1 = int(math.ceil((ys[-1] + size_m / 2) / texel_m - 0.5)) + 4
        sub = self._fbm[np.arange(r0, r1) % m][:, np.arange(c0, c1) % m]  # the fBm is periodic
        map_x = ((xs + size_m / 2) / texel_m - 0.5 - c0).astype(np.float32)
        map_y = ((ys + size_m / 2) / texel_m - 0.5 - r0).astype(np.float32)
        mx, my = np.meshgrid(map_x, map_y)
        fbm_posts = cv2.remap(sub, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        field, c_touch, b_touch = self._surface(xs, ys, fbm_posts)
        field -= np.float32(self.datum_m)
        return SiteDem(height_m=field, spacing_m=float(spacing_m), origin_xy_m=(float(xs[0]), float(ys[0])),
                       boulders=self.boulders[b_touch].astype(np.float64),
                       craters=self.craters[c_touch].astype(np.float64))


def site_dem(cfg: TerrainConfig, rng: np.random.Generator, center_xy_m: tuple[float, float] = (0.0, 0.0),
             half_size_m: float = 80.0, spacing_m: float = 0.1) -> SiteDem:
    """The fine truth DEM of one square (:class:`SiteGround` then :meth:`SiteGround.dem`)."""
    return SiteGround(cfg, rng).dem(center_xy_m, half_size_m, spacing_m)
