"""Truth-side faults: the scenario's ``[[faults]]`` and the injector that applies them.

Faults sit between the truth sensor models and the messages the flight
software receives, and in the actuator path; the flight software sees only
what a real, failing sensor or engine would give it. After Basilisk's
``BSK_Faults`` list and Trick's malfunctions: each fault has a kind, a target,
a trigger, a duration and its parameters.

Trigger (at most one; none: from t = 0): ``t_s`` or ``t_ns`` (simulation
time), ``altitude_m`` (the first instant the truth height of the body origin
above the terrain under it is at or below this), or ``phase`` (the first
control tick at which guidance reports this phase). A fault is active from its
trigger for ``duration_s`` (unset: to the end of the run).

Kinds and targets:

* sensors (``target``: ``imu.accel``, ``imu.gyro``, ``altimeter``,
  ``star_tracker``; IMU and star-tracker faults act on ``axes``):
  ``dropout`` (no message; an IMU dropout drops the whole IMU message),
  ``stuck`` (the values of the last message before the trigger, repeated with
  fresh time tags), ``bias_step`` (+ ``value``), ``bias_ramp``
  (+ ``rate_per_s`` * time since the trigger), ``noise`` (the white noise's
  1-sigma times ``factor``: an independent draw of ``sqrt(factor^2 - 1)``
  sigma is added), ``scale`` (the measurement times ``factor``),
  ``saturation`` (clipped to +-``limit``; the altimeter to ``limit``) and
  ``flagged_invalid`` (the message as measured, with ``valid = False``).
  Units: m/s^2 (accelerometer), rad/s (gyro), m (altimeter), arcsec
  (star tracker, a rotation about the body axes). ``scale`` and ``saturation``
  do not apply to the star tracker.
* camera: ``camera_blackout`` (no frame), ``frame_drop`` (each frame lost with
  ``probability``), ``exposure`` (the scene's signal times ``gain`` before the
  detector noise).
* engine: ``thrust_loss`` (delivered thrust times ``1 - fraction``, and an
  off-axis ``torque_B_Nm`` while the engine fires), ``misalignment`` (the thrust
  line tilted by ``angle_deg`` towards ``azimuth_deg``), ``stuck_throttle`` (a
  lit engine delivers the command held at the trigger, whatever is commanded;
  an off command still shuts it). One misalignment and one stuck throttle act
  at a time, the first listed (time-triggered ones that overlap are refused).
* RCS (``target = "rcs"``): ``rcs_loss`` (the torque the RCS delivers about
  each of ``axes`` times ``1 - fraction``, in both senses or only the
  ``positive`` or ``negative`` one: thrusters failed off or clogged),
  ``rcs_stuck_on`` (a thruster stuck open: a constant torque of
  ``fraction`` of the RCS's limit about ``axis`` in the ``sign`` sense, on top of
  whatever is commanded, drawing propellant when the RCS does).
* ``computer_reset``: the flight computer is down for ``down_s`` (no message
  is received, the engine and RCS are off), then the flight software restarts
  from what it can know (its own non-volatile checkpoint).
* ``terrain_step``: the terrain within ``radius_m`` of ``center_xy_m`` is
  raised by ``height_m`` (negative: a pit), for the whole run (no trigger):
  a cliff or crater rim under the ground track (Hakuto-R).

Randomness (``noise``, ``frame_drop``) comes from each fault's own child of the
run's "faults" stream, so the nominal streams draw exactly as without faults.

Ports:
    :class:`FaultInjector`: in the truth sensor messages, camera frame
    indices, actuator commands and the truth altitude and guidance phase (for
    triggers); out the messages delivered (or None), the frame decisions and the
    actuator modifications. Rate: called at each event of the closed loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from gnc.messages import AltimeterMessage, AttitudeMessage, ImuMessage
from models.sensors import rotated_by_rotvec

NS_PER_S = 1_000_000_000
FAULT_TIME_MAX_S = 1.0e6  # a trigger time or duration beyond this (11.6 days) is refused: in ns it overflowed [s]
FAULT_BIAS_MAX = 1.0e6  # a bias or bias rate beyond this, in the sensor's unit, is refused: it overflowed the filter
SENSOR_TARGETS = ("imu.accel", "imu.gyro", "altimeter", "star_tracker")
PHASES = ("approach", "terminal")


def _check_axes(axes: list[int]) -> None:
    """Body axes of a fault: distinct values among 0, 1, 2 (one-line ValueError)."""
    if any(a not in (0, 1, 2) for a in axes) or len(set(axes)) != len(axes):
        raise ValueError(f"fault axes = {axes}; allowed: distinct values among 0, 1, 2")


class _Fault(BaseModel):
    """Trigger and duration, common to every fault."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    t_s: float | None = Field(None, ge=0.0, le=FAULT_TIME_MAX_S, description="trigger: simulation time [s]")
    t_ns: int | None = Field(None, ge=0, le=int(FAULT_TIME_MAX_S) * NS_PER_S, description="trigger: simulation time [ns]")
    altitude_m: float | None = Field(
        None, description="trigger: truth height of the body origin above the terrain under it, at or below [m]"
    )
    phase: Literal["approach", "terminal"] | None = Field(None, description="trigger: guidance phase")
    duration_s: float | None = Field(None, gt=0.0, le=FAULT_TIME_MAX_S,
                                     description="how long the fault lasts [s]; unset: to the end")

    @model_validator(mode="after")
    def _one_trigger(self) -> "_Fault":
        set_ = [n for n in ("t_s", "t_ns", "altitude_m", "phase") if getattr(self, n) is not None]
        if len(set_) > 1:
            raise ValueError(f"fault '{self.kind}' has triggers {', '.join(set_)}; allowed: at most one of "
                             "t_s, t_ns, altitude_m, phase")
        return self

    def trigger_time_ns(self) -> int | None:
        """The trigger time [ns] for a time trigger (none set: 0); None for altitude and phase triggers."""
        if self.t_ns is not None:
            return self.t_ns
        if self.t_s is not None:
            return int(round(self.t_s * NS_PER_S))
        if self.altitude_m is None and self.phase is None:
            return 0
        return None

    def duration_ns(self) -> int | None:
        return None if self.duration_s is None else int(round(self.duration_s * NS_PER_S))

    def end_ns(self, start_ns: int | None) -> int | None:
        """The end of the fault's window when it starts at ``start_ns`` [ns]; None: not started, or no end."""
        d = self.duration_ns()
        return None if start_ns is None or d is None else start_ns + d

    @property
    def subsystem(self) -> str:
        """What the fault affects, as flight-software detections name it (``imu``, ``altimeter``, ...)."""
        target = getattr(self, "target", "")
        return target.split(".")[0]


