"""Contact with colliders (``massspring.model.colliders``): their geometry, the response of the
explicit integrators after a step, and the contact constraints of the implicit step.

Geometry. Each collider kind is a class of ``ti.func``s with its arrays
``dev.<kind>_<field>`` (one item per collider of that kind: ``plane_point``,
``plane_normal``, ``sphere_center``, ``sphere_radius``, ``box_lower``, ``box_upper``,
and for every kind ``_velocity`` (m/s), ``_friction``, ``_restitution``).
``cfg.colliders`` lists the kinds a model has as (kind, count, first)
(``massspring.model.colliders.collider_groups``: each collider class names its kind class
here as ``kernel``), ``first``
numbering its colliders among all of the model's (their bits in the implicit step's
per-particle masks); the kernels unroll both loops (``ti.static``), so a model without
colliders compiles none of this. ``distance(dev, cfg, k, x, t)`` is the signed
distance d (m, negative inside) of point x from collider k at time t (s), whose
geometry has moved by velocity * t, and the outward unit normal n at the nearest
surface point.

Explicit, symplectic and RK4 (``respond``, fused into the per-particle update after
the free step x0 -> (x, v) ending at time t): for each collider in turn, if the
particle touches it (d <= 0, to within ``forces.tiny_length``) and moves into it relative to it (normal relative
velocity vn < 0), the normal relative velocity becomes -e vn (restitution e) and the
tangential relative velocity u is reduced by mu times the normal velocity change
(1 + e)|vn| (Coulomb friction with the normal velocity change as the impulse per
unit mass: u = 0 if |u| <= mu (1 + e)|vn|, sticking); the position is then
recomputed from the corrected velocity, x0 + dt v (a symplectic Euler step at
contact, so a sticking particle does not creep), and moved along the normal onto the
surface (the particle has landed: neither hovering where the step began nor inside).
A particle inside but moving out is only projected onto the surface; with several
colliders, a particle whose position was recomputed for one is projected out of the
ones before it (``project``). The response is first order in dt whatever the
integrator.

Implicit (``detect``, fused into ``operator.refresh_row``): at the start of the step
(x_n, v_n, time t_n) a particle is in contact with a collider if the predicted
position x_n + dt (v_n + dt a) (a: the sum of the uniform accelerations, gravity
and any other ``uniform`` term; collider moved by its velocity) is inside it. Its
velocity along n is then prescribed through the filter of ``constraints``: the
collider's normal velocity plus e times the normal speed it arrives with
(restitution). Contacts with several colliders constrain several independent
directions (Gram-Schmidt on the normals). Friction enters the solve as forces
(``friction_terms``); ``kernels/friction.py`` decides sticking and sliding (Coulomb,
from the contact impulses of the solve) and releases pulling contacts after it. When x' is committed, a particle that
was still d > 0 away from the surface it lands on is moved back by (1 + e) d along n
(``landing``: it met the surface within the step), and ``project`` moves what would
still end inside a collider onto its surface.
"""

import taichi as ti

from .constraints import is_pinned
from .forces import tiny_length
from .terms import uniform_acceleration

# A contact normal whose part outside the directions constrained already is shorter
# than this (|S n|, n a unit vector) adds nothing independent: it is left out.
INDEPENDENT = 0.1
# The implicit step holds a sticking particle to its collider with a damper c = STICK m / dt
# (kernels/friction.py): its tangential velocity is 1 / (1 + STICK) of what it would be free.
STICK = 100


class PlaneKind:
    """``plane_point`` (m) and unit ``plane_normal``: d = (x - p) . n."""

    name = "plane"

    @staticmethod
    @ti.func
    def distance(dev, cfg: ti.template(), k, x, t):
        n = dev.plane_normal[k]
        return (x - dev.plane_point[k] - t * dev.plane_velocity[k]).dot(n), n

    @staticmethod
    @ti.func
    def curvature(dev, cfg: ti.template(), k, x, t):
        """dn/dx (1/m, f64) at x: zero (a flat surface)."""
        return ti.Matrix.zero(ti.f64, 3, 3)


