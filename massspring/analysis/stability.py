"""Stability from the spectrum: predicted dt limits, and a ladder of runs to check them.

``spectrum`` and ``predict`` (``massspring.engine.spectrum``, imported here) estimate
the stiffest mode and the explicit integrators' limits from it.

``ladder`` runs every integrator at dts around these predictions and tabulates the
outcome (``run_case``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from massspring.analysis import cluster
from massspring.analysis.hints import hints
from massspring.support.errors import DivergenceError
from massspring.integrators import INTEGRATORS, taken
from massspring.integrators.rk4 import rk4_stable_dt
from massspring.engine.spectrum import (  # noqa: F401 - this module's names too
    Prediction, Spectrum, doubling_dt, explicit_growth, explicit_stable_dt, log_explicit_growth, predict, spectrum,
    symplectic_limit)
from massspring.model import Model


# Ladder: integrator, definiteness fix, the prediction its dt is relative to, multiples
# (each integrator's ``hints.ladder``; the symplectic one first: its limit is the reference).
LADDER = tuple((name, fix, *hints(name).ladder)
               for name in sorted(INTEGRATORS, key=lambda name: not INTEGRATORS[name].traits.limit_reference)
               if hints(name).ladder for fix in ((True, False) if hints(name).ladder_without_fix else (True,)))
COLUMNS = ("integrator", "definiteness_fix", "dt", "dt_ratio", "relative_to", "outcome", "steps",
           "simulated_time", "energy_ratio", "max_strain", "cg_iterations_mean", "cg_iterations_max",
           "cg_failures")


def energy_ratio(model: Model, positions, velocities, check) -> float:
    """(kinetic + spring energy) / (initial kinetic + spring energy + work done by the
    uniform forces, ``Model.external_work`` since the start).

    1 for an exactly conservative run, below 1 when damped, above 1 when the
    integrator added energy; NaN when the denominator is 0 (nothing to move).
    """
    e0 = model.energy(model.positions, model.velocities)
    e = model.energy(positions, velocities)
    work = model.external_work(positions) - check[1]
    available = e0["kinetic"] + e0["spring"] + work
    return (e["kinetic"] + e["spring"]) / available if available > 0 else math.nan


def max_strain(model: Model, positions) -> float:
    """max over springs with l0 > 0 of |l - l0| / l0 (0 if there are none)."""
    s = model.springs[model.rest_lengths > 0]
    if not len(s):
        return 0.0
    length = np.linalg.norm(positions[s[:, 1]] - positions[s[:, 0]], axis=1)
    l0 = model.rest_lengths[model.rest_lengths > 0]
    return float(np.max(np.abs(length - l0) / l0))


def run_case(scene, integrator, dt, definiteness_fix=True, duration=1.0, max_steps=1000, samples=20,
             **sim_kwargs) -> dict:
    """Run ``scene`` for min(ceil(duration / dt), max_steps) steps and report the outcome.

    Returns a row of ``COLUMNS`` (without dt_ratio/relative_to): outcome "stable" or
    "diverged at step k"; energy_ratio and max_strain (the largest over ``samples``
    evenly spaced checks) of the last good state.
    """
    sim = scene.simulation(integrator=integrator, dt=dt, **taken(integrator, {"definiteness_fix": definiteness_fix}),
                           **sim_kwargs)
    model = sim.model
    steps = max(1, int(math.ceil(min(duration / dt - 1e-9, int(max_steps)))))
    chunk = max(1, steps // samples)
    strain = max_strain(model, model.positions)
    outcome = "stable"
    while sim.steps < steps:
        try:
            sim.step(min(chunk, steps - sim.steps))
        except DivergenceError as exc:
            outcome = f"diverged at step {exc.step}"
            break
        finally:
            strain = max(strain, max_strain(model, sim.positions))
    its = np.array(sim.cg_iterations) if sim.cg_iterations else None
    row = {"integrator": integrator, "definiteness_fix": bool(definiteness_fix), "dt": dt,
           "outcome": outcome, "steps": sim.steps, "simulated_time": sim.time,
           "energy_ratio": energy_ratio(model, sim.positions, sim.velocities, sim.check),
           "max_strain": strain,
           "cg_iterations_mean": float(its.mean()) if its is not None else None,
           "cg_iterations_max": int(its.max()) if its is not None else None,
           "cg_failures": sim.cg_failures if INTEGRATORS[integrator].traits.linear_solver else None}
    sim.close()  # the next run of the ladder reuses its fields, already compiled
    return row


def ladder(scene, prediction: Prediction, duration=1.0, max_steps=1000, cases=LADDER, progress=None,
           client=None, **sim_kwargs) -> list:
    """Rows of ``COLUMNS``: every (integrator, fix, multiple) of ``cases`` run by ``run_case``
    at dt = multiple x the named prediction, plus the scene's own default dt for each.
    ``client``: a ``dask.distributed.Client`` to run them on (None: in this process);
    the rows are the same either way, in this order."""
    tasks, scales = [], []
    for integrator, fix, relative_to, multiples in cases:
        reference = getattr(prediction, relative_to)
        dts = [m * reference for m in multiples if math.isfinite(m * reference)]
        dts.append(scene.default_dt(integrator))
        for dt in dts:
            tasks.append((scene, integrator, dt, fix, duration, max_steps, sim_kwargs))
            scales.append((dt / reference if math.isfinite(reference) else math.nan, relative_to))
    rows = [None] * len(tasks)

    def finished(index, row):
        row["dt_ratio"], row["relative_to"] = scales[index]
        rows[index] = {key: row[key] for key in COLUMNS}
        if progress:
            progress(rows[index])

    cluster.run_tasks(_ladder_case, tasks, client=client, on_result=finished)
    return rows


def _ladder_case(scene, integrator, dt, fix, duration, max_steps, sim_kwargs):
    return run_case(scene, integrator, dt, fix, duration, max_steps, **sim_kwargs)


def prediction_lines(prediction: Prediction, scene_name) -> list:
    """The predictions as printed by ``massspring stability``."""
    p = prediction
    return [
        f"scene {scene_name}: stiffest mode of M^-1 K (Lanczos, {p.lanczos_iterations} iterations, "
        f"residual {p.lanczos_residual:.2g} 1/s^2)",
        f"  omega_max                {p.omega_max:.6g} rad/s, damping rate c = 2 zeta omega {p.damping_rate:.4g} 1/s",
        f"  symplectic stable below  dt = {p.symplectic_dt:.4g} s (2/omega_max = {p.symplectic_dt_undamped:.4g} s)",
        f"  explicit: growth/step    sqrt(1 - c dt + (omega dt)^2) (undamped sqrt(1 + (omega dt)^2)); "
        f"no growth below dt = {p.explicit_stable_dt:.4g} s",
        f"  explicit doubles energy  within 1 s at dt = {p.explicit_doubling_dt:.4g} s "
        f"(growth/step {p.explicit_growth(p.explicit_doubling_dt):.10g})",
        f"  rk4 stable below         dt = {rk4_stable_dt(p.omega_max, p.damping_rate):.4g} s (both roots of the "
        "damped stiffest mode in RK4's region)",
        "  implicit                 no limit predicted (linearised backward Euler)",
    ]


def _cell(value, digits=3):
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}g}"
    return str(value)


def format_table(rows) -> str:
    """The ladder as a text table (one line per run)."""
    head = ("integrator", "fix", "dt (s)", "dt/pred", "pred", "outcome", "steps", "time (s)", "E ratio",
            "max strain", "CG mean", "CG max", "CG fail")
    keys = ("integrator", "definiteness_fix", "dt", "dt_ratio", "relative_to", "outcome", "steps",
            "simulated_time", "energy_ratio", "max_strain", "cg_iterations_mean", "cg_iterations_max", "cg_failures")
    short = {"symplectic_dt": "sympl", "explicit_doubling_dt": "double"}
    cells = [head] + [tuple(short.get(r[k], _cell(r[k])) if k == "relative_to" else
                            _cell(r[k], 4 if k in ("dt", "dt_ratio") else 3)
                            if not (k == "definiteness_fix" and not INTEGRATORS[r["integrator"]].traits.linear_solver)
                            else "-"
                            for k in keys) for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(head))]
    return "\n".join("  ".join(c[i].ljust(widths[i]) for i in range(len(head))).rstrip() for c in cells)


def write_outputs(rows, prediction: Prediction, scene_name, prefix) -> list:
    """PREFIX.csv (the table) and PREFIX.json (predictions and table), written atomically."""
    import csv
    import io
    import json

    from massspring.io.files import atomic_output

    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
             for row in rows]
    pred = {k: (None if isinstance(v, float) and not math.isfinite(v) else float(v) if isinstance(v, float)
                else v) for k, v in asdict(prediction).items()}
    data = json.dumps({"scene": scene_name, "prediction": pred, "runs": clean}, indent=1)
    written = []
    for suffix, payload in ((".csv", text.getvalue()), (".json", data)):
        path = Path(f"{prefix}{suffix}")
        with atomic_output(path) as fh:
            fh.write(payload.encode())
        written.append(path)
    return written


def plot(rows, path, title):
    """PNG: energy ratio against dt / prediction, log-log, one line per integrator (and
    fix setting); diverged runs marked with an x. Needs matplotlib (ImportError if absent)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from massspring.io.files import atomic_output

    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=90)
    lines = {}
    for row in rows:
        if hints(row["integrator"]).ladder_without_fix:
            label = f"{row['integrator']} (fix {'on' if row['definiteness_fix'] else 'off'}) vs symplectic limit"
        else:
            label = f"{row['integrator']} vs {'symplectic limit' if row['relative_to'] == 'symplectic_dt' else 'doubling dt'}"
        if math.isfinite(row["dt_ratio"]) and math.isfinite(row["energy_ratio"]) and row["energy_ratio"] > 0:
            lines.setdefault(label, []).append(row)
    for label, members in lines.items():
        members.sort(key=lambda r: r["dt_ratio"])
        x = [r["dt_ratio"] for r in members]
        y = [r["energy_ratio"] for r in members]
        (line,) = ax.plot(x, y, marker="o", markersize=4, linewidth=1.2, label=label)
        bad = [(r["dt_ratio"], r["energy_ratio"]) for r in members if r["outcome"] != "stable"]
        if bad:
            ax.plot(*zip(*bad), linestyle="none", marker="x", markersize=10, color=line.get_color())
    ax.axvline(1.0, color="grey", linewidth=0.8, linestyle="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("dt / predicted limit")
    ax.set_ylabel("energy end / (start + external work)")
    ax.set_title(title + " (x: diverged, last good state)", fontsize=9)
    ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_output(path) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)
