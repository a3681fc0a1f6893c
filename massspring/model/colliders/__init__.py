"""Colliders: rigid obstacles that particles cannot enter, static or moving at a constant velocity.

``Plane(point, normal)`` (the half-space below the plane, on the side opposite to
``normal``, is solid), ``Sphere(center, radius)`` and ``Box(lower, upper)`` (axis-aligned,
between two corners, its edges optionally rounded). Every collider also has

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
``restitution`` and ``velocity`` are keyword-only. A plane's normal is stored
normalised. Pass them as ``Model(..., colliders=[...])``, which refuses free particles
that start inside one (``check_start_outside``); how the integrators respond to
contact is described in ``kernels/contact.py``.

A collider kind is one module here, whose class holds everything about the kind (its
fields and their checks, its numpy geometry, how it is drawn and written to USD, and
``kernel``: its class of ``ti.func``s in ``kernels/contact.py``), and one entry in
``COLLIDERS``. Nothing else names a kind.
"""

from __future__ import annotations

from .base import Collider, check_start_outside
from .box import Box
from .plane import Plane
from .sphere import Sphere

COLLIDERS = {cls.kind: cls for cls in (Plane, Sphere, Box)}  # in the order the kernels visit them
MAX_COLLIDERS = 31  # the implicit step keeps one bit per collider and particle in an int32

__all__ = ["COLLIDERS", "MAX_COLLIDERS", "Box", "Collider", "Plane", "Sphere", "check_start_outside",
           "collider_arrays", "collider_groups"]


def collider_groups(model) -> tuple:
    """``cfg.colliders`` of a model: (kernel kind, count, first) for each kind it has, in
    ``COLLIDERS`` order; ``first`` numbers the kind's colliders among all of the model's."""
    groups, first = [], 0
    for cls in COLLIDERS.values():
        count = sum(isinstance(c, cls) for c in model.colliders)
        if count:
            groups.append((cls.kernel, count, first))
            first += count
    return tuple(groups)


def collider_arrays(model) -> dict:
    """Device arrays of a model's colliders: ``<kind>_<field>`` -> (count, element shape, values)."""
    out = {}
    for cls in COLLIDERS.values():
        group = [c for c in model.colliders if isinstance(c, cls)]
        if not group:
            continue
        fields = {name: [getattr(c, name) for c in group]
                  for name in (*cls.ARRAYS, "velocity", "friction", "restitution")}
        for field, values in fields.items():
            element = (3,) if isinstance(values[0], tuple) else ()
            out[f"{cls.kind}_{field}"] = (len(group), element, values)
    return out
