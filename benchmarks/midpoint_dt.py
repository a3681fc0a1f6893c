"""The midpoint rule's dt per shipped scene (issue 60): each scene run whole with
``midpoint`` at 1/60, 1/120, 1/240, ... s (none larger than the scene's implicit dt),
down to the first dt whose run ends without divergence and whose total energy never
rose above its start by more than 1% (+1 mJ). A scene driven from outside (wind, moving
pins, controls), whose energy rises with the work done on it, instead takes the first
dt whose run ends with the energy of the next smaller dt's run within 5%. Prints a row
per run (outcome, largest and final total energy, wall time) and writes them as JSON;
the dt each scene stopped at is the one its ``[dt] midpoint`` entry holds
(docs/stability-and-study.md).

    python benchmarks/midpoint_dt.py [--scenes chain cloth ...] [--smallest 1920]
"""

from __future__ import annotations

import argparse
import time

import output
from massspring.support.errors import DivergenceError
from massspring.io.files import write_json
from massspring.scene import builtin_scenes, load_scene

GAIN = 0.01  # of the start's total energy
FLOOR = 1e-3  # J
SETTLED = 0.05  # a driven scene's final energy against the next smaller dt's


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=None, help="default: every shipped scene")
    p.add_argument("--smallest", type=int, default=1920, help="the ladder's last dt is 1 / this (default 1920)")
    output.add_json(p, "midpoint_dt")
    return p.parse_args(argv)


def run(scene, dt):
    """The scene's whole run at ``dt``: a row (outcome, steps, energies J, wall s)."""
    sim = scene.simulation(integrator="midpoint", dt=dt)
    steps = int(round(scene.duration / dt))
    start = most = sim.energy()["total"]
    outcome, wall = "ok", time.perf_counter()
    try:
        while sim.steps < steps:
            sim.step(min(5, steps - sim.steps))
            most = max(most, sim.energy()["total"])
    except DivergenceError:
        outcome = f"diverged at step {sim.steps + 1}"
    end = sim.energy()["total"]
    sim.close()
    good = outcome == "ok" and most <= start + GAIN * abs(start) + FLOOR
    return {"scene": scene.name, "dt": dt, "steps": steps, "outcome": outcome, "start_J": start, "most_J": most,
            "end_J": end, "wall_s": time.perf_counter() - wall, "good": good}


def driven(scene) -> bool:
    """Whether work is done on the scene from outside: wind, moving pins or controls."""
    model = scene.model()
    return bool((model.drag > 0 and any(model.wind)) or model.has_moving_pins or model.controls is not None)


def main(argv=None):
    args = parse_args(argv)
    rows = []
    for name in args.scenes or sorted(builtin_scenes()):
        scene = load_scene(name)
        rung, before, pushed = 60, None, driven(scene)
        while rung <= args.smallest:
            dt = 1.0 / rung
            rung *= 2
            if dt > scene.default_dt("implicit") * (1 + 1e-9):
                continue
            row = run(scene, dt)
            rows.append(row)
            print(f"{name:11s} 1/{1 / dt:<5.0f} {row['outcome']:22s} energy start {row['start_J']:10.4g} J, "
                  f"most {row['most_J']:10.4g} J, end {row['end_J']:10.4g} J; {row['wall_s']:6.1f} s"
                  f"{'  <- its midpoint dt' if row['good'] and not pushed else ''}", flush=True)
            if pushed:
                settled = (before is not None and before["outcome"] == row["outcome"] == "ok"
                           and abs(before["end_J"] - row["end_J"]) <= SETTLED * abs(row["end_J"]) + FLOOR)
                if settled:
                    before["good"], row["good"] = True, False
                    print(f"{name:11s} its midpoint dt: 1/{1 / before['dt']:.0f} (driven: it ends as 1/{1 / dt:.0f} "
                          "does)", flush=True)
                    break
                row["good"], before = False, row
            elif row["good"]:
                break
    write_json(args.json, rows)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
