"""Cost of meshes in and frames out: reading an OBJ and building its Model, and writing one
frame per format.

Reading: a quad grid of N x N vertices written as OBJ (``f v/vt/vn`` indices, as Blender
writes them), then ``io.obj.read_obj`` and ``Model.from_mesh`` timed (the best of
``--repeats`` runs). Writing: the cloth scene at each resolution, one frame written by
``io.frames.FrameExport`` per format (the per-frame cost of ``run --export``, manifest
included), best of ``--repeats``, and the file's size.

    python benchmarks/mesh_io.py --help
    python benchmarks/mesh_io.py --read 300 1000 --write 32 128
"""

import argparse
import os
import tempfile
import time

import numpy as np

import massspring as ms
from massspring.io.files import write_json
from massspring.io.frames import FORMATS, FrameExport
from massspring.io.obj import read_obj
import output


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--read", type=int, nargs="*", default=[300, 1000], help="OBJ grid sizes (vertices per side)")
    p.add_argument("--write", type=int, nargs="*", default=[32, 128], help="cloth resolutions of the frames")
    p.add_argument("--repeats", type=int, default=3)
    output.add_json(p, "mesh_io")
    return p.parse_args(argv)


def grid_obj(path, n):
    """An n x n vertex quad grid of side 1 m as OBJ, with a vt per vertex and one vn."""
    g = np.arange(n) / (n - 1)
    with open(path, "w") as fh:
        fh.write("".join(f"v {x!r} {y!r} 0.0\n" for y in g.tolist() for x in g.tolist()))
        fh.write("".join(f"vt {x!r} {y!r}\n" for y in g.tolist() for x in g.tolist()))
        fh.write("vn 0 0 1\n")
        a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel() + 1
        quads = np.stack([a, a + 1, a + n + 1, a + n], axis=1)
        fh.write("".join("f {0}/{0}/1 {1}/{1}/1 {2}/{2}/1 {3}/{3}/1\n".format(*q) for q in quads.tolist()))


def best(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv=None):
    args = parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'vertices':>10s} {'faces':>10s} {'MB':>7s} {'read_obj s':>10s} {'from_mesh s':>11s} "
              f"{'springs':>10s}")
        for n in args.read:
            path = os.path.join(tmp, f"grid{n}.obj")
            grid_obj(path, n)
            read, mesh = best(lambda: read_obj(path), args.repeats)
            build, model = best(lambda: ms.Model.from_mesh(mesh.vertices, mesh.faces), args.repeats)
            size = os.path.getsize(path) / 1e6
            rows.append({"kind": "read", "vertices": n * n, "faces": len(mesh.faces), "mb": size,
                         "read_obj_s": read, "from_mesh_s": build, "springs": model.n_springs})
            print(f"{n * n:10d} {len(mesh.faces):10d} {size:7.1f} {read:10.2f} {build:11.2f} {model.n_springs:10d}",
                  flush=True)

        print(f"\n{'resolution':>10s} {'particles':>10s} " + " ".join(f"{f + ' ms':>9s} {f + ' MB':>9s}" for f in FORMATS))
        for r in args.write:
            sim = ms.load_scene("cloth").with_params(resolution=r).simulation(tol=None)
            row = {"kind": "write", "resolution": r, "particles": sim.model.n_particles}
            cells = []
            for fmt in FORMATS:
                directory = os.path.join(tmp, f"{fmt}{r}")
                try:
                    FrameExport(directory, fmt, 1, "cloth").prepare()
                except ValueError as exc:  # its module is not installed
                    print(exc)
                    cells.append(f"{'-':>9s} {'-':>9s}")
                    continue

                def frame():
                    export = FrameExport(directory, fmt, 1, "cloth")
                    export(sim)
                    export.finish("complete", sim)  # a single-file format writes here
                    return export.frames[0]["file"]

                seconds, name = best(frame, args.repeats)
                size = os.path.getsize(os.path.join(directory, name)) / 1e6
                row[f"{fmt}_ms"], row[f"{fmt}_mb"] = 1e3 * seconds, size
                cells.append(f"{1e3 * seconds:9.1f} {size:9.2f}")
            sim.close()
            rows.append(row)
            print(f"{r:10d} {r * r:10d} " + " ".join(cells), flush=True)
    write_json(args.json, rows)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
