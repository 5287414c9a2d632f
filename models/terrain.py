"""Seeded procedural lunar terrain and user-DEM loader (pure NumPy/SciPy/OpenCV).

Inputs:
    :class:`TerrainConfig` (what to build), a ``numpy.random.Generator`` (the
    only source of randomness) and the sun direction (the fine-scale shading is
    baked into the texture for that sun).

Outputs:
    :class:`Terrain`: a coarse geometry grid ``height_m`` (for a MuJoCo
    heightfield; triangle count drives render cost), a high-resolution uint8
    ``albedo`` texture carrying the fine detail, and the crater and boulder
    catalogs actually stamped.

Conventions:
    * Landing frame L: origin at the landing target, x east, y north, z up.
      The terrain is a square of side ``size_m`` centred on the origin, and its
      heights are shifted so ``height_at(0, 0) == 0`` exactly.
    * Arrays are south-up: row index increases with +y (row 0 is the south
      edge, y = -size/2), column index with +x (column 0 is the west edge).
      This holds for ``height_m`` and ``albedo``; renderers flip as needed.
    * ``height_m`` is a vertex grid: vertex (i, j) sits at
      x = -size/2 + j * spacing, y = -size/2 + i * spacing,
      spacing = size / (n - 1); n is odd so the centre vertex is the origin.
    * The texture is a cell grid: texel (i, j) covers the square centred on
      x = -size/2 + (j + 0.5) * texel, y = -size/2 + (i + 0.5) * texel,
      texel = size / m (the usual texture-mapping convention).
    * Sun azimuth is measured from north (+y) clockwise toward east (+x),
      elevation above the horizon, both in degrees.
    * DEM files are read as stored, north-up (row 0 = north edge, the raster
      and image convention) and flipped to south-up in the :class:`Terrain`.

How it is built:
    1. A fine DEM at texture resolution: spectral fBm, plus craters (Poisson
       count, truncated power-law sizes, bowl + raised rim + ejecta, stamped on
       a window around each), plus boulders (Gaussian bumps, power-law sizes).
       For a user DEM: the DEM interpolated to the texels, plus synthetic
       detail (fBm, craters, boulders) only below the DEM's resolution.
    2. Geometry = tent-weighted area average of the fine DEM at the vertices.
    3. Texture = albedo (low-contrast fBm, bright halos of fresh craters) x
       shading of the *high-pass residual* (fine DEM minus its smooth Gaussian
       low-pass at the geometry scale), with cast shadows by default. The
       renderer shades the coarse geometry itself; baking only the residual
       avoids shading the coarse relief twice. DN = texture_mean_dn *
       (albedo / albedo_mean) * relative shading, so flat lit ground of mean
       albedo maps to texture_mean_dn.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import scipy.fft
import scipy.sparse
from pydantic import BaseModel, ConfigDict, Field, model_validator

# ----------------------------------------------------------------- constants
M2_PER_KM2 = 1.0e6
MAX_CATALOG_FEATURES = 2.0e6  # craters (or boulders) one terrain may stamp; 250 000 took 6 s to generate (1024² texture)
# Texels the craters and boulders are stamped over at texture resolution, expected (stamped_texels_expected): about
# 80 million a second on the 2-core reference machine (3.5e9 took 46 s, 2e10 about 4 min); the default terrain's 7.9e7 is 1 s.
MAX_STAMPED_TEXELS = 2.0e10
STAMPED_TEXELS_PER_S = 8.0e7
MIN_DEM_PX = 16  # smallest DEM side accepted [px]
# Crater shape, in crater radii R = D/2 (see crater_profile):
CRATER_EJECTA_DECAY_R = 0.35  # e-folding distance of the ejecta blanket beyond the rim [R]
CRATER_SUPPORT_R = 2.5  # the profile is exactly 0 beyond this distance [R]
# Fresh-crater bright halo: relative albedo gain decays beyond the rim like this [R].
CRATER_HALO_DECAY_R = 0.5
# A crater is "fresh" (bright halo) when its freshness exceeds this fraction of
# the way from crater_freshness_min to 1.
CRATER_FRESH_THRESHOLD = 0.8
# Boulders: Gaussian bump of peak height ratio*D and sigma ratio*D, cut at SUPPORT sigmas.
BOULDER_HEIGHT_RATIO = 0.5  # half-buried: protrudes half its diameter
BOULDER_SIGMA_RATIO = 0.25
BOULDER_SUPPORT_SIGMA = 3.0
# Stamping: craters whose window half-width is at most this many texels are
# stamped together in vectorised batches; larger ones one by one on a slice.
STAMP_BATCH_MAX_HALF_PX = 24
STAMP_BATCH_ELEMENTS = 4_000_000  # texels per vectorised batch (bounds memory)
# User DEM: synthetic detail is added only below the DEM's own resolution.
DEM_DETAIL_MAX_WAVELENGTH_PX = 2.0  # fBm modes longer than this many DEM spacings are left to the DEM
DEM_UNRESOLVED_CRATER_PX = 2.0  # synthetic craters only up to this many DEM spacings across
# Landing-site patch: its baked detail holds wavelengths below this many coarse
# texels, and fades out over this fraction of the patch half-width at its edge.
PATCH_DETAIL_MAX_WAVELENGTH_TEXELS = 2.0
PATCH_FEATHER_FRAC = 0.15
# Texture photometry.
SHADOW_FLOOR = 0.15  # brightness of shadowed texels relative to flat lit ground (scattered light)
SHADE_MAX = 2.0  # cap on relative brightness of steep sun-facing texels
ALBEDO_REL_FLOOR = 0.2  # lower bound on albedo / albedo_mean (fBm tails)
SHADOW_FLAT_EPS_M = 1e-4  # height margin before a texel counts as cast-shadowed [m]
SHADOW_STRIP_ROWS = 256  # rows of the rotated grid swept at a time when baking cast shadows
# Residual = fine DEM minus its Gaussian low-pass with this sigma [geometry spacings]; the
# tent average + linear interpolation of the geometry passes about the same band.
RESIDUAL_LOWPASS_SIGMA_SPACINGS = 0.5
KEYS_CUBIC_A = -0.5  # cubic-convolution parameter that makes the interpolant exact for quadratics
LOWPASS_WORK_SIGMA_PX = 4.0  # the low-pass is run on a grid decimated until sigma is about this [px]
UINT8_MAX = 255


# --------------------------------------------------------------------- config
class TerrainConfig(BaseModel):
    """What terrain to build: procedural (seeded) or a user DEM plus synthetic detail.

    Defaults describe a typical lunar mare surface near crater saturation
    equilibrium, at 0.25 m/texel over a 1024 m square.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    kind: Literal["procedural", "dem"] = Field("procedural", description="'procedural' or 'dem' (user DEM file)")
    seed: int | None = Field(
        None, ge=0, description="terrain seed; None -> the caller derives it from the scenario seed (not used here)"
    )
    size_m: float = Field(
        1024.0, gt=0.0, le=100_000.0,
        description="side of the square terrain [m] (procedural; for a DEM the side is dem_spacing_m * (n - 1))",
    )
    geometry_px: int = Field(129, ge=17, le=4097, description="heightfield vertices per side (odd)")
    texture_px: int = Field(
        4096, ge=64, le=8192, description="albedo texture texels per side (>= geometry_px; memory ~ 35 B/texel)"
    )

    crater_density_per_km2: float = Field(
        2.0e4, ge=0.0, le=1.0e7,
        description="cumulative count of craters with D >= crater_min_diameter_m per km^2 "
        "(default: Trask's mare equilibrium N(>=D) = 10^-1.1 D^-2 per m^2 at D = 2 m)",
    )
    crater_sfd_exponent: float = Field(2.0, gt=0.0, le=5.0, description="b in the cumulative SFD N(>=D) ~ D^-b [-]")
    crater_min_diameter_m: float = Field(2.0, gt=0.0, description="smallest crater diameter [m]")
    crater_max_diameter_m: float = Field(200.0, gt=0.0, description="largest crater diameter [m]")
    crater_depth_ratio: float = Field(0.2, gt=0.0, le=0.5, description="depth/diameter of a fresh bowl [-]")
    crater_rim_height_ratio: float = Field(0.04, ge=0.0, le=0.2, description="rim height/diameter, fresh [-]")
    crater_freshness_min: float = Field(
        0.25, gt=0.0, le=1.0,
        description="each crater's depth and rim are scaled by a freshness ~ U(this, 1) (degradation) [-]",
    )
    crater_fresh_albedo_gain: float = Field(
        0.3, ge=0.0, le=2.0, description="relative albedo increase inside and around the freshest craters [-]"
    )

    roughness_rms_m: float = Field(2.0, ge=0.0, le=1000.0, description="RMS height of the fBm roughness [m]")
    roughness_hurst: float = Field(0.8, gt=0.0, le=1.0, description="Hurst exponent H of the fBm [-]")

    boulder_density_per_km2: float = Field(
        500.0, ge=0.0, le=1.0e7, description="cumulative count of boulders with D >= boulder_min_diameter_m per km^2"
    )
    boulder_sfd_exponent: float = Field(2.5, gt=0.0, le=6.0, description="b in boulders' N(>=D) ~ D^-b [-]")
    boulder_min_diameter_m: float = Field(0.5, gt=0.0, description="smallest boulder diameter [m]")
    boulder_max_diameter_m: float = Field(4.0, gt=0.0, description="largest boulder diameter [m]")

    target_clear_radius_m: float = Field(
        70.0, ge=0.0,
        description="no crater rim or boulder within this radius of the origin [m]: the landing ellipse. "
        "Default: 3.4 sigma of a 20 m per-axis hand-over position error, which vision (velocity only) does not remove",
    )

    patch_size_m: float = Field(
        128.0, ge=0.0,
        description="side of the high-resolution texture patch around the landing target [m]; 0 = none. "
        "Snapped to whole geometry cells. It keeps sub-texel detail in view down to the vision cut-off",
    )
    patch_texture_px: int = Field(2048, ge=64, le=8192, description="patch texture texels per side")
    patch_roughness_rms_m: float = Field(
        0.02, ge=0.0, le=1.0,
        description="RMS height of the sub-texel roughness band (wavelengths below two coarse texels) whose "
        "shading is baked into the patch texture [m]",
    )
    albedo_mean: float = Field(
        0.12, gt=0.0, le=1.0, description="physical albedo that maps to texture_mean_dn on flat lit ground [-]"
    )
    albedo_contrast: float = Field(0.15, ge=0.0, le=1.0, description="RMS of albedo/albedo_mean - 1 [-]")
    albedo_hurst: float = Field(
        0.1, ge=0.0, le=1.0, description="Hurst exponent of the albedo fBm (low = more fine-scale variation) [-]"
    )
    texture_mean_dn: float = Field(
        120.0, gt=0.0, lt=255.0, description="texture value of albedo_mean on flat lit ground [DN]"
    )
    photometric_function: Literal["lommel_seeliger", "lambert"] = Field(
        "lommel_seeliger", description="reflectance law for the baked fine-scale shading (nadir view)"
    )
    bake_cast_shadows: Literal["none", "residual", "full"] = Field(
        "residual",
        description="cast shadows baked into the texture: none; from the fine detail only (with "
        "relief_shading='texture', the whole relief: nothing is left to the renderer); "
        "from the full fine DEM (use when the renderer draws no shadows itself)",
    )
    relief_shading: Literal["renderer", "texture"] = Field(
        "texture",
        description="who shades the relief the geometry carries: 'renderer', the sun light on the heightfield "
        "(MuJoCo shades it flat per triangle; the texture carries the finer relief's shading); 'texture', the "
        "whole fine DEM's shading baked into the texture and the terrain drawn unlit (the default): no facets, so "
        "one sample per pixel (camera.multisampling='auto' or 0) keeps the frames trackable at half the render time",
    )

    dem_path: pathlib.Path | None = Field(
        None, description="kind='dem': .npy (2-D numeric), 16-bit PNG, or GeoTIFF (.tif/.tiff, the 'geo' extra)"
    )
    dem_spacing_m: float | None = Field(
        None, gt=0.0, description="kind='dem': DEM post spacing [m] (a GeoTIFF's is read from the file)"
    )
    dem_target_xy: tuple[float, float] | None = Field(
        None,
        description="GeoTIFF: the landing target in the file's own projected coordinates (x, y) [m], snapped to "
        "the nearest post; unset: the raster's centre",
    )
    dem_tile_m: float | None = Field(
        None, gt=0.0,
        description="GeoTIFF: side of the square cropped around the target [m]; unset: the largest that fits",
    )
    dem_z_scale_m: float = Field(
        1.0, gt=0.0, description="metres per stored unit, for PNG (DN) and .npy alike [m]"
    )

    @model_validator(mode="after")
    def _check_consistency(self) -> TerrainConfig:
        if self.geometry_px % 2 == 0:
            raise ValueError(
                f"geometry_px={self.geometry_px} is even; it must be odd so the centre vertex is the landing "
                f"target, e.g. {self.geometry_px + 1}"
            )
        if self.texture_px < self.geometry_px:
            raise ValueError(
                f"texture_px={self.texture_px} < geometry_px={self.geometry_px}; the texture must be at least as "
                f"fine as the geometry"
            )
        for what in ("crater", "boulder"):
            lo, hi = getattr(self, f"{what}_min_diameter_m"), getattr(self, f"{what}_max_diameter_m")
            if hi <= lo:
                raise ValueError(
                    f"{what}_min_diameter_m = {lo:g} is not below {what}_max_diameter_m = {hi:g}; allowed: "
                    f"{what}_min_diameter_m < {what}_max_diameter_m"
                )
            # The catalog's expected size (_power_law_catalog): each feature is stamped one by one.
            density = getattr(self, f"{what}_density_per_km2")
            mean = expected_feature_count(self, what)
            if mean > MAX_CATALOG_FEATURES:
                raise ValueError(
                    f"{what}_density_per_km2={density:g} over size_m={self.size_m:g} m gives about {mean:.3g} "
                    f"{what}s (from {lo:g} m); allowed: at most {MAX_CATALOG_FEATURES:.0e}: lower the density or "
                    f"raise {what}_min_diameter_m"
                )
        # Each feature is stamped over its own support, so the cost is their area, not their count (large
        # craters at a high density passed the count check and took hours).
        texels = stamped_texels_expected(self)
        if texels > MAX_STAMPED_TEXELS:
            raise ValueError(
                f"craters and boulders would be stamped over about {texels:.3g} texels (their areas at texture_px = "
                f"{self.texture_px} over size_m = {self.size_m:g} m: crater_density_per_km2 = "
                f"{self.crater_density_per_km2:g}, crater diameters {self.crater_min_diameter_m:g}-"
                f"{self.crater_max_diameter_m:g} m), about {texels / STAMPED_TEXELS_PER_S / 60.0:.2g} min of "
                f"generation on a 2-core machine; allowed: at most {MAX_STAMPED_TEXELS:.0e}: "
                f"lower the density or crater_max_diameter_m, or raise crater_sfd_exponent"
            )
        if self.kind == "procedural":
            if self.target_clear_radius_m >= self.size_m / 2:
                raise ValueError(
                    f"target_clear_radius_m={self.target_clear_radius_m} must be < size_m/2={self.size_m / 2}"
                )
            if self.dem_path is not None or self.dem_spacing_m is not None:
                raise ValueError(
                    f"dem_path={self.dem_path} / dem_spacing_m={self.dem_spacing_m} are only used with "
                    f"kind='dem'; set kind='dem' or remove them"
                )
            return self
        if self.dem_path is not None and is_geotiff(self.dem_path):
            dem, spacing = load_geotiff(self.dem_path, self.dem_target_xy, self.dem_tile_m, self.dem_z_scale_m)
            if self.dem_spacing_m is not None and not math.isclose(self.dem_spacing_m, spacing, rel_tol=1e-6):
                raise ValueError(
                    f"dem_spacing_m={self.dem_spacing_m} differs from the GeoTIFF's own {spacing} m; "
                    "leave dem_spacing_m unset for a GeoTIFF"
                )
            self.dem_spacing_m = spacing
        else:
            if self.dem_target_xy is not None or self.dem_tile_m is not None:
                raise ValueError(
                    f"dem_target_xy={self.dem_target_xy} / dem_tile_m={self.dem_tile_m} are only used with a "
                    "GeoTIFF dem_path (.tif/.tiff); remove them"
                )
            if self.dem_path is None or self.dem_spacing_m is None:
                raise ValueError(
                    f"kind='dem' requires dem_path and dem_spacing_m (got dem_path={self.dem_path}, "
                    f"dem_spacing_m={self.dem_spacing_m})"
                )
            dem = load_dem(self.dem_path, self.dem_spacing_m, self.dem_z_scale_m)  # fail now, not mid-run
        half_m = self.dem_spacing_m * (min(dem.shape) - 1) / 2
        if self.target_clear_radius_m >= half_m:
            raise ValueError(
                f"target_clear_radius_m={self.target_clear_radius_m} must be < half the DEM tile side, {half_m} m"
            )
        return self


