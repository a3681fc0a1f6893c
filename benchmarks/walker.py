"""Feedback controllers in a training loop (issue 63): their gradient's cost, and DiffTaichi's
walker trained in both engines.

1. Cost: the value and gradient of a run with a feedback controller against the same run
   forward (a Simulation stepped with the controller), alternately ``--repeats`` times
   after a warm-up of each (medians): ``examples/walker.py``'s robot (its ``SineNetwork``
   choosing the muscles at every one of 682 symplectic steps, with ground contact and
   friction), and the ``cloth`` scene at ``--resolution`` with air drag and a wind that a
   linear feedback controller (``WindFeedback``) sets every 10 steps from the cloth's mean
   velocity, 200 symplectic steps of half the predicted stability limit.
2. Training (with ``--difftaichi PATH``, the ``examples/`` folder of a checkout of
   https://github.com/taichi-dev/difftaichi): DiffTaichi's own ``mass_spring.py`` robot 2
   (``benchmarks/difftaichi_runner.py``: its source run as it is, GUI stubbed; another
   with ``--robot``) and ``examples/walker.py``'s copy of the robot, each trained ``--iterations`` iterations
   with DiffTaichi's update (a step of 0.2 along the normalised gradient); the distance
   the head travelled in the last iteration's run (682 steps of 4 ms each) and the median
   CPU and wall seconds per iteration after the first (DiffTaichi's own process, float32;
   massspring's, float64), measured in one run of this script.

    python benchmarks/walker.py --difftaichi ~/src/difftaichi/examples
    python benchmarks/walker.py --iterations 0 --json benchmarks/out/walker_cost.json   # the cost part only
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import walker  # noqa: E402
import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402


class WindFeedback(ms.Controller):
    """wind = w0 + gain @ (mean velocity of the particles), m/s, every ``interval`` s."""

    drives = ("wind",)

    def __init__(self, interval):
        self.interval = interval
        self.parameters = {"w0": np.array([1.0, 0.0, 0.5]), "gain": -0.5 * np.eye(3)}

    def controls(self, state):
        return {"wind": self.parameters["w0"] + self.parameters["gain"] @ state.velocities.mean(axis=0)}

    def vjp(self, state, cotangents):
        c = cotangents["wind"]
        n = state.velocities.shape[0]
        dv = np.tile(self.parameters["gain"].T @ c / n, (n, 1))
        return ({"w0": c, "gain": np.outer(c, state.velocities.mean(axis=0))}, np.zeros_like(dv), dv)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--difftaichi", help="the examples/ folder of a DiffTaichi checkout (the training race)")
    p.add_argument("--iterations", type=int, default=100, help="training iterations of each engine (0: none)")
    p.add_argument("--robot", type=int, choices=walker.ROBOTS, default=2, help="DiffTaichi's robot (default 2)")
    p.add_argument("--resolution", type=int, default=64, help="the cloth's resolution (default 64)")
    p.add_argument("--repeats", type=int, default=5)
    output.add_json(p, "walker")
    return p.parse_args(argv)


def cost(model, controller, steps, dt, objective, repeats):
    """Median wall s of the forward run and of the value and gradient, alternately."""
    names = [f"controller.{name}" for name in controller.parameters]

    def forward():
        ms.Simulation(model, "symplectic", dt=dt, controller=controller).step(steps).close()

    def backward():
        ms.gradient(model, objective, names, steps=steps, every=steps, integrator="symplectic", dt=dt,
                    controller=controller)

    times = {"forward": [], "gradient": []}
    for run in (forward, backward):
        run()  # compiles
    for _ in range(repeats):
        for name, run in (("forward", forward), ("gradient", backward)):
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    medians = {name: statistics.median(values) for name, values in times.items()}
    return {**{f"{name}_s": value for name, value in medians.items()}, "ratio": medians["gradient"] / medians["forward"]}


def cloth_case(resolution):
    from massspring.analysis.stability import predict
    from massspring.integrators import INTEGRATORS

    scene = ms.load_scene("cloth").with_params(resolution=resolution)
    dt = INTEGRATORS["symplectic"].suggest_dt(predict(scene.model()))  # half the predicted limit
    steps, every = 200, 10
    controller = WindFeedback(every * dt)
    intervals = steps // every
    model = scene.model().replaced(drag=0.05, controls=ms.Controls(every * dt, wind=np.zeros((intervals, 3))))

    def objective(frames):
        partials = np.zeros_like(frames.positions)
        partials[-1, :, 2] = 1.0 / frames.positions.shape[1]
        return frames.positions[-1, :, 2].mean(), {"positions": partials}
    return model, controller, steps, dt, objective


def train_massspring(iterations, number):
    """Per-iteration distance (m) and CPU and wall seconds of ``walker.train``'s loop."""
    cpu, marks = [], []

    def report(_):
        cpu.append(time.process_time())
        marks.append(time.perf_counter())

    start_cpu, start_wall = time.process_time(), time.perf_counter()
    distances, _ = walker.train(iterations, report=report, number=number)
    cpu_s = np.diff([start_cpu, *cpu])
    wall_s = np.diff([start_wall, *marks])
    return {"distances": distances.tolist(), "cpu_s": cpu_s.tolist(), "wall_s": wall_s.tolist()}


def summary(distance, cpu_s, wall_s):
    later = slice(1, None) if len(cpu_s) > 1 else slice(None)
    return {"distance": distance, "cpu_s_per_iteration": statistics.median(cpu_s[later]),
            "wall_s_per_iteration": statistics.median(wall_s[later])}


def main(argv=None):
    args = parse_args(argv)
    out = {"cost": {}, "training": {}}
    net = walker.network(number=args.robot)
    out["cost"]["walker"] = cost(walker.model(net, number=args.robot), net, walker.STEPS, walker.DT, walker.head_x,
                                 args.repeats)
    out["cost"][f"cloth {args.resolution}"] = cost(*cloth_case(args.resolution), repeats=args.repeats)
    print(f"{'run':<14} {'forward s':>10} {'gradient s':>11} {'ratio':>7}")
    for name, row in out["cost"].items():
        print(f"{name:<14} {row['forward_s']:>10.3f} {row['gradient_s']:>11.3f} {row['ratio']:>7.2f}")
    if args.iterations:
        if args.difftaichi:
            import difftaichi_runner

            theirs = difftaichi_runner.run(args.difftaichi, args.robot, args.iterations, quiet=True)
            out["training"]["difftaichi"] = {**summary(theirs["distance"], [i["cpu_s"] for i in theirs["iterations"]],
                                                      [i["wall_s"] for i in theirs["iterations"]]),
                                             "source": theirs["difftaichi"], "losses": [i["loss"] for i in theirs["iterations"]]}
        ours = train_massspring(args.iterations, args.robot)
        out["training"]["massspring"] = {**summary(ours["distances"][-1], ours["cpu_s"], ours["wall_s"]),
                                         "distances": ours["distances"]}
        print(f"\n{args.iterations} training iterations, 682 steps of 4 ms each")
        print(f"{'engine':<12} {'distance':>9} {'CPU s/it':>9} {'wall s/it':>10}")
        for name, row in out["training"].items():
            print(f"{name:<12} {row['distance']:>9.4f} {row['cpu_s_per_iteration']:>9.3f} "
                  f"{row['wall_s_per_iteration']:>10.3f}")
    out["args"] = vars(args)
    write_json(args.json, out)
    print(f"wrote {args.json}")
    json.dumps(out)  # plain data


if __name__ == "__main__":
    main()
