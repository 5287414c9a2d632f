"""G-FOLD: fuel-optimal powered descent to the gate by lossless convexification (``guidance.law = "gfold"``).

Ports (:class:`GfoldGuidance`, a :class:`gnc.guidance.GuidanceLaw`):
    Inputs: :class:`gnc.navstate.NavState` (time, position, velocity, gauged
        mass) and the :class:`gnc.guidance.LandingTarget`; never truth.
    Output: :class:`gnc.guidance.GuidanceCommand` (total acceleration in L).
    Rate: control rate (default 50 Hz); the optimal path is solved at the first
        call (hand-over) and re-solved every ``resolve_period_s`` while more
        than ``resolve_min_t_go_s`` remain, and tracked in between.

The problem (Açıkmeşe & Ploen 2007, "Convex programming approach to powered
descent guidance for Mars landing"; Blackmore, Açıkmeşe & Scharf 2010,
"Minimum-landing-error powered-descent guidance for Mars landing using convex
optimization", problem 4 with the log-mass change of variables): from the
navigated state to the gate (``gate_altitude_m`` above the target, straight
down at ``terminal_descent_rate_mps``, as the other laws), over ``N`` equal
intervals of a final time ``t_f``, with ``u = T/m`` (thrust acceleration) and
``sigma`` (its slack) piecewise constant and ``z = ln m``::

    maximise z_N                          (the least propellant)
    v_{k+1} = v_k + dt (u_k + g),  r_{k+1} = r_k + dt v_k + dt^2/2 (u_k + g)
    z_{k+1} = z_k - dt sigma_k / (Isp g0)
    ||u_k|| <= sigma_k                    (the lossless relaxation of ||T|| = m sigma)
    rho1 e^-z0_k (1 - dz + dz^2/2) <= sigma_k <= rho2 e^-z0_k (1 - dz),   dz = z_k - z0_k
    u_k,z >= cos(theta_k) sigma_k         (tilt limit)
    r_k,z - z_t >= tan(glide_slope) ||r_k,xy - r_t,xy||     (glide-slope cone, apex at the target)
    r_0, v_0, z_0 = the navigated state; r_N, v_N = the gate

with ``z0_k = ln(m_0 - rho2 t_k / (Isp g0))`` (the Taylor point: the least mass
possible at ``t_k``). ``rho1``, ``rho2`` and ``theta`` carry the same planning
margins as the polynomial laws (``plan_thrust_min_frac * thrust_min``,
``plan_thrust_max_frac * thrust_max``, ``plan_tilt_frac`` times the tilt
limit), so the fuel comparison is between laws held to the same limits. The
tilt limit depends on altitude, which is a decision variable; each node's
limit is taken at a reference altitude (a straight line to the gate at the
first pass, then the previous solution's), and the hand-over solve is done
again (at most ``TILT_PASSES`` times, the reference lowered to the path's
altitude where it is lower) while the path breaks the limit at its own
altitudes. The final time is free:
a coarse scan around the polynomial planner's time to go, then a golden-section
search (fuel is unimodal in ``t_f`` over the feasible range; Blackmore et al.).
Re-solves keep the planned arrival time (one solve); only if that is
infeasible is the final time searched again.

Tracking: between solves the law flies the solution's acceleration plus a
PD on the solution's position and velocity (natural frequency
``tracking_bandwidth_radps``, damping 1), then the terminal phase from the
gate as the other laws. Failures (solver error, infeasible, inaccurate,
time limit) are counted; if the hand-over solve fails the law falls back to
ZEM/ZEV for the rest of the descent; a failed re-solve keeps tracking the
last solution. Every solve runs under ``solve_time_limit_s`` (the solver's own
time limit, and the search stops when the budget is spent), so it never
hangs.

cvxpy and a conic solver (Clarabel by default, ECOS) are the optional extra
``landbench[opt]``; they are imported when the law is built.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gnc.guidance import (
    guidance_inputs,
    NS_PER_S,
    PHASE_APPROACH,
    PHASE_TERMINAL,
    GATE_FLOOR_M,
    GuidanceCommand,
    LandingTarget,
    ZemZevGuidance,
    cap_acceleration_L,
)
from gnc.navstate import NavState

G0_MPS2 = 9.80665
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
TILT_PASSES = 5  # solves per final time at most, while the path breaks the tilt limit at its own altitudes
TILT_TOL_RAD = 1e-3


def cvxpy_available() -> bool:
    """Is the optional extra (cvxpy with Clarabel or ECOS) installed?"""
    import importlib.util

    return importlib.util.find_spec("cvxpy") is not None


RESOLVE_HINT_MIN_S = 0.5  # a re-solve keeps the time left as its final time only above this [s]


class GfoldOptions(BaseModel):
    """``[guidance.options]`` of ``guidance.law = "gfold"``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    nodes: int = Field(30, ge=8, le=200, description="intervals of the discretised path [-]")
    glide_slope_deg: float = Field(
        5.0, ge=0.0, lt=89.0, description="minimum elevation of the vehicle seen from the target [deg] (0: no cone)"
    )
    resolve_period_s: float = Field(2.0, gt=0.0, description="re-solve interval while tracking [s]")
    resolve_min_t_go_s: float = Field(6.0, ge=0.0, description="no re-solve with less than this to the gate [s]")
    solve_time_limit_s: float = Field(2.0, gt=0.0, description="wall-clock budget of one solve, search included [s]")
    tracking_bandwidth_radps: float = Field(
        0.5, ge=0.0, le=5.0, description="natural frequency of the PD on the solution's path [rad/s]"
    )
    t_f_tolerance_s: float = Field(0.25, gt=0.0, description="final-time search resolution [s]")
    solver: Literal["CLARABEL", "ECOS"] = Field("CLARABEL", description="conic solver behind cvxpy")