class _SensorFault(_Fault):
    target: Literal["imu.accel", "imu.gyro", "altimeter", "star_tracker"] = Field(
        description="the sensor: imu.accel, imu.gyro, altimeter or star_tracker"
    )
    axes: list[int] = Field([0, 1, 2], min_length=1, max_length=3,
                            description="body axes affected (IMU and star tracker): 0 x, 1 y, 2 z")

    @model_validator(mode="after")
    def _axes(self) -> "_SensorFault":
        _check_axes(self.axes)
        return self


class Dropout(_SensorFault):
    """No message from the sensor (an IMU dropout drops the whole IMU message)."""

    kind: Literal["dropout"]


class Stuck(_SensorFault):
    """The sensor repeats the values of its last message before the trigger."""

    kind: Literal["stuck"]


class BiasStep(_SensorFault):
    """A constant bias added from the trigger."""

    kind: Literal["bias_step"]
    value: float = Field(ge=-FAULT_BIAS_MAX, le=FAULT_BIAS_MAX,
                         description="bias: m/s^2 (accel), rad/s (gyro), m (altimeter), arcsec (star tracker)")


class BiasRamp(_SensorFault):
    """A bias growing linearly from zero at the trigger."""

    kind: Literal["bias_ramp"]
    rate_per_s: float = Field(ge=-FAULT_BIAS_MAX, le=FAULT_BIAS_MAX, description="bias rate: the bias's unit per second")


class Noise(_SensorFault):
    """The white noise's 1-sigma multiplied by ``factor``."""

    kind: Literal["noise"]
    factor: float = Field(gt=1.0, le=1000.0, description="noise multiplier k > 1 [-]")


class Scale(_SensorFault):
    """The measurement multiplied by ``factor``."""

    kind: Literal["scale"]
    factor: float = Field(gt=0.0, le=100.0, description="scale factor [-]")


class Saturation(_SensorFault):
    """The measurement clipped to +-``limit`` (the altimeter's range to ``limit``)."""

    kind: Literal["saturation"]
    limit: float = Field(gt=0.0, description="saturation limit in the sensor's unit")


