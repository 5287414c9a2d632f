"""Vision measurement from feature tracks (DIMES-style), as a relative-position measurement for the filter.

Ports:
    Inputs: the tracks of one frame pair (:class:`vision.Tracks`, with
        ``prev_xy``); the attitude at both frames, the second from the filter
        and the first from it through the **gyro's relative rotation** (never
        two independent star-tracker fixes); the camera calibration (K, R_BC,
        camera position in B); and the filter's prior positions at both frames
        (the stochastic clone at the first, the propagated state at the second).
    Output: :class:`VisionMeasurement`: the measured mean ground flow ``z``,
        its prediction ``hx``, the Jacobians on the current position and the
        clone, and the covariance ``R``, for
        :meth:`gnc.estimator.NavFilter.update_relative`.
    Rate: camera rate (one measurement per frame pair).

Model and assumptions:
    * The tracked features lie on a **locally planar ground**, of height
      ``h_view`` above the target's elevation under the first camera position and
      slope ``s_view`` (both filter states). A feature seen along the unit-height
      ray ``a_i`` then lies ``h0_i = h0 / (1 + s_view . a_i)`` below the camera,
      and its flow is ``g_i = (dr_xy + dz b_i)(1 + s_view . a_i) / h0``, so the mean
      flow's model is ``h = (dr_xy (1 + s . a_mean) + dz (b_mean + M s)) / h0`` with
      ``M = mean_i b_i a_i^T``. A slope in view matters in a steep descent: with the
      features off-centre, ``dz M s`` reads as horizontal motion (0.1 m/s at
      12 m/s of descent over a 5 % slope). Relief about the plane is noise.
    * With unit-height rays ``a = d0 / -d0_z`` and ``b = d1 / -d1_z`` (``d`` the
      pixel rays rotated into L), a static feature gives
      ``c0 + h0 a = c1 + (h0 + dz) b`` for the camera positions ``c0``, ``c1``,
      the camera height ``h0 = c0_z - h_view`` above the ground at the first frame and
      ``dz = c1_z - c0_z``. Its horizontal part, per track ``i``::

          g_i = (a_i - b_i)_xy = (dr_xy + dz b_i,xy) / h0

      Vision measures the mean flow ``z = mean_i g_i`` over the tracks kept
      after iterative rejection of those whose residual exceeds
      ``outlier_mad_k`` robust sigmas (wrong tracks, moving shadows). Its model
      (level ground: ``h(x) = (dr_xy + dz b_mean,xy) / h0``; sloped: above) depends on the state only through
      the camera positions at the two frames, i.e. on the current position and
      the clone (the lever arm is removed exactly with both attitudes). Its
      Jacobians cover all three components and ``h_view``. The vertical ones
      matter: with the tracked features off-centre (``|b_mean|`` reaches 0.3 in
      a tilted approach) an error of the prior's vertical velocity ``dv_z``
      shifts the flow by ``dv_z dt b_mean / h0``, which the filter must count.
      The filter takes them as **consider** columns (Schmidt-Kalman): their
      uncertainty enters the innovation covariance and the horizontal gain,
      but vision does not correct the height, the vertical velocity or the
      terrain (the divergence would read terrain slope in view as vertical
      velocity); the altimeter does.
    * As DIMES did, only the horizontal flow is used: the vertical motion shows
      in the image only through its divergence, weak and scaled by relief.
    * Covariance: the covariance of the mean flow from the scatter of the kept
      tracks about it, cluster-robust over image cells (``cluster_px``, smaller in
      a frame below 256 px; the
      features of one template err together, so they are not independent
      samples; it reads their shared error from the spread between cells, so a
      pair whose kept tracks occupy fewer than ``min_clusters`` cells gives no
      measurement, nor one whose kept tracks scatter about their common motion
      by more than ``max_track_scatter_px``: they do not follow the ground),
      with each track's variance floored by ``pixel_sigma_px``, is the
      pixel noise of the two frames. Its per-frame part (a frame's noise moves its
      tracked positions in both pairs it belongs to) is ``2 frame_pixel_sigma_px^2``
      of the per-track variance, capped at all of it: half from each frame,
      ``R_frame``, one frame's offset, which the filter carries as a state. The
      tracker's per-frame noise is a calibration: on rendered descents, pairs
      above 250 m, where the consecutive pairs' errors correlate -0.5 (all
      per-frame), err 0.059 px per track, 0.042 px per frame; lower down the
      appearance changes more between frames, the pair's error grows and its
      white part with it.
      The rest is white, ``R``, plus the gyro's relative-rotation error over the
      interval (``sigma_rot_rad``) and a tracking error proportional to the
      rotation between the frames (``rotation_error_frac``: under a slew the
      image motion is mostly rotation, and the tracks share its error). Both
      are multiplied by ``covariance_inflation``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.numeric import all_finite, median
from vision.tracks import Tracks

NS_PER_S = 1_000_000_000
MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution per median absolute deviation
MIN_CAMERA_HEIGHT_M = 1.0  # no measurement from a camera this close to the ground plane [m]


class VisionNavConfig(BaseModel):
    """Vision-measurement settings."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    min_tracks: int = Field(8, ge=3, description="fewest consistent tracks for a measurement [-]")
    pixel_sigma_px: float = Field(
        0.05, gt=0.0, description="floor on the per-track pixel noise used for the covariance [px]"
    )
    outlier_mad_k: float = Field(4.0, gt=1.0, description="reject tracks beyond this many robust sigmas [-]")
    outlier_iterations: int = Field(3, ge=0, le=20, description="rounds of outlier rejection [-]")
    max_off_nadir_deg: float = Field(
        60.0, gt=0.0, lt=90.0, description="rays further than this from straight down are not used [deg]"
    )
    cluster_px: float = Field(
        64.0, gt=0.0,
        description="image cells whose tracks are taken to err together (cluster-robust covariance) [px]; in a "
                    "frame whose shorter side is below cluster_reference_side_px they shrink with it, so that a "
                    "small frame still has as many cells",
    )
    cluster_reference_side_px: float = Field(
        256.0, gt=0.0,
        description="the shorter frame side below which the cells shrink with the frame [px]; the side is read "
                    "from the calibration's principal point (at the image centre: side = 2 min(cx, cy) + 1)",
    )
    min_clusters: int = Field(
        5, ge=1,
        description="fewest image cells (cluster_px) the kept tracks must occupy for a measurement [-]. The "
                    "cluster-robust covariance estimates the error the tracks of one cell share from the spread "
                    "between cells: with one cell it is zero by construction, with two it has rank one, and with "
                    "G cells G - 1 degrees of freedom. On featureless-mare descents, measurements from 3-4 cells "
                    "erred beyond the 99.9 % gate 23-33 % of the time, from 5 or more 6-12 % (rendered lunar "
                    "descents: 3-7 %, and under 0.3 % of their measurements come from fewer than 5 cells)",
    )
    max_track_scatter_px: float = Field(
        1.0, gt=0.0,
        description="largest scatter of the kept tracks about their common motion, RMS per axis [px]: beyond it "
                    "the tracks do not follow the ground and the pair gives no measurement. An LK track of ground "
                    "texture errs by tenths of a pixel (rendered lunar descents, 2080 measurements over six seeds: "
                    "median 0.05 px, largest 0.16 px); on a near-featureless frame the tracks wander over the "
                    "detector noise by pixels (a 75 deg camera over the featureless mare at 500 m: 1.6-5.7 px, "
                    "velocities 10-200 m/s off, each inside its own wide covariance, all off the same way, so "
                    "that 85 of them had moved the filter's velocity from 0.9 to 2.6 m/s off)",
    )
    rotation_error_frac: float = Field(
        0.0, ge=0.0,
        description="1-sigma error of the flow per radian of rotation between the frames (tracking under slews) "
                    "[-]. 0 by default: on rendered descents the tracker's mean error does not grow with the "
                    "rotation (4.4e-5 rad below 2 mrad of rotation, 3.5e-5 rad at 10-50 mrad)",
    )
    frame_pixel_sigma_px: float = Field(
        0.042, ge=0.0,
        description="per-frame localisation noise of one track, 1-sigma per axis [px]: the part of a pair's "
                    "error that the frame shares with its neighbouring pair",
    )
    covariance_inflation: float = Field(
        1.1, ge=1.0,
        description="factor on the measurement covariance for unmodelled errors [-]. 1.1: with 1.0, three "
                    "30-case campaigns gave vision NIS / dof 1.05-1.14 per altitude band and gated out 0.5 % "
                    "of the measurements at a 99.9 % gate",
    )
    cutoff_altitude_m: float = Field(
        30.0, ge=0.0, description="vision is used only above this estimated altitude; below, IMU + altimeter [m]"
    )
    flyout_cutoff_m: float = Field(
        10.0, ge=0.0,
        description="while the terminal phase flies out a missed gate (a built-in law hovering more than twice "
                    "guidance.terminal_hold_radius_m from the target), the horizontal flow is used down to "
                    "this estimated altitude instead of cutoff_altitude_m: a fly-out below the cut-off on the IMU "
                    "alone drifts with the accelerometer bias's error (at or above cutoff_altitude_m: off) [m]",
    )
    divergence_cutoff_m: float = Field(
        4.0, ge=0.0,
        description="without an altimeter (failed or lost), the flow's divergence is used down to this estimated "
                    "altitude (and the horizontal flow down to cutoff_altitude_m as usual) [m]",
    )