# -------------------------------------------------------------------- terrain
@dataclass(frozen=True, eq=False)
class TerrainPatch:
    """High-resolution texture patch centred on the landing target.

    Its geometry is the 2x refinement of the coarse grid sampled on the coarse
    triangulated surface (same diagonal), so it is coplanar with it: the
    renderer draws it a hair above the terrain and it changes nothing but the
    texture resolution near the target.

    Attributes:
        height_m: (k, k) float32 vertex heights [m], south-up, spanning
            [-size/2, size/2] in x and y.
        size_m: Side of the patch [m].
        albedo: (p, p) uint8 texture, south-up.
    """

    height_m: np.ndarray
    size_m: float
    albedo: np.ndarray

    def __post_init__(self) -> None:
        for arr in (self.height_m, self.albedo):
            arr.setflags(write=False)


@dataclass(frozen=True, eq=False)
class Terrain:
    """A terrain tile: coarse geometry, fine albedo texture, feature catalogs.

    Attributes:
        height_m: (n, n) float32 vertex heights [m], south-up (row 0 at
            y = -size/2, column 0 at x = -size/2); height_at(0, 0) == 0.
        size_m: Side of the square tile [m], centred on the origin.
        albedo: (m, m) uint8 texture, south-up like ``height_m``; fine-scale
            shading for the generation sun is baked in.
        craters: (k, 3) float64 [x_m, y_m, diameter_m] of the stamped craters.
        boulders: (j, 3) float64 [x_m, y_m, diameter_m] of the stamped boulders.
        patch: The landing-site patch, or None.
        relief_shaded: True when ``albedo`` (and the patch's) carries the shading of the whole relief
            (``TerrainConfig.relief_shading = "texture"``): the world then draws the terrain unlit.

    The arrays are made read-only.
    """

    height_m: np.ndarray
    size_m: float
    albedo: np.ndarray
    craters: np.ndarray
    boulders: np.ndarray
    patch: "TerrainPatch | None" = None
    relief_shaded: bool = False

    def __post_init__(self) -> None:
        h = self.height_m
        if h.ndim != 2 or h.shape[0] != h.shape[1] or h.shape[0] < 2:
            raise ValueError(f"height_m has shape {h.shape}; expected a square (n, n) grid with n >= 2")
        if self.albedo.ndim != 2 or self.albedo.shape[0] != self.albedo.shape[1] or self.albedo.dtype != np.uint8:
            raise ValueError(
                f"albedo has shape {self.albedo.shape} and dtype {self.albedo.dtype}; expected (m, m) uint8"
            )
        for name in ("craters", "boulders"):
            cat = getattr(self, name)
            if cat.ndim != 2 or cat.shape[1] != 3:
                raise ValueError(f"{name} has shape {cat.shape}; expected (k, 3) [x_m, y_m, diameter_m]")
        if not self.size_m > 0:
            raise ValueError(f"size_m={self.size_m} must be > 0")
        for arr in (self.height_m, self.albedo, self.craters, self.boulders):
            arr.setflags(write=False)

    def geometry_only(self) -> "Terrain":
        """The same ground without its textures (a 1-texel albedo, no patch): enough for what reads
        only the geometry (``surface_height``, ``hillshade``, ``spacing_m``), and cheap to send to
        another process. The patch is coplanar with the coarse surface: no geometry is lost."""
        return dataclasses.replace(self, albedo=np.zeros((1, 1), np.uint8), patch=None)

    @property
    def spacing_m(self) -> float:
        """Vertex spacing of ``height_m`` [m]."""
        return self.size_m / (self.height_m.shape[0] - 1)

    def height_at(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> np.ndarray:
        """Bilinear interpolation of ``height_m``.

        Args:
            x_m: East coordinates in L [m], any shape.
            y_m: North coordinates in L [m], broadcastable with ``x_m``.

        Returns:
            Heights [m], float64, of the broadcast shape. Points outside the
            tile take the height of the nearest edge point.
        """
        x, y = np.broadcast_arrays(np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64))
        n = self.height_m.shape[0]
        centre = (n - 1) / 2  # exact: n is odd, so x = 0 lands exactly on a vertex
        u = np.clip(x / self.spacing_m + centre, 0.0, n - 1)
        v = np.clip(y / self.spacing_m + centre, 0.0, n - 1)
        j0 = np.minimum(np.floor(u).astype(np.intp), n - 2)
        i0 = np.minimum(np.floor(v).astype(np.intp), n - 2)
        fu, fv = u - j0, v - i0
        h = self.height_m
        south = (1.0 - fu) * h[i0, j0] + fu * h[i0, j0 + 1]
        north = (1.0 - fu) * h[i0 + 1, j0] + fu * h[i0 + 1, j0 + 1]
        return (1.0 - fv) * south + fv * north

    def surface_height(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> np.ndarray:
        """Height of the triangulated surface that MuJoCo collides with and renders.

        MuJoCo splits each heightfield cell into two triangles along the
        diagonal from its south-west to its north-east vertex; this is that
        piecewise-planar surface (``height_at`` is the bilinear one).

        Args:
            x_m: East coordinates in L [m], any shape.
            y_m: North coordinates in L [m], broadcastable with ``x_m``.

        Returns:
            Heights [m], float64, of the broadcast shape (clamped at the edges).
        """
        x, y = np.broadcast_arrays(np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64))
        n = self.height_m.shape[0]
        centre = (n - 1) / 2
        u = np.clip(x / self.spacing_m + centre, 0.0, n - 1)
        v = np.clip(y / self.spacing_m + centre, 0.0, n - 1)
        j0 = np.minimum(np.floor(u).astype(np.intp), n - 2)
        i0 = np.minimum(np.floor(v).astype(np.intp), n - 2)
        fu, fv = u - j0, v - i0
        h = self.height_m.astype(np.float64)
        z00, z10, z01, z11 = h[i0, j0], h[i0, j0 + 1], h[i0 + 1, j0], h[i0 + 1, j0 + 1]
        lower = z00 + fu * (z10 - z00) + fv * (z11 - z10)  # triangle (SW, SE, NE): fu >= fv
        upper = z00 + fv * (z01 - z00) + fu * (z11 - z01)  # triangle (SW, NE, NW): fu < fv
        return np.where(fu >= fv, lower, upper)

    def hillshade(self, sun_elevation_deg: float, sun_azimuth_deg: float) -> np.ndarray:
        """Lambertian shading of the geometry grid, for plots.

        Args:
            sun_elevation_deg: Sun elevation above the horizon [deg].
            sun_azimuth_deg: Sun azimuth from north, clockwise toward east [deg].

        Returns:
            (n, n) float64 in [0, 1], south-up like ``height_m`` (no cast shadows).
        """
        dz_dy, dz_dx = np.gradient(self.height_m.astype(np.float64), self.spacing_m)
        sx, sy, sz = _sun_vector(sun_elevation_deg, sun_azimuth_deg)
        cos_i = (sz - dz_dx * sx - dz_dy * sy) / np.sqrt(1.0 + dz_dx**2 + dz_dy**2)
        return np.clip(cos_i, 0.0, 1.0)


