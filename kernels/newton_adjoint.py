"""The adjoint of a Newton-solved step (backward Euler, BDF2, implicit midpoint) at its
converged iterate, for ``massspring.gradients``.

Both steps solve (*) of ``kernels/newton.py``, g(u) = M (u - v_n) - h f(x_n + h u, u) = 0,
for u (backward Euler: u = v', h = dt; implicit midpoint: u = (v_n + v')/2, h = dt/2,
then v' = 2 u - v_n, x' = x_n + dt u). By the implicit function theorem, with the
residual's true Jacobian J = M - h D - h^2 K at (x_n + h u, u) (no definiteness fix:
it is the derivative of g, not the Newton iteration's operator):

    J mu = dL/du,   dL/du = dL/dv' + dt dL/dx'   (midpoint: 2 dL/dv' + dt dL/dx')
    dL/dx_n = dL/dx' + h K mu,   dL/dv_n = M mu   (midpoint: - dL/dv' too)
    dL/dtheta += h mu . df/dtheta at (x_n + h u, u),   dL/dm += -mu . (u - v_n - h g)
    dL/dvp += -(J^T mu)_p at a pin p (u = vp there), with each step's h dL/dx' + dL/dv'
    dL/dx_n += G,   dL/dv_n += ahead G   (G = h (df/dx*)^T mu: spring damping's direction
                                          at the prediction x* = x_n + ahead v_n; a pin's to dL/dvp)

BDF2 is backward Euler from the base (x^, v^) = (4/3 x_n - 1/3 x_{n-1}, 4/3 v_n - 1/3
v_{n-1}) with h = 2 dt / 3: the same adjoint gives dL/d(x^, v^), which ``bdf2_split``
shares between the two states before the step; the prediction's share G goes to
(x_n, v_n) directly (``newton_adjoint_gather``'s ``split``).

(free rows; mu = 0 at pins; K the force's whole x-derivative). J is the operator
refreshed without the definiteness fix (damping along the prediction's directions, as
the forward step has it: linear in u), symmetric. Without the fix J is the step's own
symmetric positive definite operator S and one CG solve gives mu. With it, J, where
compressed springs lose their transverse stiffness, may be indefinite: J mu = dL/du is
solved by preconditioned MINRES (``massspring.solvers.minres``) with the run's
preconditioner of S, each product
``jacobian_product``: S's product less what the fix added (``fix_difference``), so S
stays refreshed for the preconditioner. Where MINRES does not converge within
cg_max_iter iterations or stalls, ``massspring.support.errors.GradientError`` names the step.
``newton_adjoint_rhs`` sets up the solve, CG or MINRES solves it,
``newton_adjoint_gather`` does the rest (``forces.acceleration_adjoint`` with weights
h mu: at the converged iterate h f / m = u - v_n, so its masses' share is the one above).

With colliders (a backward-Euler step: BDF2 and the midpoint rule take one where a
particle touches a collider): the contacts the step
held are detected again from (x_n, v_n) (``contacts_again``) and held by every refresh
(``operator.HELD``); the adjoint solve runs on the free directions of the particles
in contact, and the contact and friction pieces are the linearised step's
(``implicit_adjoint``) with J in place of A and the impulses the residual's
constrained part at the converged iterate (kept with the history), where g is not 0
and h f / m = u - v_n fails: the masses' share gets what that identity missed.
"""

import taichi as ti

from .constraints import constrain, is_free, is_pinned, pin_adjoint, prescribed
from .cg import apply
from .contact import constraint_adjoint, detect
from .forces import acceleration_adjoint, spring_direction, spring_sum
from .friction import friction_adjoint
from .implicit_adjoint import position_adjoint, solved
from .newton import directions
from .operator import HELD, apply_row, refresh


