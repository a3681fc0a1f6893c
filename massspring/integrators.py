"""Time integrators: each a few kernel calls over the same device arrays.

``DeviceModel`` is a Model turned into Taichi ndarrays once; ``State`` holds the
particle positions and velocities. Each integrator allocates only the work arrays
it needs: the explicit ones a second state to step into, the implicit one the CG
vectors. Arrays a run does not need are passed to kernels as 1-element
placeholders and never read (the code that would read them is compiled out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

from massspring.kernels import cg, divergence, forces, operator

REAL = {"f32": ti.f32, "f64": ti.f64}
NUMPY_REAL = {"f32": np.float32, "f64": np.float64}
SERIAL_BELOW = 8000  # springs; see ImplicitEuler


def _vec3_array(real, values):
    arr = ti.Vector.ndarray(3, real, shape=values.shape[0])
    arr.from_numpy(np.ascontiguousarray(values, dtype=np.float32 if real == ti.f32 else np.float64))
    return arr


def _scalar_array(dtype, values):
    """A Taichi ndarray copy of ``values``; an empty array becomes one unused zero."""
    values = np.asarray(values)
    if values.size == 0:
        values = np.zeros((1,) + values.shape[1:])
    arr = ti.ndarray(dtype, shape=values.shape)
    np_type = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32}[dtype]
    arr.from_numpy(np.ascontiguousarray(values, dtype=np_type))
    return arr


def _placeholder(dtype):
    return ti.ndarray(dtype, shape=1)


@dataclass
class DeviceModel:
    """The parts of a Model the kernels read, as Taichi ndarrays (see kernels/forces.py)."""

    real: object
    mass: object
    free: object
    offsets: object
    other: object
    spring: object
    ends: object
    ks: object
    kd: object
    l0: object
    gravity: tuple
    has_damping: bool
    has_gravity: bool
    has_fixed: bool
    n_springs: int

    @classmethod
    def upload(cls, model, precision):
        real = REAL[precision]
        offsets, other, spring = model.adjacency()
        has_damping, has_fixed = model.has_damping, model.has_fixed
        return cls(
            real=real,
            mass=_scalar_array(real, model.masses),
            free=_scalar_array(ti.i32, model.free_mask().astype(np.int32)) if has_fixed else _placeholder(ti.i32),
            offsets=_scalar_array(ti.i32, offsets),
            other=_scalar_array(ti.i32, other),
            spring=_scalar_array(ti.i32, spring),
            ends=_scalar_array(ti.i32, model.springs),
            ks=_scalar_array(real, model.stiffness),
            kd=_scalar_array(real, model.damping) if has_damping else _placeholder(real),
            l0=_scalar_array(real, model.rest_lengths),
            gravity=tuple(float(c) for c in model.gravity),
            has_damping=has_damping,
            has_gravity=model.has_gravity,
            has_fixed=has_fixed,
            n_springs=model.n_springs,
        )

    def terms(self):
        """Names of the force terms compiled into this run's kernels."""
        return ["spring"] + (["damping"] if self.has_damping else []) + \
            (["gravity"] if self.has_gravity else []) + (["fixed-filter"] if self.has_fixed else [])


@dataclass
class State:
    """Particle positions x (m) and velocities v (m/s): (n,) vec3 ndarrays."""

    x: object
    v: object

    @classmethod
    def upload(cls, real, positions, velocities):
        return cls(_vec3_array(real, positions), _vec3_array(real, velocities))


@dataclass(frozen=True)
class SolverStats:
    """Outcome of one implicit step's CG solve.

    iterations: CG iterations; residual: true relative residual ||b - A v|| / ||b||
    recomputed at exit; converged: residual <= tolerance; reason: why CG stopped
    ("converged", "max_iter", "indefinite" when p.Ap <= 0, "stalled" when a restart
    from the true residual no longer reduces it, as f32 round-off can cause).
    """

    iterations: int
    residual: float
    converged: bool
    reason: str

    def __getitem__(self, key):
        return getattr(self, key)


class _EulerIntegrator:
    """Explicit (Eq. 7-8) or symplectic Euler: one fused kernel per step into a spare state.

    Systems with fewer springs than ``serial_below`` run many steps per launch
    with serial loops (launch-bound size); larger ones one parallel launch per step.
    """

    symplectic = False
    work_arrays = ("x_next", "v_next")

    def __init__(self, dev: DeviceModel, state: State, serial_below=SERIAL_BELOW):
        self.dev = dev
        n = state.x.shape[0]
        self.spare = State(ti.Vector.ndarray(3, dev.real, shape=n), ti.Vector.ndarray(3, dev.real, shape=n))
        self.serial = dev.n_springs < serial_below

    def advance(self, state: State, dt: float, steps: int, check):
        """Up to ``steps`` steps from ``state``, each checked with ``check`` (see kernels/divergence.py).

        Returns (state holding the last good step, good steps done, check code of
        the first failed step or OK, its kinetic energy in J). A failed step's state
        is left in the spare buffer and never returned.
        """
        d, out = self.dev, self.spare
        args = (d.mass, d.free, d.offsets, d.other, d.spring, d.ks, d.kd, d.l0, d.gravity, dt)
        flags = (self.symplectic, d.has_damping, d.has_gravity, d.has_fixed, d.real)
        done, code, kinetic = 0, divergence.OK, 0.0
        if self.serial:
            result = forces.euler_steps_serial(state.x, state.v, out.x, out.v, *args, steps, check, *flags)
            done, code, kinetic = int(result[0]), int(result[1]), float(result[2])
            if done % 2:
                state, out = out, state
        else:
            while done < steps and code == divergence.OK:
                sums = forces.euler_step(state.x, state.v, out.x, out.v, *args, *flags)
                kinetic = float(sums[0])
                code = divergence.divergence_code(kinetic, float(sums[1]), float(sums[2]), *check)
                if code == divergence.OK:
                    state, out = out, state
                    done += 1
        self.spare = out
        return state, done, code, kinetic


