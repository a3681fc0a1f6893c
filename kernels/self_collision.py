"""Self-collision of a triangle mesh: a pass after every step of every integrator.

After an integrator has taken a step from the start positions x0 (``dev.sc_start``)
to a candidate state (x, v), ``self_collision_check`` asks whether every particle is
still within its free distance of its anchor (0. below); if so the step stands as it
is, else ``self_collision_detect`` and ``self_collision_bound`` run the full pass:

0. Reuse (after the Verlet lists of molecular dynamics and the per-vertex bounds of
   Offset Geometric Contact). A full pass ends by setting each particle's anchor
   (``sc_anchor``) to its position and its free distance (``sc_free``) to GAMMA times
   the smallest (distance - thickness) of its listed pairs at the step's end, at most
   GAMMA times the listing's reach (below). While every particle stays within its free
   distance of its anchor, the two primitives of any pair, listed or not, move
   towards each other by less than (their distance - thickness): no pair comes
   within ``thickness`` (so no repulsion is due) and none touches, and the step needs
   no pass. Particles end within thickness / 2 of their paths' boxes, so pairs
   whose boxes grown by m do not meet end more than 2 m - thickness apart: with
   m = thickness (every pair within thickness at the end is listed, as
   ``kernels/pair_penalty.py`` needs) they get no free distance, and a step whose
   particles moved less than REUSE_BELOW x thickness (explicit steps) lists pairs
   with m = REUSE_MARGIN x thickness, which gives them GAMMA x thickness.

1. Pairs. Each particle's swept box is the box of its straight path from x0 to the
   step's candidate x, grown by the listing margin m (thickness, or REUSE_MARGIN x
   thickness, 0. above); a triangle's or an edge's is its
   particles' together. Every pair of primitives that share no particle and whose
   swept boxes meet is found: point-triangle pairs and edge-edge pairs. Broad phase:
   two spatial hashes, of the particles' and of the edges' boxes by their low
   corners, in cells as large as the largest edge box along each axis, built by
   counting sort; a box then meets only boxes starting in 3 x 3 x 3 cells, so the work
   is linear in the mesh size. Narrow phase at x0: exact closest points and distance
   d (``point_triangle``, ``segment_segment``, degenerate primitives included). The
   pairs go to the pair list ``pl`` (its own bundle: ``pidx``, ``pw``, ``pkind``); a
   pass whose pairs do not fit is undone (``self_collision_restore``) and run again
   with a list large enough (``massspring/passes/self_collision/__init__.py``'s ``Pass``).
2. Repulsion (in the spirit of Bridson, Fedkiw and Anderson 2002). A pair closer
   than ``thickness`` gets an inelastic normal impulse that stops the approach of its
   closest points over the step and pushes them apart, at most to separate them at
   0.1 (thickness - d) / dt and at most a spring of ``stiffness`` would in dt, with
   Coulomb friction (mu) on the tangential relative velocity; the impulses are spread
   over the pair's four particles by their barycentric weights and inverse masses and
   averaged per particle (Jacobi). With the pairs in the implicit solve
   (``kernels/pair_penalty.py``), whose penalty pushed the pair apart by J = dt k
   (thickness - d - dt vn) (N s; its linearised force at the step's end, vn the pair's
   normal relative velocity over the step), J brings friction too: each particle's velocity
   change that would stop its pairs' tangential relative velocities (its share of
   each pair's, by weight and inverse mass), averaged over its pairs by their normal
   impulses |w_k| J, at most mu times their sum over its mass. The step's displacement x - x0 and
   the velocity change by the same amount, within the particle's path box grown by
   thickness / 2 (inside its swept box).
3. Displacement bounds on the separating plane (after the bounds of Offset Geometric
   Contact, Chen et al. 2025). A pair's closest points p - q = d n give a plane
   between its primitives. Every point of A starts at least d along n from every
   point of B, so along a straight step the two stay apart while the largest
   displacement of an A particle towards B plus the largest of a B particle towards A
   is at most 2 GAMMA (d - OFFSET thickness) (GAMMA < 1/2): a pair that approaches no
   faster stands as the step left it, whatever its common motion (a falling or
   swinging cloth). A pair that approaches faster bounds its own particles from then
   on: each may move towards the other side by at most GAMMA (d - OFFSET thickness),
   which meets the first bound too. A displacement that goes further first loses that
   excess along n (averaged over its pairs, within its box), and then, if a pair still
   objects (by more than ``BOUND_SLACK`` x thickness: not a particle the push left on
   its bound, to round-off), is scaled down until all agree (a smaller scale keeps every such bound
   met: each holds at x0). Holding particles back can make another pair approach too
   fast, so rounds repeat until one sets no new pair (after ``BOUND_ROUNDS`` every
   pair bounds its own). The primitives of a listed pair then stay on their sides of
   a plane along the whole straight step, and those of an unlisted pair in disjoint
   boxes, so no pair touches during the step and no edge passes through a triangle it
   does not share a particle with. A particle held back ends at x0 + s (x - x0) with
   velocity s (x - x0) / dt. Pinned particles are neither pushed nor held back.

Deterministic for any thread count: distances are reduced with atomic min/max (exact),
impulses summed in 64-bit fixed point (integer addition: order-free), and nothing
reads the order within a hash cell.

Fields (``massspring/passes/self_collision/__init__.py`` declares them; n particles, t triangles, e
edges, T cells per table): ``sc_tris`` (t,) int 3-vectors, ``sc_edges`` (e,) int
2-vectors, ``sc_count`` (t, e, T), ``sc_start``, ``sc_anchor``, ``sc_end`` (n,) vec3 m,
``sc_vend`` (n,) vec3 m/s, ``sc_free`` (n,) m, ``sc_scale`` (n,),
``sc_dv`` (n,) int64 3-vectors (fixed point, ``SCALE`` per m/s), ``sc_hits`` (n,),
``sc_vcell``/``sc_ecell`` (T,), ``sc_vfirst``/``sc_efirst`` (T + 1,), ``sc_vitem``
(n,), ``sc_eitem`` (e,) int32, ``sc_box`` (10,) f64 (cell span, largest displacement,
smallest distance, listing margin), ``sc_tally`` (5,) int32 (pairs found, pairs
repelled, particles held back, particles out of their free distance, pairs newly set
to bound their own particles). The pair list ``pl`` (P pairs): ``pidx`` (P,) int
4-vectors, ``pw`` (P,) 4-vectors, ``pkind`` (P,), ``pbound`` (P,): RELATIVE, OWN or
NEW (step 3).
"""