# ------------------------------------------------------------------ profiles
def _power_law_moment(lo: float, hi: float, b: float, k: int) -> float:
    """E[D^k] of diameters with the cumulative law N(>=D) ~ D^-b truncated to [lo, hi] (as _power_law_catalog)."""
    c = b * lo**b / (1.0 - (lo / hi) ** b)
    return c * (math.log(hi / lo) if abs(k - b) < 1e-12 else (hi ** (k - b) - lo ** (k - b)) / (k - b))


def expected_feature_count(cfg: "TerrainConfig", what: str) -> float:
    """Expected number of craters or boulders (``what``) on the tile, as _power_law_catalog draws them."""
    lo, hi = getattr(cfg, f"{what}_min_diameter_m"), getattr(cfg, f"{what}_max_diameter_m")
    return (getattr(cfg, f"{what}_density_per_km2") * cfg.size_m**2 / M2_PER_KM2
            * (1.0 - (hi / lo) ** -getattr(cfg, f"{what}_sfd_exponent")))


def stamped_texels_expected(cfg: "TerrainConfig") -> float:
    """Expected texels the craters and boulders are stamped over at texture resolution (_stamp_radial: each
    feature over a square of its support, ``(2 support R / texel + 1)^2``), the terrain generation's main cost."""
    texel_m = cfg.size_m / cfg.texture_px
    total = 0.0
    for what, support_r in (("crater", CRATER_SUPPORT_R), ("boulder", BOULDER_SUPPORT_R)):
        lo, hi = getattr(cfg, f"{what}_min_diameter_m"), getattr(cfg, f"{what}_max_diameter_m")
        b = getattr(cfg, f"{what}_sfd_exponent")
        n = expected_feature_count(cfg, what)
        a = support_r / texel_m  # texels per unit diameter across the square (2 support R = support D)
        total += n * (a * a * _power_law_moment(lo, hi, b, 2) + 2.0 * a * _power_law_moment(lo, hi, b, 1) + 1.0)
    return total


