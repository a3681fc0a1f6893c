"""Fields or ndarrays: the CG operator's hot loop on each, in one run.

The loop is q = A p with A's coefficients stored per adjacency entry, as
``kernels/operator.py`` applies it (a gather over each particle's springs, p.q
reduced), on the cloth's adjacency at several resolutions, f64. The same source is
compiled three ways: on Taichi fields (``ti.template()``), on plain ndarray
arguments, and on ndarrays inside an argpack (one bundle argument). Medians of
``--repeats`` launches; "serial" runs the loop in one thread, "parallel" on all.
This is the measurement behind ``massspring.device``'s choice of fields.

    python benchmarks/storage.py
    python benchmarks/storage.py --resolutions 128 512 --repeats 50
"""

import argparse
import statistics
import sys
import time

import numpy as np
import taichi as ti

import massspring as ms
from massspring.device import adjacency, ensure_taichi
from massspring.io.files import write_json
import output


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 128, 256, 512])
    p.add_argument("--repeats", type=int, default=30)
    output.add_json(p, "storage")
    return p.parse_args(argv)


V3 = ti.types.vector(3, ti.f64)
V5 = ti.types.vector(5, ti.f64)


@ti.func
def apply_row(i, p: ti.template(), mass: ti.template(), offsets: ti.template(), other: ti.template(),
              coef: ti.template()):
    pi = p[i]
    out = mass[i] * pi
    for e in range(offsets[i], offsets[i + 1]):
        c = coef[e]
        n = ti.Vector([c[0], c[1], c[2]])
        dp = pi - p[other[e]]
        out += c[3] * dp + c[4] * n.dot(dp) * n
    return out


@ti.kernel
def on_fields(p: ti.template(), q: ti.template(), mass: ti.template(), offsets: ti.template(),
              other: ti.template(), coef: ti.template(), serial: ti.template()) -> ti.f64:
    total = 0.0
    ti.loop_config(serialize=serial)
    for i in range(p.shape[0]):
        qi = apply_row(i, p, mass, offsets, other, coef)
        q[i] = qi
        total += p[i].dot(qi)
    return total


@ti.kernel
def on_ndarrays(p: ti.types.ndarray(V3, 1), q: ti.types.ndarray(V3, 1), mass: ti.types.ndarray(ti.f64, 1),
                offsets: ti.types.ndarray(ti.i32, 1), other: ti.types.ndarray(ti.i32, 1),
                coef: ti.types.ndarray(V5, 1), serial: ti.template()) -> ti.f64:
    total = 0.0
    ti.loop_config(serialize=serial)
    for i in range(p.shape[0]):
        qi = apply_row(i, p, mass, offsets, other, coef)
        q[i] = qi
        total += p[i].dot(qi)
    return total


Pack = ti.types.argpack(p=ti.types.ndarray(V3, 1), q=ti.types.ndarray(V3, 1), mass=ti.types.ndarray(ti.f64, 1),
                        offsets=ti.types.ndarray(ti.i32, 1), other=ti.types.ndarray(ti.i32, 1),
                        coef=ti.types.ndarray(V5, 1))


@ti.kernel
def on_argpack(d: Pack, serial: ti.template()) -> ti.f64:
    total = 0.0
    ti.loop_config(serialize=serial)
    for i in range(d.p.shape[0]):
        qi = apply_row(i, d.p, d.mass, d.offsets, d.other, d.coef)
        d.q[i] = qi
        total += d.p[i].dot(qi)
    return total


def median_ms(fn, args, repeats):
    fn(*args)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    print(f"{'res':>4s} {'springs':>8s} {'loops':>8s} {'fields ms':>10s} {'ndarray ms':>11s} {'argpack ms':>11s} "
          f"{'ndarray/fields':>15s}")
    rows = []
    for resolution in args.resolutions:
        model = ms.load_scene("cloth").with_params(resolution=resolution).model()
        offsets, other, _ = adjacency(model)
        n, entries = model.n_particles, len(other)
        rng = np.random.default_rng(0)
        values = {"p": rng.random((n, 3)), "mass": model.masses, "offsets": offsets, "other": other,
                  "coef": rng.random((entries, 5))}
        shapes = {"p": (V3, n), "q": (V3, n), "mass": (ti.f64, n), "offsets": (ti.i32, n + 1),
                  "other": (ti.i32, entries), "coef": (V5, entries)}
        fields, arrays = {}, {}
        for name, (dtype, size) in shapes.items():
            if dtype in (V3, V5):
                fields[name] = ti.Vector.field(dtype.n, ti.f64, size)
                arrays[name] = ti.Vector.ndarray(dtype.n, ti.f64, size)
            else:
                fields[name] = ti.field(dtype, size)
                arrays[name] = ti.ndarray(dtype, size)
            if name in values:
                fields[name].from_numpy(values[name])
                arrays[name].from_numpy(values[name])
        order = ("p", "q", "mass", "offsets", "other", "coef")
        pack = Pack(**{name: arrays[name] for name in order})
        for loops in ("serial", "parallel"):
            serial = loops == "serial"
            row = {"resolution": resolution, "springs": model.n_springs, "loops": loops,
                   "fields_ms": median_ms(on_fields, [fields[k] for k in order] + [serial], args.repeats),
                   "ndarray_ms": median_ms(on_ndarrays, [arrays[k] for k in order] + [serial], args.repeats),
                   "argpack_ms": median_ms(on_argpack, (pack, serial), args.repeats)}
            row["ndarray_over_fields"] = row["ndarray_ms"] / row["fields_ms"]
            rows.append(row)
            print(f"{resolution:4d} {model.n_springs:8d} {loops:>8s} {row['fields_ms']:10.3f} {row['ndarray_ms']:11.3f} "
                  f"{row['argpack_ms']:11.3f} {row['ndarray_over_fields']:15.2f}", flush=True)
    write_json(args.json, rows)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    sys.exit(main())
