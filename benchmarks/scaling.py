"""Cost and memory against size: cloths from about 1e3 to 1e6 springs.

Each case runs in a fresh process (peak RSS is per process): it builds the cloth,
takes one step to compile, then times steps. Reported per integrator: ms per step,
CG iterations per step, ns per spring-iteration (implicit; constant if the cost is
linear in springs x iterations), ns per spring-step (explicit, symplectic), the
bytes of Taichi arrays the run allocated (``Simulation.info()``) and the growth of
peak RSS over the process's baseline after ``import massspring`` and Taichi's
start-up, both per spring. The explicit integrators allocate no CG arrays.

    python benchmarks/scaling.py --help
    python benchmarks/scaling.py --resolutions 13 41 130 410
"""

import argparse
import json
import resource
import subprocess
import sys
import time

from massspring.io.files import write_json


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[13, 41, 130, 410],
                   help="cloth resolutions (springs ~ 6 x resolution^2)")
    p.add_argument("--integrators", nargs="+", default=["explicit", "symplectic", "implicit"])
    p.add_argument("--max-iter", type=int, default=200,
                   help="CG iteration cap per implicit step (keeps the largest cases short)")
    p.add_argument("--json", default="benchmarks/results/scaling.json")
    p.add_argument("--child", nargs=2, metavar=("INTEGRATOR", "RESOLUTION"), help=argparse.SUPPRESS)
    return p.parse_args(argv)


def peak_rss_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def child(integrator, resolution, max_iter):
    import massspring as ms
    from massspring.device import ensure_taichi

    ensure_taichi()
    scene = ms.load_scene("cloth").with_params(resolution=resolution)
    model = scene.model()
    baseline = peak_rss_bytes()
    if integrator == "implicit":
        sim = ms.Simulation(model, integrator="implicit", dt=1 / 60, cg_max_iter=max_iter)
        steps = 3
    else:
        sim = ms.Simulation(model, integrator=integrator, dt=2e-4 / resolution)
        steps = max(5, int(2e7 / model.n_springs))
    sim.step(1)
    t0 = time.perf_counter()
    sim.step(steps)
    seconds = (time.perf_counter() - t0) / steps
    iterations = sum(sim.cg_iterations[1:]) / steps if sim.cg_iterations else 0
    info = sim.info()
    return {"integrator": integrator, "resolution": resolution, "springs": model.n_springs,
            "particles": model.n_particles, "ms_per_step": 1e3 * seconds, "iterations": iterations,
            "ns_per_spring_iteration": 1e9 * seconds / (model.n_springs * iterations) if iterations else None,
            "ns_per_spring_step": 1e9 * seconds / model.n_springs,
            "array_bytes_per_spring": info["bytes"] / model.n_springs, "arrays": info["arrays"],
            "rss_bytes_per_spring": (peak_rss_bytes() - baseline) / model.n_springs,
            "loops": sim.loops}


def main(argv=None):
    args = parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child[0], int(args.child[1]), args.max_iter)))
        return 0
    print(f"{'res':>4s} {'springs':>8s} {'integrator':>10s} {'ms/step':>9s} {'iters':>6s} {'ns/spr-it':>9s} "
          f"{'ns/spr-step':>11s} {'arrays B/spr':>12s} {'RSS B/spr':>9s}")
    rows = []
    for resolution in args.resolutions:
        for integrator in args.integrators:
            out = subprocess.run([sys.executable, __file__, "--child", integrator, str(resolution),
                                  "--max-iter", str(args.max_iter)], capture_output=True, text=True)
            if out.returncode:
                print(out.stderr[-2000:], file=sys.stderr)
                return 1
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            spr_it = f"{row['ns_per_spring_iteration']:9.2f}" if row["ns_per_spring_iteration"] else f"{'-':>9s}"
            print(f"{resolution:4d} {row['springs']:8d} {integrator:>10s} {row['ms_per_step']:9.2f} "
                  f"{row['iterations']:6.0f} {spr_it} {row['ns_per_spring_step']:11.2f} "
                  f"{row['array_bytes_per_spring']:12.0f} {row['rss_bytes_per_spring']:9.0f}", flush=True)
    write_json(args.json, {"max_iter": args.max_iter, "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
