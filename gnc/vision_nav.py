"""Ground-relative velocity from feature tracks (DIMES-style), for the navigation filter.

Ports:
    Inputs: the tracks of one frame pair (:class:`vision.Tracks`, with
        ``prev_xy``), the attitude at both frames (star tracker, q_LB), the
        camera calibration (K, R_BC, camera position in B), the camera's
        height above the ground at the first frame (from the altimeter) and
        the filter's velocity change over the frame interval (IMU-propagated).
    Output: :class:`VelocityMeasurement`, a velocity in L with its covariance.
    Rate: camera rate (one measurement per frame pair).

Model and assumptions:
    * The tracked features lie on a **locally planar, horizontal ground**
      at height ``h0`` below the camera at the first frame (the altimeter
      range times the boresight's vertical component, as DIMES used its
      radar altitude). Relief under the view becomes scale error.
    * With unit-height rays ``a = d0 / -d0_z`` and ``b = d1 / -d1_z`` (``d``
      the pixel rays rotated into L), a static feature gives
      ``r0 + h0 a = r1 + (h0 + dz) b``, i.e. two linear equations per track
      in the camera displacement ``dr = r1 - r0``::

          dx + b_x dz = h0 (a_x - b_x)
          dy + b_y dz = h0 (a_y - b_y)

      Vertical motion shows in the image only through its divergence, which
      is weak and inherits every scale error (relief under the view) in
      proportion to the descent rate; the altimeter measures it far better.
      So, as DIMES did, vision measures the **horizontal** velocity: ``dz``
      is taken from the filter (its IMU + altimeter vertical displacement
      over the interval, with its uncertainty), and the two horizontal
      unknowns are solved from all tracks by least squares, with iterative
      rejection of tracks whose residual exceeds ``outlier_mad_k`` robust
      sigmas (wrong tracks, moving shadows).
    * ``dr / dt`` is the mean velocity over the interval. With the
      acceleration nearly constant over a frame, the velocity at the second
      frame is ``dr / dt + dv / 2``, with ``dv`` the filter's own
      IMU-propagated velocity change over the interval.
    * The camera's lever arm is removed exactly with both attitudes.
    * Covariance: the least-squares covariance from the residual scatter
      (floored by ``pixel_sigma_px`` projected to the ground) plus the scale
      uncertainty from ``sigma_h0_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from vision.tracks import Tracks

NS_PER_S = 1_000_000_000
UNKNOWNS = 2  # dx, dy (dz comes from the filter)
MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution per median absolute deviation


class VisionNavConfig(BaseModel):
    """Velocity-from-tracks settings."""

    model_config = ConfigDict(extra="forbid")

    min_tracks: int = Field(8, ge=3, description="fewest consistent tracks for a measurement [-]")
    pixel_sigma_px: float = Field(
        0.15, gt=0.0, description="floor on the per-track pixel noise used for the covariance [px]"
    )
    outlier_mad_k: float = Field(4.0, gt=1.0, description="reject tracks beyond this many robust sigmas [-]")
    outlier_iterations: int = Field(3, ge=0, le=20, description="rounds of outlier rejection [-]")
    max_off_nadir_deg: float = Field(
        60.0, gt=0.0, lt=90.0, description="rays further than this from straight down are not used [deg]"
    )
    covariance_inflation: float = Field(
        1.5, ge=1.0, description="factor on the measurement covariance for unmodelled errors (relief, timing) [-]"
    )
    vertical_rate_sigma_mps: float = Field(
        0.1, gt=0.0, description="1-sigma of the filter's vertical velocity, for the dz it lends vision [m/s]"
    )
    cutoff_altitude_m: float = Field(
        30.0, ge=0.0, description="vision is used only above this estimated altitude; below, IMU + altimeter [m]"
    )


@dataclass(frozen=True, slots=True)
class VelocityMeasurement:
    """Ground-relative velocity of the body at ``t_ns``.

    Attributes:
        t_ns: Time of validity (the second frame) [ns].
        v_L: Horizontal velocity in L (east, north), (2,) [m/s].
        R: Covariance, (2, 2) [m^2/s^2].
        n_tracks: Tracks offered.
        n_used: Tracks kept after outlier rejection.
        residual_px: Robust residual scatter of the kept tracks, in pixels.
    """

    t_ns: int
    v_L: np.ndarray
    R: np.ndarray
    n_tracks: int
    n_used: int
    residual_px: float


def velocity_from_tracks(
    tracks: Tracks,
    t0_ns: int,
    t1_ns: int,
    K: np.ndarray,
    R_BC: np.ndarray,
    r_cam_B: np.ndarray,
    q_LB0: np.ndarray,
    q_LB1: np.ndarray,
    h0_m: float,
    sigma_h0_m: float,
    dv_L: np.ndarray,
    dz_m: float,
    sigma_dz_m: float,
    cfg: VisionNavConfig,
) -> VelocityMeasurement | None:
    """Body velocity at the second frame from the tracks of a frame pair.

    Args:
        tracks: Tracks of the second frame; those with a finite ``prev_xy``
            (present in the first frame) are used.
        t0_ns, t1_ns: Times of the two frames [ns], t1 > t0.
        K: Intrinsics (3, 3) [px].
        R_BC: Camera-to-body rotation (3, 3).
        r_cam_B: Camera position in B (3,) [m].
        q_LB0, q_LB1: Attitude at the two frames, scalar-first (4,).
        h0_m: Camera height above the local ground plane at the first frame [m].
        sigma_h0_m: 1-sigma uncertainty of ``h0_m`` [m].
        dv_L: Velocity change over the interval from IMU propagation (3,) [m/s].
        dz_m: Vertical displacement of the camera over the interval, from the
            filter [m] (negative when descending).
        sigma_dz_m: Its 1-sigma uncertainty [m].
        cfg: Settings.

    Returns:
        The measurement, or None when there are too few usable tracks or
        the inputs are unusable (non-finite, non-positive height or interval).
    """
    dt_s = (t1_ns - t0_ns) / NS_PER_S
    if not (dt_s > 0 and math.isfinite(h0_m) and h0_m > 0 and math.isfinite(sigma_h0_m)
            and math.isfinite(dz_m) and math.isfinite(sigma_dz_m)):
        return None
    if not (np.all(np.isfinite(q_LB0)) and np.all(np.isfinite(q_LB1)) and np.all(np.isfinite(dv_L))):
        return None
    have_prev = np.all(np.isfinite(tracks.prev_xy), axis=1) & np.all(np.isfinite(tracks.xy), axis=1)
    n_tracks = int(have_prev.sum())
    if n_tracks < cfg.min_tracks:
        return None
    R_LB0 = Rotation.from_quat(q_LB0, scalar_first=True).as_matrix()
    R_LB1 = Rotation.from_quat(q_LB1, scalar_first=True).as_matrix()
    K_inv = np.linalg.inv(K)
    d0 = _rays_L(tracks.prev_xy[have_prev], K_inv, R_LB0 @ R_BC)
    d1 = _rays_L(tracks.xy[have_prev], K_inv, R_LB1 @ R_BC)
    cos_max = math.cos(math.radians(cfg.max_off_nadir_deg))
    down = (-d0[:, 2] > cos_max) & (-d1[:, 2] > cos_max)
    if int(down.sum()) < cfg.min_tracks:
        return None
    a = d0[down] / -d0[down, 2:3]
    b = d1[down] / -d1[down, 2:3]
    n = a.shape[0]
    # Two equations per track, dz known: dr_xy = h0 (a - b)_xy - dz b_xy.
    A = np.zeros((2 * n, UNKNOWNS))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    g = np.empty(2 * n)  # the right-hand side per unit height
    g[0::2] = a[:, 0] - b[:, 0]
    g[1::2] = a[:, 1] - b[:, 1]
    b_xy = np.empty(2 * n)  # the right-hand side per metre of dz
    b_xy[0::2] = -b[:, 0]
    b_xy[1::2] = -b[:, 1]
    y = h0_m * g + dz_m * b_xy
    keep = np.ones(n, bool)
    f_px = float(K[0, 0])
    for _ in range(cfg.outlier_iterations + 1):
        rows = np.repeat(keep, 2)
        if int(keep.sum()) < cfg.min_tracks:
            return None
        dr, *_ = np.linalg.lstsq(A[rows], y[rows], rcond=None)
        res = (y - A @ dr).reshape(n, 2)
        res_norm = np.hypot(res[:, 0], res[:, 1])
        sigma = MAD_TO_SIGMA * float(np.median(res_norm[keep])) / math.sqrt(2.0)  # per axis [m]
        floor = cfg.pixel_sigma_px * h0_m / f_px  # a pixel's footprint on the ground [m]
        new_keep = res_norm <= cfg.outlier_mad_k * max(sigma, floor) * math.sqrt(2.0)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    rows = np.repeat(keep, 2)
    A_k = A[rows]
    n_used = int(keep.sum())
    dof = max(2 * n_used - UNKNOWNS, 1)
    s2 = max(float(np.sum((y[rows] - A_k @ dr) ** 2)) / dof, floor**2)
    AtA_inv = np.linalg.inv(A_k.T @ A_k)
    cov_dr = s2 * AtA_inv
    # Scale and vertical displacement: dr is linear in h0 and in dz.
    J_h = AtA_inv @ A_k.T @ g[rows]
    J_z = AtA_inv @ A_k.T @ b_xy[rows]
    cov_dr = cov_dr + np.outer(J_h, J_h) * sigma_h0_m**2 + np.outer(J_z, J_z) * sigma_dz_m**2
    # Camera displacement -> body displacement: remove the lever arm's rotation.
    dr_B = dr - ((R_LB1 - R_LB0) @ r_cam_B)[:2]
    v1 = dr_B / dt_s + 0.5 * np.asarray(dv_L, float)[:2]
    R = cfg.covariance_inflation * cov_dr / dt_s**2
    return VelocityMeasurement(
        t_ns=int(t1_ns), v_L=v1, R=0.5 * (R + R.T), n_tracks=n_tracks, n_used=n_used,
        residual_px=math.sqrt(s2) * f_px / h0_m,
    )


def _rays_L(xy: np.ndarray, K_inv: np.ndarray, R_LC: np.ndarray) -> np.ndarray:
    """Pixel rays (not normalised) in L, (N, 3)."""
    pix = np.column_stack([xy, np.ones(len(xy))])
    return (R_LC @ (K_inv @ pix.T)).T
