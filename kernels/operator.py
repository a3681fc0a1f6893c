"""The matrix-free operator of the linearised implicit step (seed Eq. 13-15).

Eq. 15's matrix is A = M - dt D - dt^2 K. Every spring term adds to a spring's
block S = a I + b n n^T (``terms.base.SpringTerm.coefficients``): S goes to the
(i,i) and (j,j) blocks of A, -S to (i,j) and (j,i). Particle terms add multiples
of I to the diagonal (``ParticleTerm.diagonal``), so A_ii = d_i I + sum_s S_s with
d_i = m_i + those multiples.

The global matrix is never formed. Once per step ``refresh`` computes each
spring's (n, a, b) once into ``dev.spring_coef`` together with the right-hand
side forces of Eq. 15 into ``dev.fs``, then copies them into adjacency order
(``dev.coef``: the operator then streams its coefficients in the order it reads
them instead of looking them up by spring, which ``benchmarks/storage.py`` found faster)
and forms ``dev.diag`` (d_i) and the right-hand side ``dev.b``. ``apply_row``
gathers (A p)_i over particle i's entries:

    (A p)_i = d_i p_i + sum_e [a_e (p_i - p_j) + b_e n_e (n_e . (p_i - p_j))]

(plus, with self-collision pairs in the solve, their penalty's share,
``pair_penalty.pair_row``).

With ``cfg.lagged`` (the Newton-solved steps, ``kernels/newton.py``) the rate-dependent
terms act along a second direction m per spring, S = a I + b n n^T + c m m^T, their
(m, c) in ``dev.lag`` and, in adjacency order, ``dev.lag_coef``.

Shapes (n particles, m springs): ``spring_coef`` (m,), ``coef`` (2m,) of
5-vectors (n_x, n_y, n_z, a, b) in the run's precision; ``diag`` (n,); ``b`` (n,)
vec3 in kg m/s.
"""

import taichi as ti

from .constraints import constrain, is_pinned
from .contact import detect, friction_diagonal, friction_impulse
from .forces import particle_force, spring_direction, tiny_length
from .pair_penalty import pair_diagonal, pair_force, pair_row


@ti.func
def spring_coefficients(dev, cfg: ti.template(), x, v, h, full: ti.template()):
    """Per spring: ``dev.spring_coef[s] = (n, a, b)`` and ``dev.fs[s]`` = its f - D v
    on the first end (its whole force f with ``full``). A spring of zero length gets
    n = 0 and no force; its terms' (a, b) at n = 0 (only a zero-rest-length spring's
    a = dt^2 ks is not 0)."""
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            i = dev.ends[s][0]
            j = dev.ends[s][1]
            n, length = spring_direction(x[j] - x[i], cfg.real)
            a = ti.cast(0, cfg.real)
            b = ti.cast(0, cfg.real)
            t = ti.cast(0, cfg.real)
            m = ti.Vector.zero(cfg.real, 3)
            c = ti.cast(0, cfg.real)
            rate = ti.cast(0, cfg.real)
            if ti.static(cfg.lagged):
                lag = dev.lag[s]
                m = ti.Vector([lag[0], lag[1], lag[2]], cfg.real)
            for term in ti.static(cfg.spring_terms):
                if ti.static(cfg.lagged and term.rate_dependent):  # along m (``lagged_directions``)
                    da, dc = term.coefficients(s, dev, m, length, h, cfg.fix)
                    a += da
                    c += dc
                    if ti.static(full):
                        rate += term.tension(s, dev, i, j, x, v, m, length)
                else:
                    da, db = term.coefficients(s, dev, n, length, h, cfg.fix)
                    a += da
                    b += db
                    if length > tiny_length(cfg.real):
                        if ti.static(full):
                            t += term.tension(s, dev, i, j, x, v, n, length)
                        else:
                            t += term.rhs_tension(s, dev, i, j, x, v, n, length)
            dev.spring_coef[s] = ti.Vector([n[0], n[1], n[2], a, b], cfg.real)
            dev.fs[s] = t * n + rate * m
            if ti.static(cfg.lagged):
                dev.lag[s] = ti.Vector([m[0], m[1], m[2], c], cfg.real)


