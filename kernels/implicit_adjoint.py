"""The adjoint of the linearised implicit step (seed Eq. 15), for ``massspring.gradients``.

The step solves A(x) v' = b(x, v) on the free particles, A = M - h D - h^2 K (with the
definiteness fix as the step used it), b = M v + h (f - D v) = M v + h f_e(x) + h M g
(the damping force is D v exactly), then x' = x + h v'. Backwards, with dL/dx', dL/dv'
of the state after the step:

    A mu = dL/dv' + h dL/dx'                      (free rows; mu = 0 at pins)
    dL/dx = dL/dx' + d(mu . b)/dx - d(mu . A v')/dx,   dL/dv = M mu,
    dL/dtheta += mu . (db/dtheta - dA/dtheta v'),

A is symmetric, so the adjoint system is the step's own: ``adjoint_rhs`` refreshes the
operator at the step's state (restored from the history) and sets the right-hand side
and warm start, the Simulation's CG driver and preconditioner solve it
(``massspring.solvers.solve`` with the operator refreshed), and ``implicit_adjoint``
gathers the rest spring by spring from each term's ``rhs_adjoint`` and
``operator_adjoint`` (``kernels/terms``). Arrays of ``adj``: see ``massspring.gradients``.

With colliders (docs/gradients.md): the step's contacts are detected again from the
contact memory kept with the state (``keep_contacts``); dL/dx' goes back through the
final projection and the landing correction (``position_adjoint``), with friction
through ``friction.friction_adjoint`` to the solve's velocity (kept before friction
changed it: ``keep_solved``) and the contact impulses J = A v' - b (their gradient
``adj.cj`` joins G as A cj, and the parameters' shares are mu - cj's); the solve is
the step's filtered one, and ``contact.constraint_adjoint`` adds the constraints'
share through the normals and the arriving velocity.
"""

import taichi as ti

from .constraints import constrain, is_free, is_pinned, pin_adjoint, prescribed
from .contact import STICK, constraint_adjoint, landing, landing_adjoint, project_adjoint
from .friction import first_carrier, friction_adjoint
from .forces import spring_direction, spring_sum, tiny_length
from .operator import LINEARISED, apply_row, refresh
from .state import restore_state
from .terms import SpringDamping, uniform_acceleration


@ti.func
def solved(adj, wants: ti.template(), slot, i):
    """v' of particle i in the step from ``slot``: the solve's velocity (with friction,
    before ``friction_row`` changed it: ``adj.hw``), else the history's next state's."""
    stride = adj.stride[None]
    out = adj.hv[(slot + 1) * stride + i]
    if ti.static(wants.friction):
        out = adj.hw[slot * stride + i]
    return out


@ti.func
def position_adjoint(i, dev, cfg: ti.template(), adj, slot, xb, h, t, dt):
    """With colliders, x' = P(x^ + h v'' - landing(x_n)) of a particle not pinned
    (``cg.next_position``: x^ = ``xb``, P the final projection at the step's end t + dt,
    the landing correction at its start t, its contacts in ``dev``): from dL/dx' in
    ``adj.lx``, returns (dL/dy at y = x^ + h v'' - landing, the share of dL/dx_n through
    the landing and dL/dx^, y less the landing's)."""
    stride = adj.stride[None]
    x = adj.hx[slot * stride + i]
    y = xb + h * adj.hv[(slot + 1) * stride + i] - landing(i, dev, cfg, x, t)
    gy = project_adjoint(dev, cfg, y, t + dt, ti.static(cfg.collider_count), adj.lx[i])
    return gy, gy - landing_adjoint(i, dev, cfg, x, t, gy)