class FlaggedInvalid(_SensorFault):
    """The message as measured, flagged invalid (the data are good, the flag says otherwise)."""

    kind: Literal["flagged_invalid"]


class CameraBlackout(_Fault):
    """No camera frame reaches the flight software."""

    kind: Literal["camera_blackout"]
    target: Literal["camera"] = "camera"


class FrameDrop(_Fault):
    """Each camera frame is lost with a probability."""

    kind: Literal["frame_drop"]
    target: Literal["camera"] = "camera"
    probability: float = Field(ge=0.0, le=1.0, description="probability that a frame is lost [-]")


class Exposure(_Fault):
    """The scene's signal multiplied by ``gain`` (before the detector noise)."""

    kind: Literal["exposure"]
    target: Literal["camera"] = "camera"
    gain: float = Field(ge=0.0, le=100.0, description="exposure gain on the signal [-]")


class ThrustLoss(_Fault):
    """Delivered thrust times (1 - fraction), and an off-axis torque while the engine fires."""

    kind: Literal["thrust_loss"]
    target: Literal["engine"] = "engine"
    fraction: float = Field(ge=0.0, le=1.0, description="fraction of the thrust lost [-]")
    torque_B_Nm: tuple[float, float, float] = Field((0.0, 0.0, 0.0),
                                                    description="off-axis torque while firing, in B [N m]")


class Misalignment(_Fault):
    """The thrust line tilted from body +z."""

    kind: Literal["misalignment"]
    target: Literal["engine"] = "engine"
    angle_deg: float = Field(ge=0.0, le=45.0, description="tilt of the thrust line from body +z [deg]")
    azimuth_deg: float = Field(0.0, ge=-360.0, le=360.0, description="direction of the tilt, +x towards +y [deg]")


class StuckThrottle(_Fault):
    """A lit engine delivers the thrust command held at the trigger."""

    kind: Literal["stuck_throttle"]
    target: Literal["engine"] = "engine"


class RcsLoss(_Fault):
    """The RCS torque about ``axes`` times (1 - fraction), in one sense or both."""

    kind: Literal["rcs_loss"]
    target: Literal["rcs"] = "rcs"
    axes: list[int] = Field([0, 1, 2], min_length=1, max_length=3, description="body axes affected: 0 x, 1 y, 2 z")
    fraction: float = Field(1.0, ge=0.0, le=1.0, description="fraction of the torque lost (1: none delivered) [-]")
    direction: Literal["both", "positive", "negative"] = Field(
        "both", description="the torque sense lost: both, or only the positive or negative one (one thruster of "
                            "a pair) [-]")

    @model_validator(mode="after")
    def _axes(self) -> "RcsLoss":
        _check_axes(self.axes)
        return self


class RcsStuckOn(_Fault):
    """A thruster stuck open: a constant torque about one axis, added to what is commanded."""

    kind: Literal["rcs_stuck_on"]
    target: Literal["rcs"] = "rcs"
    axis: int = Field(ge=0, le=2, description="body axis of the stuck thruster's torque: 0 x, 1 y, 2 z")
    sign: Literal[-1, 1] = Field(1, description="sense of its torque about the axis: +1 or -1")
    fraction: float = Field(1.0, gt=0.0, le=1.0, description="its torque as a fraction of the RCS limit [-]")


class ComputerReset(_Fault):
    """The flight computer goes down for ``down_s`` (engine and RCS off), then restarts."""

    kind: Literal["computer_reset"]
    target: Literal["computer"] = "computer"
    down_s: float = Field(gt=0.0, le=60.0, description="time the computer is down, engine off [s]")

    @model_validator(mode="after")
    def _down_s_is_its_duration(self) -> "ComputerReset":
        if self.duration_s is not None:
            raise ValueError(f"duration_s = {self.duration_s:g}: a reset lasts its down_s "
                             f"({self.down_s:g} s), and duration_s was ignored; allowed: down_s alone")
        return self

    def duration_ns(self) -> int | None:
        return int(round(self.down_s * NS_PER_S))