@dataclass(frozen=True, slots=True)
class DivergenceMeasurement:
    """The flow's divergence between two frames, linearised at the filter's prior: the camera's vertical
    displacement over its height, ``w = dz / h0``, which scales every track's flow with its ray.

    Each kept track's flow is fitted as ``g_i = u + w b_i`` (``b_i`` its unit-height ray at the second frame,
    ``u`` the common horizontal part): ``w`` is the least-squares slope. The prediction fits the same line to
    the flows the prior predicts for the same tracks (with the viewed ground's slope), so a slope in view
    that makes the flow vary across the image is in the model, not read as vertical motion.

    Attributes:
        t_ns: Time of validity (the second frame) [ns].
        z: The fitted divergence ``w`` [-].
        hx: Its prediction at the prior [-].
        H_r: Jacobian on the body position at ``t_ns``, (3,) [1/m].
        H_c: Jacobian on the clone (body position at the first frame), (3,) [1/m].
        H_g: Jacobian on the viewed ground's height [1/m].
        H_s: Jacobian on the viewed ground's slope, (2,) [-].
        R: Variance of ``z`` [-]: from the fit's residuals (the larger of the classical and the
            cluster-robust estimate), floored by the pixel noise, times ``covariance_inflation`` (an offset of a whole frame moves every track alike and does not
            change the slope).
    """

    t_ns: int
    z: float
    hx: float
    H_r: np.ndarray
    H_c: np.ndarray
    H_g: float
    H_s: np.ndarray
    R: float


