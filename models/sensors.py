"""Sensor error models: IMU, laser altimeter and star tracker.

Each model turns a truth signal (computed by :class:`models.world.World`)
into the flight-software message of :mod:`gnc.messages`, with its own noise,
on its own random stream, at its own rate. Truth never leaves through a
message except as corrupted by these models.

Ports:
    ImuModel: in truth specific force f_B [m/s^2] and rate omega_B [rad/s];
        out :class:`ImuMessage`; rate ``ImuConfig.period_ns``.
    AltimeterModel: in truth slant range [m] (ray cast, NaN on no hit);
        out :class:`AltimeterMessage`; rate ``AltimeterConfig.period_ns``.
    StarTrackerModel: in truth q_LB; out :class:`AttitudeMessage`;
        rate ``StarTrackerConfig.period_ns``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage

try:  # SciPy's compiled rotation kernels, which its Rotation objects call for single NumPy rotations
    from scipy.spatial.transform import _rotation_cy
except ImportError:  # another SciPy: the public objects only
    _rotation_cy = None

NS_PER_S = 1_000_000_000

# The altimeter boresight is body -z (nadir when upright).
ALTIMETER_BORESIGHT_B = np.array([0.0, 0.0, -1.0])


class ImuConfig(BaseModel):
    """IMU error model: white noise, turn-on bias and bias random walk."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    period_ns: int = Field(10_000_000, gt=0, description="sample period [ns] (default 100 Hz)")
    accel_noise_density: float = Field(
        1e-3, ge=0, le=10.0, description="accelerometer white noise density [m/s^2/sqrt(Hz)]"
    )
    gyro_noise_density: float = Field(1e-5, ge=0, le=1.0, description="gyro white noise density [rad/s/sqrt(Hz)]")
    accel_bias_sigma: float = Field(5e-3, ge=0, description="accelerometer turn-on bias, 1-sigma per axis [m/s^2]")
    gyro_bias_sigma: float = Field(1e-5, ge=0, description="gyro turn-on bias, 1-sigma per axis [rad/s]")
    accel_bias_walk: float = Field(1e-4, ge=0, description="accelerometer bias random walk [m/s^2/sqrt(s)]")
    gyro_bias_walk: float = Field(1e-6, ge=0, description="gyro bias random walk [rad/s/sqrt(s)]")


