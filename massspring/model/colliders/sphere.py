"""The sphere collider: a solid ball."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from massspring.kernels.contact import SphereKind
from massspring.support.validate import real_number

from .base import Collider, box_corners, vector

BANDS = (12, 24)  # latitude and longitude bands of a drawn sphere


@dataclass(frozen=True)
class Sphere(Collider):
    """A solid ball of ``radius`` (> 0) about ``center``."""

    center: tuple
    radius: float
    kernel: ClassVar[type] = SphereKind
    GEOMETRY: ClassVar[tuple] = ("center",)
    ARRAYS: ClassVar[tuple] = ("center", "radius")

    def __post_init__(self):
        object.__setattr__(self, "center", vector("center", self.center))
        radius = real_number("radius", self.radius)
        if not radius > 0:
            raise ValueError(f"radius: must be > 0, got {radius:g}")
        object.__setattr__(self, "radius", radius)
        super().__post_init__()

    def signed_distance(self, points):
        return np.linalg.norm(np.asarray(points, dtype=np.float64) - self.center, axis=1) - self.radius

    def corners(self):
        return box_corners(np.array(self.center) - self.radius, np.array(self.center) + self.radius)

    def surface(self):
        lat, lon = BANDS
        theta = np.linspace(0.0, np.pi, lat + 1)
        phi = np.linspace(0.0, 2 * np.pi, lon + 1)
        points = np.stack(np.meshgrid(theta, phi, indexing="ij"), axis=-1)
        unit = np.stack([np.sin(points[..., 0]) * np.cos(points[..., 1]),
                         np.sin(points[..., 0]) * np.sin(points[..., 1]), np.cos(points[..., 0])], axis=-1)
        quads = np.stack([unit[:-1, :-1], unit[1:, :-1], unit[1:, 1:], unit[:-1, 1:]], axis=2).reshape(-1, 4, 3)
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        normals = tris.mean(axis=1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return np.array(self.center) + self.radius * tris, normals

    def hides(self, points, directions, tiny):
        offset = points - self.center
        b = np.einsum("ij,ij->i", offset, directions)
        c = np.einsum("ij,ij->i", offset, offset) - self.radius ** 2
        # outside (c > 0), the sphere ahead (b < 0) and the ray meets it (b^2 > c)
        return (c > tiny * self.radius) & (b < 0) & (b * b > c)

    def usd_shape(self, stage, path, size):
        from pxr import Gf, UsdGeom

        prim = UsdGeom.Sphere.Define(stage, path)
        prim.CreateRadiusAttr(self.radius)
        prim.CreateExtentAttr([Gf.Vec3f(-self.radius), Gf.Vec3f(self.radius)])
        return prim.AddTranslateOp()

    def origin(self):
        return np.array(self.center)
