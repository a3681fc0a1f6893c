"""Spring, damping and gravity forces (seed Eq. 1-3) and the explicit steps (Eq. 7-8).

All kernels take their data as ``ti.types.ndarray()`` arguments, so one compiled
kernel serves every simulation of the same precision and feature set; the
feature switches (``has_damping``, ``has_gravity``, ``has_fixed``) and the float
type ``real`` are ``ti.template()`` arguments, compiled away with ``ti.static``.

Forces are gathered per particle over its CSR spring list (``offsets``, ``other``,
``spring``; see ``Model.adjacency``): each spring is visited once from each end,
with no atomics, so results are deterministic.

Array shapes (n particles, m springs): ``x, v`` (n,) of vec3 [m, m/s];
``mass`` (n,) [kg]; ``free`` (n,) int32, 1 for moving particles; ``offsets``
(n+1,) int32; ``other, spring`` (2m,) int32; ``ks`` (m,) [N/m], ``kd`` (m,)
[N s/m], ``l0`` (m,) [m].
"""

import taichi as ti

from .arrays import array_kernel
from .divergence import OK, check_code, state_sums


@ti.func
def tiny_length(real: ti.template()):
    """Lengths at or below this (m) count as zero: the spring has no direction."""
    return ti.static(1e-6 if real == ti.f32 else 1e-12)


@ti.func
def spring_direction(d, real: ti.template()):
    """Unit vector ``n = d/|d|`` and length ``l = |d|``; ``n = 0`` when ``l <= tiny``.

    The zero-length rule: a spring with no direction exerts no force and adds no
    stiffness or damping in that step (it acts again as soon as its ends part).
    """
    length = ti.sqrt(d.dot(d))  # d.norm() adds a default-precision (f64) epsilon
    n = ti.Vector.zero(real, 3)
    if length > tiny_length(real):
        n = d / length
    return n, length


@ti.func
def particle_force(i, x: ti.template(), v: ti.template(), mass: ti.template(),
                   offsets: ti.template(), other: ti.template(), spring: ti.template(),
                   ks: ti.template(), kd: ti.template(), l0: ti.template(), g,
                   has_damping: ti.template(), has_gravity: ti.template(), real: ti.template()):
    """Total force on particle ``i`` (N): Eq. 1 + Eq. 2 (if damping) + Eq. 3 (if gravity)."""
    f = ti.Vector.zero(real, 3)
    xi = x[i]
    for e in range(offsets[i], offsets[i + 1]):
        j = other[e]
        s = spring[e]
        n, length = spring_direction(x[j] - xi, real)
        f += ks[s] * (length - l0[s]) * n
        if ti.static(has_damping):
            f += kd[s] * (v[j] - v[i]).dot(n) * n
    if ti.static(has_gravity):
        f += mass[i] * ti.cast(g, real)
    return f


@ti.func
def euler_row(i, x_in: ti.template(), v_in: ti.template(), x_out: ti.template(), v_out: ti.template(),
              mass: ti.template(), free: ti.template(), offsets: ti.template(), other: ti.template(),
              spring: ti.template(), ks: ti.template(), kd: ti.template(), l0: ti.template(), g, h,
              symplectic: ti.template(), has_damping: ti.template(), has_gravity: ti.template(),
              has_fixed: ti.template(), real: ti.template()):
    """Particle i of one explicit or symplectic Euler step from (x_in, v_in) to (x_out, v_out).

    ``symplectic=False``: explicit Euler, Eq. 7-8 with the dt the seed's Eq. 8 drops:
    x' = x + dt v, v' = v + dt f(x, v) / m.
    ``symplectic=True``: semi-implicit Euler: v' = v + dt f(x, v) / m, x' = x + dt v'.
    Fixed particles keep their position and zero velocity.
    Returns particle i's ``divergence.state_sums`` of the new state (the step's check).
    """
    moving = True
    if ti.static(has_fixed):
        moving = free[i] != 0
    if moving:
        f = particle_force(i, x_in, v_in, mass, offsets, other, spring, ks, kd, l0, g,
                           has_damping, has_gravity, real)
        v_new = v_in[i] + h / mass[i] * f
        if ti.static(symplectic):
            x_out[i] = x_in[i] + h * v_new
        else:
            x_out[i] = x_in[i] + h * v_in[i]
        v_out[i] = v_new
    else:
        x_out[i] = x_in[i]
        v_out[i] = ti.Vector.zero(real, 3)
    return state_sums(x_out[i], v_out[i], mass[i], g, real)