class AltimeterConfig(BaseModel):
    """Laser altimeter error model."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    period_ns: int = Field(50_000_000, gt=0, description="sample period [ns] (default 20 Hz)")
    max_range_m: float = Field(3000.0, gt=0, description="maximum range; beyond it the sample is invalid [m]")
    noise_sigma_m: float = Field(0.05, ge=0, le=1000.0, description="range noise floor, 1-sigma [m]")
    noise_frac: float = Field(1e-3, ge=0, le=10.0, description="range noise proportional to range, 1-sigma [-]")
    dropout_prob: float = Field(0.01, ge=0, le=1, description="probability that a sample is dropped [-]")


class StarTrackerConfig(BaseModel):
    """Star-tracker attitude error model."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    period_ns: int = Field(100_000_000, gt=0, description="sample period [ns] (default 10 Hz)")
    noise_sigma_arcsec: float = Field(
        10.0, ge=0, description="isotropic attitude noise, 1-sigma per axis [arcsec] (realism = 'ideal')"
    )
    cross_boresight_sigma_arcsec: float = Field(
        2.0, ge=0, description="noise about each axis across the boresight, 1-sigma [arcsec] (realism = 'realistic')"
    )
    about_boresight_sigma_arcsec: float = Field(
        12.0, ge=0, description="noise about the boresight (roll), 1-sigma [arcsec] (realism = 'realistic')"
    )
    boresight_B: tuple[float, float, float] = Field(
        (0.0, 0.6, 0.8), description="tracker boresight in the body frame (normalised on use) [-]"
    )

    @model_validator(mode="after")
    def _boresight_nonzero(self) -> "StarTrackerConfig":
        n = math.sqrt(sum(c * c for c in self.boresight_B))
        if not (math.isfinite(n) and n > 0.0):
            raise ValueError(f"sensors.star_tracker.boresight_B = {self.boresight_B}; allowed: a finite non-zero vector")
        return self

    def error_axes_B(self) -> np.ndarray:
        """Orthonormal axes of the attitude error in B, (3, 3), columns: two cross-boresight axes, then the boresight."""
        b = np.asarray(self.boresight_B, float)
        b = b / np.linalg.norm(b)
        helper = np.array([1.0, 0.0, 0.0]) if abs(b[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(b, helper)
        u /= np.linalg.norm(u)
        return np.column_stack([u, np.cross(b, u), b])

    def error_covariance_B(self) -> np.ndarray:
        """Covariance of the anisotropic attitude error (body-frame rotation vector), (3, 3) [rad^2]."""
        A = self.error_axes_B()
        s = np.radians(np.array([self.cross_boresight_sigma_arcsec, self.cross_boresight_sigma_arcsec,
                                 self.about_boresight_sigma_arcsec]) / 3600.0)
        return (A * s**2) @ A.T


class SensorsConfig(BaseModel):
    """All non-imaging sensors."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    imu: ImuConfig = ImuConfig()
    altimeter: AltimeterConfig = AltimeterConfig()
    star_tracker: StarTrackerConfig = StarTrackerConfig()


class ImuModel:
    """IMU with white noise, turn-on bias and bias random walk (per axis)."""

    def __init__(self, cfg: ImuConfig, rng: np.random.Generator):
        self.cfg = cfg
        self._rng = rng
        dt = cfg.period_ns / NS_PER_S
        # Discrete white-noise sigma from a density: sigma = density / sqrt(dt).
        self._acc_sigma = cfg.accel_noise_density / math.sqrt(dt)
        self._gyro_sigma = cfg.gyro_noise_density / math.sqrt(dt)
        self._acc_walk = cfg.accel_bias_walk * math.sqrt(dt)
        self._gyro_walk = cfg.gyro_bias_walk * math.sqrt(dt)
        self.accel_bias = rng.normal(0.0, cfg.accel_bias_sigma, 3)  # [m/s^2] truth, for scoring only
        self.gyro_bias = rng.normal(0.0, cfg.gyro_bias_sigma, 3)  # [rad/s]

    def sample(self, t_ns: int, f_B_true: np.ndarray, omega_B_true: np.ndarray) -> ImuMessage:
        """Corrupt one truth sample and advance the bias random walk."""
        # One draw of twelve standard normals instead of four of three: the same stream and the same
        # values, since rng.normal(0, s, 3) is 0 + s * (three standard normals) in the order drawn.
        z = self._rng.standard_normal(12)
        f_B = f_B_true + self.accel_bias + (0.0 + self._acc_sigma * z[0:3])
        omega_B = omega_B_true + self.gyro_bias + (0.0 + self._gyro_sigma * z[3:6])
        self.accel_bias = self.accel_bias + (0.0 + self._acc_walk * z[6:9])
        self.gyro_bias = self.gyro_bias + (0.0 + self._gyro_walk * z[9:12])
        return ImuMessage(t_ns=t_ns, f_B=f_B, omega_B=omega_B)


class AltimeterModel:
    """Laser range along the boresight with noise, maximum range and dropouts."""

    def __init__(self, cfg: AltimeterConfig, rng: np.random.Generator):
        self.cfg = cfg
        self._rng = rng

    def sample(self, t_ns: int, range_true_m: float) -> AltimeterMessage:
        """Corrupt one truth range (NaN when the ray hit nothing)."""
        cfg = self.cfg
        # Draw both numbers every sample so the stream does not depend on the geometry.
        dropped = self._rng.random() < cfg.dropout_prob
        noise = self._rng.normal()
        if dropped or not math.isfinite(range_true_m) or range_true_m > cfg.max_range_m:
            return AltimeterMessage(t_ns=t_ns, range_m=math.nan, valid=False, boresight_B=ALTIMETER_BORESIGHT_B)
        sigma = math.hypot(cfg.noise_sigma_m, cfg.noise_frac * range_true_m)
        return AltimeterMessage(
            t_ns=t_ns, range_m=range_true_m + sigma * noise, valid=True, boresight_B=ALTIMETER_BORESIGHT_B
        )


def _rotated_public(q_LB: np.ndarray, rotvec_B: np.ndarray) -> np.ndarray:
    return (Rotation.from_quat(q_LB, scalar_first=True) * Rotation.from_rotvec(rotvec_B)).as_quat(
        canonical=True, scalar_first=True)


def _rotated_kernels(q_LB: np.ndarray, rotvec_B: np.ndarray) -> np.ndarray:
    """:func:`_rotated_public`'s kernel calls, in its order and with its arguments, without its objects."""
    cy = _rotation_cy
    error = np.asarray(cy.from_rotvec(np.asarray(rotvec_B, float), degrees=False)).reshape(1, 4)
    q = cy.from_quat(np.asarray(q_LB, float).reshape(1, 4), normalize=True, copy=True, scalar_first=True)
    product = np.asarray(cy.compose_quat(q, error))[0].reshape(1, 4)
    product = cy.from_quat(product, normalize=True, copy=False, scalar_first=False)
    return np.asarray(cy.as_quat(product, canonical=True, scalar_first=True))[0]


def _kernels_agree() -> bool:
    """Whether :func:`_rotated_kernels` gives :func:`_rotated_public`'s bits on a spread of rotations (so a
    SciPy whose objects call its kernels otherwise is never used through them)."""
    if _rotation_cy is None:
        return False
    rng = np.random.default_rng(0)
    try:
        for scale in (1e-7, 1e-4, 1e-2, 1.0, 3.0):
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            rotvec = scale * rng.normal(size=3)
            if _rotated_kernels(q, rotvec).tobytes() != _rotated_public(q, rotvec).tobytes():
                return False
    except Exception:  # noqa: BLE001 - any other signature or behaviour: the public objects
        return False
    return True


# A star tracker's sample and its fault composition run at 10 Hz in the closed loop, where building the
# three Rotation objects of one composition cost about 0.5 ms; the kernels alone a third of it.
_ROTATED = _rotated_kernels if _kernels_agree() else _rotated_public


def rotated_by_rotvec(q_LB: np.ndarray, rotvec_B: np.ndarray) -> np.ndarray:
    """``q_LB`` (scalar first, (4,)) turned by the body-frame rotation vector ``rotvec_B`` [rad], (4,):
    ``(Rotation.from_quat(q_LB, scalar_first=True) * Rotation.from_rotvec(rotvec_B)).as_quat(canonical=True,
    scalar_first=True)``, bit for bit (through SciPy's kernels where they give its objects' bits)."""
    return _ROTATED(q_LB, rotvec_B)


class StarTrackerModel:
    """Attitude quaternion with a small random rotation error per sample.

    ``anisotropic = False`` (realism "ideal"): the body-frame error rotation vector is
    N(0, noise_sigma^2 I). ``anisotropic = True`` (realism "realistic"): it is
    ``A diag(s_cross, s_cross, s_about) n`` with ``n ~ N(0, I)`` and ``A`` the tracker's
    axes in B (two across the boresight, then the boresight): a real tracker measures
    roll about its boresight several times worse than the boresight's direction.
    """

    def __init__(self, cfg: StarTrackerConfig, rng: np.random.Generator, anisotropic: bool = False):
        self.cfg = cfg
        self._rng = rng
        self.anisotropic = anisotropic
        self._sigma_rad = math.radians(cfg.noise_sigma_arcsec / 3600.0)
        self._axes_B = cfg.error_axes_B()
        self._sigmas_rad = np.radians(np.array([cfg.cross_boresight_sigma_arcsec, cfg.cross_boresight_sigma_arcsec,
                                                cfg.about_boresight_sigma_arcsec]) / 3600.0)

    def sample(self, t_ns: int, q_LB_true: np.ndarray) -> AttitudeMessage:
        """Corrupt one truth attitude: q_meas = q_true (x) dq(noise), body-frame error."""
        if self.anisotropic:
            rotvec = self._axes_B @ (self._sigmas_rad * self._rng.normal(0.0, 1.0, 3))
        else:
            rotvec = self._rng.normal(0.0, self._sigma_rad, 3)
        return AttitudeMessage(t_ns=t_ns, q_LB=rotated_by_rotvec(q_LB_true, rotvec))
