"""Preconditioned conjugate gradient for Eq. 15, as Taichi kernels.

The solve runs on the unconstrained directions only (``constraints``): the iterate
holds the prescribed velocity in the constrained directions (pins, contact normals),
and every CG vector is filtered (zero there), so no penalty springs are needed. The
tolerance is relative to the first residual ||S (b - A v_n)|| of the warm start: the
right-hand side of Eq. 15's velocity-change form, h S (f + h K v_n) without contacts,
so a step is solved to the tolerance relative to the change it makes, however fast
the cloth already moves; a residual at the round-off of b (``floor`` ||S b||) counts
as solved. The operator is applied spring by
spring (``operator.apply_row``); no matrix is formed.

Each CG phase is a ``ti.func`` with its loops at its top level, reducing in fixed
blocks (``blocks``), so that two drivers run the same arithmetic:

* parallel (``massspring.solvers.cg``): one kernel per phase, each a parallel loop
  fused with the reductions the next phase needs: ``cg_begin``, ``cg_apply``,
  ``cg_update``, ``cg_direction``. For large systems, and for preconditioners
  that run kernels of their own (``cfg.precond is None``: the driver applies
  them between ``cg_update`` and ``cg_direction``).
* serial: ``cg_solve`` runs ``operator.refresh`` and the whole solve in one launch
  with serial loops, for pointwise preconditioners; for small systems, where a
  parallel loop's launch costs more than its work.

Phases: ``begin`` computes r = b - A x of the iterate x and restarts the search
direction (p = z = P r); it starts the solve from the warm start x = v_n (as the
seed says) and gives the true residual at exit, which is checked instead of the
recursively updated one. ``apply``: q = A p, p.q. ``update``: x += alpha p,
r -= alpha q, z = P r. ``direction``: p = z + beta p.

A pointwise preconditioner (``cfg.precond``) is a class of ``ti.func``s:
``setup_row(i, dev, cfg, A_ii)`` (called by ``operator.refresh`` when its
``needs_diagonal``) and ``apply_row(i, dev, cfg, r_i) -> z_i``.

Shapes: ``dev.v`` (the iterate), ``b, r, z, p, q`` (n,) vec3 (velocities in m/s,
b in kg m/s); see ``operator`` for the coefficients.
"""

import taichi as ti

from .blocks import BLOCK, block_count, block_end, ordered_sum
from .divergence import OK, is_finite, state_sums, verdict
from .constraints import constrain, is_free, is_pinned, prescribed
from .contact import landing, project
from .operator import REFRESHED, apply_row, refresh
from .terms import uniform_acceleration

CONVERGED, MAX_ITER, INDEFINITE, STALLED, NONFINITE = 0, 1, 2, 3, 4
REASONS = ("converged", "max_iter", "indefinite", "stalled", "non-finite")


@ti.func
def precondition(i, dev, cfg: ti.template(), r):
    if ti.static(cfg.pointwise):
        return cfg.precond.apply_row(i, dev, cfg, r)
    else:
        return r


@ti.func
def begin(dev, cfg: ti.template()):
    """r = S (b - A x), z = S P r, p = z, with the iterate x = ``dev.v`` set to the
    prescribed velocity in constrained directions first; returns (r.z, r.r, b.b) over
    the free directions. Without a pointwise preconditioner z and p are left to the
    driver (r.z is then 0)."""
    n = dev.size[0]
    for i in range(n):
        if not is_free(i, dev, cfg):
            dev.v[i] = constrain(i, dev, cfg, dev.v[i]) + prescribed(i, dev, cfg)
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            ri = constrain(i, dev, cfg, dev.b[i] - apply_row(i, dev, cfg, dev.v))
            dev.r[i] = ri
            bi = ti.cast(constrain(i, dev, cfg, dev.b[i]), ti.f64)
            r64 = ti.cast(ri, ti.f64)
            rz = 0.0
            if ti.static(cfg.pointwise):
                zi = constrain(i, dev, cfg, precondition(i, dev, cfg, ri))
                dev.z[i] = zi
                dev.p[i] = zi
                rz = r64.dot(ti.cast(zi, ti.f64))
            acc += ti.Vector([rz, r64.dot(r64), bi.dot(bi)], ti.f64)
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.func
def apply(dev, cfg: ti.template()):
    """q = S A p (p is filtered already); returns p.q."""
    n = dev.size[0]
    for blk in range(block_count(n)):
        acc = 0.0
        for i in range(blk * BLOCK, block_end(blk, n)):
            qi = constrain(i, dev, cfg, apply_row(i, dev, cfg, dev.p))
            dev.q[i] = qi
            acc += ti.cast(dev.p[i], ti.f64).dot(ti.cast(qi, ti.f64))
        dev.partial[blk] = ti.Vector([acc, 0.0, 0.0], ti.f64)
    return ordered_sum(dev.partial, block_count(n))[0]