@ti.func
def evaluation_point(dev, cfg: ti.template(), adj, i, slot, stride, h, midpoint: ti.template(),
                     wants: ti.template()):
    """(x^ + h u, u) of particle i from the history (slots ``slot`` and ``slot + 1``; x^ =
    x_n but for BDF2's base); a midpoint step's pin keeps its velocity u
    (``newton.midpoint_finish``). With colliders x' was moved onto surfaces after the
    solve, and with friction v' was changed: u is then the solve's velocity
    (``implicit_adjoint.solved``) and x^ + h u is formed from the base kept with the
    history (``adj.hb``)."""
    u = solved(adj, wants, slot, i)
    x = adj.hx[(slot + 1) * stride + i]
    if ti.static(midpoint):
        if ti.static(not wants.friction):  # (kept with friction: the solution w of (*) itself)
            if not is_pinned(i, dev, cfg):
                u = 0.5 * (adj.hv[slot * stride + i] + u)
        x = adj.hx[slot * stride + i] + h * u
    elif ti.static(cfg.has_colliders):  # the base x^ kept with the history: x^ + h u
        x = adj.hb[slot * stride + i] + h * u
    return x, u


@ti.func
def pin_columns(dev, cfg: ti.template()):
    """``dev.p`` = the prescribed velocities of the constrained directions (pins, contacts),
    0 elsewhere: a solve starts them there, so the operator's columns times them are
    added to b (``apply_row``) for the solve's start to take away again."""
    for i in range(dev.size[0]):
        dev.p[i] = ti.Vector.zero(cfg.real, 3)
        if not is_free(i, dev, cfg):
            dev.p[i] = prescribed(i, dev, cfg)


@ti.func
def solve_side(dev, cfg: ti.template(), h, t, values):
    """S, the operator of ``cfg``, refreshed at (``dev.x``, ``dev.v``) with the contacts
    held; ``dev.b`` = ``values`` on rows not pinned plus S's columns of the constrained
    directions times their prescribed velocities (``pin_columns``), 0 at pins."""
    refresh(dev, cfg, dev.x, dev.v, h, t, HELD)
    if ti.static(cfg.moving_pins or cfg.contact_filter):
        pin_columns(dev, cfg)
    for i in range(dev.size[0]):
        b = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            b = values[i]
            if ti.static(cfg.moving_pins or cfg.contact_filter):
                b += apply_row(i, dev, cfg, dev.p)
        dev.b[i] = b


@ti.func
def prediction(dev, cfg: ti.template(), adj, slot, ahead):
    """``adj.xs`` = x_n + ahead v_n from the history (a pin: its pin velocity), where the
    step's rate-dependent terms took their directions (``newton.lagged_directions``), and
    with ``cfg.lagged`` those directions in ``dev.lag`` for the operator."""
    stride = adj.stride[None]
    for i in range(dev.size[0]):
        v = adj.hv[slot * stride + i]
        if is_pinned(i, dev, cfg):
            v = ti.Vector.zero(ti.f64, 3)
            if ti.static(cfg.moving_pins):
                v = dev.pin_velocity[i]
        adj.xs[i] = adj.hx[slot * stride + i] + ahead * v
    if ti.static(cfg.lagged):
        directions(dev, cfg, adj.xs)


@ti.func
def contacts_again(dev, cfg: ti.template(), adj, slot, dt, t, wants: ti.template()):
    """The step's contacts detected again as ``newton.start`` detected them, from (x_n,
    v_n) in ``dev.xb``, ``dev.vb`` with the contact memory the step began with; the
    step's impulses (``adj.hj``) into ``dev.impulse``."""
    stride = adj.stride[None]
    for i in range(dev.size[0]):
        row = slot * stride + i
        dev.xb[i] = adj.hx[row]
        dev.vb[i] = adj.hv[row]
        dev.released[i] = adj.hr[row]
        if ti.static(wants.friction):
            dev.stick[i] = adj.hs[row]
            dev.fric[i] = adj.hf[row]
        dev.impulse[i] = adj.hj[row]
    for i in range(dev.size[0]):
        dev.carrier[i] = detect(i, dev, cfg, dev.xb, dev.vb, dt, t)


