"""Fits of a work-precision study: measured orders and the cheapest run per target error."""

from __future__ import annotations

import numpy as np

TARGETS = (1e-2, 1e-3, 1e-4)
# Two runs whose wall times are within this fraction tie: this shared 2-core machine's
# run-to-run noise (issue 60: the same study's explicit run timed at 67 us a step in one
# run and 40.5 us in the next, which flipped its verdict against symplectic Euler's)
TIE = 0.3


def fit_orders(runs, finest=3) -> dict:
    """{line: {"integrator", "cg_tol", "newton_tol", "preconditioner", "order", "order_finest", "points"}}.

    ``order``: least-squares slope of log(error) against log(dt) over the line's
    non-diverged runs (fixed-dt lines only) with a positive error (None with fewer than 2 dt values);
    ``order_finest``: the same over its ``finest`` smallest dts only (the asymptotic
    order, free of runs near the stability limit).
    """
    lines = {}
    for run in runs:
        if run.tol is None:  # an error-controlled line has no dt ladder to fit
            lines.setdefault(run.line, []).append(run)
    out = {}
    for line, members in lines.items():
        good = sorted((r for r in members if not r.diverged and r.error is not None and r.error > 0),
                      key=lambda r: r.dt)
        out[line] = {"integrator": members[0].integrator, "cg_tol": members[0].cg_tol,
                     "newton_tol": members[0].newton_tol,
                     "preconditioner": members[0].preconditioner,
                     "order": slope(good), "order_finest": slope(good[:finest]), "points": len(good)}
    return out


def slope(runs):
    if len({r.dt for r in runs}) < 2:
        return None
    return float(np.polyfit(np.log([r.dt for r in runs]), np.log([r.error for r in runs]), 1)[0])


def integrator_orders(orders) -> dict:
    """One order per integrator: for the implicit ones, the line with the tightest tolerance."""
    out = {}
    for entry in orders.values():
        name = entry["integrator"]
        best = out.get(name)
        tol = entry.get("newton_tol") or entry["cg_tol"]
        if best is None or (tol is not None and tol < (best.get("newton_tol") or best["cg_tol"])):
            out[name] = entry
    return {name: entry["order"] for name, entry in out.items()}


def cheapest(runs, target) -> dict | None:
    """The non-diverged run with the least wall time whose end-time error is <= target,
    and in "ties" the cheapest such run of each other line within ``TIE`` of its time
    (cheapest first): a verdict between those is the timing noise's, not theirs."""
    good = [r for r in runs if not r.diverged and r.error is not None and r.error <= target
            and r.wall_s is not None]
    if not good:
        return None
    best = min(good, key=lambda r: r.wall_s)
    per_line = {}
    for r in sorted(good, key=lambda r: r.wall_s):
        per_line.setdefault(r.line, r)
    ties = [_choice(r) for line, r in per_line.items()
            if line != best.line and r.wall_s <= (1.0 + TIE) * best.wall_s]
    return {**_choice(best), "ties": ties}


def _choice(run) -> dict:
    return {"integrator": run.integrator, "dt": run.dt, "tol": run.tol, "cg_tol": run.cg_tol,
            "newton_tol": run.newton_tol, "preconditioner": run.preconditioner, "error": run.error,
            "wall_s": run.wall_s}
