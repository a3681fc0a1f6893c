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
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            n, length = spring_direction(x[j] - x[i], cfg.real)
            t = ti.cast(0, cfg.real)
            if length > tiny_length(cfg.real):
                for term in ti.static(cfg.spring_terms):
                    if ti.static(rhs):
                        t += term.rhs_tension(s, dev, i, j, x, v, n, length)
                    else:
                        t += term.tension(s, dev, i, j, x, v, n, length)
            dev.fs[s] = t * n


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
