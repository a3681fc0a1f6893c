"""Linearised backward Euler (seed Eq. 15), solved by matrix-free preconditioned CG."""

from __future__ import annotations

import numpy as np
import taichi as ti

from massspring.passes.self_collision.forward import declare_solve
from massspring.device import Config, read_verdict
from massspring.kernels import cg, divergence, friction, implicit_adjoint, operator
from massspring.solvers import CHOICES, MULTIGRID_FROM, PRECONDITIONERS, solve

from .base import Integrator, Traits
from .options import Option

LINEAR_SOLVER = "solves no linear system"
LINEAR_OPTIONS = (
    Option("preconditioner", "choice", "auto", "the CG's preconditioner (`solvers.PRECONDITIONERS`); \"auto\" "
           f"picks multigrid from {MULTIGRID_FROM:,} free particles on (its iteration count stays flat with "
           "resolution; `\"multigrid-f32\"`, its finest level in f32, for the linearised implicit step in f64 "
           "without self-collision pairs in its solve), block-Jacobi below; the Simulation's `preconditioner` "
           "reports the one picked",
           LINEAR_SOLVER, choices=CHOICES),
    Option("cg_tol", "fraction", 1e-6, "CG's relative tolerance on the true residual ‖b − A v‖, relative to the "
           "first residual of its warm start (for the linearised step, the right-hand side of Eq. 15's "
           "velocity-change form); for a Newton-solved integrator, the tightest tolerance of an iteration's solve",
           LINEAR_SOLVER, sweep=(1e-2, 1e-4, 1e-6)),
    Option("cg_max_iter", "count", None, "CG iterations per solve at most", LINEAR_SOLVER,
           default_text="3 × free particles, at least 100"),
    Option("definiteness_fix", "switch", True, "clamp the transverse stiffness of compressed springs so that "
           "the system stays positive definite (see kernels/terms/springs.py)", LINEAR_SOLVER),
)