class SphereKind:
    """``sphere_center`` (m) and ``sphere_radius`` (m): d = |x - c| - r, n = (x - c)/|x - c|
    (+z at the centre itself)."""

    name = "sphere"

    @staticmethod
    @ti.func
    def distance(dev, cfg: ti.template(), k, x, t):
        q = x - dev.sphere_center[k] - t * dev.sphere_velocity[k]
        length = ti.sqrt(q.dot(q))
        n = ti.Vector([0.0, 0.0, 1.0], cfg.real)
        if length > tiny_length(cfg.real):
            n = q * (ti.cast(1, cfg.real) / length)
        return length - dev.sphere_radius[k], n

    @staticmethod
    @ti.func
    def curvature(dev, cfg: ti.template(), k, x, t):
        """dn/dx (1/m, f64) at x: (I - n n^T) / |x - c| (zero at the centre)."""
        q = ti.cast(x - dev.sphere_center[k] - t * dev.sphere_velocity[k], ti.f64)
        length = ti.sqrt(q.dot(q))
        out = ti.Matrix.zero(ti.f64, 3, 3)
        if length > tiny_length(cfg.real):
            n = q / length
            out = (ti.Matrix.identity(ti.f64, 3) - n.outer_product(n)) / length
        return out


class BoxKind:
    """``box_lower`` and ``box_upper`` corners (m), ``box_radius`` (m) of the rounded edges:
    the points within the radius of the inner box shrunk by it on every side. Outside the
    inner box: the distance to its nearest point (n from it to x: a face, edge or corner
    normal) less the radius; inside: minus the depth below its nearest face and the
    radius, n that face's normal. A point on an edge or a corner (several faces equally
    near, to ``forces.tiny_length``) gets the normalised sum of their normals, so that a
    particle resting on a sharp edge may go round it either way."""

    name = "box"

    @staticmethod
    @ti.func
    def distance(dev, cfg: ti.template(), k, x, t):
        shift = t * dev.box_velocity[k]
        lower = dev.box_lower[k] + shift
        upper = dev.box_upper[k] + shift
        radius = dev.box_radius[k]
        q = x - ti.cast(0.5, cfg.real) * (lower + upper)
        side = ti.Vector([1.0 if q[c] >= 0 else -1.0 for c in ti.static(range(3))], cfg.real)
        a = ti.abs(q) - (ti.cast(0.5, cfg.real) * (upper - lower) - radius)  # > 0: outside that slab
        out = ti.max(a, 0)
        length = ti.sqrt(out.dot(out))
        d = length - radius
        n = ti.Vector.zero(cfg.real, 3)
        if length > 0:
            n = side * out * (ti.cast(1, cfg.real) / length)
        else:  # on or in the inner box: the nearest faces, all of them on an edge or a corner
            top = ti.max(a[0], a[1], a[2])
            d = top - radius
            for c in ti.static(range(3)):
                if a[c] >= top - tiny_length(cfg.real):
                    n[c] = side[c]
            n = n * (ti.cast(1, cfg.real) / ti.sqrt(n.dot(n)))
        return d, n

    @staticmethod
    @ti.func
    def curvature(dev, cfg: ti.template(), k, x, t):
        """dn/dx (1/m, f64) at x: on a rounded edge or corner (L > 0 above) (A - n n^T) / L,
        A the diagonal of the slabs x is outside of; zero on a face and inside."""
        shift = t * dev.box_velocity[k]
        lower = dev.box_lower[k] + shift
        upper = dev.box_upper[k] + shift
        q = x - ti.cast(0.5, cfg.real) * (lower + upper)
        a = ti.cast(ti.abs(q) - (ti.cast(0.5, cfg.real) * (upper - lower) - dev.box_radius[k]), ti.f64)
        side = ti.Vector([1.0 if q[c] >= 0 else -1.0 for c in ti.static(range(3))], ti.f64)
        out = ti.max(a, 0)
        length = ti.sqrt(out.dot(out))
        result = ti.Matrix.zero(ti.f64, 3, 3)
        if length > 0:
            n = side * out / length
            active = ti.Matrix.zero(ti.f64, 3, 3)
            for c in ti.static(range(3)):
                if a[c] > 0:
                    active[c, c] = 1.0
            result = (active - n.outer_product(n)) / length
        return result