def crater_profile(r_over_R: np.ndarray, depth_ratio: float, rim_height_ratio: float) -> np.ndarray:
    """Height of a simple crater relative to the pre-crater surface, over its diameter.

    Parabolic bowl from -depth_ratio at the centre up to the rim crest
    (+rim_height_ratio at r = R), then an exponentially decaying ejecta blanket
    (e-folding CRATER_EJECTA_DECAY_R radii) that is tapered to reach exactly 0
    at CRATER_SUPPORT_R radii and stays 0 beyond.

    Args:
        r_over_R: Distance from the crater centre over the crater radius [-], any shape.
        depth_ratio: Floor depth / diameter [-].
        rim_height_ratio: Rim height / diameter [-].

    Returns:
        Height / diameter [-], float64, same shape as ``r_over_R``.
    """
    rho = np.abs(np.asarray(r_over_R, dtype=np.float64))
    return _crater_profile_rho2(rho * rho, depth_ratio, rim_height_ratio)


def _crater_profile_rho2(rho2: np.ndarray, depth_ratio: float, rim_height_ratio: float) -> np.ndarray:
    """crater_profile as a function of (r/R)^2 (avoids a sqrt inside the bowl); keeps rho2's dtype."""
    end = math.exp(-(CRATER_SUPPORT_R - 1.0) / CRATER_EJECTA_DECAY_R)
    bowl = rho2 * (depth_ratio + rim_height_ratio) - depth_ratio
    rho = np.sqrt(np.maximum(rho2, 1.0, dtype=rho2.dtype))
    ejecta = (np.exp((1.0 - rho) / CRATER_EJECTA_DECAY_R) - end) * (rim_height_ratio / (1.0 - end))
    out = np.where(rho2 <= 1.0, bowl, np.where(rho < CRATER_SUPPORT_R, ejecta, 0.0))
    return out.astype(rho2.dtype, copy=False)


def _halo_rho2(rho2: np.ndarray) -> np.ndarray:
    """Relative albedo gain of a fresh crater vs (r/R)^2: 1 inside, decaying to 0 at CRATER_SUPPORT_R."""
    end = math.exp(-(CRATER_SUPPORT_R - 1.0) / CRATER_HALO_DECAY_R)
    rho = np.sqrt(np.maximum(rho2, 1.0, dtype=rho2.dtype))
    out = np.where(rho < CRATER_SUPPORT_R, (np.exp((1.0 - rho) / CRATER_HALO_DECAY_R) - end) / (1.0 - end), 0.0)
    return out.astype(rho2.dtype, copy=False)


def _boulder_rho2(rho2: np.ndarray) -> np.ndarray:
    """Boulder height / diameter vs (r/R)^2, R = D/2: Gaussian, 0 beyond BOULDER_SUPPORT_SIGMA."""
    sigma_r = 2.0 * BOULDER_SIGMA_RATIO  # sigma in radii
    cut = math.exp(-0.5 * BOULDER_SUPPORT_SIGMA**2)
    g = (np.exp(rho2 * (-0.5 / sigma_r**2)) - cut) * (BOULDER_HEIGHT_RATIO / (1.0 - cut))
    out = np.maximum(g, 0.0)
    return out.astype(rho2.dtype, copy=False)


BOULDER_SUPPORT_R = BOULDER_SUPPORT_SIGMA * 2.0 * BOULDER_SIGMA_RATIO  # support of _boulder_rho2 [R]