class ImplicitEuler(Integrator):
    """(M - dt D - dt^2 K) v' = M v + dt (f - D v), x' = x + dt v' (seed Eq. 9, 12-15).

    Each step refreshes the operator at (x_n, v_n) and solves for v' in place in
    ``dev.v`` (v_n is CG's warm start, as the seed says), then commits
    x' = x + dt v' only if the new state passes the divergence check.
    ``dev.keep`` holds the velocity of the last accepted state: the commit writes it
    in the loop that stores x', so keeping it costs one store per particle and no
    launch, and a rejected step is undone by copying it back into ``dev.v`` (x_n was
    never overwritten).

    With colliders, contacts are constraints of the solve (``kernels/contact.py``):
    detected in the refresh, friction and released contacts after it
    (``kernels/friction.py``), and positions that would still end inside a collider
    moved onto its surface when x' is committed. With self-collision, the pairs within
    the thickness at x_n are penalty springs of the solve (``kernels/pair_penalty.py``).
    """

    name = "implicit"
    description = "linearised implicit Euler (Eq. 15), matrix-free preconditioned CG"
    traits = Traits(order=1, has_stats=True, linear_solver=True, differentiable=True, linearised=True)
    options = LINEAR_OPTIONS

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.preconditioner = PRECONDITIONERS[settings.preconditioner](dev, model, settings)
        self.preconditioner.bind(self.cfg)
        self._stats = None
        self.friction = model.has_friction

    @classmethod
    def config(cls, model, settings):
        return Config.of(model, settings.precision, fix=settings.definiteness_fix,
                         precond=PRECONDITIONERS[settings.preconditioner].kernel,
                         contact_filter=model.has_colliders, self_pairs=cls.pairs_in_solve(model))

    @classmethod
    def finest_f32(cls, model, precision):
        """The linearised step in f64 without self-collision pairs in its solve (which the
        f32 level does not take): one setup and 7-14 cycles a step, the cycles 0.71-0.86
        of the f64 ones' step time from 128 x 128 on. Not the Newton-solved steps: a setup
        (and its narrowing) per Newton iteration for 2-3 cycles each, 1.07x slower at
        128 x 128 (``benchmarks/results/multigrid_precision.json``)."""
        return precision == "f64" and not cls.traits.newton and not cls.pairs_in_solve(model)

    @classmethod
    def pairs_in_solve(cls, model):
        """Whether self-collision pairs are penalties of Eq. 15 (``kernels/pair_penalty.py``):
        with self-collision, in the linearised step (the Newton-solved steps leave them
        to the pass that follows every step)."""
        return model.has_self_collision and not cls.traits.newton

    @classmethod
    def declare(cls, layout, model, settings):
        real = layout.real
        for name in ("b", "r", "z", "p", "q"):
            layout.vectors(name, real)
        layout.vectors("keep", real, values=model.velocities)
        layout.add("diag", real, "particle")
        if model.n_springs:
            layout.vectors("coef", real, "entry", k=5)
            layout.vectors("spring_coef", real, "spring", k=5)
        if model.has_colliders:
            layout.add("contacts", ti.i32, "particle")
            layout.add("released", ti.i32, "particle", values=np.zeros(model.n_particles))
            layout.add("cfilter", real, "particle", (3, 3))
            layout.vectors("cvel", real)
            layout.vectors("impulse", real)
            layout.add("stick", ti.i32, "particle", values=np.zeros(model.n_particles))
            layout.vectors("fric", real, values=np.zeros((model.n_particles, 3)))
        if cls.pairs_in_solve(model):
            declare_solve(layout, model)
        PRECONDITIONERS[settings.preconditioner].declare(layout, model, settings, cls.config(model, settings))

    @property
    def stats(self):
        return self._stats

    def carried_names(self):
        """With colliders, the contact memory (``kernels/friction.py``): released contacts,
        sticking particles, kinetic friction impulses."""
        if not self.cfg.has_colliders:
            return {}
        return {"released": (np.int32, ()), "stick": (np.int32, ()), "fric": (np.float64, (3,))}

    def load_state(self, positions, velocities, carried=None):
        """The base's load, and ``keep`` (the last accepted velocity) set to ``velocities``;
        without ``carried``, the contact memory starts afresh (all contacts free to form,
        none sticking)."""
        super().load_state(positions, velocities, carried)
        self.dev.keep.copy_from(self.dev.v)
        if carried is None and self.cfg.has_colliders:
            for name in ("released", "stick"):
                getattr(self.dev, name).fill(0)
            self.dev.fric.fill(0)

    def changed(self):
        """v_n for the next step and for a failed one to fall back to (``dev.keep``, set by a
        step's commit) = the changed state's velocities."""
        self.dev.keep.copy_from(self.dev.v)

    def advance(self, steps):
        """One implicit step (``steps`` must be 1: each step has its own solver stats)."""
        assert steps == 1
        s = self.settings
        self._stats = solve(self.dev, self.cfg, self.preconditioner, self.dt, self.cg_tol, s.cg_max_iter,
                            self.serial, self.time)
        if self._stats.reason == "non-finite":  # Eq. 15 overflowed: no velocity to step with
            self.dev.v.copy_from(self.dev.keep)
            return 0, divergence.NONFINITE_VERDICT
        if self.cfg.contact_filter:
            if self.friction and self.history is not None:  # a gradient's run: v' before friction
                adj, first = self.history
                implicit_adjoint.keep_solved(self.dev, adj, self.dev.n, self.steps - first)
            friction.contact_friction(self.dev, self.cfg, self.time, self.serial)
        check = read_verdict(cg.advance_positions(self.dev, self.cfg, self.dev.x, self.dt, self.dt,
                                                  self.time_after(), self.serial, False, False))
        accepted = check[0] == divergence.OK
        if not accepted:
            self.dev.v.copy_from(self.dev.keep)
        self.count(int(accepted))
        return int(accepted), check

    @classmethod
    def declare_adjoint(cls, layout, model, stride, rows):
        """With colliders: the contact memory of each kept state (``hr``, with friction
        ``hs``, ``hf``), as the history, and, at a particle in contact, the gradient its
        solve was given (``cg``); with friction also each step's solved velocity before
        friction changed it (``hw``), dL/dJ of the contact impulses (``cj``) and dL/d(the
        kinetic friction handed to the next step) (``gf``, zero to start)."""
        if model.has_colliders:
            layout.add("hr", ti.i32, rows)
            layout.vectors("cg", layout.real)
        if model.has_friction:
            layout.add("hs", ti.i32, rows)
            for name in ("hf", "hw"):
                layout.vectors(name, layout.real, rows)
            layout.vectors("cj", layout.real)
            layout.vectors("gf", layout.real, values=np.zeros((layout.n, 3)))

    @classmethod
    def kept_bytes(cls, model):
        """The contact memory (4 bytes; with friction 32) and, with friction, the solved velocity (24)."""
        return 4 * model.has_colliders + 52 * model.has_friction

    def keep(self, adj, slot):
        """The base's, and with colliders the contact memory of the state
        (``implicit_adjoint.keep_contacts``): the adjoint's step detects its contacts again."""
        super().keep(adj, slot)
        if self.cfg.contact_filter:
            implicit_adjoint.keep_contacts(self.dev, adj, self.dev.n, slot, self.friction)

    def adjoint(self, adj, slot, wants):
        """The adjoint of Eq. 15 at the state kept at ``slot`` (``kernels/implicit_adjoint.py``):
        one solve with this run's operator, CG and preconditioner at its cg_tol; returns
        the solve's ``SolverStats``."""
        s, dt = self.settings, self.dt
        implicit_adjoint.adjoint_rhs(self.dev, self.cfg, adj, dt, self.time, slot, wants, self.serial)
        stats = solve(self.dev, self.cfg, self.preconditioner, dt, s.cg_tol, s.cg_max_iter, self.serial,
                      self.time, mode=operator.REFRESHED)
        implicit_adjoint.implicit_adjoint(self.dev, self.cfg, adj, dt, self.time, slot, wants, self.serial)
        return stats

    @staticmethod
    def suggest_dt(prediction):
        """1/60 s, a frame: the linearised implicit step has no stability limit."""
        return 1.0 / 60.0

    def release(self):
        self.preconditioner.release()