@ti.func
def velocity(dev, kind: ti.template(), k):
    """Collider k's velocity (m/s)."""
    return ti.static(getattr(dev, kind.name + "_velocity"))[k]


@ti.func
def mu(dev, kind: ti.template(), k):
    """Collider k's friction coefficient."""
    return ti.static(getattr(dev, kind.name + "_friction"))[k]


@ti.func
def restitution(dev, kind: ti.template(), k):
    """Collider k's restitution coefficient."""
    return ti.static(getattr(dev, kind.name + "_restitution"))[k]


@ti.func
def respond(dev, cfg: ti.template(), x0, x, v, h, t):
    """The explicit integrators' contact response (see the module docstring) to the free
    step x0 -> (x, v) of a free particle ending at time t: returns the new (x, v)."""
    xr, vr, _ = respond_upto(dev, cfg, x0, x, v, h, t, ti.static(cfg.collider_count))
    return xr, vr


@ti.func
def respond_upto(dev, cfg: ti.template(), x0, x, v, h, t, upto: ti.template()):
    """``respond`` by the colliders before the ``upto``-th (``cfg.collider_order``):
    returns (x, v, the moves onto surfaces so far)."""
    xr = x
    vr = v
    shift = ti.Vector.zero(cfg.real, 3)  # the moves onto surfaces so far: kept when the position is recomputed
    for kind, k, index in ti.static(cfg.collider_order):
        if ti.static(index < upto):
            xr, vr, shift = respond_one(dev, cfg, kind, k, index, x0, xr, vr, shift, h, t)
    return xr, vr, shift


@ti.func
def respond_one(dev, cfg: ti.template(), kind: ti.template(), k: ti.template(), index: ti.template(), x0, xr, vr,
                shift, h, t):
    """Collider ``index``'s part of ``respond`` (its k-th of ``kind``): (x, v, shift) after it."""
    x_out = xr
    v_out = vr
    s_out = shift
    d, n = kind.distance(dev, cfg, k, xr, t)
    if d <= tiny_length(cfg.real):  # touching, to round-off
        vc = velocity(dev, kind, k)
        rel = vr - vc
        vn = rel.dot(n)
        if vn < 0:
            e = restitution(dev, kind, k)
            tangent = rel - vn * n
            speed = ti.sqrt(tangent.dot(tangent))
            limit = -mu(dev, kind, k) * (1 + e) * vn
            kept = ti.cast(0, cfg.real)
            if speed > limit:
                kept = 1 - limit / speed
            v_out = vc + kept * tangent - e * vn * n
            moved = x0 + shift + h * v_out
            gap, normal = kind.distance(dev, cfg, k, moved, t)
            s_out = shift - gap * normal
            x_out = x0 + s_out + h * v_out
            if ti.static(index > 0):  # the new velocity may carry it back into an earlier one
                x_out = project(dev, cfg, x_out, t, index)
        elif d < 0:
            x_out = xr - d * n
    return x_out, v_out, s_out


@ti.func
def project(dev, cfg: ti.template(), x, t, upto: ti.template()):
    """x moved onto the surface of each of the first ``upto`` colliders it is inside at time t,
    in turn."""
    xr = x
    for kind, count, first in ti.static(cfg.colliders):
        for k in ti.static(range(count)):
            if ti.static(first + k < upto):
                d, n = kind.distance(dev, cfg, k, xr, t)
                if d < 0:
                    xr = xr - d * n
    return xr


@ti.func
def landing(i, dev, cfg: ti.template(), x, t):
    """The implicit step's landing correction (m) of particle i, in contact with the
    colliders of its bits ``dev.contacts[i]``, from x_n = ``x`` at the step's start t:
    sum over them of (1 + e) max(d, 0) n. A particle a distance d > 0 away arriving at
    normal speed s meets the surface d / s into the step and leaves at e s, so it ends
    e (s dt - d) above it, (1 + e) d below x_n + dt v' (v' having normal speed e s)."""
    out = ti.Vector.zero(cfg.real, 3)
    mask = dev.contacts[i]
    for kind, count, first in ti.static(cfg.colliders):
        for k in ti.static(range(count)):
            if mask & ti.static(1 << (first + k)) != 0:
                d, n = kind.distance(dev, cfg, k, x, t)
                out += (1 + restitution(dev, kind, k)) * ti.max(d, 0) * n
    return out


