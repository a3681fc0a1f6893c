"""Newton's method for the nonlinear implicit steps (``massspring/integrators/newton.py``).

Backward Euler, BDF2 and implicit midpoint all solve, for a velocity v,

    g(v) = M (v - v^) - h f(x^ + h v, v) - F(v) = 0                       (*)

with a base state (x^, v^) and a step h: (x_n, v_n) and dt for backward Euler,
(4/3 x_n - 1/3 x_{n-1}, 4/3 v_n - 1/3 v_{n-1}) and 2 dt / 3 for BDF2, (x_n, v_n) and
dt / 2 for implicit midpoint, whose v is the midpoint velocity (v_n + v_{n+1}) / 2
(``midpoint_finish`` makes the step from it); F is the
friction of contacts (linear in v, ``contact.friction_diagonal``, ``friction_impulse``),
and the directions prescribed by pins and contacts are held (contacts detected once,
at the step's start, as the linearised step detects them). Newton starts from v = v^;
each iteration refreshes the operator at the iterate (``operator.refresh`` in
``NEWTON`` mode: A = M - h D - h^2 K at x = x^ + h v, and b = A v - g(v)), so the
CG solve of A v' = b (warm-started from v) gives the Newton iterate v'.

(*) is the stationarity of the incremental potential

    E(v) = 1/2 (v - v^)^T M (v - v^) + U(x^ + h v) + h Psi(v) + 1/2 v^T C v - v^T F_0

(U: the terms' potential energy, ``potential_change``; Psi: their Rayleigh
dissipation, ``dissipation_change``, along the directions m below;
C, F_0: friction's damper and impulse), whose gradient is g. That holds because the
rate-dependent spring terms (damping, ``cfg.lagged``) act along each spring's direction
m at the step's prediction x_n + ``ahead`` v_n (``lagged_directions``: ``ahead`` = dt
for backward Euler and BDF2, dt / 2 for midpoint, so x_n + ahead v_n is within O(dt^2)
of where f is evaluated and the orders are kept): Psi = 1/2 kd (m . (v_j - v_i))^2 with
m fixed through the step. Along the iterate's own direction the damping force turns
with its spring and g has no potential (no line search could then be trusted: a cloth
with damping 1e9 at dt 1 s ran away). The operator carries m as a second direction in
each spring's block (``operator.entry_block``), so Newton's linear model is exact for
damping. ``newton_trial`` gives
E(v + a d) - E(v) for the line search, each element's change computed from the
difference of its lengths and velocities (not as a difference of two energies), so
it keeps its relative precision when the change is tiny.

Two drivers run the iteration with the same arithmetic: ``BackwardEuler._newton``
(``massspring/integrators/newton.py``) from Python, one launch per phase
(``newton_refresh``, the CG solve, ``newton_direction``, each ``newton_trial``), and
``newton_solve``, the whole iteration in one launch with serial loops (small systems
with a pointwise preconditioner, once a run has made enough tries to pay for its
compile).

Fields (n particles, vec3 in the run's precision; m springs): ``lag`` (m,) and
``lag_coef`` (2m, adjacency order) 4-vectors (m, c), c = h kd the damping block's
coefficient (``cfg.lagged``); ``xb``, ``vb`` (x^, v^), ``xk``,
``vk`` (the iterate's positions and velocity), ``dir`` (the Newton direction d =
v' - v), ``res`` (g at the iterate, filtered); with colliders ``carrier`` (the
velocity of the collider each particle touches, from ``contact.detect``); BDF2's
``xo``, ``vo`` (x_{n-1}, v_{n-1}).
"""

import taichi as ti

from .blocks import BLOCK, block_count, block_end, ordered_sum
from .cg import CONVERGED, NONFINITE, REASONS as CG_REASONS, serial_solve
from .constraints import constrain, is_free, is_pinned, prescribed
from .contact import detect, friction_diagonal, friction_impulse
from .forces import spring_direction, tiny_length
from .operator import NEWTON, refresh
from .divergence import is_finite
from .terms import uniform_acceleration

ARMIJO = 1e-4  # sufficient decrease: E(v + a d) - E(v) <= ARMIJO a g . d
MAX_CUTS = 12  # halvings of a line search before it takes the shortest step tried
ETA_FIRST = 1e-2  # CG tolerance of the first linear solve of a step (relative to its first residual)
ETA_MAX = 0.1  # loosest CG tolerance of a later solve
GOLDEN = (1 + 5**0.5) / 2  # safeguard exponent of Eisenstat and Walker's first choice
MAX_NEWTON = len(CG_REASONS)  # reason code: the Newton iteration limit came first
REASONS = CG_REASONS + ("max_newton",)