import taichi as ti

from .constraints import is_pinned
from .pair_penalty import collect
from .proximity import listed_pair, point_triangle, segment_segment

GAMMA = 0.45  # a particle moves at most this fraction of its nearest pair's distance
SEPARATION = 0.1  # a repelled pair separates at most at this fraction of its gap per step
SCALE = 2.0**40  # fixed-point units of sc_dv per m/s
DV_LIMIT = 1e6  # m/s: a pair's velocity change is clipped to this before it becomes fixed point
CELL_LIMIT = 2**30  # cell coordinates are clipped to +-this
POINT_TRIANGLE = (1, -1, -1, -1)  # the sides of a pair's particles: a point (A), a triangle (B)
EDGE_EDGE = (1, 1, -1, -1)  # two edges
REPEL, PROJECT, BOUND, LIST = 0, 1, 2, 3  # the passes over the pairs
RELATIVE, OWN, NEW = 0, 1, 2  # ``pbound``: a pair checks its relative approach, bounds its own particles (newly)
OFFSET = 0.5  # pairs closer than this fraction of the thickness may not approach at all
REUSE_BELOW = 0.05  # a step whose particles moved less than this x thickness lists pairs for reuse
BOUND_ROUNDS = 8  # rounds of step 3 before every pair bounds its own particles
REUSE_MARGIN = 1.5  # ... in boxes grown by this x thickness (unlisted pairs then end > 2 x thickness apart)
BOUND_SLACK = 1e-9  # x thickness: a particle this little past its bound is not held back (step 3)


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
def vertex_box(dev, i, margin):
    """Particle i's swept box: its straight path from x0 (``sc_start``) to the step's
    candidate position (``sc_end``), grown by ``margin`` (m)."""
    a = dev.sc_start[i]
    b = dev.sc_end[i]
    return ti.min(a, b) - margin, ti.max(a, b) + margin


@ti.func
def edge_box(dev, e, margin):
    """Edge e's swept box: its two particles' boxes together."""
    ends = dev.sc_edges[e]
    lo_a, hi_a = vertex_box(dev, ends[0], margin)
    lo_b, hi_b = vertex_box(dev, ends[1], margin)
    return ti.min(lo_a, lo_b), ti.max(hi_a, hi_b)


