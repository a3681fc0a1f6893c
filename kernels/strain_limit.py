"""Strain limiting after a step (``massspring/passes/strain_limit/``): springs stretched past
(1 + s) times their rest length are shortened to it by moving their ends along the
spring, in the manner of Provot 1995 ("Deformation constraints in a mass-spring model
to describe rigid cloth behavior"), as Jacobi iterations that do not depend on the
order of the springs or on the thread count.

One iteration (``strain_limit_iteration``) at the state (x, v) after a step of dt:

1. each spring s = (i, j) of length l > (1 + s - tol) l0 is violated by
   e = l - (1 + s - tol) l0 (m): springs are shortened a little below the limit (tol =
   ``massspring.passes.strain_limit.TOLERANCE``), so that the iterations end with every spring
   within it (a spring of zero rest length is not limited);
2. k_i: the number of violated springs at particle i;
3. the spring's correction c = w e u / ((w_i + w_j) K), w = ``RELAX``, u = (x_j - x_i) / l,
   w_i the inverse masses (0 for a pinned particle), K = max(k_i, k_j) (one share for both
   ends, so that the pair conserves momentum);
4. x_i += w_i sum of c over its violated springs (+ at its first end, - at its second), and
   v_i += that change / dt, so that the velocity is the step's displacement over dt.

Both ends move by mass-weighted shares of the same correction along the spring, so a
model with no pins and no collider keeps its linear momentum to round-off.
With colliders, a moved particle is then projected out of any collider it entered
(``contact.project``): a particle resting on a collider slides along it. Fields:
``sl_dx`` (a vec3 per spring), ``sl_k`` (an i32 per particle), ``x_sl_before``,
``v_sl_before`` (the state a pass started from: a pass whose limit cannot be met, and
that ends with its worst spring worse than it found it, is undone).
"""

import taichi as ti

from .constraints import is_pinned
from .contact import project, project_adjoint
from .forces import spring_direction, spring_sum, tiny_length

RELAX = 1.5  # over-relaxation of the corrections: 100-150 iterations where 1.0 needs over 200 (a taut hanging cloth)


@ti.func
def inverse_mass(i, dev, cfg: ti.template()):
    out = ti.cast(0, cfg.real)
    if not is_pinned(i, dev, cfg):
        out = ti.cast(1, cfg.real) / dev.mass[i]
    return out


@ti.func
def violations(dev, cfg: ti.template(), x: ti.template(), limit, tol):
    """Steps 1-2 at positions ``x`` (a vec3 field, m): ``sl_dx`` = e u of each violated
    spring (zero for the others), ``sl_k`` the violated springs at each particle. Returns
    the largest l / l0 - 1 (f64)."""
    worst = ti.cast(-1e300, ti.f64)
    for i in range(dev.size[0]):
        dev.sl_k[i] = 0
    for s in range(dev.size[1]):
        i = dev.ends[s][0]
        j = dev.ends[s][1]
        unit, length = spring_direction(x[j] - x[i], cfg.real)
        l0 = dev.l0[s]
        dev.sl_dx[s] = ti.Vector.zero(cfg.real, 3)
        if l0 > tiny_length(cfg.real):
            ti.atomic_max(worst, ti.cast(length / l0 - 1, ti.f64))
            excess = length - (1 + limit - tol) * l0
            if excess > 0 and inverse_mass(i, dev, cfg) + inverse_mass(j, dev, cfg) > 0:
                dev.sl_dx[s] = excess * unit
                ti.atomic_add(dev.sl_k[i], 1)
                ti.atomic_add(dev.sl_k[j], 1)
    return worst


@ti.func
def shares(i, j, dev, cfg: ti.template()):
    """(w_i, w_j, d) of a violated spring (i, j): its ends' inverse masses and
    d = (w_i + w_j) K, its correction c = ``RELAX`` e u / d (step 3)."""
    wi = inverse_mass(i, dev, cfg)
    wj = inverse_mass(j, dev, cfg)
    return wi, wj, (wi + wj) * ti.cast(ti.max(dev.sl_k[i], dev.sl_k[j]), cfg.real)


