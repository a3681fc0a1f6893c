"""After the implicit step's solve: contact impulses, Coulomb friction, release of pulling contacts.

The filtered CG (``constraints``, ``contact.detect``) solves Eq. 15 with the contact
velocities prescribed, so at a particle in contact the residual J_i = (A v' - b)_i
(kg m/s) is the impulse its contacts applied during the step. Along each contact
direction e_k (the orthonormalised normals, rebuilt here from the contact bits
``dev.contacts`` as ``detect`` built them) lambda_k = e_k . J_i is the normal impulse
(> 0 when the collider pushes); the Coulomb bound is B = sum_k mu_k max(lambda_k, 0).

Friction is static or kinetic per particle (``dev.stick``), and enters the solve as a
force, so that the cloth shares the load among its particles (friction applied to
each particle's velocity alone, or sticking particles held by constraints, lock a
stiff cloth: each particle that stops anchors its neighbours):

* a sticking particle is held to its collider by a damper c = STICK m_i / dt
  (``contact.friction_diagonal``, ``friction_impulse``); after the solve its
  tangential velocity u relative to the collider is set to 0 (it does not creep) if
  the damper's impulse STICK m_i |u| is within B, and otherwise it slides from the
  next step against u;
* a sliding particle's kinetic friction impulse ``dev.fric`` (from the last step's
  B, against its tangential velocity u relative to the collider) is part of b. If u
  turns to the side friction pushes (or stops), friction has overshot, and if it is
  slow enough for the damper to hold (STICK m_i |u| <= B, the sticking particle's
  test), friction can stop it: either way u is set to 0 and the particle sticks (a
  particle its cloth drags at a crawl would otherwise take the next step's friction
  direction from a velocity at round-off);
* in the first step of a contact (no friction in the solve yet), the particle's own
  velocity takes the Coulomb impulse: u is reduced by B / m_i, or set to 0 (then
  the particle sticks) if that stops it.

With a single particle all three are exact Coulomb friction; on a cloth the static
threshold is met to within 1 / (1 + STICK).

A contact with lambda_k < 0 pulls the particle towards the collider (it would have
left by itself): its bit goes to ``dev.released`` and ``detect`` skips it in the
next step. Errors (all O(dt)): friction uses the previous step's normal impulse,
switches between sticking and sliding act from the next step, and a pulling
contact holds for one step.

Arrays: ``dev.impulse`` (n,) vec3 (J_i at particles in contact), ``dev.released``
(n,) int32 bits, ``dev.stick`` (n,) int32, ``dev.fric`` (n,) vec3 N s.
"""

import taichi as ti

from .contact import STICK, add_direction, column, contact_normals, mu, normals_adjoint, orthonormal, set_column, velocity
from .operator import apply_row


@ti.func
def impulses(dev, cfg: ti.template()):
    """``dev.impulse[i]`` = (A v' - b)_i at every particle in contact."""
    for i in range(dev.size[0]):
        if dev.contacts[i] != 0:
            dev.impulse[i] = apply_row(i, dev, cfg, dev.v) - dev.b[i]


@ti.func
def friction_row(i, dev, cfg: ti.template(), t):
    """Particle i's friction state, velocity correction and released contacts (time t, s)."""
    mask = dev.contacts[i]
    released = 0
    if mask != 0:
        x = dev.x[i]
        jump = dev.impulse[i]
        S = ti.Matrix.identity(cfg.real, 3)
        w = ti.Vector.zero(cfg.real, 3)
        bound = ti.cast(0, cfg.real)
        carrier = ti.Vector.zero(cfg.real, 3)
        found = False
        for kind, count, first in ti.static(cfg.colliders):
            for k in ti.static(range(count)):
                bit = ti.static(1 << (first + k))
                if mask & bit != 0:
                    _, n = kind.distance(dev, cfg, k, x, t)
                    s_new, w_new, e, ok = add_direction(S, w, n, ti.cast(0, cfg.real))
                    if ok:
                        S = s_new
                        normal = e.dot(jump)
                        if normal < 0:
                            released |= bit
                        else:
                            bound += mu(dev, kind, k) * normal
                        if not found:
                            carrier = velocity(dev, kind, k)
                            found = True
        v = dev.v[i]
        rel = S @ (v - carrier)
        speed = ti.sqrt(rel.dot(rel))
        fric = ti.Vector.zero(cfg.real, 3)
        stick = 0
        if released == 0 and bound > 0:
            if dev.stick[i] != 0:
                if STICK * dev.mass[i] * speed <= bound:
                    stick = 1
                    v = v - rel
                else:
                    fric = -bound / speed * rel
            else:
                applied = dev.fric[i]
                if applied.dot(applied) > 0:
                    if rel.dot(applied) >= 0 or STICK * dev.mass[i] * speed <= bound:  # overshot, or held
                        stick = 1
                        v = v - rel
                    else:
                        fric = -bound / speed * rel
                else:
                    limit = bound / dev.mass[i]
                    if speed <= limit:
                        stick = 1
                        v = v - rel
                    else:
                        v = v - limit / speed * rel
                        fric = -bound / speed * rel
        dev.v[i] = v
        dev.stick[i] = stick
        dev.fric[i] = fric
    dev.released[i] = released


@ti.func
def settle(dev, cfg: ti.template(), t):
    impulses(dev, cfg)
    for i in range(dev.size[0]):
        friction_row(i, dev, cfg, t)


