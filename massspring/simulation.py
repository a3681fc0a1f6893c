"""``Simulation``: a Model turned into Taichi arrays, stepped by one integrator."""

from __future__ import annotations

import contextlib
import io
import numbers
import weakref

import numpy as np
import taichi as ti
from taichi.lang import impl

from massspring.errors import DivergenceError
from massspring.integrators import (REAL, SERIAL_BELOW, DeviceModel, ExplicitEuler, ImplicitEuler,
                                    State, SymplecticEuler)
from massspring.kernels import divergence
from massspring.model import Model

INTEGRATORS = {"explicit": ExplicitEuler, "symplectic": SymplecticEuler, "implicit": ImplicitEuler}
PRECISIONS = tuple(REAL)
PRECONDITIONERS = ("block-jacobi", "none")
STORAGES = ("auto", "ndarray", "field")
LOOPS = ("auto", "serial", "parallel")
# Springs from which "auto" storage uses fields: 1.3-2x faster kernels from a
# 32 x 32 cloth (5.8k springs) on (benchmarks/switch_point.py), for about 1 s of
# compilation per new size of simulation (storage.FieldPool reuses fields).
FIELDS_FROM = 4_000
MAX_INT32 = 2**31 - 1  # kernels count in int32
STEPS_PER_LAUNCH = 2**30  # explicit steps per kernel call at most (the count is an int32 there)
ARCHS = ("cpu", "gpu", "cuda", "vulkan", "metal", "opengl", "x64", "arm64")


def ensure_taichi(arch="cpu"):
    """Initialise Taichi once per process on ``arch``; later calls must agree with it.

    If Taichi cannot start on ``arch`` (no such device: it falls back to the CPU),
    this raises ValueError rather than silently running elsewhere.
    """
    if arch not in ARCHS:
        raise ValueError(f"arch: unknown value {arch!r}, expected one of {', '.join(ARCHS)}")
    wanted = getattr(ti, arch)
    accepted = [ti.x64, ti.arm64] if arch == "cpu" else wanted if isinstance(wanted, list) else [wanted]
    started = impl.get_runtime().prog is None
    if started:
        with contextlib.redirect_stdout(io.StringIO()):  # "[Taichi] Starting on arch=..."
            ti.init(arch=wanted, default_fp=ti.f64, log_level=ti.ERROR if arch != "cpu" else ti.WARN)
    current = impl.current_cfg().arch
    if current not in accepted:
        if started:
            raise ValueError(f"arch: {arch!r} is not available here; Taichi started on {current.name} instead")
        raise ValueError(f"arch: Taichi already runs on {current.name} in this process; "
                         f"cannot switch to {arch!r}")


DIVERGENCE_FACTOR = 100.0  # see divergence_check


def divergence_check(model: Model, factor=DIVERGENCE_FACTOR):
    """The (base, gx0, factor) of the per-step divergence check (kernels/divergence.py).

    A state is rejected if a position or velocity is not finite, or if its kinetic
    energy exceeds ``factor * (base + W)`` with W >= 0 the work gravity has done
    since the start (sum m g . (x - x0)). ``base`` (J) is the initial kinetic plus
    spring energy plus a floor, the kinetic energy of the whole mass moving at one
    scene size per second (size: the diagonal of the initial bounding box, or the
    longest rest length if larger; 1 m if both are 0). Physically kinetic energy
    never exceeds base - floor + W (springs only store and dampers only dissipate),
    so ``factor`` = 100 leaves room for the energy error of a stable integrator
    (symplectic Euler's oscillates by up to ~40x just below its limit) while an
    unstable mode, growing geometrically, crosses it within a few dozen steps.
    """
    energy = model.energy(model.positions, model.velocities)
    extent = float(np.linalg.norm(np.ptp(model.positions, axis=0)))
    size = max(extent, float(model.rest_lengths.max(initial=0.0))) or 1.0
    floor = 0.5 * float(model.masses.sum()) * size ** 2
    return (energy["kinetic"] + energy["spring"] + floor, -energy["gravity"], float(factor))