@ti.func
def add_direction(S, w, n, u):
    """Prescribe the velocity component along unit n to be u (m/s), on top of the filter S
    and prescribed velocity w of the constraints made so far: the new direction is
    e = S n / |S n|, and w gains the multiple of e that gives n . w = u. Returns
    (S - e e^T, w', e, whether n was independent of the constrained directions)."""
    m = S @ n
    length = ti.sqrt(m.dot(m))
    ok = length > INDEPENDENT
    e = m
    s_new = S
    w_new = w
    if ok:
        e = m / length
        w_new = w + (u - n.dot(w)) / length * e
        s_new = S - e.outer_product(e)
    return s_new, w_new, e, ok


@ti.func
def predicted_velocity(i, dev, cfg: ti.template(), v, h):
    """v_n + dt a: the velocity a free fall would reach, used to see contacts coming; a
    the sum of the uniform accelerations (``terms.uniform_acceleration``)."""
    out = v[i]
    if ti.static(cfg.has_uniform):
        out = v[i] + h * ti.cast(uniform_acceleration(dev, cfg), cfg.real)
    return out


@ti.func
def detect(i, dev, cfg: ti.template(), x, v, h, t):
    """Particle i's contact constraints for the implicit step from (x_n, v_n) at time t
    (see the module docstring): ``dev.cfilter[i]`` = S_i, ``dev.cvel[i]`` the prescribed
    velocity in the constrained directions, ``dev.contacts[i]`` the bits of the
    colliders it touches (0: free). Contacts released after the last step (bits of
    ``dev.released[i]``) are skipped. Pinned particles get none; a particle out of
    contact loses its friction state (``kernels/friction.py``). Returns the velocity
    of the collider it touches first (m/s; 0 without contact)."""
    S = ti.Matrix.identity(cfg.real, 3)
    w = ti.Vector.zero(cfg.real, 3)
    carrier = ti.Vector.zero(cfg.real, 3)
    mask = 0
    if not is_pinned(i, dev, cfg):
        xi = x[i]
        vi = v[i]
        ahead = predicted_velocity(i, dev, cfg, v, h)
        released = dev.released[i]
        for kind, count, first in ti.static(cfg.colliders):
            for k in ti.static(range(count)):
                bit = ti.static(1 << (first + k))
                if released & bit == 0:
                    d, n = kind.distance(dev, cfg, k, xi, t)
                    vc = velocity(dev, kind, k)
                    if d + h * (ahead - vc).dot(n) < 0:
                        arriving = ti.min((vi - vc).dot(n), 0)
                        u = vc.dot(n) - restitution(dev, kind, k) * arriving
                        s_new, w_new, _, ok = add_direction(S, w, n, u)
                        if ok:
                            if mask == 0:
                                carrier = vc
                            S = s_new
                            w = w_new
                            mask |= bit
    if mask == 0:
        dev.stick[i] = 0
        dev.fric[i] = ti.Vector.zero(cfg.real, 3)
    dev.cfilter[i] = S
    dev.cvel[i] = w
    dev.contacts[i] = mask
    return carrier


@ti.func
def friction_diagonal(i, dev, cfg: ti.template()):
    """Particle i's friction share of A's diagonal (kg; ``kernels/friction.py``): dt c for
    a sticking particle, held to its collider by a damper c = STICK m_i / dt (the normal
    direction is filtered out)."""
    out = ti.cast(0, cfg.real)
    if dev.contacts[i] != 0 and dev.stick[i] != 0:
        out = STICK * dev.mass[i]
    return out