@ti.func
def rhs(dev, cfg: ti.template(), exact: ti.template(), adj, h, hx, dt, t, slot, midpoint: ti.template(),
        wants: ti.template(), ahead):
    n = dev.size[0]
    stride = adj.stride[None]
    prediction(dev, cfg, adj, slot, ahead)
    if ti.static(cfg.contact_filter):
        contacts_again(dev, cfg, adj, slot, dt, t, wants)
    for i in range(n):
        x, u = evaluation_point(dev, cfg, adj, i, slot, stride, h, midpoint, wants)
        dev.x[i] = x
        dev.v[i] = u
        if ti.static(wants.pins):
            pin_adjoint(i, dev, cfg, adj, hx)
        gy = adj.lx[i]
        if ti.static(cfg.has_colliders):
            if not is_pinned(i, dev, cfg):
                xb = adj.hb[slot * stride + i]
                if ti.static(midpoint):  # x' = x_n + dt w = (x_n + h v_n) + h v'
                    xb = adj.hx[slot * stride + i] + h * adj.hv[slot * stride + i]
                gy, gx = position_adjoint(i, dev, cfg, adj, slot, xb, h, t, dt)
                adj.lx[i] = gx
        b = adj.lv[i] + hx * gy
        if ti.static(midpoint):
            b += adj.lv[i]
        if ti.static(wants.friction):
            adj.cj[i] = ti.Vector.zero(ti.f64, 3)
            if dev.contacts[i] != 0:  # v'' = friction_row(u, J): back to u and J
                gv, gj, gx, gm = friction_adjoint(i, dev, cfg, dev.xb[i], u, b, adj.gf[i], t)
                b = gv
                adj.cj[i] = gj
                adj.lx[i] = adj.lx[i] + gx
                if ti.static(wants.masses):
                    adj.gm[i] = adj.gm[i] + gm
        adj.jy[i] = b
    if ti.static(wants.friction):  # J = g(u): dL/dJ's share of dL/du through the true Jacobian
        refresh(dev, exact, dev.x, dev.v, h, t, HELD)
        for i in range(n):
            if not is_pinned(i, dev, cfg):
                adj.jy[i] = adj.jy[i] + apply_row(i, dev, exact, adj.cj)
    if ti.static(cfg.contact_filter):
        for i in range(n):
            adj.cg[i] = adj.jy[i]
    solve_side(dev, cfg, h, t, adj.jy)
    for i in range(n):
        dev.v[i] = adj.mu[i]


