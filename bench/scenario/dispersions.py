"""Dispersions and per-case seeds for Monte Carlo campaigns.

A scenario's ``[dispersions]`` table maps a dotted field path to a
distribution (an array's entries by index: ``faults.0.value``). A single ``landbench run`` flies the nominal scenario; a
campaign draws each case's values and applies them **to the scenario object
itself** (then re-validates it), so the truth (world, sensors) sees the
dispersed values and a case is reproduced by its own resolved
``scenario.toml``. The flight software does not: before drawing, the nominal
lander, camera and sensors are pinned into ``knowledge.lander``,
``knowledge.camera`` and ``knowledge.sensors``, which the flight software is
built from (the sensors' periods and the altimeter's range); the filter's
noise model is the sensors' specification (``estimator``), never the drawn
sensor values.

Distributions (``dist``):
    * ``normal``: nominal + N(0, sigma); ``sigma`` scalar or per component.
    * ``truncnorm``: nominal + N(0, sigma) truncated to [low, high] (offsets
      from nominal, in sigmas' units), by scipy.stats.truncnorm.
    * ``uniform``: U(low, high), absolute values.
    * ``integers``: an integer in [low, high], uniformly (e.g. terrain seeds).
    * ``choice``: one of ``values``, uniformly.
Integer fields (e.g. ``terrain.seed``) take rounded draws that stay inside
their bounds; a ``uniform`` over one draws each whole number between its
bounds alike.

Streams: paths are drawn in sorted order from the case's "dispersions" stream,
so adding a path reshuffles the draws of the paths after it. A path with
``own_stream = true`` draws from its own child of that stream instead (keyed on
the path's CRC-32), so it can be added to or removed from a table without
changing any other path's draws (the realism dispersions of issue 17 are drawn
so, and a campaign with them pairs case by case with one without).

Seeds: ``SeedSequence(campaign_seed).spawn(n)`` gives one stream per case; a
case's scenario seed is drawn from its stream, and inside the case every
component (terrain, sensors, dispersions, ...) has its own child stream
(:mod:`bench.scenario.seeding`). A case's result therefore never depends on the
number of workers or the order in which cases run.
"""

from __future__ import annotations

import copy
import zlib

from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bench.scenario.seeding import component_rng, component_seed

SEED_BITS = 63  # case seeds fit TOML's signed 64-bit integers
# Truth sections whose nominal values the flight software keeps (scenario.knowledge.<part>).
PINNED_KNOWLEDGE = ("lander", "camera", "sensors")


