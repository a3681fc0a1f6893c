"""Self-collision's cost: step time with and without it, per integrator and size.

For each resolution and integrator, the ``drape`` cloth (dropped on a ball on the
ground; 1/60 s for the implicit integrators, 2.5e-5 s x 32 / resolution for symplectic)
is run with and without ``SelfCollision(thickness = spacing / 4)`` for ``--warmup``
seconds (default 0.4: the cloth then lies on the ball), then timed interleaved in one
process: the median wall time per step of ``--steps`` steps (implicit integrators) or
``--explicit-steps`` (the others: the pass is skipped while every particle stays within
its free distance, so its cost shows only over many steps), their ratio, the share of
timed steps that ran the full pass, and the last full pass's pair counts (pairs within
reach, pairs repelled, particles held back) and the pair list's capacity then.
Without self-collision the step runs the same kernels as a model that never had it.

    python benchmarks/self_collision.py                          # 64, 128; implicit, symplectic
    python benchmarks/self_collision.py --resolutions 64 128 256 --integrators implicit
    python benchmarks/self_collision.py --json benchmarks/results/self_collision.json
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

DT = {"implicit": 1 / 60, "backward-euler": 1 / 60, "bdf2": 1 / 60, "symplectic": 2.5e-5, "explicit": 1e-5,
      "rk4": 5e-5}  # at 32 x 32; the explicit integrators' dt shrinks as 1 / resolution


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", nargs="+", type=int, default=[64, 128])
    p.add_argument("--integrators", nargs="+", default=["implicit", "symplectic"], choices=list(DT))
    p.add_argument("--steps", type=int, default=5, help="timed steps per repeat, implicit integrators (default 5)")
    p.add_argument("--explicit-steps", type=int, default=1000,
                   help="timed steps per repeat, the other integrators (default 1000)")
    p.add_argument("--warmup", type=float, default=0.4, help="simulated seconds before the timing (default 0.4)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved repeats (default 3)")
    output.add_json(p, "self_collision")
    return p.parse_args(argv)


def dt_for(integrator, resolution):
    """DT at 32 x 32, scaled as 1 / resolution for the explicit integrators (their stable dt)."""
    return DT[integrator] if linear(integrator) else DT[integrator] * 32 / resolution


def linear(integrator):
    return integrator in ("implicit", "backward-euler", "bdf2")


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'res':>4s} {'integrator':12s} {'steps':>6s} {'off ms':>9s} {'on ms':>9s} {'ratio':>6s} {'passes':>6s} "
          f"{'pairs':>8s} {'repelled':>8s} {'held':>6s} {'capacity':>9s}")
    for res in args.resolutions:
        base = ms.load_scene("drape").with_params(resolution=res, strain_limit=0.0)  # the pass alone, as measured
        spacing = base.params["size"] / (res - 1)
        for integrator in args.integrators:
            dt = dt_for(integrator, res)
            steps = args.steps if linear(integrator) else args.explicit_steps
            sims = {}
            for on in (False, True):
                scene = dataclasses.replace(base, self_collision=ms.SelfCollision(spacing / 4) if on else None)
                sim = scene.simulation(integrator, dt=dt)
                sim.step(max(1, int(round(args.warmup / dt))))
                sims[on] = sim
            before = sims[True].self_collision_stats
            times = {False: [], True: []}
            for _ in range(args.repeats):
                for on in (False, True):
                    start = time.perf_counter()
                    sims[on].step(steps)
                    times[on].append((time.perf_counter() - start) / steps * 1e3)
            stats = sims[True].self_collision_stats
            share = (stats["passes"] - before["passes"]) / (stats["steps"] - before["steps"])
            off, on = statistics.median(times[False]), statistics.median(times[True])
            pairs, repelled, held, capacity = (stats[key] for key in ("pairs", "repelled", "held", "capacity"))
            rows.append({"resolution": res, "integrator": integrator, "particles": res * res, "dt": dt,
                         "steps": steps, "off_ms": off, "on_ms": on, "ratio": on / off, "full_passes": share,
                         "pairs": pairs, "repelled": repelled, "held": held, "capacity": capacity,
                         "grown": stats["grown"]})
            print(f"{res:4d} {integrator:12s} {steps:6d} {off:9.3f} {on:9.3f} {on / off:6.2f} {share:6.1%} {pairs:8d} "
                  f"{repelled:8d} {held:6d} {capacity:9d}", flush=True)
            for sim in sims.values():
                sim.close()
    write_json(args.json, {"rows": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
