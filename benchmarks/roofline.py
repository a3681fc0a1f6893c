"""How close the CG iteration comes to this machine's memory-bandwidth bound.

1. Sustained bandwidth: a Taichi triad a = b + s c over arrays far larger than the
   caches (STREAM's count: 3 x 8 bytes per element in f64), with serial and with
   parallel loops.
2. Minimum bytes one CG iteration must move (kernels/cg.py), counting every array
   once per iteration and neighbour reads of p as cache hits:
   per spring:   adjacency indices 2 x (4 + 4) B, coefficients (n, a, b) 5 reals;
   per particle: apply  p, mass, offsets, q (3 + 1 reals + 4 B + 3 reals),
                 update x, p, r, q, minv read and x, r, z written (12 + 9 + 9 reals),
                 direction z, p read and p written (9 reals).
   For the cloth (m/n springs per particle) this gives bytes per spring-iteration,
   and with the bandwidth a bound in spring-iterations per second. This is the
   minimum for coefficients stored once per spring; massspring stores them once
   per adjacency entry (each spring twice, read in order, no spring index: 2 x (4 +
   5 reals) per spring), which moves more bytes but runs faster. The share is taken
   against the stricter minimum; "GB/s" counts the bytes of the layout actually used.
3. Measured spring-iterations per second of each loop kind (serial / parallel) on the
   cloth, from the time of CG iterations alone: (t(2k) - t(k)) / k with the
   iteration limit set to k and 2k, so the per-step set-up cancels.
4. The explicit and symplectic steps (kernels/euler.py) on the cloth of that size at its
   own stiffness, at the dt of the stability estimate, with the loops ``Simulation`` picks: minimum bytes per step, counting neighbour reads of x
   and v as cache hits and each spring force once written and once read back:
   per spring:   ends 2 x 4 B, ks, l0 (and kd if damped) 1 real each, force 3 reals
                 written and 3 read, adjacency entries 2 x 4 B;
   per particle: x, v read and written (12 reals), mass 1 real, offsets 4 B (and the
                 free flag 4 B with pins).
   The share is those bytes per second of step time against the triad bandwidth
   (issue 22's target: at least 50% at 512 x 512).

    python benchmarks/roofline.py --help
    python benchmarks/roofline.py --resolution 512
"""

import argparse
import statistics
import sys
import time

import taichi as ti

import massspring as ms
from massspring.analysis.stability import predict
from massspring.integrators import INTEGRATORS
from massspring.device import ensure_taichi
from massspring.io.files import write_json
import output

VARIANTS = ["serial", "parallel"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=512, help="cloth resolution for the CG measurement")
    p.add_argument("--triad-mib", type=int, default=256, help="size of each triad array in MiB")
    p.add_argument("--iterations", type=int, default=40, help="k: CG iterations per timed step")
    p.add_argument("--repeats", type=int, default=5, help="timed runs of each measurement (best/median kept)")
    p.add_argument("--precision", default="f64", choices=["f64", "f32"])
    p.add_argument("--steps", type=int, default=20, help="explicit steps per timed run (0: skip part 4)")
    output.add_json(p, "roofline")
    return p.parse_args(argv)


def triad_bandwidth(mib, repeats, real):
    """Sustained bytes/s of a = b + s c (serial, parallel) over Taichi fields."""
    itemsize = 8 if real == ti.f64 else 4
    n = mib * 2 ** 20 // itemsize
    a, b, c = (ti.field(real, shape=n) for _ in range(3))
    b.fill(1.0)
    c.fill(2.0)

    def make(serial):
        @ti.kernel
        def triad(s: ti.f64):
            ti.loop_config(serialize=serial)
            for i in range(n):
                a[i] = b[i] + ti.cast(s, real) * c[i]
        return triad

    out = {}
    for name, serial in (("serial", True), ("parallel", False)):
        kernel = make(serial)
        kernel(3.0)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            kernel(3.0)
            ti.sync()
            times.append(time.perf_counter() - t0)
        out[name] = 3 * itemsize * n / min(times)
    return out


def bytes_per_iteration(n, m, real_bytes, fixed, per_entry=False):
    per_spring = 2 * (4 + 5 * real_bytes) if per_entry else 2 * (4 + 4) + 5 * real_bytes
    per_particle = (3 + 1) * real_bytes + 4 + 3 * real_bytes + (12 + 9 + 9) * real_bytes + 9 * real_bytes
    per_particle += 4 * bool(fixed)
    return per_spring * m + per_particle * n


def bytes_per_explicit_step(n, m, real_bytes, fixed, damped):
    per_spring = 2 * 4 + (2 + bool(damped)) * real_bytes + 6 * real_bytes + 2 * 4
    per_particle = 13 * real_bytes + 4 + 4 * bool(fixed)
    return per_spring * m + per_particle * n


def explicit_seconds_per_step(scene, integrator, steps, repeats, precision):
    # the scene's [dt] is for its own size: take the integrator's dt from the stability estimate
    dt = INTEGRATORS[integrator].suggest_dt(predict(scene.model()))
    sim = scene.simulation(integrator=integrator, dt=dt, precision=precision)
    for _ in range(2):  # compile (the second call's state parity compiles again), warm the caches
        sim.step(steps)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.step(steps)
        times.append(time.perf_counter() - t0)
    loops = sim.loops
    sim.close()
    return statistics.median(times) / steps, loops