@ti.func
def gather_coefficients(i, dev, cfg: ti.template()):
    """Copy particle i's springs' (n, a, b) into adjacency order ``dev.coef``."""
    for e in range(dev.offsets[i], dev.offsets[i + 1]):
        s = dev.entry[e]
        if s < 0:
            s = -1 - s
        dev.coef[e] = dev.spring_coef[s]
        if ti.static(cfg.lagged):
            dev.lag_coef[e] = dev.lag[s]


@ti.func
def diagonal_scalar(i, dev, cfg: ti.template(), h):
    """d_i = m_i + the particle terms' diagonal multiples of I (kg)."""
    d = dev.mass[i]
    for term in ti.static(cfg.particle_terms):
        d += term.diagonal(i, dev, h)
    return d


@ti.func
def entry_block(e, dev, cfg: ti.template()):
    """Entry e's 3x3 spring block S = a I + b n n^T (+ c m m^T with ``cfg.lagged``)."""
    c = dev.coef[e]
    n = ti.Vector([c[0], c[1], c[2]], cfg.real)
    block = c[3] * ti.Matrix.identity(cfg.real, 3) + c[4] * n.outer_product(n)
    if ti.static(cfg.lagged):
        lag = dev.lag_coef[e]
        m = ti.Vector([lag[0], lag[1], lag[2]], cfg.real)
        block += lag[3] * m.outer_product(m)
    return block


@ti.func
def entry_times(e, dev, cfg: ti.template(), p):
    """S p for entry e's spring block S (``entry_block``) and a vector or a 3 x k block p:
    a p + b n (n^T p) (+ c m (m^T p)), rank-one updates (no 3x3 product)."""
    c = dev.coef[e]
    n = ti.Vector([c[0], c[1], c[2]], cfg.real)
    out = c[3] * p + (c[4] * n).outer_product(p.transpose() @ n)
    if ti.static(cfg.lagged):
        lag = dev.lag_coef[e]
        m = ti.Vector([lag[0], lag[1], lag[2]], cfg.real)
        out += (lag[3] * m).outer_product(p.transpose() @ m)
    return out


@ti.func
def diagonal_block(i, dev, cfg: ti.template()):
    """The 3x3 block A_ii = d_i I + sum_s S_s (``entry_block``)."""
    block = dev.diag[i] * ti.Matrix.identity(cfg.real, 3)
    if ti.static(cfg.has_springs):
        for e in range(dev.offsets[i], dev.offsets[i + 1]):
            block += entry_block(e, dev, cfg)
    if ti.static(cfg.self_pairs):
        block += pair_diagonal(i, dev, cfg)
    return block


# refresh modes: Eq. 15; a Newton iteration; none (the caller refreshed); Eq. 15's operator
# with the contacts the caller detected held (a Newton-solved step's adjoint)
LINEARISED, NEWTON, REFRESHED, HELD = 0, 1, -1, 2