@array_kernel
def euler_step(x_in: ti.types.ndarray(), v_in: ti.types.ndarray(),
               x_out: ti.types.ndarray(), v_out: ti.types.ndarray(),
               mass: ti.types.ndarray(), free: ti.types.ndarray(),
               offsets: ti.types.ndarray(), other: ti.types.ndarray(), spring: ti.types.ndarray(),
               ks: ti.types.ndarray(), kd: ti.types.ndarray(), l0: ti.types.ndarray(),
               g: ti.types.vector(3, ti.f64), dt: ti.f64,
               symplectic: ti.template(), has_damping: ti.template(), has_gravity: ti.template(),
               has_fixed: ti.template(), real: ti.template()) -> ti.types.vector(3, ti.f64):
    """One step from (x_in, v_in) to (x_out, v_out), a parallel loop; buffers must not alias.

    Returns the new state's ``divergence.state_sums`` summed over particles.
    """
    h = ti.cast(dt, real)
    sums = ti.Vector.zero(real, 3)
    for i in range(x_in.shape[0]):
        sums += euler_row(i, x_in, v_in, x_out, v_out, mass, free, offsets, other, spring, ks, kd, l0,
                          g, h, symplectic, has_damping, has_gravity, has_fixed, real)
    return ti.cast(sums, ti.f64)


@array_kernel
def euler_steps_serial(x_a: ti.types.ndarray(), v_a: ti.types.ndarray(),
                       x_b: ti.types.ndarray(), v_b: ti.types.ndarray(),
                       mass: ti.types.ndarray(), free: ti.types.ndarray(),
                       offsets: ti.types.ndarray(), other: ti.types.ndarray(), spring: ti.types.ndarray(),
                       ks: ti.types.ndarray(), kd: ti.types.ndarray(), l0: ti.types.ndarray(),
                       g: ti.types.vector(3, ti.f64), dt: ti.f64, steps: ti.i32,
                       check: ti.types.vector(3, ti.f64),
                       symplectic: ti.template(), has_damping: ti.template(), has_gravity: ti.template(),
                       has_fixed: ti.template(), real: ti.template()) -> ti.types.vector(3, ti.f64):
    """Up to ``steps`` steps in one launch with serial loops, alternating a -> b and b -> a.

    Each step's new state is checked (``divergence.check_code`` with ``check``); the
    loop stops at the first state that fails. Returns (good steps done k, check code,
    kinetic energy of the last state computed). The last good state is in (x_a, v_a)
    if k is even, else in (x_b, v_b); a failed state is in the other pair.
    """
    h = ti.cast(dt, real)
    n = x_a.shape[0]
    done = 0
    code = OK
    kinetic = 0.0
    ti.loop_config(serialize=True)
    for _ in range(1):
        while done < steps and code == OK:
            sums = ti.Vector.zero(real, 3)
            if done % 2 == 0:
                for i in range(n):
                    sums += euler_row(i, x_a, v_a, x_b, v_b, mass, free, offsets, other, spring, ks, kd,
                                      l0, g, h, symplectic, has_damping, has_gravity, has_fixed, real)
            else:
                for i in range(n):
                    sums += euler_row(i, x_b, v_b, x_a, v_a, mass, free, offsets, other, spring, ks, kd,
                                      l0, g, h, symplectic, has_damping, has_gravity, has_fixed, real)
            s = ti.cast(sums, ti.f64)
            kinetic = s[0]
            code = check_code(s[0], s[1], s[2], check[0], check[1], check[2])
            if code == OK:
                done += 1
    return ti.Vector([done, code, kinetic], ti.f64)
