"""Self-collision of a triangle mesh: a pass after every step of every integrator.

After an integrator has taken a step from the start positions x0 (``dev.sc_start``,
copied by ``self_collision_begin``) to a candidate state (x, v), ``self_collision_detect``
and ``self_collision_bound``:

1. Proximity. Every pair of non-adjacent primitives of the mesh closer than a
   radius r at x0 is found: point-triangle pairs (a vertex and a triangle that does
   not hold it) and edge-edge pairs (two edges without a common vertex). Broad phase:
   two spatial hashes of cell size c = r + L (L: the longest edge at x0), one of the
   vertices and one of the edges' midpoints, built by counting sort; each triangle
   looks up the vertices in the cells its box grown by r covers, each edge the edge
   midpoints in its box grown by r + L/2 (at most 3 cells a side), so the work is
   linear in the mesh size. Narrow phase: exact closest points (``point_triangle``,
   ``segment_segment``, degenerate primitives included).
2. Repulsion (in the spirit of Bridson, Fedkiw and Anderson 2002). A pair closer
   than ``thickness`` gets an inelastic normal impulse that stops the approach of its
   closest points over the step and pushes them apart, at most to separate them at
   0.1 (thickness - d) / dt and at most a spring of ``stiffness`` would in dt, with
   Coulomb friction (mu) on the tangential relative velocity; the impulses are
   spread over the pair's four particles by their barycentric weights and inverse
   masses and averaged per particle (Jacobi). The step's displacement x - x0 and
   the velocity change by the same amount.
3. Displacement bound (the guarantee, as in Offset Geometric Contact, Chen et al.
   2025). Each particle moves at most GAMMA (< 1/2) times the smallest distance at
   x0 of a pair it belongs to (or r): along straight paths from x0, a pair's
   distance then shrinks by less than it is, so no pair touches during the step and
   no edge passes through a triangle it does not share a vertex with. A particle
   held back so ends at x0 + s (x - x0) with velocity s (x - x0) / dt. r is
   max displacement / GAMMA + thickness (capped by the mesh's size), so a particle
   far from everything is never held back. Pinned particles are neither pushed nor
   held back.

Deterministic for any thread count: distances are reduced with atomic min/max (exact),
impulses summed in 64-bit fixed point (integer addition: order-free), and nothing
reads the order within a hash cell.

Fields (``massspring/self_collision.py`` declares them; n particles, t triangles, e
edges, T cells per table): ``sc_tris`` (t,) int 3-vectors, ``sc_edges`` (e,) int
2-vectors, ``sc_count`` (t, e, T), ``sc_start`` (n,) vec3 m, ``sc_bound`` (n,) m,
``sc_dv`` (n,) int64 3-vectors (fixed point, ``SCALE`` per m/s), ``sc_hits`` (n,),
``sc_vcell``/``sc_ecell`` (T,), ``sc_vfirst``/``sc_efirst`` (T + 1,), ``sc_vitem``
(n,), ``sc_eitem`` (e,) int32, ``sc_box`` (8,) f64, ``sc_tally`` (4,) int32.
"""

import taichi as ti

from .constraints import is_pinned

GAMMA = 0.45  # a particle moves at most this fraction of its nearest pair's distance
SEPARATION = 0.1  # a repelled pair separates at most at this fraction of its gap per step
SCALE = 2.0**40  # fixed-point units of sc_dv per m/s
DV_LIMIT = 1e6  # m/s: a pair's velocity change is clipped to this before it becomes fixed point
CELL_LIMIT = 2**30  # cell coordinates are clipped to +-this
POINT_TRIANGLE = (1, -1, -1, -1)  # the sides of a pair's particles: a point (A), a triangle (B)
EDGE_EDGE = (1, 1, -1, -1)  # two edges
REPEL, PROJECT, BOUND = 0, 1, 2  # the passes over the pairs
OFFSET = 0.5  # pairs closer than this fraction of the thickness may not approach at all