@ti.func
def rhs(dev, cfg: ti.template(), adj, h, t, slot, wants: ti.template()):
    n = dev.size[0]
    stride = adj.stride[None]
    restore_state(adj.hx, adj.hv, dev.state, n, slot, stride)
    if ti.static(cfg.contact_filter):
        for i in range(n):  # the contact memory as the step began
            dev.released[i] = adj.hr[slot * stride + i]
            if ti.static(wants.friction):
                dev.stick[i] = adj.hs[slot * stride + i]
                dev.fric[i] = adj.hf[slot * stride + i]
    refresh(dev, cfg, dev.x, dev.v, h, t, LINEARISED)
    if ti.static(cfg.moving_pins or cfg.contact_filter):
        for i in range(n):  # the solve starts constrained directions at their velocity: A's columns move to b
            dev.p[i] = ti.Vector.zero(cfg.real, 3)
            if not is_free(i, dev, cfg):
                dev.p[i] = prescribed(i, dev, cfg)
            if ti.static(cfg.contact_filter):
                dev.q[i] = solved(adj, wants, slot, i)  # v', for the contacts' impulses
    for i in range(n):
        if ti.static(wants.pins):
            pin_adjoint(i, dev, cfg, adj, h)
        b = ti.Vector.zero(cfg.real, 3)
        if ti.static(wants.friction):
            adj.cj[i] = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            gy = adj.lx[i]
            if ti.static(cfg.has_colliders):
                gy, gx = position_adjoint(i, dev, cfg, adj, slot, dev.x[i], h, t, h)
                adj.lx[i] = gx
            b = adj.lv[i] + h * gy
            if ti.static(cfg.contact_filter):
                if dev.contacts[i] != 0:
                    dev.impulse[i] = apply_row(i, dev, cfg, dev.q) - dev.b[i]
                    if ti.static(wants.friction):  # v'' = friction_row(v', J): back to v' and J
                        gv, gj, gx, gm = friction_adjoint(i, dev, cfg, dev.x[i], dev.q[i], b, adj.gf[i], t)
                        b = gv
                        adj.cj[i] = gj
                        adj.lx[i] = adj.lx[i] + gx
                        if ti.static(wants.masses):
                            adj.gm[i] = adj.gm[i] + gm
        dev.b[i] = b
        dev.v[i] = adj.w[i]
    if ti.static(cfg.moving_pins or cfg.contact_filter):
        for i in range(n):
            if not is_pinned(i, dev, cfg):
                b = dev.b[i]
                if ti.static(wants.friction):  # J = A v' - b: dL/dJ's share of dL/dv'
                    b += apply_row(i, dev, cfg, adj.cj)
                if ti.static(cfg.contact_filter):
                    if dev.contacts[i] != 0:
                        adj.cg[i] = b
                dev.b[i] = b + apply_row(i, dev, cfg, dev.p)


