"""Explicit and symplectic Euler steps per second on the cloth scene, against peers.

Peers in the same run, on the same model: a NumPy vectorised step (bincount
scatter) and, if `warp-lang` is installed (1.9.x: `pip install "warp-lang==1.9.*"`),
Warp kernels of the same spring forces on Warp's CPU backend (an atomic scatter
over springs, as warp.sim does). All start from the same state; after the timed
steps their displacements from it must agree with massspring's to 1e-9 of the
largest displacement (f64).

    python benchmarks/explicit_step.py --help
    python benchmarks/explicit_step.py --resolutions 32 64 128 --steps 200
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

def time_step(resolution):
    """dt (s) well inside the explicit limit, which shrinks as 1 / resolution."""
    return 2e-4 / resolution


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--integrators", nargs="+", default=["explicit", "symplectic"],
                   choices=["explicit", "symplectic"])
    p.add_argument("--steps", type=int, default=200, help="steps per timed run")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per case (median reported)")
    p.add_argument("--no-warp", action="store_true", help="skip the Warp peer")
    p.add_argument("--json", default="benchmarks/results/explicit_step.json")
    return p.parse_args(argv)


def timed(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


class WarpEuler:
    """Explicit / symplectic Euler with Warp kernels on the CPU, float64."""

    def __init__(self, model, symplectic):
        import warp as wp

        wp.config.quiet = True
        wp.init()
        self.wp = wp
        self.symplectic = symplectic
        self.model = model
        dev = "cpu"
        self.x = wp.array(model.positions, dtype=wp.vec3d, device=dev)
        self.v = wp.array(model.velocities, dtype=wp.vec3d, device=dev)
        self.f = wp.zeros(model.n_particles, dtype=wp.vec3d, device=dev)
        self.springs = wp.array(model.springs.astype(np.int32), dtype=wp.vec2i, device=dev)
        self.ks = wp.array(model.stiffness, dtype=wp.float64, device=dev)
        self.kd = wp.array(model.damping, dtype=wp.float64, device=dev)
        self.l0 = wp.array(model.rest_lengths, dtype=wp.float64, device=dev)
        self.inv_mass = wp.array(np.where(model.free_mask(), 1.0 / model.masses, 0.0), dtype=wp.float64, device=dev)
        self.mass = wp.array(model.masses, dtype=wp.float64, device=dev)
        self.g = wp.vec3d(*model.gravity)
        self.kernels = _warp_kernels(wp)

    def step(self, dt, steps):
        wp = self.wp
        springs_k, integrate_k = self.kernels
        for _ in range(steps):
            self.f.zero_()
            wp.launch(springs_k, dim=self.model.n_springs, device="cpu",
                      inputs=[self.x, self.v, self.springs, self.ks, self.kd, self.l0, self.f])
            wp.launch(integrate_k, dim=self.model.n_particles, device="cpu",
                      inputs=[self.x, self.v, self.f, self.mass, self.inv_mass, self.g, wp.float64(dt),
                              int(self.symplectic)])
        wp.synchronize()

    def positions(self):
        return self.x.numpy()


_WARP_KERNELS = None


def _warp_kernels(wp):
    global _WARP_KERNELS
    if _WARP_KERNELS is not None:
        return _WARP_KERNELS

    @wp.kernel
    def eval_springs(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), springs: wp.array(dtype=wp.vec2i),
                     ks: wp.array(dtype=wp.float64), kd: wp.array(dtype=wp.float64),
                     l0: wp.array(dtype=wp.float64), f: wp.array(dtype=wp.vec3d)):
        s = wp.tid()
        i = springs[s][0]
        j = springs[s][1]
        d = x[j] - x[i]
        length = wp.length(d)
        if length > wp.float64(1e-12):
            n = d / length
            mag = ks[s] * (length - l0[s]) + kd[s] * wp.dot(v[j] - v[i], n)
            wp.atomic_add(f, i, mag * n)
            wp.atomic_sub(f, j, mag * n)

    @wp.kernel
    def integrate(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.vec3d),
                  mass: wp.array(dtype=wp.float64), inv_mass: wp.array(dtype=wp.float64), g: wp.vec3d,
                  dt: wp.float64, symplectic: int):
        i = wp.tid()
        if inv_mass[i] > wp.float64(0.0):
            v_new = v[i] + dt * inv_mass[i] * (f[i] + mass[i] * g)
            if symplectic == 1:
                x[i] = x[i] + dt * v_new
            else:
                x[i] = x[i] + dt * v[i]
            v[i] = v_new

    _WARP_KERNELS = (eval_springs, integrate)
    return _WARP_KERNELS


def run_case(args, resolution, integrator, have_warp):
    scene = ms.load_scene("cloth").with_params(resolution=resolution)
    model = scene.model()
    symplectic = integrator == "symplectic"
    steps = args.steps
    dt = time_step(resolution)
    sim = ms.Simulation(model, integrator=integrator, dt=dt)
    t0 = time.perf_counter()
    sim.step(1)
    first = time.perf_counter() - t0
    ours = timed(lambda: sim.step(steps), args.repeats)
    total_steps = 1 + steps * args.repeats
    row = {"resolution": resolution, "integrator": integrator, "springs": model.n_springs,
           "steps": steps, "dt": dt, "loops": sim.loops, "steps_per_s": steps / ours, "compile_s": first, "peers": {}}

    x, v = model.positions.copy(), model.velocities.copy()

    def numpy_run(count):
        nonlocal x, v
        for _ in range(count):
            x, v = peers.numpy_euler_step(model, x, v, dt, symplectic)

    numpy_run(1)
    numpy_s = timed(lambda: numpy_run(steps), args.repeats)
    row["peers"]["numpy"] = {"steps_per_s": steps / numpy_s, "ratio": numpy_s / ours,
                             "max_rel_diff": _rel_diff(x, sim.positions, model.positions)}
    if have_warp:
        w = WarpEuler(model, symplectic)
        w.step(dt, 1)
        warp_s = timed(lambda: w.step(dt, steps), args.repeats)
        row["peers"]["warp"] = {"steps_per_s": steps / warp_s, "ratio": warp_s / ours,
                                "max_rel_diff": _rel_diff(w.positions(), sim.positions, model.positions)}
    assert sim.steps == total_steps
    return row


def _rel_diff(a, b, start):
    """Largest difference of two runs' displacements from ``start``, relative to the largest displacement."""
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b - start)))


