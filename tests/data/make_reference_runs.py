"""Make ``reference_runs.npz``: every built-in scene x integrator, f64, 100 steps.

Uses only the public API (``load_scene``, ``Scene.simulation``, ``step``,
``positions``, ``velocities``), so it runs unchanged on any revision. The stored
file was made at commit 1ab4f8d (before the device-layer refactor); the test
``tests/test_regression.py`` compares the current code against it.

    python tests/data/make_reference_runs.py [OUT.npz]
"""

import sys
from pathlib import Path

import numpy as np

import massspring as ms

SCENES = ("bigstep", "chain", "cloth", "compressed", "crumpled", "cube", "heavychain", "spring",
          "stiffchain", "stiffcloth", "zerolength")
INTEGRATORS = ("explicit", "symplectic", "implicit")
STEPS = 100


def main(out):
    data = {}
    for scene_name in SCENES:
        scene = ms.load_scene(scene_name)
        for integrator in INTEGRATORS:
            sim = scene.simulation(integrator=integrator)
            key = f"{scene_name}/{integrator}"
            try:
                sim.step(STEPS)
                diverged = 0
            except ms.DivergenceError as exc:
                diverged = exc.step
            data[f"{key}/positions"] = sim.positions
            data[f"{key}/velocities"] = sim.velocities
            data[f"{key}/steps"] = np.array(sim.steps)
            data[f"{key}/diverged_at"] = np.array(diverged)
            data[f"{key}/dt"] = np.array(sim.dt)
            print(key, sim.steps, "diverged at %d" % diverged if diverged else "")
            sim.close()
    np.savez_compressed(out, **data)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).with_name("reference_runs.npz"))
