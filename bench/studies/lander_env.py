"""Gymnasium environment ``landbench/Lander-v0``: an agent is the guidance law of the closed loop.

Importing this module registers the id: ``import bench.studies.lander_env;
gymnasium.make("landbench/Lander-v0")`` (or ``gymnasium.make("bench.studies.lander_env:landbench/Lander-v0")``).
Needs the optional extra ``landbench[gym]``.

The episode is one landing of :func:`bench.sim.run.run`, unchanged: truth
world, sensors, navigation filter and controller. The agent takes the place of
the guidance law (:class:`gnc.external.ExternalGuidance`, fed over a channel
from the loop's thread), so it gets exactly what a law gets and nothing more.

Observation (``Dict``), at every control tick (default 50 Hz), from the flight
software's own navigation state, never truth (with ``nav="truth"`` the
navigation state is the truth, the bench's oracle for first studies):
    ``t_s`` (1,) [s]; ``r_BL_L_m`` (3,) [m] (landing frame: origin at the
    target, z up); ``v_BL_L_mps`` (3,) [m/s]; ``q_LB`` (4,) scalar-first;
    ``omega_B_radps`` (3,) [rad/s]; ``mass_kg`` (1,) (the flight software's
    propellant gauge); ``phase``: 0 above the gate altitude, 1 below it
    (by the estimate), 2 touched down (the last observation).
The camera is off (vision navigation needs rendered frames; an episode is
IMU + star tracker + altimeter).

Action: the commanded **total acceleration** in L, gravity included, (3,)
[m/s^2] in ``[-10, 10]``: the same convention as every guidance law
(:class:`gnc.guidance.GuidanceCommand`). It is capped to the thrust and
tilt limits (:func:`gnc.guidance.cap_acceleration_L`), then the controller
turns it into thrust and attitude. The engine is cut by the controller when
the legs touch; from then on actions are not asked for.

Reward (``RewardConfig``), built from the landing criteria, fuel and miss:
    every step: ``-fuel_per_kg`` times the propellant burnt in the step (truth);
    at the end: ``+landed_bonus`` if the outcome is ``landed`` else
    ``-crash_penalty``; ``-miss_per_m`` times the miss distance (touchdown
    only); ``-excess_speed_per_mps`` times the touchdown speeds beyond the
    criteria (vertical and horizontal).

``terminated``: the landing ended with touchdown (landed, hard landing, tipped
over), fuel exhaustion or divergence; ``truncated``: no touchdown by
``t_max_s`` (the scenario's ``sim.t_max_ns`` unless given). The episode's
outcome and summary are in ``info``.

Seeding: ``reset(seed=...)`` seeds the env's generator (Gymnasium's
``np_random``, a ``SeedSequence``-seeded PCG64); each episode's scenario seed
is drawn from it, and every random stream of the run (dispersions, sensor
noise, hand-over error) is spawned from that seed by
:mod:`bench.scenario.seeding`. Same seed, same episode. ``dispersed=True``
draws the scenario's ``[dispersions]`` for every episode (as a campaign case).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from bench.scenario import Scenario, apply_dispersions, load_scenario
from gnc.external import Channel, EpisodeAborted, open_channel

ENV_ID = "landbench/Lander-v0"
PHASES = {"approach": 0, "terminal": 1, "touchdown": 2}
ACCEL_BOUND_MPS2 = 10.0
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward (see the module docstring)."""

    fuel_per_kg: float = 0.1
    landed_bonus: float = 100.0
    crash_penalty: float = 100.0
    miss_per_m: float = 1.0
    excess_speed_per_mps: float = 20.0


class _Recorder:
    """The loop's recorder hook: the contact message and the truth at each control tick (reward, touchdown)."""

    want_depth = False

    def __init__(self, channel: Channel):
        self.channel = channel
        self.propellant_kg: float | None = None
        self.touched = False

    def message(self, kind, msg) -> None:
        pass

    def camera_truth(self, t_ns, R_LC, r_CL_L, depth) -> None:
        pass

    def control_tick(self, t_ns, contact, truth, accel_bias_B) -> None:
        self.propellant_kg = float(truth.propellant_kg)
        if np.any(contact.legs):
            self.touched = True
            self.channel.answering = False