def main(argv=None):
    args = parse_args(argv)
    have_warp = False
    if not args.no_warp:
        try:
            import warp  # noqa: F401
            have_warp = True
        except ImportError:
            print("warp-lang not installed: skipping the Warp peer (pip install 'warp-lang==1.9.*')")
    print(f"{'res':>5s} {'integrator':>10s} {'springs':>8s} {'steps/s':>10s}  peers (steps/s, massspring ratio, max rel. diff)")
    rows, failures = [], []
    for resolution in args.resolutions:
        for integrator in args.integrators:
            row = run_case(args, resolution, integrator, have_warp)
            rows.append(row)
            text = "  ".join(f"{name} {p['steps_per_s']:.0f} ({p['ratio']:.1f}x, {p['max_rel_diff']:.1e})"
                             for name, p in row["peers"].items())
            print(f"{resolution:5d} {integrator:>10s} {row['springs']:8d} {row['steps_per_s']:10.0f}  {text}", flush=True)
            for name, p in row["peers"].items():
                if not p["max_rel_diff"] <= 1e-9:
                    failures.append(f"res {resolution} {integrator}: {name} differs by {p['max_rel_diff']:.2e}")
    write_json(args.json, {"rows": rows})
    print(f"wrote {args.json}")
    for f in failures:
        print("CHECK FAILED:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