@dataclass(frozen=True, slots=True)
class VisionMeasurement:
    """The mean ground flow between two frames, linearised at the filter's prior.

    Attributes:
        t0_ns: Time of the first frame (the clone's) [ns].
        t_ns: Time of validity (the second frame) [ns].
        z: Mean horizontal difference of the unit-height rays, ``mean (a - b)_xy``, (2,) [-].
        hx: Its prediction at the prior, (2,) [-].
        H_r: Jacobian of ``h`` on the body position at ``t_ns``, (2, 3) [1/m] (its
            vertical column, ``b_mean / h0``, is the divergence term).
        H_c: Jacobian of ``h`` on the clone (body position at ``t0_ns``), (2, 3) [1/m].
        H_g: Jacobian of ``h`` on the tracked ground's height under the camera, (2,) [1/m].
        H_s: Jacobian of ``h`` on the tracked ground's slope, (2, 2) [-].
        R: Covariance of the white part of the error of ``z``, (2, 2) [-].
        R_frame: Covariance of one frame's image offset (the shared-frame part), (2, 2) [-].
        b_mean: Mean horizontal unit-height ray of the kept tracks at the second frame, (2,) [-]
            (the model's divergence term: ``h = (dr_xy + dz b_mean) / h0``).
        v_L: Horizontal body velocity the flow implies with the prior's height and
            vertical displacement (telemetry only), (2,) [m/s].
        n_tracks: Tracks offered.
        n_used: Tracks kept after outlier rejection.
        residual_px: Robust residual scatter of the kept tracks, in pixels.
        divergence: The same pair's :class:`DivergenceMeasurement` when asked for (None otherwise, or when
            the kept tracks do not span the image enough to fit it).
    """

    t0_ns: int
    t_ns: int
    z: np.ndarray
    hx: np.ndarray
    H_r: np.ndarray
    H_c: np.ndarray
    H_g: np.ndarray
    H_s: np.ndarray
    R: np.ndarray
    R_frame: np.ndarray
    b_mean: np.ndarray
    v_L: np.ndarray
    n_tracks: int
    n_used: int
    residual_px: float
    divergence: DivergenceMeasurement | None = None