class _Dist(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    own_stream: bool = Field(
        False,
        description="draw from this path's own child stream instead of the shared one: adding or removing it "
                    "leaves every other path's draws unchanged",
    )


def _check_sigma(sigma: float | list[float], dist: str, zero_ok: bool) -> None:
    s = np.asarray(sigma, float)
    if np.any(s < 0.0) or (not zero_ok and np.any(s == 0.0)):
        raise ValueError(f"{dist} sigma = {sigma} must be {'>= 0' if zero_ok else '> 0'}"
                         + ("" if zero_ok else " (the bounds are in sigmas)"))


class Normal(_Dist):
    """Nominal plus a Gaussian offset."""

    dist: Literal["normal"]
    sigma: float | list[float] = Field(description="1-sigma of the offset (scalar or per component), >= 0 (0: a "
                                       "component not dispersed)")

    @model_validator(mode="after")
    def _not_negative(self) -> "Normal":
        _check_sigma(self.sigma, "normal", zero_ok=True)
        return self


class TruncNormal(_Dist):
    """Nominal plus a Gaussian offset truncated to [low, high] (offset units)."""

    dist: Literal["truncnorm"]
    sigma: float | list[float] = Field(description="1-sigma of the offset (scalar or per component), > 0")
    low: float | list[float] = Field(description="lowest offset from nominal")
    high: float | list[float] = Field(description="highest offset from nominal")

    @model_validator(mode="after")
    def _ordered(self) -> "TruncNormal":
        _check_sigma(self.sigma, "truncnorm", zero_ok=False)
        if np.any(np.asarray(self.low, float) >= np.asarray(self.high, float)):
            raise ValueError(f"truncnorm low = {self.low} must be below high = {self.high}")
        return self


class Uniform(_Dist):
    """Uniform between absolute bounds."""

    dist: Literal["uniform"]
    low: float | list[float] = Field(description="lower bound (absolute)")
    high: float | list[float] = Field(description="upper bound (absolute)")

    @model_validator(mode="after")
    def _ordered(self) -> "Uniform":
        if np.any(np.asarray(self.low, float) > np.asarray(self.high, float)):
            raise ValueError(f"uniform low = {self.low} must not exceed high = {self.high}")
        with np.errstate(over="ignore"):
            span = np.asarray(self.high, float) - np.asarray(self.low, float)
        if not np.all(np.isfinite(span)):  # NumPy cannot draw over a span beyond the largest float
            raise ValueError(f"uniform from low = {self.low} to high = {self.high} spans more than the largest "
                             f"float; allowed: high - low below {np.finfo(float).max:.3g}")
        return self


class Integers(_Dist):
    """A uniformly drawn integer in [low, high] (e.g. a terrain seed; the nominal may be unset)."""

    dist: Literal["integers"]
    low: int = Field(ge=0, description="smallest value")
    high: int = Field(description="largest value")

    @model_validator(mode="after")
    def _ordered(self) -> "Integers":
        if self.low > self.high:
            raise ValueError(f"integers low = {self.low} must not exceed high = {self.high}")
        return self


class Choice(_Dist):
    """One of a list of values."""

    dist: Literal["choice"]
    values: list[Any] = Field(min_length=1, description="the values to choose from")


Dispersion = Annotated[Union[Normal, TruncNormal, Uniform, Integers, Choice], Field(discriminator="dist")]


def _step(node: Any, part: str, path: str) -> Any:
    """One part of a dotted path: a table's key, or an array's index (``faults.0.value``)."""
    if isinstance(node, dict) and part in node:
        return node[part]
    if isinstance(node, list) and part.isdigit() and int(part) < len(node):
        return node[int(part)]
    raise KeyError(path)


def _get(data: dict[str, Any], path: str) -> Any:
    node: Any = data
    for part in path.split("."):
        node = _step(node, part, path)
    return node


def _set(data: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split(".")
    node: Any = data
    for part in parts[:-1]:
        node = _step(node, part, path)
    node[int(parts[-1]) if isinstance(node, list) else parts[-1]] = value


def check_dispersion_paths(scenario_data: dict[str, Any], dispersions: dict[str, Any]) -> None:
    """Every dispersed path must name a numeric field of the scenario.

    Raises:
        ValueError: One line naming the path, what it holds and what is allowed.
    """
    for path, spec in dispersions.items():
        try:
            nominal = _get(scenario_data, path)
        except KeyError:
            parts = path.split(".")
            if parts[0] == "knowledge" and len(parts) > 2 and parts[1] in PINNED_KNOWLEDGE:
                raise ValueError(
                    f"dispersions.'{path}': knowledge.{parts[1]} is the nominal {parts[1]} the campaign pins for "
                    "the flight software, not drawn; disperse what the flight software gets wrong with the "
                    "knowledge errors (e.g. 'knowledge.dry_mass_error_kg', 'knowledge.thrust_calibration_error_frac')"
                ) from None
            raise ValueError(
                f"dispersions.'{path}': no such scenario field; allowed: a dotted path to a numeric field, "
                "e.g. 'initial.r_BL_L_m' or 'lander.dry_mass_kg'"
            ) from None
        if isinstance(nominal, dict):  # a table drawn whole would replace the fields the other paths draw into
            example = next(iter(nominal), "FIELD")
            raise ValueError(f"dispersions.'{path}' is a table; disperse its fields one by one (e.g. "
                             f"'{path}.{example}')")
        if path.split(".")[0] == "propellant":
            raise ValueError(f"dispersions.'{path}': the propellant budget sets the nominal load before a campaign "
                             f"draws, so a draw of it would change nothing; disperse the loaded propellant, "
                             f"'lander.propellant_kg'")
        if spec.dist in ("choice", "integers"):
            continue  # absolute draws: the nominal may be anything, even unset
        values = nominal if isinstance(nominal, (list, tuple)) else [nominal]
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        if not numeric:
            raise ValueError(
                f"dispersions.'{path}' = {nominal!r} is not numeric; allowed: numeric fields, or dist = 'choice'"
            )
        n = len(values)
        for name in ("sigma", "low", "high"):
            v = getattr(spec, name, None)
            if isinstance(v, list) and len(v) != n:
                raise ValueError(
                    f"dispersions.'{path}'.{name} has {len(v)} components; the field has {n}"
                )
        if _is_integer(nominal) and spec.dist in ("uniform", "truncnorm"):
            lo, hi = _integer_bounds(spec, np.asarray(values, float))
            if np.any(np.abs(np.concatenate([np.ravel(lo), np.ravel(hi)])) >= 2.0**63):
                raise ValueError(f"dispersions.'{path}': bounds beyond the 64-bit whole numbers the field holds; "
                                 f"allowed: bounds within +-9.2e18")
            if np.any(lo > hi):
                raise ValueError(f"dispersions.'{path}': no whole number lies between its bounds (the field holds "
                                 f"whole numbers); allowed: bounds around at least one, or dist = 'integers'")


def _draw(spec: Any, nominal: Any, rng: np.random.Generator) -> Any:
    vector = isinstance(nominal, (list, tuple))
    nom = np.atleast_1d(np.asarray(nominal, dtype=float)) if spec.dist not in ("choice", "integers") else None
    if spec.dist == "choice":
        return spec.values[int(rng.integers(len(spec.values)))]
    if spec.dist == "integers":
        return int(rng.integers(spec.low, spec.high, endpoint=True))
    shape, integer = nom.shape, _is_integer(nominal)
    if spec.dist == "normal":
        value = nom + rng.normal(0.0, 1.0, shape) * np.broadcast_to(np.asarray(spec.sigma, float), shape)
    elif spec.dist == "truncnorm":
        sigma = np.broadcast_to(np.asarray(spec.sigma, float), shape)
        lo = np.broadcast_to(np.asarray(spec.low, float), shape) / sigma
        hi = np.broadcast_to(np.asarray(spec.high, float), shape) / sigma
        from scipy.stats import truncnorm  # here, not at import: scipy.stats costs every command about 0.6 s

        value = nom + sigma * truncnorm.rvs(lo, hi, size=shape, random_state=rng)
    elif integer:  # uniform over a field of whole numbers: each one in the bounds alike
        lo, hi = _integer_bounds(spec, nom)
        value = rng.integers(lo.astype(np.int64), hi.astype(np.int64), endpoint=True)
    else:  # uniform
        value = rng.uniform(np.broadcast_to(np.asarray(spec.low, float), shape),
                            np.broadcast_to(np.asarray(spec.high, float), shape))
    if integer:
        value = np.rint(value).astype(np.int64)
        if spec.dist == "truncnorm":  # rounding may not leave the bounds: the nearest whole number inside them
            value = np.clip(value, *(b.astype(np.int64) for b in _integer_bounds(spec, nom)))
    out = [v.item() for v in value]
    return out if vector else out[0]


def _is_integer(nominal: Any) -> bool:
    """Does the field (a number or a vector of them) hold whole numbers (its draws are rounded)?"""
    values = nominal if isinstance(nominal, (list, tuple)) else [nominal]
    return all(isinstance(v, int) and not isinstance(v, bool) for v in values)


def _integer_bounds(spec: Any, nom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The whole numbers a ``uniform`` (absolute bounds) or ``truncnorm`` (offsets from ``nom``) draw may take:
    the smallest and largest inside its bounds, per component."""
    shape = np.shape(nom)
    lo = np.broadcast_to(np.asarray(spec.low, float), shape)
    hi = np.broadcast_to(np.asarray(spec.high, float), shape)
    if spec.dist == "truncnorm":
        lo, hi = nom + lo, nom + hi
    return np.ceil(lo), np.floor(hi)


def draw_dispersions(scenario, rng: np.random.Generator | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Draw every dispersion into a plain dict of the scenario (not validated).

    This module does not import the scenario schema (the schema imports this
    module): :func:`bench.scenario.apply_dispersions` calls this and
    re-validates the dict into a Scenario.

    Args:
        scenario: The nominal scenario (its ``dispersions`` table says what to draw).
        rng: The draws' generator; by default the scenario's own "dispersions" stream.

    Returns:
        (the dispersed scenario as a dict, {path: drawn value}). The dict
        keeps the seed and has an empty ``dispersions`` table (it is one case).
    """
    rng = component_rng(scenario.seed, "dispersions") if rng is None else rng
    data = scenario.model_dump(mode="json")
    # The flight software keeps the nominal vehicle, camera and sensors: pin them before the truth is drawn.
    knowledge = data["knowledge"]
    for part in PINNED_KNOWLEDGE:
        if knowledge[part] is None:
            knowledge[part] = copy.deepcopy(data[part])  # a copy: the draws below change data[part] in place
    drawn: dict[str, Any] = {}
    for path in sorted(scenario.dispersions):  # sorted: the draws do not depend on the table's order
        spec = scenario.dispersions[path]
        value = _draw(spec, _get(data, path), own_stream_rng(scenario.seed, path) if spec.own_stream else rng)
        _set(data, path, value)
        drawn[path] = value
    data["dispersions"] = {}
    return data, drawn


def own_stream_rng(seed: int, path: str) -> np.random.Generator:
    """The own stream of a dispersed path (``own_stream = true``): a child of the case's "dispersions" stream."""
    base = component_seed(seed, "dispersions")
    return np.random.Generator(np.random.PCG64(
        np.random.SeedSequence(base.entropy, spawn_key=(*base.spawn_key, zlib.crc32(path.encode("utf-8"))))))


def case_seeds(campaign_seed: int, n_cases: int) -> list[int]:
    """One seed per case, from ``SeedSequence(campaign_seed).spawn(n_cases)``.

    A case's seed depends only on (campaign seed, case index), never on how
    many cases or workers there are.
    """
    children = np.random.SeedSequence(campaign_seed).spawn(n_cases)
    return [int(c.generate_state(1, np.uint64)[0] >> (64 - SEED_BITS)) for c in children]