@ti.func
def start(dev, cfg: ti.template(), dt, t, bdf2: ti.template(), variable: ti.template(), omega):
    """The base state (x^, v^) of the step from (x_n, v_n) = (``dev.x``, ``dev.keep``) at
    time t; contacts detected from (x_n, v_n) as the linearised step detects them
    (``contact.detect``, step dt); the iterate v = v^ with the prescribed directions set.
    BDF2's base: (4 x_n - x_{n-1}) / 3; ``variable`` (an error-controlled run's), with the
    step ratio omega = dt / (the step before's): ((1 + omega)^2 x_n - omega^2 x_{n-1}) / (1 + 2 omega).
    Returns the number of particles in contact."""
    touching = 0
    for i in range(dev.size[0]):
        xb = dev.x[i]
        vb = dev.keep[i]  # v_n, also when dev.v holds a base already
        if ti.static(bdf2 and not variable):
            xb = (4 * dev.x[i] - dev.xo[i]) / 3
            vb = (4 * dev.keep[i] - dev.vo[i]) / 3
            if is_pinned(i, dev, cfg):  # a pin moves by dt times its velocity: x' = xb + 2/3 dt v' (a still
                xb = dev.x[i] + dt / 3 * prescribed(i, dev, cfg)  # pin's xb is x_n exactly, as the adjoint has it)
        if ti.static(bdf2 and variable):
            now = (1 + omega) * (1 + omega)
            before = omega * omega
            den = 1 + 2 * omega
            xb = (now * dev.x[i] - before * dev.xo[i]) / den
            vb = (now * dev.keep[i] - before * dev.vo[i]) / den
            if is_pinned(i, dev, cfg):
                xb = dev.x[i] + dt * omega / den * prescribed(i, dev, cfg)
        dev.xb[i] = xb
        dev.vb[i] = vb
        if ti.static(cfg.contact_filter):
            dev.carrier[i] = detect(i, dev, cfg, dev.x, dev.keep, dt, t)
            if dev.contacts[i] != 0:
                touching += 1
        if not is_free(i, dev, cfg):
            vb = constrain(i, dev, cfg, vb) + prescribed(i, dev, cfg)
        dev.v[i] = vb
    return touching


@ti.kernel
def newton_start(dev: ti.template(), cfg: ti.template(), dt: ti.f64, t: ti.f64, bdf2: ti.template(),
                 variable: ti.template(), omega: ti.f64, serial: ti.template()) -> ti.i32:
    """``start`` of a step of size dt (s) at time t (s); ``bdf2``: BDF2's base, ``variable``
    with the step ratio ``omega``. Returns the number of particles in contact."""
    step = ti.cast(dt, cfg.real)
    now = ti.cast(t, cfg.real)
    ratio = ti.cast(omega, cfg.real)
    out = 0
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            touching = start(dev, cfg, step, now, bdf2, variable, ratio)
            out = touching
    else:
        touching = start(dev, cfg, step, now, bdf2, variable, ratio)
        out = touching
    return out


@ti.func
def residual_sums(dev, cfg: ti.template(), h):
    """(||S g||^2, a round-off scale of g squared): the scale sums per particle
    m (|v| + |v^|) + h m |u| (u: the sum of the uniform accelerations,
    ``terms.uniform_acceleration``) + (|a| + |b|) l / h over its springs (about h ks l: a
    tension ks (l - l0) is the difference of terms that large), the size of the terms
    whose difference g is."""
    n = dev.size[0]
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            scale = dev.mass[i] * (dev.v[i].norm() + dev.vb[i].norm())
            if ti.static(cfg.has_springs):
                for e in range(dev.offsets[i], dev.offsets[i + 1]):
                    c = dev.coef[e]
                    length = (dev.xk[dev.other[e]] - dev.xk[i]).norm()
                    size = ti.abs(c[3]) + ti.abs(c[4])
                    if ti.static(cfg.lagged):
                        size += ti.abs(dev.lag_coef[e][3])
                    scale += size * length / h
            if ti.static(cfg.has_uniform):
                scale += h * dev.mass[i] * ti.cast(uniform_acceleration(dev, cfg), cfg.real).norm()
            r = ti.cast(dev.res[i], ti.f64)
            acc += ti.Vector([r.dot(r), ti.cast(scale, ti.f64) ** 2, 0.0], ti.f64)
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.func
def directions(dev, cfg: ti.template(), xs):
    """``dev.lag[s]``'s direction m: spring s's unit vector at the positions ``xs`` (m = 0
    where it has no length there)."""
    for s in range(dev.size[1]):
        i = dev.ends[s][0]
        j = dev.ends[s][1]
        m, _ = spring_direction(xs[j] - xs[i], cfg.real)
        dev.lag[s] = ti.Vector([m[0], m[1], m[2], 0], cfg.real)


