"""The current code against an earlier revision, side by side in one run.

The base revision is checked out in a git worktree and installed beside the
current one (``pip install --no-deps --target``; run with ``python -S`` and
``PYTHONPATH`` so that the current editable install does not shadow it). Every
measurement is a fresh process running ``measure_case.py`` (public API only, so
both revisions run the same code); revisions alternate, and which goes first
alternates too, so drifting load on a shared machine hits both alike. Reported:
the median over ``--repeats`` processes, and new/base ratios.

Cases (cloth scene, f64): implicit ms per CG iteration at 32, 128, 512 (from two
solves capped at k and 2k iterations); explicit and symplectic ms per step at 32,
128, 256 (dt = 2e-4 / res); multigrid-preconditioned implicit ms per step (setup
included, dt = 1/60) at 128 and 256; cold first step (Simulation built, kernels compiled
with an empty Taichi offline cache, one step) of the implicit and symplectic
32 x 32 cloth; the sheets scene at 16 x 16 (self-collision every step, the upper
sheet landing) with the implicit, backward-Euler and symplectic steps, ms per step.

    python benchmarks/compare_revisions.py --base f17ee13
    python benchmarks/compare_revisions.py --base f17ee13 --cases symplectic-128 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
import output

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
CASES = ["implicit-32", "implicit-128", "implicit-512", "explicit-32", "explicit-128", "explicit-256",
         "symplectic-32", "symplectic-128", "symplectic-256", "multigrid-128", "multigrid-256", "cold-implicit-32",
         "cold-symplectic-32", "sheets-implicit-16", "sheets-backward-euler-16", "sheets-symplectic-16"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", required=True, help="git revision to compare against (e.g. f17ee13)")
    p.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    p.add_argument("--repeats", type=int, default=5, help="processes per case and revision (median reported)")
    p.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "massspring-revisions"),
                   help="where the base revision's worktree and install go")
    output.add_json(p, "compare_revisions")
    return p.parse_args(argv)


def install_base(rev, cache):
    """Worktree + target install of ``rev``; returns (its site dir, the commit hash)."""
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", rev], capture_output=True, text=True,
                         check=True).stdout.strip()
    tree, site = Path(cache) / f"tree-{sha[:12]}", Path(cache) / f"site-{sha[:12]}"
    if not (site / "massspring").is_dir():
        Path(cache).mkdir(parents=True, exist_ok=True)
        if not tree.is_dir():
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), sha], check=True,
                           capture_output=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
                        str(tree)], check=True)
    return site, sha


def run_case(case, base_site):
    """One fresh process measuring ``case`` on the base revision (``base_site``) or the
    current code (None); returns its JSON result."""
    env = dict(os.environ)
    command = [sys.executable]
    if base_site is not None:
        command.append("-S")  # no .pth files: the current editable install stays out of the way
        env["PYTHONPATH"] = os.pathsep.join([str(base_site), sysconfig.get_paths()["purelib"]])
    with tempfile.TemporaryDirectory() as cache:
        if case.startswith("cold-"):
            env["TI_OFFLINE_CACHE_FILE_PATH"] = cache
        proc = subprocess.run(command + [str(HERE / "measure_case.py"), case], capture_output=True, text=True,
                              env=env, cwd=tempfile.gettempdir(), timeout=1800)
    if proc.returncode:
        raise RuntimeError(f"{case} ({'base' if base_site else 'new'}) failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    args = parse_args(argv)
    from massspring.io.files import write_json

    site, sha = install_base(args.base, args.cache)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    print(f"base {sha[:10]} vs current {head} (+ working tree); {args.repeats} processes each, interleaved")
    width = max(20, *(len(case) for case in args.cases))
    print(f"{'case':{width}s} {'unit':>8s} {'base':>10s} {'new':>10s} {'new/base':>9s}")
    rows = []
    for case in args.cases:
        samples = {"base": [], "new": []}
        for k in range(args.repeats):
            order = [("base", site), ("new", None)]
            for name, where in (order if k % 2 == 0 else order[::-1]):
                samples[name].append(run_case(case, where)["value"])
        unit = "s" if case.startswith("cold-") else "ms"
        base, new = statistics.median(samples["base"]), statistics.median(samples["new"])
        rows.append({"case": case, "unit": unit, "base": base, "new": new, "ratio": new / base,
                     "samples": samples})
        print(f"{case:{width}s} {unit:>8s} {base:10.4f} {new:10.4f} {new / base:9.3f}", flush=True)
    write_json(args.json, {"base": sha, "current": head, "repeats": args.repeats, "cases": rows})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    sys.exit(main())
