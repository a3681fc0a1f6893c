"""Implicit midpoint solved by Newton's method (``kernels/newton.py``)."""

from __future__ import annotations

from massspring.kernels import newton

from .newton import BackwardEuler


class Midpoint(BackwardEuler):
    """M (v' - v_n) = dt f((x_n + x')/2, (v_n + v')/2), x' = x_n + dt (v_n + v')/2.

    With w = (v_n + v')/2 the midpoint is x_n + (dt/2) w, so the step is backward Euler's
    equation (*) of ``kernels/newton.py`` with the base (x_n, v_n) and h = dt/2, solved for
    w, then v' = 2 w - v_n and x' = x_n + dt w (``newton.midpoint_finish``). Second order,
    symplectic, A-stable without numerical damping; it conserves the energy of a linear
    undamped system (a quadratic invariant) up to the solver's tolerance.

    The line search's merit function is backward Euler's incremental potential at h = dt/2,
    E(w) = 1/2 (w - v_n)^T M (w - v_n) + U(x_n + h w) + h Psi(w): its gradient is the
    midpoint residual divided by 2 (with Rayleigh damping at w, along the springs'
    directions at x_n + h v_n: ``kernels/newton.py``), so every solution of the
    step is a stationary point of it, and the Newton direction (from the definite,
    fixed operator) descends on it. A step with a particle in contact is a backward-Euler
    step (h = dt, v' = w), as BDF2's is: an impact makes the velocity jump, and
    extrapolating w across it would bounce the particle back (contact is first order in
    every integrator).
    """

    name = "midpoint"
    order = 2
    description = "implicit midpoint (second order, symplectic) solved by Newton's method with a line search"
    half_step = True

    def ahead(self, h):
        return h

    def step_size(self, touching):
        return self.settings.dt if touching else 0.5 * self.settings.dt

    def finish(self, h, touching):
        if not touching:
            newton.midpoint_finish(self.dev, self.cfg, h)
