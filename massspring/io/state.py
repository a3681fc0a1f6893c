"""A simulation's state as a ``.npz`` file (``run --out``).

Keys: ``positions``, ``velocities`` (n, 3) float64; ``springs`` (m, 2) int;
``time`` (s), ``steps``, ``dt`` (s).
"""

from __future__ import annotations

import numpy as np

from massspring.io.files import atomic_output


def write_state(sim, path):
    """Write ``sim``'s current state to ``path`` (.npz), atomically."""
    with atomic_output(path) as fh:
        np.savez(fh, positions=sim.positions, velocities=sim.velocities,
                 springs=sim.model.springs, time=sim.time, steps=sim.steps, dt=sim.dt)
