"""A run's memory estimate and the preconditioner it resolves to: one computation for
``Simulation`` (from its Model) and for a scene (from its counts, before its arrays are
built), so the two cannot drift apart."""

from __future__ import annotations

from dataclasses import dataclass

from massspring.integrators import INTEGRATORS
from massspring.passes import for_model
from massspring.passes.self_collision.forward import SOLVE_BYTES
from massspring.solvers import CHOICES, resolve_for_count
from massspring.support import memory, validate


@dataclass(frozen=True)
class Sketch:
    """What the estimate reads of a model: its counts and the features that add fields
    (the attributes of ``Model`` that integrators' and passes' ``wanted``-style checks read)."""

    n_particles: int
    n_springs: int
    n_free: int
    has_self_collision: bool = False
    has_strain_limit: bool = False

    @classmethod
    def of(cls, model) -> "Sketch":
        return cls(model.n_particles, model.n_springs, int(model.free_mask().sum()), model.has_self_collision,
                   model.has_strain_limit)


def preconditioner(sketch, integrator, precision, name) -> str | None:
    """The preconditioner ``name`` ("auto" or one of ``solvers.CHOICES``) stands for in a
    run of ``integrator`` on ``sketch``; None for an integrator without a linear solve. An
    unknown ``name`` is a ValueError naming "preconditioner"."""
    validate.choice("preconditioner", name, CHOICES)
    cls = INTEGRATORS[integrator]
    if not cls.traits.linear_solver:
        return None
    return resolve_for_count(name, sketch.n_free, cls.finest_f32(sketch, precision))


def run_bytes(sketch, integrator, precision="f64", preconditioner_name="auto", model_built=False) -> float:
    """Bytes a run of ``integrator`` on ``sketch`` may add at its peak (``memory.run_bytes``,
    margin included): the linearised step's per-particle and per-spring bytes for its
    preconditioner, the integrator's own (its ``traits``' ``extra_bytes``, ``spring_extra_bytes``), the
    self-collision pairs of its solve, and every pass's (``Pass.bytes``). ``model_built``:
    the Model's own arrays exist already."""
    cls = INTEGRATORS[integrator]
    per_particle = cls.traits.extra_bytes + SOLVE_BYTES * cls.pairs_in_solve(sketch)
    per_spring = cls.traits.spring_extra_bytes
    for pass_cls in for_model(sketch):
        particle_bytes, spring_bytes = pass_cls.bytes(sketch)
        per_particle += particle_bytes
        per_spring += spring_bytes
    return memory.run_bytes(sketch.n_particles, sketch.n_springs,
                            preconditioner(sketch, integrator, precision, preconditioner_name),
                            model_built=model_built, extra=per_particle, spring_extra=per_spring)
