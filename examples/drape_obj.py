"""Load an OBJ mesh and drape it: a square cloth hangs from one edge under gravity.

Shows: ``massspring.io.obj.read_obj`` (a mesh from Blender or any tool that writes
OBJ; quads are kept as faces), ``Model.from_mesh`` with a surface density, spring
stiffness, bending and shear factors and a pin box, the implicit integrator at a
frame-sized step, and OBJ frames of the result written with ``io.obj.write_obj``.

Draping over an obstacle (a table, a sphere) needs colliders, which this version does
not have; here the cloth is pinned along an edge and falls into folds under gravity.

    python examples/drape_obj.py [--small] [--mesh examples/cloth.obj] [--out DIR]
"""

import argparse
import os
from pathlib import Path

import numpy as np

import massspring as ms
from massspring.io.obj import read_obj, write_obj

HERE = Path(__file__).resolve().parent


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--mesh", default=str(HERE / "cloth.obj"), help="the OBJ file (default: examples/cloth.obj)")
    parser.add_argument("--out", help="write the first and last frames as OBJ files into this directory")
    args = parser.parse_args(argv)

    mesh = read_obj(args.mesh)  # raises ObjError "FILE:LINE: reason" on a bad file
    top = mesh.vertices[:, 1].max()
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    model = ms.Model.from_mesh(mesh.vertices, mesh.faces, density=0.2, stiffness=2000.0, damping=0.5, bend=0.05,
                               shear=1.0, pin_box=[[low[0], top - 1e-6, low[2]], [high[0], top, high[2]]])
    print(f"{args.mesh}: {model.n_particles} vertices, {len(mesh.faces)} faces -> {len(model.triangles)} triangles, "
          f"{model.n_springs} springs, {model.fixed.size} pinned, {model.masses.sum():.4g} kg")

    sim = ms.Simulation(model, integrator="implicit", dt=1 / 60)
    steps = 6 if args.small else 120
    ms.run(sim, steps, frames=[steps], on_frame=lambda s: print(
        f"t = {s.time:.2f} s: lowest point z = {s.positions[:, 2].min():.3f} m, "
        f"mean CG iterations per step {np.mean(s.cg_iterations):.0f}"))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_obj(out / "drape_first.obj", model.positions, model.triangles)
        write_obj(out / "drape_last.obj", sim.positions, model.triangles)
        print(f"wrote {out / 'drape_first.obj'} and {out / 'drape_last.obj'}")
    sim.close()


if __name__ == "__main__":
    main()