@ti.func
def key(dev, i, inverse, size, margin, edges: ti.template()):
    """The bucket of vertex i's swept box's low corner, or (``edges``) edge i's."""
    lo, _ = vertex_box(dev, i, margin)
    if ti.static(edges):
        low, _ = edge_box(dev, i, margin)
        lo = low
    return bucket(cell_of(lo, inverse), size)


@ti.func
def count_sort(dev, cells: ti.template(), first: ti.template(), items: ti.template(), size, inverse, margin, count,
               edges: ti.template()):
    """Hash items 0..count-1 (vertices, or ``edges``) by ``key``: ``first[b]:first[b + 1]``
    of ``items`` lists bucket b's items (in no fixed order)."""
    for b in range(size):
        cells[b] = 0
    for i in range(count):
        ti.atomic_add(cells[key(dev, i, inverse, size, margin, edges)], 1)
    first[0] = 0
    ti.loop_config(serialize=True)
    for b in range(size):
        first[b + 1] = first[b] + cells[b]
        cells[b] = 0
    for i in range(count):
        b = key(dev, i, inverse, size, margin, edges)
        items[first[b] + ti.atomic_add(cells[b], 1)] = i


@ti.func
def pair(dev, cfg: ti.template(), pl, state, idx, w, d, h, thickness, mu, ks, sides: ti.template(), phase: ti.template()):
    """A pair of primitives at distance d (m) at x0: particles ``idx``, weights ``w``
    (side A positive, side B negative; sum w x0 = p - q, from B's closest point q to
    A's p), ``sides``: each particle's side (+1: A, -1: B), ``POINT_TRIANGLE`` or ``EDGE_EDGE``.
    ``LIST``: the pair into the list (while it has room); ``REPEL``: that and the pair's
    repulsion impulse if d < ``thickness``. ``BOUND``: each
    of its particles k, of side sign s_k, may move at most GAMMA d towards the other
    side, s_k n . dx_k >= -GAMMA d with n = (p - q) / d: a particle whose displacement
    dx_k (the state's, less x0) breaks it by more than ``BOUND_SLACK`` x thickness (not
    one that ``PROJECT`` left on it, to round-off) gets the scale that meets it
    (``sc_scale``, the smallest over its pairs; a displacement scaled down keeps every
    bound it met)."""
    gap_vector = ti.Vector.zero(cfg.real, 3)
    for k in ti.static(range(4)):
        gap_vector += w[k] * dev.sc_start[idx[k]]
    length = gap_vector.norm()
    if ti.static(phase == PROJECT or phase == BOUND):
        if length > 0:
            normal = gap_vector / length
            allowed = GAMMA * ti.max(length - OFFSET * thickness, 0)
            slack = allowed  # a push leaves a particle on its bound to round-off: it stands
            if ti.static(phase == BOUND):
                slack += BOUND_SLACK * thickness
            for k in ti.static(range(4)):
                i = idx[k]
                toward = -sides[k] * normal.dot(state.x[i] - dev.sc_start[i])
                if toward > slack and not is_pinned(i, dev, cfg):
                    if ti.static(phase == PROJECT):
                        ti.atomic_add(dev.sc_dv[i], fixed_point((toward - allowed) * sides[k] * normal))
                        ti.atomic_add(dev.sc_hits[i], 1)
                    else:
                        ti.atomic_min(dev.sc_scale[i], allowed / toward)
        else:
            for k in ti.static(range(4)):
                ti.atomic_min(dev.sc_scale[idx[k]], 0)
    else:
        slot = ti.atomic_add(dev.sc_tally[0], 1)
        if slot < pl.pidx.shape[0]:
            pl.pidx[slot] = idx
            pl.pw[slot] = w
            pl.pkind[slot] = sides[1]  # 1: edge-edge, -1: point-triangle
            pl.pbound[slot] = RELATIVE
        ti.atomic_min(dev.sc_box[8], ti.cast(d, ti.f64))
        if ti.static(phase == REPEL) and d < thickness and length > 0:
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
                tangential = rel - vn * normal
                vt = tangential.norm()
                if dvn > 0:
                    change = dvn * normal
                    if vt > 0:
                        change -= ti.min(mu * dvn, vt) / vt * tangential
                    spread(dev, cfg, idx, w, change / inverse)
                if ti.static(cfg.self_pairs):  # the friction of the implicit solve's penalty impulse
                    pushed = h * ks * ti.max(gap - h * vn, 0)  # the solve's impulse: its force at x_n + h v
                    for k in ti.static(range(4)):
                        i = idx[k]
                        if not is_pinned(i, dev, cfg):
                            weight = pushed * ti.abs(w[k])
                            want = -w[k] / (inverse * dev.mass[i]) * tangential
                            item = ti.Vector([weight * want[0], weight * want[1], weight * want[2], weight])
                            ti.atomic_add(dev.sp_friction[i], fixed_point(item))


