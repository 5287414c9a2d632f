"""Orbital map products of the landing region: a shaded orthoimage and a DEM (truth side, pure NumPy/OpenCV).

What an orbiter's camera team would hand the lander: the region imaged from
orbit under *its own* sun (not the descent's), at about 1 m/px, blurred,
noisy and quantised to 8 bits, and a stereo DEM at about 2 m posts with its
own height noise, both georeferenced with an error. The products are computed
from the physical surface (:func:`models.terrain.generate_surface`: the fine
DEM and the albedo the terrain was generated from), never from the renderer's
texture, so the descent camera is not matched against its own image.

Inputs:
    A :class:`models.terrain.Surface`, an :class:`OrbitalMapConfig`, the
    georeferencing error ``shift_xy_m`` (drawn by the caller from its own
    stream) and a ``numpy.random.Generator`` for the image and DEM noise.

Outputs:
    :class:`OrbitalProduct`: the orthoimage (uint8), the DEM (float32), their
    grids in *stated* map coordinates, and nothing else (no truth inside).

Conventions (those of :mod:`models.terrain`):
    * Map frame M: stated coordinates, x east, y north, nominally the landing
      frame L. The georeferencing error ``delta = shift_xy_m`` is the map
      position of a feature minus its true position in L: the map's content at
      stated point ``p`` is the true surface at ``p - delta``.
    * Arrays are south-up (row index increases with +y). Image pixel (i, j)
      covers the square centred on x = -S/2 + (j + 0.5) res,
      y = -S/2 + (i + 0.5) res (cell grid); DEM post (i, j) sits at
      x = -S/2 + j spacing, y = -S/2 + i spacing (vertex grid), S = ``size_m``.
    * Sun azimuth from north clockwise toward east, elevation above the
      horizon [deg].

Photometry: DN = ``image_mean_dn`` * albedo_rel * relative shading, with the
terrain texture's reflectance law and cast shadows of the *full* fine DEM
(the orbital view has no renderer to shade the coarse relief), a shadow floor
for scattered light, then a Gaussian blur standing for the pixel's area plus
the optics' PSF, resampling at the map's pixel centres, Gaussian noise and
rounding to uint8.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from models.terrain import (SHADE_MAX, SHADOW_FLOOR, UINT8_MAX, Surface, _lit_fraction, _relative_shading,
                            _sun_vector)


PIXEL_AREA_SIGMA_PX = 1.0 / math.sqrt(12.0)  # a box pixel's footprint as a Gaussian of equal variance [px]
DEM_LOWPASS_SIGMA_POSTS = 0.5  # a stereo DEM resolves about two posts: Gaussian low-pass of this sigma [posts]


MAP_SIDE_MAX = 4096  # most orthoimage pixels, and DEM posts, per side of the map [-] (768 and 384 by default)


def grid_counts(size_m: float, image_res_m: float, dem_spacing_m: float) -> tuple[int, int]:
    """The map's image pixels and DEM post intervals per side, (n_px, n_posts).

    Raises:
        ValueError: ``size_m`` is not a whole number of both, or either is more than ``MAP_SIDE_MAX`` a side
            (one line naming the field, with values that would do).
    """
    n_px, n_posts = int(round(size_m / image_res_m)), int(round(size_m / dem_spacing_m))
    grids = (("image_res_m", image_res_m, n_px, "image", "pixels"), ("dem_spacing_m", dem_spacing_m, n_posts, "DEM", "posts"))
    for name, step, _, _, unit in grids:
        if size_m / step > MAP_SIDE_MAX:  # 1 mm pixels over 768 m ran out of memory
            raise ValueError(f"onboard_map.{name} = {step:g} makes {size_m / step:.0f} {unit} a side over "
                             f"onboard_map.size_m = {size_m:g}, more than {MAP_SIDE_MAX}; allowed: {name} of at least "
                             f"{size_m / MAP_SIDE_MAX:.4g} m, or a smaller size_m")
    for name, step, n, grid, unit in grids:
        if not math.isclose(n * step, size_m, rel_tol=1e-9):
            n = max(n, 1)
            common = _common_size_m(size_m, image_res_m, dem_spacing_m)
            size_hint = f", or a size_m that is a whole number of both, e.g. {common:g}" if common <= 2 * size_m else ""
            raise ValueError(f"onboard_map.size_m = {size_m:g} is not a whole number of {grid} {unit} (onboard_map."
                             f"{name} = {step:g} m); allowed: {name} that divides it (e.g. {size_m / n:.6g} = "
                             f"{size_m:g} / {n}){size_hint}")
    return n_px, n_posts


def _common_size_m(size_m: float, image_res_m: float, dem_spacing_m: float) -> float:
    """The nearest size at or above ``size_m`` that is a whole number of both pixels and posts [m] (for messages;
    the suggestion was the posts' multiple alone, which the pixels could refuse again)."""
    from fractions import Fraction

    a = Fraction(image_res_m).limit_denominator(10**6)
    b = Fraction(dem_spacing_m).limit_denominator(10**6)
    step = Fraction(math.lcm(a.numerator * b.denominator, b.numerator * a.denominator), a.denominator * b.denominator)
    return float(math.ceil(Fraction(size_m) / step) * step)


class OrbitalMapConfig(BaseModel):
    """The onboard map product: orbital sun, image and DEM resolution and noise, georeferencing error."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    sun_elevation_deg: float = Field(
        50.0, gt=0.0, lt=90.0, description="sun elevation when the orbital image was taken [deg]"
    )
    sun_azimuth_deg: float = Field(
        200.0, ge=0.0, lt=360.0, description="sun azimuth of the orbital image, from north clockwise toward east [deg]"
    )
    size_m: float = Field(
        768.0, gt=0.0, description="side of the square map centred on the nominal target [m] (within the terrain)"
    )
    image_res_m: float = Field(1.0, gt=0.0, le=10.0, description="orthoimage pixel size [m]")
    image_psf_sigma_px: float = Field(
        0.5, ge=0.0, le=5.0, description="orbital camera's optical blur, Gaussian sigma in map pixels [px]"
    )
    image_mean_dn: float = Field(110.0, gt=0.0, lt=255.0, description="DN of flat lit ground of mean albedo [DN]")
    image_noise_dn: float = Field(2.0, ge=0.0, le=50.0, description="orthoimage noise, 1-sigma per pixel [DN]")
    dem_spacing_m: float = Field(2.0, gt=0.0, le=50.0, description="DEM post spacing [m]")
    dem_noise_m: float = Field(0.2, ge=0.0, le=10.0, description="DEM height noise, 1-sigma per post [m]")
    georef_sigma_m: float = Field(
        2.0, ge=0.0, le=100.0,
        description="georeferencing error of the map, 1-sigma per horizontal axis [m] (drawn per case)",
    )

    @model_validator(mode="after")
    def _whole_pixels_and_posts(self) -> "OrbitalMapConfig":
        grid_counts(self.size_m, self.image_res_m, self.dem_spacing_m)
        return self


@dataclass(frozen=True, eq=False)
class OrbitalProduct:
    """The map product in stated map coordinates (see the module's conventions). Arrays are read-only.

    Attributes:
        image: (N, N) uint8 orthoimage, south-up, cell grid of ``image_res_m``.
        image_res_m: Orthoimage pixel size [m].
        dem_m: (K, K) float32 DEM heights [m], south-up, vertex grid of ``dem_spacing_m``.
        dem_spacing_m: DEM post spacing [m].
        size_m: Side of the map square, centred on the stated origin [m].
    """

    image: np.ndarray
    image_res_m: float
    dem_m: np.ndarray
    dem_spacing_m: float
    size_m: float

    def __post_init__(self) -> None:
        for a in (self.image, self.dem_m):
            a.setflags(write=False)


def orbital_radiance(surface: Surface, sun_elevation_deg: float, sun_azimuth_deg: float, mean_dn: float,
                     photometric: str = "lommel_seeliger") -> np.ndarray:
    """Noise-free nadir radiance of the surface under a sun, at texel resolution.

    Args:
        surface: The physical surface.
        sun_elevation_deg: Sun elevation in (0, 90) [deg].
        sun_azimuth_deg: Sun azimuth [deg].
        mean_dn: DN of flat lit ground of mean albedo.
        photometric: "lommel_seeliger" or "lambert".

    Returns:
        (m, m) float32 DN, south-up, on the surface's texel grid.
    """
    sun = _sun_vector(sun_elevation_deg, sun_azimuth_deg)
    shade = _relative_shading(surface.height_m, surface.texel_m, sun, photometric)
    np.minimum(shade, SHADE_MAX, out=shade)
    shade *= _lit_fraction(surface.height_m, surface.texel_m, sun)
    shade *= np.float32(1.0 - SHADOW_FLOOR)
    shade += np.float32(SHADOW_FLOOR)
    shade *= surface.albedo_rel
    shade *= np.float32(mean_dn)
    return shade


def _sample(field: np.ndarray, texel_m: float, size_field_m: float, x_m: np.ndarray, y_m: np.ndarray,
            sigma_texels: float) -> np.ndarray:
    """Gaussian low-pass of a texel-grid field (cell centres), then bilinear samples at points (x, y) [m]."""
    if sigma_texels > 0.05:
        field = cv2.GaussianBlur(field, (0, 0), sigma_texels, borderType=cv2.BORDER_REFLECT)
    u = ((x_m + size_field_m / 2) / texel_m - 0.5).astype(np.float32)
    v = ((y_m + size_field_m / 2) / texel_m - 0.5).astype(np.float32)
    uu, vv = np.meshgrid(u, v)
    return cv2.remap(field, uu, vv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def render_orbital_map(surface: Surface, cfg: OrbitalMapConfig, shift_xy_m: tuple[float, float],
                       rng: np.random.Generator, photometric: str = "lommel_seeliger") -> OrbitalProduct:
    """Make the orthoimage and DEM of the map, shifted by the georeferencing error.

    Args:
        surface: The physical surface (:func:`models.terrain.generate_surface`).
        cfg: The product's settings.
        shift_xy_m: Georeferencing error delta = map position of a feature minus its true position [m].
        rng: Noise stream of the map (image noise first, then DEM noise).
        photometric: Reflectance law (the terrain's ``photometric_function``).

    Returns:
        The product.

    Raises:
        ValueError: The map does not fit in the terrain, or its size is not a whole number of pixels/posts.
    """
    s = cfg.size_m
    if s > surface.size_m:
        raise ValueError(f"onboard_map.size_m={s} is larger than the terrain ({surface.size_m:g} m); "
                         f"give at most {surface.size_m:g}")
    n_px, n_posts = grid_counts(s, cfg.image_res_m, cfg.dem_spacing_m)  # again: a model_copy skips the validator
    dx, dy = float(shift_xy_m[0]), float(shift_xy_m[1])
    texel = surface.texel_m

    radiance = orbital_radiance(surface, cfg.sun_elevation_deg, cfg.sun_azimuth_deg, cfg.image_mean_dn,
                                photometric)
    centres = -s / 2 + (np.arange(n_px) + 0.5) * cfg.image_res_m
    sigma_px = math.hypot(PIXEL_AREA_SIGMA_PX, cfg.image_psf_sigma_px) * cfg.image_res_m / texel
    # Content at stated p is the truth at p - delta.
    img = _sample(radiance, texel, surface.size_m, centres - dx, centres - dy, sigma_px)
    del radiance
    if cfg.image_noise_dn > 0:
        img += np.float32(cfg.image_noise_dn) * rng.standard_normal(img.shape, dtype=np.float32)
    image = np.clip(np.rint(img), 0.0, UINT8_MAX).astype(np.uint8)

    posts = -s / 2 + np.arange(n_posts + 1) * cfg.dem_spacing_m
    dem = _sample(surface.height_m, texel, surface.size_m, posts - dx, posts - dy,
                  DEM_LOWPASS_SIGMA_POSTS * cfg.dem_spacing_m / texel)
    if cfg.dem_noise_m > 0:
        dem += np.float32(cfg.dem_noise_m) * rng.standard_normal(dem.shape, dtype=np.float32)
    return OrbitalProduct(image=image, image_res_m=float(cfg.image_res_m), dem_m=dem.astype(np.float32),
                          dem_spacing_m=float(cfg.dem_spacing_m), size_m=float(s))