class ExplicitEuler(_EulerIntegrator):
    symplectic = False


class SymplecticEuler(_EulerIntegrator):
    symplectic = True


class ImplicitEuler:
    """Linearised backward Euler (Eq. 15) solved by matrix-free block-Jacobi PCG.

    ``serial_below``: systems with fewer springs than this run the whole solve in
    one serial kernel (launch-bound size); larger ones use the parallel kernels.
    Both run the same algorithm and agree to round-off.
    """

    def __init__(self, dev: DeviceModel, state: State, *, cg_tol, cg_max_iter,
                 definiteness_fix=True, preconditioner="block-jacobi", serial_below=SERIAL_BELOW):
        self.dev = dev
        # CG overwrites v in place (v_n is its warm start). ``keep`` holds the velocity
        # of the last accepted state: cg.advance_positions writes it in the same loop
        # that commits x_{n+1}, so keeping it costs one store per particle and no
        # launch, and a rejected step is undone by copying it back (x_n was never
        # overwritten). Cheaper than copying v_n before every solve: no extra pass.
        self.keep = _vec3_array(dev.real, state.v.to_numpy())
        self.tol = cg_tol
        self.max_iter = cg_max_iter
        self.fix = definiteness_fix
        self.precondition = preconditioner == "block-jacobi"
        self.n_springs = n_springs = dev.n_springs
        self.serial = n_springs < serial_below
        n = state.x.shape[0]
        vec = lambda: ti.Vector.ndarray(3, dev.real, shape=n)  # noqa: E731
        self.b, self.r, self.z, self.p, self.q = vec(), vec(), vec(), vec(), vec()
        self.minv = ti.Matrix.ndarray(3, 3, dev.real, shape=n if self.precondition else 1)
        self.coef = ti.Vector.ndarray(5, dev.real, shape=max(n_springs, 1))
        self.work_arrays = ("b", "r", "z", "p", "q", "coef", "keep") + (("minv",) if self.precondition else ())
        self.stats = None

    def advance(self, state: State, dt: float, steps: int, check):
        """One implicit step (``steps`` must be 1: each step has its own solver stats).

        Returns (state, good steps done (0 or 1), check code, kinetic energy in J) as
        ``_EulerIntegrator.advance``; on a failed check the state is the previous one.
        """
        assert steps == 1
        d = self.dev
        if self.n_springs:
            operator.spring_coefficients(state.x, d.ends, d.ks, d.kd, d.l0, self.coef, dt, self.fix,
                                         d.has_damping, d.real)
        if self.serial:
            iterations, residual, reason = cg.cg_solve_serial(
                state.v, self.b, self.r, self.z, self.p, self.q, self.minv, state.x, d.mass, d.free,
                d.offsets, d.other, d.spring, d.ks, d.l0, self.coef, d.gravity, dt, self.tol,
                self.max_iter, self.precondition, d.has_gravity, d.has_fixed, d.real)
            reason = int(reason)
        else:
            iterations, residual, reason = self._solve_parallel(state, dt)
        self.stats = SolverStats(int(iterations), float(residual), reason == cg.CONVERGED,
                                 cg.REASONS[reason])
        code, kinetic = cg.advance_positions(state.x, state.v, self.keep, d.mass, d.gravity, dt, check,
                                             self.serial, d.real)
        code = int(code)
        if code != divergence.OK:
            state.v.copy_from(self.keep)
        return state, int(code == divergence.OK), code, float(kinetic)

    def _begin(self, state, dt, with_rhs):
        d = self.dev
        return cg.cg_begin(state.v, self.b, self.r, self.z, self.p, self.minv, state.x,
                           d.mass, d.free, d.offsets, d.other, d.spring, d.ks, d.l0, self.coef,
                           d.gravity, dt, with_rhs, self.precondition, d.has_gravity, d.has_fixed, d.real)

    def _solve_parallel(self, state, dt):
        """PCG on A v = b from the warm start v = v_n; the loop of ``cg.cg_solve_serial``."""
        d = self.dev
        rz, rr, bb = self._begin(state, dt, True)
        if bb == 0.0:
            cg.cg_direction(0.0, self.b, state.v, d.real)  # b = 0, so v = b + 0 v = 0
            return 0, 0.0, cg.CONVERGED
        target = self.tol * self.tol * bb
        iterations, reason, best, done = 0, cg.CONVERGED, 1e308, False
        while not done:
            cycle = 0
            while rr > target and iterations < self.max_iter:
                pq = cg.cg_apply(self.p, self.q, d.mass, d.free, d.offsets, d.other, d.spring,
                                 self.coef, d.has_fixed, d.real)
                if not pq > 0.0 or rz == 0.0:
                    reason = cg.INDEFINITE
                    break
                rz_new, rr = cg.cg_update(rz / pq, state.v, self.r, self.z, self.p, self.q, self.minv,
                                          self.precondition, d.real)
                iterations += 1
                cycle += 1
                cg.cg_direction(rz_new / rz, self.z, self.p, d.real)
                rz = rz_new
            if cycle:
                rz, rr, _ = self._begin(state, dt, False)
            residual = math.sqrt(max(rr, 0.0) / bb) if math.isfinite(rr) else math.inf
            done, reason, best = cg.exit_rule(iterations, residual, self.tol, best, reason, self.max_iter)
        return iterations, residual, reason