class TerrainStep(_Fault):
    """The terrain within a disc raised by ``height_m`` (a mesa; negative: a pit), for the whole run."""

    kind: Literal["terrain_step"]
    target: Literal["terrain"] = "terrain"
    height_m: float = Field(ge=-1000.0, le=1000.0, description="height added inside the disc [m]")
    center_xy_m: tuple[float, float] = Field(description="centre of the disc in L [m]")
    radius_m: float = Field(gt=0.0, description="radius of the disc [m]")

    @model_validator(mode="after")
    def _no_trigger(self) -> "TerrainStep":
        if any(getattr(self, n) is not None for n in ("t_s", "t_ns", "altitude_m", "phase", "duration_s")):
            raise ValueError("fault 'terrain_step' is part of the terrain for the whole run; allowed: no trigger "
                             "(t_s, t_ns, altitude_m, phase) and no duration_s")
        return self


FaultConfig = Annotated[
    Union[Dropout, Stuck, BiasStep, BiasRamp, Noise, Scale, Saturation, FlaggedInvalid, CameraBlackout, FrameDrop,
          Exposure, ThrustLoss, Misalignment, StuckThrottle, RcsLoss, RcsStuckOn, ComputerReset, TerrainStep],
    Field(discriminator="kind"),
]
SENSOR_KINDS = ("dropout", "stuck", "bias_step", "bias_ramp", "noise", "scale", "saturation", "flagged_invalid")


def check_fault(f: Any) -> None:
    """Combinations the types alone do not refuse (one line, for the scenario's validator)."""
    if f.kind in ("scale", "saturation") and f.target == "star_tracker":
        raise ValueError(f"fault '{f.kind}' on target 'star_tracker'; allowed targets: imu.accel, imu.gyro, altimeter")
    if f.kind in SENSOR_KINDS and "axes" in f.model_fields_set and sorted(f.axes) != [0, 1, 2]:
        # The axes were silently ignored: the altimeter has one value; these act on the whole message.
        if f.target == "altimeter":
            why = "the altimeter has one value"
        elif f.kind in ("dropout", "flagged_invalid"):
            why = f"a {f.kind} acts on the whole message"
        elif f.target == "star_tracker" and f.kind == "stuck":
            why = "a stuck star tracker repeats its whole attitude"
        else:
            return
        raise ValueError(f"axes = {f.axes} on a '{f.kind}' fault of '{f.target}': {why}, so the axes would be "
                         "ignored; allowed: leave axes unset")


# --------------------------------------------------------------------------- the injector
@dataclass
class _State:
    """One fault's run-time state."""

    cfg: Any
    rng: np.random.Generator
    start_ns: int | None = None
    held: Any = None  # stuck: the values held; stuck_throttle: the command held

    def active(self, t_ns: int) -> bool:
        if self.start_ns is None or t_ns < self.start_ns:
            return False
        end = self.cfg.end_ns(self.start_ns)
        return end is None or t_ns < end


