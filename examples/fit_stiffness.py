"""Fit a cloth's stiffness and damping to recorded motion with gradients through its implicit steps.

The "recording" is a run of the shipped ``cloth`` scene (pinned at two corners, falling
under gravity) with its own stiffness and damping; the fit starts from a cloth whose
springs are all 0.5x or 2x as stiff and as damped and finds the two factors again with
scipy's L-BFGS-B, minimising the mean squared distance between the recorded and the
simulated positions over every frame. ``massspring.gradient`` gives the objective's
gradient in every spring's stiffness and damping (the adjoint of each implicit step,
solved with the run's own CG and preconditioner); the chain rule sums them into the
two factors' gradient.

    python examples/fit_stiffness.py [--small] [--resolution 12] [--steps 30]
"""

import argparse
import os

import numpy as np
from scipy.optimize import minimize

import massspring as ms

SOLVER = dict(integrator="implicit", dt=1 / 60, cg_tol=1e-10)


def scaled(base, factors):
    """``base`` with every spring's stiffness and damping multiplied by ``factors`` (2,)."""
    return ms.Model(base.positions, base.springs, masses=base.masses, stiffness=factors[0] * base.stiffness,
                    damping=factors[1] * base.damping, rest_lengths=base.rest_lengths, velocities=base.velocities,
                    gravity=base.gravity, fixed=base.fixed, pin_velocity=base.pin_velocity)


def record(model, steps):
    """The positions of a run of ``model``, every step: (steps + 1, n, 3)."""
    sim = ms.Simulation(model, SOLVER["integrator"], dt=SOLVER["dt"], cg_tol=SOLVER["cg_tol"])
    frames = [sim.positions]
    for _ in range(steps):
        frames.append(sim.step(1).positions)
    sim.close()
    return np.array(frames)


def fit(base, recorded, start, steps):
    """L-BFGS-B from ``start`` (the two factors); returns scipy's result."""
    scale = 1.0 / recorded[0].size

    def misfit(frames):
        diff = frames.positions - recorded
        return 0.5 * scale * np.sum(diff * diff), {"positions": scale * diff}

    def value_and_gradient(factors):
        value, grads = ms.gradient(scaled(base, factors), misfit, ["stiffness", "damping"], steps=steps, **SOLVER)
        return value, np.array([grads["stiffness"] @ base.stiffness, grads["damping"] @ base.damping])

    return minimize(value_and_gradient, start, jac=True, method="L-BFGS-B", bounds=[(1e-3, None)] * 2,
                    options=dict(maxiter=30, ftol=0.0, gtol=1e-14))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick fit: a 6 x 6 cloth over 10 steps (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--resolution", type=int, default=12)
    parser.add_argument("--steps", type=int, default=30, help="recorded steps of 1/60 s (default 30)")
    args = parser.parse_args(argv)
    resolution, steps = (6, 10) if args.small else (args.resolution, args.steps)
    base = ms.load_scene("cloth").with_params(resolution=resolution).model()
    recorded = record(base, steps)
    print(f"cloth {resolution}x{resolution}, {steps} steps of 1/60 s recorded; fitting stiffness and damping "
          f"factors (the truth: 1, 1)")
    for start in (0.5, 2.0):
        result = fit(base, recorded, [start, start], steps)
        error = np.abs(result.x - 1.0).max()
        print(f"from {start:g}x: {result.nit} L-BFGS-B iterations, {result.nfev} gradients: stiffness "
              f"{result.x[0]:.8f}, damping {result.x[1]:.8f} (largest relative error {error:.1e})")


if __name__ == "__main__":
    main()
