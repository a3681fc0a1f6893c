"""Explicit Euler (seed Eq. 7-8, with the dt Eq. 8 drops) and symplectic Euler steps.

One step from state ``src`` to state ``dst`` (``x``, ``v`` fields; they must differ):
``forces.spring_forces`` on ``src``, then per particle

    explicit:    x' = x + dt v,   v' = v + dt f(x, v) / m
    symplectic:  v' = v + dt f(x, v) / m,   x' = x + dt v'

with pinned particles moved with their prescribed velocity (``constraints``) and,
in a model with colliders, free particles' contact response after the update
(``contact.respond``; ``t`` is the simulated time at the start of the step, s),
fused with the reduction of the new state's ``divergence.state_sums`` (fixed
blocks, see ``blocks``).

``euler_adjoint`` runs one step backwards (``adjoint_step``) (``massspring.gradient``): the adjoint of
the step from ``src``, exact for springs, damping, gravity and pins.

``euler_step`` runs one step as parallel loops and returns the new state's
``divergence.verdict``; ``euler_steps`` runs up to ``steps`` steps in one launch with serial
loops (small systems, where a launch costs more than a step), alternating
a -> b and b -> a from either, stopping at the first step whose state fails the check.
"""

import taichi as ti

from .blocks import block_count, block_end, ordered_sum, BLOCK
from .divergence import OK, state_sums, verdict
from .constraints import is_free, pin_adjoint, prescribed
from .contact import respond, respond_adjoint
from .forces import acceleration_adjoint, particle_force, spring_forces, spring_sum
from .state import restore_state, store_state
from .terms import uniform_acceleration


@ti.func
def update_particles(dev, cfg: ti.template(), src, dst, h, t, symplectic: ti.template()):
    """The per-particle half of a step ending at time ``t`` (after ``spring_forces`` on
    ``src``); returns the new state's summed ``state_sums``."""
    n = dev.size[0]
    g = uniform_acceleration(dev, cfg)
    for b in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(b * BLOCK, block_end(b, n)):
            x = src.x[i]
            v = src.v[i]
            if is_free(i, dev, cfg):
                f = particle_force(i, dev, cfg, src.x, src.v, False)
                v_new = v + h / dev.mass[i] * f
                if ti.static(symplectic):
                    x = x + h * v_new
                else:
                    x = x + h * v
                v = v_new
                if ti.static(cfg.has_colliders):
                    x_out, v_out = respond(dev, cfg, src.x[i], x, v, h, t)
                    x = x_out
                    v = v_out
            else:
                v = prescribed(i, dev, cfg)
                x = x + h * v
            dst.x[i] = x
            dst.v[i] = v
            acc += state_sums(x, v, dev.mass[i], g, cfg.has_uniform)
        dev.partial[b] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.kernel
def euler_step(dev: ti.template(), cfg: ti.template(), src: ti.template(), dst: ti.template(), dt: ti.f64,
               t: ti.f64, symplectic: ti.template()) -> ti.types.vector(3, ti.f64):
    """One step src -> dst from time t (s) with parallel loops; returns the new state's
    ``divergence.verdict`` (code, kinetic energy J, bound J)."""
    h = ti.cast(dt, cfg.real)
    spring_forces(dev, cfg, src.x, src.v, False)
    sums = update_particles(dev, cfg, src, dst, h, ti.cast(t + dt, cfg.real), symplectic)
    return verdict(sums, dev.check[None])


@ti.kernel
def euler_steps(dev: ti.template(), cfg: ti.template(), a: ti.template(), b: ti.template(), dt: ti.f64,
                t: ti.f64, steps: ti.i32, parity: ti.i32, symplectic: ti.template(), adj: ti.template(),
                slot: ti.i32, record: ti.template()) -> ti.types.vector(4, ti.f64):
    """Up to ``steps`` steps from time t (s) in one launch with serial loops, a -> b, b -> a, ...
    from ``a`` if ``parity`` is 0, b -> a, a -> b, ... if it is 1 (one compiled kernel
    whichever of the two states is current). With ``record`` (a gradient's forward pass),
    the k-th new state also goes to ``adj``'s history at slot ``slot`` + k (``state.store_state``);
    without, ``adj`` is not read (pass any bundle).

    Returns (good steps done k, then the ``divergence.verdict`` of the last state
    computed: code, kinetic energy J, bound J). The last good state is the start's if k is
    even, else the other one; a failed state is in the other one.
    """
    h = ti.cast(dt, cfg.real)
    done = 0
    code = OK
    last = ti.Vector.zero(ti.f64, 3)
    ti.loop_config(serialize=True)
    for _ in range(1):
        while done < steps and code == OK:
            end = ti.cast(t + (done + 1) * dt, cfg.real)
            if (done + parity) % 2 == 0:
                spring_forces(dev, cfg, a.x, a.v, False)
                even = update_particles(dev, cfg, a, b, h, end, symplectic)
                last = verdict(even, dev.check[None])
                code = ti.cast(last[0], ti.i32)
                if ti.static(record):
                    store_state(adj.hx, adj.hv, b, dev.size[0], slot + done, adj.stride[None])
            else:
                spring_forces(dev, cfg, b.x, b.v, False)
                odd = update_particles(dev, cfg, b, a, h, end, symplectic)
                last = verdict(odd, dev.check[None])
                code = ti.cast(last[0], ti.i32)
                if ti.static(record):
                    store_state(adj.hx, adj.hv, a, dev.size[0], slot + done, adj.stride[None])
            if code == OK:
                done += 1
    return ti.Vector([done, last[0], last[1], last[2]], ti.f64)