def vision_measurement(
    tracks: Tracks,
    t0_ns: int,
    t1_ns: int,
    K: np.ndarray,
    R_BC: np.ndarray,
    r_cam_B: np.ndarray,
    R_LB0: np.ndarray,
    R_LB1: np.ndarray,
    r0_L: np.ndarray,
    r1_L: np.ndarray,
    h_view_m: float,
    sigma_rot_rad: float,
    cfg: VisionNavConfig,
    s_view: np.ndarray | None = None,
    with_divergence: bool = False,
) -> VisionMeasurement | None:
    """The vision measurement of a frame pair, for :meth:`NavFilter.update_relative`.

    Args:
        tracks: Tracks of the second frame; those with a finite ``prev_xy``
            (present in the first frame) are used.
        t0_ns, t1_ns: Times of the two frames [ns], t1 > t0.
        K: Intrinsics (3, 3) [px].
        R_BC: Camera-to-body rotation (3, 3).
        r_cam_B: Camera position in B (3,) [m].
        R_LB0, R_LB1: Attitude (B to L) at the two frames, (3, 3); ``R_LB0`` should
            be ``R_LB1`` carried back by the gyro's relative rotation.
        r0_L: Prior body position at the first frame (the clone), (3,) [m].
        r1_L: Prior body position at the second frame, (3,) [m].
        h_view_m: Prior mean height of the tracked ground above the target's elevation [m].
        sigma_rot_rad: 1-sigma per axis of the relative rotation between the frames [rad].
        cfg: Settings.
        s_view: Prior slope ``(dh/dx, dh/dy)`` of the viewed ground, (2,) [-]; None: level.
        with_divergence: Also fit the flow's divergence (:class:`DivergenceMeasurement`).

    Returns:
        The measurement, or None when there are too few usable tracks, they sit in
        fewer than ``min_clusters`` image cells or scatter beyond
        ``max_track_scatter_px``, or the inputs are unusable (non-finite, interval
        not positive, camera below ``MIN_CAMERA_HEIGHT_M``).
    """
    dt_s = (t1_ns - t0_ns) / NS_PER_S
    if not (dt_s > 0 and math.isfinite(sigma_rot_rad) and all_finite(K, R_BC, r_cam_B, R_LB0, R_LB1, r0_L, r1_L)):
        return None
    # A track is usable where both positions are finite (a sum is finite iff both terms are).
    ok = np.isfinite(tracks.prev_xy + tracks.xy)
    have_prev = ok[:, 0] & ok[:, 1]
    n_tracks = int(np.count_nonzero(have_prev))
    if n_tracks < cfg.min_tracks:
        return None
    c0 = r0_L + R_LB0 @ r_cam_B  # camera positions [m]
    c1 = r1_L + R_LB1 @ r_cam_B
    h0 = float(c0[2]) - h_view_m
    if h0 < MIN_CAMERA_HEIGHT_M:
        return None
    dz = float(c1[2] - c0[2])
    K_inv = _intrinsics_inverse(K)
    xy0 = tracks.prev_xy[have_prev]
    d0 = _rays_L(xy0, K_inv, R_LB0 @ R_BC)
    d1 = _rays_L(tracks.xy[have_prev], K_inv, R_LB1 @ R_BC)
    # Within max_off_nadir_deg of straight down: -d_z > cos_max |d|.
    cos_max = math.cos(math.radians(cfg.max_off_nadir_deg))
    down = (-d0[:, 2] > cos_max * np.sqrt((d0 * d0).sum(axis=1))) & (-d1[:, 2] > cos_max * np.sqrt((d1 * d1).sum(axis=1)))
    if int(np.count_nonzero(down)) < cfg.min_tracks:
        return None
    d0, d1, xy0 = d0[down], d1[down], xy0[down]
    a = d0[:, :2] / -d0[:, 2:3]  # unit-height rays, horizontal part [-]
    b = d1[:, :2] / -d1[:, 2:3]
    g = a - b  # per-track flow [-]
    y = h0 * g - dz * b  # each track's estimate of the horizontal camera displacement [m]
    f_px = float(K[0, 0])
    floor = cfg.pixel_sigma_px * h0 / f_px  # a pixel's footprint on the ground [m]
    n = g.shape[0]
    keep = np.ones(n, bool)
    n_used = n
    for _ in range(cfg.outlier_iterations + 1):
        if n_used < cfg.min_tracks:
            return None
        res = y - y[keep].sum(axis=0) / n_used
        res_norm = np.hypot(res[:, 0], res[:, 1])
        sigma = MAD_TO_SIGMA * median(res_norm[keep]) / math.sqrt(2.0)  # per axis [m]
        new_keep = res_norm <= cfg.outlier_mad_k * max(sigma, floor) * math.sqrt(2.0)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
        n_used = int(np.count_nonzero(keep))
    if n_used < cfg.min_tracks:
        return None
    yk, gk, ak, bk = y[keep], g[keep], a[keep], b[keep]
    res = yk - yk.sum(axis=0) / n_used
    s2 = max(float((res * res).sum()) / max(2 * n_used - 2, 1), floor**2)  # per-axis track variance [m^2]
    if s2 > (cfg.max_track_scatter_px * h0 / f_px) ** 2:  # the tracks do not move with the ground
        return None
    # The mean's covariance, cluster-robust: tracks close together in the image (one template's
    # features) err together, so the tracks are not n independent samples.
    cell_px = cluster_cell_px(K, cfg)
    cluster, n_clusters = _image_cells(xy0[keep], cell_px)
    if n_clusters < cfg.min_clusters:
        return None
    sums = np.column_stack([np.bincount(cluster, weights=res[:, 0], minlength=n_clusters),
                            np.bincount(cluster, weights=res[:, 1], minlength=n_clusters)])
    cov_mean = sums.T @ sums / (n_used * n_used) * (n_clusters / max(n_clusters - 1, 1))
    lift = max(floor**2 / n_used - min(float(cov_mean[0, 0]), float(cov_mean[1, 1])), 0.0)
    cov_mean[0, 0] += lift
    cov_mean[1, 1] += lift
    z = gk.sum(axis=0) / n_used
    b_mean = bk.sum(axis=0) / n_used
    a_mean = ak.sum(axis=0) / n_used
    M = bk.T @ ak / n_used  # mean of b_i a_i^T [-]
    sv = np.zeros(2) if s_view is None else np.asarray(s_view, dtype=float)
    dr_xy = (c1 - c0)[:2]
    scale = 1.0 + float(sv @ a_mean)
    div = b_mean + M @ sv  # the divergence term's direction, with the slope
    hx = (dr_xy * scale + dz * div) / h0
    # The vertical columns: the camera's vertical displacement enters through dz b_mean (the
    # divergence term), the clone's height also through h0. The filter takes them as consider
    # columns: their uncertainty is in the innovation covariance, but vision does not correct them.
    div_x, div_y = div.tolist()
    hx_x, hx_y = hx.tolist()
    H_r = np.array([[scale, 0.0, div_x], [0.0, scale, div_y]]) / h0
    H_c = -np.array([[scale, 0.0, div_x + hx_x], [0.0, scale, div_y + hx_y]]) / h0
    H_g = hx / h0  # a higher ground is a shorter range: a larger flow
    H_s = (np.outer(dr_xy, a_mean) + dz * M) / h0
    # The tracks' scatter about their mean holds the pixel noise of both frames. Its per-frame part,
    # 2 frame_pixel_sigma_px^2 of the per-track variance, is shared with the neighbouring pair
    # (split evenly between the frames); the rest (appearance change between the frames) is white.
    track_cov = cov_mean / (h0 * h0)  # covariance of the mean flow from the tracks' scatter [-]
    track_var_px2 = s2 * (f_px / h0) ** 2  # per-track variance of the pair, per axis [px^2]
    share = min(1.0, 2.0 * cfg.frame_pixel_sigma_px**2 / track_var_px2)
    R_frame = 0.5 * share * track_cov
    # Under a slew most of the image motion is rotation; the tracker follows it to about
    # rotation_error_frac of the rotation, an error the scatter does not show (all tracks share it).
    # trace(R_LB1^T R_LB0) = sum of the elementwise products.
    cos_rot = min(max((float((R_LB1 * R_LB0).sum()) - 1.0) / 2.0, -1.0), 1.0)
    sigma_slew = cfg.rotation_error_frac * math.acos(cos_rot)
    R = (1.0 - share) * track_cov
    white = sigma_rot_rad**2 + sigma_slew**2
    R[0, 0] += white
    R[1, 1] += white
    R = cfg.covariance_inflation * R
    R_frame = cfg.covariance_inflation * R_frame
    v_xy = (h0 * z - dz * b_mean - ((R_LB1 - R_LB0) @ r_cam_B)[:2]) / dt_s
    divergence = None
    if with_divergence:
        divergence = _divergence(int(t1_ns), gk, ak, bk, xy0[keep], dr_xy, dz, h0, sv, f_px, cell_px, cfg)
    return VisionMeasurement(
        t0_ns=int(t0_ns), t_ns=int(t1_ns), z=z, hx=hx, H_r=H_r, H_c=H_c, H_g=H_g, H_s=H_s, R=0.5 * (R + R.T),
        R_frame=R_frame, b_mean=b_mean, v_L=v_xy, n_tracks=n_tracks, n_used=n_used,
        residual_px=math.sqrt(s2) * f_px / h0, divergence=divergence,
    )


