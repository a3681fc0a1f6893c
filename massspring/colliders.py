"""Colliders: rigid obstacles that particles cannot enter, static or moving at a constant velocity.

``Plane(point, normal)`` (the half-space below the plane, on the side opposite to
``normal``, is solid), ``Sphere(center, radius)`` and ``Box(lower, upper)`` (axis-aligned,
between two corners). Every collider also has

* ``friction``: the Coulomb coefficient mu >= 0 (dimensionless). A touching particle
  sticks while its tangential velocity change needed to stop it is at most mu times
  its normal velocity change, and slides with that tangential change otherwise;
* ``restitution`` e in [0, 1]: a particle arriving with normal speed s leaves with
  e s (0: it stays in contact, 1: elastic bounce);
* ``velocity`` (m/s, constant): at simulated time t the collider is its geometry
  translated by ``velocity * t``.

Lengths in m. Each is a frozen dataclass validated in its constructor (finite real
numbers, a non-zero normal, radius > 0, lower < upper on every axis, friction >= 0,
restitution in [0, 1]); a bad field raises ``ValueError`` naming it. ``friction``,
``restitution`` and ``velocity`` are keyword-only. A plane's
normal is stored normalised. Pass them as ``Model(..., colliders=[...])``, which refuses
free particles that start inside one (``check_start_outside``, with each collider's
numpy ``signed_distance``); how the integrators respond to contact is described in
``kernels/contact.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from massspring.validate import real_array, real_number


def _vector(name, value):
    arr = real_array(name, value)
    if arr.shape != (3,):
        raise ValueError(f"{name}: expected 3 components, got shape {arr.shape}")
    return tuple(float(c) for c in arr)


@dataclass(frozen=True, kw_only=True)
class Collider:
    """What every collider has (keyword-only): ``friction``, ``restitution``, ``velocity``;
    and per class ``kind`` ("plane", "sphere", "box") and ``GEOMETRY``, the names of its
    position fields (moved by ``velocity * t``)."""

    friction: float = 0.0
    restitution: float = 0.0
    velocity: tuple = (0.0, 0.0, 0.0)
    kind: ClassVar[str] = ""
    GEOMETRY: ClassVar[tuple] = ()

    def __post_init__(self):
        friction = real_number("friction", self.friction)
        if friction < 0:
            raise ValueError(f"friction: must be >= 0, got {friction:g}")
        restitution = real_number("restitution", self.restitution)
        if not 0.0 <= restitution <= 1.0:
            raise ValueError(f"restitution: must be within [0, 1], got {restitution:g}")
        object.__setattr__(self, "friction", friction)
        object.__setattr__(self, "restitution", restitution)
        object.__setattr__(self, "velocity", _vector("velocity", self.velocity))

    @property
    def moving(self) -> bool:
        return any(c != 0.0 for c in self.velocity)

    def at(self, time):
        """The collider at simulated ``time`` (s): its geometry translated by velocity * time."""
        shift = np.asarray(self.velocity) * float(time)
        return replace(self, **{name: tuple(np.asarray(getattr(self, name)) + shift) for name in self.GEOMETRY})


@dataclass(frozen=True)
class Plane(Collider):
    """The plane through ``point`` with outward unit ``normal``; the side it points away from is solid."""

    point: tuple
    normal: tuple
    kind: ClassVar[str] = "plane"
    GEOMETRY: ClassVar[tuple] = ("point",)

    def __post_init__(self):
        object.__setattr__(self, "point", _vector("point", self.point))
        normal = np.array(_vector("normal", self.normal))
        scale = float(np.abs(normal).max())
        if scale > 0:  # scaled first: the norm of (1e-200, 0, 0) underflows, that of (1e200, 1e200, 0) overflows
            normal = normal / scale
        length = float(np.linalg.norm(normal))
        if not length > 0 or not math.isfinite(length):
            raise ValueError(f"normal: must be a non-zero vector, got {list(self.normal)}")
        object.__setattr__(self, "normal", tuple(float(c) for c in normal / length))
        super().__post_init__()

    def signed_distance(self, points):
        """(k,) signed distances (m) of (k, 3) ``points`` to the plane at t = 0: < 0 in the solid."""
        return (np.asarray(points, dtype=np.float64) - self.point) @ np.array(self.normal)


@dataclass(frozen=True)
class Sphere(Collider):
    """A solid ball of ``radius`` (> 0) about ``center``."""

    center: tuple
    radius: float
    kind: ClassVar[str] = "sphere"
    GEOMETRY: ClassVar[tuple] = ("center",)

    def __post_init__(self):
        object.__setattr__(self, "center", _vector("center", self.center))
        radius = real_number("radius", self.radius)
        if not radius > 0:
            raise ValueError(f"radius: must be > 0, got {radius:g}")
        object.__setattr__(self, "radius", radius)
        super().__post_init__()

    def signed_distance(self, points):
        """(k,) signed distances (m) of (k, 3) ``points`` to the sphere at t = 0: < 0 inside."""
        return np.linalg.norm(np.asarray(points, dtype=np.float64) - self.center, axis=1) - self.radius


@dataclass(frozen=True)
class Box(Collider):
    """A solid axis-aligned box between the corners ``lower`` and ``upper`` (lower < upper on
    every axis), its edges and corners rounded with ``radius`` (m, 0: sharp; at most half
    its smallest side).

    Contact is per particle, so a spring between a particle on the top and one down a
    side cuts across a sharp edge, and the last particle on the top carries the whole
    pull of the overhang, pointing into the top: friction there holds a cloth that would
    slide off a real table. A rounded edge (a radius of a spring length or more) spreads
    the turn over several particles, as a real cloth wraps an edge.
    """

    lower: tuple
    upper: tuple
    radius: float = 0.0
    kind: ClassVar[str] = "box"
    GEOMETRY: ClassVar[tuple] = ("lower", "upper")

    def __post_init__(self):
        object.__setattr__(self, "lower", _vector("lower", self.lower))
        object.__setattr__(self, "upper", _vector("upper", self.upper))
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
        """(k,) signed distances (m) of (k, 3) ``points`` to the rounded box at t = 0
        (as ``kernels/contact.py``'s ``BoxKind``): < 0 inside."""
        lower, upper = np.array(self.lower), np.array(self.upper)
        a = np.abs(np.asarray(points, dtype=np.float64) - 0.5 * (lower + upper)) - (0.5 * (upper - lower) - self.radius)
        outside = np.linalg.norm(np.maximum(a, 0.0), axis=1)
        return np.where(outside > 0, outside, a.max(axis=1)) - self.radius


def check_start_outside(colliders, positions, free):
    """Refuse free particles that start inside a collider (ValueError naming the collider,
    how many particles and the deepest): contact pushes a particle out along the surface
    normal, which from deep inside is a jump, not a contact. Touching (within 1e-9 of the
    model's size) is fine."""
    x = np.asarray(positions, dtype=np.float64)[free]
    if not len(x):
        return
    tolerance = 1e-9 * max(1.0, float(np.ptp(x, axis=0).max()))
    for k, collider in enumerate(colliders):
        depth = -collider.signed_distance(x)
        inside = np.flatnonzero(depth > tolerance)
        if len(inside):
            deepest = inside[np.argmax(depth[inside])]
            index = int(np.flatnonzero(free)[deepest])
            raise ValueError(f"colliders: item {k} ({collider.kind}) holds {len(inside)} free particle(s) at the "
                             f"start, particle {index} {depth[deepest]:.3g} m deep; move it or the particles outside")


COLLIDERS = {cls.kind: cls for cls in (Plane, Sphere, Box)}  # in the order the kernels visit them
MAX_COLLIDERS = 31  # the implicit step keeps one bit per collider and particle in an int32
