"""A guidance law whose command comes from outside the flight software: an agent (the Gymnasium environment).

Ports (:class:`ExternalGuidance`, a :class:`gnc.guidance.GuidanceLaw`):
    Inputs: :class:`gnc.navstate.NavState` and the :class:`gnc.guidance.LandingTarget`,
        as every law; the command is the agent's answer to that state.
    Output: :class:`gnc.guidance.GuidanceCommand` with the agent's total
        acceleration, capped to the thrust and tilt limits as any law's.
    Rate: control rate; each call hands the navigation state to the agent over
        a :class:`Channel` and blocks until the agent answers.

The law sees what every law sees and nothing more (the flight software's
navigation state, never truth). The channel is found by its id, the law's
``[guidance.options] channel``; :func:`open_channel` registers one.
"""

from __future__ import annotations

import itertools
import queue
import threading
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.guidance import PHASE_APPROACH, PHASE_TERMINAL, GuidanceCommand, GuidanceLaw, LandingTarget, cap_acceleration_L
from gnc.navstate import NavState

_CHANNELS: dict[str, "Channel"] = {}
_IDS = itertools.count()
_LOCK = threading.Lock()


class EpisodeAborted(Exception):
    """Raised inside the flight software when the agent abandons the episode (reset or close)."""


class Channel:
    """Two one-slot mailboxes between the flight software (one thread) and the agent (another).

    ``to_agent`` carries ``("nav", (NavState, phase))`` and finally ``("done", payload)``;
    ``to_flight`` carries an acceleration (3,) or ``None`` (abort).
    """

    def __init__(self, channel_id: str):
        self.id = channel_id
        self.to_agent: queue.Queue = queue.Queue(maxsize=1)
        self.to_flight: queue.Queue = queue.Queue(maxsize=1)
        self.answering = True  # False once the engine is cut: no more questions to the agent

    def close(self) -> None:
        with _LOCK:
            _CHANNELS.pop(self.id, None)


def open_channel() -> Channel:
    """A new registered channel (its ``id`` goes in ``[guidance.options] channel``)."""
    with _LOCK:
        ch = Channel(f"ch{next(_IDS)}")
        _CHANNELS[ch.id] = ch
        return ch


class ExternalOptions(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    channel: str = Field(..., description="id of the channel to the agent (gnc.external.open_channel)")


class ExternalGuidance(GuidanceLaw):
    """The agent's total acceleration, capped to the limits; phase by the estimated height above the gate.

    Ports: as :class:`gnc.guidance.GuidanceLaw`. The phase it reports is
    ``approach`` above the gate altitude and ``terminal`` below (by the
    navigated altitude); the agent decides everything else.
    """

    name = "external"
    Options = ExternalOptions

    def __init__(self, cfg, limits):
        super().__init__(cfg, limits)
        with _LOCK:
            ch = _CHANNELS.get(self.options.channel)
        if ch is None:
            raise ValueError(f"guidance.options.channel = {self.options.channel!r}: no such open channel")
        self.channel = ch

    def accel_L(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102 (not used: update is overridden)
        raise NotImplementedError("ExternalGuidance takes its command from the agent")

    def coeffs(self, r_L, v_L, r_f_L, v_f_L, t_go_s):  # noqa: D102
        raise NotImplementedError("ExternalGuidance takes its command from the agent")

    def update(self, nav: NavState, target: LandingTarget) -> GuidanceCommand:
        t_ns = int(nav.t_ns)
        r = np.asarray(nav.r_BL_L, float)
        m = float(nav.mass_kg)
        height = float(r[2] - np.asarray(target.r_L, float)[2])
        phase = PHASE_APPROACH if height > self.cfg.gate_altitude_m else PHASE_TERMINAL
        if not self.channel.answering:  # engine cut at touchdown: the command no longer matters
            return GuidanceCommand(t_ns, self.g_L.copy(), phase, 0.0, valid=False)
        self.channel.to_agent.put(("nav", (nav, phase)))
        a: Any = self.channel.to_flight.get()
        if a is None:
            raise EpisodeAborted("the agent ended the episode")
        a = np.asarray(a, float)
        if not (np.all(np.isfinite(r)) and np.isfinite(m) and m > 0.0 and np.all(np.isfinite(a))):
            return GuidanceCommand(t_ns, np.zeros(3), phase, float("nan"), valid=False)
        a_capped, saturated = cap_acceleration_L(a, self.g_L, m, self.limits, height)
        return GuidanceCommand(t_ns, a_capped, phase, float("nan"), saturated=saturated, valid=True)