@ti.func
def fixed_point(values):
    """``values`` (a vector, m/s or what sums with them) clipped to +-DV_LIMIT and
    rounded to int64 units of 1 / SCALE: sums of these are exact in any order."""
    return ti.Vector([ti.cast(ti.round(ti.min(ti.max(values[c], -DV_LIMIT), DV_LIMIT) * SCALE), ti.i64)
                      for c in ti.static(range(values.n))])


@ti.func
def spread(dev, cfg: ti.template(), idx, w, impulse):
    """Add a pair's ``impulse`` (N s, on side A; side B gets its opposite) to its free
    particles' velocity changes ``sc_dv`` (by weight and inverse mass), counted in
    ``sc_hits``."""
    for k in ti.static(range(4)):
        i = idx[k]
        if not is_pinned(i, dev, cfg):
            ti.atomic_add(dev.sc_dv[i], fixed_point(w[k] * impulse / dev.mass[i]))
            ti.atomic_add(dev.sc_hits[i], 1)


@ti.func
def overlap(lo_a, hi_a, lo_b, hi_b):
    return (lo_a <= hi_b).all() and (lo_b <= hi_a).all()


@ti.func
def vertex_candidates(dev, cfg: ti.template(), pl, state, cell, corner, tlo, thi, inverse, size, margin, h, thick, mu, ks,
                      phase: ti.template()):
    """Point-triangle pairs of triangle ``corner`` (swept box tlo, thi) with the particles
    whose swept boxes start in ``cell`` and meet it."""
    bk = bucket(cell, size)
    for slot in range(dev.sc_vfirst[bk], dev.sc_vfirst[bk + 1]):
        p = dev.sc_vitem[slot]
        if p != corner[0] and p != corner[1] and p != corner[2]:
            lo, hi = vertex_box(dev, p, margin)
            if overlap(lo, hi, tlo, thi) and (cell_of(lo, inverse) == cell).all():
                d, w = point_triangle(dev.sc_start[p], dev.sc_start[corner[0]], dev.sc_start[corner[1]],
                                      dev.sc_start[corner[2]])
                pair(dev, cfg, pl, state, ti.Vector([p, corner[0], corner[1], corner[2]]),
                     ti.Vector([1, -w[0], -w[1], -w[2]], cfg.real), d, h, thick, mu, ks, POINT_TRIANGLE, phase)


@ti.func
def edge_candidates(dev, cfg: ti.template(), pl, state, cell, e, ends, elo, ehi, inverse, size, margin, h, thick, mu, ks,
                    phase: ti.template()):
    """Edge-edge pairs of edge e (``ends``, swept box elo, ehi) with the later edges whose
    swept boxes start in ``cell`` and meet it."""
    bk = bucket(cell, size)
    for slot in range(dev.sc_efirst[bk], dev.sc_efirst[bk + 1]):
        f = dev.sc_eitem[slot]
        other = dev.sc_edges[f]
        if f > e and other[0] != ends[0] and other[0] != ends[1] and other[1] != ends[0] and other[1] != ends[1]:
            lo, hi = edge_box(dev, f, margin)
            if overlap(lo, hi, elo, ehi) and (cell_of(lo, inverse) == cell).all():
                d, s, u = segment_segment(dev.sc_start[ends[0]], dev.sc_start[ends[1]], dev.sc_start[other[0]],
                                          dev.sc_start[other[1]])
                pair(dev, cfg, pl, state, ti.Vector([ends[0], ends[1], other[0], other[1]]),
                     ti.Vector([1 - s, s, u - 1, -u], cfg.real), d, h, thick, mu, ks, EDGE_EDGE, phase)