@ti.func
def friction_impulse(i, dev, cfg: ti.template(), carrier):
    """Particle i's friction share of b (N s): dt c v_c for a sticking particle (v_c the
    velocity ``carrier`` of its collider), the kinetic friction impulse ``dev.fric[i]``
    for a sliding one."""
    out = ti.Vector.zero(cfg.real, 3)
    if dev.contacts[i] != 0:
        if dev.stick[i] != 0:
            out = STICK * dev.mass[i] * carrier
        else:
            out = dev.fric[i]
    return out


@ti.func
def respond_adjoint(dev, cfg: ti.template(), x0, x, v, h, t, gx, gv):
    """The transpose of ``respond``'s Jacobian at the free step x0 -> (x, v) of a free
    particle ending at time t, every collider's branch (free, impact sticking or sliding,
    or only projected out) frozen. From (gx, gv) = dL/d(x_r, v_r) of its outputs returns
    (dL/dx0, dL/dx, dL/dv). Backwards through the colliders in turn
    (``respond_one_adjoint``), each one's inputs computed again (``respond_upto``)."""
    gxr = ti.cast(gx, ti.f64)
    gvr = ti.cast(gv, ti.f64)
    gshift = ti.Vector.zero(ti.f64, 3)
    gx0 = ti.Vector.zero(ti.f64, 3)
    for kind, k, index in ti.static(cfg.collider_order_back):
        xr, vr, shift = respond_upto(dev, cfg, x0, x, v, h, t, index)
        gxr, gvr, gshift, gx0 = respond_one_adjoint(dev, cfg, kind, k, index, x0, xr, vr, shift, h, t, gxr, gvr,
                                                    gshift, gx0)
    return gx0, gxr, gvr


@ti.func
def projection_jacobian(dev, cfg: ti.template(), kind: ti.template(), k: ti.template(), y, t):
    """The Jacobian (f64) of P(y) = y - d(y) n(y), the projection onto collider k's
    surface: I - n n^T - d N, N = dn/dy (``curvature``)."""
    d, n_real = kind.distance(dev, cfg, k, y, t)
    n = ti.cast(n_real, ti.f64)
    return ti.Matrix.identity(ti.f64, 3) - n.outer_product(n) - ti.cast(d, ti.f64) * kind.curvature(dev, cfg, k, y, t)


@ti.func
def project_adjoint(dev, cfg: ti.template(), y, t, upto: ti.template(), g):
    """The transpose of ``project``'s Jacobian at y (by the first ``upto`` colliders, each
    one's projection frozen as taken) applied to g (f64)."""
    out = g
    for kind, k, index in ti.static(cfg.collider_order_back):
        if ti.static(index < upto):
            at = project(dev, cfg, y, t, index)  # what collider index was given
            d, _ = kind.distance(dev, cfg, k, at, t)
            if d < 0:
                out = projection_jacobian(dev, cfg, kind, k, at, t).transpose() @ out
    return out


