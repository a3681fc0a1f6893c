"""Errors a run can raise after its input was accepted."""

from __future__ import annotations

import math

from massspring.support.text import format_seconds


class DivergenceError(RuntimeError):
    """A step produced a non-finite or runaway state; the simulation kept the last good one.

    Attributes: ``step`` (1-based number of the step that failed), ``time`` (s,
    simulated time that step would have reached), ``cause`` ("non-finite" or
    "runaway"), ``energy`` (J, the energy of the rejected state that the check held to
    the bound: ``measured`` names it, "kinetic energy" for the explicit and linearised ones,
    "kinetic and spring energy" for the Newton-solved ones), ``kinetic`` (the same number,
    its older name), ``bound`` (J, the bound it was checked against), ``integrator``
    and ``dt``. After the error ``Simulation.positions``/``velocities`` are those of
    step ``step - 1`` and ``Simulation.steps == step - 1``.
    """

    def __init__(self, step, time, cause, energy, bound, integrator, dt, measured="kinetic energy"):
        self.step, self.time, self.cause = int(step), float(time), cause
        self.energy, self.bound, self.measured = float(energy), float(bound), measured
        self.kinetic = self.energy
        self.integrator, self.dt = integrator, float(dt)
        if cause == "non-finite":
            what = "non-finite position or velocity (NaN or Inf)"
        else:
            what = f"runaway growth: {measured} {self.energy:.3g} J above the bound {self.bound:.3g} J"
        super().__init__(f"{integrator} diverged at step {self.step} "
                         f"(t = {self.time:.6g} s, dt = {format_seconds(self.dt)}): "
                         f"{what}; the state of step {self.step - 1} is kept")


class SimulationClosedError(RuntimeError):
    """A Simulation was used after ``close()``: its fields may belong to another run now."""


class GradientError(RuntimeError):
    """A backward pass could not solve a step's adjoint system (``massspring.gradients``).

    Attributes: ``step`` (0-based number of the step whose adjoint failed, from the
    run's start), ``reason`` (the solver's: "max_iter", "indefinite", "stalled" or
    "non-finite"; CG's, or for a Newton-solved step with the definiteness fix MINRES's)
    and ``residual`` (its true relative residual at exit).
    """

    def __init__(self, step, reason, residual, integrator):
        self.step, self.reason, self.residual = int(step), reason, float(residual)
        advice = "Give a larger cg_max_iter or a looser cg_tol, or a smaller dt"
        if reason == "stalled":
            advice = ("Give a looser cg_tol or a smaller dt, or use the linearised 'implicit' integrator (its adjoint "
                      "is one solve with its own positive definite operator): the solve no longer reduces its "
                      "residual, at round-off or where a Newton-solved step's Jacobian is nearly singular")
        super().__init__(f"{integrator} gradient: the adjoint solve of step {self.step + 1} stopped "
                         f"({reason}, relative residual {self.residual:.3g}); no gradient is returned. {advice}")


class PassGradientError(GradientError):
    """A gradient's backward pass stopped at a step (``step``, 0-based) whose pass
    (``reason``: "self-collision" or "strain limit") it cannot run backwards (``why``)
    (``massspring.gradients``). ``residual`` is NaN."""

    reason_text = ""

    def __init__(self, step, integrator, why):
        self.step, self.reason, self.residual = int(step), self.reason_text, math.nan
        RuntimeError.__init__(self, f"{integrator} gradient: the {self.reason} of step {self.step + 1} could not be "
                                    f"run backwards: {why}. No gradient is returned: take fewer steps or a smaller dt")


class SelfCollisionGradientError(PassGradientError):
    """The self-collision pass of a step could not be run backwards: a pass the host could
    not replay as the run took it, or pairs of the linearised step's solve that it could
    not solve again. ``reason`` is "self-collision"."""

    reason_text = "self-collision"


class StrainLimitGradientError(PassGradientError):
    """The strain limit of a step could not be run backwards: its iterations run again
    from the step's state did not give the state the run kept. ``reason`` is "strain limit"."""

    reason_text = "strain limit"


class KinkWarning(RuntimeWarning):
    """A gradient taken where the run is not differentiable: ``massspring.gradient``
    starting from springs at their rest length with the definiteness fix on, whose clamp
    has a kink there (the derivative is one side's; central differences straddle it)."""

