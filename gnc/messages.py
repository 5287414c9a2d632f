"""Sensor and command messages: the interface of the flight software.

Flight software (``gnc/`` and ``vision/``) sees the world only through these
messages, as a flight computer sees it through its buses. The sensor models in
``models/`` produce them; nothing in here refers to truth.

Conventions:
    * ``t_ns``: time of validity, integer nanoseconds since scenario start.
    * Quaternions are scalar-first ``[w, x, y, z]`` (MuJoCo's convention).
      ``q_LB`` rotates body-frame vectors into the landing frame L.
    * L is the landing frame: origin at the landing target on the surface,
      x east, y north, z up. B is the lander body frame (+z is the thrust axis).
    * C is the camera frame in OpenCV's convention (x right, y down, z along
      the boresight); pixel x is the column and y the row, integer values at
      pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_LEGS = 4  # footpads, order fl, fr, rl, rr


@dataclass(frozen=True, slots=True)
class ImuMessage:
    """Strapdown IMU sample.

    Attributes:
        t_ns: Time of validity [ns].
        f_B: Specific force (non-gravitational acceleration) in B, (3,) [m/s^2].
        omega_B: Angular rate of B relative to L, in B, (3,) [rad/s].
        valid: The IMU's own validity flag (False: the unit reports its data invalid).
    """

    t_ns: int
    f_B: np.ndarray
    omega_B: np.ndarray
    valid: bool = True


@dataclass(frozen=True, slots=True)
class AltimeterMessage:
    """Laser altimeter sample.

    Attributes:
        t_ns: Time of validity [ns].
        range_m: Slant range along the boresight [m]; NaN when invalid.
        valid: False on a dropout or when the surface is beyond maximum range.
        boresight_B: Unit boresight direction in B, (3,) (a calibration constant).
    """

    t_ns: int
    range_m: float
    valid: bool
    boresight_B: np.ndarray


@dataclass(frozen=True, slots=True)
class AttitudeMessage:
    """Star-tracker attitude sample.

    Attributes:
        t_ns: Time of validity [ns].
        q_LB: Measured attitude quaternion, (4,) scalar-first.
        valid: The tracker's own validity flag (False: the unit reports its solution invalid).
    """

    t_ns: int
    q_LB: np.ndarray
    valid: bool = True


@dataclass(frozen=True, slots=True)
class ImageMessage:
    """Camera frame with its calibration.

    Attributes:
        t_ns: Time of exposure [ns].
        image: Grayscale frame, (H, W) uint8.
        K: Pinhole intrinsics, (3, 3) [px].
        R_BC: Camera-to-body rotation (mounting calibration), (3, 3).
    """

    t_ns: int
    image: np.ndarray
    K: np.ndarray
    R_BC: np.ndarray


@dataclass(frozen=True, slots=True)
class ContactMessage:
    """Footpad contact flags.

    Attributes:
        t_ns: Time of validity [ns].
        legs: Contact per footpad, (4,) bool, order fl, fr, rl, rr.
    """

    t_ns: int
    legs: np.ndarray

    def __post_init__(self) -> None:
        legs = np.asarray(self.legs)
        if legs.shape != (N_LEGS,):
            raise ValueError(f"ContactMessage.legs has shape {legs.shape}; allowed: ({N_LEGS},) booleans")


@dataclass(frozen=True, slots=True)
class LidarScanMessage:
    """One flash of the hazard lidar: a range image and the sensor's nominal geometry.

    Attributes:
        t_ns: Time of the flash [ns].
        ranges_m: (N, N) slant ranges along each pixel's ray [m]; NaN: no return.
            Pixel (i, j) looks along :func:`lidar_ray_dirs_S` ``(N, fov_deg)[i, j]`` in the sensor frame S.
        fov_deg: Full field of view, edge to edge [deg].
        R_BS: Sensor-to-body rotation (mounting calibration), (3, 3); S is x right, y down, z boresight.
        r_SB_m: Sensor position in B, (3,) [m].
    """

    t_ns: int
    ranges_m: np.ndarray
    fov_deg: float
    R_BS: np.ndarray
    r_SB_m: np.ndarray


def lidar_ray_dirs_S(pixels: int, fov_deg: float) -> np.ndarray:
    """Unit ray directions of an N x N flash lidar in its frame S, (N, N, 3).

    Pixel (row i, column j) looks along ``normalize([t_j, t_i, 1])``, ``t_k = tan(fov/2) (2 (k + 0.5) / N - 1)``.
    """
    t = np.tan(np.radians(fov_deg) / 2) * (2 * (np.arange(pixels) + 0.5) / pixels - 1)
    tx, ty = np.meshgrid(t, t)
    d = np.stack([tx, ty, np.ones_like(tx)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