@ti.func
def respond_one_adjoint(dev, cfg: ti.template(), kind: ti.template(), k: ti.template(), index: ti.template(), x0,
                        xr, vr, shift, h, t, gxr, gvr, gshift, gx0):
    """The transpose of ``respond_one``'s Jacobian at its inputs (xr, vr, shift) with the
    gradients (gxr, gvr, gshift) of its outputs; returns those of its inputs and gx0 with
    dL/dx0's share added. With the surface's distance d, normal n(xr), curvature N = dn/dx
    (``curvature``), rel = vr - v_c, vn = rel . n, T = rel - vn n: at an impact v' = v_c +
    kappa T - e vn n with kappa = 0 (sticking) or 1 + mu (1 + e) vn / |T| (sliding), then
    moved = x0 + shift + h v', shift' = shift + P(moved) - moved and x' = P(moved) (then
    ``project``ed out of the colliders before), P the projection onto the surface
    (``projection_jacobian``); projected out only, x' = P(xr). Everything in f64."""
    gx_in = gxr
    gv_in = gvr
    gs_in = gshift
    d, n_real = kind.distance(dev, cfg, k, xr, t)
    n = ti.cast(n_real, ti.f64)
    if d <= tiny_length(cfg.real):
        rel = ti.cast(vr - velocity(dev, kind, k), ti.f64)
        vn = rel.dot(n)
        if vn < 0:
            e = ti.cast(restitution(dev, kind, k), ti.f64)
            c = ti.cast(mu(dev, kind, k), ti.f64) * (1 + e)
            tangent = rel - vn * n
            speed = ti.sqrt(tangent.dot(tangent))
            sliding = speed > -c * vn
            kappa = ti.cast(0, ti.f64)
            if sliding:
                kappa = 1 + c * vn / speed
            v_new = ti.cast(velocity(dev, kind, k), ti.f64) + kappa * tangent - e * vn * n
            moved = ti.cast(x0 + shift, ti.f64) + h * v_new
            landed = ti.cast(moved, cfg.real)
            gy = gxr
            if ti.static(index > 0):
                gap, normal = kind.distance(dev, cfg, k, landed, t)
                gy = project_adjoint(dev, cfg, landed - gap * normal, t, index, gxr)
            jacobian = projection_jacobian(dev, cfg, kind, k, landed, t)
            g_moved = jacobian.transpose() @ (gy + gshift) - gshift
            gx0 += g_moved
            gs_in = gshift + g_moved
            g = gvr + h * g_moved  # v''s gradient: it also moves x' and the shift through moved
            an = ti.Vector.zero(ti.f64, 3)  # n's gradient
            if sliding:  # v' = v_c + T + c vn u - e vn n, u = T / |T|
                u = tangent / speed
                gt = g + c * vn / speed * (g - u.dot(g) * u)  # T's
                gvn = c * u.dot(g) - e * n.dot(g) - n.dot(gt)  # vn's, through T = rel - vn n too
                gv_in = gt + gvn * n
                an = -e * vn * g - vn * gt + gvn * rel
            else:  # v' = v_c - e vn n
                gv_in = -e * n.dot(g) * n
                an = -e * (n.dot(g) * rel + vn * g)
            gx_in = kind.curvature(dev, cfg, k, xr, t).transpose() @ an
        elif d < 0:
            gx_in = projection_jacobian(dev, cfg, kind, k, xr, t).transpose() @ gxr
    return gx_in, gv_in, gs_in, gx0


@ti.func
def landing_adjoint(i, dev, cfg: ti.template(), x, t, g):
    """The transpose of ``landing``'s Jacobian in x (f64) applied to g: for each contact of
    particle i at distance d > 0, (1 + e) (n n^T + d N) g, N = dn/dx (``curvature``)."""
    out = ti.Vector.zero(ti.f64, 3)
    mask = dev.contacts[i]
    for kind, count, first in ti.static(cfg.colliders):
        for k in ti.static(range(count)):
            if mask & ti.static(1 << (first + k)) != 0:
                d, n_real = kind.distance(dev, cfg, k, x, t)
                if d > 0:
                    n = ti.cast(n_real, ti.f64)
                    jacobian = n.outer_product(n) + ti.cast(d, ti.f64) * kind.curvature(dev, cfg, k, x, t)
                    out += (1 + ti.cast(restitution(dev, kind, k), ti.f64)) * (jacobian.transpose() @ g)
    return out


@ti.func
def column(matrix, j):
    """Column j (a run-time index, 0 to 2) of a 3x3 f64 matrix."""
    out = ti.Vector.zero(ti.f64, 3)
    for c in ti.static(range(3)):
        if j == c:
            out = ti.Vector([matrix[r, c] for r in ti.static(range(3))], ti.f64)
    return out


@ti.func
def set_column(matrix, j, vector):
    """The 3x3 matrix with its column j (a run-time index, 0 to 2) set to ``vector``."""
    out = matrix
    for c in ti.static(range(3)):
        if j == c:
            for r in ti.static(range(3)):
                out[r, c] = vector[r]
    return out


@ti.func
def component(vector, j):
    """Entry j (a run-time index, 0 to 2) of a 3-vector."""
    out = ti.cast(0, ti.f64)
    for c in ti.static(range(3)):
        if j == c:
            out = vector[c]
    return out