@ti.func
def pairs(dev, cfg: ti.template(), pl, state, tris, edges, span, size, margin, h, thick, mu, ks, phase: ti.template()):
    """Every point-triangle and edge-edge pair whose swept boxes meet, through ``pair`` in
    ``phase``. Cells are ``span`` (per axis, m: the largest swept edge box), so a box meets
    only boxes starting in the 3 x 3 x 3 cells from its low corner less span to its high
    corner."""
    inverse = 1 / span
    for t in range(tris):  # point-triangle pairs
        corner = dev.sc_tris[t]
        lo_a, hi_a = vertex_box(dev, corner[0], margin)
        lo_b, hi_b = vertex_box(dev, corner[1], margin)
        lo_c, hi_c = vertex_box(dev, corner[2], margin)
        tlo = ti.min(ti.min(lo_a, lo_b), lo_c)
        thi = ti.max(ti.max(hi_a, hi_b), hi_c)
        first = cell_of(tlo - span, inverse)
        last = cell_of(thi, inverse)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    vertex_candidates(dev, cfg, pl, state, ti.Vector([cx, cy, cz]), corner, tlo, thi, inverse, size,
                                      margin, h, thick, mu, ks, phase)
    for e in range(edges):  # edge-edge pairs
        ends = dev.sc_edges[e]
        elo, ehi = edge_box(dev, e, margin)
        first = cell_of(elo - span, inverse)
        last = cell_of(ehi, inverse)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    edge_candidates(dev, cfg, pl, state, ti.Vector([cx, cy, cz]), e, ends, elo, ehi, inverse, size,
                                    margin, h, thick, mu, ks, phase)


@ti.func
def clip(dev, cfg: ti.template(), state, i, margin, h):
    """Keep particle i within its path box grown by ``margin`` (m; within its swept box,
    what the broad phase assumed), its velocity changed with its position."""
    lo, hi = vertex_box(dev, i, margin)
    x = state.x[i]
    inside = ti.min(ti.max(x, lo), hi)
    state.v[i] += (inside - x) / h
    state.x[i] = inside


@ti.func
def listed_pairs(dev, cfg: ti.template(), pl, state, count, thick, go, phase: ti.template()):
    """``pair`` in ``phase`` over the pairs of the pair list ``pl`` newly set to bound their
    own particles (``pbound`` NEW), among its first ``count``; none unless ``go``."""
    for slot in range(count):
        if go and pl.pbound[slot] == NEW:
            idx = pl.pidx[slot]
            w = pl.pw[slot]
            if pl.pkind[slot] == 1:  # the second particle's side
                pair(dev, cfg, pl, state, idx, w, 0, 1, thick, 0, 0, EDGE_EDGE, phase)
            else:
                pair(dev, cfg, pl, state, idx, w, 0, 1, thick, 0, 0, POINT_TRIANGLE, phase)


@ti.func
def approach_allowed(dev, cfg: ti.template(), state, idx, w, kind, thick):
    """Whether a listed pair's particles (``idx``, weights ``w``, ``kind`` as ``pkind``)
    approach each other by at most 2 GAMMA (d - OFFSET thickness) along the normal n of
    their separating plane at x0 (step 3 of the module docstring): the largest
    displacement of a side-A particle towards B plus the largest of a side-B particle
    towards A. False for a pair with d = 0."""
    gap_vector = ti.Vector.zero(cfg.real, 3)
    for k in ti.static(range(4)):
        gap_vector += w[k] * dev.sc_start[idx[k]]
    length = gap_vector.norm()
    ok = False
    if length > 0:
        normal = gap_vector / length
        sides = ti.Vector([1, kind, -1, -1])
        toward = ti.Vector([-sides[k] * normal.dot(state.x[idx[k]] - dev.sc_start[idx[k]])
                            for k in ti.static(range(4))])
        side_a = ti.max(toward[0], ti.select(kind == 1, toward[1], toward[0]))
        side_b = ti.max(toward[2], toward[3])
        if kind == -1:
            side_b = ti.max(side_b, toward[1])
        ok = side_a + side_b <= 2 * GAMMA * ti.max(length - OFFSET * thick, 0)
    return ok


