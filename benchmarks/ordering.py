"""What a scrambled particle order costs, and what the renumbering (``massspring.model.ordering``) wins back.

For the cloth at ``--resolutions`` this builds three runs of the same system and
times their steps in one process, interleaved, reporting the median ms per step:

* grid: the scene's own (row-major) order, which ``ordering.plan`` leaves as given;
* scrambled: the same cloth with its particles and springs in a random order
  (``ordering.renumbered`` with random permutations: a mesh from a tool that does
  not keep vertex locality), stepped as given (``ordering.plan`` switched off);
* renumbered: the scrambled cloth as ``Simulation`` steps it by default, in Z-order.

Cases: symplectic Euler in f32 and f64 (dt 2e-4 / resolution, inside the explicit
limit) and, for resolutions up to ``--implicit-up-to``, the implicit step in f64
(dt 1/60, ``preconditioner="auto"``). Also printed: the far share of each order
(``ordering.far_share``) and the seconds ``ordering.plan`` takes to renumber.

    python benchmarks/ordering.py
    python benchmarks/ordering.py --resolutions 128 256 512 --json benchmarks/results/ordering.json
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.model import ordering  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

ORDERS = ("grid", "scrambled", "renumbered")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512])
    p.add_argument("--implicit-up-to", type=int, default=256, help="largest resolution of the implicit case")
    p.add_argument("--steps", type=int, default=40, help="explicit steps per timed run")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per order (median reported)")
    output.add_json(p, "ordering")
    return p.parse_args(argv)


def build(model, order, **settings):
    """A Simulation of ``model`` with the renumbering on (``order`` "renumbered" or
    "grid") or off ("scrambled")."""
    plan = ordering.plan
    if order == "scrambled":
        ordering.plan = lambda model: None
    try:
        return ms.Simulation(model, **settings)
    finally:
        ordering.plan = plan


def measure(models, settings, steps, repeats):
    """{order: median ms per step} over ``repeats`` interleaved runs of ``steps`` steps."""
    sims = {order: build(models[order], order, **settings) for order in ORDERS}
    for sim in sims.values():
        sim.step(steps)  # compile and warm up
    runs = {order: [] for order in ORDERS}
    for _ in range(repeats):
        for order, sim in sims.items():
            t0 = time.perf_counter()
            sim.step(steps)
            runs[order].append(1e3 * (time.perf_counter() - t0) / steps)
    infos = {order: sim.info()["order"] for order, sim in sims.items()}
    for sim in sims.values():
        sim.close()
    assert infos == {"grid": "given", "scrambled": "given", "renumbered": "z-order"}, infos
    return {order: statistics.median(values) for order, values in runs.items()}


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'cloth':>6s} {'case':>15s} {'grid ms':>9s} {'scrambled ms':>13s} {'renumbered ms':>14s} "
          f"{'scrambled/grid':>15s} {'renumbered/grid':>16s}")
    for resolution in args.resolutions:
        grid = ms.load_scene("cloth").with_params(resolution=resolution).model()
        rng = np.random.default_rng(resolution)
        scrambled = ordering.renumbered(grid, rng.permutation(grid.n_particles), rng.permutation(grid.n_springs))
        t0 = time.perf_counter()
        plan = ordering.plan(scrambled)
        plan_s = time.perf_counter() - t0
        if plan is None:
            print(f"{resolution:>5d}²: the scrambled cloth is not renumbered (far share "
                  f"{ordering.far_share(scrambled.springs, ordering.WINDOW):.3f}, limit {ordering.FAR_SHARE}): "
                  f"all of its {grid.n_particles} particles lie within the window of {ordering.WINDOW}")
            continue
        models = {"grid": grid, "scrambled": scrambled, "renumbered": scrambled}
        shares = {"grid": ordering.far_share(grid.springs, ordering.WINDOW),
                  "scrambled": ordering.far_share(scrambled.springs, ordering.WINDOW),
                  "renumbered": ordering.far_share(plan.model.springs, ordering.WINDOW)}
        cases = [("symplectic", "f32"), ("symplectic", "f64")]
        if resolution <= args.implicit_up_to:
            cases.append(("implicit", "f64"))
        for integrator, precision in cases:
            explicit = integrator != "implicit"
            settings = dict(integrator=integrator, precision=precision, dt=2e-4 / resolution if explicit else 1 / 60)
            steps = args.steps if explicit else 2
            repeats = args.repeats
            ms_per_step = measure(models, settings, steps, repeats)
            row = {"resolution": resolution, "particles": grid.n_particles, "springs": grid.n_springs,
                   "integrator": integrator, "precision": precision, "dt": settings["dt"], "steps": steps,
                   "repeats": repeats, "ms_per_step": ms_per_step, "far_share": shares, "plan_s": plan_s}
            rows.append(row)
            print(f"{resolution:>5d}² {integrator + ' ' + precision:>15s} {ms_per_step['grid']:9.3f} "
                  f"{ms_per_step['scrambled']:13.3f} {ms_per_step['renumbered']:14.3f} "
                  f"{ms_per_step['scrambled'] / ms_per_step['grid']:15.2f} "
                  f"{ms_per_step['renumbered'] / ms_per_step['grid']:16.2f}", flush=True)
        print(f"{resolution:>5d}² far share: grid {shares['grid']:.3f}, scrambled {shares['scrambled']:.3f}, "
              f"renumbered {shares['renumbered']:.3f}; renumbering took {plan_s:.3f} s", flush=True)
    write_json(args.json, {"window": ordering.WINDOW, "far_share_limit": ordering.FAR_SHARE, "results": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