@ti.func
def update(dev, cfg: ti.template(), alpha):
    """x += alpha p, r -= alpha q, z = S P r (pointwise preconditioners); returns (r.z, r.r)."""
    a = ti.cast(alpha, cfg.real)
    n = dev.size[0]
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            dev.v[i] += a * dev.p[i]
            ri = dev.r[i] - a * dev.q[i]
            dev.r[i] = ri
            r64 = ti.cast(ri, ti.f64)
            rz = 0.0
            if ti.static(cfg.pointwise):
                zi = constrain(i, dev, cfg, precondition(i, dev, cfg, ri))
                dev.z[i] = zi
                rz = r64.dot(ti.cast(zi, ti.f64))
            acc += ti.Vector([rz, r64.dot(r64), 0.0], ti.f64)
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.func
def direction(dev, cfg: ti.template(), beta):
    """p = z + beta p."""
    bt = ti.cast(beta, cfg.real)
    for i in range(dev.size[0]):
        dev.p[i] = dev.z[i] + bt * dev.p[i]


def exit_rule(finite, iterations, cycle, residual, tol, best, reason, max_iter):
    """The exit rule after each CG cycle, shared by both drivers: returns (done, reason, best).

    Plain Python that is also valid Taichi code: ``next_action`` is its ``ti.func``.

    ``residual`` is the true relative residual, ``finite`` whether it is finite
    (tested by the caller: ``is_finite`` in kernels), ``cycle`` the iterations of the
    cycle just ended. Stop on a non-finite residual (reason "non-finite"); converged
    if <= tol; else stop on a breakdown (p.Ap <= 0), on the iteration limit, after a
    cycle that could not iterate, or when a restart from the true residual no longer
    halves it (stalled); else restart. Every restart follows a cycle of at least one
    iteration, so the iteration limit bounds the loop.
    """
    done = True
    new_reason = reason
    new_best = best
    if not finite:
        new_reason = NONFINITE
    elif residual <= tol:
        new_reason = CONVERGED
    elif reason != CONVERGED:
        pass
    elif iterations >= max_iter:
        new_reason = MAX_ITER
    elif cycle == 0 or residual > 0.5 * best:
        new_reason = STALLED
    else:
        done = False
        new_best = residual
    return done, new_reason, new_best


next_action = ti.func(exit_rule)


@ti.kernel
def cg_precondition(dev: ti.template(), cfg: ti.template()):
    """z = S P S r with a pointwise preconditioner (for ``massspring.engine.operators``)."""
    for i in range(dev.size[0]):
        dev.z[i] = constrain(i, dev, cfg, precondition(i, dev, cfg, constrain(i, dev, cfg, dev.r[i])))