@ti.kernel
def adjoint_rhs(dev: ti.template(), cfg: ti.template(), adj: ti.template(), dt: ti.f64, t: ti.f64, slot: ti.i32,
                wants: ti.template(), serial: ti.template()):
    """The state kept at ``slot`` restored into ``dev.x``, ``dev.v`` (with colliders, the
    contacts released before it into ``dev.released``); the pins' share of the pin
    velocities' gradient (with ``wants.pins``, ``constraints.pin_adjoint``); the operator
    and contacts refreshed there (time t, s); ``dev.b`` = G = dL/dv' + h dL/dx' on rows
    not pinned (plus A's columns of the constrained directions times their prescribed
    velocities, which the solve's start subtracts again; with colliders, dL/dx' taken
    back through the final projection and the landing correction first, the rest of
    dL/dx kept in ``adj.lx``); at a particle in contact, G in ``adj.cg`` and its impulse
    A v' - b in ``dev.impulse``; ``dev.v`` = the last adjoint solution ``adj.w`` (the warm
    start)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            rhs(dev, cfg, adj, ti.cast(dt, cfg.real), ti.cast(t, cfg.real), slot, wants)
    else:
        rhs(dev, cfg, adj, ti.cast(dt, cfg.real), ti.cast(t, cfg.real), slot, wants)


@ti.func
def gather(dev, cfg: ti.template(), adj, h, t, slot, wants: ti.template()):
    n = dev.size[0]
    stride = adj.stride[None]
    g = uniform_acceleration(dev, cfg)
    for i in range(n):
        mu = ti.Vector.zero(ti.f64, 3)
        px = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            mu = constrain(i, dev, cfg, dev.v[i])
            if ti.static(wants.friction):  # with the impulse's share: mu - dL/dJ
                mu -= adj.cj[i]
            if ti.static(wants.masses):
                change = solved(adj, wants, slot, i) - adj.hv[slot * stride + i]
                adj.gm[i] = adj.gm[i] + mu.dot(h * g - change)
                if ti.static(wants.friction):  # a sticking particle's damper STICK m in A and b
                    if dev.contacts[i] != 0 and dev.stick[i] != 0:
                        adj.gm[i] = adj.gm[i] + STICK * mu.dot(first_carrier(i, dev, cfg) - solved(adj, wants, slot, i))
            adj.gg[i] = adj.gg[i] + h * dev.mass[i] * mu
            for term in ti.static(cfg.particle_terms):
                px += term.rhs_adjoint(i, dev, adj, h * mu, dev.x, dev.v)
                px -= term.operator_adjoint(i, dev, adj, mu, solved(adj, wants, slot, i), h)
        adj.px[i] = px
        adj.w[i] = mu
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            d = dev.x[j] - dev.x[i]
            u = adj.w[i] - adj.w[j]
            p = solved(adj, wants, slot, i) - solved(adj, wants, slot, j)
            unit, length = spring_direction(d, ti.f64)
            gx = ti.Vector.zero(ti.f64, 3)
            if length > tiny_length(ti.f64):
                for term in ti.static(cfg.spring_terms):
                    tx, _ = term.rhs_adjoint(s, dev, adj, h * u, d, d * 0, unit, length)
                    gx += tx
            for term in ti.static(cfg.spring_terms):
                gx -= term.operator_adjoint(s, dev, adj, u, p, d, unit, length, h, cfg.fix)
            if ti.static(wants.rate_gradient):
                if unit.dot(unit) > 0:
                    SpringDamping.operator_rate_gradient(s, adj, u, p, unit, h)
            adj.sx[s] = gx
    for i in range(n):
        lx = adj.lx[i]
        if ti.static(cfg.has_springs):
            lx -= spring_sum(i, dev, adj.sx)
        lv = dev.mass[i] * adj.w[i]
        if ti.static(cfg.contact_filter):
            if dev.contacts[i] != 0:
                mu = adj.w[i]
                unsettled = adj.cg[i] - apply_row(i, dev, cfg, adj.w)
                if ti.static(wants.friction):  # the solve's mu: w + dL/dJ
                    mu += adj.cj[i]
                    unsettled -= apply_row(i, dev, cfg, adj.cj)
                cx, cv = constraint_adjoint(i, dev, cfg, dev.x[i], adj.hv[slot * stride + i],
                                            solved(adj, wants, slot, i), mu, unsettled, dev.impulse[i], t)
                lx += cx
                lv += cv
        if ti.static(wants.friction):  # a sliding particle's kinetic friction in b came from the step before
            gf = ti.Vector.zero(ti.f64, 3)
            if dev.contacts[i] != 0 and dev.stick[i] == 0:
                gf = adj.w[i]
            adj.gf[i] = gf
        adj.lx[i] = lx + adj.px[i]
        adj.lv[i] = lv
        if ti.static(wants.pins):  # v' = vp at a pin moves A's pin columns times vp to the free rows' b
            if is_pinned(i, dev, cfg):
                adj.gp[i] = adj.gp[i] - apply_row(i, dev, cfg, adj.w)


@ti.kernel
def implicit_adjoint(dev: ti.template(), cfg: ti.template(), adj: ti.template(), dt: ti.f64, t: ti.f64,
                     slot: ti.i32, wants: ti.template(), serial: ti.template()):
    """After the adjoint solve (mu in ``dev.v``): dL/dx, dL/dv of the step's state into
    ``adj.lx``, ``adj.lv``, mu kept in ``adj.w`` (the next solve's warm start), the step's
    share of each parameter gradient added (module docstring; the masses' with
    ``wants.masses``: mu . (h g - (v' - v)); a pin velocity's, with ``wants.pins``:
    -(A mu)_p, mu = 0 at pins)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            gather(dev, cfg, adj, ti.cast(dt, ti.f64), ti.cast(t, cfg.real), slot, wants)
    else:
        gather(dev, cfg, adj, ti.cast(dt, ti.f64), ti.cast(t, cfg.real), slot, wants)


@ti.kernel
def keep_contacts(dev: ti.template(), adj: ti.template(), n: ti.i32, slot: ti.i32, friction: ti.template()):
    """The contact memory of the state kept at ``slot``, which the step from it starts
    with: released contacts (``adj.hr``: ``contact.detect`` skips them) and, with
    ``friction``, sticking particles and kinetic friction (``adj.hs``, ``adj.hf``)."""
    for i in range(n):
        row = slot * adj.stride[None] + i
        adj.hr[row] = dev.released[i]
        if ti.static(friction):
            adj.hs[row] = dev.stick[i]
            adj.hf[row] = dev.fric[i]


@ti.kernel
def keep_solved(dev: ti.template(), adj: ti.template(), n: ti.i32, slot: ti.i32):
    """adj.hw[slot * stride + i] = v' of the step from the state kept at ``slot``, as its
    solve left it in ``dev.v`` (before friction changes it)."""
    for i in range(n):
        adj.hw[slot * adj.stride[None] + i] = dev.v[i]


@ti.kernel
def keep_base(dev: ti.template(), adj: ti.template(), n: ti.i32, slot: ti.i32):
    """adj.hb[slot * stride + i] = x^ of the step from the state kept at ``slot``, as its
    positions are committed from (``dev.xb``: x' = x^ + h v', then onto surfaces)."""
    for i in range(n):
        adj.hb[slot * adj.stride[None] + i] = dev.xb[i]


@ti.kernel
def keep_impulses(dev: ti.template(), adj: ti.template(), n: ti.i32, slot: ti.i32):
    """adj.hj[slot * stride + i] = the contact impulse of the step from the state kept at
    ``slot`` (``friction.impulses``; 0 without contact): a Newton-solved step's residual
    at its converged iterate, which its adjoint does not compute again."""
    for i in range(n):
        out = ti.Vector.zero(ti.f64, 3)
        if dev.contacts[i] != 0:
            out = dev.impulse[i]
        adj.hj[slot * adj.stride[None] + i] = out