@ti.func
def point_segment(p, a, b):
    """(distance, t): the point a + t (b - a), t in [0, 1], of segment ab closest to p."""
    ab = b - a
    length2 = ab.dot(ab)
    t = p[0] * 0  # of p's precision
    if length2 > 0:
        t = ti.min(ti.max((p - a).dot(ab) / length2, 0), 1)
    return (p - (a + t * ab)).norm(), t


@ti.func
def point_triangle(p, a, b, c):
    """(distance, weights (wa, wb, wc)): the point wa a + wb b + wc c of triangle abc
    closest to p (weights >= 0, sum 1). A degenerate triangle is its edges."""
    d1, t1 = point_segment(p, a, b)
    d2, t2 = point_segment(p, b, c)
    d3, t3 = point_segment(p, c, a)
    best = d1
    w = ti.Vector([1 - t1, t1, 0 * t1])
    if d2 < best:
        best = d2
        w = ti.Vector([0 * t2, 1 - t2, t2])
    if d3 < best:
        best = d3
        w = ti.Vector([t3, 0 * t3, 1 - t3])
    ab = b - a
    ac = c - a
    ap = p - a
    d00 = ab.dot(ab)
    d01 = ab.dot(ac)
    d11 = ac.dot(ac)
    den = d00 * d11 - d01 * d01
    if den > 1e-12 * d00 * d11:  # a triangle with area: the projection, if inside, is closest
        d20 = ap.dot(ab)
        d21 = ap.dot(ac)
        wb = (d11 * d20 - d01 * d21) / den
        wc = (d00 * d21 - d01 * d20) / den
        wa = 1 - wb - wc
        if wa >= 0 and wb >= 0 and wc >= 0:
            inside = (p - (wa * a + wb * b + wc * c)).norm()
            if inside < best:
                best = inside
                w = ti.Vector([wa, wb, wc])
    return best, w


@ti.func
def segment_segment(p1, q1, p2, q2):
    """(distance, s, t): the closest points p1 + s (q1 - p1) and p2 + t (q2 - p2),
    s, t in [0, 1]. Degenerate and parallel segments included."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = d1.dot(d1)
    e = d2.dot(d2)
    f = d2.dot(r)
    s = p1[0] * 0  # of the points' precision
    t = p1[0] * 0
    if a > 0 and e > 0:
        c = d1.dot(r)
        b = d1.dot(d2)
        den = a * e - b * b
        if den > 1e-12 * a * e:  # not parallel
            s = ti.min(ti.max((b * f - c * e) / den, 0), 1)
        t = (b * s + f) / e
        if t < 0:
            t = 0
            s = ti.min(ti.max(-c / a, 0), 1)
        elif t > 1:
            t = 1
            s = ti.min(ti.max((b - c) / a, 0), 1)
    elif a > 0:
        s = ti.min(ti.max(-d1.dot(r) / a, 0), 1)
    elif e > 0:
        t = ti.min(ti.max(f / e, 0), 1)
    return ((p1 + s * d1) - (p2 + t * d2)).norm(), s, t


@ti.func
def cell_of(p, inverse):
    """Integer cell coordinates of point p in cells of size 1 / inverse."""
    q = ti.floor(p * inverse)
    return ti.Vector([ti.cast(ti.min(ti.max(q[k], -CELL_LIMIT), CELL_LIMIT), ti.i32) for k in ti.static(range(3))])


@ti.func
def bucket(cell, size):
    h = (ti.cast(cell[0], ti.i64) * 73856093) ^ (ti.cast(cell[1], ti.i64) * 19349663) \
        ^ (ti.cast(cell[2], ti.i64) * 83492791)
    return ti.cast(((h % size) + size) % size, ti.i32)


@ti.func
def midpoint(dev, e):
    ends = dev.sc_edges[e]
    return 0.5 * (dev.sc_start[ends[0]] + dev.sc_start[ends[1]])


@ti.func
def key(dev, i, inverse, size, edges: ti.template()):
    """The bucket of vertex i at x0, or (``edges``) of edge i's midpoint."""
    point = dev.sc_start[i]
    if ti.static(edges):
        point = midpoint(dev, i)
    return bucket(cell_of(point, inverse), size)


