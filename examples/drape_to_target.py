"""Rest lengths that make a hanging cloth take a target shape, by gradients through its implicit steps.

The target is the shape a cloth pinned at two corners hangs in after ``--steps`` steps
when its springs' rest lengths follow a smooth pattern (shorter along the middle, a
gathered hem); the design starts from the shipped ``cloth`` scene's rest lengths, whose
shape differs by centimetres. SciPy's L-BFGS-B moves every spring's rest length (within
+-30%) to bring each particle to its target, minimising the mean squared distance at
the last frame; ``massspring.gradient`` gives its gradient in every rest length (one
adjoint solve per implicit step with the run's own CG). Rest lengths are not unique
(many patterns hang alike), so the shape, not the pattern, is what is recovered.

    python examples/drape_to_target.py [--small] [--resolution 10] [--steps 60]
"""

import argparse
import os

import numpy as np
from scipy.optimize import minimize

import massspring as ms

SOLVER = dict(integrator="implicit", dt=1 / 60, cg_tol=1e-10)


def with_rest_lengths(base, lengths):
    return ms.Model(base.positions, base.springs, masses=base.masses, stiffness=base.stiffness,
                    damping=base.damping, rest_lengths=lengths, gravity=base.gravity, fixed=base.fixed)


def last_frame(model, steps):
    sim = ms.Simulation(model, SOLVER["integrator"], dt=SOLVER["dt"], cg_tol=SOLVER["cg_tol"])
    positions = sim.step(steps).positions
    sim.close()
    return positions


def target_lengths(base):
    """A smooth pattern: springs near the cloth's middle (in x) 15% shorter, the hem's 10%."""
    mid = base.positions[base.springs].mean(axis=1)
    x = (mid[:, 0] - mid[:, 0].min()) / np.ptp(mid[:, 0])
    y = (mid[:, 1] - mid[:, 1].min()) / np.ptp(mid[:, 1])
    return base.rest_lengths * (1 - 0.15 * np.exp(-((x - 0.5) / 0.2) ** 2) - 0.10 * y ** 4)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick design: a 6 x 6 cloth over 20 steps (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--resolution", type=int, default=10)
    parser.add_argument("--steps", type=int, default=60, help="steps of 1/60 s before the shape is taken (default 60)")
    parser.add_argument("--iterations", type=int, default=40, help="L-BFGS-B iterations at most (default 40)")
    args = parser.parse_args(argv)
    resolution, steps = (6, 20) if args.small else (args.resolution, args.steps)
    base = ms.load_scene("cloth").with_params(resolution=resolution).model()
    target = last_frame(with_rest_lengths(base, target_lengths(base)), steps)
    scale = 1.0 / target.size

    def misfit(frames):
        diff = frames.positions[-1] - target
        partials = np.zeros_like(frames.positions)
        partials[-1] = scale * diff
        return 0.5 * scale * np.sum(diff * diff), {"positions": partials}

    def value_and_gradient(lengths):
        value, grads = ms.gradient(with_rest_lengths(base, lengths), misfit, "rest_lengths", steps=steps, every=steps,
                                   **SOLVER)
        return value, grads["rest_lengths"]

    start = base.rest_lengths
    first = np.abs(last_frame(base, steps) - target).max()
    print(f"cloth {resolution}x{resolution}, {base.n_springs} rest lengths, shape after {steps} steps of 1/60 s; "
          f"from the scene's rest lengths the farthest particle is {first * 100:.2f} cm off its target")
    result = minimize(value_and_gradient, start, jac=True, method="L-BFGS-B",
                      bounds=list(zip(0.7 * start, 1.3 * start)), options=dict(maxiter=args.iterations))
    last = np.abs(last_frame(with_rest_lengths(base, result.x), steps) - target).max()
    print(f"L-BFGS-B: {str(result.message).strip()}")
    print(f"after {result.nit} L-BFGS-B iterations ({result.nfev} gradients): the farthest particle is "
          f"{last * 100:.3f} cm off ({first / last:.0f}x closer)")
    return first, last


if __name__ == "__main__":
    main()