@ti.kernel
def self_collision_begin(dev: ti.template(), state: ti.template(), fresh: ti.template(), serial: ti.template()):
    """x0 = the state's positions (``serial``: in a serial loop); ``fresh``: anchors there
    too, with no free distance (the next step runs the full pass)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        dev.sc_start[i] = state.x[i]
        if ti.static(fresh):
            dev.sc_anchor[i] = state.x[i]
            dev.sc_free[i] = 0


@ti.kernel
def self_collision_check(dev: ti.template(), state: ti.template(), serial: ti.template()) -> ti.i32:
    """The particles of ``state`` farther than their free distance from their anchors
    (0. of the module docstring); if none, x0 = the state's positions for the next step."""
    dev.sc_tally[3] = 0
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        if (state.x[i] - dev.sc_anchor[i]).norm() > dev.sc_free[i]:
            ti.atomic_add(dev.sc_tally[3], 1)
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        if dev.sc_tally[3] == 0:
            dev.sc_start[i] = state.x[i]
    return dev.sc_tally[3]


@ti.func
def broad_phase(dev, cfg: ti.template(), margin):
    """The two hashes of the swept boxes (``sc_start`` to ``sc_end``) grown by ``margin``
    (m), the tallies reset; returns the cells' span (m per axis)."""
    for k in range(3):
        dev.sc_tally[k] = 0
        dev.sc_box[k] = 0.0
    dev.sc_box[8] = 1e300
    dev.sc_box[9] = ti.cast(margin, ti.f64)
    edges = dev.sc_count[1]
    size = dev.sc_count[2]
    for e in range(edges):
        lo, hi = edge_box(dev, e, margin)
        extent = ti.cast(hi - lo, ti.f64)
        for k in ti.static(range(3)):
            ti.atomic_max(dev.sc_box[k], extent[k])
    span = ti.Vector([dev.sc_box[k] for k in ti.static(range(3))], cfg.real)
    inverse = 1 / span
    count_sort(dev, dev.sc_vcell, dev.sc_vfirst, dev.sc_vitem, size, inverse, margin, dev.size[0], False)
    count_sort(dev, dev.sc_ecell, dev.sc_efirst, dev.sc_eitem, size, inverse, margin, edges, True)
    return span


@ti.kernel
def self_collision_list(dev: ti.template(), cfg: ti.template(), pl: ti.template(), state: ti.template(),
                        thickness: ti.f64, serial: ti.template()) -> ti.i32:
    """List the pairs of the state as it stands into ``pl`` (no step: x0 = x, boxes grown
    by ``thickness``), as a pass would have, so every pair within ``thickness`` is listed.
    Returns the pairs found (more than ``pl`` holds: list again in a larger one)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        dev.sc_start[i] = state.x[i]
        dev.sc_end[i] = state.x[i]
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            list_pairs(dev, cfg, pl, state, thickness)
    else:
        list_pairs(dev, cfg, pl, state, thickness)
    return dev.sc_tally[0]


@ti.func
def list_pairs(dev, cfg: ti.template(), pl, state, thickness):
    thick = ti.cast(thickness, cfg.real)
    span = broad_phase(dev, cfg, thick)
    pairs(dev, cfg, pl, state, dev.sc_count[0], dev.sc_count[1], span, dev.sc_count[2], thick, 1, thick, 0, 0, LIST)


@ti.kernel
def self_collision_restore(dev: ti.template(), state: ti.template(), serial: ti.template()):
    """The state as the step left it, before ``self_collision_detect`` changed it (to run
    the pass again with a larger pair list)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for i in range(dev.size[0]):
        state.x[i] = dev.sc_end[i]
        state.v[i] = dev.sc_vend[i]