@ti.func
def count_sort(dev, cells: ti.template(), first: ti.template(), items: ti.template(), size, inverse, count,
               edges: ti.template()):
    """Hash items 0..count-1 (vertices, or ``edges``) by ``key``: ``first[b]:first[b + 1]``
    of ``items`` lists bucket b's items (in no fixed order)."""
    for b in range(size):
        cells[b] = 0
    for i in range(count):
        ti.atomic_add(cells[key(dev, i, inverse, size, edges)], 1)
    first[0] = 0
    ti.loop_config(serialize=True)
    for b in range(size):
        first[b + 1] = first[b] + cells[b]
        cells[b] = 0
    for i in range(count):
        b = key(dev, i, inverse, size, edges)
        items[first[b] + ti.atomic_add(cells[b], 1)] = i


@ti.func
def pair(dev, cfg: ti.template(), state, idx, w, d, h, thickness, mu, ks, sides: ti.template(), phase: ti.template()):
    """A pair of primitives at distance d (m) at x0: particles ``idx``, weights ``w``
    (side A positive, side B negative; sum w x0 = p - q, from B's closest point q to
    A's p), ``sides``: each particle's side (+1: A, -1: B), ``POINT_TRIANGLE`` or ``EDGE_EDGE``. ``REPEL``: the pair's repulsion impulse if d < ``thickness``. ``BOUND``: each
    of its particles k, of side sign s_k, may move at most GAMMA d towards the other
    side, s_k n . dx_k >= -GAMMA d with n = (p - q) / d: a particle whose displacement
    dx_k (the state's, less x0) breaks it gets the scale that meets it (``sc_scale``,
    the smallest over its pairs; a displacement scaled down keeps every bound it met)."""
    gap_vector = ti.Vector.zero(cfg.real, 3)
    for k in ti.static(range(4)):
        gap_vector += w[k] * dev.sc_start[idx[k]]
    length = gap_vector.norm()
    if ti.static(phase != REPEL):
        if length > 0:
            normal = gap_vector / length
            allowed = GAMMA * ti.max(length - OFFSET * thickness, 0)
            for k in ti.static(range(4)):
                i = idx[k]
                toward = -sides[k] * normal.dot(state.x[i] - dev.sc_start[i])
                if toward > allowed and not is_pinned(i, dev, cfg):
                    if ti.static(phase == PROJECT):
                        push = (toward - allowed) * sides[k] * normal
                        fixed = ti.Vector([ti.cast(ti.round(ti.min(ti.max(push[c], -DV_LIMIT), DV_LIMIT) * SCALE),
                                                   ti.i64) for c in ti.static(range(3))])
                        ti.atomic_add(dev.sc_dv[i], fixed)
                        ti.atomic_add(dev.sc_hits[i], 1)
                    else:
                        ti.atomic_min(dev.sc_scale[i], allowed / toward)
        else:
            for k in ti.static(range(4)):
                ti.atomic_min(dev.sc_scale[idx[k]], 0)
    else:
        slot = ti.atomic_add(dev.sc_tally[0], 1)
        if slot < dev.sc_count[3]:
            dev.sc_pidx[slot] = idx
            dev.sc_pw[slot] = w
            dev.sc_pkind[slot] = sides[1]  # 1: edge-edge, -1: point-triangle
        ti.atomic_min(dev.sc_box[8], ti.cast(d, ti.f64))
        if d < thickness and length > 0:
            ti.atomic_add(dev.sc_tally[1], 1)
            rel = ti.Vector.zero(cfg.real, 3)
            inverse = ti.cast(0, cfg.real)
            for k in ti.static(range(4)):
                i = idx[k]
                rel += w[k] * (state.x[i] - dev.sc_start[i]) / h
                if not is_pinned(i, dev, cfg):
                    inverse += w[k] * w[k] / dev.mass[i]
            if inverse > 0:
                normal = gap_vector / length
                vn = rel.dot(normal)
                gap = thickness - d
                need = SEPARATION * gap / h - vn
                cap = ti.max(-vn, 0) + h * ks * gap * inverse
                dvn = ti.max(ti.min(need, cap), 0)
                if dvn > 0:
                    change = dvn * normal
                    tangential = rel - vn * normal
                    vt = tangential.norm()
                    if vt > 0:
                        change -= ti.min(mu * dvn, vt) / vt * tangential
                    impulse = change / inverse
                    for k in ti.static(range(4)):
                        i = idx[k]
                        if not is_pinned(i, dev, cfg):
                            du = w[k] * impulse / dev.mass[i]
                            fixed = ti.Vector([ti.cast(ti.round(ti.min(ti.max(du[c], -DV_LIMIT), DV_LIMIT) * SCALE),
                                                       ti.i64) for c in ti.static(range(3))])
                            ti.atomic_add(dev.sc_dv[i], fixed)
                            ti.atomic_add(dev.sc_hits[i], 1)


