"""Output of a work-precision study: the text table and report, CSV/JSON files, the plot."""

from __future__ import annotations

import csv
import io
import json
import sys
from pathlib import Path

from massspring.analysis.fits import TARGETS, TIE, cheapest
from massspring.analysis.study import COLUMNS
from massspring.integrators import INTEGRATORS
from massspring.io.files import atomic_output


def _fmt(value, spec=".3g"):
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


def table(study) -> str:
    """The runs as a fixed-width text table."""
    head = ("integrator", "precond", "solver tol", "dt", "tol", "steps", "error", "err(t)", "energy", "wall_s",
            "CG its", "status")
    rows = [(r.integrator, _fmt(r.preconditioner), _fmt(r.cg_tol if r.newton_tol is None else r.newton_tol, ".0e"),
             _fmt(r.dt, ".4g") if r.tol is None else "chosen", _fmt(r.tol, ".0e"), str(r.steps), _fmt(r.error),
             _fmt(r.error_over_time), _fmt(r.energy_error), _fmt(r.wall_s, ".4g"),
             str(r.cg_iterations), r.status) for r in study.runs]
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(head)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in rows]
    return "\n".join(line.rstrip() for line in lines)


def report(study) -> str:
    """Table, reference check, orders and cheapest choices, as printed by the CLI."""
    out = [f"study of {study.scene}: end time {study.duration:g} s, {len(study.times)} save instants, "
           f"size {study.size:g} m", "", table(study), "", study.reference.describe(), "",
           "measured order (slope of log error vs log dt):"]
    for line, entry in study.orders.items():
        order, finest = (_fmt(entry[key], ".2f") for key in ("order", "order_finest"))
        out.append(f"  {line:28s} {order}  ({entry['points']} runs; over the 3 smallest dt: {finest})")
    out.append("")
    for target in TARGETS:
        best = cheapest(study.runs, target)
        if best is None:
            out.append(f"error <= {target:g}: no run reached it")
        else:
            line = f"error <= {target:g}: cheapest {_described(best)}"
            if best["ties"]:
                line += (f"; within the timing noise ({TIE:.0%}) of it, a tie: "
                         + ", ".join(_described(tie) for tie in best["ties"]))
            out.append(line)
    return "\n".join(out)


def _described(choice) -> str:
    """A cheapest run (``fits.cheapest``) in words."""
    tol = "" if choice["cg_tol"] is None else f" ({choice['preconditioner']}), cg_tol {choice['cg_tol']:g}"
    if choice["newton_tol"] is not None:
        tol = f" ({choice['preconditioner']}), newton_tol {choice['newton_tol']:g}"
    step = f"dt {choice['dt']:.4g} s" if choice["tol"] is None else f"error-controlled, tol {choice['tol']:g}"
    return f"{choice['integrator']} {step}{tol} (error {choice['error']:.3g}, {choice['wall_s']:.3g} s)"


def write_outputs(study, out_dir) -> list:
    """runs.csv, runs.json, summary.json and (with matplotlib) work_precision.png in ``out_dir``.

    Returns the paths written; a missing matplotlib is reported by ``plot`` raising ImportError.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [run.row() for run in study.runs]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    written = []
    for name, data in (("runs.csv", text.getvalue()), ("runs.json", json.dumps(rows, indent=1)),
                       ("summary.json", json.dumps(study.summary(), indent=1))):
        with atomic_output(out_dir / name) as fh:
            fh.write(data.encode())
        written.append(out_dir / name)
    return written


def plot(study, path, title=None):
    """Work-precision PNG: end-time error against wall time, log-log, one line per
    integrator and CG tolerance, each point labelled with its dt, and a dashed line per
    integrator's error-controlled runs, each point labelled with its tol. Needs matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=90)
    lines = {}
    for run in study.runs:
        if not run.diverged and run.error and run.wall_s:
            lines.setdefault(run.line, []).append(run)
    markers = dict(zip(INTEGRATORS, "os^vPD*X"))
    for line, members in lines.items():
        adaptive = members[0].tol is not None
        members.sort(key=lambda r: r.tol if adaptive else r.dt)
        ax.plot([r.wall_s for r in members], [r.error for r in members],
                marker=markers.get(members[0].integrator, "v"), linestyle="--" if adaptive else "-",
                markersize=4, linewidth=1.2, label=line)
        for r in members:
            label = f"tol {r.tol:.0e}" if adaptive else f"{r.dt:.2g}"
            ax.annotate(label, (r.wall_s, r.error), textcoords="offset points", xytext=(3, 3),
                        fontsize=5.5, color=ax.lines[-1].get_color())
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time of stepping (s)")
    ax.set_ylabel("RMS position error at end / scene size")
    ax.set_title(title or f"{study.scene}: work-precision, end time {study.duration:g} s (labels: dt in s, or tol)",
                 fontsize=9)
    ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    with atomic_output(path) as fh:
        fh.write(buffer.getvalue())
    return Path(path)


def new_out_dir(scene_name, base=".") -> Path:
    """A directory that does not exist yet: ``study-<scene>``, else ``study-<scene>-2``, ..."""
    base = Path(base)
    candidate = base / f"study-{scene_name}"
    k = 2
    while candidate.exists():
        candidate = base / f"study-{scene_name}-{k}"
        k += 1
    return candidate


def progress_line(run) -> str:
    step = f"dt {run.dt:<10.4g}" if run.tol is None else f"tol {run.tol:<9.0e}"
    what = f"{run.integrator:10s} {step}" + ("" if run.line == run.integrator else run.line[len(run.integrator):])
    done = run.status if run.diverged else f"{run.steps} steps in {run.wall_s:.3g} s"
    return f"  {what}: {done}"


def print_progress(run):
    print(progress_line(run), file=sys.stderr, flush=True)