@ti.kernel
def precondition_vectors(dev: ti.template(), cfg: ti.template(), r: ti.types.ndarray(dtype=ti.f64, ndim=2),
                         out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    """out = S P S r for r (n, 3) with a pointwise preconditioner, host arrays in and out
    (``integrators/newton.py``'s MINRES)."""
    for i in range(dev.size[0]):
        ri = ti.Vector([ti.cast(r[i, c], cfg.real) for c in ti.static(range(3))])
        zi = constrain(i, dev, cfg, precondition(i, dev, cfg, constrain(i, dev, cfg, ri)))
        for c in ti.static(range(3)):
            out[i, c] = ti.cast(zi[c], ti.f64)


@ti.kernel
def cg_refresh(dev: ti.template(), cfg: ti.template(), x: ti.template(), dt: ti.f64, t: ti.f64,
               mode: ti.template()):
    """``operator.refresh`` at the state (``x``, ``dev.v``) at time t (s), in ``mode``
    (``operator.LINEARISED``): parallel loops."""
    refresh(dev, cfg, x, dev.v, ti.cast(dt, cfg.real), ti.cast(t, cfg.real), mode)


@ti.kernel
def cg_begin(dev: ti.template(), cfg: ti.template()) -> ti.types.vector(3, ti.f64):
    """Parallel ``begin``: returns (r.z, r.r, b.b)."""
    return begin(dev, cfg)


@ti.kernel
def cg_apply(dev: ti.template(), cfg: ti.template()) -> ti.f64:
    """Parallel ``apply``: returns p.q."""
    return apply(dev, cfg)


@ti.kernel
def cg_update(dev: ti.template(), cfg: ti.template(), alpha: ti.f64) -> ti.types.vector(2, ti.f64):
    """Parallel ``update``: returns (r.z, r.r)."""
    sums = update(dev, cfg, alpha)
    return ti.Vector([sums[0], sums[1]], ti.f64)


@ti.kernel
def cg_direction(dev: ti.template(), cfg: ti.template(), beta: ti.f64):
    """Parallel ``direction``: p = z + beta p."""
    direction(dev, cfg, beta)


@ti.func
def serial_solve(dev, cfg: ti.template(), tol, floor, max_iter):
    """The whole PCG solve of A v = b from the iterate in ``dev.v`` with the operator as
    refreshed, inside a serialised loop: the loop of ``massspring.solvers.cg`` (``tol``
    and ``floor`` as there), written with ``begin`` once (the first residual and every
    restart share it: half the code to compile). Returns (iterations, true relative
    residual, reason code (see ``REASONS``), first residual)."""
    iterations = 0
    reason = CONVERGED
    residual = 0.0
    first = 0.0
    goal = tol
    bb = 0.0
    target = 0.0
    best = 1e308
    cycle = -1  # iterations of the cycle just ended; -1 before the first
    done = False
    while not done:
        sums = begin(dev, cfg)  # r = b - A v: the start, or the true residual after a cycle
        rz = sums[0]
        rr = sums[1]
        if cycle < 0:
            bb = rr  # the tolerance is relative to the first residual
            first = ti.sqrt(ti.max(bb, 0.0))
            if bb > 0.0:
                goal = ti.max(tol, floor * ti.sqrt(ti.max(sums[2], 0.0) / bb))
            target = goal * goal * bb
            if not is_finite(bb) or not is_finite(sums[2]):  # b or the residual overflowed
                reason = NONFINITE
                residual = bb
                done = True
            elif bb == 0.0:  # the iterate solves the system exactly
                done = True
        else:
            residual = ti.sqrt(ti.max(rr, 0.0) / bb)
            done, reason, best = next_action(is_finite(residual), iterations, cycle, residual, goal, best,
                                             reason, max_iter)
        if not done:
            cycle = 0
            while rr > target and iterations < max_iter:
                pq = apply(dev, cfg)
                if not is_finite(pq) or pq <= 0.0 or rz == 0.0:
                    reason = INDEFINITE
                    break
                s2 = update(dev, cfg, rz / pq)
                iterations += 1
                cycle += 1
                direction(dev, cfg, s2[0] / rz)
                rz = s2[0]
                rr = s2[1]
            if cycle == 0:  # nothing to restart from: decide on the residual at hand
                residual = ti.sqrt(ti.max(rr, 0.0) / bb)
                done, reason, best = next_action(is_finite(residual), iterations, cycle, residual, goal,
                                                 best, reason, max_iter)
    return ti.Vector([iterations, residual, reason, first], ti.f64)


@ti.kernel
def cg_solve(dev: ti.template(), cfg: ti.template(), x: ti.template(), dt: ti.f64, t: ti.f64, tol: ti.f64,
             floor: ti.f64, max_iter: ti.i32, mode: ti.template()) -> ti.types.vector(4, ti.f64):
    """``refresh`` at (``x``, ``dev.v``) at time t (s) in ``mode`` (none if ``mode`` is
    ``operator.REFRESHED``: the caller refreshed the operator itself) and ``serial_solve``
    from the iterate in ``dev.v`` (v_n) in one launch, serial loops."""
    out = ti.Vector.zero(ti.f64, 4)
    ti.loop_config(serialize=True)
    for _ in range(1):
        if ti.static(mode != REFRESHED):
            refresh(dev, cfg, x, dev.v, ti.cast(dt, cfg.real), ti.cast(t, cfg.real), mode)
        out = serial_solve(dev, cfg, tol, floor, max_iter)
    return out


@ti.func
def next_position(i, dev, cfg: ti.template(), xb: ti.template(), h, dt, t):
    """x^ + h v_{n+1} of particle i at the step's end time t (seed Eq. 9: x^ = x_n, h = dt;
    BDF2: its base and 2 dt / 3); with colliders, less the landing correction of a
    particle in contact (``contact.landing``, from x_n at t - dt), and moved onto the
    surface of any collider it would end inside (``contact.project``)."""
    x = xb[i] + h * dev.v[i]
    if ti.static(cfg.has_colliders):
        if not is_pinned(i, dev, cfg):
            back = landing(i, dev, cfg, dev.x[i], t - dt)
            moved = project(dev, cfg, x - back, t, ti.static(cfg.collider_count))
            x = moved
    return x


@ti.func
def advance_sums(dev, cfg: ti.template(), xb: ti.template(), h, dt, t, springs: ti.template()):
    """Summed ``state_sums`` of the candidate state (``next_position``, kept in ``dev.q``;
    v); with ``springs``, its springs' potential energy (``SpringTerm.potential``) added
    to the kinetic energy: a Newton-solved step can converge to springs stretched far
    beyond anything the motion gave them while the velocities stay small."""
    n = dev.size[0]
    g = uniform_acceleration(dev, cfg)
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            x = next_position(i, dev, cfg, xb, h, dt, t)
            dev.q[i] = x
            acc += state_sums(x, dev.v[i], dev.mass[i], g, cfg.has_uniform)
        dev.partial[blk] = acc
    sums = ordered_sum(dev.partial, block_count(n))
    if ti.static(springs and cfg.has_springs):
        sums[0] += spring_energy(dev, cfg, dev.q)
    return sums


@ti.func
def spring_energy(dev, cfg: ti.template(), x: ti.template()):
    """The springs' potential energy (J, float64) at the positions ``x``, each spring
    counted once at its first end, summed in fixed blocks of particles."""
    n = dev.size[0]
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            for e in range(dev.offsets[i], dev.offsets[i + 1]):
                s = dev.entry[e]
                if s >= 0:
                    length = (x[dev.other[e]] - x[i]).norm()
                    for term in ti.static(cfg.spring_terms):
                        acc[0] += ti.cast(term.potential(s, dev, length), ti.f64)
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))[0]