@ti.func
def corrections(dev, cfg: ti.template(), go):
    """Step 3: each violated spring's ``sl_dx`` = e u becomes its correction c (if ``go``)."""
    for s in range(dev.size[1]):
        c = dev.sl_dx[s]
        if go and c.dot(c) > 0:
            _, _, divisor = shares(dev.ends[s][0], dev.ends[s][1], dev, cfg)
            dev.sl_dx[s] = ti.cast(RELAX, cfg.real) * c / divisor


@ti.func
def iteration(dev, cfg: ti.template(), state, limit, tol, dt, t, first):
    worst = violations(dev, cfg, state.x, limit, tol)
    go = worst > limit
    corrections(dev, cfg, go)
    for i in range(dev.size[0]):
        if go and first != 0:  # the state before the pass, put back if the pass cannot help (``restore``)
            dev.x_sl_before[i] = state.x[i]
            dev.v_sl_before[i] = state.v[i]
        if go and dev.sl_k[i] > 0:
            moved = inverse_mass(i, dev, cfg) * ti.cast(spring_sum(i, dev, dev.sl_dx), cfg.real)
            x = state.x[i] + moved
            if ti.static(cfg.has_colliders):
                x = project(dev, cfg, x, t, ti.static(cfg.collider_count))
            state.v[i] += (x - state.x[i]) / dt
            state.x[i] = x
    return worst


@ti.kernel
def strain_limit_iteration(dev: ti.template(), cfg: ti.template(), state: ti.template(), limit: ti.f64,
                           tol: ti.f64, dt: ti.f64, t: ti.f64, first: ti.i32) -> ti.f64:
    """One Jacobi iteration (the module's steps 1-4) on ``state`` after a step of dt (s)
    ending at time t (s), in parallel loops: springs shortened to (1 + ``limit`` -
    ``tol``) times their rest length; none if no spring is stretched past the limit
    (steps 3-4 skipped, the state left as it is). The ``first`` (1) of a pass that moves
    particles keeps the state it starts from in ``x_sl_before``, ``v_sl_before``.
    Returns the largest l / l0 - 1 of the springs at the iteration's start."""
    return iteration(dev, cfg, state, ti.cast(limit, cfg.real), ti.cast(tol, cfg.real), ti.cast(dt, cfg.real),
                     ti.cast(t, cfg.real), first)


@ti.kernel
def strain_limit_serial(dev: ti.template(), cfg: ti.template(), state: ti.template(), limit: ti.f64, tol: ti.f64,
                        dt: ti.f64, t: ti.f64, launches: ti.i32) -> ti.types.vector(3, ti.f64):
    """Up to ``launches`` iterations of ``strain_limit_iteration`` in one serial launch
    (small systems, as the integrators' serial kernels), stopping after the first that
    finds no spring past the limit. Returns (iterations run, the largest l / l0 - 1 at
    the first's start, at the last's start)."""
    s = ti.cast(limit, cfg.real)
    out = ti.Vector.zero(ti.f64, 3)
    ti.loop_config(serialize=True)
    for _ in range(1):
        k = 0
        first = ti.cast(0, ti.f64)
        worst = ti.cast(0, ti.f64)
        while k < launches:
            worst = iteration(dev, cfg, state, s, ti.cast(tol, cfg.real), ti.cast(dt, cfg.real),
                              ti.cast(t, cfg.real), ti.select(k == 0, 1, 0))
            if k == 0:
                first = worst
            k += 1
            if worst <= limit:
                break
        out = ti.Vector([ti.cast(k, ti.f64), first, worst], ti.f64)
    return out


@ti.kernel
def strain_limit_restore(dev: ti.template(), state: ti.template()):
    """``state`` as the pass found it (``x_sl_before``, ``v_sl_before``)."""
    for i in range(dev.size[0]):
        state.x[i] = dev.x_sl_before[i]
        state.v[i] = dev.v_sl_before[i]