def divergence_fit_weights(b: np.ndarray) -> np.ndarray | None:
    """The weights ``l_i`` (N, 2) with ``w = sum_i l_i . g_i`` the least-squares slope of ``g_i = u + w b_i``
    (``u`` free, 2-D; ``b`` (N, 2)); None when the rays do not spread (a singular fit)."""
    bc = b - b.mean(axis=0)
    sbb = float((bc * bc).sum())
    if not sbb > 1e-12:
        return None
    return bc / sbb


def _divergence(t_ns: int, g: np.ndarray, a: np.ndarray, b: np.ndarray, xy: np.ndarray, dr_xy: np.ndarray,
                dz: float, h0: float, sv: np.ndarray, f_px: float, cell_px: float,
                cfg: VisionNavConfig) -> DivergenceMeasurement | None:
    """The flow's divergence of the kept tracks (flows ``g``, rays ``a``, ``b``, pixels ``xy`` at the first
    frame) and its model at the prior (:class:`DivergenceMeasurement`); ``cell_px`` the cluster cells'
    side (:func:`cluster_cell_px`)."""
    lw = divergence_fit_weights(b)
    if lw is None:
        return None
    n = g.shape[0]
    z = float((lw * g).sum())
    # The prior's flow per track and its derivatives, with the slope factor (1 + s . a_i).
    k = 1.0 + a @ sv  # (n,)
    pred = (dr_xy[None, :] + dz * b) * k[:, None] / h0
    hx = float((lw * pred).sum())
    d_dr = np.array([float((lw[:, 0] * k).sum()), float((lw[:, 1] * k).sum())]) / h0  # d hx / d dr_xy
    d_dz = float((lw * b * k[:, None]).sum()) / h0
    d_h0 = -hx / h0
    # dr = c1 - c0 (horizontal), dz = c1_z - c0_z, h0 = c0_z - h_view.
    H_r = np.array([d_dr[0], d_dr[1], d_dz])
    H_c = np.array([-d_dr[0], -d_dr[1], -d_dz + d_h0])
    H_g = -d_h0
    # d hx / d s = sum_i l_i . (dr + dz b_i) a_i^T / h0
    H_s = ((lw * (dr_xy[None, :] + dz * b)).sum(axis=1)[:, None] * a).sum(axis=0) / h0
    # Variance from the fit's residuals: the larger of the classical one (independent tracks) and the
    # cluster-robust one over image cells (one template's tracks err together), both with the three fitted
    # parameters' degrees of freedom taken out, floored by the pixel noise of the two frames.
    u = (g - z * b).mean(axis=0)
    res = g - u - z * b
    l2 = float((lw * lw).sum())
    var_white = float((res * res).sum()) / max(2 * n - 3, 1) * l2
    contrib = (lw * res).sum(axis=1)  # each track's share of the slope's error
    cluster, n_clusters = _image_cells(xy, cell_px)
    sums = np.bincount(cluster, weights=contrib, minlength=n_clusters)
    var_cluster = float(sums @ sums) * (n_clusters / max(n_clusters - 3, 1))
    floor = (cfg.pixel_sigma_px / f_px) ** 2 * 2.0 * l2
    R = cfg.covariance_inflation * max(var_white, var_cluster, floor)
    if not (math.isfinite(z) and math.isfinite(R) and n >= cfg.min_tracks):
        return None
    return DivergenceMeasurement(t_ns=t_ns, z=z, hx=hx, H_r=H_r, H_c=H_c, H_g=float(H_g), H_s=H_s, R=R)


