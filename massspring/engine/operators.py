"""The linear operators of the implicit step at a state, applied matrix-free by the
solver's own kernels: the small public device API for analysis and tests.

* ``Jacobians(model, positions)``: ``stiffness(u)`` = K u (seed Eq. 13) and
  ``damping(u)`` = D u (Eq. 14) for (n, 3) arrays u, float64. Pinned particles are
  not filtered: callers restrict u and the result as they need.
* ``SystemOperator(model, dt, ...)``: A = M - dt D - dt^2 K of Eq. 15 at the model's
  state, on the free particles: ``apply(p)`` (A p, zero at pinned particles),
  ``rhs()`` (b), ``inverse_diagonal_blocks()`` (A_ii^-1), ``precondition(r)`` (z = B r
  for the chosen preconditioner, set up at this state).
"""

from __future__ import annotations

import weakref
from types import SimpleNamespace

import numpy as np

from massspring.support import validate
from massspring.support.defaults import PRECISIONS
from massspring.device import POOL, Config, ensure_taichi, model_layout
from massspring.kernels import cg, operator
from massspring.kernels.terms import SpringDamping, Springs
from massspring.model import Model


class Jacobians:
    """K and D of ``model`` at ``positions`` (n, 3) m (default: the model's), K of
    Eq. 13 as written unless ``definiteness_fix``. ``close()`` hands the fields back (else
    done at garbage collection), for the next operator of the same size to reuse with its
    kernels compiled."""

    def __init__(self, model: Model, positions=None, definiteness_fix=False):
        ensure_taichi()
        x = _state("positions", positions, model.positions)
        self.model = model
        layout = model_layout(model, "f64")
        layout.vectors("p", layout.real)
        layout.vectors("q", layout.real)
        layout.add("diag", layout.real, "particle")
        if model.n_springs:
            layout.vectors("coef", layout.real, "entry", k=5)
            layout.vectors("spring_coef", layout.real, "spring", k=5)
        self._dev = layout.allocate()
        self._release = weakref.finalize(self, POOL.give, self._dev)
        self._dev.x.from_numpy(_padded(x, self._dev.x.shape[0]))
        base = Config.of(model, "f64")
        self._configs = {
            "stiffness": Config(base.real, (Springs,), (), base.fixed, bool(definiteness_fix)),
            "damping": Config(base.real, (SpringDamping,) if model.has_damping else (), (), base.fixed),
        }
        self._current = None

    def _apply(self, which, u):
        u = np.asarray(u, dtype=np.float64)
        if u.shape != self.model.positions.shape:
            raise ValueError(f"u: expected shape {self.model.positions.shape}, got {u.shape}")
        if not self.model.n_springs or not self._configs[which].spring_terms:
            return np.zeros_like(u)
        cfg = self._configs[which]
        if self._current != which:
            operator.jacobian_refresh(self._dev, cfg)
            self._current = which
        self._dev.p.from_numpy(_padded(u, self._dev.p.shape[0]))
        operator.jacobian_apply(self._dev, cfg)
        return -self._dev.read("q")

    def stiffness(self, u) -> np.ndarray:
        """K u (N) for displacements u (n, 3) m."""
        return self._apply("stiffness", u)

    def damping(self, u) -> np.ndarray:
        """D u (N) for velocities u (n, 3) m/s."""
        return self._apply("damping", u)

    def close(self):
        self._release()
        self._dev = None


def _state(name, values, default):
    """``values`` (default: ``default``) as float64 of ``default``'s shape, finite."""
    x = default if values is None else np.asarray(values, dtype=np.float64)
    if x.shape != default.shape or not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: expected finite values of shape {default.shape}")
    return x


def _padded(values, capacity):
    values = np.asarray(values, dtype=np.float64)
    out = np.zeros((capacity, 3))
    out[: len(values)] = values
    return out


class SystemOperator:
    """A = M - dt D - dt^2 K of Eq. 15 (with the definiteness fix unless told not to) at
    ``positions``/``velocities`` (default: the model's), in ``precision``, as the
    implicit integrator assembles it each step, with ``preconditioner`` (one of
    ``solvers.CHOICES``, "auto" resolved as by ``Simulation``) set up for it.
    ``close()`` hands the fields back (else done at garbage collection)."""

    def __init__(self, model: Model, dt, definiteness_fix=True, positions=None, velocities=None,
                 precision="f64", preconditioner="auto", loops="serial"):
        from massspring.integrators.implicit import ImplicitEuler
        from massspring.solvers import CHOICES, PRECONDITIONERS, resolve

        if not isinstance(model, Model):
            raise ValueError(f"model: expected a massspring.Model, got {type(model).__name__}")
        validate.choice("precision", precision, PRECISIONS)
        validate.choice("preconditioner", preconditioner, CHOICES)
        validate.choice("loops", loops, ("serial", "parallel"))
        dt = validate.positive_float("dt", dt)
        x = _state("positions", positions, model.positions)
        v = _state("velocities", velocities, model.velocities)
        preconditioner = resolve(preconditioner, model, ImplicitEuler.finest_f32(model, precision))
        ensure_taichi()
        self.model, self.dt = model, float(dt)
        settings = SimpleNamespace(precision=precision, definiteness_fix=bool(definiteness_fix),
                                   preconditioner=preconditioner, dt=self.dt, loops=loops)
        layout = model_layout(model, precision)
        ImplicitEuler.declare(layout, model, settings)
        self._dev = layout.allocate()
        self._cfg = ImplicitEuler.config(model, settings)
        self._dtype = np.float32 if precision == "f32" else np.float64
        for field, values in ((self._dev.x, x), (self._dev.v, v)):
            field.from_numpy(_padded(values, field.shape[0]).astype(self._dtype))
        cg.cg_refresh(self._dev, self._cfg, self._dev.x, self.dt, 0.0, operator.LINEARISED)
        self._preconditioner = PRECONDITIONERS[preconditioner](self._dev, model, settings)
        self._preconditioner.bind(self._cfg)
        self._release = weakref.finalize(self, _release, self._dev, self._preconditioner)
        self._preconditioner.setup(self.dt)

    def apply(self, p):
        """(A p, p . A p) for p (n, 3); p must be zero at pinned particles, and A p is
        zero there (their rows and columns are out of the system)."""
        p = np.asarray(p, dtype=np.float64).reshape(self.model.n_particles, 3)
        self._dev.p.from_numpy(_padded(p, self._dev.p.shape[0]).astype(self._dtype))
        pq = cg.cg_apply(self._dev, self._cfg)
        return self._dev.read("q").astype(np.float64), float(pq)

    def precondition(self, r):
        """z = B r (n, 3) for r (n, 3): the preconditioner applied once, constrained
        directions filtered out of r and z."""
        r = np.asarray(r, dtype=np.float64).reshape(self.model.n_particles, 3)
        self._dev.r.from_numpy(_padded(r, self._dev.r.shape[0]).astype(self._dtype))
        if self._preconditioner.kernel is not None:
            cg.cg_precondition(self._dev, self._cfg)
        else:
            self._preconditioner.apply()
        return self._dev.read("z").astype(np.float64)

    def rhs(self):
        """b = M v + dt (f - D v) of Eq. 15 (n, 3), zero at pinned particles."""
        return self._dev.read("b").astype(np.float64)

    def inverse_diagonal_blocks(self):
        """The block-Jacobi preconditioner's A_ii^-1 (n, 3, 3), zero at pinned particles."""
        return self._dev.read("minv").astype(np.float64)

    def close(self):
        self._release()
        self._dev = None


def _release(dev, preconditioner):
    preconditioner.release()
    POOL.give(dev)
