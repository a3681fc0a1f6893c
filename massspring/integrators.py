"""Time integrators: each a few kernel calls over the same device arrays.

``DeviceModel`` is a Model turned into Taichi arrays once; ``State`` holds the
particle positions and velocities. Each integrator allocates only the work arrays
it needs: the explicit ones a second state to step into, the implicit one the CG
vectors. Arrays a run does not need are passed to kernels as 1-element
placeholders and never read (the code that would read them is compiled out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import taichi as ti

from massspring.kernels import cg, divergence, forces, operator
from massspring.storage import ArraySet

REAL = {"f32": ti.f32, "f64": ti.f64}
# Springs below which serial kernels beat parallel ones on this project's 2-core CPU
# machine, where a parallel loop's launch costs ~0.1-0.2 ms and two threads give
# ~1.3x (measured by benchmarks/switch_point.py: serial wins at 97k springs, parallel
# at 391k). Simulation(loops=...) overrides it.
SERIAL_BELOW = 200_000


@dataclass
class DeviceModel:
    """The parts of a Model the kernels read, as Taichi arrays (see kernels/forces.py).

    Arrays a run does not need (``kd`` without damping, ``free`` without fixed
    particles) are 1-element placeholders.
    """

    real: object
    mass: object
    free: object
    offsets: object
    other: object
    spring: object
    ks: object
    kd: object
    l0: object
    gravity: tuple
    has_damping: bool
    has_gravity: bool
    has_fixed: bool
    n_springs: int
    arrays: ArraySet

    @classmethod
    def upload(cls, model, precision, storage="ndarray"):
        real = REAL[precision]
        offsets, other, spring = model.adjacency()
        has_damping, has_fixed = model.has_damping, model.has_fixed
        n, m = model.n_particles, model.n_springs
        arrays = ArraySet(storage)
        arrays.add("mass", real, n, values=model.masses)
        arrays.add("free", ti.i32, n if has_fixed else 1, values=model.free_mask() if has_fixed else None)
        arrays.add("offsets", ti.i32, n + 1, values=offsets)
        arrays.add("other", ti.i32, 2 * m, values=other)
        arrays.add("spring", ti.i32, 2 * m, values=spring)
        arrays.add("ks", real, m, values=model.stiffness)
        arrays.add("kd", real, m if has_damping else 1, values=model.damping if has_damping else None)
        arrays.add("l0", real, m, values=model.rest_lengths)
        built = arrays.build()
        return cls(real=real, **built, gravity=tuple(float(c) for c in model.gravity),
                   has_damping=has_damping, has_gravity=model.has_gravity, has_fixed=has_fixed,
                   n_springs=m, arrays=arrays)

    def terms(self):
        """Names of the force terms compiled into this run's kernels."""
        return ["spring"] + (["damping"] if self.has_damping else []) + \
            (["gravity"] if self.has_gravity else []) + (["fixed-filter"] if self.has_fixed else [])


@dataclass
class State:
    """Particle positions x (m) and velocities v (m/s): (n,) vec3 arrays."""

    x: object
    v: object
    arrays: ArraySet

    @classmethod
    def upload(cls, real, positions, velocities, storage="ndarray"):
        arrays = ArraySet(storage)
        arrays.vectors("x", real, len(positions), positions)
        arrays.vectors("v", real, len(positions), velocities)
        return cls(**arrays.build(), arrays=arrays)


@dataclass(frozen=True)
class SolverStats:
    """Outcome of one implicit step's CG solve.

    iterations: CG iterations; residual: true relative residual ||b - A v|| / ||b||
    recomputed at exit; converged: residual <= tolerance; reason: why CG stopped
    ("converged", "max_iter", "indefinite" when p.Ap <= 0, "stalled" when a restart
    from the true residual no longer reduces it, as f32 round-off can cause,
    "non-finite" when the right-hand side or the residual overflowed).
    """

    iterations: int
    residual: float
    converged: bool
    reason: str

    def __getitem__(self, key):
        return getattr(self, key)


class _EulerIntegrator:
    """Explicit (Eq. 7-8) or symplectic Euler: one fused kernel per step into a spare state.

    ``serial``: many steps per launch with serial loops (small systems, where a
    launch costs more than a step), else one parallel launch per step.
    """

    symplectic = False
    work_arrays = ("x_next", "v_next")

    def __init__(self, dev: DeviceModel, state: State, serial=True):
        self.dev = dev
        n = state.x.shape[0]
        self.arrays = ArraySet(dev.arrays.kind)
        self.arrays.vectors("x", dev.real, n)
        self.arrays.vectors("v", dev.real, n)
        self.spare = State(**self.arrays.build(), arrays=self.arrays)
        self.serial = serial

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

    ``serial``: run the whole solve in one serial kernel, else the parallel kernels,
    one launch per phase. Both run the same algorithm and agree to round-off.
    """

    def __init__(self, dev: DeviceModel, state: State, *, cg_tol, cg_max_iter,
                 definiteness_fix=True, preconditioner="block-jacobi", serial=True):
        self.dev = dev
        # CG overwrites v in place (v_n is its warm start). ``keep`` holds the velocity
        # of the last accepted state: cg.advance_positions writes it in the same loop
        # that commits x_{n+1}, so keeping it costs one store per particle and no
        # launch, and a rejected step is undone by copying it back (x_n was never
        # overwritten). Cheaper than copying v_n before every solve: no extra pass.
        self.tol = cg_tol
        self.max_iter = cg_max_iter
        self.fix = definiteness_fix
        self.precondition = preconditioner == "block-jacobi"
        self.n_springs = n_springs = dev.n_springs
        self.serial = serial
        n = state.x.shape[0]
        self.arrays = ArraySet(dev.arrays.kind)
        for name in ("b", "r", "z", "p", "q"):
            self.arrays.vectors(name, dev.real, n)
        self.arrays.vectors("keep", dev.real, n, state.v.to_numpy())
        self.arrays.add("minv", dev.real, n if self.precondition else 1, (3, 3))
        self.arrays.vectors("coef", dev.real, 2 * n_springs, k=5)
        for name, array in self.arrays.build().items():
            setattr(self, name, array)
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
            operator.entry_coefficients(state.x, d.offsets, d.other, d.spring, d.ks, d.kd, d.l0, self.coef,
                                        dt, self.fix, d.has_damping, self.serial, d.real)
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
        if reason == cg.NONFINITE:  # Eq. 15 overflowed: no velocity to step with
            state.v.copy_from(self.keep)
            return state, 0, divergence.NONFINITE, math.inf
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
        if not math.isfinite(bb):
            return 0, math.inf, cg.NONFINITE
        if bb == 0.0:
            cg.cg_direction(0.0, self.b, state.v, d.real)  # b = 0, so v = b + 0 v = 0
            return 0, 0.0, cg.CONVERGED
        target = self.tol * self.tol * bb
        iterations, reason, best, done = 0, cg.CONVERGED, 1e308, False
        while not done:
            cycle = 0
            while rr > target and iterations < self.max_iter:
                pq = cg.cg_apply(self.p, self.q, d.mass, d.free, d.offsets, d.other, self.coef,
                                 d.has_fixed, d.real)
                if not (math.isfinite(pq) and pq > 0.0) or rz == 0.0:
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
            done, reason, best = cg.exit_rule(math.isfinite(residual), iterations, cycle, residual, self.tol, best,
                                              reason, self.max_iter)
        return iterations, residual, reason
