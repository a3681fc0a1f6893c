"""The plane collider: the half-space behind a plane is solid."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from massspring.kernels.contact import PlaneKind

from .base import Collider, vector


@dataclass(frozen=True)
class Plane(Collider):
    """The plane through ``point`` with outward unit ``normal``; the side it points away from is solid."""

    point: tuple
    normal: tuple
    kernel: ClassVar[type] = PlaneKind
    GEOMETRY: ClassVar[tuple] = ("point",)
    ARRAYS: ClassVar[tuple] = ("point", "normal")
    bounded: ClassVar[bool] = False

    def __post_init__(self):
        object.__setattr__(self, "point", vector("point", self.point))
        normal = np.array(vector("normal", self.normal))
        scale = float(np.abs(normal).max())
        if scale > 0:  # scaled first: the norm of (1e-200, 0, 0) underflows, that of (1e200, 1e200, 0) overflows
            normal = normal / scale
        length = float(np.linalg.norm(normal))
        if not length > 0 or not math.isfinite(length):
            raise ValueError(f"normal: must be a non-zero vector, got {list(self.normal)}")
        object.__setattr__(self, "normal", tuple(float(c) for c in normal / length))
        super().__post_init__()

    def signed_distance(self, points):
        return (np.asarray(points, dtype=np.float64) - self.point) @ np.array(self.normal)

    def cells(self, centre, half, count):
        n = np.array(self.normal)
        middle = centre - ((centre - np.array(self.point)) @ n) * n
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        edges = np.linspace(-half, half, count + 1)
        i, j = np.meshgrid(np.arange(count), np.arange(count), indexing="ij")
        i, j = i.ravel(), j.ravel()
        corners = [middle + np.outer(edges[i + a], t1) + np.outer(edges[j + b], t2)
                   for a, b in ((0, 0), (1, 0), (1, 1), (0, 1))]
        return np.stack(corners, axis=1), np.tile(n, (len(i), 1)), (i + j) % 2

    def usd_shape(self, stage, path, size):
        from pxr import Gf, UsdGeom

        prim = UsdGeom.Plane.Define(stage, path)
        prim.CreateAxisAttr(UsdGeom.Tokens.z)
        prim.CreateWidthAttr(size)
        prim.CreateLengthAttr(size)
        prim.CreateDoubleSidedAttr(True)
        translate = prim.AddTranslateOp()
        turn = Gf.Rotation(Gf.Vec3d(0.0, 0.0, 1.0), Gf.Vec3d(*self.normal))  # +z to the normal
        prim.AddOrientOp().Set(Gf.Quatf(turn.GetQuat()))
        return translate

    def origin(self):
        return np.array(self.point)
