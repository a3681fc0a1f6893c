"""Preconditioned conjugate gradient for Eq. 15, as Taichi kernels.

The solve runs on the free particles only: fixed particles are removed from the
system by keeping every CG vector zero there (no penalty springs). The operator
is applied spring by spring (``operator.apply_row``); no matrix is formed.

The per-particle work of each CG phase is a ``ti.func`` (``*_row``), used by two
drivers that run the same algorithm:

* parallel: one kernel per phase, each a parallel loop fused with the reductions
  the next phase needs (``cg_begin``, ``cg_apply``, ``cg_update``,
  ``cg_direction``), driven from Python (``massspring.integrators``). Three
  launches per iteration; for large systems.
* serial: ``cg_solve_serial`` runs the whole solve in one launch with serial
  loops; for small systems, where a parallel loop's launch costs more than its
  work.

Phases: ``begin`` computes r = b - A x of the iterate x and restarts the search
direction (p = z = P r); it starts the solve from the warm start x = v_n (as the
seed says) and gives the true residual at exit, which is checked instead of the
recursively updated one. ``apply``: q = A p, p.q. ``update``: x += alpha p,
r -= alpha q, z = P r. ``direction``: p = z + beta p.

Shapes: ``x, b, r, z, p, q`` (n,) of vec3 (velocities in m/s, b in kg m/s);
``minv`` (n,) of 3x3; see ``operator`` for ``coef`` and ``forces`` for the rest.
"""

import taichi as ti

from .arrays import array_kernel
from .divergence import OK, check_code, is_finite, state_sums
from .forces import particle_force
from .operator import apply_row, diagonal_block

CONVERGED, MAX_ITER, INDEFINITE, STALLED, NONFINITE = 0, 1, 2, 3, 4
REASONS = ("converged", "max_iter", "indefinite", "stalled", "non-finite")


@ti.func
def begin_row(i, x: ti.template(), b: ti.template(), r: ti.template(), z: ti.template(),
              p: ti.template(), minv: ti.template(), pos: ti.template(), mass: ti.template(),
              free: ti.template(), offsets: ti.template(), other: ti.template(),
              spring: ti.template(), ks: ti.template(), l0: ti.template(), coef: ti.template(),
              g, h, with_rhs: ti.template(), precondition: ti.template(),
              has_gravity: ti.template(), has_fixed: ti.template(), real: ti.template()):
    """Row i of r = b - A x, z = P r, p = z; returns (r_i.z_i, r_i.r_i, b_i.b_i).

    ``with_rhs``: also form b_i, the right-hand side of Eq. 15, and the inverse
    diagonal block. M v + dt f - dt D v is computed as M v + dt (f_spring + f_gravity):
    the damping force of Eq. 2 is exactly D v, so it cancels against -dt D v.
    """
    out = ti.Vector.zero(real, 3)
    moving = True
    if ti.static(has_fixed):
        moving = free[i] != 0
    if moving:
        if ti.static(with_rhs):
            f = particle_force(i, pos, x, mass, offsets, other, spring, ks, ks, l0, g,
                               False, has_gravity, real)
            b[i] = mass[i] * x[i] + h * f
            if ti.static(precondition):
                minv[i] = ti.cast(diagonal_block(i, mass, offsets, coef, real).inverse(), real)
        ri = b[i] - apply_row(i, x, mass, offsets, other, coef, real)
        zi = ri
        if ti.static(precondition):
            zi = minv[i] @ ri
        r[i] = ri
        z[i] = zi
        p[i] = zi
        out = ti.Vector([ri.dot(zi), ri.dot(ri), b[i].dot(b[i])], real)
    else:
        zero = ti.Vector.zero(real, 3)
        x[i] = zero
        r[i] = zero
        z[i] = zero
        p[i] = zero
        if ti.static(with_rhs):
            b[i] = zero
    return out


@ti.func
def apply_q_row(i, p: ti.template(), q: ti.template(), mass: ti.template(), free: ti.template(),
                offsets: ti.template(), other: ti.template(), coef: ti.template(),
                has_fixed: ti.template(), real: ti.template()):
    """Row i of q = A p (0 at fixed particles); returns p_i.q_i."""
    qi = apply_row(i, p, mass, offsets, other, coef, real)
    if ti.static(has_fixed):
        if free[i] == 0:
            qi = ti.Vector.zero(real, 3)
    q[i] = qi
    return p[i].dot(qi)


@ti.func
def update_row(i, a, x: ti.template(), r: ti.template(), z: ti.template(), p: ti.template(),
               q: ti.template(), minv: ti.template(), precondition: ti.template(),
               real: ti.template()):
    """Row i of x += a p, r -= a q, z = P r; returns (r_i.z_i, r_i.r_i)."""
    x[i] += a * p[i]
    ri = r[i] - a * q[i]
    zi = ri
    if ti.static(precondition):
        zi = minv[i] @ ri
    r[i] = ri
    z[i] = zi
    return ti.Vector([ri.dot(zi), ri.dot(ri)], real)


