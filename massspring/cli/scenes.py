"""``massspring scenes`` and ``massspring info``: the built-in scenes, and what a scene's run would be."""

from __future__ import annotations

import numpy as np

from massspring.integrators import INTEGRATORS
from massspring.model.terms import active_terms
from massspring.support.text import format_seconds
from massspring.cli.common import EXIT_OK, integrator_names, make_simulation


def cmd_scenes(args):
    from massspring.scene import builtin_scenes, load_scene

    names = sorted(builtin_scenes())
    if not args.markdown:
        for name in names:
            print(f"{name:12s} {load_scene(name).description}")
        return EXIT_OK
    print("| scene | what | particles | springs | integrator, dt, tol |\n|---|---|---|---|---|")
    for name in names:
        scene = load_scene(name)
        model = scene.model()
        print(f"| {name} | {scene.description} | {model.n_particles:,} | {model.n_springs:,} | "
              f"{scene.integrator}, {format_seconds(scene.default_dt())}{_tol_note(scene)} |")
    return EXIT_OK


def cmd_info(args):
    scene, sim = make_simulation(args)
    info = sim.info()
    print(f"scene       {scene.name}: {scene.description}")
    params = ", ".join(f"{k}={v}" for k, v in scene.params.items() if k != "mesh")
    if scene.form == "mesh":
        print(f"mesh        {scene.params['mesh']}: {params}")
    elif scene.form == "particles":
        print(f"model       hand-made ([particles] and [springs]): {params}")
    else:
        print(f"generator   {scene.generator}: {params}")
    print(f"size        {info['particles']} particles, {info['springs']} springs, "
          f"{sim.model.fixed.size} fixed" + (", moving" if sim.model.has_moving_pins else ""))
    if sim.model.has_colliders:
        print("colliders   " + "; ".join(f"{c.kind} (friction {c.friction:g}, restitution {c.restitution:g}"
                                         + (", moving" if c.moving else "") + ")" for c in sim.model.colliders))
    if sim.model.has_strain_limit:
        print(f"strain      limit {sim.model.strain_limit:g}: no spring longer than "
              f"{1 + sim.model.strain_limit:g} times its rest length after a step")
    for term in active_terms(sim.model):
        if term.parameters:
            print(f"{term.name:<11} " + ", ".join(f"{p.name} {_shown(getattr(sim.model, p.name))} {p.unit}"
                                                   for p in term.parameters))
    steps = (f"dt = {format_seconds(sim.dt)}" if sim.tol is None
             else f"tol {sim.tol:g} (error-controlled steps, the first dt = {format_seconds(sim.dt)})")
    print(f"integrator  {sim.integrator}, {steps}, precision {sim.precision}; default duration {scene.duration:g} s")
    print("dt defaults " + ", ".join(f"{k} {format_seconds(scene.default_dt(k))}" + _dt_note(scene, k)
                                     for k in integrator_names()))
    if scene.tol:
        print("tol defaults " + ", ".join(f"{k} {scene.tol[k]:g}" for k in integrator_names() if k in scene.tol)
              + " (error-controlled by default; --dt or --steps asks for fixed steps)")
    if info["options"]:
        levels = info.get("levels")
        hierarchy = f" ({len(levels)} levels: {', '.join(f'{n:,}' for n in levels)} unknowns)" if levels else ""
        print("options     " + ", ".join(f"{name} {_option_value(value)}" + (hierarchy * (name == "preconditioner"))
                                          for name, value in info["options"].items()))
    print(f"terms       {', '.join(info['terms'])}")
    print(f"arrays      {', '.join(info['arrays'])} ({info['bytes'] / 1e6:.2f} MB)")
    order = ("particles as given" if info["order"] == "given"
             else "particles renumbered in Z-order (the given order scatters the springs' accesses)")
    print(f"kernels     {info['loops']} loops, {order}")
    return EXIT_OK


def _tol_note(scene) -> str:
    """The scenes table's note of the default integrator's tol, if the scene has one."""
    tol = scene.tol.get(scene.integrator)
    return "" if tol is None else f", tol {tol:g}"


def _dt_note(scene, name) -> str:
    """What ``info`` says after an integrator's default dt: where it comes from, and a
    warning if the scene's [dt] entry is above the integrator's stability limit at this
    size (a --set resolution=... larger than the one the entry was chosen for)."""
    if name not in scene.dt:
        return " (from the stability estimate)"
    cls = INTEGRATORS[name]
    try:
        limit = cls.stability_limit(scene.prediction())
    except (ValueError, ArithmeticError):
        return ""
    if limit is None or not scene.dt[name] > limit:
        return ""
    return (f" (above its stability limit {limit:.3g} s at this size: it would diverge; "
            f"--dt {cls.suggest_dt(scene.prediction()):.3g})")


def _option_value(value) -> str:
    """A solver option's value as a scene file's [solver] table writes it."""
    if isinstance(value, bool):
        return str(value).lower()
    return f"{value:g}" if isinstance(value, float) else f"{value}"


def _shown(value) -> str:
    """A term parameter as ``info`` prints it: 0.5, or [2.0, 0.0, 0.0]."""
    return f"{value:g}" if np.ndim(value) == 0 else str(np.asarray(value).tolist())