def default_cg_max_iter(model: Model) -> int:
    """3 x (free particles): the exact-arithmetic bound of CG on the free DOFs, at least 100."""
    free = model.n_particles - model.fixed.size
    return max(100, 3 * free)


class Simulation:
    """Steps a :class:`Model` with one integrator on Taichi kernels.

    Parameters
    ----------
    model : Model
    integrator : "explicit" | "symplectic" | "implicit"
    dt : float, s, > 0
    precision : "f64" (default) | "f32"
    cg_tol : float in (0, 1)
        Implicit only: relative tolerance on the true residual ||b - A v|| / ||b||.
    cg_max_iter : int or None
        Implicit only: iteration limit per step; None means ``default_cg_max_iter``.
    definiteness_fix : bool
        Implicit only: clamp the transverse stiffness of compressed springs so that
        the system stays positive definite (see kernels/operator.py).
    preconditioner : "block-jacobi" (default) | "none"
    storage : "auto" (default) | "ndarray" | "field"
        Taichi ndarrays (kernels compiled once for all simulations) or fields (1.3-2x
        faster kernels, compiled again for each new size; released fields are pooled
        and reused, see ``storage.FieldPool``); "auto" picks fields from
        ``FIELDS_FROM`` springs on.
    loops : "auto" (default) | "serial" | "parallel"
        Serial kernels (a whole CG solve, or many explicit steps, per launch) or
        parallel kernels (one launch per phase). Both give the same results to
        round-off; "auto" picks parallel from ``integrators.SERIAL_BELOW`` springs on
        the CPU, and always on other archs.
    arch : Taichi arch name, "cpu" by default.

    Only what the run needs is allocated and compiled: no CG vectors for the
    explicit integrators, no damping term with kd = 0, no gravity term with g = 0,
    no fixed-particle filter without fixed particles (see ``info()``).
    """

    def __init__(self, model, integrator="implicit", dt=1e-2, precision="f64", cg_tol=1e-6,
                 cg_max_iter=None, definiteness_fix=True, preconditioner="block-jacobi", arch="cpu",
                 storage="auto", loops="auto"):
        if not isinstance(model, Model):
            raise ValueError(f"model: expected a massspring.Model, got {type(model).__name__}")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator: unknown value {integrator!r}, expected one of "
                             f"{', '.join(INTEGRATORS)}")
        if precision not in PRECISIONS:
            raise ValueError(f"precision: unknown value {precision!r}, expected one of {', '.join(PRECISIONS)}")
        dt = _positive_float("dt", dt)
        cg_tol = _positive_float("cg_tol", cg_tol)
        if cg_tol >= 1:
            raise ValueError(f"cg_tol: must be < 1, got {cg_tol}")
        if cg_max_iter is None:
            cg_max_iter = default_cg_max_iter(model)
        elif isinstance(cg_max_iter, bool) or not isinstance(cg_max_iter, numbers.Integral) or \
                not 1 <= cg_max_iter <= MAX_INT32:
            raise ValueError(f"cg_max_iter: expected an integer within 1..{MAX_INT32} or None, got {cg_max_iter!r}")
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner: unknown value {preconditioner!r}, expected one of "
                             f"{', '.join(PRECONDITIONERS)}")
        if loops not in LOOPS:
            raise ValueError(f"loops: unknown value {loops!r}, expected one of {', '.join(LOOPS)}")
        if storage not in STORAGES:
            raise ValueError(f"storage: unknown value {storage!r}, expected one of {', '.join(STORAGES)}")
        ensure_taichi(arch)

        self.model = model
        self.integrator = integrator
        self.dt = dt
        self.precision = precision
        self.cg_tol = cg_tol
        self.cg_max_iter = int(cg_max_iter)
        self.definiteness_fix = bool(definiteness_fix)
        self.preconditioner = preconditioner
        self.arch = arch
        self.steps = 0
        self.cg_iterations = []
        self.cg_failures = 0
        self.check = divergence_check(model)

        if storage == "auto":
            storage = "field" if model.n_springs >= FIELDS_FROM else "ndarray"
        self.storage = storage
        self._dev = DeviceModel.upload(model, precision, storage)
        self._state = State.upload(self._dev.real, model.positions, model.velocities, storage)
        if loops == "auto":
            loops = "serial" if model.n_springs < SERIAL_BELOW and arch in ("cpu", "x64", "arm64") else "parallel"
        self.loops = loops
        serial = loops == "serial"
        if integrator == "implicit":
            self._integrator = ImplicitEuler(self._dev, self._state, serial=serial, cg_tol=cg_tol,
                                             cg_max_iter=self.cg_max_iter,
                                             definiteness_fix=self.definiteness_fix,
                                             preconditioner=preconditioner)
        else:
            self._integrator = INTEGRATORS[integrator](self._dev, self._state, serial=serial)
        self._release = weakref.finalize(self, _release_all,
                                         (self._dev.arrays, self._state.arrays, self._integrator.arrays))

    @property
    def time(self) -> float:
        """Simulated time (s): steps x dt."""
        return self.steps * self.dt

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) float64 copy of the current positions (m)."""
        return self._state.x.to_numpy().astype(np.float64)

    @property
    def velocities(self) -> np.ndarray:
        """(n, 3) float64 copy of the current velocities (m/s)."""
        return self._state.v.to_numpy().astype(np.float64)

    @property
    def solver_stats(self):
        """The last implicit step's ``SolverStats`` (None before the first step or if explicit)."""
        return getattr(self._integrator, "stats", None)

    def step(self, n=1):
        """Advance ``n`` steps of size ``dt``.

        Every step is checked (``divergence_check``). A step whose state has a
        non-finite value or runaway kinetic energy raises ``DivergenceError``
        naming it; the simulation then holds the last good state (``steps``,
        ``time``, ``positions`` and ``velocities`` are those of the step before).
        """
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 0:
            raise ValueError(f"n: expected a non-negative integer, got {n!r}")
        if self.integrator != "implicit":
            while n:
                chunk = min(n, STEPS_PER_LAUNCH)
                self._state, done, code, kinetic = self._integrator.advance(self._state, self.dt, chunk, self.check)
                self.steps += done
                self._raise_if_diverged(code, kinetic)
                n -= chunk
            return self
        for _ in range(n):
            self._state, done, code, kinetic = self._integrator.advance(self._state, self.dt, 1, self.check)
            if done:
                self.steps += 1
                stats = self._integrator.stats
                self.cg_iterations.append(stats.iterations)
                self.cg_failures += not stats.converged
            self._raise_if_diverged(code, kinetic)
        return self

    def _raise_if_diverged(self, code, kinetic):
        if code == divergence.OK:
            return
        positions = self.positions
        work = max(0.0, float(np.sum(self.model.masses * (positions @ self.model.gravity))) - self.check[1])
        bound = self.check[2] * (self.check[0] + work)
        failed = self.steps + 1
        raise DivergenceError(failed, failed * self.dt, divergence.CAUSES[code], kinetic, bound,
                              self.integrator, self.dt)

    def energy(self) -> dict:
        """Kinetic, spring, gravity and total energy (J) of the current state."""
        return self.model.energy(self.positions, self.velocities)

    def info(self) -> dict:
        """What this run compiled and allocated: force terms, arrays and their bytes."""
        sets = (self._dev.arrays, self._state.arrays, self._integrator.arrays)
        return {"integrator": self.integrator, "precision": self.precision, "dt": self.dt,
                "particles": self.model.n_particles, "springs": self.model.n_springs,
                "terms": self._dev.terms(), "arrays": ["x", "v"] + list(self._integrator.work_arrays),
                "storage": self.storage, "loops": self.loops, "bytes": sum(a.nbytes() for a in sets)}

    def close(self):
        """Release the Taichi fields of a ``storage="field"`` run now (else when garbage-collected)."""
        self._release()


def _release_all(sets):
    for arrays in sets:
        arrays.release()


def _positive_float(name, value):
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(out) or out <= 0:
        raise ValueError(f"{name}: must be a finite number > 0, got {value!r}")
    return out
