"""Total forces (seed Eq. 1-3 and any other registered term), each spring evaluated once.

``spring_forces`` computes every spring's force on its first end into ``dev.fs``
(a parallel loop over springs, streaming ``dev.ends`` and the terms' per-spring
arrays in order); ``particle_force`` then gathers particle i's share from its
adjacency entries (``dev.offsets``, ``dev.entry``: spring index s where i is the
spring's first end, -1 - s where it is the second) and adds the particle terms.
Gather, not scatter: no atomics, and the same sum order on every run.

Device arrays read (n particles, m springs): ``x, v`` (n,) vec3 (m, m/s);
``mass`` (n,) kg; ``ends`` (m,) int32 pairs; ``offsets`` (n+1,), ``entry`` (2m,)
int32; ``fs`` (m,) vec3 N; ``size = (n, m)``; plus each term's own arrays.
``cfg`` (``massspring.device.Config``) carries the compile-time switches:
``real`` (ti.f32 or ti.f64), ``spring_terms``, ``particle_terms``, ``fixed``.
"""

import taichi as ti

from .constraints import is_pinned
from .terms import SpringDamping, uniform_acceleration


@ti.func
def tiny_length(real: ti.template()):
    """Lengths at or below this (m) count as zero: the spring has no direction."""
    return ti.static(1e-6 if real == ti.f32 else 1e-12)


@ti.func
def spring_direction(d, real: ti.template()):
    """Unit vector ``n = d/|d|`` and length ``l = |d|``; ``n = 0`` when ``l <= tiny``.

    The zero-length rule: a spring with no direction exerts no force and adds no
    damping in that step, and no stiffness unless its rest length is 0 (it acts
    again as soon as its ends part).
    """
    length = ti.sqrt(d.dot(d))  # d.norm() adds a default-precision (f64) epsilon
    n = ti.Vector.zero(real, 3)
    if length > tiny_length(real):
        n = d * (ti.cast(1, real) / length)  # one division, not three (fast math here keeps d / l)
    return n, length


@ti.func
def spring_forces(dev, cfg: ti.template(), x, v, rhs: ti.template()):
    """``dev.fs[s]``: spring s's force on its first end (N), the sum of the spring
    terms' ``tension`` (``rhs_tension`` with ``rhs``: Eq. 15's f - D v) times n."""
    lagged_spring_forces(dev, cfg, x, v, rhs, x, False)


@ti.func
def lagged_spring_forces(dev, cfg: ti.template(), x, v, rhs: ti.template(), xs, lagged: ti.template()):
    """``spring_forces``; with ``lagged``, the rate-dependent terms' tension along the
    springs' directions at the positions ``xs`` (the Newton-solved steps' prediction,
    ``kernels/newton.py``)."""
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            n, length = spring_direction(x[j] - x[i], cfg.real)
            m = n
            if ti.static(lagged):
                m, _ = spring_direction(xs[j] - xs[i], cfg.real)
            t = ti.cast(0, cfg.real)
            rate = ti.cast(0, cfg.real)
            for term in ti.static(cfg.spring_terms):
                if ti.static(lagged and term.rate_dependent):
                    rate += term.tension(s, dev, i, j, x, v, m, length)
                elif length > tiny_length(cfg.real):
                    if ti.static(rhs):
                        t += term.rhs_tension(s, dev, i, j, x, v, n, length)
                    else:
                        t += term.tension(s, dev, i, j, x, v, n, length)
            dev.fs[s] = t * n + rate * m


@ti.func
def particle_force(i, dev, cfg: ti.template(), x, v, rhs: ti.template()):
    """Total force on particle i (N): its springs' (from ``dev.fs``, computed by
    ``spring_forces`` with the same ``rhs``) plus the particle terms'."""
    f = ti.Vector.zero(cfg.real, 3)
    if ti.static(cfg.has_springs):
        for e in range(dev.offsets[i], dev.offsets[i + 1]):
            s = dev.entry[e]
            if s >= 0:
                f += dev.fs[s]
            else:
                f -= dev.fs[-1 - s]
    for term in ti.static(cfg.particle_terms):
        if ti.static(rhs):
            f += term.rhs(i, dev, x, v)
        else:
            f += term.force(i, dev, x, v)
    return f


