"""Closest points of a mesh's primitives (exact, degenerate cases included): point to
segment, point to triangle, segment to segment. Used by the self-collision pass
(``kernels/self_collision.py``) and the implicit solve's pairs (``kernels/pair_penalty.py``)."""

import taichi as ti


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
def listed_pair(x, idx, kind, real: ti.template()):
    """(distance in m, signed weights) of a pair of the self-collision list at positions
    x: particles ``idx``, ``kind`` 1: edge-edge (idx[0:2] and idx[2:4]), else
    point-triangle (idx[0] and idx[1:4]); the weights are side A's positive, side B's
    negative, so that sum w_k x_k = p - q between the closest points."""
    d = ti.cast(0, real)
    w = ti.Vector.zero(real, 4)
    if kind == 1:
        dee, s, u = segment_segment(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
        d = dee
        w = ti.Vector([1 - s, s, u - 1, -u], real)
    else:
        dpt, b = point_triangle(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
        d = dpt
        w = ti.Vector([1, -b[0], -b[1], -b[2]], real)
    return d, w