@ti.func
def commit(dev, cfg: ti.template(), xb: ti.template(), h, dt, t, carry: ti.template(), springs: ti.template()):
    """Check the candidate state (``next_position``, v); if it passes, store it (see
    ``advance_positions``). Returns its ``divergence.verdict`` (code, kinetic (+ spring)
    J, bound J)."""
    sums = advance_sums(dev, cfg, xb, h, dt, t, springs)
    result = verdict(sums, dev.check[None])
    code = ti.cast(result[0], ti.i32)
    for i in range(dev.size[0]):
        if code == OK:
            if ti.static(carry):
                dev.xo[i] = dev.x[i]
                dev.vo[i] = dev.keep[i]
            dev.x[i] = dev.q[i]
            dev.keep[i] = dev.v[i]
    return result


@ti.kernel
def advance_positions(dev: ti.template(), cfg: ti.template(), xb: ti.template(), h: ti.f64, dt: ti.f64,
                      t: ti.f64, serial: ti.template(), carry: ti.template(),
                      springs: ti.template()) -> ti.types.vector(3, ti.f64):
    """x_{n+1} = x^ + h v_{n+1} (seed Eq. 9: ``xb`` = ``dev.x``, h = dt) at the step's end
    time t (s), committed only if the new state passes the check.

    The first loops reduce ``divergence.state_sums`` of (x_{n+1}, v_{n+1}), holding
    x_{n+1} in ``dev.q`` (with ``springs``, the Newton-solved steps', the springs'
    potential energy counted with the kinetic);
    if ``divergence.verdict`` accepts it, the last loop stores
    x_{n+1} and copies v_{n+1} into ``dev.keep``, so ``keep`` always holds the
    velocity of the last accepted state (with ``carry``, the state it replaces goes
    to ``dev.xo``, ``dev.vo``: BDF2's previous step). If the check fails, x_n is
    untouched and the caller restores v_n from ``keep``. ``serial`` serialises the
    loops. Returns the new state's ``divergence.verdict`` (code, kinetic + spring J, bound J).
    """
    hh = ti.cast(h, cfg.real)
    step = ti.cast(dt, cfg.real)
    end = ti.cast(t, cfg.real)
    out = ti.Vector.zero(ti.f64, 3)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            out = commit(dev, cfg, xb, hh, step, end, carry, springs)
    else:
        out = commit(dev, cfg, xb, hh, step, end, carry, springs)
    return out
