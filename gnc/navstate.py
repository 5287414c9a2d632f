"""The navigation state: what navigation hands to guidance and control.

Ports:
    Producer: the navigation filter (:meth:`gnc.estimator.NavFilter.nav_state`),
        or the bench's truth oracle with ``nav = "truth"``, once per control period.
    Consumers: :mod:`gnc.guidance` and :mod:`gnc.control`, at the control rate
        (default 50 Hz).

Conventions (see :mod:`gnc.messages`): L is the landing frame (origin at the
landing target on the surface, x east, y north, z up); B is the body frame
(+z is the thrust axis); quaternions are scalar-first ``[w, x, y, z]`` and
``q_LB`` rotates B vectors into L.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class NavState:
    """Navigated vehicle state at one instant.

    Attributes:
        t_ns: Time of validity, integer nanoseconds since scenario start.
        r_BL_L: Position of the body origin relative to the landing-frame
            origin, in L, (3,) [m].
        v_BL_L: Velocity of the body origin relative to L, in L, (3,) [m/s].
        q_LB: Attitude quaternion rotating B vectors into L, (4,) scalar-first.
        omega_B: Angular rate of B relative to L, in B, (3,) [rad/s].
        mass_kg: Current vehicle mass, dry plus remaining propellant [kg].
        P: Optional position/velocity error covariance from the estimator,
            (6, 6), in the order of ``r_BL_L`` then ``v_BL_L``; None for perfect
            navigation.
    """

    t_ns: int
    r_BL_L: np.ndarray
    v_BL_L: np.ndarray
    q_LB: np.ndarray
    omega_B: np.ndarray
    mass_kg: float
    P: np.ndarray | None = None

    def is_finite(self) -> bool:
        """True when every kinematic field and the mass are finite (the covariance is not checked)."""
        arrays = (self.r_BL_L, self.v_BL_L, self.q_LB, self.omega_B)
        return bool(all(np.all(np.isfinite(np.asarray(a, float))) for a in arrays) and np.isfinite(self.mass_kg))
