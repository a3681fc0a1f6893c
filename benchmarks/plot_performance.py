"""The README's performance figure and tables, from the benchmarks' JSON results.

Reads benchmarks/results/{implicit_step,explicit_step,scaling,roofline}.json
(written by the scripts of the same names), prints the README's markdown tables
and draws docs/performance.png (needs matplotlib: pip install "massspring[plot]").

    python benchmarks/plot_performance.py --help
    python benchmarks/plot_performance.py --results benchmarks/results --png docs/performance.png
"""

import argparse
import json
import sys
from pathlib import Path


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", default="benchmarks/results", help="folder of the benchmarks' JSON files")
    p.add_argument("--png", default="docs/performance.png")
    return p.parse_args(argv)


def load(folder, name):
    path = Path(folder) / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def implicit_table(data):
    lines = ["| res | ks | springs | massspring ms/step | CG it | ms/it | SciPy Jacobi-PCG ms/step "
             "(it: SciPy vs massspring), speed-up | ti.linalg.MatrixFreeCG ms/step (it), speed-up | "
             "SciPy LU ms/step, speed-up |",
             "|---|---|---|---|---|---|---|---|---|"]
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

        lines.append(f"| {row['resolution']} | {row['stiffness']:.0e} | {row['springs']} | {row['step_ms']:.1f} | "
                     f"{row['iterations']:.0f} | {row['ms_per_iteration']:.3f} | {cell('scipy')} | "
                     f"{cell('taichi-cg')} | {cell('direct')} |")
    return "\n".join(lines)


def explicit_table(data):
    lines = ["| res | integrator | massspring steps/s | NumPy steps/s (ratio) | Warp CPU steps/s (ratio) |",
             "|---|---|---|---|---|"]
    for row in data["rows"]:
        peers = row["peers"]
        cells = [f"{peers[name]['steps_per_s']:.0f} ({peers[name]['ratio']:.1f}x)" if name in peers else "-"
                 for name in ("numpy", "warp")]
        lines.append(f"| {row['resolution']} | {row['integrator']} | {row['steps_per_s']:.0f} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def plot(implicit, explicit, scaling, png):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print('matplotlib is not installed: no figure (pip install "massspring[plot]")')
        return
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    if implicit:
        ax = axes[0]
        rows = [r for r in implicit["rows"] if r["precision"] == "f64" and r["stiffness"] == 1e4]
        springs = [r["springs"] for r in rows]
        ax.loglog(springs, [r["step_ms"] for r in rows], "o-", label="massspring (block-Jacobi PCG)")
        for name, label in (("scipy", "SciPy assembled + Jacobi PCG"), ("taichi-cg", "ti.linalg.MatrixFreeCG"),
                            ("direct", "SciPy sparse LU")):
            pts = [(r["springs"], r["peers"][name]["step_ms"]) for r in rows if name in r["peers"]]
            if pts:
                ax.loglog(*zip(*pts), "s--", label=label)
        ax.set(xlabel="springs", ylabel="ms per implicit step", title="Implicit step, cloth, ks = 1e4, f64")
        ax.legend(fontsize=8)
    if explicit:
        ax = axes[1]
        for integrator, style in (("explicit", "o-"), ("symplectic", "^-")):
            rows = [r for r in explicit["rows"] if r["integrator"] == integrator]
            springs = [r["springs"] for r in rows]
            ax.loglog(springs, [r["steps_per_s"] for r in rows], style, label=f"massspring {integrator}")
            for name in ("numpy", "warp"):
                pts = [(r["springs"], r["peers"][name]["steps_per_s"]) for r in rows if name in r["peers"]]
                if pts:
                    ax.loglog(*zip(*pts), style.replace("-", ":"), label=f"{name} {integrator}", alpha=0.7)
        ax.set(xlabel="springs", ylabel="steps per second", title="Explicit steps, cloth, f64")
        ax.legend(fontsize=7)
    if scaling:
        ax = axes[2]
        rows = [r for r in scaling["rows"] if r["integrator"] == "implicit"]
        ax.semilogx([r["springs"] for r in rows], [r["ns_per_spring_iteration"] for r in rows], "o-",
                    label="implicit: ns per spring-iteration")
        for integrator in ("explicit", "symplectic"):
            rows = [r for r in scaling["rows"] if r["integrator"] == integrator]
            ax.semilogx([r["springs"] for r in rows], [r["ns_per_spring_step"] for r in rows], "^--",
                        label=f"{integrator}: ns per spring-step")
        ax.set(xlabel="springs", ylabel="ns", title="Cost per unit of work (flat = linear scaling)", ylim=(0, None))
        ax.legend(fontsize=8)
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