class GfoldSolution:
    """One solved path: node times from its start, and the nodes.

    Attributes:
        t0_ns: Time of the state it starts from [ns].
        t_f_s: Final time (to the gate) [s].
        r_L: Positions, (N + 1, 3) [m]; v_L: velocities, (N + 1, 3) [m/s];
        u_L: thrust accelerations per interval, (N, 3) [m/s^2];
        fuel_kg: Propellant of the path [kg]; m_kg: mass at the nodes, (N + 1,) [kg].
    """

    def __init__(self, t0_ns: int, t_f_s: float, r_L: np.ndarray, v_L: np.ndarray, u_L: np.ndarray, fuel_kg: float,
                 m_kg: np.ndarray | None = None):
        self.t0_ns, self.t_f_s, self.m_kg = t0_ns, t_f_s, m_kg
        self.r_L, self.v_L, self.u_L, self.fuel_kg = r_L, v_L, u_L, fuel_kg
        self.dt_s = t_f_s / u_L.shape[0]

    def reference(self, s: float, g_L: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and thrust acceleration at ``s`` seconds after the start (clamped to the path)."""
        n = self.u_L.shape[0]
        s = min(max(s, 0.0), self.t_f_s)
        k = min(int(s / self.dt_s), n - 1)
        tau = s - k * self.dt_s
        a = self.u_L[k] + g_L
        return self.r_L[k] + self.v_L[k] * tau + 0.5 * a * tau * tau, self.v_L[k] + a * tau, self.u_L[k]


class GfoldProblem:
    """The fixed-final-time convex problem, built once with cvxpy parameters (DPP) and re-solved.

    Args:
        n: Intervals.
        g_L: Gravity (3,) [m/s^2].
        alpha: Mass flow per thrust, ``1 / (Isp g0)`` [s/m].
        rho1, rho2: Thrust bounds [N].
        glide_slope_deg: Cone angle (0: none).
        solver: "CLARABEL" or "ECOS".
    """

    def __init__(self, n: int, g_L: np.ndarray, alpha: float, rho1: float, rho2: float, glide_slope_deg: float,
                 solver: str = "CLARABEL"):
        import cvxpy as cp

        self.cp, self.n, self.g_L, self.alpha, self.rho1, self.rho2 = cp, n, np.asarray(g_L, float), alpha, rho1, rho2
        self.solver = solver
        self.r = cp.Variable((n + 1, 3))
        self.v = cp.Variable((n + 1, 3))
        self.z = cp.Variable(n + 1)
        self.u = cp.Variable((n, 3))
        self.sigma = cp.Variable(n)
        self.w = cp.Variable(n)  # z_k - z0_k
        self.p_r0 = cp.Parameter(3)
        self.p_v0 = cp.Parameter(3)
        self.p_z0 = cp.Parameter()  # ln m_0
        self.p_rf = cp.Parameter(3)
        self.p_vf = cp.Parameter(3)
        self.p_target = cp.Parameter(3)
        self.p_dt = cp.Parameter(nonneg=True)
        self.p_hdt2 = cp.Parameter(nonneg=True)  # dt^2 / 2
        self.p_zref = cp.Parameter(n)  # z0_k
        self.p_mu1 = cp.Parameter(n, nonneg=True)  # rho1 e^-z0_k
        self.p_mu2 = cp.Parameter(n, nonneg=True)  # rho2 e^-z0_k
        self.p_cos = cp.Parameter(n, nonneg=True)  # cos(tilt limit) per interval
        r, v, z, u, sigma, w = self.r, self.v, self.z, self.u, self.sigma, self.w
        ones = np.ones((n, 1))
        g_row = self.g_L[None, :]
        cons = [
            r[0] == self.p_r0, v[0] == self.p_v0, z[0] == self.p_z0,
            r[n] == self.p_rf, v[n] == self.p_vf,
            v[1:] == v[:-1] + self.p_dt * u + self.p_dt * (ones @ g_row),
            r[1:] == r[:-1] + self.p_dt * v[:-1] + self.p_hdt2 * u + self.p_hdt2 * (ones @ g_row),
            z[1:] == z[:-1] - alpha * self.p_dt * sigma,
            w == z[:-1] - self.p_zref,
            cp.norm(u, 2, axis=1) <= sigma,
            cp.multiply(self.p_mu1, 1.0 - w + 0.5 * cp.square(w)) <= sigma,
            sigma <= cp.multiply(self.p_mu2, 1.0 - w),
            u[:, 2] >= cp.multiply(self.p_cos, sigma),
        ]
        if glide_slope_deg > 0.0:
            tan_gs = math.tan(math.radians(glide_slope_deg))
            for k in range(n + 1):
                cons.append(tan_gs * cp.norm(r[k, :2] - self.p_target[:2]) <= r[k, 2] - self.p_target[2])
        self.problem = cp.Problem(cp.Maximize(z[n]), cons)
        # Compile the parametrised problem now (a few tenths of a second), not inside the first solve's time limit.
        for p in self.problem.parameters():
            p.value = np.ones(p.shape)
        self.problem.get_problem_data(solver, enforce_dpp=True)

    def solve(self, r0: np.ndarray, v0: np.ndarray, m0: float, r_f: np.ndarray, v_f: np.ndarray,
              target: np.ndarray, t_f: float, cos_tilt: np.ndarray, time_limit_s: float
              ) -> tuple[dict[str, np.ndarray] | None, str]:
        """Solve for one final time; returns (solution arrays or None, status)."""
        cp, n = self.cp, self.n
        dt = t_f / n
        t_k = dt * np.arange(n)
        m_low = m0 - self.alpha * self.rho2 * t_k
        if m_low[-1] <= 0.0:
            return None, "infeasible (mass)"
        z_ref = np.log(m_low)
        self.p_r0.value, self.p_v0.value, self.p_z0.value = r0, v0, math.log(m0)
        self.p_rf.value, self.p_vf.value, self.p_target.value = r_f, v_f, target
        self.p_dt.value, self.p_hdt2.value = dt, 0.5 * dt * dt
        self.p_zref.value = z_ref
        self.p_mu1.value = self.rho1 * np.exp(-z_ref)
        self.p_mu2.value = self.rho2 * np.exp(-z_ref)
        self.p_cos.value = np.asarray(cos_tilt, float)
        kwargs: dict[str, Any] = {}
        if self.solver == "CLARABEL":
            kwargs["time_limit"] = float(time_limit_s)
        else:
            kwargs["max_iters"] = 200
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # an inaccurate solution is reported by its status, not a warning
                self.problem.solve(solver=self.solver, **kwargs)
        except (cp.error.SolverError, ValueError, ArithmeticError) as exc:
            return None, f"solver error: {type(exc).__name__}"
        status = str(self.problem.status)
        if status != cp.OPTIMAL or self.z.value is None:
            return None, status
        return {"r": np.array(self.r.value), "v": np.array(self.v.value), "u": np.array(self.u.value),
                "z": np.array(self.z.value), "sigma": np.array(self.sigma.value)}, status


class GfoldGuidance(ZemZevGuidance):
    """Fuel-optimal powered descent (lossless convexification) to the gate; ZEM/ZEV as the fallback.

    Ports: as :class:`gnc.guidance.GuidanceLaw` (NavState + LandingTarget in,
    GuidanceCommand out, control rate). ``limits.isp_s`` must be given (the
    flight software's knowledge of the engine; :mod:`bench.sim.flight_build`
    passes it).
    """

    name = "gfold"
    Options = GfoldOptions

    def __init__(self, cfg, limits):
        if limits.isp_s is None:
            raise ValueError("guidance.law = 'gfold' needs the engine's specific impulse: limits.isp_s (the flight "
                             "software's knowledge; bench.sim.flight_build passes it)")
        super().__init__(cfg, limits)
        opt: GfoldOptions = self.options
        self.alpha = 1.0 / (limits.isp_s * G0_MPS2)
        self.rho1 = cfg.plan_thrust_min_frac * limits.thrust_min_N
        self.rho2 = cfg.plan_thrust_max_frac * limits.thrust_max_N
        self.problem = GfoldProblem(opt.nodes, self.g_L, self.alpha, self.rho1, self.rho2, opt.glide_slope_deg,
                                    opt.solver)
        self.n_solves = 0  # convex solves (each final time tried counts)
        self.n_failures = 0  # path solves (hand-over or re-solve) that gave no path
        self.solve_wall_s: list[float] = []  # wall time of each path solve, search included [s]
        self.failures: list[str] = []

    def set_limits(self, limits) -> None:
        """New thrust limits: the convex problem is rebuilt with them and the path solved again at the next step."""
        super().set_limits(limits)
        opt: GfoldOptions = self.options
        self.rho1 = self.cfg.plan_thrust_min_frac * limits.thrust_min_N
        self.rho2 = self.cfg.plan_thrust_max_frac * limits.thrust_max_N
        self.problem = GfoldProblem(opt.nodes, self.g_L, self.alpha, self.rho1, self.rho2, opt.glide_slope_deg,
                                    opt.solver)
        if self.phase == PHASE_APPROACH:
            self.solution = None

    def reset(self) -> None:
        super().reset()
        self.solution: GfoldSolution | None = None
        self.fallback = False
        self.planned_fuel_kg: float | None = None
        self._last_solve_ns = 0

    # -- statistics for the run summary
    def stats(self) -> dict[str, Any]:
        """What the law did: solves, failures, fallback, wall time (the run summary's ``guidance.law_stats``)."""
        w = self.solve_wall_s
        return {"solves": self.n_solves, "path_solves": len(w), "failures": self.n_failures,
                "fallback_zem_zev": self.fallback, "failure_reasons": ", ".join(sorted(set(self.failures))),
                "planned_fuel_kg": self.planned_fuel_kg,
                "solve_wall_mean_s": float(np.mean(w)) if w else None, "solve_wall_max_s": max(w) if w else None}

    # -- solving
    def _cos_tilt(self, z_L: np.ndarray, target_z: float) -> np.ndarray:
        """Cosine of the planning tilt limit at each interval's start altitude."""
        lim = self.cfg.plan_tilt_frac * np.asarray(self.limits.tilt.tilt_max_rad(np.asarray(z_L) - target_z))
        return np.cos(lim)

    def _solve_fixed(self, r, v, m, r_f, v_f, target, t_f, z_ref_L, deadline: float):
        self.n_solves += 1
        left = deadline - time.perf_counter()
        if left <= 0.0:
            return None, "time limit"
        z_ref = np.asarray(z_ref_L, float)
        arrs, status = self.problem.solve(r, v, m, r_f, v_f, target, t_f, self._cos_tilt(z_ref, target[2]), left)
        # Further passes while the path breaks the tilt limit at its own altitudes: each takes the lower of the
        # reference and the path's altitude at every node, so the limits only tighten (and the passes settle).
        for _ in range(TILT_PASSES - 1):
            if arrs is None or not self._tilt_violated(arrs, target[2]):
                break
            z_ref = np.minimum(z_ref, arrs["r"][:-1, 2])
            left = deadline - time.perf_counter()
            if left <= 0.0:
                return None, "time limit"
            self.n_solves += 1
            arrs, status = self.problem.solve(r, v, m, r_f, v_f, target, t_f, self._cos_tilt(z_ref, target[2]), left)
        return arrs, status

    def _tilt_violated(self, arrs: dict[str, np.ndarray], target_z: float) -> bool:
        u = arrs["u"]
        tilt = np.arctan2(np.linalg.norm(u[:, :2], axis=1), u[:, 2])
        lim = self.cfg.plan_tilt_frac * np.asarray(self.limits.tilt.tilt_max_rad(arrs["r"][:-1, 2] - target_z))
        return bool(np.any(tilt > lim + TILT_TOL_RAD))

    def solve_path(self, t_ns: int, r: np.ndarray, v: np.ndarray, m: float, target_L: np.ndarray,
                   t_f_hint_s: float | None = None) -> tuple[GfoldSolution | None, str]:
        """The fuel-optimal path from this state to the gate (free final time, or ``t_f_hint_s`` first).

        Args:
            t_ns: Time of the state [ns].
            r, v: Position (3,) [m], velocity (3,) [m/s].
            m: Mass [kg].
            target_L: Landing site (3,) [m].
            t_f_hint_s: Try this final time first and keep it if feasible (re-solves); None: search.

        Returns:
            (solution or None, status).
        """
        opt: GfoldOptions = self.options
        t_start = time.perf_counter()
        deadline = t_start + opt.solve_time_limit_s
        r_f, v_f = self.gate_L(LandingTarget(target_L))
        n = opt.nodes

        def z_line(t_f):
            return r[2] + (r_f[2] - r[2]) * np.arange(n) / n

        best: tuple[float, float, dict] | None = None
        status = "not solved"
        try:
            if t_f_hint_s is not None and t_f_hint_s > RESOLVE_HINT_MIN_S:
                ref = self.solution
                z_ref = z_line(t_f_hint_s)
                if ref is not None:
                    s_nodes = (t_ns - ref.t0_ns) / NS_PER_S + t_f_hint_s * np.arange(n) / n
                    z_ref = np.array([ref.reference(s, self.g_L)[0][2] for s in s_nodes])
                arrs, status = self._solve_fixed(r, v, m, r_f, v_f, target_L, t_f_hint_s, z_ref, deadline)
                if arrs is not None:
                    best = (t_f_hint_s, m - math.exp(arrs["z"][-1]), arrs)
            if best is None:
                best, status = self._search_t_f(r, v, m, r_f, v_f, target_L, z_line, deadline)
        finally:
            self.solve_wall_s.append(time.perf_counter() - t_start)
        if best is None:
            return None, status
        t_f, fuel, arrs = best
        return GfoldSolution(t_ns, t_f, arrs["r"], arrs["v"], arrs["u"], fuel, np.exp(arrs["z"])), "optimal"

    def _search_t_f(self, r, v, m, r_f, v_f, target, z_line, deadline):
        """Free final time: coarse scan around the polynomial planner's time to go, then golden section."""
        cfg, opt = self.cfg, self.options
        t_poly, _ = self.plan_t_go(r, v, m, r_f, v_f)
        lo = max(cfg.t_go_min_s, 0.4 * t_poly)
        hi = min(cfg.t_go_max_s, 1.6 * t_poly + 5.0)
        grid = np.linspace(lo, hi, 9)
        fuel: dict[float, tuple[float, dict | None]] = {}
        last_status = "infeasible"

        def f(t_f: float) -> float:
            nonlocal last_status
            if t_f not in fuel:
                arrs, st = self._solve_fixed(r, v, m, r_f, v_f, target, t_f, z_line(t_f), deadline)
                last_status = st
                fuel[t_f] = (m - math.exp(arrs["z"][-1]), arrs) if arrs is not None else (math.inf, None)
            return fuel[t_f][0]

        vals = [f(float(t)) for t in grid]
        if not np.isfinite(vals).any():
            return None, last_status
        i = int(np.argmin(vals))
        a, b = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
        c, d = b - GOLDEN * (b - a), a + GOLDEN * (b - a)
        while b - a > opt.t_f_tolerance_s and time.perf_counter() < deadline:
            if f(c) <= f(d):
                b, d = d, c
                c = b - GOLDEN * (b - a)
            else:
                a, c = c, d
                d = a + GOLDEN * (b - a)
        t_best = min((t for t in fuel if fuel[t][1] is not None), key=lambda t: fuel[t][0])
        return (t_best, fuel[t_best][0], fuel[t_best][1]), "optimal"

    # -- the step
    def update(self, nav: NavState, target: LandingTarget) -> GuidanceCommand:
        """One guidance step: solve or re-solve when due, track the path, terminal phase from the gate."""
        if self.fallback:
            return super().update(nav, target)
        t_ns, target_L, r, v, m = guidance_inputs(nav, target)
        if target_L is None:
            return GuidanceCommand(t_ns, np.zeros(3), self.phase, float("nan"), saturated=False, valid=False)
        if self._target_L is None or not np.array_equal(self._target_L, target_L):
            self._target_L = target_L.copy()
            self.solution = None
        r_f, _ = self.gate_L(target)
        opt: GfoldOptions = self.options
        if self.phase == PHASE_APPROACH:
            sol = self.solution
            if sol is None:
                sol, status = self.solve_path(t_ns, r, v, m, target_L)
                self._last_solve_ns = t_ns
                if sol is None:
                    self.n_failures += 1
                    self.failures.append(status)
                    self.fallback = True  # ZEM/ZEV from here on
                    return super().update(nav, target)
                self.solution = sol
                self.planned_fuel_kg = sol.fuel_kg
            t_go = sol.t_f_s - (t_ns - sol.t0_ns) / NS_PER_S
            # Not below RESOLVE_HINT_MIN_S whatever the option says: that re-solve would search a fresh final
            # time of at least t_go_min_s and push the arrival back each time (a hover until the fuel is gone).
            if (t_go > max(opt.resolve_min_t_go_s, RESOLVE_HINT_MIN_S)
                    and t_ns - self._last_solve_ns >= opt.resolve_period_s * NS_PER_S):
                self._last_solve_ns = t_ns
                new, status = self.solve_path(t_ns, r, v, m, target_L, t_f_hint_s=t_go)
                if new is None:
                    self.n_failures += 1
                    self.failures.append(status)
                else:
                    sol = self.solution = new
                    t_go = sol.t_f_s
            if t_go <= 0.0 or r[2] <= r_f[2] - GATE_FLOOR_M:
                self.phase = PHASE_TERMINAL
            else:
                r_ref, v_ref, u_ref = sol.reference((t_ns - sol.t0_ns) / NS_PER_S, self.g_L)
                w = opt.tracking_bandwidth_radps
                a = u_ref + self.g_L + w * w * (r_ref - r) + 2.0 * w * (v_ref - v)
        if self.phase == PHASE_TERMINAL:
            a = self.terminal_accel_L(r, v, target_L)
            t_go = max(r[2] - target_L[2], 0.0) / self.cfg.terminal_descent_rate_mps
        a_capped, saturated = cap_acceleration_L(a, self.g_L, m, self.limits, r[2] - target_L[2])
        return GuidanceCommand(t_ns, a_capped, self.phase, float(t_go), saturated=saturated, valid=True)