@ti.func
def spring_sum(i, dev, values):
    """Sum of ``values[s]`` (a vec3 per spring) over particle i's springs, + where i is the
    spring's first end and - where its second: how a spring's force on its first end
    reaches both ends (``particle_force``), used for the adjoints' per-spring vectors."""
    out = ti.Vector.zero(ti.f64, 3)
    for e in range(dev.offsets[i], dev.offsets[i + 1]):
        s = dev.entry[e]
        if s >= 0:
            out += values[s]
        else:
            out -= values[-1 - s]
    return out


@ti.func
def acceleration_adjoint(dev, cfg: ti.template(), adj, x, v, wants: ti.template(), xs, lagged: ti.template()):
    """The adjoint of the accelerations a_i = f_i(x, v) / m_i (``massspring.gradients``): on
    entry ``adj.w[i]`` holds dL/da_i (ignored at pinned particles); on exit it holds
    w_i = dL/da_i / m_i (0 at pins), ``adj.sx[s]``, ``adj.sv[s]`` the gradients of
    sum_i w_i . f_i in spring s's d = x_j - x_i and r = v_j - v_i (each term's
    ``adjoint``; gather them with ``spring_sum``: dL/dx_i -= spring_sum(sx), likewise v),
    ``adj.px[i]``, ``adj.pv[i]`` those of the particle terms' in x_i and v_i (add them as
    they are), and the parameters' gradients added: every spring term's, dL/dm_i -= w_i . (f_i -
    m_i g) / m_i (with ``wants.masses``), dL/dg += dL/da_i (``adj.gg`` per particle).
    ``wants``: ``massspring.gradients.Wants``. With ``lagged`` (a Newton-solved step,
    ``kernels/newton.py``), the rate-dependent terms act along the directions at the
    positions ``xs`` (the step's prediction): their gradient in that d goes to
    ``adj.sl[s]`` (gather it as sx, into the prediction's positions)."""
    n = dev.size[0]
    g = uniform_acceleration(dev, cfg)
    if ti.static(wants.masses):
        lagged_spring_forces(dev, cfg, x, v, False, xs, lagged)
    for i in range(n):
        w = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            abar = adj.w[i]
            w = abar / dev.mass[i]
            if ti.static(wants.masses):
                f = particle_force(i, dev, cfg, x, v, False) - dev.mass[i] * g
                adj.gm[i] = adj.gm[i] - w.dot(f) / dev.mass[i]
            adj.gg[i] = adj.gg[i] + abar
        px = ti.Vector.zero(ti.f64, 3)
        pv = ti.Vector.zero(ti.f64, 3)
        for term in ti.static(cfg.particle_terms):
            tx, tv = term.adjoint(i, dev, adj, w, x, v)
            px += tx
            pv += tv
        adj.px[i] = px
        adj.pv[i] = pv
        adj.w[i] = w
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            d = x[j] - x[i]
            r = v[j] - v[i]
            u = adj.w[i] - adj.w[j]
            unit, length = spring_direction(d, ti.f64)
            gx = ti.Vector.zero(ti.f64, 3)
            gv = ti.Vector.zero(ti.f64, 3)
            if ti.static(lagged):
                ds = xs[j] - xs[i]
                lag, lag_length = spring_direction(ds, ti.f64)
                gl = ti.Vector.zero(ti.f64, 3)
                if lag_length > tiny_length(ti.f64):
                    for term in ti.static(cfg.spring_terms):
                        if ti.static(term.rate_dependent):
                            tx, tv = term.adjoint(s, dev, adj, u, ds, r, lag, lag_length)
                            gl += tx
                            gv += tv
                    if ti.static(wants.rate_gradient):
                        SpringDamping.rate_gradient(s, adj, u, r, lag)
                adj.sl[s] = gl
            if length > tiny_length(ti.f64):
                for term in ti.static(cfg.spring_terms):
                    if ti.static(not (lagged and term.rate_dependent)):
                        tx, tv = term.adjoint(s, dev, adj, u, d, r, unit, length)
                        gx += tx
                        gv += tv
                if ti.static(wants.rate_gradient and not lagged):
                    SpringDamping.rate_gradient(s, adj, u, r, unit)
            adj.sx[s] = gx
            adj.sv[s] = gv
