"""Self-collision's cost: step time with and without it, per integrator and size.

For each resolution and integrator, the ``drape`` cloth (dropped on a ball on the
ground; 1/60 s for the implicit integrators, 1e-4 s for symplectic) is run with and
without ``SelfCollision(thickness = spacing / 4)``, interleaved in one process: the
median wall time of ``--steps`` steps after ``--warmup`` steps (the cloth then lies
on the ball), their ratio, and the pass's pair counts in the last step (pairs within
reach, pairs repelled, particles held back) and whether they fitted its pair list. Without self-collision the step runs the
same kernels as a model that never had it.

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
    p.add_argument("--steps", type=int, default=5, help="timed steps per case (default 5)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved repeats (default 3)")
    output.add_json(p, "self_collision")
    return p.parse_args(argv)


def dt_for(integrator, resolution):
    """DT at 32 x 32, scaled as 1 / resolution for the explicit integrators (their stable dt)."""
    linear = integrator in ("implicit", "backward-euler", "bdf2")
    return DT[integrator] if linear else DT[integrator] * 32 / resolution


def warmup_steps(integrator, resolution):
    """Steps until the cloth lies on the ball (about 0.4 s; at most 2000)."""
    return max(1, int(round(0.4 / dt_for(integrator, resolution))))


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'res':>4s} {'integrator':12s} {'off ms':>9s} {'on ms':>9s} {'ratio':>6s} {'pairs':>8s} {'repelled':>8s} "
          f"{'held':>6s} {'listed':>6s}")
    for res in args.resolutions:
        base = ms.load_scene("drape").with_params(resolution=res)
        spacing = base.params["size"] / (res - 1)
        for integrator in args.integrators:
            sims = {}
            for on in (False, True):
                scene = dataclasses.replace(base, self_collision=ms.SelfCollision(spacing / 4) if on else None)
                sim = scene.simulation(integrator, dt=dt_for(integrator, res))
                sim.step(min(warmup_steps(integrator, res), 2000))
                sims[on] = sim
            times = {False: [], True: []}
            for _ in range(args.repeats):
                for on in (False, True):
                    start = time.perf_counter()
                    sims[on].step(args.steps)
                    times[on].append((time.perf_counter() - start) / args.steps * 1e3)
            off, on = statistics.median(times[False]), statistics.median(times[True])
            pairs, repelled, held, _, _, listed = sims[True]._guard.last
            rows.append({"resolution": res, "integrator": integrator, "particles": res * res, "off_ms": off,
                         "on_ms": on, "ratio": on / off, "pairs": pairs, "repelled": repelled, "held": held,
                         "listed": listed, "dt": dt_for(integrator, res)})
            print(f"{res:4d} {integrator:12s} {off:9.2f} {on:9.2f} {on / off:6.2f} {pairs:8d} {repelled:8d} {held:6d} "
                  f"{'yes' if listed else 'no':>6s}", flush=True)
            for sim in sims.values():
                sim.close()
    write_json(args.json, {"rows": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
