"""Classical fourth-order Runge-Kutta steps of Eq. 4, for reference solutions.

Eq. 4 is the first-order system y' = F(y) with y = (x, v) and F(x, v) = (v, M^-1 f(x, v)),
f the total force of Eq. 1-3 (``forces.particle_force``); fixed particles have
F = 0. One RK4 step of size h:

    k1 = F(y), k2 = F(y + h/2 k1), k3 = F(y + h/2 k2), k4 = F(y + h k3),
    y <- y + h/6 (k1 + 2 k2 + 2 k3 + k4).

``rk4_steps`` runs many steps in one launch with serial loops (a launch with a
dozen ndarray arguments costs about 0.2 ms here, more than a chain's whole step).
Only float64 is meant: the reference must be far more accurate than the runs it
judges.

Shapes: ``x, v, xt, vt, kv, sx, sv`` (n,) of vec3; the rest as in ``forces``.
"""

import taichi as ti

from .forces import particle_force


@ti.kernel
def rk4_steps(x: ti.types.ndarray(), v: ti.types.ndarray(), xt: ti.types.ndarray(), vt: ti.types.ndarray(),
              kv: ti.types.ndarray(), sx: ti.types.ndarray(), sv: ti.types.ndarray(),
              mass: ti.types.ndarray(), free: ti.types.ndarray(), offsets: ti.types.ndarray(),
              other: ti.types.ndarray(), spring: ti.types.ndarray(), ks: ti.types.ndarray(),
              kd: ti.types.ndarray(), l0: ti.types.ndarray(), g: ti.types.vector(3, ti.f64),
              dt: ti.f64, steps: ti.i32, has_damping: ti.template(), has_gravity: ti.template(),
              has_fixed: ti.template()):
    """Advance (x, v) by ``steps`` RK4 steps of ``dt`` (s) in place.

    Work arrays: (xt, vt) the stage state, kv the stage acceleration (m/s^2), (sx, sv)
    the weighted sums of the stages; their contents on entry are ignored.
    """
    n = x.shape[0]
    ti.loop_config(serialize=True)
    for _ in range(steps):
        for i in range(n):
            xt[i] = x[i]
            vt[i] = v[i]
            sx[i] = ti.Vector.zero(ti.f64, 3)
            sv[i] = ti.Vector.zero(ti.f64, 3)
        for stage in range(4):
            weight = 1.0 if stage == 0 or stage == 3 else 2.0
            offset = dt if stage == 2 else 0.5 * dt  # where the next stage is evaluated
            for i in range(n):
                moving = True
                if ti.static(has_fixed):
                    moving = free[i] != 0
                a = ti.Vector.zero(ti.f64, 3)
                if moving:
                    a = particle_force(i, xt, vt, mass, offsets, other, spring, ks, kd, l0, g,
                                       has_damping, has_gravity, ti.f64) / mass[i]
                kv[i] = a
            for i in range(n):
                sx[i] += weight * vt[i]
                sv[i] += weight * kv[i]
                xt[i] = x[i] + offset * vt[i]
                vt[i] = v[i] + offset * kv[i]
        for i in range(n):
            x[i] += dt / 6.0 * sx[i]
            v[i] += dt / 6.0 * sv[i]
