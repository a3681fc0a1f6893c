"""Backward Euler and BDF2 solved by Newton's method (``kernels/newton.py``)."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from massspring.device import read_verdict
from massspring.kernels import cg, divergence, friction, implicit_adjoint, newton, newton_adjoint, operator
from massspring.kernels import state as state_kernels
from massspring.solvers import SolverStats, solve
from massspring.solvers.cg import EPS32, EPS64, ROUNDOFF
from massspring.solvers.minres import minres
from massspring.kernels.newton import ARMIJO, ETA_FIRST, ETA_MAX, GOLDEN, MAX_CUTS

from .implicit import LINEAR_OPTIONS, ImplicitEuler
from .options import Option

NEWTON_TOL = 1e-3  # default newton_tol: a full Newton step this small relative to the step's velocity change ends it
NEWTON_MAX_ITER = 50  # default newton_max_iter: linear solves per step
ONE_LAUNCH_AFTER = 1000  # tries of a run before it compiles newton.newton_solve (BackwardEuler.one_launch)
NEWTON = "takes no Newton iterations"
NEWTON_OPTIONS = (
    Option("newton_tol", "fraction", NEWTON_TOL, "Newton stops when a full Newton step changes the velocities by "
           "at most this fraction of the step's velocity change (kinetic-energy norm)", NEWTON,
           sweep=(1e-3, 1e-6)),
    Option("newton_max_iter", "count", NEWTON_MAX_ITER, "Newton iterations (linear solves) per step at most", NEWTON),
)


class BackwardEuler(ImplicitEuler):
    """Backward Euler M (v' - v_n) = dt f(x_n + dt v', v'), x' = x_n + dt v', solved by Newton
    (spring damping along the springs' directions at x_n + dt v_n: ``kernels/newton.py``).

    Newton starts from v_n. Each iteration solves Eq. 15's system at the iterate (the
    same matrix-free operator, preconditioners, definiteness fix and contact
    constraints as the linearised step: ``kernels/newton.py``) by CG to a forcing
    tolerance (inexact Newton): ``ETA_FIRST`` in a step's first solve, then how far
    the last linear model missed, |‖g_k‖ - ‖r_{k-1}‖| / ‖g_{k-1}‖ (Eisenstat and Walker's
    first choice, safeguarded), within [cg_tol, ``ETA_MAX``]. A backtracking line
    search on the incremental potential makes every iteration decrease it (Armijo).
    Once it has had to cut a step, the step's later solves go to cg_tol: on the stiff
    chain loose solves then zigzagged (50 iterations, residual 2.3e-4) where tight ones
    converge (11, 2.6e-7: ``benchmarks/newton.py``'s residual table); a cloth whose
    steps are never cut keeps the cheap loose solves.

    The step has converged when a full Newton step moved v by at most newton_tol
    times the step's velocity change, ‖v_{k+1} - v_k‖_M <= newton_tol ‖v_{k+1} - v^‖_M
    (M-norms: kinetic energy), or when ‖g‖ is at the round-off of the terms it is the
    difference of; at most newton_max_iter linear solves. With the definiteness fix
    the Jacobian is not exact where springs are compressed: convergence is linear
    there, quadratic elsewhere. Contacts are detected once per step,
    from (x_n, v_n), and held through its iterations; friction is decided after the
    last, as in the linearised step.
    """

    name = "backward-euler"
    description = "backward Euler solved by Newton's method with a line search (CG per iteration)"
    traits = dataclasses.replace(
        ImplicitEuler.traits, order=1, newton=True, linearised=False,
        checked_energy="kinetic and spring energy",  # cg.advance_positions with springs
        differentiable=True,  # kernels/newton_adjoint.py: the true Jacobian at the converged iterate
        extra_bytes=7 * 24,  # xb, vb, xk, vk, dir, res and a contact's carrier: f64 3-vectors
        spring_extra_bytes=3 * 32)  # damping's lagged direction and coefficient, per spring and per entry (2 a spring)
    options = LINEAR_OPTIONS + NEWTON_OPTIONS
    carries = False  # whether a step's commit keeps the state it replaces (BDF2's history)

    @classmethod
    def declare(cls, layout, model, settings):
        super().declare(layout, model, settings)
        real = layout.real
        for name in ("xb", "vb", "xk", "vk", "dir", "res"):  # kernels/newton.py
            layout.vectors(name, real)
        if model.has_colliders:
            layout.vectors("carrier", real)
        if cls.config(model, settings).lagged:  # kernels/newton.py lagged_directions
            layout.vectors("lag", real, "spring", k=4)
            layout.vectors("lag_coef", real, "entry", k=4)

    @classmethod
    def declare_adjoint(cls, layout, model, stride, rows):
        """The last adjoint solution (the next one's warm start), the velocity of the point
        its Jacobian is taken at, and a GMRES product's vector and its J^T y. The warm start begins at zero
        (filled even when the bundle comes from the pool: a gradient never depends on the
        one before it)."""
        layout.vectors("mu", layout.real, values=np.zeros((layout.n, 3)))
        for name in ("ue", "y", "jy", "xs"):  # xs: the step's prediction (kernels/newton_adjoint.py)
            layout.vectors(name, layout.real)
        layout.vectors("sl", layout.real, "spring")
        super().declare_adjoint(layout, model, stride, rows)  # contact's (the linearised step's)
        if model.has_colliders:  # and each step's contact impulses (g at the converged iterate) and base x^
            layout.vectors("hj", layout.real, rows)
            layout.vectors("hb", layout.real, rows)

    @classmethod
    def kept_bytes(cls, model):
        """The linearised step's, and the contact impulses and base positions (48)."""
        return super().kept_bytes(model) + 48 * model.has_colliders

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.taken = {}  # step -> (a particle touched, BDF2's base used): a gradient's record of each step
        self._log = None  # newton.newton_solve's record of a step: ||S g|| and CG iterations of each solve
        self.tries = 0  # steps tried (accepted or not)

    def adjoint(self, adj, slot, wants):
        """The adjoint of (*) at the converged iterate (``kernels/newton_adjoint.py``):
        J^T mu = dL/du with the residual's true Jacobian J, by this run's CG and
        preconditioner at its cg_tol (GMRES around them where J is not the step's own
        operator); returns the ``SolverStats`` of it all."""
        exact = dataclasses.replace(self.cfg, fix=False)
        touching = self.taken[self.steps][0]
        mean = self.solves_mean(touching)
        h = self.step_size(touching)
        hx = self.dt if mean else h  # x' = base + hx u
        newton_adjoint.newton_adjoint_rhs(self.dev, self.cfg, exact, adj, h, hx, self.dt, self.time, slot, mean,
                                          wants, self.ahead(h), self.serial)
        stats = self._adjoint_solve(adj, exact, h, slot, wants)
        newton_adjoint.newton_adjoint_gather(self.dev, exact, adj, h, self.time, slot, mean, wants,
                                             self.ahead(h), self.carries, self.serial)
        return stats

    def _adjoint_solve(self, adj, exact, h, slot, wants):
        """mu for J mu = dL/du (J symmetric: K and D are, spring damping acting along fixed
        directions). Without the definiteness fix J is the step's own operator S: one CG
        solve. With it, J = S less what the fix adds where springs are compressed, and may
        be indefinite: preconditioned MINRES (``solvers.minres``) on the free directions,
        each iteration one product with J (``newton_adjoint.jacobian_product``: S's, less
        what the fix added) and one with the run's preconditioner of S
        (symmetric positive definite), from the last step's mu, to cg_tol in the
        preconditioner's norm, at most cg_max_iter iterations."""
        s = self.settings
        dev, cfg, pre = self.dev, self.cfg, self.preconditioner
        if not cfg.fix:
            return solve(dev, cfg, pre, h, s.cg_tol, s.cg_max_iter, self.serial, self.time, mode=operator.REFRESHED)
        start = time.perf_counter()
        pre.setup(h)  # a pointwise one was set up by the refresh
        setup_s = time.perf_counter() - start
        unconstrained = self._unconstrained(exact)

        def product(y):  # J y
            out = np.empty_like(y)
            newton_adjoint.jacobian_product(dev, cfg, h, y, out)
            return out

        def precondition(r):  # B r
            if pre.kernel is not None:
                out = np.empty_like(r)
                cg.precondition_vectors(dev, cfg, r, out)
                return out
            state_kernels.load_vectors(dev.r, r)
            pre.apply()
            return unconstrained(dev.read("z"))

        eps = EPS64 if s.precision == "f64" else EPS32
        rhs, start = unconstrained(adj.read("jy", dev.n)), unconstrained(dev.read("v"))
        out = minres(product, precondition, rhs, start, s.cg_tol, s.cg_max_iter, floor=ROUNDOFF * eps)
        state_kernels.load_vectors(dev.v, out.x)
        return SolverStats(out.iterations, out.residual, out.converged, out.reason, setup_s)

    def _unconstrained(self, cfg):
        """v -> v without its constrained directions (a solve sets them to their prescribed
        velocities; mu has none): 0 at pins, S_i v_i at a particle in contact."""
        free = (self.dev.read("free") != 0)[:, None] if cfg.fixed else np.ones((self.dev.n, 1), bool)
        if not cfg.contact_filter:
            return lambda v: np.where(free, v, 0.0)
        touching = self.dev.read("contacts") != 0
        filters = self.dev.read("cfilter")[touching]

        def unconstrained(v):
            out = np.where(free, v, 0.0)
            out[touching] = np.einsum("kij,kj->ki", filters, v[touching])
            return out

        return unconstrained

    @classmethod
    def config(cls, model, settings):
        """The linearised step's, with the rate-dependent terms ``lagged``."""
        cfg = super().config(model, settings)
        return dataclasses.replace(cfg, lagged=cfg.rate_stiffness)

    def ahead(self, h) -> float:
        """How far ahead (s) of x_n the rate-dependent terms take their directions:
        x_n + ahead v_n is within O(dt^2) of where (*) evaluates the forces."""
        return self.dt

    def step_size(self, touching) -> float:
        """h of (*) in ``kernels/newton.py`` for the step being taken (``touching``: its
        particles in contact)."""
        return self.dt

    def solves_mean(self, touching) -> bool:
        """Whether the step being taken (``touching``: its particles in contact) solves (*)
        for its mean velocity u = (v_n + v')/2, so that v' = 2 u - v_n and x' = x_n + dt u
        (``finish`` makes them; a gradient's adjoint takes them back), rather than for v'
        itself (backward Euler's and BDF2's: False)."""
        return False

    def finish(self, h, touching):
        """Turn the solution v of (*) into the step's velocity, with ``dev.xb`` and h such
        that x' = x^ + h v' (``cg.advance_positions``); backward Euler's are already so."""

    def base_is_bdf2(self) -> bool:
        return False

    def ratio(self) -> float:
        """BDF2's step ratio omega = dt / (the step before's size): 1 with a fixed dt."""
        return 1.0

    def advance(self, steps):
        """One step (``steps`` must be 1: each step has its own solver stats)."""
        assert steps == 1
        s = self.settings
        dev, cfg, serial, eps = self.dev, self.cfg, self.serial, EPS64 if s.precision == "f64" else EPS32
        t = self.time
        variable = self.clock is not None
        touching = newton.newton_start(dev, cfg, self.dt, t, self.base_is_bdf2(), variable, self.ratio(), serial)
        if touching and self.base_is_bdf2():  # contact breaks the history: a backward-Euler step
            self.ready = False
            newton.newton_start(dev, cfg, self.dt, t, False, False, 1.0, serial)
        h = self.step_size(touching)
        if self.history is not None:
            self.taken[self.steps] = (touching > 0, self.base_is_bdf2())
        if cfg.lagged:
            newton.newton_lag(dev, cfg, self.ahead(h), self.serial)
        self.tries += 1
        if self.one_launch():
            self._stats = self._newton_in_one_launch(h, t, eps)
        else:
            self._stats = self._newton(h, t, eps)
        reason = self._stats.reason
        if reason == "non-finite":  # no velocity to step with
            dev.v.copy_from(dev.keep)
            return 0, divergence.NONFINITE_VERDICT
        if cfg.contact_filter:
            if self.history is not None and self.friction:  # a gradient's run: v' before friction
                implicit_adjoint.keep_solved(dev, self.history[0], dev.n, self.steps - self.history[1])
            friction.contact_friction(dev, cfg, t, serial)
            if self.history is not None:  # and the step's impulses
                implicit_adjoint.keep_impulses(dev, self.history[0], dev.n, self.steps - self.history[1])
        self.finish(h, touching)
        if cfg.contact_filter and self.history is not None:  # x' = x^ + h v' from here
            implicit_adjoint.keep_base(dev, self.history[0], dev.n, self.steps - self.history[1])
        check = read_verdict(cg.advance_positions(dev, cfg, dev.xb, h, self.dt, self.time_after(), serial,
                                                  self.carries, True))
        accepted = check[0] == divergence.OK
        if not accepted:
            dev.v.copy_from(dev.keep)
        self.count(int(accepted))
        self.after_step(accepted, touching)
        return int(accepted), check

    def one_launch(self) -> bool:
        """Whether this try runs Newton's iteration in one launch (``newton.newton_solve``, the
        same bits as the loop from Python): with serial loops (a small system on the CPU) and
        a pointwise preconditioner, once the run has made ``ONE_LAUNCH_AFTER`` tries or the
        kernel is compiled for its bundle already (a run before it in the pool did so). Its
        compile costs about 2 s more than the loop's kernels (cold, without Taichi's offline
        cache), what a thousand steps of a 20-particle chain save
        (``benchmarks/newton_launches.py``), so short runs (tests, sweeps of short runs) keep
        the loop."""
        if not (self.serial and self.preconditioner.kernel is not None):
            return False
        key = ("newton_solve", self.cfg)
        if key not in self.dev.compiled and self.tries >= ONE_LAUNCH_AFTER:
            self.dev.compiled.add(key)
        return key in self.dev.compiled

    def _newton(self, h, t, eps):
        """Newton's iteration for (*) (``kernels/newton.py``) from Python, one launch per
        phase: CG's, the direction's, each line-search trial's, each refresh's. Returns its
        ``SolverStats``."""
        s = self.settings
        dev, cfg, serial = self.dev, self.cfg, self.serial
        g2, scale2, _, _ = newton.newton_refresh(dev, cfg, h, t, serial)
        first = norm = math.sqrt(g2)
        norms = [norm]
        floor = ROUNDOFF * eps * math.sqrt(scale2)
        solves, cuts, total, setup, reason, last = [], 0, 0, 0.0, "converged", None
        previous = predicted = math.inf
        eta = ETA_FIRST
        cut = False
        while math.isfinite(norm) and norm > floor:
            if len(solves) >= s.newton_max_iter:
                reason = "max_newton"
                break
            if solves:
                safeguard = eta ** GOLDEN
                eta = abs(norm - predicted) / previous  # how far the linear model missed
                if safeguard > 0.1:
                    eta = max(eta, safeguard)
            if cut:  # a line search has cut a step: loose solves' directions are not to be trusted
                eta = self.cg_tol
            eta = min(max(eta, self.cg_tol), ETA_MAX)
            last = solve(dev, cfg, self.preconditioner, h, eta, s.cg_max_iter, serial, t, mode=operator.REFRESHED)
            solves.append(last.iterations)
            total += last.iterations
            setup += last.setup_s
            predicted = last.residual * last.first_residual  # ||g|| the linear model predicts
            if last.reason == "non-finite":
                norm = math.inf
                break
            newton.newton_direction(dev, cfg, self.serial)
            alpha, tried = 1.0, 0
            while True:
                change, slope, _ = newton.newton_trial(dev, cfg, h, alpha, serial)
                if change <= ARMIJO * alpha * slope or tried == MAX_CUTS or not math.isfinite(change):
                    break
                alpha *= 0.5
                tried += 1
            cuts += tried
            cut = cut or tried > 0
            previous = norm
            g2, scale2, moved2, change2 = newton.newton_refresh(dev, cfg, h, t, serial)
            norm = math.sqrt(g2)
            norms.append(norm)
            floor = max(floor, ROUNDOFF * eps * math.sqrt(scale2))
            if tried == 0 and moved2 <= self.newton_tol**2 * change2:
                if moved2 == 0.0 and not last.converged:
                    reason = last.reason  # CG could not move v (indefinite, stalled): nor can Newton
                break  # a full Newton step this small: what is left is smaller still
        if not math.isfinite(norm):
            reason = "non-finite"
        relative = tuple(value / first if first > 0 else 0.0 for value in norms)
        return SolverStats(total, last.residual if last else 0.0, reason == "converged", reason, setup,
                           newton_iterations=len(solves), cg_per_newton=tuple(solves), cuts=cuts,
                           newton_residual=relative[-1], newton_residuals=relative, first_residual=first)

    def _newton_in_one_launch(self, h, t, eps):
        """``_newton``'s iteration in one launch with serial loops (``newton.newton_solve``: the
        same arithmetic), for a pointwise preconditioner on a small system, where a step's
        dozen launches cost more than its work. Returns its ``SolverStats``."""
        s = self.settings
        log = self._log
        if log is None or len(log) < s.newton_max_iter + 1:
            log = self._log = np.zeros((s.newton_max_iter + 1, 2))
        out = newton.newton_solve(self.dev, self.cfg, h, t, ROUNDOFF * eps, self.cg_tol, self.newton_tol,
                                  s.cg_max_iter, s.newton_max_iter, log)
        solves, total, cuts, code, residual, first = (float(value) for value in out)
        solves = int(solves)
        reason = newton.REASONS[int(code)]
        norms = log[:solves + 1, 0]
        relative = tuple(float(value / first) if first > 0 else 0.0 for value in norms)
        return SolverStats(int(total), residual, reason == "converged", reason, 0.0,
                           newton_iterations=solves, cg_per_newton=tuple(int(k) for k in log[:solves, 1]),
                           cuts=int(cuts), newton_residual=relative[-1], newton_residuals=relative,
                           first_residual=first)

    def after_step(self, accepted, touching):
        """Hook after a step (BDF2 records whether it has a history to use)."""


class BDF2(BackwardEuler):
    """BDF2: v' = 4/3 v_n - 1/3 v_{n-1} + 2/3 dt a', x' = 4/3 x_n - 1/3 x_{n-1} + 2/3 dt v',
    a' = f(x', v') / m, solved as backward Euler is (``kernels/newton.py`` (*) with
    the base (4/3 x_n - 1/3 x_{n-1}, 4/3 v_n - 1/3 v_{n-1}) and h = 2 dt / 3). Second
    order. A backward-Euler step instead where the history is missing or broken: the
    first step (and the first after a restart without the carried state), and a step
    with a particle in contact or following one (an impact makes the velocity jump,
    and a base extrapolated across the jump would add energy: contact is first order
    in every integrator). Carries (x_{n-1}, v_{n-1}) and whether it may use them."""

    name = "bdf2"
    description = "BDF2 (second order, first step backward Euler) solved by Newton's method with a line search"
    traits = dataclasses.replace(BackwardEuler.traits, order=2, error_constant=2 / 9,
                                 extra_bytes=BackwardEuler.traits.extra_bytes + 2 * 24)  # and x_{n-1}, v_{n-1}
    carries = True

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.ready = False
        self.previous = None  # an error-controlled run's size (s) of the step that made the current state

    @classmethod
    def declare(cls, layout, model, settings):
        super().declare(layout, model, settings)
        layout.vectors("xo", layout.real)
        layout.vectors("vo", layout.real)

    def base_is_bdf2(self):
        return self.ready

    @classmethod
    def declare_adjoint(cls, layout, model, stride, rows):
        """Backward Euler's, and the share of dL/d(state) a step's adjoint keeps for the
        state two steps back (``newton_adjoint.bdf2_split``), zero to start."""
        super().declare_adjoint(layout, model, stride, rows)
        for name in ("kx", "kv"):
            layout.vectors(name, layout.real, values=np.zeros((layout.n, 3)))
        for name in ("ox", "ov"):  # the prediction's share (newton_adjoint.newton_adjoint_gather)
            layout.vectors(name, layout.real)

    def adjoint(self, adj, slot, wants):
        """Backward Euler's adjoint from BDF2's base, shared between the two states it is
        made of, where the step used it (``taken``: not the first step, nor a step with a
        particle in contact or following one)."""
        self.ready = self.taken[self.steps][1]
        stats = super().adjoint(adj, slot, wants)
        variable = self.ready and self.previous is not None
        if variable:  # the base's coefficients of variable-step BDF2 (``step_size``)
            omega = self.ratio()
            den = 1.0 + 2.0 * omega
            now, before, third = (1.0 + omega) ** 2 / den, omega * omega / den, self.dt * omega / den
        else:
            now, before, third = 4.0 / 3.0, 1.0 / 3.0, self.dt / 3
        newton_adjoint.bdf2_split(self.dev, self.cfg, adj, int(self.ready), third, wants, variable, now, before)
        return stats

    def at_step(self, k, clock=None, size=None, before=None):
        """The base class's, and the size ``before`` of the step that made step k's state
        (BDF2's step ratio; None: the first step)."""
        super().at_step(k, clock, size, before)
        if clock is not None:
            self.previous = before

    def ratio(self):
        """dt over the size of the step that made the current state (``previous``: None with a
        fixed dt, whose ratio is 1)."""
        return 1.0 if self.previous is None else self.dt / self.previous

    def step_size(self, touching):
        """Variable-step BDF2's h = dt (1 + omega) / (1 + 2 omega) with its base
        ((1 + omega)^2 x_n - omega^2 x_{n-1}) / (1 + 2 omega) (``kernels/newton.py``), omega the
        step ratio (``ratio``): 2 dt / 3 and (4 x_n - x_{n-1}) / 3 at a fixed dt."""
        if not self.ready:
            return self.dt
        if self.previous is None:
            return 2.0 * self.dt / 3.0
        omega = self.ratio()
        return (1.0 + omega) * self.dt / (1.0 + 2.0 * omega)

    def after_step(self, accepted, touching):
        if accepted:
            self.ready = not touching
            if self.clock is not None:
                self.previous = self.dt

    def carried_names(self):
        """The previous state x_{n-1} ("x_prev", m), v_{n-1} ("v_prev", m/s) and "ready"
        (1: they hold the previous step; 0: the next step is backward Euler), with the
        linearised step's contact memory; in an error-controlled run also "h_prev" (s, the
        size of the step that made the current state, on every row)."""
        names = {**super().carried_names(), "x_prev": (np.float64, (3,)), "v_prev": (np.float64, (3,)),
                 "ready": (np.int32, ())}
        if self.clock is not None:
            names["h_prev"] = (np.float64, ())
        return names

    def carried_fields(self):
        return {**{name: name for name in super().carried_names()}, "x_prev": "xo", "v_prev": "vo"}

    def carried_values(self):
        n = self.dev.n
        out = {"ready": np.full(n, int(self.ready), np.int32)}
        if self.clock is not None:
            out["h_prev"] = np.full(n, self.previous or 0.0)
        return out

    def load_state(self, positions, velocities, carried=None):
        """Continue from (positions, velocities); with ``carried``, from its previous state."""
        own = ("x_prev", "v_prev", "ready", "h_prev")
        rest = None if carried is None else {k: v for k, v in carried.items() if k not in own}
        super().load_state(positions, velocities, rest)
        self.previous = None
        if carried is None:
            self.ready = False
            return
        if "h_prev" in carried and len(carried["h_prev"]) and carried["h_prev"][0] > 0:
            self.previous = float(carried["h_prev"][0])
        state_kernels.load_vectors(self.dev.xo, carried["x_prev"].astype(np.float64))
        state_kernels.load_vectors(self.dev.vo, carried["v_prev"].astype(np.float64))
        self.ready = bool(np.all(carried["ready"] != 0)) and len(carried["ready"]) > 0
