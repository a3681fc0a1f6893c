"""Export the frames of a run as OBJ files for Blender (or Houdini, ParaView).

Shows: the frame schedule of the command line (``io.render.frame_steps``), the
per-frame exporter ``io.frames.FrameExport`` as the run loop's frame callback (each
file written as the run goes, with a manifest of steps and times), and marking the
manifest when the run ends. The same from the shell:

    massspring run cloth --export frames/ --format obj --frames 60

In Blender, import the numbered OBJ files as one animated object with a mesh-sequence
add-on (for example "Stop-motion-OBJ"); in Houdini, a File node reading
frames/frame_$F5.obj (numbers start at 0); for ParaView use --format vtk and open
frames/frames.pvd.

    python examples/export_for_blender.py [--small] [--out DIR]
"""

import argparse
import os

import massspring as ms
from massspring.io.frames import FrameExport
from massspring.io.render import frame_steps


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", default=bool(os.environ.get("MASSSPRING_EXAMPLE_SMALL")),
                        help="a quick run (also with MASSSPRING_EXAMPLE_SMALL=1)")
    parser.add_argument("--out", default="frames", help="the directory of the frames (default ./frames)")
    args = parser.parse_args(argv)

    scene = ms.load_scene("cloth").with_params(resolution=6 if args.small else 32)
    sim = scene.simulation(tol=None)  # fixed steps of the scene's integrator and dt (implicit, 1/60 s)
    steps = 6 if args.small else int(round(scene.duration / sim.dt))
    schedule = frame_steps(steps, frames=min(steps + 1, 60))
    export = FrameExport(args.out, "obj", len(schedule), scene=scene.name,
                         info={"scene": {"name": scene.name, "params": scene.params}, "dt": sim.dt})
    export.prepare()  # creates the directory; ValueError if it cannot be written
    status, message = "complete", ""
    try:
        ms.run(sim, steps, frames=schedule, on_frame=export)
    except ms.DivergenceError as exc:
        status, message = "diverged", str(exc)
    except KeyboardInterrupt:
        status = "interrupted"
    error = export.finish(status, sim, message)
    print(f"{len(export)} OBJ frames in {args.out}/ ({status}); manifest {args.out}/manifest.json"
          + (f"; {error}" if error else ""))
    sim.close()


if __name__ == "__main__":
    main()