class IterationTimer:
    """Seconds of one block-Jacobi CG iteration of ``scene``: two simulations whose CG
    stops after k and 2k iterations, each stepped once to compile and leave the flat
    start behind; ``sample()`` times one step of each, the difference over k."""

    def __init__(self, scene, loops, k, precision):
        self.k = k
        self.sims = [scene.simulation(integrator="implicit", dt=1 / 60, cg_max_iter=limit, loops=loops,
                                      precision=precision, preconditioner="block-jacobi")
                     for limit in (k, 2 * k)]
        for sim in self.sims:
            sim.step(1)

    def sample(self):
        seconds = []
        for sim, limit in zip(self.sims, (self.k, 2 * self.k)):
            t0 = time.perf_counter()
            sim.step(1)
            seconds.append(time.perf_counter() - t0)
            assert sim.solver_stats.iterations == limit, sim.solver_stats
        return (seconds[1] - seconds[0]) / self.k

    def close(self):
        for sim in self.sims:
            sim.close()


def cg_seconds_per_iteration(scene, loops, k, repeats, precision):
    """The median of ``repeats`` samples of ``IterationTimer``."""
    timer = IterationTimer(scene, loops, k, precision)
    try:
        return statistics.median([timer.sample() for _ in range(repeats)])
    finally:
        timer.close()


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    real = ti.f64 if args.precision == "f64" else ti.f32
    bandwidth = triad_bandwidth(args.triad_mib, args.repeats, real)
    scene = ms.load_scene("cloth").with_params(resolution=args.resolution, stiffness=1e6)
    model = scene.model()
    n, m = model.n_particles, model.n_springs
    real_bytes = 8 if args.precision == "f64" else 4
    moved = bytes_per_iteration(n, m, real_bytes, model.has_fixed)
    layout = bytes_per_iteration(n, m, real_bytes, model.has_fixed, per_entry=True)
    print(f"triad bandwidth: serial {bandwidth['serial'] / 1e9:.1f} GB/s, parallel {bandwidth['parallel'] / 1e9:.1f} GB/s")
    print(f"cloth {args.resolution}: {n} particles, {m} springs; CG iteration moves >= {moved / 1e6:.1f} MB "
          f"({moved / m:.0f} bytes per spring-iteration, {args.precision}; massspring's layout moves "
          f"{layout / m:.0f})")
    best = max(bandwidth.values())
    bound = best / (moved / m)
    print(f"bound: {bound / 1e6:.1f} M spring-iterations/s at {best / 1e9:.1f} GB/s")
    print(f"{'loops':>8s} {'ms/iter':>8s} {'Msi/s':>8s} {'GB/s':>6s} {'share':>6s}")
    rows = []
    for loops in VARIANTS:
        seconds = cg_seconds_per_iteration(scene, loops, args.iterations, args.repeats, args.precision)
        rate = m / seconds
        row = {"loops": loops, "ms_per_iteration": 1e3 * seconds,
               "spring_iterations_per_s": rate, "gb_per_s": layout / seconds / 1e9, "share_of_bound": rate / bound}
        rows.append(row)
        print(f"{loops:>8s} {row['ms_per_iteration']:8.3f} {rate / 1e6:8.1f} "
              f"{row['gb_per_s']:6.1f} {row['share_of_bound']:6.0%}", flush=True)
    explicit = []
    step_bytes = bytes_per_explicit_step(n, m, real_bytes, model.has_fixed, model.has_damping)
    if args.steps:
        print(f"explicit step moves >= {step_bytes / 1e6:.1f} MB ({step_bytes / m:.0f} bytes per spring)")
        print(f"{'integrator':>10s} {'loops':>8s} {'ms/step':>8s} {'ns/spring':>9s} {'GB/s':>6s} {'share':>6s}")
        soft = ms.load_scene("cloth").with_params(resolution=args.resolution)  # at the scene's stiffness
        for integrator in ("explicit", "symplectic"):
            seconds, loops = explicit_seconds_per_step(soft, integrator, args.steps, args.repeats, args.precision)
            row = {"integrator": integrator, "loops": loops, "ms_per_step": 1e3 * seconds,
                   "ns_per_spring": 1e9 * seconds / m, "gb_per_s": step_bytes / seconds / 1e9,
                   "share_of_bandwidth": step_bytes / seconds / best}
            explicit.append(row)
            print(f"{integrator:>10s} {loops:>8s} {row['ms_per_step']:8.3f} {row['ns_per_spring']:9.2f} "
                  f"{row['gb_per_s']:6.1f} {row['share_of_bandwidth']:6.0%}", flush=True)
    write_json(args.json, {"triad_bytes_per_s": bandwidth, "resolution": args.resolution, "particles": n,
                           "springs": m, "bytes_per_iteration": moved, "layout_bytes_per_iteration": layout, "bound_spring_iterations_per_s": bound,
                           "precision": args.precision, "variants": rows, "explicit_steps": explicit,
                           "bytes_per_explicit_step": step_bytes})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
