"""Make ``reference_runs.npz``: every built-in scene x integrator, f64, 100 steps
at the scene's default dt, the implicit one with CG to a relative residual of 1e-12
(so that a change in summation order shows as round-off, not as CG tolerance).

Uses only the public API (``load_scene``, ``Scene.simulation``, ``step``,
``positions``, ``velocities``), so it runs unchanged on any revision. The stored
file was made at commit f17ee13 (before the device-layer refactor, with the
pre-refactor kernels installed beside the current ones: ``pip install --no-deps
--target OLD_SITE <worktree>``, then ``PYTHONPATH=OLD_SITE:SITE_PACKAGES python -S``
so that the editable install does not shadow it); ``tests/test_regression.py``
compares the current code against it.

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
IMPLICIT_CG_TOL = 1e-12


def main(out):
    data = {}
    for scene_name in SCENES:
        scene = ms.load_scene(scene_name)
        for integrator in INTEGRATORS:
            options = {"cg_tol": IMPLICIT_CG_TOL} if integrator == "implicit" else {}
            sim = scene.simulation(integrator=integrator, **options)
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