@ti.func
def contact_normals(i, dev, cfg: ti.template(), x, t):
    """The normals (f64) at x, time t, of particle i's contacts (``dev.contacts[i]``, at most
    3, independent) as the columns of a 3x3 matrix in ``cfg.colliders``' order, and their count."""
    mask = dev.contacts[i]
    normals = ti.Matrix.zero(ti.f64, 3, 3)
    count = 0
    for kind, kinds, first in ti.static(cfg.colliders):
        for k in ti.static(range(kinds)):
            if mask & ti.static(1 << (first + k)) != 0:
                _, n = kind.distance(dev, cfg, k, x, t)
                normals = set_column(normals, count, ti.cast(n, ti.f64))
                count += 1
    return normals, count


@ti.func
def orthonormal(normals, count):
    """``add_direction``'s filter and directions for the first ``count`` columns of
    ``normals``: (S = I - sum e_j e_j^T, the e_j as columns)."""
    S = ti.Matrix.identity(ti.f64, 3)
    directions = ti.Matrix.zero(ti.f64, 3, 3)
    for j in ti.static(range(3)):
        if j < count:
            e = S @ column(normals, j)
            e = e / ti.sqrt(e.dot(e))
            S = S - e.outer_product(e)
            directions = set_column(directions, j, e)
    return S, directions


@ti.func
def normals_adjoint(i, dev, cfg: ti.template(), x, t, g_normals):
    """dL/dx (f64) through the curvature dn/dx of particle i's contact normals at x, time
    t, from their gradients as the columns of ``g_normals`` (``contact_normals``' order)."""
    mask = dev.contacts[i]
    out = ti.Vector.zero(ti.f64, 3)
    count = 0
    for kind, kinds, first in ti.static(cfg.colliders):
        for k in ti.static(range(kinds)):
            if mask & ti.static(1 << (first + k)) != 0:
                out += kind.curvature(dev, cfg, k, x, t).transpose() @ column(g_normals, count)
                count += 1
    return out


@ti.func
def constraint_adjoint(i, dev, cfg: ti.template(), x, v, v_new, mu_i, unsettled, impulse, t):
    """The contact constraints' share of the implicit step's adjoint at particle i (f64),
    its contacts as ``detect`` made them from (x, v) = (x_n, v_n) at time t.

    The step's equations at i are A v' - b = N lam and N^T v' = u, N the normals n_k of
    its contacts (columns), u_k = n_k . v_c - e min((v_n - v_c) . n_k, 0). With the
    adjoint solution ``mu_i`` (N^T mu = 0), ``unsettled`` = G - A mu (G: dL/dv' the solve
    was given) = N beta, and ``impulse`` = A v' - b = N lam, the gradient has, per
    contact, dL/dn_k = lam_k mu - beta_k v' + beta_k du_k/dn_k (to x through dn/dx:
    ``curvature``) and dL/dv_n = beta_k du_k/dv_n. Returns (dL/dx_n, dL/dv_n) shares."""
    mask = dev.contacts[i]
    normals, count = contact_normals(i, dev, cfg, x, t)
    gram = normals.transpose() @ normals
    for c in ti.static(range(3)):
        if c >= count:
            gram[c, c] = 1.0
    inverse = gram.inverse()
    lam = inverse @ (normals.transpose() @ impulse)
    beta = inverse @ (normals.transpose() @ unsettled)
    gv = ti.Vector.zero(ti.f64, 3)
    g_normals = ti.Matrix.zero(ti.f64, 3, 3)
    slot = 0
    for kind, kinds, first in ti.static(cfg.colliders):
        for k in ti.static(range(kinds)):
            if mask & ti.static(1 << (first + k)) != 0:
                n = column(normals, slot)
                beta_k = component(beta, slot)
                vc = ti.cast(velocity(dev, kind, k), ti.f64)
                du = vc  # du_k / dn_k
                if (v - vc).dot(n) < 0:  # arriving: restitution reflects its normal speed
                    e = ti.cast(restitution(dev, kind, k), ti.f64)
                    du = vc - e * (v - vc)
                    gv -= beta_k * e * n
                g_normals = set_column(g_normals, slot, component(lam, slot) * mu_i + beta_k * (du - v_new))
                slot += 1
    return normals_adjoint(i, dev, cfg, x, t, g_normals), gv
