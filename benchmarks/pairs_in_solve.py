"""Self-collision pairs inside the linearised implicit solve, against the pass alone.

Runs the ``sheets`` scene (two cloths dropped over a ball, self-collision on) with the
``implicit`` integrator twice, once as shipped (pairs closer than the thickness are
penalty springs of Eq. 15, ``kernels/pair_penalty.py``) and once with the pairs left to
the pass that follows every step (``ImplicitEuler.pairs_in_solve`` switched off in this
process, as the Newton-solved integrators run), and prints, at sampled times: the
pairs within the thickness and the particles held back by the last pass, the
smallest pair distance, the kinetic energy, the mean CG iterations since the last
sample and the wall time so far (kernels compiled before).

    python benchmarks/pairs_in_solve.py                     # 16 x 16 per sheet, 2 s
    python benchmarks/pairs_in_solve.py --resolution 24 --duration 3
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.integrators.implicit import ImplicitEuler  # noqa: E402
from massspring.io.files import write_json  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=16, help="particles per sheet side (default 16, as shipped)")
    p.add_argument("--duration", type=float, default=2.0, help="simulated seconds (default 2, as shipped)")
    p.add_argument("--samples", type=int, default=4, help="sampled times (default 4)")
    output.add_json(p, "pairs_in_solve")
    return p.parse_args(argv)


def run(scene, samples, steps, in_solve):
    """Rows at each sampled time of one run."""
    shipped = ImplicitEuler.pairs_in_solve
    if not in_solve:
        ImplicitEuler.pairs_in_solve = classmethod(lambda cls, model: False)
    try:
        scene.simulation("implicit").step(1).close()  # compiles this variant's kernels outside the timing
        sim = scene.simulation("implicit")
    finally:
        ImplicitEuler.pairs_in_solve = shipped
    rows, wall = [], 0.0
    for k in range(samples):
        start = time.perf_counter()
        sim.step(steps)
        wall += time.perf_counter() - start
        stats = sim.self_collision_stats
        close, held, closest = stats["repelled"], stats["held"], stats["closest"]
        rows.append({"in_solve": in_solve, "time": sim.time, "within_thickness": close, "held": held,
                     "closest": closest, "kinetic": sim.energy()["kinetic"],
                     "cg_mean": float(np.mean(sim.cg_iterations[-steps:])), "wall_s": wall})
    sim.close()
    return rows


def main(argv=None):
    args = parse_args(argv)
    scene = ms.load_scene("sheets").with_params(resolution=args.resolution)
    dt = scene.default_dt("implicit")
    steps = max(1, int(round(args.duration / dt / args.samples)))
    print(f"sheets {args.resolution} x {args.resolution} x 2, implicit, dt {dt:.6g} s, "
          f"thickness {scene.self_collision.thickness} m")
    print(f"{'pairs':10s} {'time s':>7s} {'within t':>9s} {'held':>5s} {'closest m':>10s} {'kinetic J':>10s} "
          f"{'CG':>5s} {'wall s':>7s}")
    rows = []
    for in_solve in (True, False):
        for row in run(scene, args.samples, steps, in_solve):
            rows.append(row)
            print(f"{'in solve' if in_solve else 'pass only':10s} {row['time']:7.3f} {row['within_thickness']:9d} "
                  f"{row['held']:5d} {row['closest']:10.5f} {row['kinetic']:10.5f} {row['cg_mean']:5.1f} "
                  f"{row['wall_s']:7.2f}", flush=True)
    write_json(args.json, {"resolution": args.resolution, "dt": dt, "rows": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