@dataclass
class FaultInjector:
    """Applies a scenario's faults to the truth-side signals of one run.

    Args:
        faults: The scenario's faults.
        sensor_sigmas: White-noise 1-sigma per sensor channel, for ``noise``:
            ``imu.accel`` [m/s^2], ``imu.gyro`` [rad/s], ``star_tracker``
            [arcsec], and ``altimeter`` a function of the range [m] -> [m].
        seed: The run's "faults" ``SeedSequence``; fault ``i`` draws from its child ``i``.
    """

    faults: list[Any]
    sensor_sigmas: dict[str, Any]
    seed: np.random.SeedSequence
    states: list[_State] = field(init=False)
    _last_imu: ImuMessage | None = field(default=None, init=False)
    _last_alt: AltimeterMessage | None = field(default=None, init=False)
    _last_att: AttitudeMessage | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self.states = []
        for i, f in enumerate(self.faults):
            rng = np.random.Generator(np.random.PCG64(
                np.random.SeedSequence(self.seed.entropy, spawn_key=(*self.seed.spawn_key, i))))
            self.states.append(_State(f, rng))

    # ------------------------------------------------------------------ triggers
    def needs_altitude(self) -> bool:
        """Whether an untriggered fault waits for an altitude (the caller then passes the truth altitude)."""
        return any(s.start_ns is None and s.cfg.altitude_m is not None for s in self.states)

    def update(self, t_ns: int, altitude_m: float | None = None, phase: str | None = None) -> list[int]:
        """Evaluate the triggers at ``t_ns``; returns the indices of the faults triggered now."""
        started = []
        for i, s in enumerate(self.states):
            if s.start_ns is not None or s.cfg.kind == "terrain_step":
                continue
            c = s.cfg
            t0 = c.trigger_time_ns()
            hit = ((t0 is not None and t_ns >= t0)
                   or (c.altitude_m is not None and altitude_m is not None and altitude_m <= c.altitude_m)
                   or (c.phase is not None and phase == c.phase))
            if hit:
                s.start_ns = t_ns
                started.append(i)
        return started

    def _active(self, t_ns: int, kinds: tuple[str, ...] | None = None, target: str | None = None):
        for s in self.states:
            if (kinds is None or s.cfg.kind in kinds) and (target is None or getattr(s.cfg, "target", None) == target) \
                    and s.active(t_ns):
                yield s

    def windows(self) -> list[tuple[int | None, int | None]]:
        """Per fault, its (start, end) [ns]; None: not triggered / no end."""
        return [(s.start_ns, s.cfg.end_ns(s.start_ns)) for s in self.states]

    # ------------------------------------------------------------------ sensors
    def _vector(self, s: _State, t_ns: int, v: np.ndarray, held: np.ndarray | None, sigma: float,
                unit: float = 1.0) -> np.ndarray:
        """One sensor fault applied to the selected axes of a vector measurement."""
        c, ax = s.cfg, s.cfg.axes
        v = np.array(v, dtype=float)
        if c.kind == "stuck":
            if held is not None:
                v[ax] = held[ax]
        elif c.kind == "bias_step":
            v[ax] += c.value * unit
        elif c.kind == "bias_ramp":
            v[ax] += c.rate_per_s * unit * (t_ns - s.start_ns) / NS_PER_S
        elif c.kind == "noise":
            v[ax] += s.rng.normal(0.0, math.sqrt(c.factor**2 - 1.0) * sigma, len(ax))
        elif c.kind == "scale":
            v[ax] *= c.factor
        elif c.kind == "saturation":
            v[ax] = np.clip(v[ax], -c.limit, c.limit)
        return v

    def imu(self, msg: ImuMessage) -> ImuMessage | None:
        """The IMU message delivered (None: dropped)."""
        t = msg.t_ns
        f_B, w_B, valid = msg.f_B, msg.omega_B, msg.valid
        for s in self._active(t, SENSOR_KINDS):
            tgt = s.cfg.target
            if tgt not in ("imu.accel", "imu.gyro"):
                continue
            if s.cfg.kind == "dropout":
                return None
            if s.cfg.kind == "flagged_invalid":
                valid = False
                continue
            if s.cfg.kind == "stuck" and s.held is None:
                s.held = self._last_imu if self._last_imu is not None else msg
            held = None if s.held is None else (s.held.f_B if tgt == "imu.accel" else s.held.omega_B)
            if tgt == "imu.accel":
                f_B = self._vector(s, t, f_B, held, self.sensor_sigmas["imu.accel"])
            else:
                w_B = self._vector(s, t, w_B, held, self.sensor_sigmas["imu.gyro"])
        self._last_imu = msg
        return replace(msg, f_B=f_B, omega_B=w_B, valid=valid)

    def altimeter(self, msg: AltimeterMessage) -> AltimeterMessage | None:
        """The altimeter message delivered (None: dropped)."""
        t = msg.t_ns
        rng_m, valid = msg.range_m, msg.valid
        for s in self._active(t, SENSOR_KINDS, "altimeter"):
            c = s.cfg
            if c.kind == "dropout":
                return None
            if c.kind == "flagged_invalid":
                valid = False
            elif c.kind == "stuck":
                if s.held is None:
                    s.held = self._last_alt if self._last_alt is not None else msg
                rng_m, valid = s.held.range_m, s.held.valid
            elif valid and math.isfinite(rng_m):
                if c.kind == "bias_step":
                    rng_m += c.value
                elif c.kind == "bias_ramp":
                    rng_m += c.rate_per_s * (t - s.start_ns) / NS_PER_S
                elif c.kind == "noise":
                    rng_m += s.rng.normal(0.0, math.sqrt(c.factor**2 - 1.0) * self.sensor_sigmas["altimeter"](rng_m))
                elif c.kind == "scale":
                    rng_m *= c.factor
                elif c.kind == "saturation":
                    rng_m = min(rng_m, c.limit)
        self._last_alt = msg
        return replace(msg, range_m=float(rng_m), valid=bool(valid))

    def star_tracker(self, msg: AttitudeMessage) -> AttitudeMessage | None:
        """The star-tracker message delivered (None: dropped)."""
        t = msg.t_ns
        q, valid = msg.q_LB, msg.valid
        arcsec = math.pi / (180.0 * 3600.0)
        for s in self._active(t, SENSOR_KINDS, "star_tracker"):
            c = s.cfg
            if c.kind == "dropout":
                return None
            if c.kind == "flagged_invalid":
                valid = False
                continue
            if c.kind == "stuck":
                if s.held is None:
                    s.held = self._last_att if self._last_att is not None else msg
                q = s.held.q_LB
                continue
            rotvec = self._vector(s, t, np.zeros(3), None, self.sensor_sigmas["star_tracker"] * arcsec, unit=arcsec)
            q = rotated_by_rotvec(q, rotvec)
        self._last_att = msg
        return replace(msg, q_LB=np.asarray(q, float), valid=valid)

    # ------------------------------------------------------------------ camera
    def frame_delivered(self, t_ns: int) -> bool:
        """Whether the camera frame at ``t_ns`` reaches the flight software (one draw per active frame_drop)."""
        delivered = True
        for s in self._active(t_ns, ("camera_blackout", "frame_drop")):
            if s.cfg.kind == "camera_blackout":
                delivered = False
            elif s.rng.random() < s.cfg.probability:  # drawn for every frame, so the stream is the frame count's
                delivered = False
        return delivered

    def exposure_gain(self, t_ns: int) -> float:
        """The product of the active exposure gains (1.0: none)."""
        g = 1.0
        for s in self._active(t_ns, ("exposure",)):
            g *= s.cfg.gain
        return g

    # ------------------------------------------------------------------ engine and computer
    def thrust_command(self, t_ns: int, thrust_cmd_N: float) -> float:
        """The thrust command the engine acts on (a stuck throttle holds the one at its trigger)."""
        for s in self._active(t_ns, ("stuck_throttle",)):
            if s.held is None:
                s.held = float(thrust_cmd_N)
            return s.held if thrust_cmd_N > 0.0 else thrust_cmd_N
        return thrust_cmd_N

    def thrust_gain(self, t_ns: int) -> float:
        """Factor on the delivered thrust (1.0: no loss)."""
        g = 1.0
        for s in self._active(t_ns, ("thrust_loss",)):
            g *= 1.0 - s.cfg.fraction
        return g

    def fault_torque_B_Nm(self, t_ns: int) -> np.ndarray | None:
        """The off-axis torque of an active thrust loss while the engine fires, (3,) [N m]; None: none."""
        tau = None
        for s in self._active(t_ns, ("thrust_loss",)):
            tau = np.asarray(s.cfg.torque_B_Nm, float) + (0.0 if tau is None else tau)
        return tau

    def thrust_direction_B(self, t_ns: int) -> tuple[float, float] | None:
        """(angle_deg, azimuth_deg) of an active misalignment; None: none."""
        for s in self._active(t_ns, ("misalignment",)):
            return s.cfg.angle_deg, s.cfg.azimuth_deg
        return None

    def rcs_fault(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The active RCS faults: per body axis, the factor on a positive and on a negative delivered torque,
        and the stuck-on torque as a fraction of the RCS limit, ((3,), (3,), (3,)); None: none active."""
        active = list(self._active(t_ns, ("rcs_loss", "rcs_stuck_on")))
        if not active:
            return None
        pos, neg, stuck = np.ones(3), np.ones(3), np.zeros(3)
        for s in active:
            c = s.cfg
            if c.kind == "rcs_loss":
                for a in c.axes:
                    if c.direction in ("both", "positive"):
                        pos[a] *= 1.0 - c.fraction
                    if c.direction in ("both", "negative"):
                        neg[a] *= 1.0 - c.fraction
            else:
                stuck[c.axis] += c.sign * c.fraction
        return pos, neg, stuck

    def computer_down(self, t_ns: int) -> bool:
        """Whether the flight computer is down at ``t_ns``."""
        return any(True for _ in self._active(t_ns, ("computer_reset",)))


def terrain_step_heights(height_m: np.ndarray, size_m: float, steps: list[TerrainStep]) -> np.ndarray:
    """A height grid (south-up, centred on the origin) with every terrain step added, float32."""
    n = height_m.shape[0]
    c = (np.arange(n) - (n - 1) / 2) * (size_m / (n - 1))
    X, Y = np.meshgrid(c, c)  # rows: y (south to north), columns: x
    h = height_m.astype(np.float64).copy()
    for st in steps:
        inside = np.hypot(X - st.center_xy_m[0], Y - st.center_xy_m[1]) <= st.radius_m
        h[inside] += st.height_m
    return h.astype(np.float32)
