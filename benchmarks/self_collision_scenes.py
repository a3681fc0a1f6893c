"""Every shipped self-collision scene with every integrator: crossings in sampled frames.

Runs each built-in scene that has a ``[self_collision]`` table, at its shipped size and
dt, with each integrator, for ``--duration`` seconds (default: the scene's, capped at
``--cap`` seconds for the explicit integrators, whose tiny dt makes a whole run long),
and counts at ``--frames`` evenly spaced frames the crossings (an edge through a triangle
it shares no particle with) with the tests' numpy counter (``tests/crossings.py``)
(not the project's own detection). Prints a table and writes JSON.

    python benchmarks/self_collision_scenes.py
    python benchmarks/self_collision_scenes.py --scenes ledge --integrators implicit bdf2
    python benchmarks/self_collision_scenes.py --json benchmarks/results/self_collision_scenes.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
import output  # noqa: E402
from crossings import crossings  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
from massspring.scene import builtin_scenes  # noqa: E402
from massspring.model.self_collision import mesh_edges  # noqa: E402

INTEGRATORS = ["explicit", "symplectic", "rk4", "implicit", "backward-euler", "bdf2"]
EXPLICIT = {"explicit", "symplectic", "rk4"}


def parse_args(argv=None):
    scenes = sorted(n for n in builtin_scenes() if ms.load_scene(n).self_collision is not None)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=scenes, choices=scenes)
    p.add_argument("--integrators", nargs="+", default=INTEGRATORS, choices=INTEGRATORS)
    p.add_argument("--frames", type=int, default=10, help="sampled frames per run (default 10)")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scene's)")
    p.add_argument("--cap", type=float, default=0.5,
                   help="at most this many simulated seconds for explicit, symplectic and rk4 (default 0.5)")
    output.add_json(p, "self_collision_scenes")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'scene':10s} {'integrator':14s} {'dt':>9s} {'time s':>7s} {'wall s':>7s}  crossings per frame")
    for name in args.scenes:
        scene = ms.load_scene(name)
        model = scene.model()
        edges = mesh_edges(model.triangles)
        for integrator in args.integrators:
            sim = scene.simulation(integrator)
            duration = args.duration or scene.duration
            if integrator in EXPLICIT:
                duration = min(duration, args.cap)
            steps = max(1, int(round(duration / sim.dt / args.frames)))
            counts, start = [], time.perf_counter()
            for _ in range(args.frames):
                sim.step(steps)
                counts.append(crossings(sim.positions, model.triangles, edges))
            wall = time.perf_counter() - start
            rows.append({"scene": name, "integrator": integrator, "dt": sim.dt, "time": sim.time, "wall_s": wall,
                         "crossings": counts})
            print(f"{name:10s} {integrator:14s} {sim.dt:9.3g} {sim.time:7.3f} {wall:7.1f}  {counts}", flush=True)
            sim.close()
    write_json(args.json, {"rows": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