@ti.kernel
def strain_limit_adjoint(dev: ti.template(), cfg: ti.template(), adj: ti.template(), limit: ti.f64, tol: ti.f64,
                         dt: ti.f64, t: ti.f64):
    """One iteration of ``strain_limit_iteration`` run backwards (a gradient's run, f64
    models; ``massspring/passes/strain_limit/backward.py``): at the positions it started
    from, ``adj.sl_x`` (m), with its active set as it finds it there, dL/d(x', v') of the
    state it left, in ``adj.lx``, ``adj.lv``, becomes dL/d(x, v) of the state it started
    from (``lv`` is unchanged: v' = v + (x' - x) / dt); the rest lengths' share is added to
    ``adj.gl0`` (per spring) and the masses' to ``adj.gm``.

    With c = a (l - b) u of each violated spring (a = ``RELAX`` / ((w_i + w_j) K),
    b = (1 + limit - tol) l0),
    y_i = x_i + w_i (sum of +-c), x' = P(y) (``project``): dL/dy = P^T (dL/dx' + dL/dv' / dt),
    dL/dc = w_i dL/dy_i - w_j dL/dy_j, and dL/d(x_j - x_i) = a ((1 - b / l) dL/dc +
    (b / l) (u . dL/dc) u). Uses ``sl_gy`` (dL/dy), ``sl_gd`` (dL/d(x_j - x_i)) and ``sl_gw``
    (dL/dw of either end through a); each particle gathers its springs' in a fixed order
    (no atomics: the same bits at any thread count)."""
    s_limit = ti.cast(limit, cfg.real)
    s_tol = ti.cast(tol, cfg.real)
    h = ti.cast(dt, ti.f64)
    worst = violations(dev, cfg, adj.sl_x, s_limit, s_tol)
    go = worst > limit
    corrections(dev, cfg, go)
    for i in range(dev.size[0]):
        if go and dev.sl_k[i] > 0:
            w = ti.cast(inverse_mass(i, dev, cfg), ti.f64)
            moved = spring_sum(i, dev, dev.sl_dx)
            g = adj.lx[i] + adj.lv[i] / h
            if ti.static(cfg.has_colliders):
                y = adj.sl_x[i] + ti.cast(inverse_mass(i, dev, cfg) * ti.cast(moved, cfg.real), ti.f64)
                g = project_adjoint(dev, cfg, y, ti.cast(t, cfg.real), ti.static(cfg.collider_count), g)
            adj.sl_gy[i] = g
            adj.gm[i] -= w * w * g.dot(moved)
    for s in range(dev.size[1]):
        adj.sl_gd[s] = ti.Vector.zero(ti.f64, 3)
        adj.sl_gw[s] = ti.cast(0, ti.f64)
        c = dev.sl_dx[s]
        if go and c.dot(c) > 0:
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            wi, wj, divisor = shares(i, j, dev, cfg)
            a = ti.cast(RELAX, cfg.real) / divisor
            unit, length = spring_direction(adj.sl_x[j] - adj.sl_x[i], cfg.real)
            stretch = 1 + s_limit - s_tol
            b = stretch * dev.l0[s]
            gc = wi * adj.sl_gy[i] - wj * adj.sl_gy[j]
            along = unit.dot(gc)
            adj.sl_gd[s] = a * ((1 - b / length) * gc + b / length * along * unit)
            adj.gl0[s] -= stretch * a * along
            adj.sl_gw[s] = -a / (wi + wj) * (length - b) * along  # dL/dw_i (and dL/dw_j) through a
    for i in range(dev.size[0]):
        if go and dev.sl_k[i] > 0:
            adj.lx[i] = adj.sl_gy[i] - adj.lv[i] / h - spring_sum(i, dev, adj.sl_gd)
            w = ti.cast(inverse_mass(i, dev, cfg), ti.f64)
            through = ti.cast(0, ti.f64)
            for e in range(dev.offsets[i], dev.offsets[i + 1]):  # its springs, in a fixed order
                through += adj.sl_gw[ti.select(dev.entry[e] >= 0, dev.entry[e], -1 - dev.entry[e])]
            adj.gm[i] -= w * w * through
