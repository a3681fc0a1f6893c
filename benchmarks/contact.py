"""What colliders cost: a 128 x 128 cloth step with and without a ground plane and a sphere.

Two situations, each measured with and without the colliders in the same run
(implicit at dt = 1/60 s, symplectic at dt = 2e-4 s / resolution as in
``measure_case.py``; f64; default loops):

* "hanging": the cloth scene (two corners pinned) swinging far above a ground
  plane and beside a sphere it never reaches: what the compiled collider checks
  cost every step (detection, projection) when nothing touches;
* "draping": the same cloth with the sphere right under its middle, its top poking
  through the cloth: a few percent of the particles in contact at first, more as
  the cloth falls around it;
* "lying": a cloth lying flat on a ground plane with a sphere under its middle,
  sliding about (random horizontal velocities): every particle in contact (the
  implicit step constrains and applies friction to all of them), against the same
  cloth falling freely without colliders: the worst case.

Reported per case: the median ms per step over ``--repeats`` timed chunks of steps
after a warm-up (compilation). Contact changes the implicit step's linear system
(and so its CG iterations), so for implicit also the cost of one CG iteration and of
the rest of a step (refresh with contact detection, friction, commit), from solves
capped at 40 and 80 iterations (``measure_case.py`` does the same with 20 and 40).
The implicit step uses ``--preconditioner`` (default block-jacobi, whose solves run
past those caps; a multigrid solve takes 10-20 iterations, so its split into per-
iteration and fixed costs is not meaningful). Prints a table and writes JSON.

    python benchmarks/contact.py
    python benchmarks/contact.py --resolution 64 --repeats 5
"""

import argparse
import statistics
import time

import numpy as np

import massspring as ms
from massspring.integrators import taken
from massspring.io.files import write_json
import output


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--repeats", type=int, default=7, help="timed chunks per case (median reported)")
    p.add_argument("--preconditioner", default="block-jacobi", choices=["block-jacobi", "multigrid", "none"],
                   help="the implicit step's (default block-jacobi)")
    output.add_json(p, "contact")
    return p.parse_args(argv)


def models(resolution):
    """{situation: (model without colliders, model with a ground plane and a sphere)}."""
    cloth = ms.load_scene("cloth").with_params(resolution=resolution)
    hanging = cloth.model()
    far = [ms.Plane((0.0, 0.0, -5.0), (0.0, 0.0, 1.0), friction=0.5),
           ms.Sphere((3.0, 0.5, -0.5), 0.3, friction=0.5)]
    flat = cloth.with_params(pin="none").model()
    # sliding about on the ground (so that CG has work to do): random horizontal velocities
    slide = np.random.default_rng(0).normal(scale=0.1, size=flat.positions.shape) * [1.0, 1.0, 0.0]
    lying = rebuilt(flat, velocities=slide)
    under = [ms.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), friction=0.5),
             ms.Sphere((0.5, 0.5, -0.2), 0.25, friction=0.5)]
    poking = [ms.Plane((0.0, 0.0, -5.0), (0.0, 0.0, 1.0), friction=0.5),
              ms.Sphere((0.5, 0.5, -0.28), 0.3, friction=0.5)]  # its top 2 cm through the cloth
    return {"hanging": (hanging, rebuilt(hanging, colliders=far)),
            "draping": (hanging, rebuilt(hanging, colliders=poking)),
            "lying": (lying, rebuilt(lying, colliders=under))}


def rebuilt(model, **changes):
    args = dict(positions=model.positions, springs=model.springs, masses=model.masses,
                stiffness=model.stiffness, damping=model.damping, rest_lengths=model.rest_lengths,
                velocities=model.velocities, gravity=model.gravity, fixed=model.fixed, triangles=model.triangles)
    return ms.Model(**dict(args, **changes))


def timed_steps(sim, chunk, repeats):
    """Median seconds per step over ``repeats`` chunks of ``chunk`` steps."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.step(chunk)
        times.append((time.perf_counter() - t0) / chunk)
    return statistics.median(times)


def measure(model, integrator, dt, repeats, preconditioner, capped=40):
    """{"ms": median ms per step, and for implicit: "its" mean CG iterations per step, and from
    solves capped at ``capped`` and 2 ``capped`` iterations, "ms_per_it" (one CG iteration)
    and "ms_fixed" (the rest of a step: refresh, contact detection, friction, commit)}."""
    sim = ms.Simulation(model, integrator=integrator, dt=dt, **taken(integrator, {"preconditioner": preconditioner}))
    chunk = 1 if integrator == "implicit" else 20
    sim.step(2 * chunk)  # compile, and leave the first step's special case behind
    start = len(sim.cg_iterations)
    out = {"ms": 1e3 * timed_steps(sim, chunk, repeats)}
    if integrator == "implicit":
        out["its"] = float(np.mean(sim.cg_iterations[start:]))
    if integrator == "implicit" and preconditioner != "multigrid":
        per_limit = []
        for limit in (capped, 2 * capped):
            capped_sim = ms.Simulation(model, integrator=integrator, dt=dt, cg_max_iter=limit,
                                       preconditioner=preconditioner)
            capped_sim.step(1)
            per_limit.append(timed_steps(capped_sim, 1, repeats))
            assert capped_sim.solver_stats.iterations == limit, capped_sim.solver_stats
            capped_sim.close()
        out["ms_per_it"] = 1e3 * (per_limit[1] - per_limit[0]) / capped
        out["ms_fixed"] = 1e3 * per_limit[0] - capped * out["ms_per_it"]
    sim.close()
    return out


def main(argv=None):
    args = parse_args(argv)
    dts = {"implicit": 1 / 60, "symplectic": 2e-4 / args.resolution}  # as benchmarks/measure_case.py
    rows = []
    for situation, (plain, touched) in models(args.resolution).items():
        for integrator, dt in dts.items():
            without = measure(plain, integrator, dt, args.repeats, args.preconditioner)
            with_ = measure(touched, integrator, dt, args.repeats, args.preconditioner)
            row = {"situation": situation, "integrator": integrator, "dt": dt, "without": without,
                   "with": with_, "ratio": with_["ms"] / without["ms"]}
            text = (f"{situation:8s} {integrator:10s} ms/step {without['ms']:8.3f} -> {with_['ms']:8.3f} "
                    f"(x{row['ratio']:.3f})")
            if integrator == "implicit":
                text += f"; CG its/step {without['its']:.1f} -> {with_['its']:.1f}"
            if "ms_per_it" in with_:
                row["ratio_per_it"] = with_["ms_per_it"] / without["ms_per_it"]
                row["ratio_fixed"] = with_["ms_fixed"] / without["ms_fixed"]
                text += (f"; ms per CG iteration "
                         f"{without['ms_per_it']:.3f} -> {with_['ms_per_it']:.3f} (x{row['ratio_per_it']:.3f}); "
                         f"rest of the step {without['ms_fixed']:.2f} -> {with_['ms_fixed']:.2f} ms "
                         f"(x{row['ratio_fixed']:.3f})")
            rows.append(row)
            print(text, flush=True)
    write_json(args.json, {"resolution": args.resolution, "repeats": args.repeats,
                           "preconditioner": args.preconditioner, "rows": rows})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
