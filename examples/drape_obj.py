"""Load an OBJ mesh and drape it over a sphere standing on the ground.

Shows: ``massspring.io.obj.read_obj`` (a mesh from Blender or any tool that writes
OBJ; quads are kept as faces), ``Model.from_mesh`` with a surface density, spring
stiffness, bending and shear factors and colliders (a sphere and the ground, with
friction), the implicit integrator at a frame-sized step, and OBJ frames of the
result written with ``io.obj.write_obj``.

The mesh is centred over the sphere and dropped from just above it: it lands on the
sphere's top, and its free edges fall into folds around it.

    python examples/drape_obj.py [--small] [--mesh examples/cloth.obj] [--out DIR]
"""

import argparse
import os
from pathlib import Path

import numpy as np

import massspring as ms
from massspring.io.obj import read_obj, write_obj

HERE = Path(__file__).resolve().parent
RADIUS = 0.3  # m, the sphere's; it stands on the ground (z = 0) with its top at 2 RADIUS
GAP = 0.05    # m between the sphere's top and the mesh at the start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--mesh", default=str(HERE / "cloth.obj"), help="the OBJ file (default: examples/cloth.obj)")
    parser.add_argument("--out", help="write the first and last frames as OBJ files into this directory")
    args = parser.parse_args(argv)

    mesh = read_obj(args.mesh)  # raises ObjError "FILE:LINE: reason" on a bad file
    # lay the mesh flat (its thinnest extent vertical), centred over the sphere's top
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    flat = int(np.argmin(high - low))
    vertices = np.roll(mesh.vertices - (low + high) / 2, 2 - flat, axis=1) + [0.0, 0.0, 2 * RADIUS + GAP]
    sphere = ms.Sphere((0.0, 0.0, RADIUS), RADIUS, friction=0.5)
    ground = ms.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), friction=0.5)
    model = ms.Model.from_mesh(vertices, mesh.faces, density=0.2, stiffness=2000.0, damping=0.5, bend=0.05,
                               shear=1.0, colliders=[sphere, ground])
    print(f"{args.mesh}: {model.n_particles} vertices, {len(mesh.faces)} faces -> {len(model.triangles)} triangles, "
          f"{model.n_springs} springs, {model.masses.sum():.4g} kg, over a sphere of radius {RADIUS} m")

    sim = ms.Simulation(model, integrator="implicit", dt=1 / 60)
    steps = 40 if args.small else 180

    def report(s):
        x = s.positions
        on_sphere = np.abs(np.linalg.norm(x - sphere.center, axis=1) - RADIUS) < 0.01
        print(f"t = {s.time:.2f} s: {on_sphere.sum()} of {len(x)} vertices rest on the sphere (within 1 cm), "
              f"highest z = {x[:, 2].max():.3f} m, lowest z = {x[:, 2].min():.3f} m")

    ms.run(sim, steps, frames=[steps], on_frame=report)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_obj(out / "drape_first.obj", model.positions, model.triangles)
        write_obj(out / "drape_last.obj", sim.positions, model.triangles)
        print(f"wrote {out / 'drape_first.obj'} and {out / 'drape_last.obj'}")
    sim.close()


if __name__ == "__main__":
    main()
