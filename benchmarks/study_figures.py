"""Regenerate the figures of docs/stability-and-study.md: the work-precision study of
the cloth and chain scenes at their default sizes (``massspring study`` defaults).

Writes study_<scene>.png (work-precision plots; into benchmarks/out/ unless --docs docs,
which replaces the committed ones) and each study's runs.csv,
runs.json and summary.json under --out, and prints the Markdown table docs/stability-and-study.md
shows: measured orders and, for target errors 1e-2 and 1e-4, the cheapest run.

    python benchmarks/study_figures.py                 # cloth and chain, a few minutes each
    python benchmarks/study_figures.py --scenes chain  # one scene
"""

from __future__ import annotations

import argparse
from pathlib import Path

import massspring as ms
from massspring.analysis import fits, report, study

import output


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["cloth", "chain"])
    p.add_argument("--docs", default=str(output.OUT), help="where the PNGs go (default benchmarks/out/; "
                   "docs/stability-and-study.md shows those)")
    p.add_argument("--out", default="study-figures", help="where the CSV/JSON of each study go")
    return p.parse_args(argv)


def markdown(results) -> str:
    lines = ["| scene | order explicit | order symplectic | order implicit | "
             + " | ".join(f"cheapest for error <= {t:g}" for t in fits.TARGETS) + " |",
             "|---" * (4 + len(fits.TARGETS)) + "|"]
    for result in results:
        orders = fits.integrator_orders(result.orders)
        cells = [result.scene] + [_order(orders.get(name)) for name in ("explicit", "symplectic", "implicit")]
        for target in fits.TARGETS:
            best = fits.cheapest(result.runs, target)
            if best is None:
                cells.append("none reached it")
            else:
                tol = "" if best["cg_tol"] is None else f", cg_tol {best['cg_tol']:g}"
                cells.append(f"{best['integrator']} dt {best['dt']:.3g} s{tol}: {best['wall_s']:.3g} s "
                             f"(error {best['error']:.2g})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _order(value):
    return "-" if value is None else f"{value:.2f}"


def main(argv=None):
    args = parse_args(argv)
    docs = Path(args.docs)
    docs.mkdir(parents=True, exist_ok=True)
    results = []
    for name in args.scenes:
        scene = ms.load_scene(name)
        result = study.run_study(scene, progress=report.print_progress)
        print(report.report(result), "\n")
        report.write_outputs(result, Path(args.out) / name)
        report.plot(result, docs / f"study_{name}.png")
        results.append(result)
    print(markdown(results))


if __name__ == "__main__":
    main()
