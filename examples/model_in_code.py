"""Build a Model in code and run it: a rope with a heavy end weight, swinging down.

Shows: ``massspring.Model`` from numpy arrays (positions, springs, masses, stiffness,
damping, pins, gravity), a time step from the stability prediction, ``Simulation`` and
the run loop ``massspring.run`` with a frame callback that records the energy, and the
final state as a file that ``massspring run --restart`` could continue.

    python examples/model_in_code.py [--small] [--out state.npz]
"""

import argparse
import os

import numpy as np

import massspring as ms
from massspring.analysis.stability import predict
from massspring.integrators import INTEGRATORS
from massspring.io.state import write_state


def rope(count, length=1.0, total_mass=0.2, weight=0.5, stiffness=2000.0, damping=0.5):
    """A straight horizontal rope of ``count`` particles along x, pinned at x = 0, with a
    ``weight`` kg mass at its free end. ``stiffness`` (N) and ``damping`` (N s) are those
    of the whole rope: each of its springs, of length h, gets stiffness / h and damping / h."""
    h = length / (count - 1)
    positions = np.zeros((count, 3))
    positions[:, 0] = np.arange(count) * h
    springs = np.stack([np.arange(count - 1), np.arange(1, count)], axis=1)
    masses = np.full(count, total_mass / count)
    masses[-1] += weight
    return ms.Model(positions, springs, masses=masses, stiffness=stiffness / h, damping=damping / h,
                    gravity=(0.0, 0.0, -9.81), fixed=[0])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--out", help="write the final state here (.npz)")
    args = parser.parse_args(argv)

    model = rope(count=8 if args.small else 40)
    dt = INTEGRATORS["symplectic"].suggest_dt(predict(model))  # half the predicted stability limit
    duration = 0.05 if args.small else 2.0
    sim = ms.Simulation(model, integrator="symplectic", dt=dt)
    steps = int(round(duration / dt))

    print(f"{model.n_particles} particles, {model.n_springs} springs; symplectic Euler at dt = {dt:.3g} s")
    print("    t (s)   kinetic (J)   spring (J)   gravity (J)   lowest z (m)")

    def report(sim):
        e = sim.energy()
        print(f"{sim.time:9.3f} {e['kinetic']:13.4g} {e['spring']:12.4g} {e['gravity'] + 0.0:13.4g} "
              f"{sim.positions[:, 2].min():14.4f}")

    ms.run(sim, steps, frames=np.linspace(0, steps, 6).astype(int), on_frame=report)
    if args.out:
        write_state(sim, args.out, "rope")
        print(f"wrote {args.out}")
    sim.close()


if __name__ == "__main__":
    main()