# ----------------------------------------------------------------------- fBm
def fbm_surface(
    n_px: int,
    spacing_m: float,
    rms_m: float,
    hurst: float,
    rng: np.random.Generator,
    max_wavelength_m: float | None = None,
) -> np.ndarray:
    """Periodic fractional-Brownian surface by spectral synthesis.

    Complex Gaussian Fourier coefficients (Hermitian-symmetric, so the field
    is real) shaped to a power spectral density ~ k^-(2H+2), zero mean, scaled
    so the full-band field has RMS exactly ``rms_m``.

    Args:
        n_px: Samples per side.
        spacing_m: Sample spacing [m].
        rms_m: RMS height of the full-band field [m].
        hurst: Hurst exponent H [-] (0 <= H <= 1).
        rng: Random source.
        max_wavelength_m: If given, modes with longer wavelengths are removed
            after the RMS scaling (the result then has a smaller RMS).

    Returns:
        (n_px, n_px) float32 heights [m].
    """
    n_cols = n_px // 2 + 1
    spec = rng.standard_normal((n_px, n_cols, 2), dtype=np.float32).view(np.complex64)[:, :, 0]
    # Columns 0 and (even n) n/2 hold modes that are their own conjugate's
    # column: make them Hermitian along rows, as a real field's rfft2 is.
    for col in (0, n_px // 2) if n_px % 2 == 0 else (0,):
        c = spec[:, col]
        c[n_px // 2 + 1:] = np.conj(c[1:(n_px + 1) // 2][::-1])
        c[0] = c[0].real
        if n_px % 2 == 0:
            c[n_px // 2] = c[n_px // 2].real
    ky = scipy.fft.fftfreq(n_px, d=spacing_m).astype(np.float32)[:, None]
    kx = scipy.fft.rfftfreq(n_px, d=spacing_m).astype(np.float32)[None, :]
    gain = ky * ky + kx * kx  # k^2, turned into the amplitude gain in place
    too_long = None if max_wavelength_m is None else gain < np.float32(1.0 / max_wavelength_m) ** 2
    gain[0, 0] = 1.0  # DC is zeroed below; avoid 0 ** negative
    np.power(gain, np.float32(-(hurst + 1.0) / 2.0), out=gain)  # amplitude ~ k^-(H+1)
    gain[0, 0] = 0.0
    spec *= gain
    del gain
    # Realised variance (Parseval): columns other than 0 and n/2 stand for two modes each.
    edge_cols = [0] + ([n_px // 2] if n_px % 2 == 0 else [])
    total = 2.0 * np.vdot(spec, spec).real - sum(np.vdot(spec[:, c], spec[:, c]).real for c in edge_cols)
    var = float(total) / float(n_px) ** 4
    if too_long is not None:
        spec[too_long] = 0.0
    spec *= np.float32(rms_m / math.sqrt(var) if var > 0 else 0.0)
    field = scipy.fft.irfft2(spec, s=(n_px, n_px), workers=-1, overwrite_x=True)
    return field.astype(np.float32, copy=False)


# ------------------------------------------------------------------ sampling
def _power_law_catalog(
    rng: np.random.Generator,
    density_per_km2: float,
    size_m: float,
    d_min_m: float,
    d_max_m: float,
    exponent: float,
) -> np.ndarray:
    """Poisson-distributed features, uniform in the tile, with a truncated power-law SFD.

    ``density_per_km2`` is N(>=d_min) of the untruncated law, so the expected
    count in [d_min, d_max) is density * area * (1 - (d_max/d_min)^-b).

    Returns:
        (k, 3) float64 [x_m, y_m, diameter_m].
    """
    tail = (d_max_m / d_min_m) ** -exponent
    mean = density_per_km2 * size_m**2 / M2_PER_KM2 * (1.0 - tail)
    count = int(rng.poisson(mean))
    xy = rng.uniform(-size_m / 2, size_m / 2, size=(count, 2))
    u = rng.uniform(size=count)
    # Inverse CDF of the truncated Pareto: N(>=D) ~ D^-b - d_max^-b on [d_min, d_max).
    a_min, a_max = d_min_m**-exponent, d_max_m**-exponent
    diam = (a_min - u * (a_min - a_max)) ** (-1.0 / exponent)
    return np.column_stack([xy, diam])


def _clear_target(catalog: np.ndarray, clear_radius_m: float) -> np.ndarray:
    """Mask of features whose rim/edge (radius D/2) stays outside the target circle."""
    dist = np.hypot(catalog[:, 0], catalog[:, 1])
    return dist - catalog[:, 2] / 2 >= clear_radius_m


# ------------------------------------------------------------------ stamping
def _stamp_radial(
    field: np.ndarray,
    size_m: float,
    x_m: np.ndarray,
    y_m: np.ndarray,
    radius_m: np.ndarray,
    amplitude: np.ndarray,
    profile_rho2: Callable[[np.ndarray], np.ndarray],
    support_r: float,
) -> None:
    """Add ``amplitude_k * profile((r_k / radius_k)^2)`` of every feature k to a texel grid, in place.

    Each feature is evaluated only on the window of texels within
    ``support_r * radius`` of its centre (the profile must be 0 beyond).

    Args:
        field: (m, m) float32 texel grid, south-up, covering the tile.
        size_m: Side of the tile [m].
        x_m, y_m: (k,) feature centres [m].
        radius_m: (k,) feature radii [m].
        amplitude: (k,) multipliers of the profile [m].
        profile_rho2: Profile as a function of (r/R)^2 (float32 in, float32 out).
        support_r: Support of the profile [radii].
    """
    m = field.shape[0]
    texel_m = size_m / m
    cu = (x_m + size_m / 2) / texel_m - 0.5  # fractional texel index of the centres
    cv = (y_m + size_m / 2) / texel_m - 0.5
    half_px = np.ceil(support_r * radius_m / texel_m).astype(np.intp)
    inv_r_px = (texel_m / radius_m).astype(np.float32)  # texels -> radii
    amp = amplitude.astype(np.float32)
    flat = field.reshape(-1)
    batched = half_px <= STAMP_BATCH_MAX_HALF_PX
    for half in np.unique(half_px[batched]):
        idx_all = np.flatnonzero(batched & (half_px == half))
        offsets = np.arange(-half, half + 1)
        per_chunk = max(1, STAMP_BATCH_ELEMENTS // offsets.size**2)
        for start in range(0, idx_all.size, per_chunk):
            idx = idx_all[start:start + per_chunk]
            ix = np.rint(cu[idx]).astype(np.intp)[:, None] + offsets  # (k, w)
            iy = np.rint(cv[idx]).astype(np.intp)[:, None] + offsets
            dx2 = (((ix - cu[idx, None]) * inv_r_px[idx, None]) ** 2).astype(np.float32)
            dy2 = (((iy - cv[idx, None]) * inv_r_px[idx, None]) ** 2).astype(np.float32)
            val = profile_rho2(dy2[:, :, None] + dx2[:, None, :]) * amp[idx, None, None]  # (k, w, w)
            inside = ((iy >= 0) & (iy < m))[:, :, None] & ((ix >= 0) & (ix < m))[:, None, :]
            lin = iy[:, :, None] * m + ix[:, None, :]
            # add.at: several features may share a texel in one batch.
            np.add.at(flat, lin[inside], val[inside])
    for k in np.flatnonzero(~batched):
        ic, jc, half = int(round(cv[k])), int(round(cu[k])), int(half_px[k])
        i0, i1 = max(ic - half, 0), min(ic + half + 1, m)
        j0, j1 = max(jc - half, 0), min(jc + half + 1, m)
        if i0 >= i1 or j0 >= j1:
            continue
        dx2 = (((np.arange(j0, j1) - cu[k]) * inv_r_px[k]) ** 2).astype(np.float32)
        dy2 = (((np.arange(i0, i1) - cv[k]) * inv_r_px[k]) ** 2).astype(np.float32)
        field[i0:i1, j0:j1] += profile_rho2(dy2[:, None] + dx2[None, :]) * amp[k]


# ---------------------------------------------------------------- resampling
def _tent_matrix(src_x: np.ndarray, dst_x: np.ndarray, half_width: float) -> scipy.sparse.csr_matrix:
    """(len(dst), len(src)) area-average operator with tent weights of the given half-width [same units].

    Rows are normalised to 1 (near the edges the tent is cut and renormalised).
    """
    src_dx = src_x[1] - src_x[0]
    reach = int(math.ceil(half_width / src_dx)) + 1
    first = np.searchsorted(src_x, dst_x - half_width)  # leftmost candidate per destination
    cols = first[:, None] + np.arange(reach * 2 + 1)[None, :]
    cols = np.clip(cols, 0, src_x.size - 1)
    w = np.maximum(0.0, 1.0 - np.abs(src_x[cols] - dst_x[:, None]) / half_width)
    # Clipped duplicates at the edges would double-count: keep only the first.
    dup = np.zeros_like(w, dtype=bool)
    dup[:, 1:] = cols[:, 1:] == cols[:, :-1]
    w[dup] = 0.0
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(dst_x.size), cols.shape[1])
    return scipy.sparse.csr_matrix((w.ravel().astype(np.float32), (rows, cols.ravel())),
                                   shape=(dst_x.size, src_x.size))


def _interp_matrix(src_x: np.ndarray, dst_x: np.ndarray) -> scipy.sparse.csr_matrix:
    """(len(dst), len(src)) Keys cubic-convolution interpolation on a uniform source grid, edge-clamped.

    Keys with a = -0.5 is C1 and exact for quadratics (smooth bowls stay smooth).
    """
    n = src_x.size
    u = np.clip((dst_x - src_x[0]) / (src_x[1] - src_x[0]), 0.0, n - 1)
    base = np.minimum(np.floor(u).astype(np.intp), n - 2)
    taps = np.arange(-1, 3)
    s = np.abs((u - base)[:, None] - taps[None, :])
    a = KEYS_CUBIC_A
    w = np.where(s <= 1, (a + 2) * s**3 - (a + 3) * s**2 + 1, a * s**3 - 5 * a * s**2 + 8 * a * s - 4 * a)
    w = np.where(s < 2, w, 0.0)
    cols = np.clip(base[:, None] + taps[None, :], 0, n - 1)  # clamped duplicates are summed by COO -> CSR
    rows = np.repeat(np.arange(dst_x.size), taps.size)
    return scipy.sparse.csr_matrix((w.ravel().astype(np.float32), (rows, cols.ravel())), shape=(dst_x.size, n))


def _separable(op: scipy.sparse.csr_matrix, grid: np.ndarray) -> np.ndarray:
    """Apply the same 1-D operator along both axes of a square grid: op @ grid @ op.T."""
    return np.ascontiguousarray((op @ (op @ grid).T).T)


def _gaussian_lowpass(field: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian low-pass of a square cell-centred grid, run on a decimated copy for speed.

    Area-average decimation, Gaussian blur, then Keys cubic upsampling (exact
    for quadratics, so smooth crater bowls leave no periodic ripple).

    Args:
        field: (m, m) float32 grid.
        sigma_px: Gaussian sigma [texels of ``field``].

    Returns:
        (m, m) float32 low-pass, same cell-centred alignment.
    """
    m = field.shape[0]
    work = max(8, min(m, int(round(m * LOWPASS_WORK_SIGMA_PX / sigma_px))))
    small = cv2.resize(field, (work, work), interpolation=cv2.INTER_AREA)  # cell centres stay aligned
    small = cv2.GaussianBlur(small, (0, 0), sigma_px * work / m, borderType=cv2.BORDER_REFLECT)
    if work == m:
        return small
    up = _interp_matrix(_texel_centres_m(1.0, work), _texel_centres_m(1.0, m))
    return _separable(up, small)


def _texel_centres_m(size_m: float, m: int) -> np.ndarray:
    return (np.arange(m) + 0.5) * (size_m / m) - size_m / 2


def _vertices_m(size_m: float, n: int) -> np.ndarray:
    return np.linspace(-size_m / 2, size_m / 2, n)


# ------------------------------------------------------------------- shading
def _sun_vector(sun_elevation_deg: float, sun_azimuth_deg: float) -> tuple[float, float, float]:
    """Unit vector toward the sun in L (x east, y north, z up)."""
    el, az = math.radians(sun_elevation_deg), math.radians(sun_azimuth_deg)
    return math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)


def _relative_shading(residual_m: np.ndarray, texel_m: float, sun: tuple[float, float, float],
                      photometric: str) -> np.ndarray:
    """Brightness of each texel relative to flat ground, from the slopes of the residual (nadir view).

    Args:
        residual_m: (m, m) float32 fine-scale heights [m], south-up.
        texel_m: Texel size [m].
        sun: Unit vector toward the sun in L.
        photometric: "lommel_seeliger" or "lambert".

    Returns:
        (m, m) float32 >= 0; 1 on flat ground, 0 in attached shadow.
    """
    sx, sy, sz = sun
    # Central differences along x (columns) and y (rows): kernel [-1, 0, 1] / (2 texel).
    dz_dx = cv2.Sobel(residual_m, cv2.CV_32F, 1, 0, ksize=1, scale=1.0 / (2 * texel_m))
    dz_dy = cv2.Sobel(residual_m, cv2.CV_32F, 0, 1, ksize=1, scale=1.0 / (2 * texel_m))
    norm = None
    if photometric == "lambert":
        norm = cv2.magnitude(dz_dx, dz_dy)
        cv2.sqrt(1.0 + norm * norm, norm)
    # cos(incidence) * |(-zx, -zy, 1)| = sz - zx*sx - zy*sy (in place, large arrays).
    cos_i = dz_dx
    cos_i *= np.float32(-sx)
    dz_dy *= np.float32(-sy)
    cos_i += dz_dy
    cos_i += np.float32(sz)
    np.maximum(cos_i, 0.0, out=cos_i)
    if norm is None:
        # Lommel-Seeliger mu0 / (mu0 + mu), nadir view: the normal's length cancels.
        np.add(cos_i, 1.0, out=dz_dy)
        cos_i /= dz_dy
        cos_i *= np.float32((sz + 1.0) / sz)
    else:
        cos_i /= norm
        cos_i *= np.float32(1.0 / sz)
    return cos_i


def _lit_fraction(height_m: np.ndarray, texel_m: float, sun: tuple[float, float, float]) -> np.ndarray:
    """Fraction of each texel not in a cast shadow (0..1, soft at shadow edges).

    The grid is rotated so its rows run away from the sun; a texel is in
    shadow when a texel nearer the sun rises above the sun ray through it,
    found with a running maximum along each row.

    Args:
        height_m: (m, m) float32 heights [m], south-up.
        texel_m: Texel size [m].
        sun: Unit vector toward the sun in L (elevation < 90 deg).

    Returns:
        (m, m) float32 in [0, 1].
    """
    sx, sy, sz = sun
    horiz = math.hypot(sx, sy)
    m = height_m.shape[0]
    ax, ay = -sx / horiz, -sy / horiz  # rotated +column axis = away from the sun, in (x, y) = (col, row)
    side = int(math.ceil(m * (abs(ax) + abs(ay)))) + 2
    c_src, c_dst = (m - 1) / 2, (side - 1) / 2
    # Rotated pixel (u, v) -> source pixel c_src + (u - c_dst) * a + (v - c_dst) * a_perp, a_perp = (-ay, ax).
    to_src = np.array([[ax, -ay, c_src - (ax - ay) * c_dst],
                       [ay, ax, c_src - (ay + ax) * c_dst]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    low = float(height_m.min()) - 1.0e6  # outside the tile: never casts a shadow
    # g = h + (distance from the sun side) * tan(el): a texel is lit iff no texel before it in its row has a larger g.
    # Rows are independent, so the rotated grid is warped and swept in strips of
    # rows: neither g (up to 2 m^2 texels) nor its running maximum is ever held
    # whole (they were the terrain generator's memory peak).
    ramp = np.arange(side, dtype=np.float32)[None, :] * np.float32(texel_m * sz / horiz)
    shadow = np.zeros((side, side), np.uint8)
    for r0 in range(0, side, SHADOW_STRIP_ROWS):
        rows = min(SHADOW_STRIP_ROWS, side - r0)
        to_src_strip = to_src.copy()
        to_src_strip[:, 2] += to_src[:, 1] * r0  # strip row v' is rotated row v' + r0
        strip = cv2.warpAffine(height_m, to_src_strip, (side, rows), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=low)
        strip += ramp
        highest_before = np.maximum.accumulate(strip, axis=1)
        highest_before -= np.float32(SHADOW_FLAT_EPS_M)
        np.less(strip[:, 1:], highest_before[:, :-1], out=shadow[r0:r0 + rows, 1:].view(bool))
    del strip, highest_before
    shadow *= np.uint8(UINT8_MAX)  # 0/255 so the warp back gives soft edges
    back = cv2.warpAffine(shadow, cv2.invertAffineTransform(to_src), (m, m), flags=flags,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    lit = back.astype(np.float32)
    lit *= np.float32(-1.0 / UINT8_MAX)
    lit += 1.0
    return lit


# ------------------------------------------------------------------------ DEM
def load_dem(path: str | pathlib.Path, spacing_m: float, z_scale_m: float = 1.0) -> np.ndarray:
    """Load a user DEM as stored (row 0 = north edge), in metres.

    Supported: ``.npy`` (2-D real numeric array) and 16-bit single-channel
    ``.png``. Stored values are multiplied by ``z_scale_m`` for both formats
    (for .npy in metres leave it at 1).

    Args:
        path: File path.
        spacing_m: Post spacing [m]; validated here (> 0, finite).
        z_scale_m: Metres per stored unit (> 0).

    Returns:
        (rows, cols) float64 heights [m], north-up.

    Raises:
        ValueError: Missing or unreadable file, unsupported type or dtype,
            not 2-D, non-finite values, or smaller than MIN_DEM_PX per side.
    """
    p = pathlib.Path(path)
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"dem_spacing_m={spacing_m} for dem_path='{p}' must be a finite number > 0 [m]")
    if not (math.isfinite(z_scale_m) and z_scale_m > 0):
        raise ValueError(f"dem_z_scale_m={z_scale_m} for dem_path='{p}' must be a finite number > 0 [m/unit]")
    if not p.is_file():
        raise ValueError(f"dem_path='{p}': file not found; give an existing .npy or 16-bit .png file")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            data = np.load(p, allow_pickle=False)
        except Exception as exc:  # numpy raises several types for corrupt files
            raise ValueError(f"dem_path='{p}': cannot be read as a .npy array ({type(exc).__name__}: {exc})") from None
        if not isinstance(data, np.ndarray) or data.dtype.kind not in "fiu":
            kind = data.dtype if isinstance(data, np.ndarray) else type(data).__name__
            raise ValueError(f"dem_path='{p}': dtype {kind} is not supported; expected a real float or integer array")
    elif suffix == ".png":
        raw = np.fromfile(p, dtype=np.uint8)
        data = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
        if data is None:
            raise ValueError(f"dem_path='{p}': cannot be decoded as a PNG image (corrupt or not a PNG)")
        if data.dtype != np.uint16:
            raise ValueError(
                f"dem_path='{p}': PNG has dtype {data.dtype} ({8 * data.dtype.itemsize}-bit); expected a 16-bit "
                f"single-channel PNG (8 bits give too few height levels)"
            )
    else:
        raise ValueError(f"dem_path='{p}': unsupported file type '{p.suffix}'; expected .npy or .png")
    if data.ndim != 2:
        raise ValueError(
            f"dem_path='{p}': array has shape {data.shape}; expected a 2-D (rows, cols) height grid "
            f"(single channel)"
        )
    if min(data.shape) < MIN_DEM_PX:
        raise ValueError(f"dem_path='{p}': shape {data.shape} is too small; need at least {MIN_DEM_PX} px per side")
    heights = data.astype(np.float64) * z_scale_m
    bad = int(np.count_nonzero(~np.isfinite(heights)))
    if bad:
        raise ValueError(f"dem_path='{p}': {bad} non-finite values (NaN/inf); fill the voids first")
    return heights


GEOTIFF_SUFFIXES = (".tif", ".tiff")
# How to bring a raster to what landbench flies: metres, square pixels, north up. A local polar
# stereographic on the Moon's sphere (IAU 2015 radius) suits a south-pole site.
REPROJECT_HINT = ("reproject it to a metric grid with square pixels, e.g. gdalwarp -t_srs "
                  "'+proj=stere +lat_0=-90 +lon_0=0 +k=1 +x_0=0 +y_0=0 +R=1737400 +units=m +no_defs' "
                  "-tr 5 5 -r bilinear in.tif out.tif")


def is_geotiff(path: str | pathlib.Path) -> bool:
    """Whether a DEM path names a GeoTIFF (by its suffix)."""
    return pathlib.Path(path).suffix.lower() in GEOTIFF_SUFFIXES


def load_geotiff(path: str | pathlib.Path, target_xy: tuple[float, float] | None, tile_m: float | None,
                 z_scale_m: float = 1.0) -> tuple[np.ndarray, float]:
    """Read the square of a projected GeoTIFF DEM around a target (needs rasterio, the 'geo' extra).

    The spacing, nodata and extent come from the file. Refused, with how to fix it: a raster
    without a CRS, in degrees (geographic), in non-metre units, rotated or with non-square pixels.

    Args:
        path: The GeoTIFF (band 1 = heights).
        target_xy: The landing target in the file's coordinates [m]; None: the raster's centre.
            Snapped to the nearest post, which becomes the tile's centre.
        tile_m: Side of the square to crop [m] (rounded to an even number of spacings);
            None: the largest square around the target that fits.
        z_scale_m: Metres per stored unit.

    Returns:
        ((n, n) float64 heights [m], north-up (row 0 = north edge), n odd; the post spacing [m]).

    Raises:
        ValueError: One line naming the file, what is wrong and how to fix it.
    """
    p = pathlib.Path(path)
    if not p.is_file():
        raise ValueError(f"dem_path='{p}': file not found; give an existing GeoTIFF")
    try:
        import rasterio
        from rasterio.windows import Window
    except ImportError:
        raise ValueError(f"dem_path='{p}': reading GeoTIFF needs rasterio; install the geo extra "
                         "(pip install 'landbench[geo]'), or convert the DEM to .npy") from None
    try:
        ds = rasterio.open(p)
    except rasterio.errors.RasterioIOError as exc:
        raise ValueError(f"dem_path='{p}': cannot be read as a GeoTIFF ({str(exc).splitlines()[0]})") from None
    with ds:
        crs, t = ds.crs, ds.transform
        if crs is None:
            raise ValueError(f"dem_path='{p}': the raster has no coordinate reference system; {REPROJECT_HINT}")
        if crs.is_geographic:
            raise ValueError(f"dem_path='{p}': the raster is in degrees ({crs.to_string()}), not metres; "
                             f"{REPROJECT_HINT}")
        units, factor = crs.linear_units_factor
        if not math.isclose(factor, 1.0, rel_tol=1e-9):
            raise ValueError(f"dem_path='{p}': the raster's units are {units}, not metres; {REPROJECT_HINT}")
        if t.b != 0.0 or t.d != 0.0 or t.a <= 0.0 or t.e >= 0.0:
            raise ValueError(f"dem_path='{p}': the raster is rotated or not north-up (transform {tuple(t)[:6]}); "
                             f"{REPROJECT_HINT}")
        if not math.isclose(t.a, -t.e, rel_tol=1e-6):
            raise ValueError(f"dem_path='{p}': its pixels are not square ({t.a} m x {-t.e} m); {REPROJECT_HINT}")
        spacing = float(t.a)
        rows, cols = ds.height, ds.width
        if target_xy is None:
            r_c, c_c = (rows - 1) // 2, (cols - 1) // 2
        else:
            # Pixel (row, col) has its centre at x = c + (col + 0.5) a, y = f + (row + 0.5) e.
            c_c = int(round((target_xy[0] - t.c) / t.a - 0.5))
            r_c = int(round((target_xy[1] - t.f) / t.e - 0.5))
            if not (0 <= r_c < rows and 0 <= c_c < cols):
                x0, y1 = t.c, t.f
                raise ValueError(
                    f"dem_target_xy={tuple(target_xy)} is outside the raster '{p.name}' (x {x0:.1f} to "
                    f"{x0 + cols * t.a:.1f}, y {y1 + rows * t.e:.1f} to {y1:.1f} m, in its {crs.to_string()})"
                )
        fits = min(r_c, c_c, rows - 1 - r_c, cols - 1 - c_c)
        half = fits if tile_m is None else int(round(tile_m / spacing / 2.0))
        if half > fits:
            raise ValueError(
                f"dem_tile_m={tile_m} around the target does not fit in '{p.name}' "
                f"(at most {2 * fits * spacing:g} m there); choose a smaller tile or another target"
            )
        if 2 * half + 1 < MIN_DEM_PX:
            field = f"dem_tile_m={tile_m}" if tile_m is not None else f"dem_path='{p}'"
            raise ValueError(f"{field}: the tile around the target is {2 * half + 1} px; need at least {MIN_DEM_PX} "
                             "px per side" + ("; give a larger dem_tile_m" if tile_m is not None else ""))
        band = ds.read(1, window=Window(c_c - half, r_c - half, 2 * half + 1, 2 * half + 1), masked=True)
    heights = np.ma.getdata(band).astype(np.float64) * z_scale_m
    # A post that is both nodata and NaN (NaN declared as nodata) counts once.
    bad = int(np.count_nonzero(np.ma.getmaskarray(band) | ~np.isfinite(heights)))
    if bad:
        raise ValueError(f"dem_path='{p}': {bad} nodata or non-finite posts in the tile around the target; "
                         "fill the voids first (e.g. gdal_fillnodata.py) or choose another target")
    return heights, spacing


# ---------------------------------------------------------------- generation
def _catalogs(cfg: TerrainConfig, rng_craters: np.random.Generator, rng_boulders: np.random.Generator,
              size_m: float, crater_d_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The crater catalog, its freshness and the boulder catalog (each from its own stream), target cleared.

    Returns:
        (craters (k, 3) [x_m, y_m, diameter_m], freshness (k,), boulders (j, 3) [x_m, y_m, diameter_m]).
    """
    if crater_d_max > cfg.crater_min_diameter_m:
        craters = _power_law_catalog(rng_craters, cfg.crater_density_per_km2, size_m, cfg.crater_min_diameter_m,
                                     crater_d_max, cfg.crater_sfd_exponent)
        freshness = rng_craters.uniform(cfg.crater_freshness_min, 1.0, size=len(craters))
        keep = _clear_target(craters, cfg.target_clear_radius_m)
        craters, freshness = craters[keep], freshness[keep]
    else:
        craters, freshness = np.zeros((0, 3)), np.zeros(0)
    boulders = _power_law_catalog(rng_boulders, cfg.boulder_density_per_km2, size_m, cfg.boulder_min_diameter_m,
                                  cfg.boulder_max_diameter_m, cfg.boulder_sfd_exponent)
    boulders = boulders[_clear_target(boulders, cfg.target_clear_radius_m)]
    return craters, freshness, boulders


def _fine_dem(cfg: TerrainConfig, rng_craters: np.random.Generator, rng_rough: np.random.Generator,
              rng_boulders: np.random.Generator) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray, np.ndarray]:
    """The fine DEM at texture resolution (before the datum shift) and the catalogs stamped into it.

    Returns:
        (fine (m, m) float32 heights [m] south-up, size_m, texel_m, craters (k, 3), freshness (k,),
        boulders (j, 3)).
    """
    m = cfg.texture_px

    if cfg.kind == "procedural":
        size_m = cfg.size_m
        texel_m = size_m / m
        fine = fbm_surface(m, texel_m, cfg.roughness_rms_m, cfg.roughness_hurst, rng_rough)
        crater_d_max = cfg.crater_max_diameter_m
    else:
        assert cfg.dem_path is not None and cfg.dem_spacing_m is not None  # guaranteed by the validator
        if is_geotiff(cfg.dem_path):  # already the square around the target
            dem = load_geotiff(cfg.dem_path, cfg.dem_target_xy, cfg.dem_tile_m, cfg.dem_z_scale_m)[0]
        else:
            dem = load_dem(cfg.dem_path, cfg.dem_spacing_m, cfg.dem_z_scale_m)
        side = min(dem.shape)
        r0, c0 = (dem.shape[0] - side) // 2, (dem.shape[1] - side) // 2
        dem = np.flipud(dem[r0:r0 + side, c0:c0 + side]).astype(np.float32)  # north-up -> south-up
        size_m = cfg.dem_spacing_m * (side - 1)
        texel_m = size_m / m
        texels = _texel_centres_m(size_m, m)
        dem_x = _vertices_m(size_m, side)
        if texel_m < cfg.dem_spacing_m:
            fine = _separable(_interp_matrix(dem_x, texels), dem)
        else:
            fine = _separable(_tent_matrix(dem_x, texels, texel_m), dem)
        fine += fbm_surface(m, texel_m, cfg.roughness_rms_m, cfg.roughness_hurst, rng_rough,
                            max_wavelength_m=DEM_DETAIL_MAX_WAVELENGTH_PX * cfg.dem_spacing_m)
        crater_d_max = min(cfg.crater_max_diameter_m, DEM_UNRESOLVED_CRATER_PX * cfg.dem_spacing_m)

    craters, freshness, boulders = _catalogs(cfg, rng_craters, rng_boulders, size_m, crater_d_max)
    d, hr = cfg.crater_depth_ratio, cfg.crater_rim_height_ratio
    _stamp_radial(fine, size_m, craters[:, 0], craters[:, 1], craters[:, 2] / 2, craters[:, 2] * freshness,
                  lambda rho2: _crater_profile_rho2(rho2, d, hr), CRATER_SUPPORT_R)

    # Boulders.
    _stamp_radial(fine, size_m, boulders[:, 0], boulders[:, 1], boulders[:, 2] / 2, boulders[:, 2],
                  _boulder_rho2, BOULDER_SUPPORT_R)

    return fine, size_m, texel_m, craters, freshness, boulders


def _albedo_rel(cfg: TerrainConfig, m: int, texel_m: float, size_m: float, craters: np.ndarray,
                freshness: np.ndarray, rng_albedo: np.random.Generator) -> np.ndarray:
    """Albedo / albedo_mean at texture resolution, (m, m) float32 south-up (a property of the surface, no sun)."""
    # Albedo / albedo_mean: low-contrast fBm, brighter in and around the freshest craters.
    albedo_rel = fbm_surface(m, texel_m, cfg.albedo_contrast, cfg.albedo_hurst, rng_albedo)
    albedo_rel += 1.0
    span = 1.0 - cfg.crater_freshness_min
    fresh_level = (freshness - cfg.crater_freshness_min) / span if span > 0 else np.ones_like(freshness)
    halo_amp = cfg.crater_fresh_albedo_gain * np.clip(
        (fresh_level - CRATER_FRESH_THRESHOLD) / (1.0 - CRATER_FRESH_THRESHOLD), 0.0, 1.0
    )
    fresh = halo_amp > 0
    _stamp_radial(albedo_rel, size_m, craters[fresh, 0], craters[fresh, 1], craters[fresh, 2] / 2,
                  halo_amp[fresh], _halo_rho2, CRATER_SUPPORT_R)
    np.maximum(albedo_rel, ALBEDO_REL_FLOOR, out=albedo_rel)

    return albedo_rel


def generate_terrain(
    cfg: TerrainConfig, rng: np.random.Generator, sun_elevation_deg: float, sun_azimuth_deg: float
) -> Terrain:
    """Build the terrain tile described by ``cfg``.

    Args:
        cfg: Terrain configuration.
        rng: The only random source. Independent child streams are spawned
            for craters, roughness, boulders and albedo, so changing one
            part's parameters does not reshuffle the others.
        sun_elevation_deg: Sun elevation for the baked shading, in (0, 90] [deg].
        sun_azimuth_deg: Sun azimuth from north, clockwise toward east [deg].

    Returns:
        The terrain. For kind="dem" the tile side is dem_spacing_m * (n - 1)
        with n the side of the DEM's central square crop, and the DEM is
        centred on the origin.
    """
    if not (math.isfinite(sun_elevation_deg) and 0.0 < sun_elevation_deg <= 90.0):
        raise ValueError(f"sun_elevation_deg={sun_elevation_deg} must be in (0, 90] [deg]")
    if not math.isfinite(sun_azimuth_deg):
        raise ValueError(f"sun_azimuth_deg={sun_azimuth_deg} must be finite [deg]")
    rng_craters, rng_rough, rng_boulders, rng_albedo, rng_patch = rng.spawn(5)
    sun = _sun_vector(sun_elevation_deg, sun_azimuth_deg)
    m = cfg.texture_px
    fine, size_m, texel_m, craters, freshness, boulders = _fine_dem(cfg, rng_craters, rng_rough, rng_boulders)

    # Geometry: tent-weighted area average at the vertices, origin shifted to 0.
    n = cfg.geometry_px
    verts, texels = _vertices_m(size_m, n), _texel_centres_m(size_m, m)
    spacing_m = size_m / (n - 1)
    height = _separable(_tent_matrix(texels, verts, spacing_m), fine)
    datum_m = height[(n - 1) // 2, (n - 1) // 2]
    height -= datum_m
    fine -= datum_m
    # What the renderer does not shade: with relief_shading="renderer" the fine DEM minus a smooth
    # low-pass at the geometry scale (smooth, so the texture shows no trace of the vertex grid);
    # with "texture" the whole fine DEM (the terrain is drawn unlit).
    if cfg.relief_shading == "texture":
        residual = fine  # read only from here on: no 67 MB copy at 4096^2
    else:
        residual = _gaussian_lowpass(fine, RESIDUAL_LOWPASS_SIGMA_SPACINGS * spacing_m / texel_m)
        np.subtract(fine, residual, out=residual)
    # Each (m, m) array is freed as soon as it is spent: at m = 4096 each is
    # 67 MB, and this function sets a campaign worker's peak memory.
    caster = None
    if cfg.bake_cast_shadows != "none" and sun_elevation_deg < 90.0:
        caster = residual if cfg.bake_cast_shadows == "residual" else fine
    del fine

    # Baked shading of the residual (the whole relief with relief_shading="texture").
    shade = _relative_shading(residual, texel_m, sun, cfg.photometric_function)
    np.minimum(shade, SHADE_MAX, out=shade)
    del residual
    if caster is not None:
        shade *= _lit_fraction(caster, texel_m, sun)
    del caster
    shade *= np.float32(1.0 - SHADOW_FLOOR)
    shade += np.float32(SHADOW_FLOOR)

    albedo_rel = _albedo_rel(cfg, m, texel_m, size_m, craters, freshness, rng_albedo)

    dn = albedo_rel
    dn *= shade
    dn *= np.float32(cfg.texture_mean_dn)
    np.clip(dn, 0.0, UINT8_MAX, out=dn)
    texture = np.rint(dn, out=dn).astype(np.uint8)
    del dn, albedo_rel, shade
    shaded = cfg.relief_shading == "texture"
    terrain = Terrain(height_m=height.astype(np.float32, copy=False), size_m=float(size_m), albedo=texture,
                      craters=craters.astype(np.float64), boulders=boulders.astype(np.float64), relief_shaded=shaded)
    if cfg.patch_size_m <= 0:
        return terrain
    patch = _make_patch(terrain, cfg, sun, rng_patch)
    return dataclasses.replace(terrain, patch=patch)


@dataclass(frozen=True, eq=False)
class Surface:
    """The physical surface behind a terrain, at texture resolution, with no sun baked in.

    Attributes:
        height_m: (m, m) float32 fine DEM [m] on the texel grid (south-up, texel centres), in the same
            datum as :class:`Terrain` (its geometry is the tent average of this).
        albedo_rel: (m, m) float32 albedo / albedo_mean [-], on the same grid.
        size_m: Side of the square [m], centred on the origin.
        craters, boulders: The catalogs stamped, as in :class:`Terrain`.
    """

    height_m: np.ndarray
    albedo_rel: np.ndarray
    size_m: float
    craters: np.ndarray
    boulders: np.ndarray

    @property
    def texel_m(self) -> float:
        """Texel size [m]."""
        return self.size_m / self.height_m.shape[0]


def generate_surface(cfg: TerrainConfig, rng: np.random.Generator) -> Surface:
    """Regenerate the surface of :func:`generate_terrain` (same ``cfg``, a generator in the same state).

    The fine DEM and the albedo are drawn exactly as :func:`generate_terrain` draws them (the same child
    streams, the same code), so a product made from them under another sun (an orbital map) shows the
    same ground the camera flies over, without the renderer's texture.

    Args:
        cfg: Terrain configuration.
        rng: A generator in the state the terrain was generated from.

    Returns:
        The surface (about 8 bytes per texel).
    """
    rng_craters, rng_rough, rng_boulders, rng_albedo, _ = rng.spawn(5)
    fine, size_m, texel_m, craters, freshness, boulders = _fine_dem(cfg, rng_craters, rng_rough, rng_boulders)
    n, m = cfg.geometry_px, cfg.texture_px
    verts, texels = _vertices_m(size_m, n), _texel_centres_m(size_m, m)
    tent = _tent_matrix(texels, verts[[(n - 1) // 2]], size_m / (n - 1))
    datum_m = float((tent @ fine @ tent.T)[0, 0])
    fine -= np.float32(datum_m)
    albedo_rel = _albedo_rel(cfg, m, texel_m, size_m, craters, freshness, rng_albedo)
    return Surface(height_m=fine, albedo_rel=albedo_rel, size_m=float(size_m),
                   craters=craters.astype(np.float64), boulders=boulders.astype(np.float64))


def _make_patch(terrain: Terrain, cfg: TerrainConfig, sun: tuple[float, float, float],
                rng: np.random.Generator) -> TerrainPatch | None:
    """Landing-site patch: the coarse texture resampled finer, times baked sub-texel shading.

    The detail is fBm roughness with wavelengths below two coarse texels
    (what the coarse texture cannot carry), shaded under the sun, and
    feathered to nothing at the patch edge so the seam does not show.
    """
    spacing = terrain.spacing_m
    n = terrain.height_m.shape[0]
    half_cells = min(max(1, int(round(cfg.patch_size_m / 2 / spacing))), (n - 1) // 2 - 1)
    if half_cells < 1:
        return None
    half_m = half_cells * spacing
    verts = np.linspace(-half_m, half_m, 4 * half_cells + 1)
    X, Y = np.meshgrid(verts, verts)
    heights = terrain.surface_height(X, Y).astype(np.float32)

    p = cfg.patch_texture_px
    patch_texel_m = 2 * half_m / p
    coarse_texel_m = terrain.size_m / terrain.albedo.shape[0]
    centres = _texel_centres_m(2 * half_m, p)
    # Coarse-texture coordinates (texel index, centre convention) of the patch texel centres.
    idx = ((centres + terrain.size_m / 2) / coarse_texel_m - 0.5).astype(np.float32)
    # Only the texels under the patch (plus the cubic kernel's reach) are
    # converted to float: the whole texture would be a 67 MB copy at 4096^2.
    m = terrain.albedo.shape[0]
    lo = max(0, int(np.floor(idx[0])) - 2)
    hi = min(m, int(np.ceil(idx[-1])) + 3)
    idx -= np.float32(lo)  # exact: lo is an integer within a factor 2 of idx (or 0)
    map_x, map_y = np.meshgrid(idx, idx)
    coarse = terrain.albedo[lo:hi, lo:hi].astype(np.float32)
    base = cv2.remap(coarse, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    del coarse, map_x, map_y

    detail = fbm_surface(p, patch_texel_m, 1.0, cfg.roughness_hurst, rng,
                         max_wavelength_m=PATCH_DETAIL_MAX_WAVELENGTH_TEXELS * coarse_texel_m)
    # The RMS applies to the detail band itself (what the coarse texture lacks).
    detail *= np.float32(cfg.patch_roughness_rms_m / max(float(detail.std()), 1e-12))
    shade = _relative_shading(detail, patch_texel_m, sun, cfg.photometric_function)
    np.minimum(shade, SHADE_MAX, out=shade)
    # Feather: full detail inside, fading to none over the outer band (smoothstep).
    # Smoothstep of the distance to the nearest edge. The step is monotonic, so
    # it is the smaller of the two 1-D steps: no (p, p) float64 temporaries.
    t = np.clip((half_m - np.abs(centres)) / (PATCH_FEATHER_FRAC * half_m), 0.0, 1.0)
    step = (t * t * (3.0 - 2.0 * t)).astype(np.float32)
    weight = np.minimum(step[:, None], step[None, :])
    base *= 1.0 + weight * (shade - 1.0)
    albedo = np.clip(np.rint(base), 0.0, UINT8_MAX).astype(np.uint8)
    return TerrainPatch(height_m=heights, size_m=float(2 * half_m), albedo=albedo)
