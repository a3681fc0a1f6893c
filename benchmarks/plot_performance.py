"""The performance figure and tables, from the benchmarks' JSON results.

Reads benchmarks/results/{implicit_step,explicit_step,scaling,roofline}.json
(written by the scripts of the same names), prints the markdown tables of docs/performance.md
and draws the figure, by default into benchmarks/out/ (docs/performance.png is the
one docs/performance.md shows: pass --png docs/performance.png to replace it; needs matplotlib: pip install
-e ".[plot]" in the checkout).

    python benchmarks/plot_performance.py --help
    python benchmarks/plot_performance.py --results benchmarks/results --png docs/performance.png
"""

import argparse
import json
import sys
from pathlib import Path

import output
from massspring.support.extras import install_hint


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", default="benchmarks/results", help="folder of the benchmarks' JSON files")
    p.add_argument("--png", default=str(output.OUT / "performance.png"),
                   help="the figure (default benchmarks/out/performance.png; docs/performance.md shows "
                        "docs/performance.png)")
    return p.parse_args(argv)


def load(folder, name):
    path = Path(folder) / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def implicit_table(data):
    lines = ["| res | ks | springs | preconditioner | massspring ms/step | CG it | ms/it | "
             "SciPy Jacobi-PCG ms/step (it: SciPy vs massspring), speed-up | SciPy + pyamg ms/step (it), speed-up | "
             "ti.linalg.MatrixFreeCG ms/step (it), speed-up | SciPy LU ms/step, speed-up |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in data["rows"]:
        if row["precision"] != "f64":
            continue
        peers = row["peers"]

        def cell(name):
            p = peers.get(name)
            if not p:
                return "-"
            its = f" ({p['iterations']:.0f} vs {p['massspring_iterations']:.0f})" if p.get("iterations") else ""
            return f"{p['step_ms']:.0f}{its}, {p['speedup']:.1f}x"

        lines.append(f"| {row['resolution']} | {row['stiffness']:.0e} | {row['springs']} | {row['preconditioner']} | "
                     f"{row['step_ms']:.1f} | {row['iterations']:.0f} | {row['ms_per_iteration']:.3f} | "
                     f"{cell('scipy')} | {cell('pyamg')} | {cell('taichi-cg')} | {cell('direct')} |")
    return "\n".join(lines)


def scaling_table(data):
    """One row per mesh, size and stiffness; per solver "mean CG iterations (max) / ms per step"."""
    solvers = [name for name in SOLVER_STYLES if any(r["solver"] == name for r in data["rows"])]
    cases = {}
    for r in data["rows"]:
        cases.setdefault((r["mesh"], r["size"], r["stiffness"], r["springs"]), {})[r["solver"]] = r
    lines = ["| mesh | size | ks | springs | " + " | ".join(f"{name}: its (max), ms/step" for name in solvers) + " |",
             "|---|---|---|---|" + "---|" * len(solvers)]
    for (mesh, size, ks, springs), by_solver in cases.items():
        cells = []
        for name in solvers:
            r = by_solver.get(name)
            if r is None:
                cells.append("-")
                continue
            setup = f", setup {r['setup_share']:.0%}" if name == "multigrid" else ""
            cells.append(f"{r['iterations_mean']:.1f} ({r['iterations_max']}), {r['ms_per_step']:.1f}{setup}"
                         + ("" if r["converged"] else " (not converged)"))
        label = f"{size}^2" if mesh == "cloth" else f"{size:,} points"
        lines.append(f"| {mesh} | {label} | {ks:.0e} | {springs:,} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def explicit_table(data):
    lines = ["| res | precision | integrator | massspring steps/s | NumPy steps/s (ratio) | Warp kernels steps/s (ratio) | "
             "warp.sim steps/s (ratio) |",
             "|---|---|---|---|---|---|---|"]
    for row in data["rows"]:
        peers = row["peers"]
        cells = [f"{peers[name]['steps_per_s']:.0f} ({peers[name]['ratio']:.2f}x)" if name in peers else "-"
                 for name in ("numpy", "warp", "warp.sim")]
        lines.append(f"| {row['resolution']} | {row.get('precision', 'f64')} | {row['integrator']} | "
                     f"{row['steps_per_s']:.0f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


SOLVER_STYLES = {"none": "x", "block-jacobi": "o", "multigrid": "^", "pyamg": "s"}


def plot(implicit, explicit, scaling, png):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"matplotlib is not installed: no figure ({install_hint('plot')})")
        return
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    if implicit:
        ax = axes[0, 0]
        rows = [r for r in implicit["rows"] if r["precision"] == "f64" and r["stiffness"] == 1e4]
        for pre in dict.fromkeys(r["preconditioner"] for r in rows):
            mine = [r for r in rows if r["preconditioner"] == pre]
            ax.loglog([r["springs"] for r in mine], [r["step_ms"] for r in mine], SOLVER_STYLES.get(pre, "o") + "-",
                      label=f"massspring ({pre} PCG)")
        first = [r for r in rows if r["preconditioner"] == rows[0]["preconditioner"]] if rows else []
        for name, label in (("scipy", "SciPy assembled + Jacobi PCG"), ("pyamg", "SciPy + pyamg SA (setup each step)"),
                            ("taichi-cg", "ti.linalg.MatrixFreeCG"), ("direct", "SciPy sparse LU")):
            pts = [(r["springs"], r["peers"][name]["step_ms"]) for r in first if name in r["peers"]]
            if pts:
                ax.loglog(*zip(*pts), "s--", label=label, alpha=0.8)
        ax.set(xlabel="springs", ylabel="ms per implicit step", title="Implicit step, cloth, ks = 1e4, f64")
        ax.legend(fontsize=7)
    if scaling:
        cloth = [r for r in scaling["rows"] if r["mesh"] == "cloth"]
        for ax, key, ylabel, title in ((axes[0, 1], "iterations_mean", "CG iterations per step (mean)",
                                        "CG iterations against size (ks 1e4 solid, 1e6 dashed)"),
                                       (axes[1, 0], "ms_per_step", "ms per implicit step",
                                        "Step time against size (ks 1e4 solid, 1e6 dashed)")):
            for solver, marker in SOLVER_STYLES.items():
                for ks, line in ((1e4, "-"), (1e6, "--")):
                    pts = [(r["springs"], r[key]) for r in cloth if r["solver"] == solver and r["stiffness"] == ks]
                    if pts:
                        ax.plot(*zip(*pts), marker + line, label=f"{solver}, ks {ks:.0e}")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set(xlabel="springs", ylabel=ylabel, title=title)
            ax.legend(fontsize=7, ncol=2)
    if explicit:
        ax = axes[1, 1]
        precision = "f32" if any(r.get("precision") == "f32" for r in explicit["rows"]) else "f64"
        for integrator, style in (("explicit", "o-"), ("symplectic", "^-")):
            rows = [r for r in explicit["rows"]
                    if r["integrator"] == integrator and r.get("precision", "f64") == precision]
            if not rows:
                continue
            springs = [r["springs"] for r in rows]
            ax.loglog(springs, [r["steps_per_s"] for r in rows], style, label=f"massspring {integrator}")
            for name in ("numpy", "warp", "warp.sim"):
                pts = [(r["springs"], r["peers"][name]["steps_per_s"]) for r in rows if name in r["peers"]]
                if pts:
                    ax.loglog(*zip(*pts), style.replace("-", ":"), label=f"{name} {integrator}", alpha=0.7)
        ax.set(xlabel="springs", ylabel="steps per second", title=f"Explicit steps, cloth, {precision}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=80)
    print(f"wrote {png}")


def main(argv=None):
    args = parse_args(argv)
    implicit, explicit = load(args.results, "implicit_step"), load(args.results, "explicit_step")
    scaling, roofline = load(args.results, "scaling"), load(args.results, "roofline")
    if implicit:
        print(implicit_table(implicit), end="\n\n")
    if scaling:
        print(scaling_table(scaling), end="\n\n")
    if explicit:
        print(explicit_table(explicit), end="\n\n")
    if roofline:
        print(f"roofline: cloth {roofline['resolution']}, triad {max(roofline['triad_bytes_per_s'].values()) / 1e9:.1f} GB/s, "
              f"{roofline['bytes_per_iteration'] / roofline['springs']:.0f} B per spring-iteration; "
              + ", ".join(f"{v['loops']} {v['share_of_bound']:.0%}" for v in roofline["variants"]))
    plot(implicit, explicit, scaling, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