_K_INV_CACHE: dict[bytes, np.ndarray] = {}


def _intrinsics_inverse(K: np.ndarray) -> np.ndarray:
    """``inv(K)``, computed once per distinct calibration (a camera's is constant)."""
    key = np.ascontiguousarray(K, dtype=float).tobytes()
    K_inv = _K_INV_CACHE.get(key)
    if K_inv is None:
        if len(_K_INV_CACHE) > 16:
            _K_INV_CACHE.clear()
        K_inv = _K_INV_CACHE[key] = np.linalg.inv(K)
        K_inv.flags.writeable = False
    return K_inv


def _rays_L(xy: np.ndarray, K_inv: np.ndarray, R_LC: np.ndarray) -> np.ndarray:
    """Pixel rays (not normalised) in L, (N, 3): ``R_LC K^-1 (x, y, 1)`` per pixel."""
    A = R_LC @ K_inv
    return xy @ A[:, :2].T + A[:, 2]


def cluster_cell_px(K: np.ndarray, cfg: VisionNavConfig) -> float:
    """The side of the cluster-robust covariance's image cells [px]: ``cluster_px``, scaled down with a frame
    whose shorter side (``2 min(cx, cy) + 1`` from the principal point of ``K``) is below
    ``cluster_reference_side_px`` (a 128 px frame has 32 px cells: sixteen, as a 256 px frame has, where 64 px
    cells would be four and never reach ``min_clusters``). Larger frames keep ``cluster_px``: on the featureless
    mare at 512 px (20 cases), 64 px cells gave a horizontal-velocity ANEES inside its band from 500 m to 80 m
    and 13 landings, 128 px cells (a cell per sixteenth of the frame) 9 landings and 2.3-4.3 per 2 dof."""
    side = 2.0 * min(float(K[0, 2]), float(K[1, 2])) + 1.0
    return cfg.cluster_px * min(1.0, side / cfg.cluster_reference_side_px)


def _image_cells(xy: np.ndarray, cell_px: float) -> tuple[np.ndarray, int]:
    """Which ``cell_px`` square of the image each point (N >= 1, (N, 2) [px]) falls in, and how many
    distinct squares there are: labels 0..n-1 in the order of the squares' (column, row)."""
    cell = np.floor(xy / cell_px).astype(np.int64)
    cell -= cell.min(axis=0)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    label = np.cumsum(np.bincount(key) > 0) - 1
    return label[key], int(label[-1]) + 1
