"""Random streams: one ``SeedSequence`` per run, one child stream per component.

Every component draws only from its own ``numpy.random.Generator``; nothing
uses the global ``np.random``. Child streams are addressed by a fixed index
per component name (``spawn_key``), so adding a component later never
reshuffles the streams of the existing ones, and a component's draws never
depend on how much another component drew.
"""

from __future__ import annotations

import numpy as np

# Append-only: an entry's index is its stream identity.
COMPONENTS: tuple[str, ...] = (
    "terrain",
    "imu",
    "altimeter",
    "star_tracker",
    "camera",
    "dispersions",
    "estimator",
    "vision",
    "map",
    "faults",
    "lidar",
    "tracker",
)


def component_rng(seed: int, component: str) -> np.random.Generator:
    """The generator of one component of the run with this seed.

    Args:
        seed: The scenario's seed (for the terrain: the terrain seed).
        component: A name from :data:`COMPONENTS`.

    Returns:
        A generator that depends only on (seed, component).
    """
    return np.random.default_rng(component_seed(seed, component))


def component_seed(seed: int, component: str) -> np.random.SeedSequence:
    """The ``SeedSequence`` behind :func:`component_rng` (for per-item child streams of a component)."""
    try:
        index = COMPONENTS.index(component)
    except ValueError:
        raise ValueError(f"unknown random-stream component {component!r}; known: {', '.join(COMPONENTS)}") from None
    return np.random.SeedSequence(seed, spawn_key=(index,))
