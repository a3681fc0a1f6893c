"""The box collider: a solid axis-aligned box, its edges optionally rounded."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from massspring.kernels.contact import BoxKind
from massspring.support.validate import real_number

from .base import Collider, box_corners, vector

CELLS = 8  # cells along each edge of a drawn box face


@dataclass(frozen=True)
class Box(Collider):
    """A solid axis-aligned box between the corners ``lower`` and ``upper`` (lower < upper on
    every axis), its edges and corners rounded with ``radius`` (m, 0: sharp; at most half
    its smallest side).

    Contact is per particle, so a spring between a particle on the top and one down a
    side cuts across a sharp edge, and the last particle on the top carries the whole
    pull of the overhang, pointing into the top: friction there holds a cloth that would
    slide off a real table. A rounded edge (a radius of a spring length or more) spreads
    the turn over several particles, as a real cloth wraps an edge. It is drawn (and
    written to USD) with sharp edges.
    """

    lower: tuple
    upper: tuple
    radius: float = 0.0
    kernel: ClassVar[type] = BoxKind
    GEOMETRY: ClassVar[tuple] = ("lower", "upper")
    ARRAYS: ClassVar[tuple] = ("lower", "upper", "radius")

    def __post_init__(self):
        object.__setattr__(self, "lower", vector("lower", self.lower))
        object.__setattr__(self, "upper", vector("upper", self.upper))
        for axis, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            if not lo < hi:
                raise ValueError(f"lower: must be < upper on every axis; on {'xyz'[axis]} lower is {lo:g} "
                                 f"and upper {hi:g}")
        radius = real_number("radius", self.radius)
        half = 0.5 * min(hi - lo for lo, hi in zip(self.lower, self.upper))
        if not 0 <= radius <= half:
            raise ValueError(f"radius: must be within [0, {half:g}] (half the smallest side), got {radius:g}")
        object.__setattr__(self, "radius", radius)
        super().__post_init__()

    def signed_distance(self, points):
        """As ``kernels/contact.py``'s ``BoxKind``, rounded edges included."""
        lower, upper = np.array(self.lower), np.array(self.upper)
        a = np.abs(np.asarray(points, dtype=np.float64) - 0.5 * (lower + upper)) - (0.5 * (upper - lower) - self.radius)
        outside = np.linalg.norm(np.maximum(a, 0.0), axis=1)
        return np.where(outside > 0, outside, a.max(axis=1)) - self.radius

    def corners(self):
        return box_corners(self.lower, self.upper)

    def surface(self):
        lower, upper = np.array(self.lower), np.array(self.upper)
        steps = np.linspace(0.0, 1.0, CELLS + 1)
        tris, normals = [], []
        for axis in range(3):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            for side, level in ((-1.0, lower[axis]), (1.0, upper[axis])):
                a, b = np.meshgrid(lower[u] + steps * (upper[u] - lower[u]),
                                   lower[v] + steps * (upper[v] - lower[v]), indexing="ij")
                grid = np.zeros(a.shape + (3,))
                grid[..., axis], grid[..., u], grid[..., v] = level, a, b
                quads = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]],
                                 axis=2).reshape(-1, 4, 3)
                tris.append(np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))
                normal = np.zeros(3)
                normal[axis] = side
                normals.append(np.tile(normal, (len(tris[-1]), 1)))
        return np.concatenate(tris), np.concatenate(normals)

    def hides(self, points, directions, tiny):
        safe = np.where(np.abs(directions) > 1e-12, directions, 1e-12)
        t1, t2 = (np.array(self.lower) - points) / safe, (np.array(self.upper) - points) / safe
        near, far = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
        return (near > tiny) & (near <= far)

    def usd_shape(self, stage, path, size):
        from pxr import Gf, UsdGeom

        prim = UsdGeom.Cube.Define(stage, path)
        prim.CreateSizeAttr(1.0)
        translate = prim.AddTranslateOp()
        prim.AddScaleOp().Set(Gf.Vec3f(*(np.asarray(self.upper) - np.asarray(self.lower))))
        return translate

    def origin(self):
        return (np.asarray(self.lower) + np.asarray(self.upper)) / 2