@array_kernel
def cg_begin(x: ti.types.ndarray(), b: ti.types.ndarray(),
             r: ti.types.ndarray(), z: ti.types.ndarray(), p: ti.types.ndarray(),
             minv: ti.types.ndarray(), pos: ti.types.ndarray(),
             mass: ti.types.ndarray(), free: ti.types.ndarray(),
             offsets: ti.types.ndarray(), other: ti.types.ndarray(), spring: ti.types.ndarray(),
             ks: ti.types.ndarray(), l0: ti.types.ndarray(), coef: ti.types.ndarray(),
             g: ti.types.vector(3, ti.f64), dt: ti.f64,
             with_rhs: ti.template(), precondition: ti.template(), has_gravity: ti.template(),
             has_fixed: ti.template(), real: ti.template()) -> ti.types.vector(3, ti.f64):
    """Parallel ``begin``: r = b - A x, z = P r, p = z; returns (r.z, r.r, b.b).

    With ``with_rhs``, x must hold v_n: b and ``minv`` are formed from it first.
    """
    h = ti.cast(dt, real)
    sums = ti.Vector.zero(real, 3)
    for i in range(x.shape[0]):
        sums += begin_row(i, x, b, r, z, p, minv, pos, mass, free, offsets, other, spring, ks, l0,
                          coef, g, h, with_rhs, precondition, has_gravity, has_fixed, real)
    return ti.cast(sums, ti.f64)


@array_kernel
def cg_apply(p: ti.types.ndarray(), q: ti.types.ndarray(), mass: ti.types.ndarray(),
             free: ti.types.ndarray(), offsets: ti.types.ndarray(), other: ti.types.ndarray(),
             coef: ti.types.ndarray(), has_fixed: ti.template(), real: ti.template()) -> ti.f64:
    """Parallel ``apply``: q = A p on the free particles (0 on fixed ones); returns p.q."""
    pq = ti.cast(0, real)
    for i in range(p.shape[0]):
        pq += apply_q_row(i, p, q, mass, free, offsets, other, coef, has_fixed, real)
    return pq


@array_kernel
def cg_update(alpha: ti.f64, x: ti.types.ndarray(), r: ti.types.ndarray(), z: ti.types.ndarray(),
              p: ti.types.ndarray(), q: ti.types.ndarray(), minv: ti.types.ndarray(),
              precondition: ti.template(), real: ti.template()) -> ti.types.vector(2, ti.f64):
    """Parallel ``update``: x += alpha p, r -= alpha q, z = P r; returns (r.z, r.r)."""
    a = ti.cast(alpha, real)
    sums = ti.Vector.zero(real, 2)
    for i in range(x.shape[0]):
        sums += update_row(i, a, x, r, z, p, q, minv, precondition, real)
    return ti.cast(sums, ti.f64)


@array_kernel
def cg_direction(beta: ti.f64, z: ti.types.ndarray(), p: ti.types.ndarray(), real: ti.template()):
    """Parallel ``direction``: p = z + beta p."""
    bt = ti.cast(beta, real)
    for i in range(p.shape[0]):
        p[i] = z[i] + bt * p[i]