@ti.func
def vertex_candidates(dev, cfg: ti.template(), state, cell, corner, a, b, c, low, high, r, inverse, size, h, thick, mu,
                      ks, phase: ti.template()):
    """Point-triangle pairs of triangle ``corner`` (a, b, c at x0) with the vertices of ``cell``."""
    bk = bucket(cell, size)
    for slot in range(dev.sc_vfirst[bk], dev.sc_vfirst[bk + 1]):
        p = dev.sc_vitem[slot]
        x = dev.sc_start[p]
        if p != corner[0] and p != corner[1] and p != corner[2] and (x >= low).all() and (x <= high).all() \
                and (cell_of(x, inverse) == cell).all():
            d, w = point_triangle(x, a, b, c)
            if d < r:
                pair(dev, cfg, state, ti.Vector([p, corner[0], corner[1], corner[2]]),
                     ti.Vector([1, -w[0], -w[1], -w[2]], cfg.real), d, h, thick, mu, ks, POINT_TRIANGLE, phase)


@ti.func
def edge_candidates(dev, cfg: ti.template(), state, cell, e, ends, p1, q1, low, high, r, inverse, size, h, thick, mu,
                    ks, phase: ti.template()):
    """Edge-edge pairs of edge e (``ends``, p1 q1 at x0) with the later edges whose midpoints are in ``cell``."""
    bk = bucket(cell, size)
    for slot in range(dev.sc_efirst[bk], dev.sc_efirst[bk + 1]):
        f = dev.sc_eitem[slot]
        other = dev.sc_edges[f]
        if f > e and other[0] != ends[0] and other[0] != ends[1] and other[1] != ends[0] and other[1] != ends[1]:
            p2 = dev.sc_start[other[0]]
            q2 = dev.sc_start[other[1]]
            if (ti.min(p2, q2) <= high + r).all() and (ti.max(p2, q2) >= low - r).all() \
                    and (cell_of(midpoint(dev, f), inverse) == cell).all():
                d, s, u = segment_segment(p1, q1, p2, q2)
                if d < r:
                    pair(dev, cfg, state, ti.Vector([ends[0], ends[1], other[0], other[1]]),
                         ti.Vector([1 - s, s, u - 1, -u], cfg.real), d, h, thick, mu, ks, EDGE_EDGE, phase)


@ti.func
def pairs(dev, cfg: ti.template(), state, tris, edges, r, longest, inverse, size, h, thick, mu, ks,
          phase: ti.template()):
    """Every point-triangle and edge-edge pair within r at x0, through ``pair`` in ``phase``."""
    for t in range(tris):  # point-triangle pairs
        corner = dev.sc_tris[t]
        a = dev.sc_start[corner[0]]
        b = dev.sc_start[corner[1]]
        c = dev.sc_start[corner[2]]
        low = ti.min(ti.min(a, b), c) - r
        high = ti.max(ti.max(a, b), c) + r
        first = cell_of(low, inverse)
        last = cell_of(high, inverse)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    vertex_candidates(dev, cfg, state, ti.Vector([cx, cy, cz]), corner, a, b, c, low, high, r, inverse,
                                      size, h, thick, mu, ks, phase)
    margin = r + ti.cast(0.5 * longest, cfg.real)
    for e in range(edges):  # edge-edge pairs
        ends = dev.sc_edges[e]
        p1 = dev.sc_start[ends[0]]
        q1 = dev.sc_start[ends[1]]
        low = ti.min(p1, q1)
        high = ti.max(p1, q1)
        first = cell_of(low - margin, inverse)
        last = cell_of(high + margin, inverse)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    edge_candidates(dev, cfg, state, ti.Vector([cx, cy, cz]), e, ends, p1, q1, low, high, r, inverse,
                                    size, h, thick, mu, ks, phase)