@ti.func
def lagged_directions(dev, cfg: ti.template(), ahead):
    """The directions of ``cfg.lagged``'s rate-dependent terms through a step: the
    springs' at its prediction x_n + ``ahead`` v_n (a pin: x_n + ahead times its pin
    velocity), held in ``dev.xk`` until the first refresh."""
    for i in range(dev.size[0]):
        v = dev.keep[i]
        if is_pinned(i, dev, cfg):
            v = ti.Vector.zero(cfg.real, 3)
            if ti.static(cfg.moving_pins):
                v = dev.pin_velocity[i]
        dev.xk[i] = dev.x[i] + ahead * v
    directions(dev, cfg, dev.xk)


@ti.kernel
def newton_lag(dev: ti.template(), cfg: ti.template(), ahead: ti.f64, serial: ti.template()):
    """``lagged_directions`` at x_n + ``ahead`` v_n (``ahead`` in s), once a step, before its
    first refresh (``serial``: in one thread, as ``newton_start``)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            lagged_directions(dev, cfg, ti.cast(ahead, cfg.real))
    else:
        lagged_directions(dev, cfg, ti.cast(ahead, cfg.real))


@ti.func
def iterate(dev, cfg: ti.template(), h, t):
    n = dev.size[0]
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            step = ti.cast(dev.v[i] - dev.vk[i], ti.f64)
            change = ti.cast(dev.v[i] - dev.vb[i], ti.f64)
            m = ti.cast(dev.mass[i], ti.f64)
            acc += ti.Vector([m * step.dot(step), m * change.dot(change), 0.0], ti.f64)
        dev.partial[blk] = acc
    sizes = ordered_sum(dev.partial, block_count(n))
    for i in range(n):
        dev.vk[i] = dev.v[i]
        dev.xk[i] = dev.xb[i] + h * dev.v[i]
    refresh(dev, cfg, dev.xk, dev.v, h, t, NEWTON)
    sums = residual_sums(dev, cfg, h)
    return ti.Vector([sums[0], sums[1], sizes[0], sizes[1]], ti.f64)


@ti.kernel
def newton_refresh(dev: ti.template(), cfg: ti.template(), h: ti.f64, t: ti.f64,
                   serial: ti.template()) -> ti.types.vector(4, ti.f64):
    """At the iterate v = ``dev.v``: v_k = v, x_k = x^ + h v, the operator and b of
    Newton's linear system, g(v) in ``dev.res``. Returns (``residual_sums``, then
    ||v - v_k||_M^2 with the v_k of the last call (the step just taken) and
    ||v - v^||_M^2 (the step's velocity change), in kg m^2/s^2)."""
    hh = ti.cast(h, cfg.real)
    now = ti.cast(t, cfg.real)
    out = ti.Vector.zero(ti.f64, 4)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            sums = iterate(dev, cfg, hh, now)
            for k in ti.static(range(4)):
                out[k] = sums[k]
    else:
        sums = iterate(dev, cfg, hh, now)
        for k in ti.static(range(4)):
            out[k] = sums[k]
    return out


@ti.func
def spring_change(s, dev, cfg: ti.template(), h, alpha):
    """Spring s's change of U + h Psi from the iterate (``xk``, ``vk``) to (x^ + h v, v),
    v = v_k + alpha d (its ends' displacement h alpha (d_j - d_i), not a difference of v's)."""
    out = ti.cast(0, cfg.real)
    i = dev.ends[s][0]
    j = dev.ends[s][1]
    old = dev.xk[j] - dev.xk[i]
    step = h * alpha * (dev.dir[j] - dev.dir[i])
    new = old + step
    _, old_length = spring_direction(old, cfg.real)
    _, new_length = spring_direction(new, cfg.real)
    change = ti.cast(0, cfg.real)
    if old_length + new_length > tiny_length(cfg.real):
        change = step.dot(old + new) / (old_length + new_length)  # l' - l without cancellation
    for term in ti.static(cfg.spring_terms):
        out += term.potential_change(s, dev, old_length, new_length, change)
        if ti.static(term.rate_dependent):
            lag = dev.lag[s]
            m = ti.Vector([lag[0], lag[1], lag[2]], cfg.real)
            out += h * term.dissipation_change(s, dev, m, dev.vk[j] - dev.vk[i], dev.v[j] - dev.v[i])
    return out


@ti.func
def particle_change(i, dev, cfg: ti.template(), h, alpha):
    """Particle i's change of inertia, particle terms' U + h Psi and friction from ``vk`` to
    v = v_k + alpha d (dv = alpha d, not v - v_k)."""
    v = dev.v[i]
    w = dev.vk[i]
    dv = alpha * dev.dir[i]
    out = 0.5 * dev.mass[i] * dv.dot(v + w - 2 * dev.vb[i])
    for term in ti.static(cfg.particle_terms):
        out += term.potential_change(i, dev, h * dv)
        out += h * term.dissipation_change(i, dev, w, v)
    if ti.static(cfg.contact_filter):
        out += 0.5 * friction_diagonal(i, dev, cfg) * dv.dot(v + w)
        out -= friction_impulse(i, dev, cfg, dev.carrier[i]).dot(dv)
    return out


@ti.func
def trial(dev, cfg: ti.template(), h, alpha):
    """v = v_k + alpha d; returns (E(v) - E(v_k), g(v_k) . d)."""
    n = dev.size[0]
    for i in range(n):
        dev.v[i] = dev.vk[i] + alpha * dev.dir[i]
    if ti.static(cfg.has_springs):
        for s in range(dev.size[1]):
            dev.fs[s] = ti.Vector([spring_change(s, dev, cfg, h, alpha), 0, 0], cfg.real)  # fs is scratch here
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            change = ti.cast(particle_change(i, dev, cfg, h, alpha), ti.f64)
            if ti.static(cfg.has_springs):
                for e in range(dev.offsets[i], dev.offsets[i + 1]):
                    s = dev.entry[e]
                    if s >= 0:  # each spring once, at its first end
                        change += ti.cast(dev.fs[s][0], ti.f64)
            slope = ti.cast(dev.res[i], ti.f64).dot(ti.cast(dev.dir[i], ti.f64))
            acc += ti.Vector([change, slope, 0.0], ti.f64)
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))