@ti.func
def detect(dev, cfg: ti.template(), pl, state, dt, thickness, friction, stiffness):
    """Steps 1 and 2 of the pass (module docstring): the listing margin, the swept boxes,
    the hashes, the pairs (listed in ``pl`` while it has room), their repulsion applied
    within the boxes. Returns (pairs, pairs repelled, 0, the largest displacement in m,
    the smallest distance of a pair in m, 1 if the pairs fitted the list)."""
    n = dev.size[0]
    h = ti.cast(dt, cfg.real)
    thick = ti.cast(thickness, cfg.real)
    mu = ti.cast(friction, cfg.real)
    ks = ti.cast(stiffness, cfg.real)
    dev.sc_box[6] = 0.0
    for i in range(n):
        dev.sc_end[i] = state.x[i]
        dev.sc_vend[i] = state.v[i]
        ti.atomic_max(dev.sc_box[6], ti.cast((state.x[i] - dev.sc_start[i]).norm(), ti.f64))
        dev.sc_dv[i] = ti.Vector.zero(ti.i64, 3)
        dev.sc_hits[i] = 0
        if ti.static(cfg.self_pairs):
            dev.sp_friction[i] = ti.Vector.zero(ti.i64, 4)
    margin = thick
    if dev.sc_box[6] < REUSE_BELOW * thickness:
        margin = REUSE_MARGIN * thick
    span = broad_phase(dev, cfg, margin)
    pairs(dev, cfg, pl, state, dev.sc_count[0], dev.sc_count[1], span, dev.sc_count[2], margin, h, thick, mu, ks,
          REPEL)
    for i in range(n):
        hits = dev.sc_hits[i]
        touched = hits > 0
        du = ti.Vector.zero(cfg.real, 3)
        if hits > 0:
            du = ti.cast(dev.sc_dv[i], cfg.real) / ti.cast(SCALE * hits, cfg.real)
        if ti.static(cfg.self_pairs):
            sums = ti.cast(dev.sp_friction[i], cfg.real) / ti.cast(SCALE, cfg.real)
            if sums[3] > 0:
                want = ti.Vector([sums[0], sums[1], sums[2]]) / sums[3]
                limit = mu * sums[3] / dev.mass[i]
                size = want.norm()
                if size > limit:
                    want *= limit / size
                touched = True
                du += want
        if touched and not is_pinned(i, dev, cfg):
            state.x[i] += h * du
            state.v[i] += du
            clip(dev, cfg, state, i, 0.5 * thick, h)
    fits = 1 if dev.sc_tally[0] <= pl.pidx.shape[0] else 0
    return ti.Vector([dev.sc_tally[0], dev.sc_tally[1], 0, dev.sc_box[6], dev.sc_box[8], fits], ti.f64)


@ti.func
def anchor(dev, cfg: ti.template(), pl, state, count, thick, margin, go):
    """Step 0 of the pass (module docstring) at the pass's end (if ``go``): anchors at
    the state's positions (and x0 for the next step), free distances GAMMA (d -
    thickness) over each particle's listed pairs, at most GAMMA (2 margin - 2 thickness)
    (unlisted pairs end more than 2 margin - thickness apart)."""
    cap = GAMMA * ti.max(2 * margin - 2 * thick, 0)
    for i in range(dev.size[0]):
        if go:
            dev.sc_start[i] = state.x[i]
            dev.sc_anchor[i] = state.x[i]
            dev.sc_free[i] = cap
    for slot in range(count):
        if go:
            idx = pl.pidx[slot]
            d, _ = listed_pair(state.x, idx, pl.pkind[slot], cfg.real)
            allowed = GAMMA * ti.max(d - thick, 0)
            for k in ti.static(range(4)):
                ti.atomic_min(dev.sc_free[idx[k]], allowed)


@ti.func
def bound(dev, cfg: ti.template(), pl, state, dt, thickness, first, every):
    """One round of step 3 of the pass (module docstring) over the listed pairs: each
    pair still checked by its relative approach (``pbound`` RELATIVE) whose particles
    approach by more than it allows (all of them with ``every``) bounds its own
    particles from now on; those newly set are projected (``first``: the round after
    ``detect``) and then held back. A round that sets none leaves every pair's bound
    met and is the last: it counts the particles held back and sets step 0's anchors.
    Returns (pairs newly set, particles held back)."""
    n = dev.size[0]
    h = ti.cast(dt, cfg.real)
    thick = ti.cast(thickness, cfg.real)
    count = dev.sc_tally[0]
    dev.sc_tally[4] = 0
    for slot in range(count):
        if pl.pbound[slot] == RELATIVE:
            if every != 0 or not approach_allowed(dev, cfg, state, pl.pidx[slot], pl.pw[slot], pl.pkind[slot], thick):
                pl.pbound[slot] = NEW
                ti.atomic_add(dev.sc_tally[4], 1)
    for i in range(n):
        dev.sc_dv[i] = ti.Vector.zero(ti.i64, 3)
        if first != 0:
            dev.sc_hits[i] = 0
        dev.sc_scale[i] = 1
    listed_pairs(dev, cfg, pl, state, count, thick, first != 0, PROJECT)
    for i in range(n):
        hits = dev.sc_hits[i]
        if first != 0 and hits > 0:
            dx = ti.cast(dev.sc_dv[i], cfg.real) / ti.cast(SCALE * hits, cfg.real)
            state.x[i] += dx
            state.v[i] += dx / h
            clip(dev, cfg, state, i, 0.5 * thick, h)
        if first != 0:
            dev.sc_hits[i] = 0
    listed_pairs(dev, cfg, pl, state, count, thick, True, BOUND)
    for i in range(n):
        scale = dev.sc_scale[i]
        if scale < 1 and not is_pinned(i, dev, cfg):
            dx = scale * (state.x[i] - dev.sc_start[i])
            state.x[i] = dev.sc_start[i] + dx
            state.v[i] = dx / h
            dev.sc_hits[i] = 1  # held back
    for slot in range(count):
        if pl.pbound[slot] == NEW:
            pl.pbound[slot] = OWN
    last = dev.sc_tally[4] == 0
    dev.sc_tally[2] = 0
    for i in range(n):
        if last and dev.sc_hits[i] == 1:
            ti.atomic_add(dev.sc_tally[2], 1)
    anchor(dev, cfg, pl, state, count, thick, ti.cast(dev.sc_box[9], cfg.real), last)
    return ti.Vector([dev.sc_tally[4], dev.sc_tally[2]])


