"""Nadir camera model: pinhole intrinsics, mounting and detector noise.

Ports:
    Input: the rendered grayscale irradiance image (H, W) float from the
        MuJoCo off-screen renderer, at the camera rate.
    Output: a uint8 frame with shot and read noise, and K.
    Rate: ``CameraConfig.period_ns``.

The MuJoCo camera sits on the body with its axes equal to the body axes, so
it looks along body -z. In OpenCV's camera frame C (x right, y down, z along
the boresight) that is ``R_BC = diag(1, -1, -1)``: image x is body +x and
image y is body -y.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

# Camera frame C (OpenCV) expressed in the body frame B: columns are x_C, y_C, z_C.
R_BC = np.diag([1.0, -1.0, -1.0])
# MuJoCo's camera frame (x right, y up, looking along -z) to OpenCV's C.
R_MJCAM_C = np.diag([1.0, -1.0, -1.0])

UINT8_MAX = 255.0


class CameraConfig(BaseModel):
    """Nadir camera: resolution, field of view, rate and detector noise."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    width_px: int = Field(256, ge=16, le=4096, description="image width [px]")
    height_px: int = Field(256, ge=16, le=4096, description="image height [px]")
    fovy_deg: float = Field(60.0, gt=1.0, lt=170.0, description="vertical field of view [deg]")
    period_ns: int = Field(100_000_000, gt=0, description="frame period [ns] (default 10 Hz)")
    enabled: bool = Field(True, description="render frames in the loop")
    multisampling: Literal["auto", 0, 4] = Field(
        "auto", description="samples per pixel of the off-screen render (MuJoCo's offsamples): 4 antialiases the "
        "edges of the heightfield's flat-shaded triangles (terrain.relief_shading='renderer'); 0 renders one "
        "sample per pixel in about half the time, for a terrain shaded in its texture (relief_shading='texture', "
        "the default), which has no such edges; 'auto' (default) picks 4 or 0 by the terrain's relief_shading")
    read_noise_dn: float = Field(1.0, ge=0, description="read noise, 1-sigma [DN]")
    gain_e_per_dn: float = Field(
        40.0, gt=0, description="conversion gain [e-/DN]; shot noise is Poisson in electrons"
    )
    shot_noise: bool = Field(True, description="apply Poisson shot noise")
    near_m: float = Field(0.5, gt=0, description="near clipping distance [m]")


def offscreen_samples(cfg: CameraConfig, relief_shaded: bool) -> int:
    """MuJoCo's ``offsamples`` for this camera over a terrain: ``cfg.multisampling``, or when it is "auto",
    0 over a terrain shaded in its texture (``relief_shaded``) and 4 over one the renderer shades."""
    if cfg.multisampling == "auto":
        return 0 if relief_shaded else 4
    return int(cfg.multisampling)


def intrinsics(cfg: CameraConfig) -> np.ndarray:
    """Pinhole matrix K of a centred camera with square pixels.

    MuJoCo's ``fovy`` is the vertical field of view, so
    ``f = (H / 2) / tan(fovy / 2)``; with pixel centres at integers the
    principal point is ``((W - 1) / 2, (H - 1) / 2)``.

    Returns:
        K, (3, 3) [px].
    """
    f_px = 0.5 * cfg.height_px / math.tan(math.radians(cfg.fovy_deg) / 2.0)
    return np.array(
        [[f_px, 0.0, (cfg.width_px - 1) / 2.0], [0.0, f_px, (cfg.height_px - 1) / 2.0], [0.0, 0.0, 1.0]]
    )


def detector_normal(shape: tuple[int, int], cfg: CameraConfig, rng: np.random.Generator) -> np.ndarray | None:
    """The standard normal draws :func:`apply_detector_noise` takes from ``rng`` for a frame of ``shape``
    (None: the configuration adds no noise, and nothing is drawn). Drawn ahead (while the frame is
    rendered) and passed as its ``normal``, they give the same frame."""
    if cfg.shot_noise or cfg.read_noise_dn > 0:
        return rng.standard_normal(shape, dtype=np.float32)
    return None


def apply_detector_noise(signal_dn: np.ndarray, cfg: CameraConfig, rng: np.random.Generator | None,
                         normal: np.ndarray | None = None) -> np.ndarray:
    """Add shot and read noise and quantise to uint8.

    Shot noise is Poisson in electrons, variance ``S / gain`` in DN^2. At the
    signal levels of a lit scene (hundreds to thousands of electrons) the
    Poisson law is Gaussian to well below a DN, so shot and read noise are
    drawn together as one zero-mean Gaussian of variance
    ``S / gain + read^2``: one float32 draw per pixel, several times faster
    than ``rng.poisson``.

    Args:
        signal_dn: Noise-free image, (H, W) in DN [0, 255].
        cfg: Camera configuration (gain and read noise).
        rng: The camera's own random stream (unused when ``normal`` is given).
        normal: The frame's draws, taken ahead from the stream by :func:`detector_normal`.

    Returns:
        Noisy frame, (H, W) uint8.
    """
    noisy = cfg.shot_noise or cfg.read_noise_dn > 0
    if noisy and normal is None:
        normal = detector_normal(signal_dn.shape, cfg, rng)
    if noisy and signal_dn.dtype == np.uint8:
        # A uint8 signal (the renderer's) has 256 levels: each pixel's sigma is looked up, the same
        # float32 values as computed per pixel below (noise_sigma_dn), in a fraction of the time.
        img = cv2.LUT(signal_dn, _sigma_table(cfg.shot_noise, cfg.gain_e_per_dn, cfg.read_noise_dn))
        img *= normal
        img += signal_dn
    else:
        img = signal_dn.astype(np.float32)
        if noisy:
            img += noise_sigma_dn(img, cfg.shot_noise, cfg.gain_e_per_dn, cfg.read_noise_dn) * normal
    np.rint(img, out=img)
    np.clip(img, 0.0, UINT8_MAX, out=img)
    return img.astype(np.uint8)


@functools.lru_cache(maxsize=8)
def _sigma_table(shot_noise: bool, gain_e_per_dn: float, read_noise_dn: float) -> np.ndarray:
    """:func:`noise_sigma_dn` of the 256 levels of a uint8 signal, (1, 256) float32 (read-only)."""
    table = noise_sigma_dn(np.arange(256, dtype=np.float32), shot_noise, gain_e_per_dn, read_noise_dn).reshape(1, 256)
    table.flags.writeable = False
    return table


def noise_sigma_dn(signal_dn: np.ndarray, shot_noise: bool, gain_e_per_dn: float, read_noise_dn: float) -> np.ndarray:
    """The detector noise's 1-sigma of each pixel of a float32 signal, float32 [DN]:
    ``sqrt(max(S, 0) / gain + read^2)`` (the shot noise only when ``shot_noise``; the
    :class:`CameraConfig` fields of the same names)."""
    var = np.zeros_like(signal_dn)
    if shot_noise:
        var += np.maximum(signal_dn, 0.0) * np.float32(1.0 / gain_e_per_dn)
    if read_noise_dn > 0:
        var += np.float32(read_noise_dn**2)
    return np.sqrt(var)
