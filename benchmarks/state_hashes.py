"""The state of every shipped scene with every integrator after a few steps at the
scene's default dt, as a SHA-1 of its positions and velocities: run it in two checkouts
and compare the JSON files to see that a refactor left every forward result bit for bit
the same (``--compare`` does that and exits 1 on a difference).

    python benchmarks/state_hashes.py --json benchmarks/out/new.json
    (cd OTHER_CHECKOUT && python benchmarks/state_hashes.py --json benchmarks/out/base.json)
    python benchmarks/state_hashes.py --compare OTHER_CHECKOUT/benchmarks/out/base.json benchmarks/out/new.json

Scenes of more than ``LARGE`` particles take ``--large-steps`` steps, the others
``--steps``. A run that raises is recorded as "error: ..." (and so compared too).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import output

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LARGE = 5000  # particles


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--large-steps", type=int, default=3)
    p.add_argument("--compare", nargs=2, metavar=("BASE", "NEW"), help="compare two outputs instead of running")
    output.add_json(p, "state_hashes")
    return p.parse_args(argv)


def state_hash(sim) -> str:
    import numpy as np

    data = np.ascontiguousarray(sim.positions).tobytes() + np.ascontiguousarray(sim.velocities).tobytes()
    return hashlib.sha1(data).hexdigest()


def hashes(steps, large_steps) -> dict:
    import massspring as ms
    from massspring.integrators import INTEGRATORS
    from massspring.scene import builtin_scenes

    out = {}
    for name in builtin_scenes():
        scene = ms.load_scene(name)
        count = large_steps if scene.counts()[0] > LARGE else steps
        for integrator in INTEGRATORS:
            start = time.perf_counter()
            try:
                sim = scene.simulation(integrator, tol=None)
                try:
                    out[f"{name}/{integrator}"] = state_hash(sim.step(count))
                finally:
                    sim.close()
            except Exception as exc:  # recorded, and compared like a hash
                out[f"{name}/{integrator}"] = f"error: {type(exc).__name__}: {str(exc)[:120]}"
            print(f"{name:12s} {integrator:15s} {count:3d} steps  {out[f'{name}/{integrator}'][:16]}  "
                  f"{time.perf_counter() - start:6.2f} s", flush=True)
    return out


def compare(base_path, new_path) -> int:
    base, new = (json.loads(Path(p).read_text()) for p in (base_path, new_path))
    differ = sorted(k for k in base.keys() | new.keys() if base.get(k) != new.get(k))
    for key in differ:
        print(f"{key}: {base.get(key)} -> {new.get(key)}")
    print(f"{len(base.keys() & new.keys())} cases in both, {len(differ)} differ")
    return 1 if differ else 0


def main(argv=None):
    args = parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    result = hashes(args.steps, args.large_steps)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    print(f"{len(result)} cases -> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