@ti.kernel
def euler_adjoint(dev: ti.template(), cfg: ti.template(), adj: ti.template(), src: ti.template(), dt: ti.f64,
                  t: ti.f64, slot: ti.i32, symplectic: ti.template(), wants: ti.template(),
                  masses_from_history: ti.template(), serial: ti.template()):
    """``adjoint_step`` as parallel loops, or with ``serial`` in one serial loop (small
    systems, as ``euler_steps``)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            adjoint_step(dev, cfg, adj, src, dt, t, slot, symplectic, wants, masses_from_history)
    else:
        adjoint_step(dev, cfg, adj, src, dt, t, slot, symplectic, wants, masses_from_history)


@ti.kernel
def euler_adjoints(dev: ti.template(), cfg: ti.template(), adj: ti.template(), src: ti.template(), dt: ti.f64,
                   slot: ti.i32, count: ti.i32, symplectic: ti.template(), wants: ti.template(),
                   masses_from_history: ti.template()):
    """``count`` steps backwards in one serial launch, from the step kept at ``slot`` down to
    ``slot - count + 1`` (without moving colliders: the steps' times are not read)."""
    ti.loop_config(serialize=True)
    for k in range(count):
        adjoint_step(dev, cfg, adj, src, dt, 0.0, slot - k, symplectic, wants, masses_from_history)


@ti.func
def adjoint_step(dev, cfg: ti.template(), adj, src, dt, t, slot, symplectic: ti.template(), wants: ti.template(),
                 masses_from_history: ti.template()):
    """One step backwards, in f64, from the state kept in ``adj``'s history at ``slot``
    (``state.save_state``; restored into ``src`` first), the step ending at time ``t``
    (s; where moving colliders are): on entry ``adj.lx``, ``adj.lv``
    (n,) vec3 hold dL/dx', dL/dv' of the step's end state; on exit dL/dx, dL/dv of
    ``src``, and every parameter gradient array of ``adj`` has this step's share added.
    With mu = dL/dv' (+ dt dL/dx' if ``symplectic``) the adjoint of the free particles'
    accelerations is dt mu, and with w = dt mu / m (0 for pinned particles)

        dL/dx = dL/dx' + K w,   dL/dv = dL/dv' + dt dL/dx' + D w  (free; pinned: D w),

    K w and D w gathered spring by spring and particle by particle
    (``forces.acceleration_adjoint``, which adds the parameters' shares; K and D are
    symmetric, their transposes themselves). With colliders, ``contact_adjoint`` first
    takes the contact response's share (its branches frozen).

    With ``masses_from_history`` (f64, no colliders; ``wants.masses`` then off) the
    masses' share -w_i . (f_i / m_i - g) comes from the history instead of a force pass:
    a free particle's step is v' = v + h f / m, so f / m = (v' - v) / h with v' the
    state after the step, kept at ``slot + 1``."""
    h = ti.cast(dt, ti.f64)
    n = dev.size[0]
    stride = adj.stride[None]
    restore_state(adj.hx, adj.hv, src, n, slot, stride)
    if ti.static(cfg.has_colliders):
        contact_adjoint(dev, cfg, adj, src, h, t, symplectic)
    g = uniform_acceleration(dev, cfg)
    for i in range(n):
        mu = adj.lv[i]
        if ti.static(symplectic):
            mu += h * adj.lx[i]
        adj.w[i] = h * mu
        if ti.static(wants.pins):
            pin_adjoint(i, dev, cfg, adj, h)
        if ti.static(masses_from_history):
            if is_free(i, dev, cfg):
                accel = (adj.hv[(slot + 1) * stride + i] - src.v[i]) / h
                adj.gm[i] = adj.gm[i] - (h * mu / dev.mass[i]).dot(accel - g)
    acceleration_adjoint(dev, cfg, adj, src.x, src.v, wants, src.x, False)
    for i in range(n):
        lx = adj.lx[i]
        lv = ti.Vector.zero(ti.f64, 3)
        if is_free(i, dev, cfg):
            lv = adj.lv[i] + h * adj.lx[i]
        if ti.static(cfg.has_springs):
            lx -= spring_sum(i, dev, adj.sx)
            lv -= spring_sum(i, dev, adj.sv)
        if ti.static(cfg.has_colliders):
            lx += adj.cx[i]
        adj.lx[i] = lx + adj.px[i]
        adj.lv[i] = lv + adj.pv[i]


@ti.func
def contact_adjoint(dev, cfg: ti.template(), adj, src, h, t, symplectic: ti.template()):
    """The contact response's share of a step backwards (``contact.respond_adjoint``,
    branches frozen): the free step of each free particle computed again from ``src``,
    then ``adj.lx``, ``adj.lv`` turned from dL/d(x', v') of the response's outputs into
    dL/d(x, v) of the free step's, and the response's direct gradient in the step's
    start position into ``adj.cx``."""
    spring_forces(dev, cfg, src.x, src.v, False)
    for i in range(dev.size[0]):
        cx = ti.Vector.zero(ti.f64, 3)
        if is_free(i, dev, cfg):
            x = src.x[i]
            v = src.v[i]
            v_new = v + h / dev.mass[i] * particle_force(i, dev, cfg, src.x, src.v, False)
            if ti.static(symplectic):
                x = x + h * v_new
            else:
                x = x + h * v
            ax0, ax, av = respond_adjoint(dev, cfg, src.x[i], x, v_new, h, t, adj.lx[i], adj.lv[i])
            cx = ax0
            adj.lx[i] = ax
            adj.lv[i] = av
        adj.cx[i] = cx