@ti.func
def listed_pairs(dev, cfg: ti.template(), state, count, thick, phase: ti.template()):
    """``pair`` in ``phase`` over the first ``count`` pairs of the pair list."""
    for slot in range(count):
        idx = dev.sc_pidx[slot]
        w = dev.sc_pw[slot]
        if dev.sc_pkind[slot] == 1:  # the second particle's side
            pair(dev, cfg, state, idx, w, 0, 1, thick, 0, 0, EDGE_EDGE, phase)
        else:
            pair(dev, cfg, state, idx, w, 0, 1, thick, 0, 0, POINT_TRIANGLE, phase)


@ti.kernel
def self_collision_begin(dev: ti.template(), state: ti.template(), serial: ti.template()):
    """x0 = the state's positions, before a step (``serial``: in a serial loop)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        dev.sc_start[i] = state.x[i]


@ti.func
def detect(dev, cfg: ti.template(), state, dt, thickness, friction, stiffness):
    """Steps 1 and 2 of the pass (module docstring): the reach, the hashes, the pairs
    (listed while the list has room), their repulsion applied, and no particle moved
    further than GAMMA r. Returns (pairs within r, pairs repelled, 0, r in m, the
    smallest distance of a pair in m, 1 if the pairs fitted the list)."""
    n = dev.size[0]
    tris = dev.sc_count[0]
    edges = dev.sc_count[1]
    size = dev.sc_count[2]
    h = ti.cast(dt, cfg.real)
    thick = ti.cast(thickness, cfg.real)
    mu = ti.cast(friction, cfg.real)
    ks = ti.cast(stiffness, cfg.real)
    for k in range(4):
        dev.sc_tally[k] = 0
    for k in range(3):
        dev.sc_box[k] = 1e300
        dev.sc_box[3 + k] = -1e300
    dev.sc_box[6] = 0.0
    dev.sc_box[7] = 0.0
    dev.sc_box[8] = 1e300
    for i in range(n):
        x0 = ti.cast(dev.sc_start[i], ti.f64)
        ti.atomic_max(dev.sc_box[6], ti.cast((state.x[i] - dev.sc_start[i]).norm(), ti.f64))
        for k in ti.static(range(3)):
            ti.atomic_min(dev.sc_box[k], x0[k])
            ti.atomic_max(dev.sc_box[3 + k], x0[k])
        dev.sc_dv[i] = ti.Vector.zero(ti.i64, 3)
        dev.sc_hits[i] = 0
    for e in range(edges):
        ends = dev.sc_edges[e]
        ti.atomic_max(dev.sc_box[7], ti.cast((dev.sc_start[ends[1]] - dev.sc_start[ends[0]]).norm(), ti.f64))
    span = ti.Vector([dev.sc_box[3 + k] - dev.sc_box[k] for k in ti.static(range(3))]).norm()
    reach = ti.min(dev.sc_box[6] / GAMMA, span) + thickness
    dev.sc_box[9] = reach
    r = ti.cast(reach, cfg.real)
    inverse = ti.cast(1.0 / (reach + dev.sc_box[7]), cfg.real)
    count_sort(dev, dev.sc_vcell, dev.sc_vfirst, dev.sc_vitem, size, inverse, n, False)
    count_sort(dev, dev.sc_ecell, dev.sc_efirst, dev.sc_eitem, size, inverse, edges, True)
    pairs(dev, cfg, state, tris, edges, r, dev.sc_box[7], inverse, size, h, thick, mu, ks, REPEL)
    for i in range(n):
        if not is_pinned(i, dev, cfg):
            x = state.x[i]
            v = state.v[i]
            hits = dev.sc_hits[i]
            if hits > 0:
                du = ti.cast(dev.sc_dv[i], cfg.real) / ti.cast(SCALE * hits, cfg.real)
                x += h * du
                v += du
            dx = x - dev.sc_start[i]
            length = dx.norm()
            if length > GAMMA * r:  # what no pair within r can see
                dx *= GAMMA * r / length
                x = dev.sc_start[i] + dx
                v = dx / h
            state.x[i] = x
            state.v[i] = v
    fits = 1 if dev.sc_tally[0] <= dev.sc_count[3] else 0
    return ti.Vector([dev.sc_tally[0], dev.sc_tally[1], 0, reach, dev.sc_box[8], fits], ti.f64)


@ti.func
def bound(dev, cfg: ti.template(), state, dt, thickness, from_list: ti.template()):
    """Step 3 of the pass (module docstring) over the listed pairs, or (not
    ``from_list``: the list overflowed) over all pairs found again. Returns the number
    of particles held back."""
    n = dev.size[0]
    h = ti.cast(dt, cfg.real)
    thick = ti.cast(thickness, cfg.real)
    tris = dev.sc_count[0]
    edges = dev.sc_count[1]
    size = dev.sc_count[2]
    r = ti.cast(dev.sc_box[9], cfg.real)
    inverse = ti.cast(1.0 / (dev.sc_box[9] + dev.sc_box[7]), cfg.real)
    count = dev.sc_tally[0]
    dev.sc_tally[2] = 0
    for i in range(n):
        dev.sc_dv[i] = ti.Vector.zero(ti.i64, 3)
        dev.sc_hits[i] = 0
        dev.sc_scale[i] = 1
    if ti.static(from_list):
        listed_pairs(dev, cfg, state, count, thick, PROJECT)
    else:
        pairs(dev, cfg, state, tris, edges, r, dev.sc_box[7], inverse, size, h, thick, 0, 0, PROJECT)
    for i in range(n):
        hits = dev.sc_hits[i]
        if hits > 0:
            dx = ti.cast(dev.sc_dv[i], cfg.real) / ti.cast(SCALE * hits, cfg.real)
            state.x[i] += dx
            state.v[i] += dx / h
    if ti.static(from_list):
        listed_pairs(dev, cfg, state, count, thick, BOUND)
    else:
        pairs(dev, cfg, state, tris, edges, r, dev.sc_box[7], inverse, size, h, thick, 0, 0, BOUND)
    for i in range(n):
        scale = dev.sc_scale[i]
        if scale < 1 and not is_pinned(i, dev, cfg):
            dx = scale * (state.x[i] - dev.sc_start[i])
            state.x[i] = dev.sc_start[i] + dx
            state.v[i] = dx / h
            ti.atomic_add(dev.sc_tally[2], 1)
    return dev.sc_tally[2]


@ti.kernel
def self_collision_detect(dev: ti.template(), cfg: ti.template(), state: ti.template(), dt: ti.f64,
                          thickness: ti.f64, friction: ti.f64, stiffness: ti.f64,
                          serial: ti.template()) -> ti.types.vector(6, ti.f64):
    """``detect`` on ``state`` after a step of dt (s) from ``sc_start``: thickness (m),
    friction (mu), stiffness (N/m); ``serial``: in one serial loop (small models, where
    a parallel loop's start costs more than its work)."""
    out = ti.Vector.zero(ti.f64, 6)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            result = detect(dev, cfg, state, dt, thickness, friction, stiffness)
            out = result
    else:
        result = detect(dev, cfg, state, dt, thickness, friction, stiffness)
        out = result
    return out


@ti.kernel
def self_collision_bound(dev: ti.template(), cfg: ti.template(), state: ti.template(), dt: ti.f64,
                         thickness: ti.f64, from_list: ti.template(), serial: ti.template()) -> ti.i32:
    """``bound`` after ``self_collision_detect``; returns the particles held back. (The
    sweeping variant, ``from_list`` False, is compiled only if a list overflows.)"""
    out = 0
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            held = bound(dev, cfg, state, dt, thickness, from_list)
            out = held
    else:
        held = bound(dev, cfg, state, dt, thickness, from_list)
        out = held
    return out
