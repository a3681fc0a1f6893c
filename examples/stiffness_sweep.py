"""Sweep the stiffness of a falling cloth and plot how far its springs stretch.

Shows: one scene run at several parameter values (``Scene.with_params``), the
simulations of a sweep sharing compiled kernels (each closed before the next), a
frame callback of the run loop that measures the state (the largest spring strain
l / l0 - 1), and a log-log plot with matplotlib (skipped, with a note, when matplotlib
is not installed: ``pip install -e ".[plot]"`` in the checkout). The cloth, pinned at two
corners, falls and swings; the stiffer it is, the less it stretches (strain ~ 1/stiffness).

    python examples/stiffness_sweep.py [--small] [--out strain.png]

The command line runs such sweeps without code, on several processes if asked:
``massspring sweep cloth --vary stiffness=1e2,1e3,1e4 --out sweep.csv --plot sweep.png --metric max_strain``
(docs/sweeps.md).
"""

import argparse
import os

import numpy as np

import massspring as ms
from massspring.support.extras import install_hint
from massspring.io.render import spring_strain


def peak_strain(scene, stiffness, steps):
    """The largest strain of any spring over ``steps`` implicit steps of 1/60 s (every other step)."""
    sim = scene.with_params(stiffness=stiffness).simulation(integrator="implicit", dt=1 / 60)
    peak = 0.0

    def measure(sim):
        nonlocal peak
        peak = max(peak, float(spring_strain(sim.positions, sim.model.springs, sim.model.rest_lengths).max()))

    ms.run(sim, steps, frames=range(0, steps + 1, 2), on_frame=measure)
    sim.close()  # hands the fields to the next run of the sweep: it compiles nothing again
    return peak


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--out", default="stiffness_sweep.png", help="the plot (PNG; default stiffness_sweep.png)")
    args = parser.parse_args(argv)

    scene = ms.load_scene("cloth").with_params(resolution=6 if args.small else 16)
    stiffnesses = np.geomspace(1e2, 1e4, 3 if args.small else 9)  # N/m per structural spring
    steps = 10 if args.small else 120
    print(f"stiffness (N/m)   largest strain within {steps / 60:.3g} s")
    strains = []
    for k in stiffnesses:
        strains.append(peak_strain(scene, k, steps))
        print(f"{k:15.4g}   {strains[-1]:.4g}")

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"plot skipped: matplotlib is not installed ({install_hint('plot')})")
        return
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.loglog(stiffnesses, strains, "o-")
    ax.set_xlabel("stiffness per spring (N/m)")
    ax.set_ylabel("largest strain l/l0 - 1")
    ax.set_title(f"falling cloth, {scene.params['resolution']}^2 particles, {steps / 60:.3g} s")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