@ti.func
def refresh_row(i, dev, cfg: ti.template(), x, v, h, t, mode: ti.template()):
    """Particle i's part of ``refresh`` (after ``spring_coefficients``): its contact
    constraints at time t (``contact.detect``, with colliders; a ``NEWTON`` iteration
    holds the contacts its step started with, ``kernels/newton.py``, and ``HELD`` those
    the caller detected), its entries of
    ``coef``, ``diag``, the right-hand side, with a contact's friction
    (``contact.friction_diagonal``, ``friction_impulse``) in both, and, for a
    preconditioner that needs it, its setup from A_ii.

    The right-hand side (0 at pinned particles): b_i = m_i v_i + dt (f - D v)_i of
    Eq. 15; in ``NEWTON`` mode, at the iterate v (positions ``x`` = x^ + h v,
    ``dev.fs`` holding whole spring forces), b_i = (A v)_i - g_i with g the residual
    of the implicit equations M (v - v^) = h f(x, v) + friction, stored filtered in
    ``dev.res``: A v' = b is then Newton's linear system for the next iterate v'."""
    carrier = ti.Vector.zero(cfg.real, 3)
    if ti.static(cfg.has_springs):
        gather_coefficients(i, dev, cfg)
    dev.diag[i] = diagonal_scalar(i, dev, cfg, h)
    if ti.static(cfg.contact_filter):
        if ti.static(mode == NEWTON or mode == HELD):
            carrier = dev.carrier[i]
        else:
            found = detect(i, dev, cfg, x, v, h, t)
            carrier = found
        dev.diag[i] += friction_diagonal(i, dev, cfg)
    if not is_pinned(i, dev, cfg):
        if ti.static(mode == NEWTON):
            f = particle_force(i, dev, cfg, x, v, False)
            g = dev.mass[i] * (v[i] - dev.vb[i]) - h * f
            if ti.static(cfg.contact_filter):
                g += friction_diagonal(i, dev, cfg) * v[i] - friction_impulse(i, dev, cfg, carrier)
            dev.b[i] = apply_row(i, dev, cfg, v) - g
            dev.res[i] = constrain(i, dev, cfg, g)
        else:
            f = particle_force(i, dev, cfg, x, v, True)
            if ti.static(cfg.self_pairs):
                f += pair_force(i, dev, cfg)
            dev.b[i] = dev.mass[i] * v[i] + h * f
            if ti.static(cfg.contact_filter):
                dev.b[i] += friction_impulse(i, dev, cfg, carrier)
        if ti.static(cfg.needs_diagonal):
            block = diagonal_block(i, dev, cfg)
            cfg.precond.setup_row(i, dev, cfg, block)
    else:
        dev.b[i] = ti.Vector.zero(cfg.real, 3)
        if ti.static(mode == NEWTON):
            dev.res[i] = ti.Vector.zero(cfg.real, 3)


@ti.func
def refresh(dev, cfg: ti.template(), x, v, h, t, mode: ti.template()):
    """Operator coefficients, diagonal, right-hand side, contact constraints and pointwise
    preconditioner for the state (x, v) at time t (s): two loops, over springs then
    particles (with ``cfg.self_pairs``, the self-collision pairs collected by the pass
    before, ``kernels/pair_penalty.py``). ``mode``: see ``refresh_row``."""
    spring_coefficients(dev, cfg, x, v, h, mode == NEWTON)
    for i in range(dev.size[0]):
        refresh_row(i, dev, cfg, x, v, h, t, mode)


@ti.func
def apply_row(i, dev, cfg: ti.template(), p):
    """(A p)_i for the matrix-free A of Eq. 15."""
    pi = p[i]
    out = dev.diag[i] * pi
    if ti.static(cfg.has_springs):
        for e in range(dev.offsets[i], dev.offsets[i + 1]):
            c = dev.coef[e]
            n = ti.Vector([c[0], c[1], c[2]], cfg.real)
            dp = pi - p[dev.other[e]]
            out += c[3] * dp + c[4] * n.dot(dp) * n
            if ti.static(cfg.lagged):
                lag = dev.lag_coef[e]
                m = ti.Vector([lag[0], lag[1], lag[2]], cfg.real)
                out += lag[3] * m.dot(dp) * m
    if ti.static(cfg.self_pairs):
        out += pair_row(i, dev, cfg, p)
    return out


@ti.kernel
def jacobian_refresh(dev: ti.template(), cfg: ti.template()):
    """Coefficients of one Jacobian alone at the state (dev.x, dev.v): with dt = 1 and a
    single spring term in ``cfg`` (springs or damping), each spring's S is -K_ii (Eq. 13)
    or -D_ii (Eq. 14); the diagonal d is set to 0 (no mass)."""
    spring_coefficients(dev, cfg, dev.x, dev.v, ti.cast(1.0, cfg.real), False)
    for i in range(dev.size[0]):
        if ti.static(cfg.has_springs):
            gather_coefficients(i, dev, cfg)
        dev.diag[i] = 0.0


@ti.kernel
def jacobian_apply(dev: ti.template(), cfg: ti.template()):
    """dev.q = sum_s S_s (p_i - p_j) at every particle: -K p or -D p after ``jacobian_refresh``."""
    for i in range(dev.size[0]):
        dev.q[i] = apply_row(i, dev, cfg, dev.p)