@ti.kernel
def newton_direction(dev: ti.template(), cfg: ti.template(), serial: ti.template()):
    """``direction`` (``serial``: in one thread, as ``newton_start``)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            direction(dev, cfg)
    else:
        direction(dev, cfg)


@ti.func
def direction(dev, cfg: ti.template()):
    """d = S (v' - v_k) after the linear solve (``dev.v`` = v'): the prescribed directions,
    which v' and v_k both hold at their prescribed velocities, projected out of d, so that
    their round-off (eps |v|) neither moves them nor enters the line search's slope and
    change (a contact's normal carries the impulse's large share of g)."""
    for i in range(dev.size[0]):
        d = dev.v[i] - dev.vk[i]
        if not is_free(i, dev, cfg):
            d = constrain(i, dev, cfg, d)
        dev.dir[i] = d


@ti.kernel
def newton_trial(dev: ti.template(), cfg: ti.template(), h: ti.f64, alpha: ti.f64,
                 serial: ti.template()) -> ti.types.vector(3, ti.f64):
    """``trial``: v = v_k + alpha d; returns (E(v) - E(v_k) in J, g(v_k) . d, 0)."""
    hh = ti.cast(h, cfg.real)
    a = ti.cast(alpha, cfg.real)
    out = ti.Vector.zero(ti.f64, 3)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            sums = trial(dev, cfg, hh, a)
            for k in ti.static(range(3)):
                out[k] = sums[k]
    else:
        sums = trial(dev, cfg, hh, a)
        for k in ti.static(range(3)):
            out[k] = sums[k]
    return out


@ti.kernel
def newton_solve(dev: ti.template(), cfg: ti.template(), h: ti.f64, t: ti.f64, roundoff: ti.f64, cg_tol: ti.f64,
                 newton_tol: ti.f64, cg_max_iter: ti.i32, newton_max_iter: ti.i32,
                 log: ti.types.ndarray(dtype=ti.f64, ndim=2)) -> ti.types.vector(6, ti.f64):
    """Newton's iteration for (*) with step h (s) at time t (s), from the base and the
    directions ``newton_start`` and ``newton_lag`` set, in one launch with serial loops:
    the loop ``BackwardEuler.advance`` (``massspring/integrators/newton.py``) drives from
    Python with one launch per phase, the same arithmetic, for pointwise preconditioners
    on small systems.

    ``roundoff``: ROUNDOFF eps of the run's precision (the floors of CG and of ||g||);
    ``cg_tol``, ``newton_tol``, ``cg_max_iter``, ``newton_max_iter``: the options.
    ``log`` (at least newton_max_iter + 1 rows, 2 columns) gets ||S g|| at each iterate
    (column 0, row k: after k solves) and each solve's CG iterations (column 1).
    Returns (solves, CG iterations in all, line-search cuts, reason code (``REASONS``),
    the last solve's relative residual (0 without one), ||S g|| at the warm start)."""
    hh = ti.cast(h, cfg.real)
    now = ti.cast(t, cfg.real)
    out = ti.Vector.zero(ti.f64, 6)
    ti.loop_config(serialize=True)
    for _ in range(1):
        solves = 0
        total = 0
        cuts = 0
        tried = 0
        reason = CONVERGED
        last_code = CONVERGED
        last_residual = 0.0
        previous = 0.0
        predicted = 0.0
        eta = ETA_FIRST
        cut = False
        floor = 0.0
        first = 0.0
        norm = 0.0
        broken = False  # a solve's right-hand side or residual overflowed
        while True:
            sums = iterate(dev, cfg, hh, now)
            norm = ti.sqrt(sums[0])
            log[solves, 0] = norm
            floor = ti.max(floor, roundoff * ti.sqrt(sums[1]))
            if solves == 0:
                first = norm
            elif tried == 0 and sums[2] <= newton_tol * newton_tol * sums[3]:
                if sums[2] == 0.0 and last_code != CONVERGED:
                    reason = last_code  # CG could not move v (indefinite, stalled): nor can Newton
                break  # a full Newton step this small: what is left is smaller still
            if not is_finite(norm) or norm <= floor:
                break
            if solves >= newton_max_iter:
                reason = MAX_NEWTON
                break
            if solves > 0:
                safeguard = ti.pow(eta, GOLDEN)
                eta = ti.abs(norm - predicted) / previous  # how far the linear model missed
                if safeguard > 0.1:
                    eta = ti.max(eta, safeguard)
            if cut:  # a line search has cut a step: loose solves' directions are not to be trusted
                eta = cg_tol
            eta = ti.min(ti.max(eta, cg_tol), ETA_MAX)
            result = serial_solve(dev, cfg, eta, roundoff, cg_max_iter)
            iterations = ti.cast(result[0], ti.i32)
            log[solves, 1] = result[0]
            solves += 1
            total += iterations
            last_residual = result[1]
            last_code = ti.cast(result[2], ti.i32)
            predicted = result[1] * result[3]  # ||g|| the linear model predicts
            if last_code == NONFINITE:
                broken = True
                break
            direction(dev, cfg)
            alpha = 1.0
            tried = 0
            while True:
                change = trial(dev, cfg, hh, ti.cast(alpha, cfg.real))
                if change[0] <= ARMIJO * alpha * change[1] or tried == MAX_CUTS or not is_finite(change[0]):
                    break
                alpha *= 0.5
                tried += 1
            cuts += tried
            cut = cut or tried > 0
            previous = norm
        if broken or not is_finite(norm):
            reason = NONFINITE
        out = ti.Vector([solves, total, cuts, reason, last_residual, first], ti.f64)
    return out


@ti.kernel
def midpoint_finish(dev: ti.template(), cfg: ti.template(), h: ti.f64):
    """Implicit midpoint's step from the solution w = ``dev.v`` of (*) with h = dt / 2 and
    the base (x_n, v_n): v' = 2 w - v_n (v_n = ``dev.keep``) and x^ = x_n + h v_n in
    ``dev.xb``, so that x' = x^ + h v' = x_n + dt w (``cg.advance_positions``). A pin
    moves with its velocity w and keeps it (x^ = x_n + h w; the same while w = v_n, which
    keyframed pins change between steps)."""
    hh = ti.cast(h, cfg.real)
    for i in range(dev.size[0]):
        if is_pinned(i, dev, cfg):
            dev.xb[i] = dev.xb[i] + hh * dev.v[i]
        else:
            dev.xb[i] = dev.xb[i] + hh * dev.keep[i]
            dev.v[i] = 2 * dev.v[i] - dev.keep[i]