def exit_rule(finite, iterations, cycle, residual, tol, best, reason, max_iter):
    """The exit rule after each CG cycle, shared by both drivers: returns (done, reason, best).

    Plain Python that is also valid Taichi code: ``next_action`` is its ``ti.func``.

    ``residual`` is the true relative residual, ``finite`` whether it is finite
    (tested by the caller: ``is_finite`` in kernels), ``cycle`` the iterations of the
    cycle just ended. Stop on a non-finite residual (reason "non-finite"); converged if
    <= tol; else stop on a breakdown (p.Ap <= 0), on the iteration limit, after a
    cycle that could not iterate, or when a restart from the true residual no
    longer halves it (stalled); else restart. Every restart follows a cycle of at
    least one iteration, so the iterations bound the loop.
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


@array_kernel
def cg_solve_serial(x: ti.types.ndarray(), b: ti.types.ndarray(),
                    r: ti.types.ndarray(), z: ti.types.ndarray(), p: ti.types.ndarray(),
                    q: ti.types.ndarray(), minv: ti.types.ndarray(), pos: ti.types.ndarray(),
                    mass: ti.types.ndarray(), free: ti.types.ndarray(),
                    offsets: ti.types.ndarray(), other: ti.types.ndarray(), spring: ti.types.ndarray(),
                    ks: ti.types.ndarray(), l0: ti.types.ndarray(), coef: ti.types.ndarray(),
                    g: ti.types.vector(3, ti.f64), dt: ti.f64, tol: ti.f64, max_iter: ti.i32,
                    precondition: ti.template(), has_gravity: ti.template(),
                    has_fixed: ti.template(), real: ti.template()) -> ti.types.vector(3, ti.f64):
    """The whole PCG solve of A x = b from x = v_n in one launch, serial loops.

    Returns (iterations, true relative residual, reason code; see ``REASONS``).
    """
    n = x.shape[0]
    h = ti.cast(dt, real)
    iterations = 0
    reason = CONVERGED
    residual = 0.0
    ti.loop_config(serialize=True)
    for _ in range(1):
        sums = ti.Vector.zero(real, 3)
        for i in range(n):
            sums += begin_row(i, x, b, r, z, p, minv, pos, mass, free, offsets, other, spring, ks, l0,
                              coef, g, h, True, precondition, has_gravity, has_fixed, real)
        rz = ti.cast(sums[0], ti.f64)
        rr = ti.cast(sums[1], ti.f64)
        bb = ti.cast(sums[2], ti.f64)
        if not is_finite(bb):
            reason = NONFINITE
            residual = bb
        elif bb == 0.0:
            for i in range(n):
                x[i] = ti.Vector.zero(real, 3)
        else:
            target = tol * tol * bb
            best = 1e308
            done = False
            while not done:
                cycle = 0
                while rr > target and iterations < max_iter:
                    pq = ti.cast(0, real)
                    for i in range(n):
                        pq += apply_q_row(i, p, q, mass, free, offsets, other, coef, has_fixed, real)
                    if not is_finite(pq) or pq <= 0 or rz == 0.0:
                        reason = INDEFINITE
                        break
                    a = ti.cast(rz / ti.cast(pq, ti.f64), real)
                    s2 = ti.Vector.zero(real, 2)
                    for i in range(n):
                        s2 += update_row(i, a, x, r, z, p, q, minv, precondition, real)
                    iterations += 1
                    cycle += 1
                    rz_new = ti.cast(s2[0], ti.f64)
                    rr = ti.cast(s2[1], ti.f64)
                    bt = ti.cast(rz_new / rz, real)
                    for i in range(n):
                        p[i] = z[i] + bt * p[i]
                    rz = rz_new
                if cycle > 0:
                    sums = ti.Vector.zero(real, 3)
                    for i in range(n):
                        sums += begin_row(i, x, b, r, z, p, minv, pos, mass, free, offsets, other,
                                          spring, ks, l0, coef, g, h, False, precondition,
                                          has_gravity, has_fixed, real)
                    rz = ti.cast(sums[0], ti.f64)
                    rr = ti.cast(sums[1], ti.f64)
                residual = ti.sqrt(ti.max(rr, 0.0) / bb)
                done, reason, best = next_action(is_finite(residual), iterations, cycle, residual, tol, best,
                                                 reason, max_iter)
    return ti.Vector([iterations, residual, reason], ti.f64)


@array_kernel
def advance_positions(pos: ti.types.ndarray(), v: ti.types.ndarray(), keep: ti.types.ndarray(),
                      mass: ti.types.ndarray(), g: ti.types.vector(3, ti.f64), dt: ti.f64,
                      check: ti.types.vector(3, ti.f64), serial: ti.template(),
                      real: ti.template()) -> ti.types.vector(2, ti.f64):
    """x_{n+1} = x_n + dt v_{n+1} (seed Eq. 9), committed only if the new state passes the check.

    The first loop reduces ``divergence.state_sums`` of (x_n + dt v_{n+1}, v_{n+1})
    without storing anything; if ``divergence.check_code`` accepts it, the second
    loop stores x_{n+1} and copies v_{n+1} into ``keep``, so ``keep`` always holds
    the velocity of the last accepted state. If the check fails, x_n is untouched
    and the caller restores v_n from ``keep``. ``serial`` serialises both loops
    (small systems, where a parallel loop's launch costs more than its work).
    Returns (check code, kinetic energy of the new state).
    """
    h = ti.cast(dt, real)
    sums = ti.Vector.zero(real, 3)
    ti.loop_config(serialize=serial)
    for i in range(pos.shape[0]):
        sums += state_sums(pos[i] + h * v[i], v[i], mass[i], g, real)
    s = ti.cast(sums, ti.f64)
    code = check_code(s[0], s[1], s[2], check[0], check[1], check[2])
    ti.loop_config(serialize=serial)
    for i in range(pos.shape[0]):
        if code == OK:
            pos[i] += h * v[i]
            keep[i] = v[i]
    return ti.Vector([code, s[0]], ti.f64)
