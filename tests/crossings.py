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
