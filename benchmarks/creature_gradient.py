"""The cost of ``examples/creature.py``'s gradient against its forward run (issue 60's
target: at most 4x): the 10-particle creature crawling on a ground with friction, its
muscles' rest lengths set per interval of 0.05 s (``controls.rest_lengths``), symplectic
steps of 1 ms, the value and gradient of the distance it crawls in ``--seconds`` s
(the last frame only, as the example asks) against ``Simulation.step`` over the same
steps, timed alternately ``--repeats`` times after a warm-up of each (medians).

    python benchmarks/creature_gradient.py
    python benchmarks/creature_gradient.py --json benchmarks/results/creature_gradient.json
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
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "examples"))
import creature  # noqa: E402
import massspring as ms  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=1.0)
    p.add_argument("--repeats", type=int, default=7)
    output.add_json(p, "creature_gradient")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    intervals = max(1, round(args.seconds / creature.INTERVAL))
    steps = round(intervals * creature.INTERVAL / creature.DT)
    positions, springs, muscles = creature.lattice()
    rest = np.linalg.norm(np.diff(positions[springs[muscles]], axis=1)[:, 0], axis=1)
    lengths = np.tile(rest, intervals) * (1 + 0.1 * np.sin(np.arange(intervals * muscles.size)))  # muscles at work
    model = creature.creature(lengths, muscles, intervals)

    def forward():
        sim = ms.Simulation(model, "symplectic", dt=creature.DT)
        sim.step(steps)
        sim.close()

    def gradient():
        ms.gradient(model, creature.distance, "controls.rest_lengths", steps=steps, every=steps,
                    integrator="symplectic", dt=creature.DT)

    forward(), gradient()  # compiled
    times = {"forward": [], "gradient": []}
    for _ in range(args.repeats):
        for name, call in (("forward", forward), ("gradient", gradient)):
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    fwd, grad = statistics.median(times["forward"]), statistics.median(times["gradient"])
    result = {"steps": steps, "intervals": intervals, "repeats": args.repeats, "forward_s": fwd, "gradient_s": grad,
              "ratio": grad / fwd}
    print(f"creature, {steps} symplectic steps, {intervals} control intervals: forward {1e3 * fwd:.2f} ms, value and "
          f"gradient {1e3 * grad:.2f} ms (median of {args.repeats}): {grad / fwd:.2f}x")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