@ti.kernel
def contact_friction(dev: ti.template(), cfg: ti.template(), t: ti.f64, serial: ti.template()):
    """Friction and released contacts after the solve of the step from time t (s); two
    loops (``serial``: serialised)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            settle(dev, cfg, ti.cast(t, cfg.real))
    else:
        settle(dev, cfg, ti.cast(t, cfg.real))


@ti.func
def gram_schmidt_adjoint(i, dev, cfg: ti.template(), x, t, normals, count, S, directions, gS, ge):
    """The transpose of the Jacobian of particle i's contact directions (f64): ``detect``
    and ``friction_row`` turn its contacts' normals n_k (at x, time t) into orthonormal
    directions e_k and the filter S = I - sum e_k e_k^T, one ``contact.add_direction``
    at a time (e = S n / |S n|, then S - e e^T). From gS (3x3) = dL/dS and the columns
    ge[:, j] = dL/de_j (j counting the contacts in order), back through each step in
    reverse (S before a step = S after it + e e^T; |S n| = e . n), returns dL/dx through
    each normal's curvature dn/dx. ``normals``, ``count``: ``contact.contact_normals`` at
    x; ``S``, ``directions``: ``contact.orthonormal`` of them."""
    g_normals = ti.Matrix.zero(ti.f64, 3, 3)
    g = gS
    for back in ti.static(range(3)):
        j = ti.static(2 - back)
        if j < count:
            n = column(normals, j)
            e = column(directions, j)
            S = S + e.outer_product(e)
            ge_j = column(ge, j) - (g + g.transpose()) @ e
            gm = (ge_j - e.dot(ge_j) * e) / e.dot(n)
            g = g + gm.outer_product(n)
            g_normals = set_column(g_normals, j, S @ gm)
    return normals_adjoint(i, dev, cfg, x, t, g_normals)


@ti.func
def friction_adjoint(i, dev, cfg: ti.template(), x, v_solved, g_new, g_fric, t):
    """The transpose of the Jacobian of ``friction_row`` at particle i (f64), its branch
    frozen as the step took it, from its inputs as they were (``dev.stick``, ``dev.fric``
    the step's start, ``dev.impulse`` J = A v' - b, ``v_solved`` v' the solve's velocity,
    x = x_n) given g_new = dL/dv'' of the velocity after it and g_fric = dL/dfric of the
    kinetic friction it hands to the next step. With rel = S (v' - v_c), r = rel / |rel|
    and the bound B = sum_k mu_k e_k . J: a particle that sticks gets v'' = v' - rel; one
    that slides hands on fric = -B r; in the first step of a contact, a sliding one also
    gets v'' = v' - (B / m) r. Returns (dL/dv', dL/dJ, dL/dx_n through the normals,
    dL/dm)."""
    mask = dev.contacts[i]
    jump = ti.cast(dev.impulse[i], ti.f64)
    normals, count = contact_normals(i, dev, cfg, x, t)
    S, directions = orthonormal(normals, count)
    carrier = ti.cast(first_carrier(i, dev, cfg), ti.f64)
    frictions = ti.Vector.zero(ti.f64, 3)  # mu_k by contact, in order
    bound = 0.0
    released = False
    slot = 0
    for kind, kinds, first in ti.static(cfg.colliders):
        for k in ti.static(range(kinds)):
            if mask & ti.static(1 << (first + k)) != 0:
                normal = column(directions, slot).dot(jump)
                coefficient = ti.cast(mu(dev, kind, k), ti.f64)
                if normal < 0:
                    released = True
                else:
                    bound += coefficient * normal
                for c in ti.static(range(3)):
                    if slot == c:
                        frictions[c] = coefficient
                slot += 1
    g_solved = g_new
    g_jump = ti.Vector.zero(ti.f64, 3)
    gx = ti.Vector.zero(ti.f64, 3)
    gm = 0.0
    if not released and bound > 0:
        mass = ti.cast(dev.mass[i], ti.f64)
        rel = S @ (v_solved - carrier)
        speed = ti.sqrt(rel.dot(rel))
        applied = ti.cast(dev.fric[i], ti.f64)
        sticks = False
        first_step = False
        if dev.stick[i] != 0:
            sticks = STICK * mass * speed <= bound
        elif applied.dot(applied) > 0:
            sticks = rel.dot(applied) >= 0 or STICK * mass * speed <= bound
        else:
            first_step = True
            sticks = speed <= bound / mass
        g_rel = ti.Vector.zero(ti.f64, 3)
        g_bound = 0.0
        if sticks:
            g_rel = -g_new
        else:
            r = rel / speed
            across = g_fric - r.dot(g_fric) * r
            g_rel = -bound / speed * across
            g_bound = -r.dot(g_fric)
            if first_step:
                across_new = g_new - r.dot(g_new) * r
                g_rel -= bound / (mass * speed) * across_new
                g_bound -= r.dot(g_new) / mass
                gm = bound / (mass * mass) * r.dot(g_new)
        g_solved += S @ g_rel
        g_directions = ti.Matrix.zero(ti.f64, 3, 3)
        for c in ti.static(range(3)):
            if c < count:
                g_jump += frictions[c] * g_bound * column(directions, c)
                g_directions = set_column(g_directions, c, frictions[c] * g_bound * jump)
        gx = gram_schmidt_adjoint(i, dev, cfg, x, t, normals, count, S, directions,
                                  g_rel.outer_product(v_solved - carrier), g_directions)
    return g_solved, g_jump, gx, gm


@ti.func
def first_carrier(i, dev, cfg: ti.template()):
    """The velocity (m/s) of the first collider particle i is in contact with (``detect``'s)."""
    mask = dev.contacts[i]
    out = ti.Vector.zero(cfg.real, 3)
    found = False
    for kind, count, first in ti.static(cfg.colliders):
        for k in ti.static(range(count)):
            if mask & ti.static(1 << (first + k)) != 0:
                if not found:
                    out = velocity(dev, kind, k)
                    found = True
    return out