@ti.kernel
def self_collision_detect(dev: ti.template(), cfg: ti.template(), pl: ti.template(), state: ti.template(),
                          dt: ti.f64, thickness: ti.f64, friction: ti.f64, stiffness: ti.f64,
                          serial: ti.template()) -> ti.types.vector(6, ti.f64):
    """``detect`` on ``state`` after a step of dt (s) from ``sc_start``, listing into
    ``pl``: thickness (m), friction (mu), stiffness (N/m); ``serial``: in one serial loop
    (small models, where a parallel loop's start costs more than its work)."""
    out = ti.Vector.zero(ti.f64, 6)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            result = detect(dev, cfg, pl, state, dt, thickness, friction, stiffness)
            out = result
    else:
        result = detect(dev, cfg, pl, state, dt, thickness, friction, stiffness)
        out = result
    return out


@ti.kernel
def self_collision_bound(dev: ti.template(), cfg: ti.template(), pl: ti.template(), state: ti.template(),
                         dt: ti.f64, thickness: ti.f64, first: ti.i32, every: ti.i32,
                         serial: ti.template()) -> ti.types.vector(2, ti.i32):
    """A round of ``bound`` after ``self_collision_detect`` (whose pairs fitted ``pl``);
    returns (the pairs it newly set to bound their own particles, none in the last
    round; the particles held back, counted in the last round)."""
    out = ti.Vector.zero(ti.i32, 2)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            result = bound(dev, cfg, pl, state, dt, thickness, first, every)
            out = result
    else:
        result = bound(dev, cfg, pl, state, dt, thickness, first, every)
        out = result
    return out


@ti.kernel
def self_collision_solve_pairs(dev: ti.template(), cfg: ti.template(), pl: ti.template(), state: ti.template(),
                               dt: ti.f64, serial: ti.template()):
    """With ``cfg.self_pairs``: the next implicit solve's pairs (``kernels/pair_penalty.py``,
    steps of dt, s) from the pairs of ``pl`` at the state's positions, after a pass or a
    listing (one kernel for both, so a restart computes them to the bit)."""
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for _ in range(1):
            collect(dev, cfg, pl, state.x, ti.cast(dt, cfg.real))
    else:
        collect(dev, cfg, pl, state.x, ti.cast(dt, cfg.real))


@ti.kernel
def self_collision_read_pairs(pl: ti.template(), count: ti.i32, idx: ti.types.ndarray(dtype=ti.i32, ndim=2),
                              w: ti.types.ndarray(dtype=ti.f64, ndim=2), kind: ti.types.ndarray(dtype=ti.i32, ndim=1),
                              bound: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """The first ``count`` pairs of the pair list ``pl``: particles ``idx`` (count, 4),
    weights ``w`` (count, 4), ``kind`` and ``bound`` (count,) (``pkind``, ``pbound``), without
    copying the whole list out (a gradient's record of a step: ``massspring.gradients``)."""
    for slot in range(count):
        for c in ti.static(range(4)):
            idx[slot, c] = pl.pidx[slot][c]
            w[slot, c] = ti.cast(pl.pw[slot][c], ti.f64)
        kind[slot] = pl.pkind[slot]
        bound[slot] = pl.pbound[slot]
