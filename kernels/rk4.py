"""Classical fourth-order Runge-Kutta steps of seed Eq. 4.

Eq. 4 is the first-order system y' = F(y) with y = (x, v) and F(x, v) = (v, M^-1 f(x, v)),
f the total force (``forces``); a pinned particle has F = (its velocity, 0): it
moves with its prescribed (constant) velocity. One step of size h
from ``src`` to ``dst`` (ending at time t, s):

    k1 = F(y), k2 = F(y + h/2 k1), k3 = F(y + h/2 k2), k4 = F(y + h k3),
    y' = y + h/6 (k1 + 2 k2 + 2 k3 + k4),

with the stage state in ``stage`` (x, v) and the weighted sums of the stages in
``dev.sx``, ``dev.sv``; the new state's ``divergence.state_sums`` are reduced in
the last loop, where a model with colliders also gets the explicit integrators'
contact response (``contact.respond``: first order in dt at contact). ``rk4_step``
runs one step with parallel loops, ``rk4_steps`` up to ``steps`` in one launch with
serial loops (as ``euler``). ``rk4_adjoint`` runs a step backwards (``adjoint_step``).
"""

import taichi as ti

from .blocks import BLOCK, block_count, block_end, ordered_sum
from .divergence import OK, state_sums, verdict
from .constraints import is_free
from .contact import respond, respond_adjoint
from .forces import acceleration_adjoint, particle_force, spring_forces, spring_sum
from .state import restore_state
from .terms import uniform_acceleration


@ti.func
def one_step(dev, cfg: ti.template(), src, dst, stage, h, t):
    """One RK4 step src -> dst; returns the new state's summed ``state_sums``."""
    n = dev.size[0]
    for i in range(n):
        stage.x[i] = src.x[i]
        stage.v[i] = src.v[i]
        dev.sx[i] = ti.Vector.zero(cfg.real, 3)
        dev.sv[i] = ti.Vector.zero(cfg.real, 3)
    for k in ti.static(range(4)):
        weight = ti.static(1 if k in (0, 3) else 2)
        offset = ti.cast(ti.static(1.0 if k == 2 else 0.5), cfg.real)  # where the next stage is evaluated, in units of h
        spring_forces(dev, cfg, stage.x, stage.v, False)
        for i in range(n):
            f = particle_force(i, dev, cfg, stage.x, stage.v, False)
            a = ti.Vector.zero(cfg.real, 3)
            if is_free(i, dev, cfg):
                a = f / dev.mass[i]
            vt = stage.v[i]
            dev.sx[i] += weight * vt
            dev.sv[i] += weight * a
            if ti.static(k < 3):
                stage.x[i] = src.x[i] + offset * h * vt
                stage.v[i] = src.v[i] + offset * h * a
    g = uniform_acceleration(dev, cfg)
    for b in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(b * BLOCK, block_end(b, n)):
            x = src.x[i] + h / ti.cast(6, cfg.real) * dev.sx[i]
            v = src.v[i] + h / ti.cast(6, cfg.real) * dev.sv[i]
            if ti.static(cfg.has_colliders):
                if is_free(i, dev, cfg):
                    x_out, v_out = respond(dev, cfg, src.x[i], x, v, h, t)
                    x = x_out
                    v = v_out
            dst.x[i] = x
            dst.v[i] = v
            acc += state_sums(x, v, dev.mass[i], g, cfg.has_uniform)
        dev.partial[b] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.kernel
def rk4_step(dev: ti.template(), cfg: ti.template(), src: ti.template(), dst: ti.template(),
             stage: ti.template(), dt: ti.f64, t: ti.f64) -> ti.types.vector(3, ti.f64):
    """One step src -> dst from time t (s) with parallel loops; returns the new state's
    ``divergence.verdict`` (code, kinetic energy J, bound J)."""
    sums = one_step(dev, cfg, src, dst, stage, ti.cast(dt, cfg.real), ti.cast(t + dt, cfg.real))
    return verdict(sums, dev.check[None])


@ti.kernel
def rk4_steps(dev: ti.template(), cfg: ti.template(), a: ti.template(), b: ti.template(), stage: ti.template(),
              dt: ti.f64, t: ti.f64, steps: ti.i32, parity: ti.i32) -> ti.types.vector(4, ti.f64):
    """Up to ``steps`` steps from time t (s) in one launch with serial loops, from ``a``
    (``parity`` 0) or ``b`` (1), as ``euler.euler_steps``."""
    h = ti.cast(dt, cfg.real)
    done = 0
    code = OK
    last = ti.Vector.zero(ti.f64, 3)
    ti.loop_config(serialize=True)
    for _ in range(1):
        while done < steps and code == OK:
            end = ti.cast(t + (done + 1) * dt, cfg.real)
            if (done + parity) % 2 == 0:
                even = one_step(dev, cfg, a, b, stage, h, end)
                last = verdict(even, dev.check[None])
                code = ti.cast(last[0], ti.i32)
            else:
                odd = one_step(dev, cfg, b, a, stage, h, end)
                last = verdict(odd, dev.check[None])
                code = ti.cast(last[0], ti.i32)
            if code == OK:
                done += 1
    return ti.Vector([done, last[0], last[1], last[2]], ti.f64)


