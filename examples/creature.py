"""A mass-spring creature that learns to crawl forward on the ground by gradient descent.

The creature is a 5 x 2 lattice of particles (0.1 m apart, in the x-z plane) with
springs along its rows, columns and diagonals, standing on a ground plane with
friction. Its "muscles" are the springs of its bottom row and its columns: their
rest lengths change every interval of 0.05 s (``ms.Controls(rest_lengths=...)``).
The objective is the distance its centre of mass moves along x in 1 s; its gradient
in every muscle's rest length in every interval comes from ``ms.gradient`` through
the symplectic steps and the contact with the ground (the gradient of each contact
as it was taken: sticking or sliding). SciPy's L-BFGS-B raises the distance within
bounds of +-25% on every rest length, from a gait that does nothing (all at rest).

    python examples/creature.py [--small] [--iterations 30] [--seconds 1]
"""

import argparse
import os

import numpy as np
from scipy.optimize import minimize

import massspring as ms

SPACING = 0.1  # m
COLUMNS, ROWS = 5, 2
INTERVAL = 0.05  # s: one set of muscle lengths
DT = 1e-3  # s
STRETCH = 0.25  # a muscle's rest length stays within (1 +- STRETCH) of its own


def lattice():
    """Positions (n, 3), springs (m, 2) and the muscles (indices of springs)."""
    index = lambda i, j: j * COLUMNS + i  # noqa: E731
    positions = np.array([[i * SPACING, 0.0, 0.002 + j * SPACING] for j in range(ROWS) for i in range(COLUMNS)])
    springs, muscles = [], []
    for j in range(ROWS):
        for i in range(COLUMNS):
            if i + 1 < COLUMNS:
                if j == 0:
                    muscles.append(len(springs))
                springs.append([index(i, j), index(i + 1, j)])
            if j + 1 < ROWS:
                muscles.append(len(springs))
                springs.append([index(i, j), index(i, j + 1)])
            if i + 1 < COLUMNS and j + 1 < ROWS:
                springs += [[index(i, j), index(i + 1, j + 1)], [index(i + 1, j), index(i, j + 1)]]
    return positions, np.array(springs), np.array(muscles)


def creature(lengths, muscles, intervals):
    """The model with muscle rest lengths ``lengths`` (intervals, muscles)."""
    positions, springs, _ = lattice()
    controls = ms.Controls(INTERVAL, springs=muscles, rest_lengths=lengths.reshape(intervals, muscles.size))
    ground = ms.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), friction=1.0)
    return ms.Model(positions, springs, masses=0.05, stiffness=300.0, damping=0.5, colliders=[ground],
                    controls=controls)


def distance(frames):
    """L = minus the centre of mass's move along x (a minimum crawls furthest)."""
    n = frames.positions.shape[1]
    partials = np.zeros_like(frames.positions)
    partials[-1, :, 0] = -1.0 / n
    return -(frames.positions[-1, :, 0].mean() - frames.positions[0, :, 0].mean()), {"positions": partials}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run: 0.25 s of crawling, 5 iterations (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--iterations", type=int, default=30, help="L-BFGS-B iterations at most (default 30)")
    parser.add_argument("--seconds", type=float, default=1.0, help="crawling time (default 1 s)")
    args = parser.parse_args(argv)
    seconds, iterations = (0.25, 5) if args.small else (args.seconds, args.iterations)
    intervals = max(1, round(seconds / INTERVAL))
    steps = round(intervals * INTERVAL / DT)
    _, springs, muscles = lattice()
    rest = np.linalg.norm(np.diff(lattice()[0][springs[muscles]], axis=1)[:, 0], axis=1)
    start = np.tile(rest, intervals)
    bounds = list(zip((1 - STRETCH) * start, (1 + STRETCH) * start))
    history = []

    def value_and_gradient(lengths):
        value, grads = ms.gradient(creature(lengths, muscles, intervals), distance, "controls.rest_lengths",
                                   steps=steps, every=steps, integrator="symplectic", dt=DT)  # the last frame
        history.append(-value)
        return value, grads["controls.rest_lengths"].ravel()

    print(f"creature: {COLUMNS * ROWS} particles, {springs.shape[0]} springs, {muscles.size} muscles x "
          f"{intervals} intervals of {INTERVAL:g} s; {steps} symplectic steps of {DT:g} s per run")
    result = minimize(value_and_gradient, start, jac=True, method="L-BFGS-B", bounds=bounds,
                      options=dict(maxiter=iterations))
    said = str(result.message).strip().rstrip(":")
    if result.success:
        print(f"L-BFGS-B converged ({said})")
    elif result.nit < iterations:  # the contacts make the distance piecewise smooth: a step can end on a kink
        print(f"L-BFGS-B stopped ({said}): its line search found no decrease along the gradient, which the "
              "contacts with the ground make piecewise smooth (sticking and sliding switch between nearby gaits)")
    print(f"at rest: moved {history[0] * 100:.2f} cm; after {result.nit} L-BFGS-B iterations "
          f"({len(history)} gradients): moved {-result.fun * 100:.2f} cm forward in {intervals * INTERVAL:g} s")
    return history[0], -result.fun


if __name__ == "__main__":
    main()