@ti.kernel
def newton_adjoint_rhs(dev: ti.template(), cfg: ti.template(), exact: ti.template(), adj: ti.template(), h: ti.f64,
                       hx: ti.f64, dt: ti.f64, t: ti.f64, slot: ti.i32, midpoint: ti.template(), wants: ti.template(),
                       ahead: ti.f64, serial: ti.template()):
    """The step's prediction x_n + ``ahead`` v_n (``prediction``);
    ``dev.x``, ``dev.v`` = the converged iterate's (x_n + h u, u) from the history; the
    pins' share of the pin velocities' gradient (``wants.pins``); the operator refreshed
    there (``cfg``: the step's own, with its definiteness fix: S); ``dev.b`` = dL/du =
    dL/dv' + hx dL/dx' on rows not pinned (hx: x' moves by hx u from the base: dt, or
    BDF2's 2 dt / 3; plus S's columns of the constrained directions times their
    prescribed velocities, which the solve's start subtracts again); ``dev.v`` = the last
    adjoint solution ``adj.mu`` (the warm start). With colliders (backward Euler), the
    step's contacts detected again (``contacts_again``), dL/dx' taken back through the
    final projection and landing first, and with friction back through
    ``friction.friction_adjoint`` (its dL/dJ through ``exact``, the true Jacobian, into
    dL/du); dL/du at a particle in contact kept in ``adj.cg``."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            rhs(dev, cfg, exact, adj, h, hx, dt, t, slot, midpoint, wants, ahead)
    else:
        rhs(dev, cfg, exact, adj, h, hx, dt, t, slot, midpoint, wants, ahead)


@ti.func
def fix_difference(dev, cfg: ti.template(), h):
    """``dev.q`` -= S_i ((S - J) p)_i for p in ``dev.p`` (filtered), rows not pinned: after
    ``dev.q`` = S p (S the step's operator, refreshed with the definiteness fix at the
    positions ``dev.x``), ``dev.q`` = J p, J the same operator without the fix. S - J is
    each spring term's block with the fix less the one without (``coefficients``: k c (I
    - n n^T) for a compressed spring, c = l0/l - 1 > 0, zero elsewhere), so J p costs a
    product with S and a pass over the springs, and S stays in place for the
    preconditioner. Each particle gathers its own entries: the same bits for any thread
    count."""
    step = ti.cast(h, cfg.real)
    for i in range(dev.size[0]):
        out = ti.Vector.zero(cfg.real, 3)
        if ti.static(cfg.has_springs):
            if not is_pinned(i, dev, cfg):
                for e in range(dev.offsets[i], dev.offsets[i + 1]):
                    s = dev.entry[e]
                    if s < 0:
                        s = -1 - s
                    n, length = spring_direction(dev.x[dev.other[e]] - dev.x[i], cfg.real)
                    da = ti.cast(0, cfg.real)
                    db = ti.cast(0, cfg.real)
                    for term in ti.static(cfg.spring_terms):
                        if ti.static(not (cfg.lagged and term.rate_dependent)):  # along m: no fix
                            fa, fb = term.coefficients(s, dev, n, length, step, True)
                            ea, eb = term.coefficients(s, dev, n, length, step, False)
                            da += fa - ea
                            db += fb - eb
                    dp = dev.p[i] - dev.p[dev.other[e]]
                    out += da * dp + db * n * n.dot(dp)
        dev.q[i] -= constrain(i, dev, cfg, out)


@ti.kernel
def jacobian_product(dev: ti.template(), cfg: ti.template(), h: ti.f64, y: ti.types.ndarray(dtype=ti.f64, ndim=2),
                     out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    """out = J y for y (n, 3) on the free directions (``integrators/newton.py``'s MINRES):
    ``cg.apply``'s S y through ``dev.p``, ``dev.q``, then ``fix_difference``; filtered."""
    for i in range(dev.size[0]):
        dev.p[i] = ti.Vector([ti.cast(y[i, c], cfg.real) for c in ti.static(range(3))])
    apply(dev, cfg)
    fix_difference(dev, cfg, h)
    for i in range(dev.size[0]):
        for c in ti.static(range(3)):
            out[i, c] = ti.cast(dev.q[i][c], ti.f64)


@ti.func
def gather(dev, cfg: ti.template(), adj, h, t, slot, midpoint: ti.template(), wants: ti.template(), ahead,
           split: ti.template()):
    n = dev.size[0]
    stride = adj.stride[None]
    for i in range(n):
        mu = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            mu = constrain(i, dev, cfg, dev.v[i])
        adj.mu[i] = mu
        if ti.static(wants.friction):  # the parameters' and state's shares: mu - dL/dJ (J = g(u))
            mu -= adj.cj[i]
        adj.y[i] = mu
        adj.w[i] = h * dev.mass[i] * mu  # dL/da: f / m enters g as h f / m per unit mass
        _, u = evaluation_point(dev, cfg, adj, i, slot, stride, h, midpoint, wants)
        adj.ue[i] = u
    if ti.static(wants.pins or cfg.contact_filter):  # J's coefficients (a solve may have left S's)
        refresh(dev, cfg, dev.x, adj.ue, h, t, HELD)
    if ti.static(wants.pins):  # u = vp at a pin: -(J^T mu)_p, mu = 0 at pins (module docstring)
        for i in range(n):
            if is_pinned(i, dev, cfg):
                adj.gp[i] = adj.gp[i] - apply_row(i, dev, cfg, adj.y)
    acceleration_adjoint(dev, cfg, adj, dev.x, adj.ue, wants, adj.xs, cfg.lagged or wants.rate_gradient)
    for i in range(n):
        lx = adj.lx[i] + adj.px[i]
        if ti.static(cfg.has_springs):
            lx -= spring_sum(i, dev, adj.sx)
        lv = ti.Vector.zero(ti.f64, 3)
        if not is_pinned(i, dev, cfg):
            lv = dev.mass[i] * adj.y[i]
            if ti.static(midpoint):
                lv -= adj.lv[i]
        if ti.static(cfg.contact_filter):
            if dev.contacts[i] != 0:
                u = adj.ue[i]
                unsettled = adj.cg[i] - apply_row(i, dev, cfg, adj.mu)
                cx, cv = constraint_adjoint(i, dev, cfg, dev.xb[i], dev.vb[i], u, adj.mu[i], unsettled,
                                            dev.impulse[i], t)
                lx += cx
                lv += cv
                if ti.static(wants.masses and wants.friction):
                    # -(mu - dL/dJ) . dg/dm beyond acceleration_adjoint's share, which takes
                    # g / m = u - v_n - h a: -(mu - dL/dJ) . (g without friction) / m, g = J here
                    # (mu . J = 0) less its friction (a sticking particle's STICK m (u - v_c),
                    # whose own m-derivative cancels it; a sliding one's -fric)
                    extra = adj.cj[i].dot(dev.impulse[i]) / dev.mass[i]
                    if dev.stick[i] == 0:
                        extra -= adj.y[i].dot(dev.fric[i]) / dev.mass[i]
                    adj.gm[i] = adj.gm[i] + extra
        if ti.static(wants.friction):  # a sliding particle's kinetic friction in g came from the step before
            gf = ti.Vector.zero(ti.f64, 3)
            if dev.contacts[i] != 0 and dev.stick[i] == 0:
                gf = adj.y[i]
            adj.gf[i] = gf
        if ti.static(cfg.lagged):  # x* = x_n + ahead v_n: straight to the state before the step
            ox = -spring_sum(i, dev, adj.sl)
            ov = ahead * ox
            if is_pinned(i, dev, cfg):
                if ti.static(wants.pins):
                    adj.gp[i] = adj.gp[i] + ov
                ov = ti.Vector.zero(ti.f64, 3)
            if ti.static(split):
                adj.ox[i] = ox
                adj.ov[i] = ov
            else:
                lx += ox
                lv += ov
        adj.lx[i] = lx
        adj.lv[i] = lv


@ti.kernel
def newton_adjoint_gather(dev: ti.template(), cfg: ti.template(), adj: ti.template(), h: ti.f64, t: ti.f64, slot: ti.i32,
                          midpoint: ti.template(), wants: ti.template(), ahead: ti.f64, split: ti.template(),
                          serial: ti.template()):
    """After the adjoint solve (mu in ``dev.v``): dL/dx_n, dL/dv_n into ``adj.lx``,
    ``adj.lv``, mu kept in ``adj.mu`` (the next solve's warm start), the parameters'
    shares added (module docstring); with ``split`` (BDF2, whose ``adj.lx``, ``adj.lv``
    are then its base's), the prediction's share kept in ``adj.ox``, ``adj.ov`` for
    ``bdf2_split``."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            gather(dev, cfg, adj, h, t, slot, midpoint, wants, ahead, split)
    else:
        gather(dev, cfg, adj, h, t, slot, midpoint, wants, ahead, split)


@ti.kernel
def bdf2_split(dev: ti.template(), cfg: ti.template(), adj: ti.template(), history: ti.i32, third: ti.f64,
               wants: ti.template(), variable: ti.template(), now: ti.f64, before: ti.f64):
    """After a BDF2 step's adjoint, whose ``adj.lx``, ``adj.lv`` hold dL/d(x^, v^) of its
    base: with ``history`` (the step used x^ = (4 x_n - x_{n-1}) / 3, v^ likewise), 4/3 of
    it goes to the state before the step and -1/3 to the one before that, kept in
    ``adj.kx``, ``adj.kv`` until the backward pass reaches it; without (a backward-Euler
    step), all to the state before. The share kept for x_n by the step after is added
    either way. A pin's base is x_n moved by ``third`` = dt / 3 times its velocity: all of
    it to x_n, and ``third`` dL/dx^ to its velocity's gradient (``wants.pins``).
    ``variable`` (a replayed run's steps, ``kernels/newton.py``'s ``start``): the base is
    ``now`` x_n - ``before`` x_{n-1}, with now = (1 + omega)^2 / (1 + 2 omega), before =
    omega^2 / (1 + 2 omega) and ``third`` = dt omega / (1 + 2 omega) for the step ratio omega."""
    for i in range(dev.size[0]):
        lx = adj.lx[i]
        lv = adj.lv[i]
        kx = ti.Vector.zero(ti.f64, 3)
        kv = ti.Vector.zero(ti.f64, 3)
        if history != 0:
            if not is_pinned(i, dev, cfg):
                if ti.static(variable):
                    kx = -before * lx
                    kv = -before * lv
                    lx = now * lx
                    lv = now * lv
                else:
                    kx = -lx / 3
                    kv = -lv / 3
                    lx = 4 * lx / 3
                    lv = 4 * lv / 3
            elif ti.static(wants.pins):
                adj.gp[i] = adj.gp[i] + third * lx
        if ti.static(cfg.lagged):
            lx += adj.ox[i]
            lv += adj.ov[i]
        adj.lx[i] = lx + adj.kx[i]
        adj.lv[i] = lv + adj.kv[i]
        adj.kx[i] = kx
        adj.kv[i] = kv