@ti.func
def adjoint_step(dev, cfg: ti.template(), adj, src, stage, h, t, slot, wants: ti.template()):
    """One step backwards, in f64, from the state kept at ``slot`` of ``adj``'s history
    (restored into ``src``): dL/dy' in ``adj.lx``, ``adj.lv`` on entry, dL/dy on exit,
    the parameters' shares added. The stages y2, y3, y4 are computed again as the step
    computed them and kept in ``adj.xs``, ``adj.vs`` (a slot of ``stride`` rows each);
    then, from the last stage back, with k4^ = h/6 y'^ and ki^ = b_i h y'^ + c_i h J(y_i+1)^T
    k_i+1^ (b = 1/6, 1/3, 1/3; c = 1/2, 1/2, 1: y_i+1 = y + c_i h k_i), each stage's
    J(y_i)^T k_i^ is added to dL/dy. J^T of F(x, v) = (v, f/m) at a stage: dL/dx += K w,
    dL/dv += k^_x + D w with w = k^_v / m (``forces.acceleration_adjoint``). With colliders
    the step ends at time t (s) with the contact response: the free step's end is computed
    again as ``one_step`` computed it (its weighted sums in ``dev.sx``, ``dev.sv``) and
    ``contact.respond_adjoint`` (branches frozen) turns dL/dy' into dL/d(free end) first,
    its share in the start position going to ``adj.cx``."""
    n = dev.size[0]
    stride = adj.stride[None]
    restore_state(adj.hx, adj.hv, src, n, slot, stride)
    for i in range(n):
        stage.x[i] = src.x[i]
        stage.v[i] = src.v[i]
        if ti.static(cfg.has_colliders):
            dev.sx[i] = ti.Vector.zero(cfg.real, 3)
            dev.sv[i] = ti.Vector.zero(cfg.real, 3)
    for k in ti.static(range(3)):
        offset = ti.cast(ti.static(1.0 if k == 2 else 0.5), ti.f64)
        weight = ti.static(1 if k == 0 else 2)
        spring_forces(dev, cfg, stage.x, stage.v, False)
        for i in range(n):
            f = particle_force(i, dev, cfg, stage.x, stage.v, False)
            a = ti.Vector.zero(ti.f64, 3)
            if is_free(i, dev, cfg):
                a = f / dev.mass[i]
            vt = stage.v[i]
            if ti.static(cfg.has_colliders):
                dev.sx[i] += weight * vt
                dev.sv[i] += weight * a
            stage.x[i] = src.x[i] + offset * h * vt
            stage.v[i] = src.v[i] + offset * h * a
            adj.xs[k * stride + i] = stage.x[i]
            adj.vs[k * stride + i] = stage.v[i]
    if ti.static(cfg.has_colliders):
        spring_forces(dev, cfg, stage.x, stage.v, False)
        for i in range(n):
            cx = ti.Vector.zero(ti.f64, 3)
            if is_free(i, dev, cfg):
                a = particle_force(i, dev, cfg, stage.x, stage.v, False) / dev.mass[i]
                x = src.x[i] + h / ti.cast(6, cfg.real) * (dev.sx[i] + stage.v[i])
                v = src.v[i] + h / ti.cast(6, cfg.real) * (dev.sv[i] + a)
                ax0, ax, av = respond_adjoint(dev, cfg, src.x[i], x, v, h, t, adj.lx[i], adj.lv[i])
                cx = ax0
                adj.lx[i] = ax
                adj.lv[i] = av
            adj.cx[i] = cx
    for k in ti.static((3, 2, 1, 0)):
        b = ti.static(1.0 / 6.0 if k in (0, 3) else 1.0 / 3.0)
        c = ti.static((0.5, 0.5, 1.0, 0.0)[k])
        for i in range(n):
            kx = b * h * adj.lx[i]
            kv = b * h * adj.lv[i]
            if ti.static(k < 3):
                kx += c * h * adj.yx[i]
                kv += c * h * adj.yv[i]
            adj.kx[i] = kx
            adj.w[i] = kv
            if ti.static(k > 0):
                stage.x[i] = adj.xs[(k - 1) * stride + i]
                stage.v[i] = adj.vs[(k - 1) * stride + i]
        if ti.static(k == 0):
            acceleration_adjoint(dev, cfg, adj, src.x, src.v, wants, src.x, False)
        else:
            acceleration_adjoint(dev, cfg, adj, stage.x, stage.v, wants, stage.x, False)
        for i in range(n):
            yx = adj.px[i]
            yv = adj.kx[i] + adj.pv[i]
            if ti.static(cfg.has_springs):
                yx -= spring_sum(i, dev, adj.sx)
                yv -= spring_sum(i, dev, adj.sv)
            adj.yx[i] = yx
            adj.yv[i] = yv
            if ti.static(k == 3):
                adj.ax[i] = yx
                adj.av[i] = yv
            else:
                adj.ax[i] = adj.ax[i] + yx
                adj.av[i] = adj.av[i] + yv
    for i in range(n):
        lx = adj.lx[i] + adj.ax[i]
        if ti.static(cfg.has_colliders):
            lx += adj.cx[i]
        adj.lx[i] = lx
        adj.lv[i] = adj.lv[i] + adj.av[i]


@ti.kernel
def rk4_adjoint(dev: ti.template(), cfg: ti.template(), adj: ti.template(), src: ti.template(), stage: ti.template(),
                dt: ti.f64, t: ti.f64, slot: ti.i32, wants: ti.template(), serial: ti.template()):
    """``adjoint_step`` of the step of dt (s) ending at time t (s) as parallel loops, or
    with ``serial`` in one serial loop."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            adjoint_step(dev, cfg, adj, src, stage, ti.cast(dt, ti.f64), ti.cast(t, ti.f64), slot, wants)
    else:
        adjoint_step(dev, cfg, adj, src, stage, ti.cast(dt, ti.f64), ti.cast(t, ti.f64), slot, wants)