class LanderEnv(gym.Env):
    """One closed-loop landing per episode; the agent commands the acceleration at the control rate.

    Args:
        scenario: Base scenario (default: the bundled one) or None.
        overrides: ``--set``-style overrides applied to it.
        nav: ``"estimator"`` (the filter's estimate; default) or ``"truth"``.
        dispersed: Draw the scenario's dispersions every episode.
        t_max_s: Episode time limit [s] (None: the scenario's).
        reward: Reward weights.
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: Scenario | None = None, overrides: tuple[str, ...] | list[str] = (),
                 nav: str = "estimator", dispersed: bool = True, t_max_s: float | None = None,
                 reward: RewardConfig | None = None):
        if nav not in ("estimator", "truth"):
            raise ValueError(f"nav = {nav!r}; allowed: 'estimator' or 'truth'")
        sets = [*overrides, "camera.enabled=false", 'vision="off"', f'nav="{nav}"']
        if t_max_s is not None:
            if not (t_max_s > 0 and math.isfinite(t_max_s)):
                raise ValueError(f"t_max_s = {t_max_s}: must be finite and > 0 [s]")
            sets.append(f"sim.t_max_ns={int(round(t_max_s * NS_PER_S))}")
        if scenario is None:
            self.base = load_scenario(None, sets)
        else:
            from bench.scenario.schema import scenario_from_data
            from pathlib import Path

            self.base = scenario_from_data(scenario.model_dump(mode="json", exclude_none=True), Path.cwd(), sets)
        self.dispersed = dispersed
        self.reward_cfg = reward or RewardConfig()
        box = lambda n, lo=-np.inf, hi=np.inf: spaces.Box(lo, hi, (n,), np.float64)  # noqa: E731
        self.observation_space = spaces.Dict({
            "t_s": box(1, 0.0), "r_BL_L_m": box(3), "v_BL_L_mps": box(3), "q_LB": box(4, -1.0, 1.0),
            "omega_B_radps": box(3), "mass_kg": box(1, 0.0), "phase": spaces.Discrete(3),
        })
        self.action_space = spaces.Box(-ACCEL_BOUND_MPS2, ACCEL_BOUND_MPS2, (3,), np.float32)
        self._thread: threading.Thread | None = None
        self._channel: Channel | None = None
        self._result: dict[str, Any] = {}
        self._last_obs: dict[str, Any] | None = None
        self.scenario: Scenario | None = None

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _obs(nav, phase: str) -> dict[str, Any]:
        return {"t_s": np.array([nav.t_ns / NS_PER_S]), "r_BL_L_m": np.array(nav.r_BL_L, np.float64),
                "v_BL_L_mps": np.array(nav.v_BL_L, np.float64),
                "q_LB": np.clip(np.array(nav.q_LB, np.float64), -1.0, 1.0),
                "omega_B_radps": np.array(nav.omega_B, np.float64), "mass_kg": np.array([max(nav.mass_kg, 0.0)]),
                "phase": PHASES[phase]}

    def _stop(self) -> None:
        """Abandon the running episode (its thread ends with EpisodeAborted) and wait for it."""
        ch, th = self._channel, self._thread
        if th is not None and th.is_alive():
            ch.answering = False
            try:
                ch.to_flight.put_nowait(None)
            except Exception:  # noqa: BLE001 - the slot is full: the loop has not read the last action yet
                pass
            while th.is_alive():
                try:
                    ch.to_agent.get(timeout=0.05)  # unblock a loop waiting to hand over a state
                except Exception:  # noqa: BLE001
                    pass
                try:
                    ch.to_flight.put_nowait(None)
                except Exception:  # noqa: BLE001
                    pass
            th.join()
        if ch is not None:
            ch.close()
        self._thread = self._channel = None

    def _episode(self, scenario: Scenario, ch: Channel, recorder: _Recorder) -> None:
        from bench.sim.run import run

        try:
            res = run(scenario, recorder=recorder)
            ch.to_agent.put(("done", res.summary))
        except EpisodeAborted:
            pass
        except Exception as exc:  # noqa: BLE001 - handed to the agent's thread, raised there
            ch.to_agent.put(("error", exc))

    def _next(self) -> tuple[str, Any]:
        return self._channel.to_agent.get()

    # ------------------------------------------------------------------ the API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._stop()
        episode_seed = int(self.np_random.integers(0, 2**31 - 1))
        sc = self.base.model_copy(update={"seed": episode_seed})
        if self.dispersed and sc.dispersions:
            sc, _ = apply_dispersions(sc)
        ch = open_channel()
        sc = sc.model_copy(update={"guidance": sc.guidance.model_copy(
            update={"law": "gnc.external:ExternalGuidance", "options": {"channel": ch.id}})})
        self.scenario = sc
        self._channel = ch
        self._recorder = _Recorder(ch)
        self._propellant_kg = None
        self._thread = threading.Thread(target=self._episode, args=(sc, ch, self._recorder), daemon=True)
        self._thread.start()
        kind, payload = self._next()
        if kind == "error":
            raise payload
        if kind != "nav":
            raise RuntimeError(f"the episode ended before its first control tick ({payload.get('outcome')})")
        self._last_obs = self._obs(payload[0], payload[1])
        self._propellant_kg = self._recorder.propellant_kg
        return self._last_obs, {"seed": episode_seed}

    def step(self, action):
        if self._thread is None:
            raise RuntimeError("call reset() before step()")
        a = np.clip(np.asarray(action, np.float64).reshape(3), -ACCEL_BOUND_MPS2, ACCEL_BOUND_MPS2)
        self._channel.to_flight.put(a)
        kind, payload = self._next()
        cfg = self.reward_cfg
        prop = self._recorder.propellant_kg
        reward = -cfg.fuel_per_kg * max((self._propellant_kg or prop) - prop, 0.0) if prop is not None else 0.0
        self._propellant_kg = prop
        if kind == "nav":
            self._last_obs = self._obs(*payload)
            return self._last_obs, float(reward), False, False, {}
        if kind == "error":
            self._thread = None
            raise payload
        summary = payload
        self._thread.join()
        self._channel.close()
        self._thread = self._channel = None
        reward += self._final_reward(summary)
        obs = dict(self._last_obs)
        if summary["touchdown"]["t_s"] is not None:
            obs["phase"] = PHASES["touchdown"]
        truncated = summary["outcome"] == "timeout"
        info = {"outcome": summary["outcome"], "landed": summary["landed"], "summary": summary}
        return obs, float(reward), not truncated, truncated, info

    def _final_reward(self, summary: dict[str, Any]) -> float:
        cfg, crit = self.reward_cfg, summary["criteria"]
        r = cfg.landed_bonus if summary["landed"] else -cfg.crash_penalty
        td = summary["touchdown"]
        if td["t_s"] is not None:
            r -= cfg.miss_per_m * td["miss_distance_m"]
            r -= cfg.excess_speed_per_mps * (max(td["v_vertical_mps"] - crit["v_vertical_max_mps"], 0.0)
                                             + max(td["v_horizontal_mps"] - crit["v_horizontal_max_mps"], 0.0))
        return float(r)

    def close(self) -> None:
        self._stop()
        super().close()


if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="bench.studies.lander_env:LanderEnv")
