"""What every collider kind has: ``Collider`` (friction, restitution, velocity and the
hooks each kind fills in) and the start check of a model's particles."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from massspring.support.validate import real_array, real_number


def vector(name, value):
    """A 3-vector of finite floats, refused by ``name``."""
    arr = real_array(name, value)
    if arr.shape != (3,):
        raise ValueError(f"{name}: expected 3 components, got shape {arr.shape}")
    return tuple(float(c) for c in arr)


def box_corners(lower, upper):
    """The 8 corners (8, 3) of the axis-aligned box from ``lower`` to ``upper`` (m)."""
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    return np.array([[(lower, upper)[i][0], (lower, upper)[j][1], (lower, upper)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


@dataclass(frozen=True, kw_only=True)
class Collider:
    """What every collider has (keyword-only): ``friction``, ``restitution``, ``velocity``.

    Each kind sets ``kernel`` (its class of ``ti.func``s in ``kernels/contact.py``,
    whose ``name`` is the kind's: ``kind``), ``GEOMETRY`` (the names of its position
    fields, moved by ``velocity * t``), ``ARRAYS`` (the fields the kernel class reads, as
    ``dev.<kind>_<field>``) and ``bounded``, and gives ``signed_distance``,
    ``usd_shape`` and ``origin``; a bounded kind is drawn from ``corners``, ``surface``
    and ``hides``, an unbounded one as a ground of ``cells``.
    """

    friction: float = 0.0
    restitution: float = 0.0
    velocity: tuple = (0.0, 0.0, 0.0)
    kernel: ClassVar[type] = None
    kind: ClassVar[str] = ""
    GEOMETRY: ClassVar[tuple] = ()
    ARRAYS: ClassVar[tuple] = ()
    bounded: ClassVar[bool] = True

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.kernel is not None:
            cls.kind = cls.kernel.name

    def __post_init__(self):
        friction = real_number("friction", self.friction)
        if friction < 0:
            raise ValueError(f"friction: must be >= 0, got {friction:g}")
        restitution = real_number("restitution", self.restitution)
        if not 0.0 <= restitution <= 1.0:
            raise ValueError(f"restitution: must be within [0, 1], got {restitution:g}")
        object.__setattr__(self, "friction", friction)
        object.__setattr__(self, "restitution", restitution)
        object.__setattr__(self, "velocity", vector("velocity", self.velocity))

    @property
    def moving(self) -> bool:
        return any(c != 0.0 for c in self.velocity)

    def at(self, time):
        """The collider at simulated ``time`` (s): its geometry translated by velocity * time."""
        shift = np.asarray(self.velocity) * float(time)
        return replace(self, **{name: tuple(np.asarray(getattr(self, name)) + shift) for name in self.GEOMETRY})

    def signed_distance(self, points):
        """(k,) signed distances (m) of (k, 3) ``points`` to the collider at t = 0: < 0 in the solid."""
        raise NotImplementedError

    def corners(self):
        """The 8 corners (8, 3) of a bounded collider's bounding box (m)."""
        raise NotImplementedError

    def surface(self):
        """A bounded collider as triangles: corners (t, 3, 3) and outward unit normals (t, 3)."""
        raise NotImplementedError

    def hides(self, points, directions, tiny):
        """(k,) bool: whether the ray from each of ``points`` (k, 3) along ``directions``
        (k, 3, unit) enters the solid as drawn by ``surface`` more than ``tiny`` (m)
        ahead of the point. A point on its surface or inside is not hidden."""
        raise NotImplementedError

    def cells(self, centre, half, count):
        """An unbounded collider's drawn ground: a square 2 ``half`` (m) wide about the
        point nearest ``centre``, in ``count``^2 cells: corners (c, 4, 3), normals (c, 3)
        and each cell's checker parity (c,) 0 or 1."""
        raise NotImplementedError

    def usd_shape(self, stage, path, size):
        """Define the collider as a ``UsdGeom`` prim at ``path`` of ``stage`` (an unbounded
        one ``size`` m across) and return its translate op, set to ``origin()`` by the caller."""
        raise NotImplementedError

    def origin(self):
        """Where ``usd_shape``'s prim is translated to (m)."""
        raise NotImplementedError


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
