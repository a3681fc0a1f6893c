"""The tests' own crossing counter (numpy only, independent of the project's detection):
used by tests/test_self_collision.py and benchmarks/self_collision_scenes.py."""

import numpy as np


def crossings(x, triangles, edges):
    """How many (edge, triangle) pairs without a common vertex cross: the segment meets the
    triangle (Moller-Trumbore, both end points included). An edge parallel to the triangle's
    plane to round-off (the sine of their angle under 1e-12: a flat sheet's own edges) does
    not cross it."""
    a, b, c = x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
    e1, e2 = b - a, c - a
    area = np.linalg.norm(np.cross(e1, e2), axis=1)
    count = 0
    for i, j in edges:
        d = x[j] - x[i]
        h = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, h)
        ok = np.abs(det) > 1e-12 * area * np.linalg.norm(d)
        f = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = x[i] - a
        u = f * np.einsum("ij,ij->i", s, h)
        q = np.cross(s, e1)
        v = f * (q @ d)
        t = f * np.einsum("ij,ij->i", e2, q)
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
        shared = (triangles == i).any(axis=1) | (triangles == j).any(axis=1)
        count += int(np.sum(hit & ~shared))
    return count


def _point_segment(p, a, b):
    """Distances from points p to segments ab (arrays of rows, broadcast)."""
    ab = b - a
    length2 = np.einsum("...i,...i->...", ab, ab)
    t = np.where(length2 > 0, np.einsum("...i,...i->...", p - a, ab) / np.where(length2 > 0, length2, 1), 0)
    t = np.clip(t, 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def pair_distances(x, triangles, edges):
    """The distance (m) of every point-triangle and edge-edge pair that shares no vertex,
    and the pair's four particles: (distances (k,), particles (k, 4)). A pair's distance
    is the smallest of its boundary distances (point to the triangle's edges; each end
    point to the other segment) and, where the closest points of the plane or of the
    two lines fall inside both primitives, that distance."""
    out_d, out_i = [], []
    a, b, c = x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
    normal = np.cross(b - a, c - a)
    twice_area = np.linalg.norm(normal, axis=1)
    for p in range(len(x)):
        keep = ~(triangles == p).any(axis=1)
        q = x[p]
        d = np.minimum(np.minimum(_point_segment(q, a, b), _point_segment(q, b, c)), _point_segment(q, c, a))
        flat = twice_area > 0
        n = normal / np.where(flat, twice_area, 1)[:, None]
        height = np.einsum("ij,ij->i", q - a, n)
        foot = q - height[:, None] * n
        inside = flat.copy()
        for u, v in ((a, b), (b, c), (c, a)):  # the foot is on the inner side of every edge
            inside &= np.einsum("ij,ij->i", np.cross(v - u, foot - u), normal) >= 0
        d = np.where(inside, np.minimum(d, np.abs(height)), d)
        out_d.append(d[keep])
        out_i.append(np.column_stack([np.full(keep.sum(), p), triangles[keep]]))
    e0, e1 = x[edges[:, 0]], x[edges[:, 1]]
    for k, (i, j) in enumerate(edges):
        rest = np.arange(k + 1, len(edges))
        rest = rest[~np.isin(edges[rest], (i, j)).any(axis=1)]
        p1, q1, p2, q2 = x[i], x[j], e0[rest], e1[rest]
        d = np.minimum.reduce([_point_segment(p1, p2, q2), _point_segment(q1, p2, q2),
                               _point_segment(p2, p1, q1), _point_segment(q2, p1, q1)])
        d1, d2, r = q1 - p1, q2 - p2, p1 - p2
        aa, bb, ee = d1 @ d1, d2 @ d1, np.einsum("ij,ij->i", d2, d2)
        cc, ff = r @ d1, np.einsum("ij,ij->i", d2, r)
        den = aa * ee - bb * bb
        ok = den > 1e-12 * aa * ee
        s = np.where(ok, (bb * ff - cc * ee) / np.where(ok, den, 1), -1)
        t = np.where(ok, (aa * ff - bb * cc) / np.where(ok, den, 1), -1)
        interior = ok & (s > 0) & (s < 1) & (t > 0) & (t < 1)
        line = np.linalg.norm((p1 + s[:, None] * d1) - (p2 + t[:, None] * d2), axis=1)
        out_d.append(np.where(interior, np.minimum(d, line), d))
        out_i.append(np.column_stack([np.full((len(rest), 2), (i, j)), edges[rest]]))
    return np.concatenate(out_d), np.concatenate(out_i).astype(np.int64)
